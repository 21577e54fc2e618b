//! `Reply`: a protocol-level failure, answered to the client with an `error` message.

use voxlight_protocol::ErrorCode;

/// A protocol-level failure answered with an `error` message.
#[derive(Debug)]
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
    pub(crate) fn bad(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::BadValue, message)
    }
}
