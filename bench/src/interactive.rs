//! `voxlight bench interactive`: a scripted drag (an orbit of the camera with TF opacity edits
//! among it) replayed against a running server, as a user's browser sends it, for each
//! technique and viewport. It reports per-edit input-to-frame latency (from sending an edit to
//! the first frame whose `scene_version` shows it), the frames that arrived while dragging
//! (their spacing, how many were previews, at which resolution scale), the time from the last
//! edit to the lossless still, and the change of mean brightness from the last preview to that
//! still (the interaction mode's continuity, which should stay under 1%). The drag starts once
//! the session's first still has arrived, as a user looks at a picture before turning it.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use tokio_tungstenite::tungstenite::Message;
use voxlight_protocol::{
    Camera, ClientMessage, FrameFormat, PROTOCOL_VERSION, ServerMessage, TransferFunction,
    Viewport, split_frame,
};

use voxlight_app::loadgen::Percentiles;

/// Frames the bench lets be in flight (as the web viewer).
const WINDOW: u32 = 2;
/// How long connecting, `welcome` and the first frame may take.
const START_TIMEOUT: Duration = Duration::from_secs(300);
/// Degrees the camera turns per camera edit.
const ORBIT_STEP_DEG: f32 = 3.0;
/// Every this many edits, one is a TF edit.
const TF_EVERY: u32 = 4;

#[derive(Debug, Clone)]
pub struct InteractiveBench {
    /// `ws://host:port/ws`
    pub url: String,
    pub techniques: Vec<String>,
    pub viewports: Vec<Viewport>,
    pub dataset: Option<String>,
    /// Edits in the drag.
    pub edits: u32,
    /// Edits per second while dragging.
    pub edit_rate: f64,
    /// Progressive iterations the still refines to (sent as `quality`), so that the time to
    /// the still is measurable on a software adapter.
    pub still_iterations: u32,
    /// Longest wait for the still after the drag.
    pub still_timeout: Duration,
    /// Start the drag at the first technique frame (the technique still refining, as when a
    /// user turns the volume before it converged), not after the first still.
    pub drag_while_converging: bool,
}

/// What one technique at one viewport measured.
#[derive(Debug, Clone, Serialize)]
pub struct InteractiveRun {
    pub technique: String,
    pub width: u32,
    pub height: u32,
    /// From `hello` to the first frame.
    pub first_frame_ms: f64,
    /// From `hello` to what the drag waits for: the session's first converged still (a user
    /// looks at the picture before turning it; the preview's brightness match is fitted to
    /// it), or with `drag_while_converging` its first technique frame.
    pub drag_started_ms: f64,
    pub drag_while_converging: bool,
    pub edits: u32,
    pub input_to_frame_ms: Percentiles,
    /// Frames that arrived from the first edit until the last edit was shown.
    pub drag_frames: u32,
    /// Spacing of those frames.
    pub drag_frame_interval_ms: Percentiles,
    /// Of those frames, how many were previews, by resolution scale.
    pub drag_previews: u32,
    pub drag_scales: BTreeMap<String, u32>,
    /// The server's render time of the drag's frames.
    pub drag_render_ms: Percentiles,
    /// From sending the last edit to the converged lossless still showing it; None when it
    /// did not arrive within the timeout.
    pub time_to_still_ms: Option<f64>,
    pub still_iterations: u32,
    /// Mean brightness of the still over that of the last preview of the same scene, minus
    /// one, as encoded luma (Y' of the sRGB values, which JPEG's DC terms keep) and as linear
    /// luminance (which JPEG's ringing at edges raises, by convexity); None without both.
    pub still_vs_preview_luma: Option<f64>,
    pub still_vs_preview_linear: Option<f64>,
    /// The last preview's brightness match (FrameMeta.preview_match).
    pub last_preview_match: Option<voxlight_protocol::PreviewMatch>,
    pub errors: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct InteractiveReport {
    pub url: String,
    pub adapter: String,
    pub dataset: String,
    pub edit_rate: f64,
    pub runs: Vec<InteractiveRun>,
}

pub fn validate(bench: &InteractiveBench) -> anyhow::Result<()> {
    if bench.techniques.is_empty() || bench.viewports.is_empty() {
        bail!("name at least one technique and one viewport");
    }
    if !(1..=10_000).contains(&bench.edits) {
        bail!("--edits must be in 1..=10000");
    }
    if !(bench.edit_rate > 0.0 && bench.edit_rate <= 100.0) {
        bail!("--edit-rate must be in (0, 100] per second");
    }
    if bench.still_iterations == 0 {
        bail!("--still-iterations must be at least 1");
    }
    if !bench.url.starts_with("ws://") && !bench.url.starts_with("wss://") {
        bail!("--url must be a ws:// URL of the server's /ws endpoint");
    }
    Ok(())
}

/// `WxH` (e.g. `1024x768`) or one edge (`512`).
pub fn parse_viewport(text: &str) -> anyhow::Result<Viewport> {
    let (w, h) = text.split_once('x').unwrap_or((text, text));
    let parse = |s: &str| -> anyhow::Result<u32> {
        let v: u32 = s
            .trim()
            .parse()
            .with_context(|| format!("viewport `{text}`: `{s}` is not a number"))?;
        if !(8..=8192).contains(&v) {
            bail!("viewport `{text}`: edges must be in 8..=8192");
        }
        Ok(v)
    };
    Ok(Viewport {
        width: parse(w)?,
        height: parse(h)?,
    })
}

/// The drag's edit `k`: a camera turn, or every `TF_EVERY`th edit the TF's opacities scaled
/// as a slider drag would (down to 60% and back).
fn edit(k: u32, start: &Camera, tf: &TransferFunction) -> ClientMessage {
    if k % TF_EVERY == TF_EVERY - 1 {
        let phase = (k / TF_EVERY) as f32 * 0.8;
        let scale = 0.8 + 0.2 * phase.cos();
        let mut tf = tf.clone();
        for point in &mut tf.points {
            point.opacity = (point.opacity * scale).clamp(0.0, 1.0);
        }
        ClientMessage::Tf(tf)
    } else {
        let turns = k - k / TF_EVERY;
        ClientMessage::Camera(orbit(start, turns as f32 * ORBIT_STEP_DEG))
    }
}

/// `camera` turned by `degrees` about its up axis through its target (also `bench orbit`'s).
pub(crate) fn orbit(camera: &Camera, degrees: f32) -> Camera {
    let (s, c) = degrees.to_radians().sin_cos();
    let up = voxlight_engine::camera::normalize(camera.up).unwrap_or([0.0, 0.0, 1.0]);
    let v: [f32; 3] = std::array::from_fn(|i| camera.eye[i] - camera.target[i]);
    // Rodrigues' rotation of v about up.
    let dot = v[0] * up[0] + v[1] * up[1] + v[2] * up[2];
    let cross = [
        up[1] * v[2] - up[2] * v[1],
        up[2] * v[0] - up[0] * v[2],
        up[0] * v[1] - up[1] * v[0],
    ];
    let eye = std::array::from_fn(|i| {
        camera.target[i] + v[i] * c + cross[i] * s + up[i] * dot * (1.0 - c)
    });
    Camera { eye, ..*camera }
}

/// Mean brightness of an encoded frame (sRGB JPEG or PNG).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Brightness {
    /// Y' = 0.2126 R' + 0.7152 G' + 0.0722 B' of the encoded values, in [0, 1].
    pub luma: f64,
    /// Rec. 709 luminance of the linearised values.
    pub linear: f64,
}

pub fn mean_brightness(format: FrameFormat, image: &[u8]) -> anyhow::Result<Brightness> {
    let (pixels, channels) = match format {
        FrameFormat::Jpeg => {
            let mut decoder = jpeg_decoder::Decoder::new(image);
            let pixels = decoder.decode().context("decoding a JPEG frame")?;
            let info = decoder.info().context("JPEG without a header")?;
            let channels = match info.pixel_format {
                jpeg_decoder::PixelFormat::RGB24 => 3,
                jpeg_decoder::PixelFormat::L8 => 1,
                other => bail!("unexpected JPEG pixel format {other:?}"),
            };
            (pixels, channels)
        }
        FrameFormat::Png => {
            let decoder = png::Decoder::new(std::io::Cursor::new(image));
            let mut reader = decoder.read_info().context("reading a PNG frame")?;
            let size = reader.output_buffer_size().context("PNG frame too large")?;
            let mut pixels = vec![0; size];
            let info = reader
                .next_frame(&mut pixels)
                .context("decoding a PNG frame")?;
            pixels.truncate(info.buffer_size());
            if info.bit_depth != png::BitDepth::Eight {
                bail!("unexpected PNG bit depth {:?}", info.bit_depth);
            }
            (pixels, info.color_type.samples())
        }
    };
    if channels < 3 || pixels.is_empty() {
        bail!("frame has {channels} channels");
    }
    let linear = |v: u8| {
        let c = f64::from(v) / 255.0;
        if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    };
    let count = (pixels.len() / channels) as f64;
    let (mut luma, mut lin) = (0.0, 0.0);
    for p in pixels.chunks_exact(channels) {
        luma += (0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]))
            / 255.0;
        lin += 0.2126 * linear(p[0]) + 0.7152 * linear(p[1]) + 0.0722 * linear(p[2]);
    }
    Ok(Brightness {
        luma: luma / count,
        linear: lin / count,
    })
}

async fn ack(socket: &mut Socket, seq: u64) -> anyhow::Result<()> {
    let ack = format!(r#"{{"type":"ack","seq":{seq}}}"#);
    socket.send(Message::Text(ack.into())).await.context("ack")
}

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn send(socket: &mut Socket, message: &ClientMessage) -> anyhow::Result<()> {
    socket
        .send(Message::Text(serde_json::to_string(message)?.into()))
        .await
        .context("send")
}

/// What the server sent, with frames split into metadata and image (one at a time, so its
/// size does not matter).
#[allow(clippy::large_enum_variant)]
enum Received {
    Frame(voxlight_protocol::FrameMeta, Vec<u8>),
    Server(ServerMessage),
}

/// The next message; cancel-safe (it only reads), so frames are acknowledged by the caller.
async fn receive(socket: &mut Socket) -> anyhow::Result<Received> {
    loop {
        match socket.next().await.context("connection closed")?? {
            Message::Binary(bytes) => {
                let (meta, image) = split_frame(&bytes).context("malformed frame")?;
                return Ok(Received::Frame(meta, image.to_vec()));
            }
            Message::Text(text) => {
                return Ok(Received::Server(serde_json::from_str(text.as_str())?));
            }
            Message::Close(_) => bail!("the server closed the connection"),
            _ => {}
        }
    }
}

/// The first message `pick` accepts within `START_TIMEOUT`; an `error` from the server fails.
async fn wait_for<T>(
    socket: &mut Socket,
    what: &str,
    mut pick: impl FnMut(Received) -> Option<T>,
) -> anyhow::Result<T> {
    let wait = async {
        loop {
            match receive(socket).await? {
                Received::Server(ServerMessage::Error { message, .. }) => bail!("{message}"),
                received => {
                    if let Some(found) = pick(received) {
                        return Ok(found);
                    }
                }
            }
        }
    };
    tokio::time::timeout(START_TIMEOUT, wait)
        .await
        .with_context(|| format!("no {what}"))?
}

/// Runs every technique at every viewport in turn, one session each.
pub async fn run(bench: &InteractiveBench) -> anyhow::Result<InteractiveReport> {
    validate(bench)?;
    let mut report = InteractiveReport {
        url: bench.url.clone(),
        adapter: String::new(),
        dataset: String::new(),
        edit_rate: bench.edit_rate,
        runs: Vec::new(),
    };
    for technique in &bench.techniques {
        for &viewport in &bench.viewports {
            let (run, adapter, dataset) =
                run_one(bench, technique, viewport).await.with_context(|| {
                    format!("{technique} at {}x{}", viewport.width, viewport.height)
                })?;
            tracing::info!(
                technique,
                width = viewport.width,
                height = viewport.height,
                p50 = run.input_to_frame_ms.p50,
                p99 = run.input_to_frame_ms.p99,
                still_ms = run.time_to_still_ms,
                "interactive run done"
            );
            report.adapter = adapter;
            report.dataset = dataset;
            report.runs.push(run);
        }
    }
    Ok(report)
}

async fn run_one(
    bench: &InteractiveBench,
    technique: &str,
    viewport: Viewport,
) -> anyhow::Result<(InteractiveRun, String, String)> {
    let started = Instant::now();
    let (mut socket, _) = tokio::time::timeout(
        START_TIMEOUT,
        tokio_tungstenite::connect_async(bench.url.as_str()),
    )
    .await
    .context("connect timed out")??;
    send(
        &mut socket,
        &ClientMessage::Hello {
            protocol: PROTOCOL_VERSION,
            session: None,
            token: None,
            viewport: Some(viewport),
            dataset: bench.dataset.clone(),
            technique: Some(technique.to_owned()),
            technique_options: None,
            name: Some("bench-interactive".into()),
            max_in_flight: Some(WINDOW),
        },
    )
    .await?;
    // The welcome, then the first frame.
    let (own_id, state, adapter, dataset) =
        wait_for(&mut socket, "welcome", |received| match received {
            Received::Server(ServerMessage::Welcome {
                viewer,
                state,
                adapter,
                dataset,
                ..
            }) => Some((viewer.id, state, adapter, dataset.name)),
            _ => None,
        })
        .await?;
    send(
        &mut socket,
        &ClientMessage::Quality {
            jpeg_quality: None,
            iterations: Some(bench.still_iterations),
        },
    )
    .await?;
    let first = wait_for(&mut socket, "first frame", |received| match received {
        Received::Frame(meta, _) => Some(meta.seq),
        _ => None,
    })
    .await?;
    ack(&mut socket, first).await?;
    let first_frame_ms = started.elapsed().as_secs_f64() * 1e3;
    let drag_start = tokio::time::timeout(bench.still_timeout, async {
        loop {
            if let Received::Frame(meta, _) = receive(&mut socket).await? {
                ack(&mut socket, meta.seq).await?;
                let ready = if bench.drag_while_converging {
                    !meta.preview && !meta.converged
                } else {
                    meta.converged && meta.lossless
                };
                if ready {
                    return anyhow::Ok(());
                }
            }
        }
    });
    drag_start.await.context(
        "no still (or technique frame) to start the drag from within --still-timeout-s",
    )??;
    let drag_started_ms = started.elapsed().as_secs_f64() * 1e3;

    // The drag. Edits are sent on a timer; every frame is acknowledged as it arrives.
    let mut errors = Vec::new();
    let mut sent_at: Vec<Instant> = Vec::new();
    // Per edit: the scene version the server's echo gave it.
    let mut versions: Vec<Option<u64>> = Vec::new();
    let mut latencies = Vec::new();
    let mut shown = 0usize;
    let mut drag_frames = Vec::new();
    let mut last_preview: Option<(u64, FrameFormat, Vec<u8>)> = None;
    let mut last_preview_match = None;
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / bench.edit_rate));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let drag_deadline = Instant::now()
        + Duration::from_secs_f64(f64::from(bench.edits) / bench.edit_rate)
        + START_TIMEOUT;
    let mut still: Option<(Instant, voxlight_protocol::FrameMeta, Vec<u8>)> = None;
    let still_deadline = |last: Instant| last + bench.still_timeout;
    loop {
        let last_sent = (sent_at.len() == bench.edits as usize).then(|| sent_at[sent_at.len() - 1]);
        let deadline = last_sent.map_or(drag_deadline, still_deadline);
        tokio::select! {
            _ = ticker.tick(), if sent_at.len() < bench.edits as usize => {
                let k = sent_at.len() as u32;
                send(&mut socket, &edit(k, &state.camera, &state.tf)).await?;
                sent_at.push(Instant::now());
                versions.push(None);
            }
            _ = tokio::time::sleep_until(tokio::time::Instant::from_std(deadline)) => {
                if last_sent.is_some() {
                    errors.push("no still within the timeout".to_owned());
                } else {
                    errors.push("the drag's edits were not all shown".to_owned());
                }
                break;
            }
            received = receive(&mut socket) => match received? {
                Received::Server(ServerMessage::Edited { by, version, .. }) if by.id == own_id => {
                    if let Some(slot) = versions.iter_mut().find(|v| v.is_none()) {
                        *slot = Some(version);
                    }
                }
                Received::Server(ServerMessage::Error { code, message }) => {
                    errors.push(format!("{code:?}: {message}"));
                }
                Received::Server(_) => {}
                Received::Frame(meta, image) => {
                    let now = Instant::now();
                    ack(&mut socket, meta.seq).await?;
                    // Frames from the first edit to the one that shows the last are the drag's.
                    if !sent_at.is_empty() && shown < bench.edits as usize {
                        drag_frames.push((now, meta.clone()));
                    }
                    while shown < versions.len()
                        && versions[shown].is_some_and(|v| meta.scene_version >= v)
                    {
                        latencies.push(now.duration_since(sent_at[shown]).as_secs_f64() * 1e3);
                        shown += 1;
                    }
                    if meta.preview {
                        last_preview = Some((meta.scene_version, meta.format, image.clone()));
                        last_preview_match = meta.preview_match;
                    }
                    let final_version = versions.last().copied().flatten();
                    if sent_at.len() == bench.edits as usize
                        && final_version.is_some_and(|v| meta.scene_version >= v)
                        && meta.converged
                        && meta.lossless
                    {
                        still = Some((now, meta, image));
                        break;
                    }
                }
            }
        }
    }
    let _ = socket.close(None).await;

    let intervals: Vec<f64> = drag_frames
        .windows(2)
        .map(|w| w[1].0.duration_since(w[0].0).as_secs_f64() * 1e3)
        .collect();
    let mut drag_scales = BTreeMap::new();
    for (_, meta) in drag_frames.iter().filter(|(_, m)| m.preview) {
        *drag_scales
            .entry(format!("{}", meta.resolution_scale))
            .or_insert(0) += 1;
    }
    let time_to_still_ms = still.as_ref().and_then(|(at, ..)| {
        sent_at
            .last()
            .map(|last| at.duration_since(*last).as_secs_f64() * 1e3)
    });
    let (still_vs_preview_luma, still_vs_preview_linear) = match (&still, &last_preview) {
        (Some((_, meta, image)), Some((version, format, preview)))
            if *version == meta.scene_version =>
        {
            let still = mean_brightness(meta.format, image)?;
            let preview = mean_brightness(*format, preview)?;
            let ratio = |a: f64, b: f64| (b > 0.0).then(|| a / b - 1.0);
            (
                ratio(still.luma, preview.luma),
                ratio(still.linear, preview.linear),
            )
        }
        _ => (None, None),
    };
    let run = InteractiveRun {
        technique: technique.to_owned(),
        width: viewport.width,
        height: viewport.height,
        first_frame_ms,
        drag_started_ms,
        drag_while_converging: bench.drag_while_converging,
        edits: bench.edits,
        input_to_frame_ms: Percentiles::of(latencies),
        drag_frames: drag_frames.len() as u32,
        drag_frame_interval_ms: Percentiles::of(intervals),
        drag_previews: drag_frames.iter().filter(|(_, m)| m.preview).count() as u32,
        drag_scales,
        drag_render_ms: Percentiles::of(
            drag_frames
                .iter()
                .map(|(_, m)| f64::from(m.render_ms))
                .collect(),
        ),
        time_to_still_ms,
        still_iterations: bench.still_iterations,
        still_vs_preview_luma,
        still_vs_preview_linear,
        last_preview_match,
        errors,
    };
    Ok((run, adapter, dataset))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viewports_parse_and_are_checked() {
        let v = parse_viewport("1024x768").unwrap();
        assert_eq!((v.width, v.height), (1024, 768));
        let v = parse_viewport("512").unwrap();
        assert_eq!((v.width, v.height), (512, 512));
        assert!(parse_viewport("0x10").is_err());
        assert!(parse_viewport("axb").is_err());
    }

    #[test]
    fn the_drag_orbits_and_edits_the_tf() {
        let camera = Camera::default();
        let tf = voxlight_protocol::TransferFunction::default();
        let messages: Vec<_> = (0..8).map(|k| edit(k, &camera, &tf)).collect();
        let tf_edits = messages
            .iter()
            .filter(|m| matches!(m, ClientMessage::Tf(_)))
            .count();
        assert_eq!(tf_edits, 2);
        // The camera keeps its distance to the target and turns 3° per camera edit.
        let ClientMessage::Camera(c) = &messages[1] else {
            panic!("edit 1 is a camera turn");
        };
        let r = |e: [f32; 3]| (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
        assert!((r(c.eye) - r(camera.eye)).abs() < 1e-5);
        let cos = (c.eye[0] * camera.eye[0] + c.eye[1] * camera.eye[1] + c.eye[2] * camera.eye[2])
            / (r(c.eye) * r(camera.eye));
        assert!(
            (cos.acos().to_degrees() - ORBIT_STEP_DEG).abs() < 0.01,
            "{cos}"
        );
    }

    #[test]
    fn luminance_of_encoded_frames() {
        let grey = vec![188u8; 16 * 16 * 4];
        let png = voxlight_app::encode::png(&grey, 16, 16).unwrap();
        // sRGB 188 is linear 0.5.
        let b = mean_brightness(FrameFormat::Png, &png).unwrap();
        assert!((b.linear - 0.5).abs() < 0.01, "{b:?}");
        assert!((b.luma - 188.0 / 255.0).abs() < 1e-9, "{b:?}");
        let jpeg = voxlight_app::encode::jpeg(&grey, 16, 16, 95).unwrap();
        let b = mean_brightness(FrameFormat::Jpeg, &jpeg).unwrap();
        assert!((b.linear - 0.5).abs() < 0.02, "{b:?}");
    }
}
