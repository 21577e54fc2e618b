//! The render thread: owns the engine and every session's GPU state, takes commands from the
//! async side over a bounded channel, and publishes each session's newest frame into a
//! `watch` slot (newest wins). Sessions needing work get time slices in turn; converged
//! sessions get none.

use std::collections::HashMap;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use tokio::sync::{mpsc, oneshot, watch};
use voxlight_engine::{
    Change, Engine, EngineError, Frame, GpuVolume, Renderer, Scene, TechniqueStats,
};
use voxlight_protocol::ErrorCode;
use voxlight_volumes::Volume;

/// GPU time one session gets before the next session's turn.
pub const TIME_SLICE: Duration = Duration::from_millis(30);

/// Commands queued to the render thread before senders wait.
const COMMAND_QUEUE: usize = 256;

pub type SessionId = u64;

/// A frame as rendered, before encoding.
#[derive(Debug)]
pub struct RenderedFrame {
    pub frame: Frame,
    pub technique: &'static str,
    /// The session's edit counter when this picture's state was applied.
    pub scene_version: u64,
    /// Wall time of the slice: progressive work, tone mapping and readback.
    pub render_ms: f32,
    /// GPU time of the slice's technique passes (timestamp queries where available).
    pub gpu_ms: f32,
    pub stats: TechniqueStats,
}

pub type FrameSlot = watch::Sender<Option<Arc<RenderedFrame>>>;

/// Something the render thread tells a session outside frames.
#[derive(Debug, Clone)]
pub struct RenderEvent {
    pub code: ErrorCode,
    pub message: String,
}

pub enum Command {
    Open {
        id: SessionId,
        volume: Arc<Volume>,
        technique: String,
        scene: Scene,
        version: u64,
        frames: FrameSlot,
        events: mpsc::Sender<RenderEvent>,
        reply: oneshot::Sender<Result<(), EngineError>>,
    },
    Edit {
        id: SessionId,
        scene: Scene,
        changes: Vec<Change>,
        version: u64,
    },
    /// Replace volume and/or technique: rebuilds the session's renderer.
    Rebuild {
        id: SessionId,
        volume: Option<Arc<Volume>>,
        technique: String,
        scene: Scene,
        version: u64,
        reply: oneshot::Sender<Result<(), EngineError>>,
    },
    Close {
        id: SessionId,
    },
    /// Drop every session and end the thread.
    Stop,
}

/// Maps engine errors to protocol error codes.
pub fn error_code(error: &EngineError) -> ErrorCode {
    match error {
        EngineError::OutOfMemory { .. } | EngineError::ViewportTooLarge { .. } => {
            ErrorCode::GpuMemory
        }
        EngineError::UnknownTechnique(_) => ErrorCode::UnknownTechnique,
        EngineError::InvalidScene(_) => ErrorCode::BadValue,
        EngineError::NoAdapter(_) | EngineError::Gpu(_) | EngineError::DeviceLost => ErrorCode::Gpu,
    }
}

/// The async side's handle to the render thread.
#[derive(Clone)]
pub struct RenderHandle {
    commands: mpsc::Sender<Command>,
}

impl RenderHandle {
    /// Queues a command; waits while the queue is full.
    pub async fn send(&self, command: Command) -> Result<(), EngineError> {
        self.commands
            .send(command)
            .await
            .map_err(|_| EngineError::Gpu("the render thread has stopped".into()))
    }
}

struct Session {
    renderer: Renderer,
    scene: Scene,
    version: u64,
    frames: FrameSlot,
    events: mpsc::Sender<RenderEvent>,
    /// A frame of the current state is still owed to viewers.
    dirty: bool,
    failed: bool,
}

/// Starts the render thread. It stops when every `RenderHandle` is dropped.
pub fn spawn(
    engine: Arc<Engine>,
    metrics: Arc<crate::metrics::Metrics>,
) -> std::io::Result<(RenderHandle, std::thread::JoinHandle<()>)> {
    let (commands, receiver) = mpsc::channel(COMMAND_QUEUE);
    let thread = std::thread::Builder::new()
        .name("voxlight-render".into())
        .spawn(move || RenderThread::new(engine, metrics).run(receiver))?;
    Ok((RenderHandle { commands }, thread))
}

struct RenderThread {
    engine: Arc<Engine>,
    metrics: Arc<crate::metrics::Metrics>,
    sessions: HashMap<SessionId, Session>,
    volumes: HashMap<String, Weak<GpuVolume>>,
    /// Round-robin position.
    last_served: SessionId,
}

impl RenderThread {
    fn new(engine: Arc<Engine>, metrics: Arc<crate::metrics::Metrics>) -> Self {
        Self {
            engine,
            metrics,
            sessions: HashMap::new(),
            volumes: HashMap::new(),
            last_served: 0,
        }
    }

    fn run(mut self, mut receiver: mpsc::Receiver<Command>) {
        tracing::info!("render thread started");
        loop {
            let busy = self.sessions.values().any(|s| s.dirty && !s.failed);
            if !busy {
                match receiver.blocking_recv() {
                    Some(Command::Stop) | None => break,
                    Some(command) => self.handle(command),
                }
            }
            loop {
                match receiver.try_recv() {
                    Ok(Command::Stop) => {
                        tracing::info!("render thread stopped");
                        return;
                    }
                    Ok(command) => self.handle(command),
                    Err(mpsc::error::TryRecvError::Empty) => break,
                    Err(mpsc::error::TryRecvError::Disconnected) => {
                        tracing::info!("render thread stopping");
                        return;
                    }
                }
            }
            if let Some(id) = self.next_session() {
                self.serve(id);
            }
        }
        tracing::info!("render thread stopped");
    }

    /// The next session after the last one served that owes a frame.
    fn next_session(&self) -> Option<SessionId> {
        let mut ids: Vec<SessionId> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.dirty && !s.failed)
            .map(|(id, _)| *id)
            .collect();
        ids.sort_unstable();
        ids.iter()
            .copied()
            .find(|&id| id > self.last_served)
            .or(ids.first().copied())
    }

    fn gpu_volume(&mut self, volume: &Volume) -> Result<Arc<GpuVolume>, EngineError> {
        if let Some(existing) = self.volumes.get(&volume.name).and_then(Weak::upgrade) {
            return Ok(existing);
        }
        let uploaded = self.engine.upload_volume(volume)?;
        self.volumes.retain(|_, weak| weak.strong_count() > 0);
        self.volumes
            .insert(volume.name.clone(), Arc::downgrade(&uploaded));
        Ok(uploaded)
    }

    fn handle(&mut self, command: Command) {
        match command {
            Command::Open {
                id,
                volume,
                technique,
                scene,
                version,
                frames,
                events,
                reply,
            } => {
                let result = self.gpu_volume(&volume).and_then(|gpu_volume| {
                    self.engine.create_renderer(&technique, gpu_volume, &scene)
                });
                match result {
                    Ok(renderer) => {
                        self.sessions.insert(
                            id,
                            Session {
                                renderer,
                                scene,
                                version,
                                frames,
                                events,
                                dirty: true,
                                failed: false,
                            },
                        );
                        let _ = reply.send(Ok(()));
                    }
                    Err(e) => {
                        let _ = reply.send(Err(e));
                    }
                }
            }
            Command::Edit {
                id,
                scene,
                changes,
                version,
            } => {
                let Some(session) = self.sessions.get_mut(&id) else {
                    return;
                };
                session.scene = scene;
                session.version = version;
                session.dirty = true;
                for change in &changes {
                    if let Err(e) = session.renderer.apply(&self.engine, &session.scene, change) {
                        session.failed = true;
                        let _ = session.events.try_send(RenderEvent {
                            code: error_code(&e),
                            message: e.to_string(),
                        });
                        break;
                    }
                    session.failed = false;
                }
            }
            Command::Rebuild {
                id,
                volume,
                technique,
                scene,
                version,
                reply,
            } => {
                let Some(current) = self.sessions.get(&id).map(|s| s.renderer.volume().clone())
                else {
                    let _ = reply.send(Err(EngineError::Gpu("session is closed".into())));
                    return;
                };
                let gpu_volume = match volume {
                    Some(volume) => self.gpu_volume(&volume),
                    None => Ok(current),
                };
                let result =
                    gpu_volume.and_then(|v| self.engine.create_renderer(&technique, v, &scene));
                match (result, self.sessions.get_mut(&id)) {
                    (Ok(renderer), Some(session)) => {
                        session.renderer = renderer;
                        session.scene = scene;
                        session.version = version;
                        session.dirty = true;
                        session.failed = false;
                        let _ = reply.send(Ok(()));
                    }
                    (Err(e), _) => {
                        let _ = reply.send(Err(e));
                    }
                    (Ok(_), None) => {
                        let _ = reply.send(Err(EngineError::Gpu("session is closed".into())));
                    }
                }
            }
            Command::Close { id } => {
                self.sessions.remove(&id);
                self.volumes.retain(|_, weak| weak.strong_count() > 0);
            }
            Command::Stop => {}
        }
    }

    /// One time slice for a session: progressive work, then a frame for its viewers.
    fn serve(&mut self, id: SessionId) {
        self.last_served = id;
        let engine = self.engine.clone();
        let Some(session) = self.sessions.get_mut(&id) else {
            return;
        };
        let started = Instant::now();
        let result = session
            .renderer
            .step(&engine, &session.scene, TIME_SLICE)
            .and_then(|report| Ok((report, session.renderer.frame(&engine, &session.scene)?)));
        match result {
            Ok((report, frame)) => {
                self.metrics
                    .gpu_time(session.renderer.technique_name(), report.gpu_time);
                session.dirty = !frame.converged;
                let rendered = RenderedFrame {
                    technique: session.renderer.technique_name(),
                    scene_version: session.version,
                    render_ms: started.elapsed().as_secs_f32() * 1000.0,
                    gpu_ms: report.gpu_time.as_secs_f32() * 1000.0,
                    stats: session.renderer.stats(),
                    frame,
                };
                session.frames.send_replace(Some(Arc::new(rendered)));
            }
            Err(e) => {
                tracing::error!(session = id, error = %e, "rendering failed");
                session.failed = true;
                let _ = session.events.try_send(RenderEvent {
                    code: error_code(&e),
                    message: e.to_string(),
                });
            }
        }
    }
}
