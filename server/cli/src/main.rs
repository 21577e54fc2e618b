//! The `voxlight` binary: `serve`, `render`, `bench` and `loadgen`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};
use tokio_util::sync::CancellationToken;
use voxlight_app::{Server, ServerConfig, lifecycle, loadgen, offline};

#[derive(Parser)]
#[command(
    name = "voxlight",
    version,
    about = "Remote volume rendering with global illumination"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// Parsed once per run: the size of its largest variant (`bench`'s options) does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Serve the web viewer, /ws, /healthz and /api/datasets.
    Serve {
        #[arg(long, default_value = "127.0.0.1:8080")]
        listen: SocketAddr,
        /// Folder of volumes (DICOM series folders, .nrrd/.nhdr, .nii/.nii.gz, .vti).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Dataset opened when a client names none (default: phantom:cornell).
        #[arg(long)]
        default_dataset: Option<String>,
        /// Do not load every dataset in the background at start-up (then /api/datasets shows
        /// dims, range and histogram only for datasets opened so far).
        #[arg(long)]
        no_preload: bool,
        /// A token clients must present (`Authorization: Bearer` or the WebSocket subprotocol
        /// `voxlight.token.<token>`); repeat for several. None: no token needed.
        #[arg(long = "token")]
        tokens: Vec<String>,
        /// A file with one token per line (blank lines and `#` comments ignored).
        #[arg(long)]
        tokens_file: Option<PathBuf>,
        /// An origin besides the server's own whose pages may open sessions (repeatable).
        #[arg(long = "allow-origin")]
        allowed_origins: Vec<String>,
        /// Seconds a session is kept after its last viewer left, so a reconnecting client
        /// resumes it (and its converged picture).
        #[arg(long, default_value_t = 120)]
        grace_period_s: u64,
        /// GPU memory (MiB) all sessions and volumes together may use; a session that would
        /// exceed it is refused with `gpu_memory`.
        #[arg(long, default_value_t = voxlight_app::DEFAULT_GPU_MEMORY_BUDGET >> 20)]
        gpu_memory_mib: u64,
        /// Preview frame time (ms) the interaction mode picks its resolution scale for while
        /// edits stream in; 0 turns the interaction mode off (every edit goes straight to the
        /// technique at full resolution).
        #[arg(long, default_value_t = 60)]
        interactive_frame_ms: u64,
        /// Milliseconds without an edit after which input counts as stopped and the technique
        /// refines the still.
        #[arg(long, default_value_t = 250)]
        rest_after_ms: u64,
        /// Most sessions this process holds (those in their reconnect grace period included);
        /// the next new one gets `at_capacity` and `/readyz` answers 503. Joining a shared
        /// session is still allowed.
        #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..))]
        max_sessions: u32,
        /// The path prefix under which a router reaches this very process and strips before
        /// forwarding (e.g. `/p/3/` for StatefulSet pod 3); told to viewers so their share
        /// links and reconnects come back to the process that holds their session.
        #[arg(long)]
        route_prefix: Option<String>,
        /// On SIGTERM: seconds the open sessions are still served (no new ones) before every
        /// viewer gets `bye` and the process exits; it exits earlier once no viewer is left.
        /// A second SIGTERM or Ctrl-C stops at once.
        #[arg(long, default_value_t = 300)]
        drain_timeout_s: u64,
        /// GPU memory (MiB) one volume may take; a larger volume (or one over the GPU's 3D
        /// texture size) is rendered from a copy downsampled by the smallest factor that fits,
        /// and the viewer is told. Default: half of --gpu-memory-mib.
        #[arg(long)]
        max_volume_mib: Option<u64>,
        /// A PACS's DICOMweb root (e.g. https://pacs.example.org/dicom-web): its series are
        /// listed (QIDO-RS) at start-up and fetched (WADO-RS) when a viewer opens one.
        #[arg(long)]
        dicomweb: Option<String>,
        /// A file with the DICOMweb credentials: `user:password` or `Bearer <token>` (first
        /// line that is not blank or a `#` comment; never logged).
        #[arg(long, requires = "dicomweb")]
        dicomweb_credentials: Option<PathBuf>,
    },
    /// Scripted viewers against a running server: each session has an editor that orbits
    /// the camera and edits the TF, and watchers that join it. Reports input-to-frame
    /// latency, fps per viewer, bytes/s and errors.
    Loadgen {
        #[arg(long, default_value = "ws://127.0.0.1:8080/ws")]
        url: String,
        #[arg(long, default_value_t = 4)]
        sessions: u32,
        /// Viewers per session (the first one edits).
        #[arg(long, default_value_t = 1)]
        viewers: u32,
        /// Seconds to run.
        #[arg(long, default_value_t = 20.0)]
        duration: f64,
        #[arg(long, default_value_t = 512)]
        width: u32,
        #[arg(long, default_value_t = 512)]
        height: u32,
        #[arg(long)]
        dataset: Option<String>,
        #[arg(long)]
        technique: Option<String>,
        /// Technique options as JSON, e.g. `{"manylight":{"virtual_lights":1000}}` (sent in
        /// every session's `hello`; docs/protocol.md §4.5).
        #[arg(long)]
        technique_options: Option<String>,
        /// Sent as `Authorization: Bearer`.
        #[arg(long)]
        token: Option<String>,
        /// Camera edits per second per session.
        #[arg(long, default_value_t = 10.0)]
        edit_rate: f64,
        /// Seconds between TF edits.
        #[arg(long, default_value_t = 2.0)]
        tf_interval: f64,
        /// Extra sessions that nobody edits and that keep refining (scheduler check).
        #[arg(long, default_value_t = 0)]
        background_sessions: u32,
        /// Print one JSON object on the last line.
        #[arg(long)]
        json: bool,
    },
    /// Render a scene file to a PNG (and optionally a PFM of linear radiance).
    Render {
        #[arg(long)]
        scene: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        pfm: Option<PathBuf>,
    },
    /// Run a benchmark (`voxlight bench --help` lists them; docs/benchmarks.md has their
    /// results).
    Bench {
        #[command(subcommand)]
        bench: voxlight_bench::cli::Bench,
    },
}

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            // The whole cause chain on one line, without a backtrace: this is for users.
            eprintln!("voxlight: {error:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,wgpu_core=warn,wgpu_hal=warn,naga=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Serve {
            listen,
            data,
            default_dataset,
            no_preload,
            mut tokens,
            tokens_file,
            allowed_origins,
            grace_period_s,
            gpu_memory_mib,
            interactive_frame_ms,
            rest_after_ms,
            max_sessions,
            route_prefix,
            drain_timeout_s,
            max_volume_mib,
            dicomweb,
            dicomweb_credentials,
        } => {
            if let Some(file) = tokens_file {
                let text = std::fs::read_to_string(&file)
                    .with_context(|| format!("reading tokens file {}", file.display()))?;
                tokens.extend(
                    text.lines()
                        .map(str::trim)
                        .filter(|l| !l.is_empty() && !l.starts_with('#'))
                        .map(str::to_owned),
                );
            }
            serve(
                listen,
                ServerConfig {
                    data_dir: data,
                    default_dataset,
                    preload: !no_preload,
                    access: voxlight_app::auth::Access {
                        tokens,
                        allowed_origins,
                    },
                    grace_period: Some(Duration::from_secs(grace_period_s)),
                    gpu_memory_budget: Some(gpu_memory_mib.saturating_mul(1 << 20)),
                    interaction: Some(voxlight_app::render_service::Interaction {
                        enabled: interactive_frame_ms > 0,
                        frame_target: Duration::from_millis(interactive_frame_ms),
                        rest_after: Duration::from_millis(rest_after_ms),
                    }),
                    max_sessions: Some(max_sessions as usize),
                    route_prefix,
                    ping_interval: None,
                    max_volume_bytes: max_volume_mib.map(|m| m.saturating_mul(1 << 20)),
                    dicomweb: dicomweb.map(|url| voxlight_app::DicomWebSource {
                        url,
                        credentials: dicomweb_credentials,
                    }),
                },
                Duration::from_secs(drain_timeout_s),
            )
        }
        Command::Loadgen {
            url,
            sessions,
            viewers,
            duration,
            width,
            height,
            dataset,
            technique,
            technique_options,
            token,
            edit_rate,
            tf_interval,
            background_sessions,
            json,
        } => {
            let technique_options = technique_options
                .map(|text| serde_json::from_str(&text))
                .transpose()
                .context("--technique-options is not valid technique options JSON")?;
            let config = loadgen::LoadConfig {
                url,
                sessions,
                viewers,
                duration: Duration::try_from_secs_f64(duration)
                    .context("--duration must be a positive number of seconds")?,
                viewport: voxlight_protocol::Viewport { width, height },
                dataset,
                technique,
                technique_options,
                token,
                edit_rate,
                tf_interval: Duration::try_from_secs_f64(tf_interval)
                    .context("--tf-interval must be a positive number of seconds")?,
                background_sessions,
            };
            loadgen::validate(&config)?;
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .thread_name("voxlight-loadgen")
                .build()?;
            let report = runtime.block_on(loadgen::run(config))?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("{}", serde_json::to_string_pretty(&report)?);
            }
            Ok(())
        }
        Command::Render { scene, out, pfm } => offline::render(&scene, &out, pfm.as_deref()),
        Command::Bench { bench } => voxlight_bench::cli::run(&bench),
    }
}

fn serve(listen: SocketAddr, config: ServerConfig, drain_timeout: Duration) -> anyhow::Result<()> {
    let engine = voxlight_engine::Engine::new()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("voxlight-io")
        .build()?;
    runtime.block_on(async move {
        let shutdown = CancellationToken::new();
        let server = Server::start(&config, engine, shutdown.clone())?;
        let listener = tokio::net::TcpListener::bind(listen)
            .await
            .with_context(|| format!("cannot listen on {listen}"))?;
        tracing::info!("serving http://{}", listener.local_addr()?);
        let state = server.state.clone();
        tokio::spawn(async move {
            wait_for_signal().await;
            tracing::info!("SIGTERM or Ctrl-C: draining (again to stop at once)");
            tokio::select! {
                _ = lifecycle::drain(&state, drain_timeout) => {}
                _ = wait_for_signal() => tracing::info!("second signal: stopping now"),
            }
            tracing::info!("shutting down");
            shutdown.cancel();
        });
        server.run(listener).await?;
        Ok(())
    })
}

async fn wait_for_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(term) => term,
                Err(_) => {
                    let _ = ctrl_c.await;
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}
