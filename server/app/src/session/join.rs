//! The `hello` handshake: a session opened (its dataset loaded, progress reported) or joined.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use axum::extract::ws::Message;
use futures_util::{SinkExt, StreamExt};
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use voxlight_engine::Scene;
use voxlight_engine::scene::validate_viewport;
use voxlight_protocol::{
    ClientMessage, ErrorCode, PROTOCOL_VERSION, RenderParams, ServerMessage, ViewerInfo, Viewport,
};

use crate::AppState;
use crate::hub::{EVENT_BUFFER, SessionCore, SharedSession};
use crate::metrics::Metrics;
use crate::render_service::{Command, SessionId};
use crate::reply::Reply;

use super::edit::validate_message;
use super::{
    CLOSE_LINGER, DEFAULT_ITERATIONS, DEFAULT_JPEG_QUALITY, HELLO_TIMEOUT, Sink, Stream, parse,
    text, transport_close,
};

static NEXT_SESSION: AtomicU64 = AtomicU64::new(1);

/// Answers everything before a valid `hello` with `not_ready`.
pub(super) async fn wait_for_hello(
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
                let _ = sink.send(text(&ServerMessage::from(reply))).await;
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
        if sink.send(text(&ServerMessage::from(reply))).await.is_err() {
            return None;
        }
    }
}

/// A connection admitted to a session.
pub(super) struct Viewer {
    pub(super) session: Arc<SharedSession>,
    pub(super) info: ViewerInfo,
    pub(super) events: broadcast::Receiver<Arc<ServerMessage>>,
    pub(super) welcome: ServerMessage,
    /// Frames in flight before acknowledgements (None: the client does not acknowledge).
    pub(super) window: Option<u32>,
}

/// Where a dataset's load progress goes: `done` and `total` parts (a PACS series' instances).
pub(super) type Progress = Box<dyn Fn(u32, u32) + Send + Sync>;

pub(super) async fn load_dataset(
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
pub(super) fn check_viewport(state: &AppState, viewport: &Viewport) -> Result<(), Reply> {
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

pub(super) fn check_technique(state: &AppState, name: &str) -> Result<(), Reply> {
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
pub(super) fn loading_progress(
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

pub(super) async fn open_or_join(
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
