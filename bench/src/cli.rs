//! `voxlight bench <name>`: one clap subcommand and one `Args` struct per benchmark, with the
//! defaults `docs/benchmarks.md` quotes.
//!
//! - Every benchmark prints its result as pretty JSON, or as one JSON line with `--json`.
//! - `--data` is the data folder (`../shared/data` when found).

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Subcommand, ValueEnum};
use tokio_util::sync::CancellationToken;
use voxlight_app::{Server, ServerConfig};
use voxlight_engine::techniques::irradiance::{
    CachedLight, DEFAULT_BOUNCES, Historygrams, IrradianceConfig, ViewEvent,
};

use crate::{engine, interactive, irradiance, load, manylight, vtk};

/// The benchmarks.
#[derive(Debug, Subcommand)]
pub enum Bench {
    /// Raymarch frame time at each image size.
    Raymarch(SizesArgs),
    /// The interaction-mode preview's frame time at each image size.
    Preview(SizesArgs),
    /// The full-resolution preview beside VTK's FixedPoint ray caster (offscreen, one run).
    PreviewVtk(PreviewVtkArgs),
    /// Incremental TF updates against full recomputes (`photon`, `irradiance`).
    TfEdit(TfEditArgs),
    /// `manylight`: AVSM against ray-marched transmittance; rebuilds after edits.
    Manylight(ManylightArgs),
    /// `irradiance` against plain Monte Carlo at equal time (the paper's Table 2).
    Convergence(ConvergenceArgs),
    /// `irradiance` across a camera orbit: the cache kept against a cleared one at equal time
    /// (the paper's Fig. 10).
    Orbit(OrbitArgs),
    /// A scripted drag against a server: input to frame, frame rate, the still.
    Interactive(InteractiveArgs),
    /// Time and peak host memory of loading each dataset.
    Load(LoadArgs),
}

/// Options every benchmark takes.
#[derive(Debug, Args)]
pub struct Common {
    /// Print one JSON object on the last line.
    #[arg(long)]
    pub json: bool,
    /// Data folder (default: ../shared/data when found).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

impl Common {
    fn data_dir(&self) -> Option<PathBuf> {
        self.data
            .clone()
            .or_else(voxlight_volumes::testdata::shared_data_dir)
    }
}

#[derive(Debug, Args)]
pub struct SizesArgs {
    #[command(flatten)]
    pub common: Common,
    /// Image edges to measure.
    #[arg(long, value_delimiter = ',', default_value = "512,1024")]
    pub sizes: Vec<u32>,
    /// Timed iterations per size.
    #[arg(long, default_value_t = 8)]
    pub iterations: u32,
}

#[derive(Debug, Args)]
pub struct PreviewVtkArgs {
    /// `--iterations`: timed frames per size and divisor.
    #[command(flatten)]
    pub sizes: SizesArgs,
    /// VTK baseline datasets (`bonsai`, `ct`).
    #[arg(long, value_delimiter = ',', default_value = "bonsai,ct")]
    pub datasets: Vec<String>,
}

/// The techniques whose TF updates `tf-edit` measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TfEditTechnique {
    Photon,
    Irradiance,
}

/// Where camera rays find their scattering event (`irradiance`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ViewEventArg {
    /// Picked along a jittered march.
    Marched,
    /// Delta tracking, as Exposure Render.
    Tracked,
}

/// What `irradiance`'s cache entries hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum CachedLightArg {
    /// The indirect light (the render pass traces the lights' direct light).
    Indirect,
    /// All light, direct included (the paper).
    All,
}

/// What `irradiance`'s entry historygrams record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum HistogramsArg {
    Samples,
    Cells,
}

/// `irradiance`'s options that `convergence` and `tf-edit --technique irradiance` share.
#[derive(Debug, Args)]
pub struct IrradianceArgs {
    /// Largest cache-zone radius in voxels (the technique's default when absent).
    #[arg(long)]
    pub max_radius: Option<f32>,
    /// γ, the accepted relative error of an entry's estimate (the technique's default when
    /// absent).
    #[arg(long)]
    pub gamma: Option<f32>,
    /// How camera rays find their scattering event, for plain MCVR and the cache alike.
    #[arg(long, value_enum, default_value = "marched")]
    pub view_event: ViewEventArg,
    /// The update also checks the entries at its point against a fresh estimate there.
    #[arg(long)]
    pub validate_hits: bool,
    /// Share of each frame for validation rounds of their own (beyond the paper; 0: none):
    /// each checks one point per 16 × 8 block, as `--validate-hits` does within the update.
    #[arg(long, default_value_t = 0.0)]
    pub validation_share: f32,
    /// Validation rounds: relative disagreement (beyond the fresh estimate's 95% interval)
    /// that shrinks an entry.
    #[arg(long, default_value_t = 0.1)]
    pub validation_threshold: f32,
    /// Validation rounds: irradiance samples of each fresh estimate.
    #[arg(long, default_value_t = 8)]
    pub validation_samples: u32,
    /// What cache entries hold.
    #[arg(long, value_enum, default_value = "indirect")]
    pub cached_light: CachedLightArg,
    /// Scattering events per camera sample along the marched view ray (the technique's
    /// default when absent).
    #[arg(long)]
    pub view_picks: Option<u32>,
}

impl IrradianceArgs {
    fn config(&self) -> IrradianceConfig {
        let defaults = IrradianceConfig::default();
        IrradianceConfig {
            view_event: match self.view_event {
                ViewEventArg::Marched => ViewEvent::Marched,
                ViewEventArg::Tracked => ViewEvent::DeltaTracking,
            },
            validate_hits: self.validate_hits,
            validation_fraction: self.validation_share,
            validation_threshold: self.validation_threshold,
            validation_samples: self.validation_samples,
            cached_light: match self.cached_light {
                CachedLightArg::Indirect => CachedLight::Indirect,
                CachedLightArg::All => CachedLight::All,
            },
            view_picks: self.view_picks.unwrap_or(defaults.view_picks),
            gamma: self.gamma.unwrap_or(defaults.gamma),
            max_radius_voxels: self.max_radius.unwrap_or(defaults.max_radius_voxels),
            ..defaults
        }
    }
}

#[derive(Debug, Args)]
pub struct TfEditArgs {
    #[command(flatten)]
    pub common: Common,
    /// The technique measured.
    #[arg(long, value_enum, default_value = "photon")]
    pub technique: TfEditTechnique,
    /// Image edge in pixels.
    #[arg(long, default_value_t = 96)]
    pub size: u32,
    /// Largest volume edge after downsampling.
    #[arg(long, default_value_t = 96)]
    pub max_dim: u32,
    /// `photon`: photon paths per pass.
    #[arg(long, default_value_t = 16384)]
    pub photons: u32,
    /// `photon`: photon passes in the map.
    #[arg(long, default_value_t = 4)]
    pub passes: u32,
    /// `photon`: scattering events stored per photon path (default 2); `irradiance`: most
    /// scattering events on a camera path (default 1024; 1 is the paper's single scattering).
    #[arg(long)]
    pub bounces: Option<u32>,
    /// `photon`: view-ray segments per pixel.
    #[arg(long, default_value_t = 8)]
    pub segments: u32,
    /// Timed repetitions of each edit (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub repeats: u32,
    /// `photon`: instead of timing the update, count the full recompute's work per photon
    /// record under the old and the new TF, and report the least any bit-exact update must
    /// redo and the highest speedup that leaves.
    #[arg(long)]
    pub census: bool,
    /// `photon`: segments sum every photon's weighted term (the formulation without per-sample
    /// photon sums), to compare the two in one build.
    #[arg(long)]
    pub segment_sums: bool,
    /// The scenarios measured (default: all of cornell, engine and chest).
    #[arg(long, value_delimiter = ',')]
    pub scenarios: Vec<String>,
    /// `irradiance`: frames that build the cache before each edit.
    #[arg(long, default_value_t = 120)]
    pub build_frames: u32,
    /// `irradiance`: frames measured after each edit.
    #[arg(long, default_value_t = 40)]
    pub frames: u32,
    /// `irradiance`: samples per pixel of the reference.
    #[arg(long, default_value_t = 512)]
    pub reference_spp: u32,
    /// `irradiance`: what entries' historygrams record.
    #[arg(long, value_enum, default_value = "samples")]
    pub historygrams: HistogramsArg,
    #[command(flatten)]
    pub irradiance: IrradianceArgs,
}

#[derive(Debug, Args)]
pub struct ManylightArgs {
    #[command(flatten)]
    pub common: Common,
    /// Image edge in pixels.
    #[arg(long, default_value_t = 96)]
    pub size: u32,
    /// Virtual-light counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "64,128,256,512")]
    pub vls: Vec<u32>,
    /// AVSM texels per cube-face edge.
    #[arg(long, default_value_t = 24)]
    pub face_res: u32,
    /// AVSM nodes per texel.
    #[arg(long, default_value_t = 8)]
    pub nodes: u32,
    /// Gather passes timed per mode.
    #[arg(long, default_value_t = 8)]
    pub iterations: u32,
    /// Samples per pixel of the `pathtrace` reference.
    #[arg(long, default_value_t = 64)]
    pub reference_spp: u32,
}

#[derive(Debug, Args)]
pub struct ConvergenceArgs {
    #[command(flatten)]
    pub common: Common,
    /// Image edge in pixels.
    #[arg(long, default_value_t = 96)]
    pub size: u32,
    /// Largest volume edge after downsampling.
    #[arg(long, default_value_t = 96)]
    pub max_dim: u32,
    /// Frames each of plain MCVR and the cache runs.
    #[arg(long, default_value_t = 200)]
    pub frames: u32,
    /// Samples per pixel of the reference.
    #[arg(long, default_value_t = 1024)]
    pub reference_spp: u32,
    /// Light setups (1, 3, 4 lights as in the paper's Table 2).
    #[arg(long, value_delimiter = ',', default_value = "1,3,4")]
    pub lights: Vec<u32>,
    /// Datasets of ../shared/data.
    #[arg(long, value_delimiter = ',', default_value = "bonsai,chest,engine")]
    pub datasets: Vec<String>,
    /// Most scattering events on a camera path (1 is the paper's single scattering).
    #[arg(long, default_value_t = DEFAULT_BOUNCES)]
    pub bounces: u32,
    /// Write each case's pictures (PNG) to this folder.
    #[arg(long)]
    pub dump: Option<PathBuf>,
    /// Instead of running the cache, measure the most any cache of the indirect light could
    /// gain (plain MCVR with and without its indirect light).
    #[arg(long)]
    pub ceiling: bool,
    #[command(flatten)]
    pub irradiance: IrradianceArgs,
}

#[derive(Debug, Args)]
pub struct OrbitArgs {
    #[command(flatten)]
    pub common: Common,
    /// Image edge in pixels.
    #[arg(long, default_value_t = 96)]
    pub size: u32,
    /// Largest volume edge after downsampling.
    #[arg(long, default_value_t = 64)]
    pub max_dim: u32,
    /// Frames that build the cache from the first view (at plain MCVR's frame time there).
    #[arg(long, default_value_t = 200)]
    pub build_frames: u32,
    /// Frames measured after the orbit, at equal time per frame.
    #[arg(long, default_value_t = 100)]
    pub frames: u32,
    /// Samples per pixel of each turned view's reference.
    #[arg(long, default_value_t = 512)]
    pub reference_spp: u32,
    /// Orbits in degrees about the camera's up axis through the volume's centre.
    #[arg(long, value_delimiter = ',', default_value = "30,90")]
    pub angles: Vec<f32>,
    /// Light setups (1, 3, 4 lights as in `convergence`).
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub lights: Vec<u32>,
    /// Datasets of ../shared/data.
    #[arg(long, value_delimiter = ',', default_value = "bonsai,chest,engine")]
    pub datasets: Vec<String>,
    /// Most scattering events on a camera path (1 is the paper's single scattering).
    #[arg(long, default_value_t = DEFAULT_BOUNCES)]
    pub bounces: u32,
    #[command(flatten)]
    pub irradiance: IrradianceArgs,
}

#[derive(Debug, Args)]
pub struct InteractiveArgs {
    #[command(flatten)]
    pub common: Common,
    /// The running server's WebSocket endpoint; without it the bench starts one in this
    /// process on loopback (interaction mode on, `serve`'s defaults).
    #[arg(long)]
    pub url: Option<String>,
    /// Techniques to drag with.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "raymarch,photon,manylight,irradiance"
    )]
    pub techniques: Vec<String>,
    /// Viewports, `WxH` or one edge.
    #[arg(long, value_delimiter = ',', default_value = "512x512,1024x768")]
    pub viewports: Vec<String>,
    /// The dataset (the server's default when absent).
    #[arg(long)]
    pub dataset: Option<String>,
    /// Edits in the scripted drag (every 4th a TF edit, the rest 3° turns).
    #[arg(long, default_value_t = 24)]
    pub edits: u32,
    /// Edits per second while dragging.
    #[arg(long, default_value_t = 8.0)]
    pub edit_rate: f64,
    /// Progressive iterations of the still (sent as `quality`).
    #[arg(long, default_value_t = 4)]
    pub still_iterations: u32,
    /// Longest wait (s) for the still after the drag.
    #[arg(long, default_value_t = 600.0)]
    pub still_timeout_s: f64,
    /// Start the drag at the session's first technique frame, while it converges, instead of
    /// after its first still.
    #[arg(long)]
    pub drag_while_converging: bool,
}

#[derive(Debug, Args)]
pub struct LoadArgs {
    #[command(flatten)]
    pub common: Common,
    /// Paths under the data folder.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "ct-chest-lidc,vti/bonsai.vti,nrrd/tooth.nhdr,nifti/example_ct.nii.gz"
    )]
    pub datasets: Vec<String>,
    /// Loads per dataset, each in a fresh process (the median time and the largest peak).
    #[arg(long, default_value_t = 5)]
    pub repeats: u32,
}

impl Bench {
    fn common(&self) -> &Common {
        match self {
            Bench::Raymarch(a) | Bench::Preview(a) => &a.common,
            Bench::PreviewVtk(a) => &a.sizes.common,
            Bench::TfEdit(a) => &a.common,
            Bench::Manylight(a) => &a.common,
            Bench::Convergence(a) => &a.common,
            Bench::Orbit(a) => &a.common,
            Bench::Interactive(a) => &a.common,
            Bench::Load(a) => &a.common,
        }
    }
}

/// Runs a benchmark and prints its result.
pub fn run(bench: &Bench) -> anyhow::Result<()> {
    let common = bench.common();
    let data = common.data_dir();
    let result = match bench {
        Bench::Raymarch(a) => engine::raymarch(&engine::RaymarchBench {
            data_dir: data.as_deref(),
            sizes: &a.sizes,
            iterations: a.iterations.max(1),
        })?,
        Bench::Preview(a) => engine::preview(&engine::RaymarchBench {
            data_dir: data.as_deref(),
            sizes: &a.sizes,
            iterations: a.iterations.max(1),
        })?,
        Bench::PreviewVtk(a) => vtk::preview_vtk(&vtk::PreviewVtkBench {
            data_dir: data.as_deref(),
            sizes: &a.sizes.sizes,
            frames: a.sizes.iterations.max(1),
            datasets: &a.datasets,
        })?,
        Bench::TfEdit(a) => tf_edit(a, data.as_deref())?,
        Bench::Manylight(a) => manylight::manylight(&manylight::ManylightBench {
            data_dir: data.as_deref(),
            size: a.size.max(8),
            vls: &a.vls,
            face_res: a.face_res.max(1),
            nodes: a.nodes,
            iterations: a.iterations.max(1),
            reference_spp: a.reference_spp.max(1),
        })?,
        Bench::Convergence(a) => irradiance::convergence(&irradiance::ConvergenceBench {
            data_dir: data.as_deref(),
            size: a.size.max(8),
            max_dim: a.max_dim.max(8),
            frames: a.frames.max(1),
            reference_spp: a.reference_spp.max(2),
            lights: &a.lights,
            datasets: &a.datasets,
            bounces: a.bounces.max(1),
            dump: a.dump.as_deref(),
            config: a.irradiance.config(),
            ceiling: a.ceiling,
        })?,
        Bench::Orbit(a) => irradiance::orbit(&irradiance::OrbitBench {
            data_dir: data.as_deref(),
            size: a.size.max(8),
            max_dim: a.max_dim.max(8),
            build_frames: a.build_frames.max(1),
            frames: a.frames.max(1),
            reference_spp: a.reference_spp.max(2),
            lights: &a.lights,
            datasets: &a.datasets,
            angles: &a.angles,
            bounces: a.bounces.max(1),
            config: a.irradiance.config(),
        })?,
        Bench::Interactive(a) => serde_json::to_value(run_interactive(a, data)?)?,
        Bench::Load(a) => {
            let data =
                data.context("bench load reads ../shared/data (or --data DIR); none found")?;
            let bench = load::LoadBench {
                data_dir: &data,
                datasets: &a.datasets,
                repeats: a.repeats,
            };
            if load::child(&bench)? {
                return Ok(());
            }
            load::load(&bench)?
        }
    };
    if common.json {
        println!("{result}");
    } else {
        println!("{}", serde_json::to_string_pretty(&result)?);
    }
    Ok(())
}

fn tf_edit(a: &TfEditArgs, data: Option<&Path>) -> anyhow::Result<serde_json::Value> {
    let scenarios = engine::TfEditBench {
        data_dir: data,
        technique: match a.technique {
            TfEditTechnique::Photon => "photon",
            TfEditTechnique::Irradiance => "irradiance",
        },
        size: a.size.max(1),
        max_dim: a.max_dim.max(8),
        photons_per_pass: a.photons.max(1),
        passes: a.passes.max(1),
        bounces: a.bounces.unwrap_or(2).max(1),
        segments: a.segments.max(1),
        repeats: a.repeats.max(1),
        census: a.census,
        segment_sums: a.segment_sums,
        scenarios: &a.scenarios,
    };
    match a.technique {
        TfEditTechnique::Photon => engine::tf_edit(&scenarios),
        TfEditTechnique::Irradiance => {
            if a.census {
                anyhow::bail!("--census counts the work of `photon`'s TF updates");
            }
            irradiance::tf_edit(&irradiance::IrradianceTfEditBench {
                scenarios: engine::TfEditBench {
                    bounces: a.bounces.unwrap_or(DEFAULT_BOUNCES).max(1),
                    ..scenarios
                },
                build_frames: a.build_frames.max(1),
                frames: a.frames.max(1),
                reference_spp: a.reference_spp.max(2),
                historygrams: match a.historygrams {
                    HistogramsArg::Samples => Historygrams::Samples,
                    HistogramsArg::Cells => Historygrams::Cells,
                },
                config: a.irradiance.config(),
            })
        }
    }
}

/// `bench interactive` against `--url`, or against a server started here on loopback.
fn run_interactive(
    a: &InteractiveArgs,
    data: Option<PathBuf>,
) -> anyhow::Result<interactive::InteractiveReport> {
    let viewports = a
        .viewports
        .iter()
        .map(|v| interactive::parse_viewport(v))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut bench = interactive::InteractiveBench {
        url: a.url.clone().unwrap_or_default(),
        techniques: a.techniques.clone(),
        viewports,
        dataset: a.dataset.clone(),
        edits: a.edits,
        edit_rate: a.edit_rate,
        still_iterations: a.still_iterations,
        still_timeout: Duration::try_from_secs_f64(a.still_timeout_s)
            .context("--still-timeout-s must be a positive number of seconds")?,
        drag_while_converging: a.drag_while_converging,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("voxlight-io")
        .build()?;
    runtime.block_on(async move {
        if !bench.url.is_empty() {
            return interactive::run(&bench).await;
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
        let report = interactive::run(&bench).await;
        shutdown.cancel();
        serving.await??;
        report
    })
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    use super::*;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(subcommand)]
        bench: Bench,
    }

    fn parse(line: &str) -> Result<Bench, clap::Error> {
        Cli::try_parse_from(std::iter::once("bench").chain(line.split_whitespace()))
            .map(|c| c.bench)
    }

    #[test]
    fn documented_command_lines_parse() {
        for line in [
            "raymarch --json --iterations 4",
            "preview --sizes 512",
            "preview-vtk --datasets bonsai,ct --sizes 64 --iterations 1",
            "tf-edit --technique photon --census --json",
            "tf-edit --technique irradiance --build-frames 120 --frames 40 --historygrams cells",
            "manylight --vls 256 --json",
            "convergence --ceiling --max-dim 64 --json",
            "convergence --max-dim 64 --reference-spp 512 --cached-light all --view-event tracked",
            "orbit --angles 0,30,90 --datasets chest --lights 1,3 --frames 50 --json",
            "interactive --url ws://127.0.0.1:8391/ws --dataset vti/bonsai.vti --techniques raymarch",
            "load --data /tmp/loadbench --datasets float256.nrrd,int256.nrrd",
        ] {
            parse(line).unwrap_or_else(|e| panic!("`{line}`: {e}"));
        }
    }

    #[test]
    fn a_flag_of_another_bench_or_an_unknown_choice_is_refused() {
        assert!(parse("load --census").is_err());
        assert!(parse("tf-edit --technique manylight").is_err());
        assert!(parse("convergence --view-event sideways").is_err());
        assert!(parse("orbit --ceiling").is_err());
        assert!(parse("orbit --angles left").is_err());
        assert!(parse("nosuchbench").is_err());
    }

    #[test]
    fn defaults_are_the_documented_ones() {
        let Bench::Load(load) = parse("load").expect("load") else {
            panic!("load")
        };
        assert_eq!(load.repeats, 5);
        assert_eq!(load.datasets.len(), 4);
        let Bench::Convergence(c) = parse("convergence").expect("convergence") else {
            panic!("convergence")
        };
        assert_eq!((c.size, c.max_dim, c.frames), (96, 96, 200));
        assert_eq!(c.lights, vec![1, 3, 4]);
        assert_eq!(c.irradiance.config(), IrradianceConfig::default());
        let Bench::Orbit(o) = parse("orbit").expect("orbit") else {
            panic!("orbit")
        };
        assert_eq!(
            (o.size, o.max_dim, o.build_frames, o.frames, o.reference_spp),
            (96, 64, 200, 100, 512)
        );
        assert_eq!(o.angles, vec![30.0, 90.0]);
        assert_eq!(o.lights, vec![1]);
        assert_eq!(o.irradiance.config(), IrradianceConfig::default());
    }

    /// Every `--flag` that the docs and scripts write after `voxlight bench <name>` is a flag of
    /// that benchmark.
    #[test]
    fn flags_in_the_docs_exist() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut files = vec![root.join("README.md")];
        for dir in ["docs", "scripts"] {
            for entry in std::fs::read_dir(root.join(dir)).expect("folder").flatten() {
                files.push(entry.path());
            }
        }
        let command = Cli::command();
        let mut checked = 0;
        for file in files {
            let Ok(text) = std::fs::read_to_string(&file) else {
                continue;
            };
            for (at, _) in text.match_indices("voxlight bench ") {
                let rest = &text[at + "voxlight bench ".len()..];
                let line = rest.lines().next().unwrap_or("");
                let line = line.split(['`', '|', ')', '"']).next().unwrap_or("");
                let mut words = line.split_whitespace();
                let Some(name) = words.next() else { continue };
                let Some(sub) = command.find_subcommand(name) else {
                    // Prose such as "voxlight bench …".
                    assert!(
                        !name.chars().all(|c| c.is_ascii_lowercase() || c == '-'),
                        "{}: `voxlight bench {name}` is no benchmark",
                        file.display()
                    );
                    continue;
                };
                for word in words {
                    let flag = word
                        .trim_start_matches('[')
                        .trim_end_matches([']', ',', '.']);
                    let Some(long) = flag.strip_prefix("--") else {
                        continue;
                    };
                    let long = long.split('=').next().unwrap_or(long);
                    assert!(
                        sub.get_arguments().any(|a| a.get_long() == Some(long)),
                        "{}: `voxlight bench {name}` has no --{long}",
                        file.display()
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 20, "found only {checked} documented flags");
    }
}
