//! The voxlight server: axum routes, sessions, streaming and frame encoding. GPU work runs on
//! the render thread (`render_service`); the async side never blocks on the GPU.

pub mod adapt;
pub mod auth;
pub mod datasets;
pub mod dicomweb;
pub mod encode;
pub mod hub;
pub mod lifecycle;
pub mod loadgen;
pub mod metrics;
pub mod offline;
pub mod render_service;
pub mod reply;
pub mod routes;
pub mod session;

use std::path::PathBuf;
use std::sync::Arc;

use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use voxlight_engine::Engine;
use voxlight_protocol::TechniqueInfo;

pub use routes::app;

use crate::datasets::Catalog;
use crate::render_service::RenderHandle;

/// Shared by every request and session.
pub struct AppState {
    pub catalog: Arc<Catalog>,
    pub render: RenderHandle,
    pub techniques: Vec<TechniqueInfo>,
    pub adapter: String,
    pub software_renderer: bool,
    /// Largest viewport (width × height) one session may render on this GPU.
    pub max_viewport_pixels: u64,
    pub default_dataset: String,
    pub access: auth::Access,
    pub metrics: Arc<metrics::Metrics>,
    /// Shared sessions by id.
    pub hub: hub::Hub,
    pub shutdown: CancellationToken,
    pub tracker: TaskTracker,
    /// Most sessions this process holds (None: no limit but the GPU memory budget).
    pub max_sessions: Option<usize>,
    /// The path prefix a router uses to reach this process directly (`/p/3/`), told to
    /// viewers in `welcome`.
    pub route_prefix: Option<String>,
    /// Cancelled when the process starts draining (`lifecycle::drain`).
    pub draining: CancellationToken,
    /// When a drain ends at the latest.
    pub drain_deadline: std::sync::Mutex<Option<tokio::time::Instant>>,
    /// How often every viewer's socket gets a WebSocket ping.
    pub ping_interval: std::time::Duration,
}

/// What `serve` needs besides a listener.
#[derive(Debug, Clone, Default)]
pub struct ServerConfig {
    pub data_dir: Option<PathBuf>,
    /// Dataset for clients that name none; `phantom:cornell` when unset.
    pub default_dataset: Option<String>,
    /// Load every dataset once in the background at start-up so `/api/datasets` can show
    /// dims, spacing, value range and histogram before anyone opens them.
    pub preload: bool,
    /// Tokens and allowed origins, checked before WebSocket upgrades and `/api/` requests.
    pub access: auth::Access,
    /// How long a session is kept after its last viewer left (for reconnects);
    /// `hub::DEFAULT_GRACE_PERIOD` when unset.
    pub grace_period: Option<std::time::Duration>,
    /// GPU bytes all sessions and volumes together may use; `DEFAULT_GPU_MEMORY_BUDGET`
    /// when unset.
    pub gpu_memory_budget: Option<u64>,
    /// The interaction mode (previews while edits stream in); off when unset (`voxlight serve`
    /// turns it on with `Interaction::default()`).
    pub interaction: Option<render_service::Interaction>,
    /// Most sessions this process holds; the next gets `at_capacity` and `/readyz` turns
    /// false at it. None: no limit but the GPU memory budget.
    pub max_sessions: Option<usize>,
    /// The path prefix under which a router reaches this very process (`/p/3/`, stripped by
    /// the router); sent to viewers so their share links and reconnects come back here.
    pub route_prefix: Option<String>,
    /// A PACS whose series are offered as datasets (DICOMweb: QIDO-RS and WADO-RS).
    pub dicomweb: Option<DicomWebSource>,
    /// GPU bytes one volume may take; a larger one is rendered from a downsampled copy (the
    /// viewer is told). Half the GPU memory budget when unset.
    pub max_volume_bytes: Option<u64>,
    /// How often viewers get a WebSocket ping (keeps proxies from cutting a quiet, converged
    /// viewer); `session::PING_INTERVAL` when unset.
    pub ping_interval: Option<std::time::Duration>,
}

/// Where `--dicomweb` points.
#[derive(Debug, Clone)]
pub struct DicomWebSource {
    /// The DICOMweb root, e.g. `https://pacs.example.org/dicom-web`.
    pub url: String,
    /// A file holding `user:password` or `Bearer <token>` (never logged).
    pub credentials: Option<PathBuf>,
}

/// Default global GPU memory budget: 4 GiB, which fits most GPUs that run this (a larger
/// GPU is told so with `--gpu-memory-mib`).
pub const DEFAULT_GPU_MEMORY_BUDGET: u64 = 4 << 30;

/// A route prefix is an absolute path ending in `/` of plain path characters.
fn check_route_prefix(prefix: &str) -> anyhow::Result<()> {
    let plain = prefix
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || "/-_.~".contains(c));
    if !(prefix.starts_with('/') && prefix.ends_with('/') && plain) || prefix.contains("//") {
        anyhow::bail!(
            "route prefix `{prefix}` must be a path like `/p/3/`: starting and ending with `/`, \
             letters, digits and -_.~ only"
        );
    }
    Ok(())
}

/// A started server core: the state for `app`, plus the render thread to join at the end.
pub struct Server {
    pub state: Arc<AppState>,
    render_thread: std::thread::JoinHandle<()>,
}

impl Server {
    /// Opens the GPU, scans the data folder and starts the render thread.
    pub fn start(
        config: &ServerConfig,
        engine: Engine,
        shutdown: CancellationToken,
    ) -> anyhow::Result<Self> {
        let budget = config
            .gpu_memory_budget
            .unwrap_or(DEFAULT_GPU_MEMORY_BUDGET);
        let fit = datasets::GpuFit {
            max_dim: engine.gpu.limits.max_texture_dimension_3d,
            max_bytes: config.max_volume_bytes.unwrap_or(budget / 2),
            bytes_per_voxel: voxlight_engine::volume::GpuVolume::bytes_needed(
                &engine.gpu,
                [1, 1, 1],
            ),
        };
        let mut catalog = Catalog::new(config.data_dir.as_deref(), fit)?;
        if let Some(source) = &config.dicomweb {
            let authorization = source
                .credentials
                .as_deref()
                .map(dicomweb::read_credentials)
                .transpose()?;
            catalog =
                catalog.with_dicomweb(dicomweb::DicomWeb::new(&source.url, authorization)?)?;
        }
        let catalog = Arc::new(catalog);
        let default_dataset = config
            .default_dataset
            .clone()
            .unwrap_or_else(|| datasets::DEFAULT_DATASET.to_owned());
        if !catalog.contains(&default_dataset) {
            anyhow::bail!("default dataset `{default_dataset}` is not in the catalog");
        }
        let techniques = engine.techniques();
        let adapter = engine.gpu.adapter_name();
        let software_renderer = engine.gpu.is_software();
        let max_viewport_pixels = engine.max_viewport_pixels();
        if let Some(prefix) = &config.route_prefix {
            check_route_prefix(prefix)?;
        }
        if config.max_sessions == Some(0) {
            anyhow::bail!("max sessions must be at least 1");
        }
        if software_renderer {
            tracing::warn!(%adapter, "rendering on a software adapter (CPU): expect low frame rates");
        }
        let metrics = Arc::new(metrics::Metrics::default());
        let _ = metrics.adapter.set((adapter.clone(), software_renderer));
        metrics.session_capacity.store(
            config.max_sessions.map_or(-1, |m| m as i64),
            std::sync::atomic::Ordering::Relaxed,
        );
        tracing::info!(
            %adapter,
            software_renderer,
            max_sessions = config.max_sessions,
            route_prefix = config.route_prefix.as_deref(),
            "GPU adapter opened"
        );
        let (render, render_thread) = render_service::spawn(
            Arc::new(engine),
            metrics.clone(),
            budget,
            config
                .interaction
                .unwrap_or(render_service::Interaction::OFF),
        )?;
        if config.preload {
            let catalog = catalog.clone();
            std::thread::Builder::new()
                .name("voxlight-preload".into())
                .spawn(move || catalog.preload())?;
        }
        let state = Arc::new(AppState {
            catalog,
            render,
            techniques,
            adapter,
            software_renderer,
            max_viewport_pixels,
            default_dataset,
            access: config.access.clone(),
            metrics,
            hub: hub::Hub::new(config.grace_period.unwrap_or(hub::DEFAULT_GRACE_PERIOD)),
            shutdown,
            tracker: TaskTracker::new(),
            max_sessions: config.max_sessions,
            route_prefix: config.route_prefix.clone(),
            draining: CancellationToken::new(),
            drain_deadline: Default::default(),
            ping_interval: config
                .ping_interval
                .unwrap_or(session::PING_INTERVAL)
                .max(std::time::Duration::from_millis(10)),
        });
        Ok(Self {
            state,
            render_thread,
        })
    }

    /// Serves until `shutdown` is cancelled, then drains sessions and stops the render thread.
    pub async fn run(self, listener: TcpListener) -> std::io::Result<()> {
        let Server {
            state,
            render_thread,
        } = self;
        let shutdown = state.shutdown.clone();
        let tracker = state.tracker.clone();
        let router = app(state.clone());
        let serve = axum::serve(listener, router)
            .with_graceful_shutdown(async move { shutdown.cancelled().await });
        let result = serve.await;
        tracker.close();
        tracker.wait().await;
        let _ = state.render.send(render_service::Command::Stop).await;
        let _ = tokio::task::spawn_blocking(move || render_thread.join()).await;
        tracing::info!("server stopped");
        result
    }
}
