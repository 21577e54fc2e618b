//! `Reply`: a protocol-level failure, answered to the client with an `error` message.

use voxlight_protocol::{ErrorCode, ServerMessage};

/// A protocol-level failure answered with an `error` message: the code a client program acts
/// on and a sentence for the person.
#[derive(Debug, thiserror::Error)]
#[error("{code:?}: {message}")]
pub struct Reply {
    pub code: ErrorCode,
    pub message: String,
}

impl Reply {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    /// A value out of its documented range (`bad_value`).
    pub(crate) fn bad(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::BadValue, message)
    }
}

impl From<Reply> for ServerMessage {
    fn from(reply: Reply) -> Self {
        ServerMessage::Error {
            code: reply.code,
            message: reply.message,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reply_becomes_an_error_message() {
        let reply = Reply::bad("jpeg_quality must be in 1..=100, got 0");
        assert_eq!(
            reply.to_string(),
            "BadValue: jpeg_quality must be in 1..=100, got 0"
        );
        let ServerMessage::Error { code, message } = ServerMessage::from(reply) else {
            panic!("an error message")
        };
        assert_eq!(code, ErrorCode::BadValue);
        assert!(message.starts_with("jpeg_quality"));
    }
}
