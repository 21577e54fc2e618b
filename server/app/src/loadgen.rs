//! `voxlight loadgen`: scripted viewers against a running server. Each session has one editor
//! (orbits the camera and edits the TF) and `viewers − 1` watchers that join it by id. Every
//! viewer acknowledges frames (`max_in_flight` 2) without decoding them, so the client costs
//! little. Input-to-frame latency is measured by the editor: from sending an edit to the first
//! frame whose `scene_version` reaches the version the server's `edited` echo gave that edit.
//! Connections, messages and time are bounded; it stops by itself after `duration`.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use voxlight_protocol::{
    Camera, ClientMessage, MAX_VIEWERS_PER_SESSION, PROTOCOL_VERSION, ServerMessage,
    TransferFunction, Viewport, split_frame,
};

/// Most sessions one run may open.
pub const MAX_SESSIONS: u32 = 1024;
/// How long connecting and the `welcome` may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(30);
/// Frames a viewer lets be in flight.
const WINDOW: u32 = 2;

#[derive(Debug, Clone)]
pub struct LoadConfig {
    /// `ws://host:port/ws`
    pub url: String,
    pub sessions: u32,
    pub viewers: u32,
    pub duration: Duration,
    pub viewport: Viewport,
    pub dataset: Option<String>,
    pub technique: Option<String>,
    /// Sent in every session's `hello`.
    pub technique_options: Option<voxlight_protocol::TechniqueOptions>,
    pub token: Option<String>,
    /// Camera edits per second from each session's editor.
    pub edit_rate: f64,
    /// Seconds between TF edits.
    pub tf_interval: Duration,
    /// Extra sessions nobody edits that keep refining (a very high iteration target): the
    /// GPU scheduler should keep them from slowing the edited ones down.
    pub background_sessions: u32,
}

#[derive(Debug, Clone, Serialize)]
pub struct Percentiles {
    pub count: usize,
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

impl Percentiles {
    pub fn of(mut values: Vec<f64>) -> Self {
        values.sort_by(f64::total_cmp);
        let at = |q: f64| {
            if values.is_empty() {
                0.0
            } else {
                values[((values.len() - 1) as f64 * q).round() as usize]
            }
        };
        Self {
            count: values.len(),
            p50: at(0.5),
            p99: at(0.99),
            max: values.last().copied().unwrap_or(0.0),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct LoadReport {
    pub url: String,
    pub sessions: u32,
    pub viewers_per_session: u32,
    pub width: u32,
    pub height: u32,
    pub duration_s: f64,
    pub frames: u64,
    /// Frames per second of each viewer, over the time after its first frame.
    pub fps_per_viewer: Percentiles,
    pub min_fps: f64,
    /// Sessions whose every viewer received at least 10 frames a second.
    pub sessions_at_10fps: u32,
    pub input_to_frame_ms: Percentiles,
    pub bytes_per_s: f64,
    pub background_sessions: u32,
    /// Mean frames per second of the background sessions.
    pub background_fps: f64,
    pub errors: u64,
    /// Error messages and failures by code.
    pub error_codes: BTreeMap<String, u64>,
}

/// What one viewer saw.
#[derive(Debug, Default)]
struct ViewerResult {
    frames: u64,
    bytes: u64,
    first_frame: Option<Instant>,
    last_frame: Option<Instant>,
    latencies_ms: Vec<f64>,
    errors: Vec<String>,
}

impl ViewerResult {
    fn fps(&self, end: Instant) -> f64 {
        match self.first_frame {
            Some(first) if self.frames > 1 => {
                (self.frames - 1) as f64 / end.duration_since(first).as_secs_f64().max(1e-3)
            }
            _ => 0.0,
        }
    }
}

pub fn validate(config: &LoadConfig) -> anyhow::Result<()> {
    if !(1..=MAX_SESSIONS).contains(&config.sessions) {
        bail!("--sessions must be in 1..={MAX_SESSIONS}");
    }
    if config.background_sessions > MAX_SESSIONS {
        bail!("--background-sessions must be at most {MAX_SESSIONS}");
    }
    if !(1..=MAX_VIEWERS_PER_SESSION as u32).contains(&config.viewers) {
        bail!("--viewers must be in 1..={MAX_VIEWERS_PER_SESSION}");
    }
    if config.duration.is_zero() || config.duration > Duration::from_secs(3600) {
        bail!("--duration must be in (0, 3600] seconds");
    }
    if !(config.edit_rate > 0.0 && config.edit_rate <= 100.0) {
        bail!("--edit-rate must be in (0, 100] per second");
    }
    if !config.url.starts_with("ws://") && !config.url.starts_with("wss://") {
        bail!("--url must be a ws:// URL of the server's /ws endpoint");
    }
    Ok(())
}

/// Runs the whole load and reports it.
pub async fn run(config: LoadConfig) -> anyhow::Result<LoadReport> {
    validate(&config)?;
    let started = Instant::now();
    let deadline = started + config.duration;
    let mut sessions = tokio::task::JoinSet::new();
    for index in 0..config.sessions {
        let config = config.clone();
        sessions.spawn(async move { run_session(&config, index, deadline).await });
    }
    let mut background = tokio::task::JoinSet::new();
    for _ in 0..config.background_sessions {
        let config = config.clone();
        background.spawn(async move { run_background(&config, deadline).await });
    }
    let mut per_session: Vec<Vec<ViewerResult>> = Vec::new();
    while let Some(result) = sessions.join_next().await {
        per_session.push(result.context("a session task panicked")?);
    }
    let mut background_results = Vec::new();
    while let Some(result) = background.join_next().await {
        background_results.push(result.context("a background task panicked")?);
    }
    let end = Instant::now().min(deadline);
    let background_fps = if background_results.is_empty() {
        0.0
    } else {
        background_results.iter().map(|v| v.fps(end)).sum::<f64>() / background_results.len() as f64
    };
    let viewers: Vec<&ViewerResult> = per_session.iter().flatten().collect();
    let fps: Vec<f64> = viewers.iter().map(|v| v.fps(end)).collect();
    let mut error_codes = BTreeMap::new();
    for error in viewers.iter().flat_map(|v| &v.errors) {
        *error_codes.entry(error.clone()).or_insert(0) += 1;
    }
    let elapsed = end.duration_since(started).as_secs_f64().max(1e-3);
    Ok(LoadReport {
        url: config.url.clone(),
        sessions: config.sessions,
        viewers_per_session: config.viewers,
        width: config.viewport.width,
        height: config.viewport.height,
        duration_s: elapsed,
        frames: viewers.iter().map(|v| v.frames).sum(),
        min_fps: fps.iter().copied().reduce(f64::min).unwrap_or(0.0),
        fps_per_viewer: Percentiles::of(fps),
        sessions_at_10fps: per_session
            .iter()
            .filter(|s| !s.is_empty() && s.iter().all(|v| v.fps(end) >= 10.0))
            .count() as u32,
        input_to_frame_ms: Percentiles::of(
            viewers
                .iter()
                .flat_map(|v| v.latencies_ms.iter().copied())
                .collect(),
        ),
        bytes_per_s: viewers.iter().map(|v| v.bytes).sum::<u64>() as f64 / elapsed,
        background_sessions: config.background_sessions,
        background_fps,
        errors: error_codes.values().sum(),
        error_codes,
    })
}

type Socket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

async fn connect(config: &LoadConfig) -> anyhow::Result<Socket> {
    let mut request = config.url.as_str().into_client_request()?;
    if let Some(token) = &config.token {
        request
            .headers_mut()
            .insert("authorization", format!("Bearer {token}").parse()?);
    }
    let (socket, _) =
        tokio::time::timeout(CONNECT_TIMEOUT, tokio_tungstenite::connect_async(request))
            .await
            .context("connect timed out")??;
    Ok(socket)
}

/// Sends `hello` and waits for `welcome`: (session id, own viewer id, TF).
async fn hello(
    socket: &mut Socket,
    config: &LoadConfig,
    name: String,
    join: Option<String>,
) -> anyhow::Result<(String, u32, TransferFunction)> {
    let hello = ClientMessage::Hello {
        protocol: PROTOCOL_VERSION,
        session: join,
        token: None,
        viewport: Some(config.viewport),
        dataset: config.dataset.clone(),
        technique: config.technique.clone(),
        // Ignored by the server when joining.
        technique_options: config.technique_options,
        name: Some(name),
        max_in_flight: Some(WINDOW),
    };
    socket
        .send(Message::Text(serde_json::to_string(&hello)?.into()))
        .await?;
    let wait = async {
        while let Some(message) = socket.next().await {
            if let Message::Text(text) = message? {
                match serde_json::from_str::<ServerMessage>(text.as_str())? {
                    ServerMessage::Welcome {
                        session,
                        viewer,
                        state,
                        ..
                    } => return Ok((session, viewer.id, state.tf)),
                    ServerMessage::Error { code, message } => {
                        bail!("{}: {message}", code_name(&code))
                    }
                    _ => {}
                }
            }
        }
        bail!("connection closed before welcome")
    };
    tokio::time::timeout(CONNECT_TIMEOUT, wait)
        .await
        .context("no welcome")?
}

fn code_name(code: &voxlight_protocol::ErrorCode) -> String {
    serde_json::to_value(code)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| "unknown".into())
}

async fn run_session(config: &LoadConfig, index: u32, deadline: Instant) -> Vec<ViewerResult> {
    let mut results = Vec::new();
    let mut editor = match connect(config).await {
        Ok(socket) => socket,
        Err(e) => {
            results.push(failed(format!("connect: {e:#}")));
            return results;
        }
    };
    let (session, own_id, tf) =
        match hello(&mut editor, config, format!("loadgen-{index}-0"), None).await {
            Ok(welcome) => welcome,
            Err(e) => {
                results.push(failed(format!("hello: {e:#}")));
                return results;
            }
        };
    let mut watchers = tokio::task::JoinSet::new();
    for v in 1..config.viewers {
        let (config, session) = (config.clone(), session.clone());
        watchers.spawn(async move {
            let mut socket = match connect(&config).await {
                Ok(socket) => socket,
                Err(e) => return failed(format!("connect: {e:#}")),
            };
            let name = format!("loadgen-{index}-{v}");
            if let Err(e) = hello(&mut socket, &config, name, Some(session)).await {
                return failed(format!("join: {e:#}"));
            }
            drive(socket, None, deadline).await
        });
    }
    let editing = Editing {
        own_id,
        tf,
        edit_rate: config.edit_rate,
        tf_interval: config.tf_interval,
        phase: index as f32 * 0.7,
    };
    results.push(drive(editor, Some(editing), deadline).await);
    while let Some(result) = watchers.join_next().await {
        results.push(result.unwrap_or_else(|e| failed(format!("task: {e}"))));
    }
    results
}

/// A session that nobody edits and that keeps refining until the deadline.
async fn run_background(config: &LoadConfig, deadline: Instant) -> ViewerResult {
    let mut socket = match connect(config).await {
        Ok(socket) => socket,
        Err(e) => return failed(format!("connect: {e:#}")),
    };
    if let Err(e) = hello(&mut socket, config, "loadgen-background".into(), None).await {
        return failed(format!("hello: {e:#}"));
    }
    let quality = r#"{"type":"quality","iterations":65536}"#;
    if socket.send(Message::Text(quality.into())).await.is_err() {
        return failed("send".into());
    }
    drive(socket, None, deadline).await
}

fn failed(error: String) -> ViewerResult {
    ViewerResult {
        errors: vec![error.split(':').next().unwrap_or("error").to_owned()],
        ..ViewerResult::default()
    }
}

/// The editor's script.
struct Editing {
    own_id: u32,
    tf: TransferFunction,
    edit_rate: f64,
    tf_interval: Duration,
    phase: f32,
}

impl Editing {
    fn camera(&self, t: f32) -> ClientMessage {
        // 20° a second around the volume, slightly from above.
        let a = self.phase + t * 20f32.to_radians();
        ClientMessage::Camera(Camera {
            eye: [2.4 * a.sin(), -2.4 * a.cos(), 0.6],
            ..Camera::default()
        })
    }

    fn tf(&self, step: u32) -> ClientMessage {
        let scale = if step.is_multiple_of(2) { 0.7 } else { 1.0 };
        let mut tf = self.tf.clone();
        for point in &mut tf.points {
            point.opacity *= scale;
        }
        ClientMessage::Tf(tf)
    }
}

/// Reads (and acknowledges) frames until the deadline; the editor also sends its edits.
async fn drive(mut socket: Socket, editing: Option<Editing>, deadline: Instant) -> ViewerResult {
    let mut result = ViewerResult::default();
    let start = Instant::now();
    let deadline = tokio::time::Instant::from_std(deadline);
    let mut edit_timer = tokio::time::interval(Duration::from_secs_f64(
        1.0 / editing.as_ref().map_or(1.0, |e| e.edit_rate),
    ));
    edit_timer.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut last_tf = Instant::now();
    let mut tf_step = 0;
    // Edits sent and not yet echoed (send time), then echoed edits waiting for their frame.
    let mut unechoed: VecDeque<Instant> = VecDeque::new();
    let mut awaiting: VecDeque<(u64, Instant)> = VecDeque::new();
    loop {
        tokio::select! {
            _ = tokio::time::sleep_until(deadline) => break,
            _ = edit_timer.tick(), if editing.is_some() => {
                let Some(editing) = &editing else { continue };
                let edit = if last_tf.elapsed() >= editing.tf_interval {
                    last_tf = Instant::now();
                    tf_step += 1;
                    editing.tf(tf_step)
                } else {
                    editing.camera(start.elapsed().as_secs_f32())
                };
                let Ok(text) = serde_json::to_string(&edit) else { continue };
                if socket.send(Message::Text(text.into())).await.is_err() {
                    result.errors.push("send".into());
                    break;
                }
                unechoed.push_back(Instant::now());
            }
            message = socket.next() => {
                let message = match message {
                    Some(Ok(message)) => message,
                    Some(Err(_)) | None => {
                        result.errors.push("disconnected".into());
                        break;
                    }
                };
                match message {
                    Message::Binary(bytes) => {
                        let now = Instant::now();
                        let Some((meta, _)) = split_frame(&bytes) else {
                            result.errors.push("malformed_frame".into());
                            continue;
                        };
                        result.frames += 1;
                        result.bytes += bytes.len() as u64;
                        result.first_frame.get_or_insert(now);
                        result.last_frame = Some(now);
                        while let Some(&(version, sent)) = awaiting.front()
                            && meta.scene_version >= version
                        {
                            result.latencies_ms.push(now.duration_since(sent).as_secs_f64() * 1e3);
                            awaiting.pop_front();
                        }
                        let ack = format!(r#"{{"type":"ack","seq":{}}}"#, meta.seq);
                        if socket.send(Message::Text(ack.into())).await.is_err() {
                            result.errors.push("send".into());
                            break;
                        }
                    }
                    Message::Text(text) => match serde_json::from_str::<ServerMessage>(text.as_str()) {
                        Ok(ServerMessage::Edited { by, version, .. })
                            if editing.as_ref().is_some_and(|e| e.own_id == by.id) =>
                        {
                            if let Some(sent) = unechoed.pop_front() {
                                awaiting.push_back((version, sent));
                            }
                        }
                        Ok(ServerMessage::Error { code, .. }) => result.errors.push(code_name(&code)),
                        Ok(ServerMessage::Bye { .. }) => {
                            result.errors.push("bye".into());
                            break;
                        }
                        Ok(_) => {}
                        Err(_) => result.errors.push("unparsable".into()),
                    },
                    Message::Close(_) => {
                        result.errors.push("closed".into());
                        break;
                    }
                    _ => {}
                }
            }
        }
    }
    let _ = socket.close(None).await;
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_and_limits() {
        let p = Percentiles::of((1..=100).map(f64::from).collect());
        assert_eq!((p.count, p.p50, p.max), (100, 51.0, 100.0));
        assert_eq!(p.p99, 99.0);
        let empty = Percentiles::of(Vec::new());
        assert_eq!((empty.count, empty.p50), (0, 0.0));
        let mut config = LoadConfig {
            url: "ws://127.0.0.1:1/ws".into(),
            sessions: 2,
            viewers: 2,
            duration: Duration::from_secs(1),
            viewport: Viewport::default(),
            dataset: None,
            technique: None,
            technique_options: None,
            token: None,
            edit_rate: 10.0,
            tf_interval: Duration::from_secs(2),
            background_sessions: 0,
        };
        assert!(validate(&config).is_ok());
        config.viewers = 0;
        assert!(validate(&config).is_err());
        config.viewers = 2;
        config.url = "http://x".into();
        assert!(validate(&config).is_err());
    }
}
