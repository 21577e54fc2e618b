//! Helpers for end-to-end tests: a real server on a free loopback port, and a scripted
//! WebSocket client that speaks the protocol.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use anyhow::{Context, bail};
use futures_util::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};
use tokio_util::sync::CancellationToken;
use voxlight_app::{AppState, Server, ServerConfig};
use voxlight_protocol::{FrameFormat, FrameMeta, ServerMessage, split_frame};

/// The shared engine of a test binary (opening lavapipe once is enough).
pub fn engine_gpu() -> Arc<voxlight_engine::Gpu> {
    static GPU: OnceLock<Arc<voxlight_engine::Gpu>> = OnceLock::new();
    GPU.get_or_init(|| {
        Arc::new(voxlight_engine::Gpu::new().unwrap_or_else(|e| {
            panic!("end-to-end tests need a GPU adapter (lavapipe: apt-get install mesa-vulkan-drivers): {e}")
        }))
    })
    .clone()
}

/// The real data folder (../shared/data); panics with a clear message when missing.
pub fn shared_data() -> PathBuf {
    voxlight_volumes::testdata::shared_data_dir()
        .expect("../shared/data not found: set VOXLIGHT_DATA to the shared data folder")
}

/// A running server on 127.0.0.1 with a free port.
pub struct TestServer {
    pub addr: SocketAddr,
    pub state: Arc<AppState>,
    pub shutdown: CancellationToken,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl TestServer {
    /// A server whose default dataset is the small sphere phantom, without preloading.
    pub async fn start(data_dir: Option<PathBuf>) -> anyhow::Result<Self> {
        Self::start_with(ServerConfig {
            data_dir,
            default_dataset: Some("phantom:sphere".into()),
            preload: false,
            ..Default::default()
        })
        .await
    }

    pub async fn start_with(config: ServerConfig) -> anyhow::Result<Self> {
        let engine = voxlight_engine::Engine::with_gpu(engine_gpu())?;
        let shutdown = CancellationToken::new();
        let server = Server::start(&config, engine, shutdown.clone())?;
        let state = server.state.clone();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let task = tokio::spawn(server.run(listener));
        Ok(Self {
            addr,
            state,
            shutdown,
            task,
        })
    }

    pub fn ws_url(&self) -> String {
        format!("ws://{}/ws", self.addr)
    }

    /// `GET path` through the router: status and body text.
    pub async fn get(&self, path: &str) -> (u16, String) {
        use http_body_util::BodyExt;
        use tower::ServiceExt;
        let request = axum::http::Request::get(path)
            .body(axum::body::Body::empty())
            .expect("request");
        let response = voxlight_app::app(self.state.clone())
            .oneshot(request)
            .await
            .expect("route");
        let status = response.status().as_u16();
        let body = response.into_body().collect().await.expect("body");
        (
            status,
            String::from_utf8_lossy(&body.to_bytes()).into_owned(),
        )
    }

    /// `GET /metrics`, as text.
    pub async fn metrics(&self) -> String {
        self.get("/metrics").await.1
    }

    /// One metric's value (the first line starting with `prefix`).
    pub async fn metric(&self, prefix: &str) -> f64 {
        metric(&self.metrics().await, prefix)
    }

    /// Cancels and waits for the server to drain.
    pub async fn stop(self) -> anyhow::Result<()> {
        self.shutdown.cancel();
        tokio::time::timeout(Duration::from_secs(30), self.task)
            .await
            .context("server did not stop within 30 s")???;
        Ok(())
    }
}

/// The value of the first metric line starting with `prefix`.
pub fn metric(text: &str, prefix: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(prefix))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no metric {prefix} in:\n{text}"))
}

/// A decoded frame.
#[derive(Debug, Clone)]
pub struct DecodedFrame {
    pub meta: FrameMeta,
    pub width: u32,
    pub height: u32,
    /// RGB8, row-major.
    pub rgb: Vec<u8>,
}

impl DecodedFrame {
    /// Largest difference of any channel between two pictures of equal size.
    pub fn max_diff(&self, other: &DecodedFrame) -> u8 {
        self.rgb
            .iter()
            .zip(&other.rgb)
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap_or(255)
    }

    /// Number of distinct colours (a flat picture has one).
    pub fn distinct_colors(&self) -> usize {
        let mut colors: Vec<[u8; 3]> = self
            .rgb
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        colors.sort_unstable();
        colors.dedup();
        colors.len()
    }
}

pub fn decode_image(format: FrameFormat, bytes: &[u8]) -> anyhow::Result<(u32, u32, Vec<u8>)> {
    match format {
        FrameFormat::Png => {
            let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
            let mut reader = decoder.read_info()?;
            let size = reader.output_buffer_size().context("PNG too large")?;
            let mut buf = vec![0; size];
            let info = reader.next_frame(&mut buf)?;
            buf.truncate(info.buffer_size());
            let rgb = match info.color_type {
                png::ColorType::Rgb => buf,
                png::ColorType::Rgba => buf
                    .chunks_exact(4)
                    .flat_map(|p| [p[0], p[1], p[2]])
                    .collect(),
                other => bail!("unexpected PNG colour type {other:?}"),
            };
            Ok((info.width, info.height, rgb))
        }
        FrameFormat::Jpeg => {
            let mut decoder = jpeg_decoder::Decoder::new(bytes);
            let pixels = decoder.decode()?;
            let info = decoder.info().context("JPEG without info")?;
            if info.pixel_format != jpeg_decoder::PixelFormat::RGB24 {
                bail!("unexpected JPEG pixel format {:?}", info.pixel_format);
            }
            Ok((info.width as u32, info.height as u32, pixels))
        }
    }
}

/// What the server sent.
// One value per received message in tests: the frame's size does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Incoming {
    Text(Box<ServerMessage>),
    Frame(DecodedFrame),
}

/// A scripted protocol client.
pub struct Client {
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
}

/// How long a test waits for any single server message.
pub const RECV_TIMEOUT: Duration = Duration::from_secs(60);

impl Client {
    pub async fn connect(url: &str) -> anyhow::Result<Self> {
        let (ws, _) = tokio_tungstenite::connect_async(url).await?;
        Ok(Self { ws })
    }

    /// Connects with extra request headers (token, Origin, subprotocols). Returns the
    /// client and the server's `Sec-WebSocket-Protocol` answer, or the refusal's HTTP status.
    pub async fn connect_with(
        url: &str,
        headers: &[(&str, &str)],
    ) -> Result<(Self, Option<String>), u16> {
        use tokio_tungstenite::tungstenite::client::IntoClientRequest;
        let mut request = url.into_client_request().map_err(|_| 0u16)?;
        for (name, value) in headers {
            let name =
                tokio_tungstenite::tungstenite::http::HeaderName::from_bytes(name.as_bytes())
                    .map_err(|_| 0u16)?;
            request
                .headers_mut()
                .insert(name, value.parse().map_err(|_| 0u16)?);
        }
        match tokio_tungstenite::connect_async(request).await {
            Ok((ws, response)) => {
                let protocol = response
                    .headers()
                    .get("sec-websocket-protocol")
                    .and_then(|v| v.to_str().ok())
                    .map(str::to_owned);
                Ok((Self { ws }, protocol))
            }
            Err(tokio_tungstenite::tungstenite::Error::Http(response)) => {
                Err(response.status().as_u16())
            }
            Err(_) => Err(0),
        }
    }

    pub async fn send_json(&mut self, value: serde_json::Value) -> anyhow::Result<()> {
        self.send_text(value.to_string()).await
    }

    pub async fn send_text(&mut self, text: String) -> anyhow::Result<()> {
        self.ws.send(Message::Text(text.into())).await?;
        Ok(())
    }

    pub async fn send_binary(&mut self, bytes: Vec<u8>) -> anyhow::Result<()> {
        self.ws.send(Message::Binary(bytes.into())).await?;
        Ok(())
    }

    /// The next protocol message (text or decoded frame).
    pub async fn recv(&mut self) -> anyhow::Result<Incoming> {
        loop {
            let message = tokio::time::timeout(RECV_TIMEOUT, self.ws.next())
                .await
                .context("no message from the server within the timeout")?
                .context("connection closed")??;
            match message {
                Message::Text(text) => {
                    let parsed: ServerMessage = serde_json::from_str(text.as_str())
                        .with_context(|| format!("server sent an unparsable message: {text}"))?;
                    return Ok(Incoming::Text(Box::new(parsed)));
                }
                Message::Binary(bytes) => {
                    let (meta, image) = split_frame(&bytes).context("malformed frame")?;
                    let (width, height, rgb) = decode_image(meta.format, image)?;
                    return Ok(Incoming::Frame(DecodedFrame {
                        meta,
                        width,
                        height,
                        rgb,
                    }));
                }
                Message::Close(_) => bail!("server closed the connection"),
                _ => continue,
            }
        }
    }

    /// Skips frames, `stats` and session chatter (`viewers`, `edited`, `state`) until another
    /// text message arrives.
    pub async fn recv_text(&mut self) -> anyhow::Result<ServerMessage> {
        loop {
            match self.recv().await? {
                Incoming::Frame(_) => {}
                Incoming::Text(message)
                    if matches!(
                        *message,
                        ServerMessage::Stats(_)
                            | ServerMessage::Viewers { .. }
                            | ServerMessage::Edited { .. }
                            | ServerMessage::State { .. }
                    ) => {}
                Incoming::Text(message) => return Ok(*message),
            }
        }
    }

    /// Skips frames until a text message satisfies `accept`; errors fail.
    pub async fn text_where(
        &mut self,
        accept: impl Fn(&ServerMessage) -> bool,
    ) -> anyhow::Result<ServerMessage> {
        loop {
            if let Incoming::Text(message) = self.recv().await? {
                if accept(&message) {
                    return Ok(*message);
                }
                if let ServerMessage::Error { code, message } = *message {
                    bail!("unexpected error {code:?}: {message}")
                }
            }
        }
    }

    /// Skips text messages (except errors, which fail) until a frame arrives that satisfies `accept`.
    pub async fn frame_where(
        &mut self,
        accept: impl Fn(&DecodedFrame) -> bool,
    ) -> anyhow::Result<DecodedFrame> {
        loop {
            match self.recv().await? {
                Incoming::Frame(frame) if accept(&frame) => return Ok(frame),
                Incoming::Frame(_) => {}
                Incoming::Text(message) => {
                    if let ServerMessage::Error { code, message } = *message {
                        bail!("unexpected error {code:?}: {message}")
                    }
                }
            }
        }
    }

    /// Sends `hello` and returns the `welcome`.
    pub async fn hello(
        &mut self,
        dataset: Option<&str>,
        width: u32,
        height: u32,
    ) -> anyhow::Result<ServerMessage> {
        let mut hello = serde_json::json!({"type": "hello", "protocol": 1, "viewport": {"width": width, "height": height}});
        if let Some(name) = dataset {
            hello["dataset"] = name.into();
        }
        self.send_json(hello).await?;
        let reply = self.recv_text().await?;
        if !matches!(reply, ServerMessage::Welcome { .. }) {
            bail!("expected welcome, got {reply:?}");
        }
        Ok(reply)
    }

    /// Sends a `hello` built by the test and returns the server's first reply (not counting
    /// session chatter): `welcome`, or an `error`.
    pub async fn hello_with(&mut self, hello: serde_json::Value) -> anyhow::Result<ServerMessage> {
        self.send_json(hello).await?;
        self.recv_text().await
    }

    /// Waits for a WebSocket ping, skipping everything else; the time it took.
    pub async fn wait_for_ping(&mut self, timeout: Duration) -> anyhow::Result<Duration> {
        let started = std::time::Instant::now();
        loop {
            let left = timeout.saturating_sub(started.elapsed());
            let message = tokio::time::timeout(left, self.ws.next())
                .await
                .context("no ping within the timeout")?
                .context("connection closed")??;
            if let Message::Ping(_) = message {
                return Ok(started.elapsed());
            }
        }
    }

    /// Drops the TCP connection without a close handshake (a network failure).
    pub fn drop_connection(self) {
        drop(self.ws);
    }

    pub async fn close(mut self) {
        let _ = self.ws.close(None).await;
    }
}
