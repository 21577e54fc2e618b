//! The writer task of one connection: the newest frame when the viewer is ready for one, the
//! session's broadcasts, this viewer's replies, pings, and the close.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::extract::ws::Message;
use futures_util::{Sink, SinkExt};
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, mpsc};
use tokio_util::sync::CancellationToken;
use voxlight_protocol::{ServerMessage, Stats};

use crate::AppState;
use crate::adapt::QualityController;
use crate::datasets::Catalog;
use crate::hub::{Encoding, SharedSession};
use crate::metrics::Metrics;

use super::{CLOSE_LINGER, SEND_TIMEOUT, STATS_INTERVAL, ViewerLink, text};

/// Sends with a deadline, so a viewer that stopped reading cannot hold its task forever.
pub(super) async fn send<S: Sink<Message> + Unpin>(sink: &mut S, message: Message) -> bool {
    matches!(
        tokio::time::timeout(SEND_TIMEOUT, sink.send(message)).await,
        Ok(Ok(()))
    )
}

/// What the writer needs of the server: its shutdown and drain, metrics, the dataset catalog
/// (a viewer that fell behind gets the whole state) and the ping interval.
pub(super) struct WriterEnv {
    pub shutdown: CancellationToken,
    pub draining: CancellationToken,
    pub metrics: Arc<Metrics>,
    pub catalog: Arc<Catalog>,
    pub ping_interval: Duration,
}

impl WriterEnv {
    pub(super) fn of(state: &AppState) -> Self {
        Self {
            shutdown: state.shutdown.clone(),
            draining: state.draining.clone(),
            metrics: state.metrics.clone(),
            catalog: state.catalog.clone(),
            ping_interval: state.ping_interval,
        }
    }
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

pub(super) async fn write_loop<S: Sink<Message> + Unpin>(
    mut sink: S,
    mut outbox: mpsc::Receiver<ServerMessage>,
    session: Arc<SharedSession>,
    mut events: broadcast::Receiver<Arc<ServerMessage>>,
    link: Arc<ViewerLink>,
    env: WriterEnv,
) {
    let _end_reader = link.connection.clone().drop_guard();
    let (shutdown, metrics) = (&env.shutdown, &*env.metrics);
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
        tokio::time::Instant::now() + env.ping_interval,
        env.ping_interval,
    );
    loop {
        let ready = pacing.ready();
        let outgoing = tokio::select! {
            biased;
            _ = shutdown.cancelled() => {
                let reason = if env.draining.is_cancelled() {
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
                    let Some(dataset) = env.catalog.info(&core.dataset) else { continue };
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

#[cfg(test)]
mod tests {
    //! The writer over channels: a sink that records what it is given, a frame slot and a
    //! broadcast as the render thread and the session would fill them.

    use std::sync::atomic::AtomicU8;

    use tokio::sync::{mpsc, watch};
    use voxlight_engine::Scene;
    use voxlight_engine::renderer::Frame;
    use voxlight_engine::technique::TechniqueStats;

    use super::*;
    use crate::datasets::GpuFit;
    use crate::hub::{EVENT_BUFFER, SessionCore};
    use crate::render_service::RenderedFrame;

    fn rendered(frame_number: u64, converged: bool) -> Option<Arc<RenderedFrame>> {
        Some(Arc::new(RenderedFrame {
            frame_number,
            frame: Frame {
                width: 8,
                height: 8,
                rgba: vec![frame_number as u8; 8 * 8 * 4],
                iteration: 1,
                target_iterations: 4,
                converged,
                divisor: 1,
                preview: false,
                preview_match: None,
            },
            technique: "raymarch",
            scene_version: 0,
            render_ms: 1.0,
            gpu_ms: 1.0,
            stats: TechniqueStats::default(),
        }))
    }

    struct Harness {
        sent: mpsc::UnboundedReceiver<Message>,
        outbox: mpsc::Sender<ServerMessage>,
        frames: watch::Sender<Option<Arc<RenderedFrame>>>,
        link: Arc<ViewerLink>,
        shutdown: CancellationToken,
        writer: tokio::task::JoinHandle<()>,
    }

    fn start(window: Option<u32>) -> Harness {
        let (frames, frames_rx) = watch::channel(None);
        let (events, events_rx) = broadcast::channel(EVENT_BUFFER);
        let session = Arc::new(SharedSession::new(
            1,
            SessionCore {
                dataset: "phantom:cornell".into(),
                technique: "raymarch".into(),
                scene: Scene::default(),
                version: 0,
            },
            frames_rx,
            events,
        ));
        let link = Arc::new(ViewerLink {
            jpeg_quality: AtomicU8::new(80),
            acked: watch::Sender::new(0),
            window,
            connection: CancellationToken::new(),
            close: std::sync::Mutex::new(None),
        });
        let shutdown = CancellationToken::new();
        let env = WriterEnv {
            shutdown: shutdown.clone(),
            draining: CancellationToken::new(),
            metrics: Arc::new(Metrics::default()),
            catalog: Arc::new(Catalog::new(None, GpuFit::UNLIMITED).expect("phantom catalog")),
            ping_interval: Duration::from_secs(3600),
        };
        let (sent_tx, sent) = mpsc::unbounded_channel();
        let sink = Box::pin(futures_util::sink::unfold(
            sent_tx,
            |tx, message: Message| async move {
                tx.send(message).map_err(|_| "receiver gone")?;
                Ok::<_, &'static str>(tx)
            },
        ));
        let (outbox, outbox_rx) = mpsc::channel(8);
        let writer = tokio::spawn(write_loop(
            sink,
            outbox_rx,
            session,
            events_rx,
            link.clone(),
            env,
        ));
        Harness {
            sent,
            outbox,
            frames,
            link,
            shutdown,
            writer,
        }
    }

    async fn next(h: &mut Harness) -> Message {
        tokio::time::timeout(Duration::from_secs(10), h.sent.recv())
            .await
            .expect("the writer sent something in time")
            .expect("the writer is running")
    }

    /// The frame number of a binary frame (after its header's length prefix, the JSON header).
    fn frame_seq(message: &Message) -> u64 {
        let Message::Binary(bytes) = message else {
            panic!("a frame, got {message:?}")
        };
        let len = u32::from_le_bytes(bytes[..4].try_into().expect("length")) as usize;
        let header: serde_json::Value =
            serde_json::from_slice(&bytes[4..4 + len]).expect("frame header");
        header["seq"].as_u64().expect("seq")
    }

    #[tokio::test]
    async fn replies_and_frames_reach_the_viewer() {
        let mut h = start(None);
        let reply = ServerMessage::from(crate::reply::Reply::bad("out of range"));
        h.outbox.send(reply).await.expect("outbox");
        let Message::Text(text) = next(&mut h).await else {
            panic!("a text message")
        };
        assert!(text.as_str().contains("\"error\""), "{}", text.as_str());
        h.frames.send_replace(rendered(1, false));
        assert_eq!(frame_seq(&next(&mut h).await), 1);
    }

    #[tokio::test]
    async fn with_a_window_of_one_the_newest_frame_follows_the_ack() {
        let mut h = start(Some(1));
        h.frames.send_replace(rendered(1, false));
        assert_eq!(frame_seq(&next(&mut h).await), 1);
        // Two more frames while the first is unacknowledged: nothing goes out.
        h.frames.send_replace(rendered(2, false));
        h.frames.send_replace(rendered(3, false));
        let deadline = tokio::time::Instant::now() + Duration::from_millis(300);
        while let Ok(Some(message)) = tokio::time::timeout_at(deadline, h.sent.recv()).await {
            // The first frame's `stats` may follow it; no frame may.
            assert!(
                matches!(message, Message::Text(_)),
                "sent past the window: {message:?}"
            );
        }
        // The ack opens the window: the newest frame wins, frame 2 is skipped.
        h.link.acked.send_replace(1);
        let mut seqs = Vec::new();
        while seqs.is_empty() {
            let message = next(&mut h).await;
            if let Message::Binary(_) = message {
                seqs.push(frame_seq(&message));
            }
        }
        assert_eq!(seqs, vec![3]);
    }

    #[tokio::test]
    async fn shutdown_says_bye_and_closes() {
        let mut h = start(None);
        h.shutdown.cancel();
        let Message::Text(text) = next(&mut h).await else {
            panic!("a text message")
        };
        assert!(text.as_str().contains("\"bye\""), "{}", text.as_str());
        tokio::time::timeout(Duration::from_secs(10), &mut h.writer)
            .await
            .expect("the writer ends")
            .expect("no panic");
    }
}
