//! One WebSocket connection = one rendering session (for now). The reader side owns the
//! session's state and turns client messages into engine changes; the writer side encodes the
//! newest rendered frame (off the runtime) and sends it with text messages.

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use axum::extract::ws::{Message, Utf8Bytes, WebSocket};
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use tokio::sync::{mpsc, oneshot, watch};
use voxlight_engine::camera::CameraBasis;
use voxlight_engine::scene::{validate_lights, validate_params, validate_viewport};
use voxlight_engine::{Change, Scene};
use voxlight_protocol::{
    ClientMessage, ErrorCode, FrameFormat, FrameMeta, MAX_MESSAGE_BYTES, MAX_MESSAGES_PER_SECOND,
    PROTOCOL_VERSION, RenderParams, ServerMessage, SessionState, Stats, Viewport, join_frame,
};

use crate::AppState;
use crate::metrics::Metrics;
use crate::render_service::{Command, RenderEvent, RenderedFrame, SessionId};

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

static NEXT_SESSION: AtomicU64 = AtomicU64::new(1);

type Sink = SplitSink<WebSocket, Message>;
type Stream = SplitStream<WebSocket>;

/// A protocol-level failure answered with an `error` message.
#[derive(Debug)]
struct Reply {
    code: ErrorCode,
    message: String,
}

impl Reply {
    fn new(code: ErrorCode, message: impl Into<String>) -> Self {
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

/// Everything one session edits, and the scene the engine renders from it.
struct SessionCore {
    id: SessionId,
    dataset: String,
    technique: String,
    scene: Scene,
    version: u64,
    edit_clock: EditClock,
}

/// The oldest edit no frame has shown yet (scene version, arrival), for the input-to-frame
/// latency metric.
type EditClock = Arc<std::sync::Mutex<Option<(u64, Instant)>>>;

impl SessionCore {
    /// Counts an edit: the next scene version, remembered with its arrival time unless an
    /// older edit is still waiting for its frame.
    fn bump_version(&mut self, arrived: Instant) {
        self.version += 1;
        if let Ok(mut pending) = self.edit_clock.lock() {
            pending.get_or_insert((self.version, arrived));
        }
    }

    fn state(&self, jpeg_quality: u8) -> SessionState {
        SessionState {
            dataset: self.dataset.clone(),
            technique: self.technique.clone(),
            camera: self.scene.camera,
            tf: self.scene.tf.clone(),
            lights: self.scene.lights.clone(),
            params: self.scene.params,
            viewport: self.scene.viewport,
            iterations: self.scene.target_iterations,
            jpeg_quality,
        }
    }
}

/// Serves one WebSocket connection until it closes or the server shuts down.
pub async fn handle_socket(socket: WebSocket, state: Arc<AppState>) {
    let (mut sink, mut stream) = socket.split();
    let hello = tokio::select! {
        hello = wait_for_hello(&mut sink, &mut stream, &state.metrics) => hello,
        _ = state.shutdown.cancelled() => None,
    };
    let Some(hello) = hello else { return };
    let session = match open_session(&state, hello).await {
        Ok(session) => session,
        Err(reply) => {
            state.metrics.error_sent(reply.code);
            let _ = sink.send(text(&error_message(reply))).await;
            let _ = sink.close().await;
            return;
        }
    };
    let OpenSession {
        core,
        frames,
        events,
        welcome,
    } = session;
    let id = core.id;
    tracing::info!(session = id, dataset = %core.dataset, "session opened");
    let jpeg_quality = Arc::new(AtomicU8::new(DEFAULT_JPEG_QUALITY));
    let (outbox, outbox_rx) = mpsc::channel(OUTBOX);
    let _ = outbox.send(welcome).await;
    let writer = state.tracker.spawn(write_loop(
        sink,
        outbox_rx,
        frames,
        events,
        jpeg_quality.clone(),
        state.clone(),
        core.edit_clock.clone(),
    ));
    state
        .metrics
        .sessions_active
        .fetch_add(1, Ordering::Relaxed);
    state.metrics.sessions_total.fetch_add(1, Ordering::Relaxed);
    read_loop(&state, core, stream, outbox, jpeg_quality).await;
    let _ = state.render.send(Command::Close { id }).await;
    let _ = writer.await;
    state
        .metrics
        .sessions_active
        .fetch_sub(1, Ordering::Relaxed);
    tracing::info!(session = id, "session closed");
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
            Ok(_) => return None,
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

struct OpenSession {
    core: SessionCore,
    frames: watch::Receiver<Option<Arc<RenderedFrame>>>,
    events: mpsc::Receiver<RenderEvent>,
    welcome: ServerMessage,
}

async fn load_dataset(
    state: &Arc<AppState>,
    name: &str,
) -> Result<Arc<voxlight_volumes::Volume>, Reply> {
    if !state.catalog.contains(name) {
        return Err(Reply::new(
            ErrorCode::UnknownDataset,
            format!("unknown dataset `{name}`; GET /api/datasets lists them"),
        ));
    }
    let catalog = state.catalog.clone();
    let owned = name.to_owned();
    tokio::task::spawn_blocking(move || catalog.load(&owned))
        .await
        .map_err(|e| Reply::new(ErrorCode::Internal, format!("loader task failed: {e}")))?
        .map_err(|e| Reply::new(ErrorCode::LoadFailed, e.to_string()))
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

async fn open_session(state: &Arc<AppState>, hello: ClientMessage) -> Result<OpenSession, Reply> {
    let ClientMessage::Hello {
        protocol,
        session,
        viewport,
        dataset,
        technique,
        ..
    } = hello
    else {
        return Err(Reply::new(ErrorCode::NotReady, "expected hello"));
    };
    if protocol != PROTOCOL_VERSION {
        return Err(Reply::new(
            ErrorCode::ProtocolVersion,
            format!("this server speaks protocol {PROTOCOL_VERSION}, the client {protocol}"),
        ));
    }
    if session.is_some() {
        return Err(Reply::new(
            ErrorCode::BadValue,
            "joining sessions is not supported yet; omit `session`",
        ));
    }
    let viewport = viewport.unwrap_or_default();
    check_viewport(state, &viewport)?;
    let technique = technique.unwrap_or_else(|| "raymarch".to_owned());
    check_technique(state, &technique)?;
    let dataset = dataset.unwrap_or_else(|| state.default_dataset.clone());
    let volume = load_dataset(state, &dataset).await?;
    let scene = Scene {
        tf: crate::datasets::default_tf(&volume),
        lights: crate::datasets::default_lights_for(&volume),
        params: RenderParams::default(),
        viewport,
        target_iterations: DEFAULT_ITERATIONS,
        ..Scene::default()
    };
    let core = SessionCore {
        id: NEXT_SESSION.fetch_add(1, Ordering::Relaxed),
        dataset: dataset.clone(),
        technique: technique.clone(),
        scene: scene.clone(),
        version: 0,
        edit_clock: Default::default(),
    };
    let (frame_slot, frames) = watch::channel(None);
    let (event_slot, events) = mpsc::channel(16);
    let (reply, opened) = oneshot::channel();
    state
        .render
        .send(Command::Open {
            id: core.id,
            volume,
            technique,
            scene,
            version: 0,
            frames: frame_slot,
            events: event_slot,
            reply,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    opened
        .await
        .map_err(|_| Reply::new(ErrorCode::Internal, "render thread dropped the request"))?
        .map_err(|e| Reply::new(crate::render_service::error_code(&e), e.to_string()))?;
    let welcome = ServerMessage::Welcome {
        protocol: PROTOCOL_VERSION,
        session: format!("{:016x}", core.id),
        server_version: env!("CARGO_PKG_VERSION").to_owned(),
        adapter: state.adapter.clone(),
        dataset: state
            .catalog
            .info(&dataset)
            .ok_or_else(|| Reply::new(ErrorCode::Internal, "dataset vanished"))?,
        techniques: state.techniques.clone(),
        state: core.state(DEFAULT_JPEG_QUALITY),
    };
    Ok(OpenSession {
        core,
        frames,
        events,
        welcome,
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
    mut core: SessionCore,
    mut stream: Stream,
    outbox: mpsc::Sender<ServerMessage>,
    jpeg_quality: Arc<AtomicU8>,
) {
    let mut limit = RateLimit::new();
    loop {
        let message = tokio::select! {
            message = stream.next() => message,
            _ = state.shutdown.cancelled() => return,
        };
        let message = match message {
            Some(Ok(Message::Close(_))) | None => return,
            Some(Ok(message)) => message,
            Some(Err(e)) => {
                tracing::debug!(session = core.id, error = %e, "websocket read failed");
                return;
            }
        };
        if let Err(report) = limit.take() {
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
        let result = match parse(message) {
            Ok(Some(message)) => {
                handle_message(state, &mut core, message, &outbox, &jpeg_quality).await
            }
            Ok(None) => Ok(()),
            Err(reply) => Err(reply),
        };
        if let Err(reply) = result {
            tracing::debug!(session = core.id, code = ?reply.code, message = %reply.message, "client error");
            if outbox.send(error_message(reply)).await.is_err() {
                return;
            }
        }
    }
}

async fn handle_message(
    state: &Arc<AppState>,
    core: &mut SessionCore,
    message: ClientMessage,
    outbox: &mpsc::Sender<ServerMessage>,
    jpeg_quality: &AtomicU8,
) -> Result<(), Reply> {
    let arrived = Instant::now();
    let mut scene = core.scene.clone();
    let change = match message {
        ClientMessage::Hello { .. } => {
            return Err(Reply::new(
                ErrorCode::NotReady,
                "this connection already said hello",
            ));
        }
        ClientMessage::Camera(camera) => {
            CameraBasis::new(&camera).map_err(Reply::bad)?;
            scene.camera = camera;
            Change::Camera
        }
        ClientMessage::Tf(tf) => {
            voxlight_engine::tf::validate(&tf).map_err(Reply::bad)?;
            let change = Change::tf(&scene.tf, &tf);
            scene.tf = tf;
            change
        }
        ClientMessage::Lights { lights } => {
            validate_lights(&lights).map_err(Reply::bad)?;
            scene.lights = lights;
            Change::Lights
        }
        ClientMessage::Viewport(viewport) => {
            check_viewport(state, &viewport)?;
            if viewport == scene.viewport {
                return Ok(());
            }
            scene.viewport = viewport;
            Change::Viewport
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
            Change::Params
        }
        ClientMessage::Quality {
            jpeg_quality: quality,
            iterations,
        } => {
            if let Some(q) = quality {
                if !(1..=100).contains(&q) {
                    return Err(Reply::bad(format!(
                        "jpeg_quality must be in 1..=100, got {q}"
                    )));
                }
                jpeg_quality.store(q, Ordering::Relaxed);
            }
            match iterations {
                None => return Ok(()),
                Some(n) if (1..=65536).contains(&n) => {
                    scene.target_iterations = n;
                    Change::Iterations
                }
                Some(n) => {
                    return Err(Reply::bad(format!(
                        "iterations must be in 1..=65536, got {n}"
                    )));
                }
            }
        }
        ClientMessage::Technique { name } => {
            check_technique(state, &name)?;
            core.bump_version(arrived);
            rebuild(state, core, None, name.clone(), scene).await?;
            core.technique = name;
            return Ok(());
        }
        ClientMessage::Dataset { name } => {
            let volume = load_dataset(state, &name).await?;
            // A new dataset is a new scene: its own default TF and lights.
            scene.tf = crate::datasets::default_tf(&volume);
            scene.lights = crate::datasets::default_lights_for(&volume);
            core.bump_version(arrived);
            rebuild(state, core, Some(volume), core.technique.clone(), scene).await?;
            core.dataset = name.clone();
            let dataset = state
                .catalog
                .info(&name)
                .ok_or_else(|| Reply::new(ErrorCode::Internal, "dataset vanished"))?;
            let state = core.state(jpeg_quality.load(Ordering::Relaxed));
            let _ = outbox
                .send(ServerMessage::DatasetLoaded { dataset, state })
                .await;
            return Ok(());
        }
    };
    core.scene = scene.clone();
    core.bump_version(arrived);
    state
        .render
        .send(Command::Edit {
            id: core.id,
            scene,
            changes: vec![change],
            version: core.version,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))
}

/// Swaps the session's volume and/or technique on the render thread.
async fn rebuild(
    state: &Arc<AppState>,
    core: &mut SessionCore,
    volume: Option<Arc<voxlight_volumes::Volume>>,
    technique: String,
    scene: Scene,
) -> Result<(), Reply> {
    let (reply, done) = oneshot::channel();
    state
        .render
        .send(Command::Rebuild {
            id: core.id,
            volume,
            technique,
            scene: scene.clone(),
            version: core.version,
            reply,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    done.await
        .map_err(|_| Reply::new(ErrorCode::Internal, "render thread dropped the request"))?
        .map_err(|e| Reply::new(crate::render_service::error_code(&e), e.to_string()))?;
    core.scene = scene;
    Ok(())
}

async fn write_loop(
    mut sink: Sink,
    mut outbox: mpsc::Receiver<ServerMessage>,
    mut frames: watch::Receiver<Option<Arc<RenderedFrame>>>,
    mut events: mpsc::Receiver<RenderEvent>,
    jpeg_quality: Arc<AtomicU8>,
    state: Arc<AppState>,
    edit_clock: EditClock,
) {
    let (shutdown, metrics) = (&state.shutdown, &state.metrics);
    let mut seq = 0u64;
    let mut last_stats = Instant::now() - STATS_INTERVAL;
    let mut sent_times: std::collections::VecDeque<Instant> = Default::default();
    loop {
        let outgoing = tokio::select! {
            biased;
            _ = shutdown.cancelled() => {
                let bye = ServerMessage::Bye { reason: "server shutting down".into() };
                let _ = sink.send(text(&bye)).await;
                let _ = sink.close().await;
                return;
            }
            message = outbox.recv() => match message {
                Some(message) => {
                    if let ServerMessage::Error { code, .. } = &message {
                        metrics.error_sent(*code);
                    }
                    text(&message)
                }
                None => {
                    let _ = sink.close().await;
                    return;
                }
            },
            Some(event) = events.recv() => {
                metrics.error_sent(event.code);
                text(&ServerMessage::Error { code: event.code, message: event.message })
            }
            changed = frames.changed() => {
                if changed.is_err() {
                    return;
                }
                let Some(rendered) = frames.borrow_and_update().clone() else { continue };
                let quality = jpeg_quality.load(Ordering::Relaxed);
                seq += 1;
                let encoded = tokio::task::spawn_blocking(move || encode_frame(&rendered, seq, quality)).await;
                let (bytes, stats, meta) = match encoded {
                    Ok(Ok(done)) => done,
                    Ok(Err(e)) => {
                        tracing::error!(error = %e, "frame encoding failed");
                        continue;
                    }
                    Err(e) => {
                        tracing::error!(error = %e, "encoder task failed");
                        continue;
                    }
                };
                let size = bytes.len();
                if sink.send(Message::Binary(bytes.into())).await.is_err() {
                    return;
                }
                let now = Instant::now();
                metrics.frame_sent(meta.format, size, Duration::from_secs_f32(meta.encode_ms / 1000.0));
                if let Ok(mut pending) = edit_clock.lock()
                    && let Some((version, arrived)) = *pending
                    && meta.scene_version >= version
                {
                    metrics.input_to_frame_seconds.observe(now.duration_since(arrived));
                    *pending = None;
                }
                sent_times.push_back(now);
                while sent_times.front().is_some_and(|t| now.duration_since(*t) > Duration::from_secs(1)) {
                    sent_times.pop_front();
                }
                if now.duration_since(last_stats) < STATS_INTERVAL && !stats.converged {
                    continue;
                }
                last_stats = now;
                text(&ServerMessage::Stats(Stats { fps: sent_times.len() as f32, ..stats }))
            }
        };
        if sink.send(outgoing).await.is_err() {
            return;
        }
    }
}

/// Encodes a rendered frame as a binary frame message: PNG once converged, JPEG before.
fn encode_frame(
    rendered: &RenderedFrame,
    seq: u64,
    quality: u8,
) -> Result<(Vec<u8>, Stats, FrameMeta), crate::encode::EncodeError> {
    let started = Instant::now();
    let frame = &rendered.frame;
    let (image, format) = if frame.converged {
        (
            crate::encode::png(&frame.rgba, frame.width, frame.height)?,
            FrameFormat::Png,
        )
    } else {
        (
            crate::encode::jpeg(&frame.rgba, frame.width, frame.height, quality)?,
            FrameFormat::Jpeg,
        )
    };
    let meta = FrameMeta {
        seq,
        format,
        width: frame.width,
        height: frame.height,
        technique: rendered.technique.to_owned(),
        iteration: frame.iteration,
        target_iterations: frame.target_iterations,
        converged: frame.converged,
        lossless: format == FrameFormat::Png,
        quality: (format == FrameFormat::Jpeg).then_some(quality),
        scene_version: rendered.scene_version,
        render_ms: rendered.render_ms,
        encode_ms: started.elapsed().as_secs_f32() * 1000.0,
    };
    let stats = Stats {
        technique: rendered.technique.to_owned(),
        iteration: frame.iteration,
        target_iterations: frame.target_iterations,
        converged: frame.converged,
        gpu_ms: rendered.gpu_ms,
        memory_bytes: rendered.stats.memory_bytes,
        fps: 0.0,
    };
    Ok((join_frame(&meta, &image), stats, meta))
}
