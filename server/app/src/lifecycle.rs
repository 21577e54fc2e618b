//! Capacity and drain: what lets a router spread sessions over several processes.
//!
//! - A process holds at most `max_sessions` sessions (those in their reconnect grace period
//!   included: they keep their GPU state). The next new session gets `at_capacity`; joining an
//!   existing session is still allowed, it adds no GPU state.
//! - `/readyz` is true while the process takes new sessions (not full, not draining), so a
//!   Kubernetes Service sends new sessions only where they fit.
//! - `drain` (on SIGTERM): readiness false, new sessions refused with `draining`, every viewer
//!   told how long it has; the sessions are served until their viewers leave or the deadline
//!   passes; then the caller cancels the server (`bye` to whoever is left).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio::time::Instant;
use voxlight_protocol::{ErrorCode, ServerMessage};

use crate::AppState;
use crate::reply::Reply;

/// Default time a draining process keeps serving its sessions.
pub const DEFAULT_DRAIN_TIMEOUT: Duration = Duration::from_secs(300);

/// How often `drain` looks whether every viewer has left.
const DRAIN_POLL: Duration = Duration::from_millis(100);

/// Why the process takes no new session now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotReady {
    Full,
    Draining,
}

impl NotReady {
    pub fn as_str(self) -> &'static str {
        match self {
            NotReady::Full => "at_capacity",
            NotReady::Draining => "draining",
        }
    }
}

/// Whether a new session would be admitted now.
pub fn readiness(state: &AppState) -> Result<(), NotReady> {
    if state.draining.is_cancelled() {
        return Err(NotReady::Draining);
    }
    let active = state.metrics.sessions_active.load(Ordering::Relaxed);
    match state.max_sessions {
        Some(max) if active >= max as i64 => Err(NotReady::Full),
        _ => Ok(()),
    }
}

/// A reserved place for a session being opened; given back on drop unless kept (the session
/// then gives it back when it closes).
pub struct SessionSlot {
    state: Arc<AppState>,
    kept: bool,
}

impl SessionSlot {
    pub fn keep(mut self) {
        self.kept = true;
    }
}

impl Drop for SessionSlot {
    fn drop(&mut self) {
        if !self.kept {
            self.state
                .metrics
                .sessions_active
                .fetch_sub(1, Ordering::Relaxed);
        }
    }
}

/// Reserves a place for a new session, or says why there is none. The count is
/// `voxlight_sessions_active`, so two hellos racing for the last place cannot both get it.
pub fn admit(state: &Arc<AppState>) -> Result<SessionSlot, Reply> {
    if state.draining.is_cancelled() {
        return Err(draining_reply());
    }
    let max = state.max_sessions.map_or(i64::MAX, |m| m as i64);
    state
        .metrics
        .sessions_active
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (n < max).then_some(n + 1)
        })
        .map_err(|n| {
            Reply::new(
                ErrorCode::AtCapacity,
                format!(
                    "this server holds {n} sessions, its capacity; try again later or on another \
                     server (joining a shared session still works)"
                ),
            )
        })?;
    Ok(SessionSlot {
        state: state.clone(),
        kept: false,
    })
}

fn draining_reply() -> Reply {
    Reply::new(
        ErrorCode::Draining,
        "this server is draining for a restart and opens no new sessions; open the viewer at \
         the deployment's root to get another server",
    )
}

/// Seconds until the drain deadline (0 when not draining or past it).
pub fn seconds_left(state: &AppState) -> u64 {
    let deadline = state.drain_deadline.lock().ok().and_then(|d| *d);
    deadline.map_or(0, |d| {
        d.saturating_duration_since(Instant::now())
            .as_secs_f64()
            .ceil() as u64
    })
}

/// The message a viewer gets while the server drains.
pub fn draining_message(state: &AppState) -> ServerMessage {
    let seconds_left = seconds_left(state);
    ServerMessage::Draining {
        seconds_left,
        message: format!(
            "this server is shutting down for a restart or scale-down; the session ends in at \
             most {seconds_left} s, then the viewer reopens it on another server"
        ),
    }
}

/// Drains the process: no new sessions, viewers told, sessions served until every viewer
/// has left or `timeout` has passed. Does not stop the server; cancel `state.shutdown` after.
pub async fn drain(state: &Arc<AppState>, timeout: Duration) {
    let deadline = Instant::now() + timeout;
    if let Ok(mut d) = state.drain_deadline.lock() {
        *d = Some(deadline);
    }
    state.draining.cancel();
    state.metrics.draining.store(1, Ordering::Relaxed);
    let message = draining_message(state);
    let sessions = state.hub.sessions();
    tracing::info!(
        sessions = sessions.len(),
        viewers = state.metrics.viewers_active.load(Ordering::Relaxed),
        timeout_s = timeout.as_secs(),
        "draining: no new sessions; serving the open ones until their viewers leave"
    );
    for session in &sessions {
        session.publish(message.clone());
    }
    loop {
        let viewers = state.metrics.viewers_active.load(Ordering::Relaxed);
        if viewers <= 0 {
            tracing::info!("drained: no viewer left");
            return;
        }
        if Instant::now() >= deadline {
            tracing::info!(
                viewers,
                "drain deadline passed; closing the remaining sessions"
            );
            return;
        }
        tokio::select! {
            _ = tokio::time::sleep(DRAIN_POLL) => {}
            _ = state.shutdown.cancelled() => return,
        }
    }
}
