//! One WebSocket connection = one viewer of a shared session (`hub`). The reader side turns
//! the viewer's messages into edits of the session (last writer wins, every viewer told with
//! `edited`); the writer side sends the session's newest frame when this viewer is ready for
//! one (its acknowledgement window, or the socket accepting the last one), in the encoding
//! chosen for it, plus the session's broadcast messages and this viewer's own replies.
//!
//! - `join`: the `hello` handshake, opening or joining a session, loading its dataset.
//! - `edit`: checking and applying the viewer's edits to the session.
//! - `writer`: the connection's writer task (frames, broadcasts, replies, pings).

mod edit;
mod join;
mod writer;

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::{Duration, Instant};

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocket, close_code};
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use voxlight_protocol::{
    ClientMessage, ErrorCode, MAX_MESSAGE_BYTES, MAX_MESSAGES_PER_SECOND, ServerMessage, ViewerInfo,
};

use crate::AppState;
use crate::hub::SharedSession;
use crate::render_service::Command;
pub use crate::reply::Reply;
use edit::handle_message;
pub use edit::validate_message;
use join::{Viewer, open_or_join, wait_for_hello};
use writer::{WriterEnv, send, write_loop};

/// Range of `quality.iterations`.
pub const MAX_ITERATIONS: u32 = 65536;
/// How long a client may take to say `hello`.
const HELLO_TIMEOUT: Duration = Duration::from_secs(30);
/// Outgoing text messages queued per connection before the reader waits.
const OUTBOX: usize = 64;
/// Default JPEG quality while the picture changes.
pub const DEFAULT_JPEG_QUALITY: u8 = 85;
/// Default progressive iterations until a picture is converged.
pub const DEFAULT_ITERATIONS: u32 = 128;
/// Interval of `stats` messages.
const STATS_INTERVAL: Duration = Duration::from_millis(500);
/// A viewer whose socket accepts nothing for this long is disconnected.
const SEND_TIMEOUT: Duration = Duration::from_secs(30);
/// A WebSocket ping this often by default: a converged picture sends nothing else, and proxies
/// cut quiet connections (nginx after 60 s by default, cloud load balancers after 30 s or more).
pub const PING_INTERVAL: Duration = Duration::from_secs(20);
/// How long a connection closed for a transport error (e.g. 1009) stays open after its close
/// frame. The rest of the offending message is still unread in the socket, and closing a
/// socket with unread data resets the connection: a reset that reaches the client before it
/// has read the close frame destroys the frame, and the client sees a dropped connection.
const CLOSE_LINGER: Duration = Duration::from_secs(2);

type Sink = SplitSink<WebSocket, Message>;
type Stream = SplitStream<WebSocket>;

fn text(message: &ServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(message).unwrap_or_default(),
    ))
}

/// Parses one incoming WebSocket message. `Ok(None)`: nothing to do (ping, pong).
fn parse(message: Message) -> Result<Option<ClientMessage>, Reply> {
    match message {
        Message::Text(body) => {
            if body.len() > MAX_MESSAGE_BYTES {
                return Err(Reply::new(
                    ErrorCode::TooLarge,
                    format!(
                        "message of {} bytes exceeds the limit of {MAX_MESSAGE_BYTES}",
                        body.len()
                    ),
                ));
            }
            serde_json::from_str(body.as_str()).map(Some).map_err(|e| {
                Reply::new(ErrorCode::BadMessage, format!("cannot parse message: {e}"))
            })
        }
        Message::Binary(_) => Err(Reply::new(
            ErrorCode::BadMessage,
            "binary messages are not accepted; send JSON text",
        )),
        Message::Ping(_) | Message::Pong(_) | Message::Close(_) => Ok(None),
    }
}

/// The close frame for a connection whose transport failed, when the peer should get one:
/// a message over the transport limit (1009), text that is not UTF-8 (1007), a frame that
/// breaks the WebSocket protocol (1002). `None` for a connection that is simply gone.
fn transport_close(error: &axum::Error) -> Option<CloseFrame> {
    use std::error::Error as _;
    use tungstenite::error::{CapacityError, Error as WsError, ProtocolError};
    let (code, reason) = match error.source()?.downcast_ref::<WsError>()? {
        WsError::Capacity(CapacityError::MessageTooLong { size, max_size }) => (
            close_code::SIZE,
            format!("message of {size} bytes exceeds the transport limit of {max_size}"),
        ),
        WsError::Capacity(e) => (close_code::SIZE, e.to_string()),
        WsError::Utf8(_) => (close_code::INVALID, "text message is not UTF-8".to_owned()),
        // The peer is gone already: nobody to tell.
        WsError::Protocol(ProtocolError::ResetWithoutClosingHandshake) => return None,
        WsError::Protocol(e) => (close_code::PROTOCOL, e.to_string()),
        _ => return None,
    };
    Some(CloseFrame {
        code,
        reason: Utf8Bytes::from(reason),
    })
}

/// What the reader shares with the writer of one connection.
struct ViewerLink {
    /// The viewer's own JPEG quality (the adaptation never goes above it).
    jpeg_quality: AtomicU8,
    /// Highest frame `seq` acknowledged.
    acked: watch::Sender<u64>,
    /// Frames in flight before acknowledgements (None: the client does not acknowledge).
    window: Option<u32>,
    /// Ends the reader when the writer gives up on the viewer (or the server shuts down).
    connection: CancellationToken,
    /// Set by the reader when the transport failed in a way the client should hear about
    /// (e.g. 1009 for a message over the transport limit); the writer closes with it.
    close: std::sync::Mutex<Option<CloseFrame>>,
}

/// Serves one WebSocket connection until it closes or the server shuts down.
pub async fn handle_socket(socket: WebSocket, state: Arc<AppState>) {
    let (mut sink, mut stream) = socket.split();
    let hello = tokio::select! {
        hello = wait_for_hello(&mut sink, &mut stream, &state.metrics) => hello,
        _ = state.shutdown.cancelled() => None,
    };
    let Some(hello) = hello else { return };
    // A dataset fetched from a PACS reports its progress before the welcome.
    let (progress, mut progress_rx) = mpsc::channel(8);
    let opening = open_or_join(&state, hello, progress);
    tokio::pin!(opening);
    let opened = loop {
        tokio::select! {
            opened = &mut opening => break opened,
            Some(message) = progress_rx.recv() => {
                let _ = send(&mut sink, text(&message)).await;
            }
        }
    };
    let viewer = match opened {
        Ok(viewer) => viewer,
        Err(reply) => {
            state.metrics.error_sent(reply.code);
            let _ = sink.send(text(&ServerMessage::from(reply))).await;
            let _ = sink.close().await;
            return;
        }
    };
    let Viewer {
        session,
        info,
        events,
        welcome,
        window,
    } = viewer;
    state.metrics.viewers_active.fetch_add(1, Ordering::Relaxed);
    tracing::info!(
        session = session.render_id,
        viewer = info.id,
        viewers = session.viewers().len(),
        "viewer connected"
    );
    let link = Arc::new(ViewerLink {
        jpeg_quality: AtomicU8::new(DEFAULT_JPEG_QUALITY),
        acked: watch::Sender::new(0),
        window,
        connection: state.shutdown.child_token(),
        close: std::sync::Mutex::new(None),
    });
    let (outbox, outbox_rx) = mpsc::channel(OUTBOX);
    let _ = outbox.send(welcome).await;
    if state.draining.is_cancelled() {
        // Joined (or came back) while the server drains: it has as long as the others.
        let _ = outbox
            .send(crate::lifecycle::draining_message(&state))
            .await;
    }
    session.publish(ServerMessage::Viewers {
        viewers: session.viewers(),
    });
    let writer = state.tracker.spawn(write_loop(
        sink,
        outbox_rx,
        session.clone(),
        events,
        link.clone(),
        WriterEnv::of(&state),
    ));
    read_loop(&state, &session, info.clone(), stream, outbox, &link).await;
    leave(&state, &session, &info);
    let _ = writer.await;
}

/// Takes a viewer off its session; the last one out starts the grace period, after which
/// the session and its GPU state are dropped unless someone came back.
fn leave(state: &Arc<AppState>, session: &Arc<SharedSession>, viewer: &ViewerInfo) {
    let (left, generation) = session.remove_viewer(viewer.id);
    state.metrics.viewers_active.fetch_sub(1, Ordering::Relaxed);
    tracing::info!(
        session = session.render_id,
        viewer = viewer.id,
        viewers = left,
        "viewer left"
    );
    session.publish(ServerMessage::Viewers {
        viewers: session.viewers(),
    });
    if left > 0 {
        return;
    }
    let (state, id) = (state.clone(), session.id.clone());
    let grace = state.hub.grace;
    state.tracker.clone().spawn(async move {
        tokio::select! {
            _ = tokio::time::sleep(grace) => {}
            _ = state.shutdown.cancelled() => {}
        }
        if let Some(session) = state.hub.expire(&id, generation) {
            let _ = state
                .render
                .send(Command::Close {
                    id: session.render_id,
                })
                .await;
            state
                .metrics
                .sessions_active
                .fetch_sub(1, Ordering::Relaxed);
            if !state.shutdown.is_cancelled() {
                state
                    .metrics
                    .sessions_expired_total
                    .fetch_add(1, Ordering::Relaxed);
            }
            tracing::info!(session = session.render_id, "session closed");
        }
    });
}

/// Token bucket: `MAX_MESSAGES_PER_SECOND` on average, bursts of twice that.
struct RateLimit {
    tokens: f64,
    last: Instant,
    /// When the last `rate_limited` error went out (at most one a second).
    last_reported: Option<Instant>,
}

impl RateLimit {
    fn new() -> Self {
        Self {
            tokens: 2.0 * MAX_MESSAGES_PER_SECOND as f64,
            last: Instant::now(),
            last_reported: None,
        }
    }

    /// Ok: accept the message. Err(report): drop it; `report` says whether to send an error.
    fn take(&mut self) -> Result<(), bool> {
        let now = Instant::now();
        let rate = MAX_MESSAGES_PER_SECOND as f64;
        self.tokens =
            (self.tokens + now.duration_since(self.last).as_secs_f64() * rate).min(2.0 * rate);
        self.last = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            return Ok(());
        }
        let report = self
            .last_reported
            .is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1));
        if report {
            self.last_reported = Some(now);
        }
        Err(report)
    }
}

async fn read_loop(
    state: &Arc<AppState>,
    session: &Arc<SharedSession>,
    mut viewer: ViewerInfo,
    mut stream: Stream,
    outbox: mpsc::Sender<ServerMessage>,
    link: &ViewerLink,
) {
    let mut limit = RateLimit::new();
    loop {
        let message = tokio::select! {
            message = stream.next() => message,
            _ = link.connection.cancelled() => return,
        };
        let message = match message {
            Some(Ok(Message::Close(_))) | None => return,
            Some(Ok(message)) => message,
            Some(Err(e)) => {
                tracing::debug!(session = session.render_id, viewer = viewer.id, error = %e, "websocket read failed");
                if let Some(frame) = transport_close(&e)
                    && let Ok(mut close) = link.close.lock()
                {
                    *close = Some(frame);
                }
                return;
            }
        };
        let parsed = parse(message);
        // Acknowledgements are exempt: dropping one would stall the viewer's frame window.
        let is_ack = matches!(parsed, Ok(Some(ClientMessage::Ack { .. })));
        if !is_ack && let Err(report) = limit.take() {
            if report {
                let reply = Reply::new(
                    ErrorCode::RateLimited,
                    format!(
                        "more than {MAX_MESSAGES_PER_SECOND} messages a second; messages are being dropped"
                    ),
                );
                if outbox.send(ServerMessage::from(reply)).await.is_err() {
                    return;
                }
            }
            continue;
        }
        let result = match parsed {
            Ok(Some(message)) => handle_message(state, session, &mut viewer, message, link).await,
            Ok(None) => Ok(()),
            Err(reply) => Err(reply),
        };
        if let Err(reply) = result {
            tracing::debug!(session = session.render_id, viewer = viewer.id, code = ?reply.code, "client error");
            if outbox.send(ServerMessage::from(reply)).await.is_err() {
                return;
            }
        }
    }
}
