//! One WebSocket connection = one viewer of a shared session (`hub`). The reader side turns
//! the viewer's messages into edits of the session (last writer wins, every viewer told with
//! `edited`); the writer side sends the session's newest frame when this viewer is ready for
//! one (its acknowledgement window, or the socket accepting the last one), in the encoding
//! chosen for it, plus the session's broadcast messages and this viewer's own replies.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocket, close_code};
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio_util::sync::CancellationToken;
use voxlight_engine::camera::CameraBasis;
use voxlight_engine::scene::{validate_lights, validate_params, validate_viewport};
use voxlight_engine::{Change, Scene};
use voxlight_protocol::{
    ClientMessage, ErrorCode, MAX_FRAMES_IN_FLIGHT, MAX_MESSAGE_BYTES, MAX_MESSAGES_PER_SECOND,
    PROTOCOL_VERSION, RenderParams, ServerMessage, Stats, ViewerInfo, Viewport,
};

use crate::AppState;
use crate::adapt::QualityController;
use crate::hub::{EVENT_BUFFER, Encoding, SessionCore, SharedSession};
use crate::metrics::Metrics;
use crate::render_service::{Command, SessionId};

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

static NEXT_SESSION: AtomicU64 = AtomicU64::new(1);

type Sink = SplitSink<WebSocket, Message>;
type Stream = SplitStream<WebSocket>;

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
    fn bad(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::BadValue, message)
    }
}

fn text(message: &ServerMessage) -> Message {
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(message).unwrap_or_default(),
    ))
}

fn error_message(reply: Reply) -> ServerMessage {
    ServerMessage::Error {
        code: reply.code,
        message: reply.message,
    }
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

/// Every check of a client message that needs no session state: ranges, finite numbers,
/// list lengths. `handle_message` runs it before touching the session (so a refused message
/// has no effect at all), `open_or_join` before anything else; what depends on the session or
/// the GPU (the viewport's pixel budget, technique and dataset names) is checked where it is
/// used. A message it accepts carries no number out of its documented range.
pub fn validate_message(message: &ClientMessage) -> Result<(), Reply> {
    match message {
        ClientMessage::Hello {
            viewport,
            technique_options,
            max_in_flight,
            ..
        } => {
            if let Some(n) = max_in_flight
                && !(1..=MAX_FRAMES_IN_FLIGHT).contains(n)
            {
                return Err(Reply::bad(format!(
                    "max_in_flight must be in 1..={MAX_FRAMES_IN_FLIGHT}, got {n}"
                )));
            }
            // Checked when joining too, where they are not used: a value out of range is a
            // client bug either way.
            if let Some(viewport) = viewport {
                validate_viewport(viewport).map_err(Reply::bad)?;
            }
            match technique_options {
                Some(options) => {
                    voxlight_engine::technique_options::validate(options).map_err(Reply::bad)
                }
                None => Ok(()),
            }
        }
        ClientMessage::Camera(camera) => CameraBasis::new(camera).map(|_| ()).map_err(Reply::bad),
        ClientMessage::Tf(tf) => voxlight_engine::tf::validate(tf).map_err(Reply::bad),
        ClientMessage::Lights { lights } => validate_lights(lights).map_err(Reply::bad),
        ClientMessage::Viewport(viewport) => validate_viewport(viewport).map_err(Reply::bad),
        ClientMessage::Params {
            density_scale,
            g,
            exposure,
        } => {
            // Each parameter has its own range: the given ones are checked beside defaults.
            let d = RenderParams::default();
            validate_params(&RenderParams {
                density_scale: density_scale.unwrap_or(d.density_scale),
                g: g.unwrap_or(d.g),
                exposure: exposure.unwrap_or(d.exposure),
            })
            .map_err(Reply::bad)
        }
        ClientMessage::Quality {
            jpeg_quality,
            iterations,
        } => {
            if let Some(q) = jpeg_quality
                && !(1..=100).contains(q)
            {
                return Err(Reply::bad(format!(
                    "jpeg_quality must be in 1..=100, got {q}"
                )));
            }
            if let Some(n) = iterations
                && !(1..=MAX_ITERATIONS).contains(n)
            {
                return Err(Reply::bad(format!(
                    "iterations must be in 1..={MAX_ITERATIONS}, got {n}"
                )));
            }
            Ok(())
        }
        ClientMessage::Technique {
            options: Some(options),
            ..
        } => voxlight_engine::technique_options::validate(options).map_err(Reply::bad),
        ClientMessage::Technique { options: None, .. }
        | ClientMessage::Ack { .. }
        | ClientMessage::Name { .. }
        | ClientMessage::Dataset { .. } => Ok(()),
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
            let _ = sink.send(text(&error_message(reply))).await;
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
        state.clone(),
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

/// Answers everything before a valid `hello` with `not_ready`.
async fn wait_for_hello(
    sink: &mut Sink,
    stream: &mut Stream,
    metrics: &Metrics,
) -> Option<ClientMessage> {
    let deadline = tokio::time::Instant::now() + HELLO_TIMEOUT;
    loop {
        let message = match tokio::time::timeout_at(deadline, stream.next()).await {
            Ok(Some(Ok(message))) => message,
            Ok(Some(Err(e))) => {
                if let Some(frame) = transport_close(&e) {
                    tracing::debug!(error = %e, code = frame.code, "closing a connection before hello");
                    if sink.send(Message::Close(Some(frame))).await.is_ok() {
                        tokio::time::sleep(CLOSE_LINGER).await;
                    }
                }
                return None;
            }
            Ok(None) => return None,
            Err(_) => {
                let reply = Reply::new(ErrorCode::NotReady, "no hello within 30 s; closing");
                metrics.error_sent(reply.code);
                let _ = sink.send(text(&error_message(reply))).await;
                return None;
            }
        };
        if let Message::Close(_) = message {
            return None;
        }
        let reply = match parse(message) {
            Ok(Some(hello @ ClientMessage::Hello { .. })) => return Some(hello),
            Ok(Some(_)) => Reply::new(ErrorCode::NotReady, "the first message must be `hello`"),
            Ok(None) => continue,
            Err(reply) => reply,
        };
        metrics.error_sent(reply.code);
        if sink.send(text(&error_message(reply))).await.is_err() {
            return None;
        }
    }
}

/// A connection admitted to a session.
struct Viewer {
    session: Arc<SharedSession>,
    info: ViewerInfo,
    events: broadcast::Receiver<Arc<ServerMessage>>,
    welcome: ServerMessage,
    /// Frames in flight before acknowledgements (None: the client does not acknowledge).
    window: Option<u32>,
}

/// Where a dataset's load progress goes: `done` and `total` parts (a PACS series' instances).
type Progress = Box<dyn Fn(u32, u32) + Send + Sync>;

async fn load_dataset(
    state: &Arc<AppState>,
    name: &str,
    progress: Progress,
) -> Result<Arc<voxlight_volumes::Volume>, Reply> {
    if !state.catalog.contains(name) {
        return Err(Reply::new(
            ErrorCode::UnknownDataset,
            format!("unknown dataset `{name}`; GET /api/datasets lists them"),
        ));
    }
    let catalog = state.catalog.clone();
    let owned = name.to_owned();
    tokio::task::spawn_blocking(move || catalog.load_with_progress(&owned, &progress))
        .await
        .map_err(|e| Reply::new(ErrorCode::Internal, format!("loader task failed: {e}")))?
        .map_err(|e| {
            tracing::warn!(dataset = name, error = %e, "dataset could not be loaded");
            Reply::new(ErrorCode::LoadFailed, without_server_folders(&e))
        })
}

/// A load error as a viewer may read it: the server's folders left out, file names kept
/// (clients never see server paths).
fn without_server_folders(error: &crate::datasets::DatasetError) -> String {
    use voxlight_volumes::VolumeError;
    let text = error.to_string();
    let crate::datasets::DatasetError::Load { source, .. } = error else {
        return text;
    };
    let path = match source {
        VolumeError::Io { path, .. }
        | VolumeError::Format { path, .. }
        | VolumeError::Unsupported { path, .. }
        | VolumeError::TooLarge { path, .. }
        | VolumeError::UnknownFormat { path } => path,
        _ => return text,
    };
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => text.replace(
            &format!("{}{}", dir.display(), std::path::MAIN_SEPARATOR),
            "",
        ),
        _ => text,
    }
}

/// A viewport the protocol allows and this GPU can hold.
fn check_viewport(state: &AppState, viewport: &Viewport) -> Result<(), Reply> {
    validate_viewport(viewport).map_err(Reply::bad)?;
    let pixels = viewport.width as u64 * viewport.height as u64;
    if pixels > state.max_viewport_pixels {
        return Err(Reply::new(
            ErrorCode::GpuMemory,
            format!(
                "a {}×{} viewport is {pixels} pixels; this GPU allows at most {} per session",
                viewport.width, viewport.height, state.max_viewport_pixels
            ),
        ));
    }
    Ok(())
}

fn check_technique(state: &AppState, name: &str) -> Result<(), Reply> {
    if state.techniques.iter().any(|t| t.name == name) {
        Ok(())
    } else {
        let offered: Vec<&str> = state.techniques.iter().map(|t| t.name.as_str()).collect();
        Err(Reply::new(
            ErrorCode::UnknownTechnique,
            format!(
                "unknown technique `{name}`; offered: {}",
                offered.join(", ")
            ),
        ))
    }
}

fn welcome(
    state: &AppState,
    session: &SharedSession,
    core: &SessionCore,
    viewer: &ViewerInfo,
    joined: bool,
) -> Result<ServerMessage, Reply> {
    Ok(ServerMessage::Welcome {
        protocol: PROTOCOL_VERSION,
        session: session.id.clone(),
        server_version: env!("CARGO_PKG_VERSION").to_owned(),
        adapter: state.adapter.clone(),
        software_renderer: state.software_renderer,
        dataset: state
            .catalog
            .info(&core.dataset)
            .ok_or_else(|| Reply::new(ErrorCode::Internal, "dataset vanished"))?,
        techniques: state.techniques.clone(),
        state: core.state(DEFAULT_JPEG_QUALITY),
        viewer: viewer.clone(),
        viewers: session.viewers(),
        joined,
        version: core.version,
        route: state.route_prefix.clone(),
    })
}

/// `loading` messages for `dataset`, handed to `deliver` (a viewer's channel before it has a
/// session, or a session's broadcast on a dataset switch).
fn loading_progress(
    dataset: &str,
    deliver: impl Fn(ServerMessage) + Send + Sync + 'static,
) -> Progress {
    let dataset = dataset.to_owned();
    Box::new(move |done, total| {
        deliver(ServerMessage::Loading {
            dataset: dataset.clone(),
            done,
            total,
        })
    })
}

async fn open_or_join(
    state: &Arc<AppState>,
    hello: ClientMessage,
    progress: mpsc::Sender<ServerMessage>,
) -> Result<Viewer, Reply> {
    // The version first: another version's fields may mean something else.
    if let ClientMessage::Hello { protocol, .. } = &hello
        && *protocol != PROTOCOL_VERSION
    {
        return Err(Reply::new(
            ErrorCode::ProtocolVersion,
            format!("this server speaks protocol {PROTOCOL_VERSION}, the client {protocol}"),
        ));
    }
    validate_message(&hello)?;
    let ClientMessage::Hello {
        session: join,
        viewport,
        dataset,
        technique,
        technique_options,
        name,
        max_in_flight,
        ..
    } = hello
    else {
        return Err(Reply::new(ErrorCode::NotReady, "expected hello"));
    };
    // `validate_message` checked its range.
    let window = max_in_flight;
    if let Some(id) = join {
        let (session, info, _) = state.hub.join(&id, name.as_deref())?;
        state.metrics.joins_total.fetch_add(1, Ordering::Relaxed);
        // Subscribe before reading the state: an edit in between arrives twice (harmless)
        // rather than never.
        let events = session.subscribe();
        // The session may have been paused without viewers.
        let _ = state.render.send(Command::Wake).await;
        let welcome = {
            let core = session.core.lock().await;
            welcome(state, &session, &core, &info, true)?
        };
        return Ok(Viewer {
            session,
            info,
            events,
            welcome,
            window,
        });
    }
    // A place is reserved before the dataset loads, so the limit holds while loads overlap.
    let slot = crate::lifecycle::admit(state)?;
    let viewport = viewport.unwrap_or_default();
    check_viewport(state, &viewport)?;
    let technique = technique.unwrap_or_else(|| "raymarch".to_owned());
    check_technique(state, &technique)?;
    // `validate_message` checked the options' ranges.
    let technique_options = technique_options.unwrap_or_default();
    let dataset = dataset.unwrap_or_else(|| state.default_dataset.clone());
    let progress = loading_progress(&dataset, move |message| {
        // A full channel drops this update; the writer is behind and a later one follows.
        let _ = progress.try_send(message);
    });
    let volume = load_dataset(state, &dataset, progress).await?;
    let scene = Scene {
        tf: crate::datasets::default_tf(&volume),
        lights: crate::datasets::default_lights_for(&volume),
        params: RenderParams::default(),
        viewport,
        target_iterations: DEFAULT_ITERATIONS,
        technique_options,
        ..Scene::default()
    };
    let render_id: SessionId = NEXT_SESSION.fetch_add(1, Ordering::Relaxed);
    let (frame_slot, frames) = watch::channel(None);
    let (events_tx, _) = broadcast::channel(EVENT_BUFFER);
    let session = Arc::new(SharedSession::new(
        render_id,
        SessionCore {
            dataset,
            technique: technique.clone(),
            scene: scene.clone(),
            version: 0,
        },
        frames,
        events_tx.clone(),
    ));
    let (reply, opened) = oneshot::channel();
    state
        .render
        .send(Command::Open {
            id: render_id,
            volume,
            technique,
            scene,
            version: 0,
            frames: frame_slot,
            events: events_tx,
            viewers: session.viewer_count(),
            reply,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    opened
        .await
        .map_err(|_| Reply::new(ErrorCode::Internal, "render thread dropped the request"))?
        .map_err(|e| Reply::new(crate::render_service::error_code(&e), e.to_string()))?;
    let events = session.subscribe();
    let info = match state.hub.insert(session.clone(), name.as_deref()) {
        Ok(info) => info,
        Err(reply) => {
            let _ = state.render.send(Command::Close { id: render_id }).await;
            return Err(reply);
        }
    };
    // The render thread saw the session before its first viewer: look again.
    let _ = state.render.send(Command::Wake).await;
    // The session gives its place back when it closes (`leave`).
    slot.keep();
    state.metrics.sessions_total.fetch_add(1, Ordering::Relaxed);
    tracing::info!(session = render_id, "session opened");
    let welcome = {
        let core = session.core.lock().await;
        welcome(state, &session, &core, &info, false)?
    };
    Ok(Viewer {
        session,
        info,
        events,
        welcome,
        window,
    })
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
                if outbox.send(error_message(reply)).await.is_err() {
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
            if outbox.send(error_message(reply)).await.is_err() {
                return;
            }
        }
    }
}

/// Applies one message. Session edits happen under the session lock, so every viewer sees
/// them in the order they were applied (last writer wins).
async fn handle_message(
    state: &Arc<AppState>,
    session: &SharedSession,
    viewer: &mut ViewerInfo,
    message: ClientMessage,
    link: &ViewerLink,
) -> Result<(), Reply> {
    let arrived = Instant::now();
    match message {
        ClientMessage::Hello { .. } => {
            return Err(Reply::new(
                ErrorCode::NotReady,
                "this connection already said hello",
            ));
        }
        ClientMessage::Name { name } => {
            if let Some(renamed) = session.rename_viewer(viewer.id, &name) {
                *viewer = renamed;
                session.publish(ServerMessage::Viewers {
                    viewers: session.viewers(),
                });
            }
            return Ok(());
        }
        ClientMessage::Ack { seq } => {
            link.acked.send_if_modified(|acked| {
                let newer = seq > *acked;
                if newer {
                    *acked = seq;
                }
                newer
            });
            return Ok(());
        }
        _ => {}
    }
    validate_message(&message)?;
    let mut core = session.core.lock().await;
    let mut scene = core.scene.clone();
    let (change, edit) = match message {
        ClientMessage::Camera(camera) => {
            scene.camera = camera;
            (Change::Camera, ClientMessage::Camera(camera))
        }
        ClientMessage::Tf(tf) => {
            let change = Change::tf(&scene.tf, &tf);
            scene.tf = tf.clone();
            (change, ClientMessage::Tf(tf))
        }
        ClientMessage::Lights { lights } => {
            scene.lights = lights.clone();
            (Change::Lights, ClientMessage::Lights { lights })
        }
        ClientMessage::Viewport(viewport) => {
            check_viewport(state, &viewport)?;
            if viewport == scene.viewport {
                return Ok(());
            }
            scene.viewport = viewport;
            (Change::Viewport, ClientMessage::Viewport(viewport))
        }
        ClientMessage::Params {
            density_scale,
            g,
            exposure,
        } => {
            let params = &mut scene.params;
            params.density_scale = density_scale.unwrap_or(params.density_scale);
            params.g = g.unwrap_or(params.g);
            params.exposure = exposure.unwrap_or(params.exposure);
            validate_params(params).map_err(Reply::bad)?;
            let edit = ClientMessage::Params {
                density_scale: Some(params.density_scale),
                g: Some(params.g),
                exposure: Some(params.exposure),
            };
            (Change::Params, edit)
        }
        ClientMessage::Quality {
            jpeg_quality: quality,
            iterations,
        } => {
            if let Some(q) = quality {
                link.jpeg_quality.store(q, Ordering::Relaxed);
            }
            let Some(n) = iterations else {
                return Ok(());
            };
            scene.target_iterations = n;
            let edit = ClientMessage::Quality {
                jpeg_quality: None,
                iterations: Some(n),
            };
            (Change::Iterations, edit)
        }
        ClientMessage::Technique { name, options } => {
            check_technique(state, &name)?;
            if let Some(options) = &options {
                scene.technique_options = scene.technique_options.overlaid(options);
                voxlight_engine::technique_options::validate(&scene.technique_options)
                    .map_err(Reply::bad)?;
            }
            rebuild(
                state,
                session,
                &mut core,
                None,
                name.clone(),
                scene,
                arrived,
            )
            .await?;
            core.technique = name.clone();
            session.publish(ServerMessage::Edited {
                by: viewer.clone(),
                version: core.version,
                edit: Box::new(ClientMessage::Technique { name, options }),
            });
            return Ok(());
        }
        ClientMessage::Dataset { name } => {
            let events = session.events.clone();
            let progress = loading_progress(&name, move |message| {
                let _ = events.send(Arc::new(message));
            });
            let volume = load_dataset(state, &name, progress).await?;
            // A new dataset is a new scene: its own default TF and lights.
            scene.tf = crate::datasets::default_tf(&volume);
            scene.lights = crate::datasets::default_lights_for(&volume);
            let technique = core.technique.clone();
            let volume = Some(volume);
            rebuild(state, session, &mut core, volume, technique, scene, arrived).await?;
            core.dataset = name.clone();
            let dataset = state
                .catalog
                .info(&name)
                .ok_or_else(|| Reply::new(ErrorCode::Internal, "dataset vanished"))?;
            session.publish(ServerMessage::DatasetLoaded {
                dataset,
                state: core.state(link.jpeg_quality.load(Ordering::Relaxed)),
                by: Some(viewer.clone()),
            });
            return Ok(());
        }
        ClientMessage::Hello { .. } | ClientMessage::Ack { .. } | ClientMessage::Name { .. } => {
            return Ok(());
        }
    };
    core.scene = scene.clone();
    bump_version(session, &mut core, arrived);
    state
        .render
        .send(Command::Edit {
            id: session.render_id,
            scene,
            changes: vec![change],
            version: core.version,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    session.publish(ServerMessage::Edited {
        by: viewer.clone(),
        version: core.version,
        edit: Box::new(edit),
    });
    Ok(())
}

/// Counts an edit: the next scene version, remembered with its arrival time unless an older
/// edit is still waiting for its frame.
fn bump_version(session: &SharedSession, core: &mut SessionCore, arrived: Instant) {
    core.version += 1;
    if let Ok(mut pending) = session.edit_clock.lock() {
        pending.get_or_insert((core.version, arrived));
    }
}

/// Swaps the session's volume and/or technique on the render thread; the version advances
/// only when that worked.
async fn rebuild(
    state: &Arc<AppState>,
    session: &SharedSession,
    core: &mut SessionCore,
    volume: Option<Arc<voxlight_volumes::Volume>>,
    technique: String,
    scene: Scene,
    arrived: Instant,
) -> Result<(), Reply> {
    let (reply, done) = oneshot::channel();
    state
        .render
        .send(Command::Rebuild {
            id: session.render_id,
            volume,
            technique,
            scene: scene.clone(),
            version: core.version + 1,
            reply,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    done.await
        .map_err(|_| Reply::new(ErrorCode::Internal, "render thread dropped the request"))?
        .map_err(|e| Reply::new(crate::render_service::error_code(&e), e.to_string()))?;
    core.scene = scene;
    bump_version(session, core, arrived);
    Ok(())
}

/// Sends with a deadline, so a viewer that stopped reading cannot hold its task forever.
async fn send(sink: &mut Sink, message: Message) -> bool {
    matches!(
        tokio::time::timeout(SEND_TIMEOUT, sink.send(message)).await,
        Ok(Ok(()))
    )
}

/// Per-viewer frame pacing: what was sent and not yet acknowledged, and what was skipped.
struct Pacing {
    window: Option<u32>,
    in_flight: VecDeque<(u64, Instant)>,
    last_seq: u64,
    skipped: u64,
    adapt: QualityController,
    sent_times: VecDeque<Instant>,
    last_stats: Instant,
}

impl Pacing {
    fn ready(&self) -> bool {
        self.window
            .is_none_or(|w| self.in_flight.len() < w as usize)
    }

    fn acknowledge(&mut self, upto: u64, metrics: &Metrics) {
        let now = Instant::now();
        while let Some(&(seq, sent)) = self.in_flight.front()
            && seq <= upto
        {
            self.in_flight.pop_front();
            self.adapt.observe(now.duration_since(sent));
            metrics.frames_in_flight.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

async fn write_loop(
    mut sink: Sink,
    mut outbox: mpsc::Receiver<ServerMessage>,
    session: Arc<SharedSession>,
    mut events: broadcast::Receiver<Arc<ServerMessage>>,
    link: Arc<ViewerLink>,
    state: Arc<AppState>,
) {
    let _end_reader = link.connection.clone().drop_guard();
    let (shutdown, metrics) = (&state.shutdown, &state.metrics);
    let mut frames = session.frames();
    let mut acked = link.acked.subscribe();
    let mut pacing = Pacing {
        window: link.window,
        in_flight: VecDeque::new(),
        last_seq: 0,
        skipped: 0,
        adapt: QualityController::default(),
        sent_times: VecDeque::new(),
        last_stats: Instant::now() - STATS_INTERVAL,
    };
    let mut ping = tokio::time::interval_at(
        tokio::time::Instant::now() + state.ping_interval,
        state.ping_interval,
    );
    loop {
        let ready = pacing.ready();
        let outgoing = tokio::select! {
            biased;
            _ = shutdown.cancelled() => {
                let reason = if state.draining.is_cancelled() {
                    "server drained for a restart or scale-down; reopen the view at the deployment's root"
                } else {
                    "server shutting down"
                };
                let bye = ServerMessage::Bye { reason: reason.into() };
                let _ = send(&mut sink, text(&bye)).await;
                let _ = sink.close().await;
                break;
            }
            message = outbox.recv() => match message {
                Some(message) => {
                    if let ServerMessage::Error { code, .. } = &message {
                        metrics.error_sent(*code);
                    }
                    text(&message)
                }
                None => {
                    let frame = link.close.lock().ok().and_then(|mut close| close.take());
                    match frame {
                        Some(frame) => {
                            if send(&mut sink, Message::Close(Some(frame))).await {
                                tokio::select! {
                                    _ = tokio::time::sleep(CLOSE_LINGER) => {}
                                    _ = shutdown.cancelled() => {}
                                }
                            }
                        }
                        None => {
                            let _ = sink.close().await;
                        }
                    }
                    break;
                }
            },
            event = events.recv() => match event {
                Ok(message) => {
                    if let ServerMessage::Error { code, .. } = *message {
                        metrics.error_sent(code);
                    }
                    text(&message)
                }
                Err(RecvError::Lagged(_)) => {
                    // Fell behind on edits: one message with the whole state replaces them.
                    let core = session.core.lock().await;
                    let Some(dataset) = state.catalog.info(&core.dataset) else { continue };
                    text(&ServerMessage::State {
                        state: core.state(link.jpeg_quality.load(Ordering::Relaxed)),
                        version: core.version,
                        dataset,
                        viewers: session.viewers(),
                    })
                }
                Err(RecvError::Closed) => break,
            },
            _ = ping.tick() => Message::Ping(Default::default()),
            changed = acked.changed() => {
                if changed.is_err() {
                    break;
                }
                let upto = *acked.borrow_and_update();
                pacing.acknowledge(upto, metrics);
                continue;
            }
            changed = frames.changed(), if ready => {
                if changed.is_err() {
                    break;
                }
                let Some(rendered) = frames.borrow_and_update().clone() else { continue };
                if rendered.frame_number <= pacing.last_seq {
                    continue;
                }
                let encoding = if rendered.frame.converged {
                    Encoding::Png
                } else {
                    Encoding::Jpeg(pacing.adapt.quality(link.jpeg_quality.load(Ordering::Relaxed)))
                };
                let encoded = match session.encoded(&rendered, encoding, metrics).await {
                    Ok(encoded) => encoded,
                    Err(e) => {
                        tracing::error!(session = session.render_id, error = %e, "frame encoding failed");
                        continue;
                    }
                };
                // Counted before the send: a viewer that has the frame must find it counted.
                if pacing.last_seq > 0 {
                    let skipped = rendered.frame_number - pacing.last_seq - 1;
                    pacing.skipped += skipped;
                    metrics.frames_skipped.fetch_add(skipped, Ordering::Relaxed);
                }
                pacing.last_seq = rendered.frame_number;
                let started = Instant::now();
                if !send(&mut sink, Message::Binary(encoded.bytes.clone())).await {
                    break;
                }
                let now = Instant::now();
                match pacing.window {
                    Some(_) => {
                        pacing.in_flight.push_back((rendered.frame_number, started));
                        metrics.frames_in_flight.fetch_add(1, Ordering::Relaxed);
                    }
                    None => pacing.adapt.observe(now.duration_since(started)),
                }
                metrics.frame_sent(encoded.meta.format, encoded.bytes.len());
                session.frames_sent.fetch_add(1, Ordering::Relaxed);
                if let Ok(mut pending) = session.edit_clock.lock()
                    && let Some((version, arrived)) = *pending
                    && encoded.meta.scene_version >= version
                {
                    metrics.input_to_frame_seconds.observe(now.duration_since(arrived));
                    *pending = None;
                }
                pacing.sent_times.push_back(now);
                while pacing.sent_times.front().is_some_and(|t| now.duration_since(*t) > Duration::from_secs(1)) {
                    pacing.sent_times.pop_front();
                }
                if now.duration_since(pacing.last_stats) < STATS_INTERVAL && !encoded.meta.converged {
                    continue;
                }
                pacing.last_stats = now;
                text(&ServerMessage::Stats(Stats {
                    fps: pacing.sent_times.len() as f32,
                    viewers: session.viewers().len() as u32,
                    jpeg_quality: pacing.adapt.quality(link.jpeg_quality.load(Ordering::Relaxed)),
                    frames_skipped: pacing.skipped,
                    ..encoded.stats.clone()
                }))
            }
        };
        if !send(&mut sink, outgoing).await {
            break;
        }
    }
    metrics
        .frames_in_flight
        .fetch_sub(pacing.in_flight.len() as i64, Ordering::Relaxed);
}
