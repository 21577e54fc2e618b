//! The writer task of one connection: the newest frame when the viewer is ready for one, the
//! session's broadcasts, this viewer's replies, pings, and the close.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::extract::ws::Message;
use futures_util::SinkExt;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, mpsc};
use voxlight_protocol::{ServerMessage, Stats};

use crate::AppState;
use crate::adapt::QualityController;
use crate::hub::{Encoding, SharedSession};
use crate::metrics::Metrics;

use super::{CLOSE_LINGER, SEND_TIMEOUT, STATS_INTERVAL, Sink, ViewerLink, text};

/// Sends with a deadline, so a viewer that stopped reading cannot hold its task forever.
pub(super) async fn send(sink: &mut Sink, message: Message) -> bool {
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

pub(super) async fn write_loop(
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
