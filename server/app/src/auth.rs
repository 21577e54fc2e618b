//! Access control, checked before a WebSocket upgrade (and for `/api/...`): bearer tokens and an
//! Origin allowlist against cross-site WebSocket hijacking. Tokens are never logged.

use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// The WebSocket subprotocol the server speaks; browsers, which cannot set headers on a
/// WebSocket, send their token as a second subprotocol `voxlight.token.<TOKEN>`.
pub const SUBPROTOCOL: &str = "voxlight";
const TOKEN_SUBPROTOCOL_PREFIX: &str = "voxlight.token.";

/// Who may connect.
#[derive(Debug, Clone, Default)]
pub struct Access {
    /// Accepted bearer tokens; empty: no token needed.
    pub tokens: Vec<String>,
    /// Origins (e.g. `https://viewer.hospital.example`) allowed to open sockets besides the
    /// server's own; requests without an Origin header (scripts) are not browser requests
    /// and pass this check.
    pub allowed_origins: Vec<String>,
}

/// Why a request is refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    MissingToken,
    BadToken,
    ForeignOrigin(String),
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        let (status, code, message) = match &self {
            Refusal::MissingToken => (
                StatusCode::UNAUTHORIZED,
                "unauthorized",
                "this server needs a token: send `Authorization: Bearer <token>` or the WebSocket subprotocol `voxlight.token.<token>`".to_owned(),
            ),
            Refusal::BadToken => (StatusCode::UNAUTHORIZED, "unauthorized", "the token is not valid".to_owned()),
            Refusal::ForeignOrigin(origin) => (
                StatusCode::FORBIDDEN,
                "forbidden_origin",
                format!("pages from {origin} may not open sessions here"),
            ),
        };
        let body = serde_json::json!({ "error": code, "message": message }).to_string();
        let mut response =
            (status, [(header::CONTENT_TYPE, "application/json")], body).into_response();
        if status == StatusCode::UNAUTHORIZED {
            response
                .headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        response
    }
}

/// Equal strings in time independent of where they differ.
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// The token a request carries, if any: a bearer header or a `voxlight.token.` subprotocol.
fn presented_token(headers: &HeaderMap) -> Option<String> {
    if let Some(bearer) = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
    {
        return Some(bearer.trim().to_owned());
    }
    headers
        .get_all(header::SEC_WEBSOCKET_PROTOCOL)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .find_map(|p| {
            p.trim()
                .strip_prefix(TOKEN_SUBPROTOCOL_PREFIX)
                .map(str::to_owned)
        })
}

/// True when `origin` names the host the request was sent to (same-origin page).
fn same_host(origin: &str, headers: &HeaderMap) -> bool {
    let Some(host) = headers.get(header::HOST).and_then(|v| v.to_str().ok()) else {
        return false;
    };
    let authority = origin.split_once("://").map_or(origin, |(_, rest)| rest);
    authority.eq_ignore_ascii_case(host)
}

impl Access {
    pub fn check(&self, headers: &HeaderMap) -> Result<(), Refusal> {
        if let Some(origin) = headers.get(header::ORIGIN).and_then(|v| v.to_str().ok()) {
            let allowed =
                same_host(origin, headers) || self.allowed_origins.iter().any(|o| o == origin);
            if !allowed {
                return Err(Refusal::ForeignOrigin(origin.to_owned()));
            }
        }
        if self.tokens.is_empty() {
            return Ok(());
        }
        match presented_token(headers) {
            None => Err(Refusal::MissingToken),
            Some(token) if self.tokens.iter().any(|t| same(t, &token)) => Ok(()),
            Some(_) => Err(Refusal::BadToken),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
        let mut map = HeaderMap::new();
        for (name, value) in pairs {
            map.append(name.clone(), HeaderValue::from_str(value).unwrap());
        }
        map
    }

    #[test]
    fn origins() {
        let open = Access::default();
        assert!(
            open.check(&headers(&[(header::HOST, "127.0.0.1:8080")]))
                .is_ok()
        );
        let same = headers(&[
            (header::HOST, "127.0.0.1:8080"),
            (header::ORIGIN, "http://127.0.0.1:8080"),
        ]);
        assert!(open.check(&same).is_ok());
        let foreign = headers(&[
            (header::HOST, "127.0.0.1:8080"),
            (header::ORIGIN, "https://evil.example"),
        ]);
        assert_eq!(
            open.check(&foreign),
            Err(Refusal::ForeignOrigin("https://evil.example".into()))
        );
        let listed = Access {
            allowed_origins: vec!["https://evil.example".into()],
            ..Access::default()
        };
        assert!(listed.check(&foreign).is_ok());
    }

    #[test]
    fn tokens() {
        let access = Access {
            tokens: vec!["s3cret".into()],
            ..Access::default()
        };
        assert_eq!(access.check(&HeaderMap::new()), Err(Refusal::MissingToken));
        assert!(
            access
                .check(&headers(&[(header::AUTHORIZATION, "Bearer s3cret")]))
                .is_ok()
        );
        assert_eq!(
            access.check(&headers(&[(header::AUTHORIZATION, "Bearer nope")])),
            Err(Refusal::BadToken)
        );
        let sub = headers(&[(
            header::SEC_WEBSOCKET_PROTOCOL,
            "voxlight, voxlight.token.s3cret",
        )]);
        assert!(access.check(&sub).is_ok());
        assert!(!same("s3cret", "s3cre"));
    }
}
