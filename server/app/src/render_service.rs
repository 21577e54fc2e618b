//! The render thread: owns the engine and every session's GPU state, takes commands from the
//! async side over a bounded channel, and publishes each session's newest frame into a
//! `watch` slot (newest wins) that every viewer of the session reads.
//!
//! Scheduling: sessions that owe a frame get `TIME_SLICE`s in turn. Sessions edited in the
//! last `INTERACTIVE_WINDOW` (someone is dragging the camera or editing the TF) come first;
//! the others still get every `BACKGROUND_TURN`-th slice so they never starve. Converged
//! sessions and sessions without viewers (in their reconnect grace period) get none.
//! Interaction mode (docs/architecture.md): while edits stream in, a session's first slice
//! after each edit renders the engine's preview (any technique) at a resolution divisor
//! adapted to `Interaction::frame_target`, and the technique sees the edits only once input
//! has rested for `Interaction::rest_after` (merged, so a drag costs it one update). At rest a
//! reduced preview is followed by a full-resolution one, then the technique refines to its
//! converged, lossless still.
//! GPU memory: every session and uploaded volume is counted against a global budget, and a
//! session, dataset switch or viewport that would exceed it is refused (`gpu_memory`).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use tokio::sync::{broadcast, mpsc, oneshot, watch};
use voxlight_engine::preview::LightDetail;
use voxlight_engine::{
    Change, Engine, EngineError, Frame, GpuVolume, Renderer, Scene, TechniqueStats, session_bytes,
};
use voxlight_protocol::{ErrorCode, ServerMessage};
use voxlight_volumes::Volume;

/// GPU time one session gets before the next session's turn.
pub const TIME_SLICE: Duration = Duration::from_millis(30);

/// The longest one submission of a technique should take (`Renderer::set_part_time`).
const PART_TIME: Duration = Duration::from_millis(40);

/// Commands queued to the render thread before senders wait.
const COMMAND_QUEUE: usize = 256;

/// A session edited this recently counts as interactive and is served first.
pub const INTERACTIVE_WINDOW: Duration = Duration::from_secs(1);

/// While interactive sessions exist, every this-many-th slice goes to the others.
const BACKGROUND_TURN: u64 = 4;

pub type SessionId = u64;

/// How sessions behave while edits stream in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interaction {
    /// Off: every edit goes to the technique at once and no preview is rendered.
    pub enabled: bool,
    /// Preview frame time the resolution divisor is chosen for.
    pub frame_target: Duration,
    /// Input counts as stopped after this long without an edit.
    pub rest_after: Duration,
}

impl Interaction {
    /// Every edit straight to the technique, no previews.
    pub const OFF: Self = Self {
        enabled: false,
        frame_target: Duration::ZERO,
        rest_after: Duration::ZERO,
    };
}

impl Default for Interaction {
    fn default() -> Self {
        Self {
            enabled: true,
            frame_target: Duration::from_millis(60),
            rest_after: Duration::from_millis(250),
        }
    }
}

/// The resolution divisor for the next preview after one at `current` took `took`: the finest
/// of `voxlight_engine::preview::DIVISORS` whose predicted time (cost ∝ pixels) fits `target`;
/// a finer one than now only with 30% to spare, so the scale does not flicker.
pub fn next_divisor(current: u32, took: Duration, target: Duration) -> u32 {
    use voxlight_engine::preview::DIVISORS;
    let at_full = took.as_secs_f64() * f64::from(current * current);
    let target = target.as_secs_f64();
    DIVISORS
        .iter()
        .copied()
        .find(|&d| {
            let predicted = at_full / f64::from(d * d);
            let headroom = if d < current { 0.7 } else { 1.0 };
            predicted <= target * headroom
        })
        .unwrap_or(DIVISORS[DIVISORS.len() - 1])
}

/// A frame as rendered, before encoding.
#[derive(Debug)]
pub struct RenderedFrame {
    /// The session's frame counter (FrameMeta.seq): the same for every viewer.
    pub frame_number: u64,
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

/// Messages for every viewer of a session (edits, viewer lists, render errors).
pub type SessionEvents = broadcast::Sender<Arc<ServerMessage>>;

pub enum Command {
    Open {
        id: SessionId,
        volume: Arc<Volume>,
        technique: String,
        scene: Scene,
        version: u64,
        frames: FrameSlot,
        events: SessionEvents,
        /// The session's viewer count: with none it gets no GPU time (but keeps its state).
        viewers: Arc<AtomicUsize>,
        reply: oneshot::Sender<Result<(), EngineError>>,
    },
    /// Look again at which sessions want GPU time (a viewer came back).
    Wake,
    Edit {
        id: SessionId,
        scene: Scene,
        change: Change,
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
        EngineError::MemoryBudget { .. } => ErrorCode::GpuMemory,
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
    events: SessionEvents,
    frame_number: u64,
    viewers: Arc<AtomicUsize>,
    last_edit: Instant,
    /// No frame shows the latest edit yet: the next slice renders one iteration and sends it
    /// at once, so input-to-frame latency is one iteration, not one slice.
    fresh_edit: bool,
    /// A frame of the current state is still owed to viewers.
    dirty: bool,
    failed: bool,
    /// The technique has not stepped since its last edits (its first step is one iteration).
    technique_fresh: bool,
    /// Resolution divisor of the next preview.
    divisor: u32,
    /// Divisor of the last frame sent when it was a preview.
    shown_preview: Option<u32>,
}

impl Session {
    /// GPU bytes of this session's buffers (at least the per-pixel estimate).
    fn bytes(&self) -> u64 {
        let estimate = session_bytes(self.scene.viewport.width, self.scene.viewport.height);
        self.renderer.stats().memory_bytes.max(estimate)
    }

    fn owes_frame(&self) -> bool {
        self.dirty && !self.failed && self.viewers.load(Ordering::Relaxed) > 0
    }

    /// Edits arrived within `rest_after`: the technique waits, the preview shows them.
    fn moving(&self, interaction: &Interaction, now: Instant) -> bool {
        interaction.enabled && now.duration_since(self.last_edit) < interaction.rest_after
    }

    fn wants_gpu(&self, interaction: &Interaction, now: Instant) -> bool {
        self.owes_frame() && (self.fresh_edit || !self.moving(interaction, now))
    }

    /// When a session that waits for input to rest will want GPU time.
    fn wakes_at(&self, interaction: &Interaction, now: Instant) -> Option<Instant> {
        (self.owes_frame() && !self.fresh_edit && self.moving(interaction, now))
            .then(|| self.last_edit + interaction.rest_after)
    }

    fn report(&self, error: &EngineError) {
        let _ = self.events.send(Arc::new(ServerMessage::Error {
            code: error_code(error),
            message: error.to_string(),
        }));
    }
}

/// Starts the render thread. It stops when every `RenderHandle` is dropped.
/// `memory_budget`: GPU bytes all sessions and volumes together may use.
pub fn spawn(
    engine: Arc<Engine>,
    metrics: Arc<crate::metrics::Metrics>,
    memory_budget: u64,
    interaction: Interaction,
) -> std::io::Result<(RenderHandle, std::thread::JoinHandle<()>)> {
    let (commands, receiver) = mpsc::channel(COMMAND_QUEUE);
    let thread = std::thread::Builder::new()
        .name("voxlight-render".into())
        .spawn(move || {
            RenderThread::new(engine, metrics, memory_budget, interaction).run(receiver)
        })?;
    Ok((RenderHandle { commands }, thread))
}

struct RenderThread {
    engine: Arc<Engine>,
    metrics: Arc<crate::metrics::Metrics>,
    sessions: HashMap<SessionId, Session>,
    volumes: HashMap<String, Weak<GpuVolume>>,
    memory_budget: u64,
    interaction: Interaction,
    /// Round-robin position.
    last_served: SessionId,
    /// Slices served, for the background turn.
    turn: u64,
}

impl RenderThread {
    fn new(
        engine: Arc<Engine>,
        metrics: Arc<crate::metrics::Metrics>,
        memory_budget: u64,
        interaction: Interaction,
    ) -> Self {
        Self {
            engine,
            metrics,
            sessions: HashMap::new(),
            volumes: HashMap::new(),
            memory_budget,
            interaction,
            last_served: 0,
            turn: 0,
        }
    }

    /// GPU bytes in use: every session's buffers plus each live volume once.
    fn memory_in_use(&self) -> u64 {
        let sessions: u64 = self.sessions.values().map(Session::bytes).sum();
        let volumes: u64 = self
            .volumes
            .values()
            .filter_map(Weak::upgrade)
            .map(|v| v.bytes)
            .sum();
        sessions + volumes
    }

    /// Refuses a session state that would take the total over the budget. `replacing`: the
    /// session whose current buffers the new ones replace; `volume`: a volume to upload.
    fn check_memory(
        &self,
        replacing: Option<SessionId>,
        scene: &Scene,
        volume: Option<&Volume>,
    ) -> Result<(), EngineError> {
        let upload = volume
            .filter(|v| {
                self.volumes
                    .get(&v.name)
                    .is_none_or(|w| w.strong_count() == 0)
            })
            .map_or(0, |v| GpuVolume::bytes_needed(&self.engine.gpu, v.dims));
        let needed = session_bytes(scene.viewport.width, scene.viewport.height) + upload;
        self.check_fits(replacing, needed)
    }

    /// After creating a renderer: its actual buffers (techniques beyond the per-pixel estimate,
    /// e.g. photon maps or shadow maps) must fit too.
    fn check_actual(
        &self,
        replacing: Option<SessionId>,
        renderer: &Renderer,
    ) -> Result<(), EngineError> {
        self.check_fits(replacing, renderer.stats().memory_bytes)
    }

    fn check_fits(&self, replacing: Option<SessionId>, needed: u64) -> Result<(), EngineError> {
        let freed = replacing
            .and_then(|id| self.sessions.get(&id))
            .map_or(0, Session::bytes);
        let in_use = self.memory_in_use() - freed;
        if in_use + needed > self.memory_budget {
            return Err(EngineError::MemoryBudget {
                needed,
                in_use,
                budget: self.memory_budget,
            });
        }
        Ok(())
    }

    fn publish_memory(&self) {
        self.metrics
            .gpu_memory_bytes
            .store(self.memory_in_use(), Ordering::Relaxed);
    }

    fn run(mut self, mut receiver: mpsc::Receiver<Command>) {
        tracing::info!("render thread started");
        let mut deferred = VecDeque::new();
        loop {
            // Commands a preview looked at while it rendered come first, in order.
            while let Some(command) = deferred.pop_front() {
                if matches!(command, Command::Stop) {
                    tracing::info!("render thread stopped");
                    return;
                }
                self.handle(command);
            }
            let now = Instant::now();
            let busy = self
                .sessions
                .values()
                .any(|s| s.wants_gpu(&self.interaction, now));
            let wake = self
                .sessions
                .values()
                .filter_map(|s| s.wakes_at(&self.interaction, now))
                .min();
            if !busy {
                let command = match wake {
                    None => receiver.blocking_recv(),
                    Some(deadline) => match wait_until(&mut receiver, deadline) {
                        Waited::Command(command) => Some(*command),
                        Waited::Deadline => continue,
                        Waited::Disconnected => None,
                    },
                };
                match command {
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
                self.serve(id, &mut receiver, &mut deferred);
            }
        }
        tracing::info!("render thread stopped");
    }

    /// The next session to serve: round-robin over the interactive sessions that owe a
    /// frame, with every `BACKGROUND_TURN`-th slice round-robin over all of them.
    fn next_session(&mut self) -> Option<SessionId> {
        let now = Instant::now();
        let mut waiting: Vec<(SessionId, bool)> = self
            .sessions
            .iter()
            .filter(|(_, s)| s.wants_gpu(&self.interaction, now))
            .map(|(id, s)| (*id, now.duration_since(s.last_edit) < INTERACTIVE_WINDOW))
            .collect();
        waiting.sort_unstable();
        self.turn += 1;
        choose_session(&mut waiting, self.last_served, self.turn)
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
                viewers,
                reply,
            } => {
                let result = self
                    .check_memory(None, &scene, Some(&volume))
                    .and_then(|()| self.gpu_volume(&volume))
                    .and_then(|gpu_volume| {
                        self.engine.create_renderer(&technique, gpu_volume, &scene)
                    })
                    .map(with_part_time)
                    .and_then(|renderer| self.check_actual(None, &renderer).map(|()| renderer));
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
                                frame_number: 0,
                                viewers,
                                last_edit: Instant::now(),
                                fresh_edit: true,
                                dirty: true,
                                failed: false,
                                technique_fresh: true,
                                // The first preview at the coarsest divisor: its time predicts
                                // the finer ones (next_divisor refines), where one at full
                                // resolution would hold the first edit for the slowest preview
                                // (3.3 s at 512² on lavapipe).
                                divisor: voxlight_engine::preview::DIVISORS
                                    [voxlight_engine::preview::DIVISORS.len() - 1],
                                shown_preview: None,
                            },
                        );
                        self.publish_memory();
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
                change,
                version,
            } => {
                if change == Change::Viewport
                    && let Err(e) = self.check_memory(Some(id), &scene, None)
                {
                    if let Some(session) = self.sessions.get(&id) {
                        session.report(&e);
                    }
                    return;
                }
                let Some(session) = self.sessions.get_mut(&id) else {
                    return;
                };
                session.scene = scene;
                session.version = version;
                session.dirty = true;
                session.last_edit = Instant::now();
                session.fresh_edit = true;
                session.technique_fresh = true;
                let interactive = self.interaction.enabled;
                let applied = if interactive {
                    session
                        .renderer
                        .defer(&self.engine, &session.scene, &change)
                } else {
                    session
                        .renderer
                        .apply(&self.engine, &session.scene, &change)
                };
                session.failed = applied.is_err();
                if let Err(e) = applied {
                    session.report(&e);
                }
                self.publish_memory();
            }
            Command::Wake => {}
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
                let gpu_volume = self
                    .check_memory(Some(id), &scene, volume.as_deref())
                    .and_then(|()| match volume {
                        Some(volume) => self.gpu_volume(&volume),
                        None => Ok(current),
                    });
                let result = gpu_volume
                    .and_then(|v| self.engine.create_renderer(&technique, v, &scene))
                    .map(with_part_time)
                    .and_then(|renderer| self.check_actual(Some(id), &renderer).map(|()| renderer));
                match (result, self.sessions.get_mut(&id)) {
                    (Ok(renderer), Some(session)) => {
                        session.renderer = renderer;
                        session.scene = scene;
                        session.version = version;
                        session.last_edit = Instant::now();
                        session.fresh_edit = true;
                        session.technique_fresh = true;
                        session.shown_preview = None;
                        session.dirty = true;
                        session.failed = false;
                        self.volumes.retain(|_, weak| weak.strong_count() > 0);
                        self.publish_memory();
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
                self.publish_memory();
            }
            Command::Stop => {}
        }
    }

    /// One time slice for a session: a preview of its newest edit while input streams in (and
    /// once at full resolution when it rests), else progressive work; then a frame for its
    /// viewers.
    /// `receiver` and `deferred`: commands a long preview looks at between its parts
    /// (`interrupted`); they are handled after the slice.
    fn serve(
        &mut self,
        id: SessionId,
        receiver: &mut mpsc::Receiver<Command>,
        deferred: &mut VecDeque<Command>,
    ) {
        self.last_served = id;
        let engine = self.engine.clone();
        let interaction = self.interaction;
        let Some(session) = self.sessions.get_mut(&id) else {
            return;
        };
        let started = Instant::now();
        let preview_divisor = if !interaction.enabled {
            None
        } else if session.fresh_edit && session.moving(&interaction, started) {
            Some(session.divisor)
        } else {
            // At rest: a reduced preview is replaced by a full-resolution one first.
            session.shown_preview.filter(|&d| d > 1).map(|_| 1)
        };
        session.fresh_edit = false;
        // While edits stream in, a stale light volume is rebuilt coarse (a TF drag rebuilds it
        // every edit); the preview at rest rebuilds it in full.
        let light_detail = if session.moving(&interaction, started) {
            LightDetail::Interactive
        } else {
            LightDetail::Full
        };
        let result = match preview_divisor {
            Some(divisor) => {
                // The preview at rest (full resolution: seconds on a software adapter) runs in
                // parts and gives way to an edit of this session; one while moving is sized to
                // the frame target and runs whole (parts cost throughput).
                let mut stop = || interrupted(id, receiver, deferred);
                let stop: Option<&mut dyn FnMut() -> bool> =
                    (!session.moving(&interaction, started)).then_some(&mut stop);
                session
                    .renderer
                    .preview_frame_until(&engine, &session.scene, divisor, light_detail, stop)
                    .map(|rendered| {
                        rendered.map(|(frame, report)| {
                            if session.moving(&interaction, started) {
                                session.divisor = next_divisor(
                                    divisor,
                                    report.view_time,
                                    interaction.frame_target,
                                );
                            }
                            session.shown_preview = Some(divisor);
                            (report.view_time + report.light_time, frame)
                        })
                    })
                    .map(|rendered| match rendered {
                        Some((time, frame)) => (time, Some(frame)),
                        None => (started.elapsed(), None),
                    })
            }
            None => {
                let budget = if session.technique_fresh {
                    Duration::ZERO
                } else {
                    TIME_SLICE
                };
                session.technique_fresh = false;
                session.shown_preview = None;
                session
                    .renderer
                    .step(&engine, &session.scene, budget)
                    .and_then(|report| {
                        self.metrics
                            .gpu_time(session.renderer.technique_name(), report.gpu_time);
                        // A long iteration runs in bands: until one completes there is nothing
                        // new to show (and the first iteration's rows are not all written).
                        if report.iterations_done == 0 && !report.converged {
                            return Ok((report.gpu_time, None));
                        }
                        Ok((
                            report.gpu_time,
                            Some(session.renderer.frame(&engine, &session.scene)?),
                        ))
                    })
            }
        };
        tracing::trace!(
            session = id,
            preview = ?preview_divisor,
            ms = started.elapsed().as_secs_f64() * 1e3,
            "slice"
        );
        match result {
            // Part of a banded iteration, or a preview that gave way to an edit: the session
            // still owes its frame.
            Ok((_, None)) => {}
            Ok((gpu_time, Some(frame))) => {
                // A preview still owes the technique's picture.
                session.dirty = frame.preview || !frame.converged;
                session.frame_number += 1;
                self.metrics.frames_rendered.fetch_add(1, Ordering::Relaxed);
                let rendered = RenderedFrame {
                    frame_number: session.frame_number,
                    technique: session.renderer.technique_name(),
                    scene_version: session.version,
                    render_ms: started.elapsed().as_secs_f32() * 1000.0,
                    gpu_ms: gpu_time.as_secs_f32() * 1000.0,
                    stats: session.renderer.stats(),
                    frame,
                };
                session.frames.send_replace(Some(Arc::new(rendered)));
            }
            Err(e) => {
                tracing::error!(session = id, error = %e, "rendering failed");
                session.failed = true;
                session.report(&e);
            }
        }
    }
}

/// A renderer whose technique keeps each submission to about `PART_TIME`, so that an edit
/// waits for a part of the technique's work, not for an iteration of it.
fn with_part_time(mut renderer: Renderer) -> Renderer {
    renderer.set_part_time(Some(PART_TIME));
    renderer
}

/// Whether a long preview of session `id` should give way: takes the queued commands into
/// `deferred` (handled after the slice, in order) until one edits, rebuilds or closes that
/// session, or stops the thread. At most `COMMAND_QUEUE` are held, the rest stay queued.
fn interrupted(
    id: SessionId,
    receiver: &mut mpsc::Receiver<Command>,
    deferred: &mut VecDeque<Command>,
) -> bool {
    while deferred.len() < COMMAND_QUEUE {
        let command = match receiver.try_recv() {
            Ok(command) => command,
            Err(mpsc::error::TryRecvError::Empty) => return false,
            Err(mpsc::error::TryRecvError::Disconnected) => return true,
        };
        let stops = match &command {
            Command::Edit { id: of, .. }
            | Command::Rebuild { id: of, .. }
            | Command::Close { id: of } => *of == id,
            Command::Stop => true,
            Command::Open { .. } | Command::Wake => false,
        };
        deferred.push_back(command);
        if stops {
            return true;
        }
    }
    false
}

enum Waited {
    Command(Box<Command>),
    Deadline,
    Disconnected,
}

/// Waits for a command until `deadline` (the render thread has no async runtime: it polls in
/// short sleeps, only while a session waits for its input to rest).
fn wait_until(receiver: &mut mpsc::Receiver<Command>, deadline: Instant) -> Waited {
    const POLL: Duration = Duration::from_millis(2);
    loop {
        match receiver.try_recv() {
            Ok(command) => return Waited::Command(Box::new(command)),
            Err(mpsc::error::TryRecvError::Disconnected) => return Waited::Disconnected,
            Err(mpsc::error::TryRecvError::Empty) => {}
        }
        let now = Instant::now();
        if now >= deadline {
            return Waited::Deadline;
        }
        std::thread::sleep(POLL.min(deadline - now));
    }
}

/// Picks from `waiting` (sorted (id, interactive) pairs): interactive sessions only, except
/// on every `BACKGROUND_TURN`-th turn; round-robin after `last`.
fn choose_session(
    waiting: &mut Vec<(SessionId, bool)>,
    last: SessionId,
    turn: u64,
) -> Option<SessionId> {
    let any_interactive = waiting.iter().any(|&(_, interactive)| interactive);
    if any_interactive && !turn.is_multiple_of(BACKGROUND_TURN) {
        waiting.retain(|&(_, interactive)| interactive);
    }
    pick_round_robin(waiting, last)
}

/// The first id after `last` in the sorted `waiting` list, wrapping around.
fn pick_round_robin(waiting: &[(SessionId, bool)], last: SessionId) -> Option<SessionId> {
    waiting
        .iter()
        .map(|&(id, _)| id)
        .find(|&id| id > last)
        .or(waiting.first().map(|&(id, _)| id))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn divisor_coarsens_when_slow_and_refines_with_headroom() {
        let target = Duration::from_millis(60);
        let ms = Duration::from_millis;
        // Fast enough at full resolution: stay there.
        assert_eq!(next_divisor(1, ms(30), target), 1);
        // 200 ms at full resolution: a quarter of the pixels takes ~50 ms.
        assert_eq!(next_divisor(1, ms(200), target), 2);
        // 40 ms at divisor 2 predicts 160 ms at 1: stay at 2.
        assert_eq!(next_divisor(2, ms(40), target), 2);
        // 10 ms at divisor 2 predicts 40 ms at 1, within 70% of the target: refine.
        assert_eq!(next_divisor(2, ms(10), target), 1);
        // 13 ms at 2 predicts 52 ms at 1: fits the target but not the headroom.
        assert_eq!(next_divisor(2, ms(13), target), 2);
        // Hopelessly slow: the coarsest.
        assert_eq!(next_divisor(1, Duration::from_secs(30), target), 8);
    }

    #[test]
    fn a_long_preview_gives_way_only_to_its_own_session() {
        let edit = |id| Command::Edit {
            id,
            scene: Scene::default(),
            change: Change::Camera,
            version: 1,
        };
        let (sender, mut receiver) = mpsc::channel(COMMAND_QUEUE);
        let mut deferred = VecDeque::new();
        assert!(
            !interrupted(7, &mut receiver, &mut deferred),
            "nothing queued"
        );
        for command in [
            Command::Wake,
            edit(3),
            Command::Close { id: 4 },
            edit(7),
            edit(3),
        ] {
            sender.try_send(command).expect("room in the queue");
        }
        // Another session's edit or close does not stop it; its own edit does, and what was
        // taken before it waits in order; the rest stays queued.
        assert!(interrupted(7, &mut receiver, &mut deferred));
        let taken: Vec<_> = deferred
            .iter()
            .map(|c| match c {
                Command::Wake => "wake".to_owned(),
                Command::Edit { id, .. } => format!("edit {id}"),
                Command::Close { id } => format!("close {id}"),
                _ => "other".to_owned(),
            })
            .collect();
        assert_eq!(taken, ["wake", "edit 3", "close 4", "edit 7"]);
        assert!(matches!(
            receiver.try_recv(),
            Ok(Command::Edit { id: 3, .. })
        ));
        // A stopped thread stops it; so does a closed channel.
        sender.try_send(Command::Stop).expect("room in the queue");
        assert!(interrupted(7, &mut receiver, &mut deferred));
        drop(sender);
        assert!(interrupted(7, &mut receiver, &mut deferred));
    }

    #[test]
    fn round_robin_wraps_and_skips_nothing() {
        let waiting = [(2, true), (5, false), (9, true)];
        assert_eq!(pick_round_robin(&waiting, 0), Some(2));
        assert_eq!(pick_round_robin(&waiting, 2), Some(5));
        assert_eq!(pick_round_robin(&waiting, 5), Some(9));
        assert_eq!(pick_round_robin(&waiting, 9), Some(2));
        assert_eq!(pick_round_robin(&[], 3), None);
    }

    #[test]
    fn interactive_sessions_come_first_and_others_never_starve() {
        let all = vec![(1, false), (2, true), (3, false), (4, true)];
        let mut served = Vec::new();
        let mut last = 0;
        for turn in 1..=16 {
            let id = choose_session(&mut all.clone(), last, turn).unwrap();
            served.push(id);
            last = id;
        }
        let count = |id| served.iter().filter(|&&s| s == id).count();
        assert!(count(2) + count(4) >= 12, "{served:?}");
        assert!(
            count(1) >= 1 && count(3) >= 1,
            "background starved: {served:?}"
        );
        // With no interactive session, plain round-robin.
        let idle = vec![(1, false), (3, false)];
        assert_eq!(choose_session(&mut idle.clone(), 1, 1), Some(3));
        assert_eq!(choose_session(&mut idle.clone(), 3, 2), Some(1));
    }
}
