//! Shared sessions. A session has a public id, one render-thread session (one picture, rendered
//! once) and any number of viewers. Its editable state lives here, behind an async lock that
//! every viewer's edits go through (last writer wins); frames are encoded once per quality and
//! the bytes shared by every viewer that wants that quality. A session outlives its last
//! viewer for the hub's grace period, so a reconnecting client finds its converged picture.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use tokio::sync::{broadcast, watch};
use voxlight_engine::Scene;
use voxlight_protocol::{
    ErrorCode, FrameFormat, FrameMeta, MAX_NAME_CHARS, MAX_VIEWERS_PER_SESSION, ServerMessage,
    SessionState, Stats, ViewerInfo, join_frame,
};

use crate::metrics::Metrics;
use crate::render_service::{RenderedFrame, SessionEvents, SessionId};
use crate::reply::Reply;

/// Default time a session waits for a viewer to come back.
pub const DEFAULT_GRACE_PERIOD: Duration = Duration::from_secs(120);

/// `edited`/`viewers`/error messages buffered per viewer; a viewer further behind gets one
/// `state` message instead.
pub const EVENT_BUFFER: usize = 64;

/// Everything viewers edit, and the scene the engine renders from it.
pub struct SessionCore {
    pub dataset: String,
    pub technique: String,
    pub scene: Scene,
    /// Counts edits; frames carry the version they show.
    pub version: u64,
}

impl SessionCore {
    pub fn state(&self, jpeg_quality: u8) -> SessionState {
        SessionState {
            dataset: self.dataset.clone(),
            technique: self.technique.clone(),
            technique_options: self.scene.technique_options,
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

/// The oldest edit no frame has shown yet (scene version, arrival), for the input-to-frame
/// latency metric.
pub type EditClock = std::sync::Mutex<Option<(u64, Instant)>>;

/// How a frame is encoded for a viewer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Png,
    Jpeg(u8),
}

/// A frame message ready to send: header and image, shared by the viewers that want it.
#[derive(Debug)]
pub struct EncodedFrame {
    pub bytes: Bytes,
    pub meta: FrameMeta,
    pub stats: Stats,
}

#[derive(Default)]
struct EncodeCache {
    frame_number: u64,
    entries: Vec<(Encoding, Arc<EncodedFrame>)>,
}

#[derive(Default)]
struct Viewers {
    list: Vec<ViewerInfo>,
    /// Bumped on every join and leave, so a grace timer knows whether it is stale.
    generation: u64,
}

pub struct SharedSession {
    /// Public id: 128 random bits in hex. Knowing it (plus a token, when the server wants
    /// one) is what lets someone join.
    pub id: String,
    pub render_id: SessionId,
    pub core: tokio::sync::Mutex<SessionCore>,
    frames: watch::Receiver<Option<Arc<RenderedFrame>>>,
    pub events: SessionEvents,
    viewers: std::sync::Mutex<Viewers>,
    /// The viewer count, read by the render thread (no viewers: no GPU time).
    viewer_count: Arc<AtomicUsize>,
    next_viewer: AtomicU32,
    encoded: tokio::sync::Mutex<EncodeCache>,
    pub edit_clock: EditClock,
    /// Frames sent to all viewers (for tests and stats).
    pub frames_sent: AtomicU64,
}

impl SharedSession {
    pub fn new(
        render_id: SessionId,
        core: SessionCore,
        frames: watch::Receiver<Option<Arc<RenderedFrame>>>,
        events: SessionEvents,
    ) -> Self {
        Self {
            id: new_session_id(),
            render_id,
            core: tokio::sync::Mutex::new(core),
            frames,
            events,
            viewers: Default::default(),
            viewer_count: Default::default(),
            next_viewer: AtomicU32::new(1),
            encoded: Default::default(),
            edit_clock: Default::default(),
            frames_sent: AtomicU64::new(0),
        }
    }

    /// A frame receiver that yields the current picture at once (a joiner sees the converged
    /// image without waiting for a new one).
    pub fn frames(&self) -> watch::Receiver<Option<Arc<RenderedFrame>>> {
        let mut frames = self.frames.clone();
        frames.mark_changed();
        frames
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<ServerMessage>> {
        self.events.subscribe()
    }

    /// Sends a message to every viewer (none listening is fine).
    pub fn publish(&self, message: ServerMessage) {
        let _ = self.events.send(Arc::new(message));
    }

    pub fn viewer_count(&self) -> Arc<AtomicUsize> {
        self.viewer_count.clone()
    }

    pub fn viewers(&self) -> Vec<ViewerInfo> {
        self.viewers
            .lock()
            .map(|v| v.list.clone())
            .unwrap_or_default()
    }

    /// Adds a viewer; refused when the session is full.
    fn add_viewer(&self, name: Option<&str>) -> Result<(ViewerInfo, usize), Reply> {
        let mut viewers = self
            .viewers
            .lock()
            .map_err(|_| Reply::new(ErrorCode::Internal, "viewer list poisoned"))?;
        if viewers.list.len() >= MAX_VIEWERS_PER_SESSION {
            return Err(Reply::new(
                ErrorCode::SessionFull,
                format!("the session already has {MAX_VIEWERS_PER_SESSION} viewers"),
            ));
        }
        let id = self.next_viewer.fetch_add(1, Ordering::Relaxed);
        let viewer = ViewerInfo {
            id,
            name: display_name(name, id),
        };
        viewers.list.push(viewer.clone());
        viewers.generation += 1;
        self.viewer_count
            .store(viewers.list.len(), Ordering::Relaxed);
        Ok((viewer, viewers.list.len()))
    }

    /// Changes a viewer's display name; returns the viewer as now listed.
    pub fn rename_viewer(&self, id: u32, name: &str) -> Option<ViewerInfo> {
        let mut viewers = self.viewers.lock().ok()?;
        let viewer = viewers.list.iter_mut().find(|v| v.id == id)?;
        viewer.name = display_name(Some(name), id);
        Some(viewer.clone())
    }

    /// Removes a viewer; returns the viewers left and the list generation.
    pub fn remove_viewer(&self, id: u32) -> (usize, u64) {
        match self.viewers.lock() {
            Ok(mut viewers) => {
                viewers.list.retain(|v| v.id != id);
                viewers.generation += 1;
                self.viewer_count
                    .store(viewers.list.len(), Ordering::Relaxed);
                (viewers.list.len(), viewers.generation)
            }
            Err(_) => (0, 0),
        }
    }

    /// The frame as `encoding`, encoded once per frame and encoding however many viewers ask.
    pub async fn encoded(
        &self,
        rendered: &Arc<RenderedFrame>,
        encoding: Encoding,
        metrics: &Metrics,
    ) -> Result<Arc<EncodedFrame>, String> {
        let mut cache = self.encoded.lock().await;
        if cache.frame_number == rendered.frame_number
            && let Some((_, hit)) = cache.entries.iter().find(|(e, _)| *e == encoding)
        {
            return Ok(hit.clone());
        }
        let frame = rendered.clone();
        let started = Instant::now();
        let encoded = tokio::task::spawn_blocking(move || encode_frame(&frame, encoding))
            .await
            .map_err(|e| format!("encoder task failed: {e}"))?
            .map_err(|e| e.to_string())?;
        metrics.frame_encoded(started.elapsed());
        let encoded = Arc::new(encoded);
        if rendered.frame_number > cache.frame_number {
            cache.frame_number = rendered.frame_number;
            cache.entries.clear();
        }
        if rendered.frame_number == cache.frame_number {
            cache.entries.push((encoding, encoded.clone()));
        }
        Ok(encoded)
    }
}

/// Trims, drops control characters and caps the length; empty names become `viewer N`.
fn display_name(name: Option<&str>, id: u32) -> String {
    let cleaned: String = name
        .unwrap_or_default()
        .chars()
        .filter(|c| !c.is_control())
        .take(MAX_NAME_CHARS)
        .collect();
    let cleaned = cleaned.trim();
    if cleaned.is_empty() {
        format!("viewer {id}")
    } else {
        cleaned.to_owned()
    }
}

fn new_session_id() -> String {
    let mut bytes = [0u8; 16];
    if getrandom::fill(&mut bytes).is_err() {
        // No OS randomness: fall back to std's randomly keyed hasher (still unpredictable
        // across processes).
        use std::hash::{BuildHasher, RandomState};
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let a = RandomState::new().hash_one(nanos);
        let b = RandomState::new().hash_one(a);
        bytes[..8].copy_from_slice(&a.to_le_bytes());
        bytes[8..].copy_from_slice(&b.to_le_bytes());
    }
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Every live session by public id.
pub struct Hub {
    sessions: std::sync::Mutex<HashMap<String, Arc<SharedSession>>>,
    /// How long a session without viewers is kept.
    pub grace: Duration,
}

impl Hub {
    pub fn new(grace: Duration) -> Self {
        Self {
            sessions: Default::default(),
            grace,
        }
    }

    pub fn len(&self) -> usize {
        self.sessions.lock().map(|s| s.len()).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every live session (e.g. to tell all viewers the server drains).
    pub fn sessions(&self) -> Vec<Arc<SharedSession>> {
        self.sessions
            .lock()
            .map(|s| s.values().cloned().collect())
            .unwrap_or_default()
    }

    /// Registers a new session with its first viewer.
    pub fn insert(
        &self,
        session: Arc<SharedSession>,
        name: Option<&str>,
    ) -> Result<ViewerInfo, Reply> {
        let (viewer, _) = session.add_viewer(name)?;
        self.sessions
            .lock()
            .map_err(|_| Reply::new(ErrorCode::Internal, "session table poisoned"))?
            .insert(session.id.clone(), session);
        Ok(viewer)
    }

    /// Adds a viewer to an existing session. Returns the session, the viewer and the viewer
    /// count.
    pub fn join(
        &self,
        id: &str,
        name: Option<&str>,
    ) -> Result<(Arc<SharedSession>, ViewerInfo, usize), Reply> {
        // The table lock is held while adding, so an expiring session cannot slip away between
        // lookup and join.
        let sessions = self
            .sessions
            .lock()
            .map_err(|_| Reply::new(ErrorCode::Internal, "session table poisoned"))?;
        let session = sessions.get(id).cloned().ok_or_else(|| {
            Reply::new(
                ErrorCode::UnknownSession,
                "no such session: it ended, or its grace period after the last viewer expired",
            )
        })?;
        let (viewer, count) = session.add_viewer(name)?;
        Ok((session, viewer, count))
    }

    /// Removes the session if it still has no viewers and nobody joined or left since
    /// `generation`. Returns it when removed.
    pub fn expire(&self, id: &str, generation: u64) -> Option<Arc<SharedSession>> {
        let mut sessions = self.sessions.lock().ok()?;
        let session = sessions.get(id)?;
        let idle = session
            .viewers
            .lock()
            .is_ok_and(|v| v.list.is_empty() && v.generation == generation);
        if idle { sessions.remove(id) } else { None }
    }
}

/// Encodes a rendered frame as a binary frame message.
fn encode_frame(
    rendered: &RenderedFrame,
    encoding: Encoding,
) -> Result<EncodedFrame, crate::encode::EncodeError> {
    let started = Instant::now();
    let frame = &rendered.frame;
    let technique = &rendered.stats;
    let details = technique.details.clone();
    let (image, format, quality) = match encoding {
        Encoding::Png => (
            crate::encode::png(&frame.rgba, frame.width, frame.height)?,
            FrameFormat::Png,
            None,
        ),
        Encoding::Jpeg(quality) => (
            crate::encode::jpeg(&frame.rgba, frame.width, frame.height, quality)?,
            FrameFormat::Jpeg,
            Some(quality),
        ),
    };
    let meta = FrameMeta {
        seq: rendered.frame_number,
        format,
        width: frame.width,
        height: frame.height,
        technique: rendered.technique.to_owned(),
        iteration: frame.iteration,
        target_iterations: frame.target_iterations,
        converged: frame.converged,
        lossless: format == FrameFormat::Png,
        quality,
        scene_version: rendered.scene_version,
        preview: frame.preview,
        resolution_scale: 1.0 / frame.divisor.max(1) as f32,
        preview_match: frame
            .preview_match
            .map(|m| voxlight_protocol::PreviewMatch {
                gain: m.gain,
                multiple_weight: m.multiple_weight,
            }),
        render_ms: rendered.render_ms,
        encode_ms: started.elapsed().as_secs_f32() * 1000.0,
        details: details.clone(),
    };
    let stats = Stats {
        technique: rendered.technique.to_owned(),
        iteration: frame.iteration,
        target_iterations: frame.target_iterations,
        converged: frame.converged,
        gpu_ms: rendered.gpu_ms,
        memory_bytes: rendered.stats.memory_bytes,
        details,
        ..Stats::default()
    };
    Ok(EncodedFrame {
        bytes: Bytes::from(join_frame(&meta, &image)),
        meta,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_cleaned_and_capped() {
        assert_eq!(display_name(Some("  Dr. Ada \n"), 3), "Dr. Ada");
        assert_eq!(display_name(Some("\u{7}\t"), 4), "viewer 4");
        assert_eq!(display_name(None, 5), "viewer 5");
        let long = "x".repeat(500);
        assert_eq!(display_name(Some(&long), 1).chars().count(), MAX_NAME_CHARS);
    }

    #[test]
    fn session_ids_are_long_and_distinct() {
        let a = new_session_id();
        let b = new_session_id();
        assert_eq!(a.len(), 32);
        assert!(a.chars().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(a, b);
    }
}
