//! The `voxlight` binary: `serve`, `render`, `bench` and `loadgen`.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Parser, Subcommand};
use tokio_util::sync::CancellationToken;
use voxlight_app::{Server, ServerConfig, lifecycle, loadgen, offline};
use voxlight_bench::{
    engine as bench, interactive as bench_interactive, irradiance as bench_irradiance,
    manylight as bench_manylight,
};
use voxlight_engine::techniques::irradiance::{DEFAULT_BOUNCES, Historygrams};

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
    /// Run a benchmark (`raymarch`, `preview`, `preview-vtk`, `interactive`, `tf-edit`,
    /// `manylight`, `convergence`, `load`).
    Bench {
        name: String,
        /// Technique measured by `tf-edit`.
        #[arg(long, default_value = "photon")]
        technique: String,
        /// `tf-edit`: image edge in pixels.
        #[arg(long, default_value_t = 96)]
        size: u32,
        /// `tf-edit`: largest volume edge after downsampling.
        #[arg(long, default_value_t = 96)]
        max_dim: u32,
        /// `tf-edit`: photon paths per pass.
        #[arg(long, default_value_t = 16384)]
        photons: u32,
        /// `tf-edit`: photon passes in the map.
        #[arg(long, default_value_t = 4)]
        passes: u32,
        /// `tf-edit --technique photon`: scattering events stored per photon path (default 2);
        /// `convergence`, `tf-edit --technique irradiance`: most scattering events on a camera
        /// path (default 1024; 1 is the paper's single scattering).
        #[arg(long)]
        bounces: Option<u32>,
        /// `tf-edit`: view-ray segments per pixel.
        #[arg(long, default_value_t = 8)]
        segments: u32,
        /// `tf-edit`: timed repetitions of each edit (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: u32,
        /// `tf-edit --technique photon`: instead of timing the update, count the full
        /// recompute's work per photon record under the old and the new TF, and report the
        /// least any bit-exact update must redo and the highest speedup that leaves.
        #[arg(long)]
        census: bool,
        /// `convergence`: instead of running the cache, measure the most any cache of the
        /// indirect light could gain (plain MCVR with and without its indirect light).
        #[arg(long)]
        ceiling: bool,
        /// Print one JSON object on the last line.
        #[arg(long)]
        json: bool,
        /// Data folder (default: ../shared/data when found).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Image edges to measure.
        #[arg(long, value_delimiter = ',', default_value = "512,1024")]
        sizes: Vec<u32>,
        /// Timed iterations per size.
        #[arg(long, default_value_t = 8)]
        iterations: u32,
        /// `manylight`: virtual-light counts to measure.
        #[arg(long, value_delimiter = ',', default_value = "64,128,256,512")]
        vls: Vec<u32>,
        /// `manylight`: AVSM texels per cube-face edge.
        #[arg(long, default_value_t = 24)]
        face_res: u32,
        /// `manylight`: AVSM nodes per texel.
        #[arg(long, default_value_t = 8)]
        nodes: u32,
        /// `manylight`, `convergence`, `tf-edit --technique irradiance`: samples per pixel of
        /// the reference (defaults 64, 1024, 512).
        #[arg(long)]
        reference_spp: Option<u32>,
        /// `convergence`, `tf-edit --technique irradiance`: frames measured per run (defaults
        /// 200 and 40).
        #[arg(long)]
        frames: Option<u32>,
        /// `convergence`: light setups (1, 3, 4 lights as in the paper's Table 2).
        #[arg(long, value_delimiter = ',', default_value = "1,3,4")]
        lights: Vec<u32>,
        /// `convergence`: datasets of ../shared/data (default bonsai,chest,engine);
        /// `preview-vtk`: those of VTK's baseline (default bonsai,ct); `load`: paths under the
        /// data folder (default the chest series, bonsai, tooth.nhdr, example_ct.nii.gz).
        #[arg(long, value_delimiter = ',')]
        datasets: Option<Vec<String>>,
        /// `convergence`, `tf-edit --technique irradiance`: largest cache-zone radius in voxels
        /// (the technique's default when absent).
        #[arg(long)]
        max_radius: Option<f32>,
        /// `convergence`, `tf-edit --technique irradiance`: γ, the accepted relative error of
        /// an entry's estimate (the technique's default when absent).
        #[arg(long)]
        gamma: Option<f32>,
        /// `convergence`: write each case's pictures (PNG) to this folder.
        #[arg(long)]
        dump: Option<PathBuf>,
        /// `convergence`, `tf-edit --technique irradiance`: how camera rays find their
        /// scattering event, for plain MCVR and the cache alike: `marched` (picked along a
        /// jittered march, the default) or `tracked` (delta tracking, as Exposure Render).
        #[arg(long, default_value = "marched")]
        view_event: String,
        /// `convergence`, `tf-edit --technique irradiance`: the update also checks the entries
        /// at its point against a fresh estimate there (beyond the paper).
        #[arg(long)]
        validate_hits: bool,
        /// `tf-edit --technique irradiance`: frames that build the cache before each edit.
        #[arg(long, default_value_t = 120)]
        build_frames: u32,
        /// `tf-edit --technique irradiance`: what entries' historygrams record (`samples` or
        /// `cells`).
        #[arg(long, default_value = "samples")]
        historygrams: String,
        /// `convergence`, `tf-edit --technique irradiance`: what cache entries hold: `indirect`
        /// (the default: the render pass traces the lights' direct light) or `all` (the paper).
        #[arg(long, default_value = "indirect")]
        cached_light: String,
        /// `convergence`, `tf-edit --technique irradiance`: scattering events per camera sample
        /// along the marched view ray, for plain MCVR and the cache alike (the technique's
        /// default when absent).
        #[arg(long)]
        view_picks: Option<u32>,
        /// `interactive`: the running server's WebSocket endpoint; without it the bench starts
        /// one in this process on loopback (interaction mode on, `serve`'s defaults).
        #[arg(long)]
        url: Option<String>,
        /// `interactive`: techniques to drag with (default raymarch,photon,manylight,irradiance).
        #[arg(long, value_delimiter = ',')]
        techniques: Option<Vec<String>>,
        /// `interactive`: viewports, `WxH` or one edge.
        #[arg(long, value_delimiter = ',', default_value = "512x512,1024x768")]
        viewports: Vec<String>,
        /// `interactive`: the dataset (the server's default when absent).
        #[arg(long)]
        dataset: Option<String>,
        /// `interactive`: edits in the scripted drag (every 4th a TF edit, the rest 3° turns).
        #[arg(long, default_value_t = 24)]
        edits: u32,
        /// `interactive`: edits per second while dragging.
        #[arg(long, default_value_t = 8.0)]
        edit_rate: f64,
        /// `interactive`: progressive iterations of the still (sent as `quality`).
        #[arg(long, default_value_t = 4)]
        still_iterations: u32,
        /// `interactive`: longest wait (s) for the still after the drag.
        #[arg(long, default_value_t = 600.0)]
        still_timeout_s: f64,
        /// `interactive`: start the drag at the session's first technique frame, while it
        /// converges, instead of after its first still.
        #[arg(long)]
        drag_while_converging: bool,
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
        Command::Bench {
            name,
            technique,
            size,
            max_dim,
            photons,
            passes,
            bounces,
            segments,
            repeats,
            census,
            ceiling,
            json,
            data,
            sizes,
            iterations,
            vls,
            face_res,
            nodes,
            reference_spp,
            frames,
            lights,
            datasets,
            build_frames,
            historygrams,
            dump,
            max_radius,
            gamma,
            view_event,
            validate_hits,
            cached_light,
            view_picks,
            url,
            techniques,
            viewports,
            dataset,
            edits,
            edit_rate,
            still_iterations,
            still_timeout_s,
            drag_while_converging,
        } => {
            use voxlight_engine::techniques::irradiance::{CachedLight, ViewEvent};
            let cached_light = match cached_light.as_str() {
                "indirect" => CachedLight::Indirect,
                "all" => CachedLight::All,
                other => {
                    anyhow::bail!("--cached-light must be `indirect` or `all`, got `{other}`")
                }
            };
            let view_event = match view_event.as_str() {
                "marched" => ViewEvent::Marched,
                "tracked" => ViewEvent::DeltaTracking,
                other => {
                    anyhow::bail!("--view-event must be `marched` or `tracked`, got `{other}`")
                }
            };
            let irradiance_config = voxlight_engine::techniques::irradiance::IrradianceConfig {
                view_event,
                validate_hits,
                cached_light,
                view_picks: view_picks.unwrap_or(
                    voxlight_engine::techniques::irradiance::IrradianceConfig::default().view_picks,
                ),
                gamma: gamma.unwrap_or(
                    voxlight_engine::techniques::irradiance::IrradianceConfig::default().gamma,
                ),
                max_radius_voxels: max_radius.unwrap_or(
                    voxlight_engine::techniques::irradiance::IrradianceConfig::default()
                        .max_radius_voxels,
                ),
                ..Default::default()
            };
            let data = data.or_else(voxlight_volumes::testdata::shared_data_dir);
            let result = match name.as_str() {
                "raymarch" => bench::raymarch(&bench::RaymarchBench {
                    data_dir: data.as_deref(),
                    sizes: &sizes,
                    iterations: iterations.max(1),
                })?,
                "tf-edit" => {
                    let scenarios = bench::TfEditBench {
                        data_dir: data.as_deref(),
                        technique: &technique,
                        size: size.max(1),
                        max_dim: max_dim.max(8),
                        photons_per_pass: photons.max(1),
                        passes: passes.max(1),
                        bounces: bounces.unwrap_or(2).max(1),
                        segments: segments.max(1),
                        repeats: repeats.max(1),
                        census,
                    };
                    if technique == "irradiance" {
                        if census {
                            anyhow::bail!("--census counts the work of `photon`'s TF updates");
                        }
                        let historygrams = match historygrams.as_str() {
                            "samples" => Historygrams::Samples,
                            "cells" => Historygrams::Cells,
                            other => anyhow::bail!(
                                "--historygrams is `samples` or `cells`, not `{other}`"
                            ),
                        };
                        bench_irradiance::tf_edit(&bench_irradiance::IrradianceTfEditBench {
                            scenarios: bench::TfEditBench {
                                bounces: bounces.unwrap_or(DEFAULT_BOUNCES).max(1),
                                ..scenarios
                            },
                            build_frames: build_frames.max(1),
                            frames: frames.unwrap_or(40).max(1),
                            reference_spp: reference_spp.unwrap_or(512).max(2),
                            historygrams,
                            config: irradiance_config,
                        })?
                    } else {
                        bench::tf_edit(&scenarios)?
                    }
                }
                "convergence" => {
                    let datasets = datasets.clone().unwrap_or_else(|| {
                        ["bonsai", "chest", "engine"].map(str::to_owned).to_vec()
                    });
                    bench_irradiance::convergence(&bench_irradiance::ConvergenceBench {
                        data_dir: data.as_deref(),
                        size: size.max(8),
                        max_dim: max_dim.max(8),
                        frames: frames.unwrap_or(200).max(1),
                        reference_spp: reference_spp.unwrap_or(1024).max(2),
                        lights: &lights,
                        datasets: &datasets,
                        bounces: bounces.unwrap_or(DEFAULT_BOUNCES).max(1),
                        dump: dump.as_deref(),
                        config: irradiance_config,
                        ceiling,
                    })?
                }
                "manylight" => bench_manylight::manylight(&bench_manylight::ManylightBench {
                    data_dir: data.as_deref(),
                    size: size.max(8),
                    vls: &vls,
                    face_res: face_res.max(1),
                    nodes,
                    iterations: iterations.max(1),
                    reference_spp: reference_spp.unwrap_or(64).max(1),
                })?,
                "preview" => bench::preview(&bench::RaymarchBench {
                    data_dir: data.as_deref(),
                    sizes: &sizes,
                    iterations: iterations.max(1),
                })?,
                "preview-vtk" => {
                    let vtk_datasets = datasets
                        .clone()
                        .unwrap_or_else(|| vec!["bonsai".to_owned(), "ct".to_owned()]);
                    voxlight_bench::vtk::preview_vtk(&voxlight_bench::vtk::PreviewVtkBench {
                        data_dir: data.as_deref(),
                        sizes: &sizes,
                        frames: iterations.max(1),
                        datasets: &vtk_datasets,
                    })?
                }
                "interactive" => {
                    let viewports = viewports
                        .iter()
                        .map(|v| bench_interactive::parse_viewport(v))
                        .collect::<anyhow::Result<Vec<_>>>()?;
                    let techniques = techniques.unwrap_or_else(|| {
                        ["raymarch", "photon", "manylight", "irradiance"]
                            .map(str::to_owned)
                            .to_vec()
                    });
                    let bench = bench_interactive::InteractiveBench {
                        url: url.unwrap_or_default(),
                        techniques,
                        viewports,
                        dataset,
                        edits,
                        edit_rate,
                        still_iterations,
                        still_timeout: Duration::try_from_secs_f64(still_timeout_s)
                            .context("--still-timeout-s must be a positive number of seconds")?,
                        drag_while_converging,
                    };
                    serde_json::to_value(interactive(bench, data.clone())?)?
                }
                "load" => {
                    let data = data
                        .clone()
                        .context("bench load reads ../shared/data (or --data DIR); none found")?;
                    let load_datasets = datasets.clone().unwrap_or_else(|| {
                        [
                            "ct-chest-lidc",
                            "vti/bonsai.vti",
                            "nrrd/tooth.nhdr",
                            "nifti/example_ct.nii.gz",
                        ]
                        .map(str::to_owned)
                        .to_vec()
                    });
                    let bench = voxlight_bench::load::LoadBench {
                        data_dir: &data,
                        datasets: &load_datasets,
                        repeats,
                    };
                    if voxlight_bench::load::child(&bench)? {
                        return Ok(());
                    }
                    voxlight_bench::load::load(&bench)?
                }
                other => anyhow::bail!(
                    "unknown benchmark `{other}`; available: raymarch, preview, preview-vtk, interactive, tf-edit, manylight, convergence, load"
                ),
            };
            if json {
                println!("{result}");
            } else {
                println!("{}", serde_json::to_string_pretty(&result)?);
            }
            Ok(())
        }
    }
}

/// `bench interactive` against `bench.url`, or against a server started here on loopback.
fn interactive(
    mut bench: bench_interactive::InteractiveBench,
    data: Option<PathBuf>,
) -> anyhow::Result<bench_interactive::InteractiveReport> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("voxlight-io")
        .build()?;
    runtime.block_on(async move {
        if !bench.url.is_empty() {
            return bench_interactive::run(&bench).await;
        }
        let engine = voxlight_engine::Engine::new()?;
        let shutdown = CancellationToken::new();
        let config = ServerConfig {
            data_dir: data,
            preload: false,
            interaction: Some(voxlight_app::render_service::Interaction::default()),
            ..ServerConfig::default()
        };
        let server = Server::start(&config, engine, shutdown.clone())?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        bench.url = format!("ws://{}/ws", listener.local_addr()?);
        let serving = tokio::spawn(server.run(listener));
        let report = bench_interactive::run(&bench).await;
        shutdown.cancel();
        serving.await??;
        report
    })
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
