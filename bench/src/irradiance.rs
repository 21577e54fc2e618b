//! `voxlight bench convergence` (the irradiance-caching paper's Table 2), `voxlight bench orbit`
//! (the cache kept across a camera orbit against a cleared one, its Fig. 10) and `voxlight bench
//! tf-edit --technique irradiance` (historygram invalidation against a cleared cache).
//!
//! Errors are measured against a long plain Monte-Carlo run (the `pathtrace` estimator) of the
//! same scene with its own random numbers: the relative RMS luminance error over the image,
//! with the reference's own noise (the variance of its pixel means, from its samples) taken
//! out, so that the error is that against the converged picture, not against a noisy one.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use serde_json::json;
use voxlight_engine::image_stats::luminance;
use voxlight_engine::techniques::irradiance::{
    CachedLight, Historygrams, Invalidation, Irradiance, IrradianceConfig, Locking, ViewEvent,
    cached_light,
};
use voxlight_engine::{Change, Engine, GpuVolume, Scene, Technique};
use voxlight_protocol::{Camera, Light, TransferFunction, Viewport};

use crate::interactive::orbit as orbit_camera;

/// Options of `bench convergence`.
pub struct ConvergenceBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub size: u32,
    pub max_dim: u32,
    /// Frames each of plain MCVR and `irradiance` runs.
    pub frames: u32,
    /// Samples per pixel of the reference.
    pub reference_spp: u32,
    pub lights: &'a [u32],
    pub datasets: &'a [String],
    /// Most scattering events on a camera path (1: single scattering, as in the paper).
    pub bounces: u32,
    /// Where to write each case's pictures (reference, plain, irradiance at the last frame).
    pub dump: Option<&'a Path>,
    /// The cache's configuration besides what each case sets.
    pub config: IrradianceConfig,
    /// Measure the ceiling of any cache of the indirect light (`ceiling`) instead.
    pub ceiling: bool,
}

/// Writes linear radiance as an sRGB PNG (exposure 1, clamped).
fn save_png(path: &Path, picture: &[[f32; 3]], size: u32) -> anyhow::Result<()> {
    let srgb = |x: f32| {
        let x = x.clamp(0.0, 1.0);
        let s = if x <= 0.0031308 {
            12.92 * x
        } else {
            1.055 * x.powf(1.0 / 2.4) - 0.055
        };
        (s * 255.0 + 0.5) as u8
    };
    let rgba: Vec<u8> = picture
        .iter()
        .flat_map(|p| [srgb(p[0]), srgb(p[1]), srgb(p[2]), 255])
        .collect();
    std::fs::write(path, voxlight_app::encode::png(&rgba, size, size)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// A converged picture and the variance of each pixel's mean luminance.
struct Reference {
    mean: Vec<[f32; 3]>,
    mean_luminance: f64,
    noise: f64,
}

impl Reference {
    fn new(mean: Vec<[f32; 3]>, variance: Vec<f32>) -> Self {
        let n = mean.len().max(1) as f64;
        let mean_luminance = mean.iter().map(|&c| luminance(c)).sum::<f64>() / n;
        let noise = variance.iter().map(|&v| v as f64).sum::<f64>() / n;
        Self {
            mean,
            mean_luminance,
            noise,
        }
    }

    /// Relative RMS luminance error of `picture` against the converged image: the mean
    /// squared difference less the reference's own variance, over the mean luminance.
    fn error(&self, picture: &[[f32; 3]]) -> f64 {
        let n = picture.len().max(1) as f64;
        let squared = picture
            .iter()
            .zip(&self.mean)
            .map(|(&a, &b)| (luminance(a) - luminance(b)).powi(2))
            .sum::<f64>()
            / n;
        (squared - self.noise).max(0.0).sqrt() / self.mean_luminance.max(1e-12)
    }

    /// The mean luminance of `picture` relative to the reference's, less 1 (> 0: too bright).
    fn bias(&self, picture: &[[f32; 3]]) -> f64 {
        let n = picture.len().max(1) as f64;
        let mean = picture.iter().map(|&c| luminance(c)).sum::<f64>() / n;
        mean / self.mean_luminance.max(1e-12) - 1.0
    }

    /// The reference's own relative noise (what `error` takes out).
    fn relative_noise(&self) -> f64 {
        self.noise.sqrt() / self.mean_luminance.max(1e-12)
    }
}

/// The paper's three light setups (§8), with the lights this renderer has, placed for the
/// default camera (at −y looking along +y, +z up): one small distant light from above the
/// camera; three intense lights close to the volume on the camera's side; four dim lights
/// around it. `up` is +1, or −1 for a volume seen upside down (its lights are mirrored).
pub fn light_setup(count: u32, up: f32) -> anyhow::Result<Vec<Light>> {
    let mirror = |v: [f32; 3]| [v[0], v[1], v[2] * up];
    Ok(match count {
        1 => vec![Light::Directional {
            direction: mirror([0.35, 0.6, -0.7]),
            irradiance: [3.0, 2.9, 2.7],
        }],
        3 => [
            ([-0.7, -0.6, 0.4], [1.6, 1.4, 1.2]),
            ([0.75, -0.5, 0.3], [1.2, 1.4, 1.6]),
            ([0.0, -0.3, 0.85], [1.5, 1.5, 1.5]),
        ]
        .into_iter()
        .map(|(position, intensity)| Light::Point {
            position: mirror(position),
            intensity,
        })
        .collect(),
        4 => [
            [1.0, 0.3, -0.3],
            [-1.0, 0.3, -0.3],
            [0.0, 1.0, -0.3],
            [0.0, -1.0, -0.3],
        ]
        .into_iter()
        .map(|direction| Light::Directional {
            direction: mirror(direction),
            irradiance: [0.7, 0.7, 0.7],
        })
        .collect(),
        other => anyhow::bail!("light setups are 1, 3 and 4 lights, not {other}"),
    })
}

/// +1, or −1 for datasets the default camera sees upside down (the bonsai grows along −z).
fn dataset_up(name: &str) -> f32 {
    if name == "bonsai" { -1.0 } else { 1.0 }
}

/// A dataset of ../shared/data by short name, downsampled.
fn dataset(data_dir: &Path, name: &str, max_dim: u32) -> anyhow::Result<voxlight_volumes::Volume> {
    let rel = match name {
        "bonsai" => "vti/bonsai.vti",
        "chest" => "ct-chest-lidc",
        "engine" => "vti/engine.vti",
        other => anyhow::bail!("unknown dataset `{other}`; available: bonsai, chest, engine"),
    };
    let path = data_dir.join(rel);
    let mut volume = voxlight_volumes::load(&path)
        .with_context(|| format!("loading {}", path.display()))?
        .downsampled(max_dim);
    volume.name = rel.to_owned();
    Ok(volume)
}

pub fn cached_light_name(light: CachedLight) -> &'static str {
    match light {
        CachedLight::All => "all",
        CachedLight::Indirect => "indirect",
    }
}

pub fn view_event_name(event: ViewEvent) -> &'static str {
    match event {
        ViewEvent::Marched => "marched",
        ViewEvent::DeltaTracking => "tracked",
    }
}

/// Plain MCVR with the same camera-ray estimator as the cache runs (`view_event`,
/// `view_picks`).
fn plain(config: &IrradianceConfig) -> IrradianceConfig {
    IrradianceConfig {
        cache: false,
        priorities: false,
        bounces: config.bounces,
        view_event: config.view_event,
        view_picks: config.view_picks,
        ..IrradianceConfig::default()
    }
}

/// The paper's own error measure (the left side of its Eq. 5): the 95% confidence half-width
/// of each pixel's mean from its samples' variance, averaged over the pixels, relative to the
/// reference's mean luminance. It sees noise only, not bias.
fn estimated_error(variance: &[f32], reference: &Reference) -> f64 {
    let n = variance.len().max(1) as f64;
    let half_width = variance
        .iter()
        .map(|&v| 1.96 * (v as f64).sqrt())
        .sum::<f64>()
        / n;
    half_width / reference.mean_luminance.max(1e-12)
}

/// Errors of a run, per frame: against the reference, and as the paper estimates them.
#[derive(Default)]
struct Errors {
    reference: Vec<f64>,
    estimated: Vec<f64>,
    /// The picture's mean luminance against the reference's, less 1 (`Reference::bias`).
    bias: Vec<f64>,
}

impl Errors {
    /// The last picture's bias (0 before any frame).
    fn last_bias(&self) -> f64 {
        self.bias.last().copied().unwrap_or(0.0)
    }
}

/// One frame: its wall time and its split (render, create, update, rest); its errors are
/// appended to `errors`.
fn timed_frame(
    engine: &Engine,
    technique: &mut Irradiance,
    scene: &Scene,
    reference: &Reference,
    errors: &mut Errors,
) -> anyhow::Result<(Duration, [Duration; 4])> {
    let started = Instant::now();
    let t = technique.frame(engine, scene, true)?;
    let elapsed = started.elapsed();
    let (picture, variance) = technique.read_estimate(engine)?;
    errors.reference.push(reference.error(&picture));
    errors.estimated.push(estimated_error(&variance, reference));
    errors.bias.push(reference.bias(&picture));
    Ok((
        elapsed,
        [t.render, t.create, t.update + t.validate, t.bookkeeping],
    ))
}

/// Runs `frames` frames, returning each frame's errors and time.
fn run_frames(
    engine: &Engine,
    technique: &mut Irradiance,
    scene: &Scene,
    frames: u32,
    reference: &Reference,
) -> anyhow::Result<(Errors, Vec<Duration>)> {
    let mut errors = Errors {
        reference: Vec::with_capacity(frames as usize),
        estimated: Vec::with_capacity(frames as usize),
        bias: Vec::with_capacity(frames as usize),
    };
    let mut times = Vec::with_capacity(frames as usize);
    let mut split = [Duration::ZERO; 4];
    for _ in 0..frames {
        let started = Instant::now();
        let t = technique.frame(engine, scene, true)?;
        times.push(started.elapsed());
        for (s, d) in
            split
                .iter_mut()
                .zip([t.render, t.create, t.update + t.validate, t.bookkeeping])
        {
            *s += d;
        }
        let (picture, variance) = technique.read_estimate(engine)?;
        errors.reference.push(reference.error(&picture));
        errors.estimated.push(estimated_error(&variance, reference));
        errors.bias.push(reference.bias(&picture));
    }
    let ms = split.map(|d| d.as_secs_f64() * 1e3 / frames.max(1) as f64);
    eprintln!(
        "    per frame: render {:.1} ms, create {:.1} ms, update and validation {:.1} ms, rest {:.1} ms",
        ms[0], ms[1], ms[2], ms[3]
    );
    Ok((errors, times))
}

fn reference(
    engine: &Engine,
    volume: &Arc<GpuVolume>,
    scene: &Scene,
    spp: u32,
    config: &IrradianceConfig,
) -> anyhow::Result<Reference> {
    let scene = Scene {
        seed: scene.seed ^ 0x5eed_0001,
        ..scene.clone()
    };
    let config = plain(&IrradianceConfig {
        view_event: IrradianceConfig::default().view_event,
        ..*config
    });
    let mut technique = Irradiance::new(engine, Arc::clone(volume), &scene, config)?;
    for _ in 0..spp {
        technique.frame(engine, &scene, true)?;
    }
    let (mean, variance) = technique.read_estimate(engine)?;
    Ok(Reference::new(mean, variance))
}

/// Mean samples per estimation point and mean zone radius (voxels) of the cache's entries.
fn entry_shape(
    engine: &Engine,
    technique: &mut Irradiance,
    max_dim: u32,
) -> anyhow::Result<String> {
    let snapshot = technique.snapshot(engine)?;
    let n = snapshot.entries.len().max(1) as f64;
    let samples = snapshot
        .entries
        .iter()
        .map(|e| e.samples as f64)
        .sum::<f64>()
        / n;
    let radius = snapshot.radii.iter().map(|&r| r as f64).sum::<f64>() / (6.0 * n);
    Ok(format!(
        "{samples:.0} samples per point, mean radius {:.1} voxels",
        radius * max_dim as f64
    ))
}

/// Runs a few frames of every pass once, so no measured frame pays for a shader's first use.
fn warm_up(engine: &Engine, volume: &Arc<GpuVolume>, scene: &Scene) -> anyhow::Result<()> {
    let config = IrradianceConfig {
        fixed_rounds: Some((1, 1)),
        ..IrradianceConfig::default()
    };
    let mut technique = Irradiance::new(engine, Arc::clone(volume), scene, config)?;
    for _ in 0..4 {
        technique.frame(engine, scene, true)?;
    }
    Ok(())
}

fn median(mut values: Vec<Duration>) -> Duration {
    values.sort();
    values.get(values.len() / 2).copied().unwrap_or_default()
}

fn mean_ratio(numerator: &[f64], denominator: &[f64]) -> f64 {
    let ratios: Vec<f64> = numerator
        .iter()
        .zip(denominator)
        .filter(|(_, d)| **d > 0.0)
        .map(|(n, d)| n / d)
        .collect();
    ratios.iter().sum::<f64>() / ratios.len().max(1) as f64
}

/// The TF each dataset is measured with: the bonsai's leaves, trunk and pot without its
/// background noise (values below 0.22, most of the volume), the engine's two materials, the
/// chest CT's soft tissue and bone (the viewer's default).
fn bench_tf(name: &str, volume: &voxlight_volumes::Volume) -> TransferFunction {
    use crate::engine::tf_point as point;
    match name {
        "bonsai" => TransferFunction {
            points: vec![
                point(0.0, [0.3, 0.6, 0.2], 0.0),
                point(0.22, [0.3, 0.6, 0.2], 0.0),
                point(0.32, [0.35, 0.65, 0.25], 0.5),
                point(0.55, [0.55, 0.4, 0.25], 0.7),
                point(0.72, [0.8, 0.45, 0.3], 1.0),
                point(1.0, [0.8, 0.45, 0.3], 1.0),
            ],
        },
        "engine" => crate::engine::engine_tf(),
        _ => voxlight_app::datasets::default_tf(volume),
    }
}

fn base_scene(
    name: &str,
    volume: &voxlight_volumes::Volume,
    size: u32,
    lights: Vec<Light>,
) -> Scene {
    let up = dataset_up(name);
    Scene {
        camera: Camera {
            up: [0.0, 0.0, up],
            ..Camera::default()
        },
        tf: bench_tf(name, volume),
        lights,
        viewport: Viewport {
            width: size,
            height: size,
        },
        target_iterations: u32::MAX,
        seed: 11,
        ..Scene::default()
    }
}

/// The datasets and light setups a benchmark runs over, and their image and volume sizes.
struct Cases<'a> {
    /// The benchmark's name (for the error without data).
    bench: &'a str,
    data_dir: Option<&'a Path>,
    datasets: &'a [String],
    lights: &'a [u32],
    size: u32,
    max_dim: u32,
}

impl<'a> ConvergenceBench<'a> {
    fn cases(&self) -> Cases<'a> {
        Cases {
            bench: "convergence",
            data_dir: self.data_dir,
            datasets: self.datasets,
            lights: self.lights,
            size: self.size,
            max_dim: self.max_dim,
        }
    }
}

/// Runs `case` for each dataset and light setup of `options`, with the dataset on the GPU and
/// the case's scene.
fn for_each_case(
    options: &Cases,
    engine: &Engine,
    mut case: impl FnMut(&str, u32, &Arc<GpuVolume>, &Scene) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let data_dir = options
        .data_dir
        .with_context(|| format!("bench {} needs ../shared/data (or --data)", options.bench))?;
    for name in options.datasets {
        let volume = dataset(data_dir, name, options.max_dim)?;
        let gpu_volume = engine.upload_volume(&volume)?;
        for &lights in options.lights {
            let lights_in_scene = light_setup(lights, dataset_up(name))?;
            let scene = base_scene(name, &volume, options.size, lights_in_scene);
            case(name, lights, &gpu_volume, &scene)?;
        }
    }
    Ok(())
}

/// `bench convergence`: plain MCVR against `irradiance` at equal time per frame (the plain
/// run's median frame time), for each dataset, light setup, with and without priorities,
/// object- and screen-space locking; the ratio of their errors averaged over the frames.
pub fn convergence(options: &ConvergenceBench) -> anyhow::Result<serde_json::Value> {
    if options.ceiling {
        return ceiling(options);
    }
    let engine = Engine::new()?;
    let config = IrradianceConfig {
        bounces: options.bounces,
        ..options.config
    };
    let mut cases = Vec::new();
    let mut controls = Vec::new();
    let over = options.cases();
    for_each_case(&over, &engine, |name, lights, gpu_volume, scene| {
        warm_up(&engine, gpu_volume, scene)?;
        let started = Instant::now();
        let reference = reference(&engine, gpu_volume, scene, options.reference_spp, &config)?;
        eprintln!(
            "{name}, {lights} light(s): reference {} spp in {:.1} s (its own relative noise {:.4})",
            options.reference_spp,
            started.elapsed().as_secs_f64(),
            reference.relative_noise()
        );
        // Plain MCVR and every variant run interleaved, frame by frame, each variant's
        // frame given the time the plain frame just before it took: the machine's speed
        // drifts (a shared VM), and this keeps "equal time per frame" true under drift.
        let variants: Vec<(bool, Locking)> = [false, true]
            .into_iter()
            .flat_map(|p| [(p, Locking::Object), (p, Locking::Screen)])
            .collect();
        let mut baseline = Irradiance::new(&engine, Arc::clone(gpu_volume), scene, plain(&config))?;
        let mut techniques = variants
            .iter()
            .map(|&(priorities, locking)| {
                let config = IrradianceConfig {
                    locking,
                    priorities,
                    frame_time: Some(Duration::from_millis(1)),
                    ..config
                };
                Irradiance::new(&engine, Arc::clone(gpu_volume), scene, config)
            })
            .collect::<Result<Vec<_>, _>>()?;
        // A control: plain MCVR with the same priorities and no cache. Eq. 12 draws blocks by
        // their samples' variance alone, so this separates what the priorities gain from
        // what the cache gains.
        let mut control = Irradiance::new(
            &engine,
            Arc::clone(gpu_volume),
            scene,
            IrradianceConfig {
                priorities: true,
                frame_time: Some(Duration::from_millis(1)),
                ..plain(&config)
            },
        )?;
        let mut control_run = Errors::default();
        let mut plain_run = Errors::default();
        let mut plain_times = Vec::new();
        let mut runs: Vec<Errors> = variants.iter().map(|_| Errors::default()).collect();
        let mut times: Vec<Vec<Duration>> = variants.iter().map(|_| Vec::new()).collect();
        let mut splits = vec![[Duration::ZERO; 4]; variants.len()];
        for _ in 0..options.frames {
            let t = timed_frame(&engine, &mut baseline, scene, &reference, &mut plain_run)?;
            plain_times.push(t.0);
            control.set_frame_time(Some(t.0));
            timed_frame(&engine, &mut control, scene, &reference, &mut control_run)?;
            for (i, technique) in techniques.iter_mut().enumerate() {
                technique.set_frame_time(Some(t.0));
                let (elapsed, split) =
                    timed_frame(&engine, technique, scene, &reference, &mut runs[i])?;
                times[i].push(elapsed);
                for (sum, d) in splits[i].iter_mut().zip(split) {
                    *sum += d;
                }
            }
        }
        let plain_errors = &plain_run.reference;
        let frame_time = median(plain_times.clone());
        let control_ratio = mean_ratio(plain_errors, &control_run.reference);
        eprintln!(
            "{name}, {lights} light(s), plain MCVR with priorities (no cache): error ratio {control_ratio:.2} (the paper's estimate: {:.2}); {} vs {} image-equivalents; bias {:+.2}% (plain {:+.2}%)",
            mean_ratio(&plain_run.estimated, &control_run.estimated),
            control.iteration(),
            baseline.iteration(),
            100.0 * control_run.last_bias(),
            100.0 * plain_run.last_bias(),
        );
        controls.push(json!({
            "dataset": name,
            "lights": lights,
            "error_ratio": control_ratio,
            "estimated_error_ratio": mean_ratio(&plain_run.estimated, &control_run.estimated),
            "samples_per_pixel": control.iteration(),
            "mean_bias": control_run.last_bias(),
            "mean_bias_plain": plain_run.last_bias(),
        }));
        let dump = |what: &str, picture: &[[f32; 3]]| -> anyhow::Result<()> {
            match options.dump {
                Some(dir) => {
                    std::fs::create_dir_all(dir)?;
                    save_png(
                        &dir.join(format!("{name}-{lights}-{what}.png")),
                        picture,
                        options.size,
                    )
                }
                None => Ok(()),
            }
        };
        dump("reference", &reference.mean)?;
        dump("plain", &baseline.read_estimate(&engine)?.0)?;
        for (i, technique) in techniques.iter_mut().enumerate() {
            let (priorities, locking) = variants[i];
            {
                let errors = &runs[i].reference;
                let ratio = mean_ratio(plain_errors, errors);
                let estimated_ratio = mean_ratio(&plain_run.estimated, &runs[i].estimated);
                let frame_ms = median(times[i].clone()).as_secs_f64() * 1e3;
                let split = splits[i].map(|d| d.as_secs_f64() * 1e3 / options.frames as f64);
                let shape = entry_shape(&engine, technique, options.max_dim)?;
                let locking_name = match locking {
                    Locking::Object => "object",
                    Locking::Screen => "screen",
                };
                dump(
                    &format!(
                        "irradiance-{}-{locking_name}",
                        if priorities { "priorities" } else { "in-turn" },
                    ),
                    &technique.read_estimate(&engine)?.0,
                )?;
                let stats = technique.cache_stats();
                let last = options.frames as usize - 1;
                eprintln!(
                    "{name}, {lights} light(s), priorities {priorities}, {locking_name} locking: \
                     error ratio {ratio:.2} (the paper's estimate: {estimated_ratio:.2}; last frame: plain {:.4}, irradiance {:.4}); \
                     {} entries ({shape}), {} references, hit rate {:.2}; frame {:.1} ms vs plain {:.1} ms \
                     (render {:.1}, create {:.1}, update {:.1}, rest {:.1}); {} vs {} image-equivalents; \
                     bias {:+.2}% (plain {:+.2}%); {} radius reductions, {} validation rounds",
                    plain_errors[last],
                    errors[last],
                    stats.entries,
                    stats.references,
                    stats.hit_rate,
                    frame_ms,
                    frame_time.as_secs_f64() * 1e3,
                    split[0],
                    split[1],
                    split[2],
                    split[3],
                    technique.iteration(),
                    baseline.iteration(),
                    100.0 * runs[i].last_bias(),
                    100.0 * plain_run.last_bias(),
                    stats.radius_reductions,
                    stats.validation_rounds,
                );
                cases.push(json!({
                    "dataset": name,
                    "lights": lights,
                    "priorities": priorities,
                    "locking": locking_name,
                    "error_ratio": ratio,
                    "estimated_error_ratio": estimated_ratio,
                    "cache_entries": stats.entries,
                    "references": stats.references,
                    "hit_rate": stats.hit_rate,
                    "final_error_plain": plain_errors[last],
                    "final_error_irradiance": errors[last],
                    "frame_ms_plain": frame_time.as_secs_f64() * 1e3,
                    "frame_ms_irradiance": frame_ms,
                    "reference_noise": reference.relative_noise(),
                    "samples_per_pixel": technique.iteration(),
                    "samples_per_pixel_plain": baseline.iteration(),
                    "mean_bias": runs[i].last_bias(),
                    "mean_bias_plain": plain_run.last_bias(),
                    "radius_reductions": stats.radius_reductions,
                    "validation_rounds": stats.validation_rounds,
                    "ms_per_frame_split": {
                        "render": split[0], "create": split[1], "update": split[2], "rest": split[3],
                    },
                }));
            }
        }
        Ok(())
    })?;
    let mut result = convergence_json("convergence", options, &engine);
    for (key, value) in [
        ("reference_spp", json!(options.reference_spp)),
        ("max_radius_voxels", json!(options.config.max_radius_voxels)),
        ("gamma", json!(options.config.gamma)),
        ("validate_hits", json!(options.config.validate_hits)),
        (
            "validation_share",
            json!(options.config.validation_fraction),
        ),
        (
            "validation_threshold",
            json!(options.config.validation_threshold),
        ),
        (
            "validation_samples",
            json!(options.config.validation_samples),
        ),
        (
            "cached_light",
            json!(cached_light_name(options.config.cached_light)),
        ),
        (
            "mean_error_ratio",
            json!(mean_over(&cases, |c| c["error_ratio"].as_f64())),
        ),
        (
            "mean_estimated_error_ratio",
            json!(mean_over(&cases, |c| c["estimated_error_ratio"].as_f64())),
        ),
        (
            "largest_abs_mean_bias",
            json!(
                cases
                    .iter()
                    .filter_map(|c| c["mean_bias"].as_f64())
                    .fold(0.0f64, |a, b| a.max(b.abs()))
            ),
        ),
        ("cases", json!(cases)),
        ("priorities_without_cache", json!(controls)),
    ] {
        result[key] = value;
    }
    Ok(result)
}

/// What `bench convergence` and its `--ceiling` report besides their cases.
fn convergence_json(bench: &str, options: &ConvergenceBench, engine: &Engine) -> serde_json::Value {
    json!({
        "bench": bench,
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "width": options.size,
        "height": options.size,
        "max_dim": options.max_dim,
        "frames": options.frames,
        "bounces": options.bounces,
        "view_event": view_event_name(options.config.view_event),
        "view_picks": options.config.view_picks,
    })
}

/// The mean of `value` over the cases that have it.
fn mean_over(
    cases: &[serde_json::Value],
    value: impl Fn(&serde_json::Value) -> Option<f64>,
) -> f64 {
    let values: Vec<f64> = cases.iter().filter_map(value).collect();
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// Frames after which `ceiling`'s ramp-up supposes the cache complete.
const CEILING_RAMPS: [u32; 6] = [0, 1, 5, 10, 20, 50];

/// The error ratio, averaged over `frames` frames as `convergence` averages it, of a cache that
/// answers nothing for its first `complete_after` frames and then every event, at equal time
/// per frame: plain MCVR renders `a` = t_plain / t_cached times fewer samples per frame once it
/// is complete, each of `1 / b` = V_plain / V_cached times the variance. The running mean weighs
/// every sample alike, so after n frames, f = min(n, F) of them without the cache and g = n − f
/// with it, the squared ratio is (f + g·a)² / (n · (f + g·a·b)).
pub fn ramp_ratio(a: f64, b: f64, complete_after: u32, frames: u32) -> f64 {
    let sum: f64 = (1..=frames.max(1))
        .map(|n| {
            let f = n.min(complete_after) as f64;
            let g = n as f64 - f;
            ((f + g * a).powi(2) / (n as f64 * (f + g * a * b))).sqrt()
        })
        .sum();
    sum / frames.max(1) as f64
}

/// The paper's error (Eq. 5's left side) summed over the pixels: 1.96 √(variance of the mean).
fn half_width(variance: &[f32]) -> f64 {
    variance.iter().map(|&v| 1.96 * (v as f64).sqrt()).sum()
}

/// The mean over the pixels of each sample's luminance variance (from each pixel's variance of
/// its mean and its sample count).
fn sample_variance(technique: &Irradiance, engine: &Engine) -> anyhow::Result<f64> {
    let (_, variance) = technique.read_estimate(engine)?;
    let n = technique.iteration() as f64;
    Ok(variance.iter().map(|&v| v as f64 * n).sum::<f64>() / variance.len().max(1) as f64)
}

/// `bench convergence --ceiling`: the most any cache of the indirect light (the default
/// `cached_light`) could gain. For each dataset and light setup, plain MCVR runs as in
/// `convergence` and, interleaved frame by frame, without its indirect light (one bounce and
/// no environment: the scattered path is not traced): what a free, perfect cache would leave
/// (its exact answer adds a variance of its own, unless that happens to cancel the direct
/// light's). The ceiling is √(V_plain·t_plain / (V_direct·t_direct)), the error ratio at equal
/// time of a cache complete from the first frame; `ramp` gives the same averaged over the
/// frames as `convergence` does for a cache complete only after F frames (`ramp_ratio`).
/// Each also runs with Eq. 12's priorities at its own frame time: their gain by the paper's
/// error measure (the larger of the two) scales the ramp for the benchmark's priority variants,
/// which `convergence` averages with the in-turn ones (`with_priority_variants`).
pub fn ceiling(options: &ConvergenceBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let config = IrradianceConfig {
        bounces: options.bounces,
        ..options.config
    };
    let mut cases = Vec::new();
    let over = options.cases();
    for_each_case(&over, &engine, |name, lights, gpu_volume, scene| {
        let environment = scene
            .lights
            .iter()
            .any(|l| matches!(l, Light::Environment { .. }));
        if cached_light(&config, scene) != CachedLight::Indirect || environment {
            anyhow::bail!(
                "--ceiling bounds a cache of the indirect light: it needs multiple scattering, \
                 `--cached-light indirect` and no environment light"
            );
        }
        warm_up(&engine, gpu_volume, scene)?;
        let mut plain_run =
            Irradiance::new(&engine, Arc::clone(gpu_volume), scene, plain(&config))?;
        let direct_config = IrradianceConfig {
            bounces: 1,
            ..plain(&config)
        };
        let mut direct_run =
            Irradiance::new(&engine, Arc::clone(gpu_volume), scene, direct_config)?;
        // Each with Eq. 12's priorities at the time its frame just took: what the
        // benchmark's priority variants add (the control's gain, and the same for a renderer
        // whose indirect light a perfect cache answers).
        let prioritised = |config: IrradianceConfig| IrradianceConfig {
            priorities: true,
            frame_time: Some(Duration::from_millis(1)),
            ..config
        };
        let mut plain_priorities = Irradiance::new(
            &engine,
            Arc::clone(gpu_volume),
            scene,
            prioritised(plain(&config)),
        )?;
        let mut direct_priorities = Irradiance::new(
            &engine,
            Arc::clone(gpu_volume),
            scene,
            prioritised(direct_config),
        )?;
        let (mut plain_times, mut direct_times) = (Vec::new(), Vec::new());
        let (mut plain_gain, mut direct_gain) = (Vec::new(), Vec::new());
        for _ in 0..options.frames {
            for (run, with_priorities, times, gain) in [
                (
                    &mut plain_run,
                    &mut plain_priorities,
                    &mut plain_times,
                    &mut plain_gain,
                ),
                (
                    &mut direct_run,
                    &mut direct_priorities,
                    &mut direct_times,
                    &mut direct_gain,
                ),
            ] {
                let started = Instant::now();
                run.frame(&engine, scene, true)?;
                let elapsed = started.elapsed();
                times.push(elapsed);
                with_priorities.set_frame_time(Some(elapsed));
                with_priorities.frame(&engine, scene, true)?;
                // Until every pixel has two samples the paper's measure reads 0 there: such
                // frames say nothing of the gain.
                let (without, with) = (
                    half_width(&run.read_estimate(&engine)?.1),
                    half_width(&with_priorities.read_estimate(&engine)?.1),
                );
                if without > 0.0 && with > 0.0 {
                    gain.push(without / with);
                }
            }
        }
        let average = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        // The paper's error measure of the priorities' gain (no reference needed); the
        // larger of the two stands for what they add on top of any cache.
        let (plain_gain, direct_gain) = (average(&plain_gain), average(&direct_gain));
        let priority_gain = plain_gain.max(direct_gain);
        let (t_plain, t_direct) = (
            median(plain_times).as_secs_f64() * 1e3,
            median(direct_times).as_secs_f64() * 1e3,
        );
        let (v_plain, v_direct) = (
            sample_variance(&plain_run, &engine)?,
            sample_variance(&direct_run, &engine)?,
        );
        let (a, b) = (t_plain / t_direct.max(1e-9), v_direct / v_plain.max(1e-30));
        let ceiling = (a / b.max(1e-30)).sqrt();
        // The benchmark averages its in-turn and its priority variants alike.
        let with_variants = (1.0 + priority_gain) / 2.0;
        let ramp: Vec<serde_json::Value> = CEILING_RAMPS
            .iter()
            .map(|&f| {
                let r = ramp_ratio(a, b, f, options.frames);
                json!({
                    "complete_after_frames": f,
                    "mean_error_ratio": r,
                    "with_priority_variants": r * with_variants,
                })
            })
            .collect();
        eprintln!(
            "{name}, {lights} light(s): plain {t_plain:.1} ms/frame, without the indirect light \
             {t_direct:.1} ms; the indirect light is {:.0}% of the variance; ceiling {ceiling:.2} \
             (complete after 10 frames: {:.2}); priorities gain {plain_gain:.2} (plain), \
             {direct_gain:.2} (without the indirect light)",
            100.0 * (1.0 - b),
            ramp_ratio(a, b, 10, options.frames),
        );
        cases.push(json!({
            "dataset": name,
            "lights": lights,
            "frame_ms_plain": t_plain,
            "frame_ms_direct": t_direct,
            "sample_variance_plain": v_plain,
            "sample_variance_direct": v_direct,
            "indirect_variance_share": 1.0 - b,
            "ceiling": ceiling,
            "priority_gain_plain": plain_gain,
            "priority_gain_direct": direct_gain,
            "ramp": ramp,
        }));
        Ok(())
    })?;
    let mean_ceiling = mean_over(&cases, |c| c["ceiling"].as_f64());
    let mean_ramp: Vec<serde_json::Value> = CEILING_RAMPS
        .iter()
        .enumerate()
        .map(|(i, &f)| {
            json!({
                "complete_after_frames": f,
                "mean_error_ratio": mean_over(&cases, |c| c["ramp"][i]["mean_error_ratio"].as_f64()),
                "with_priority_variants":
                    mean_over(&cases, |c| c["ramp"][i]["with_priority_variants"].as_f64()),
            })
        })
        .collect();
    let mut result = convergence_json("convergence-ceiling", options, &engine);
    result["mean_ceiling"] = json!(mean_ceiling);
    result["mean_ramp"] = json!(mean_ramp);
    result["cases"] = json!(cases);
    Ok(result)
}

/// Options of `bench orbit`.
pub struct OrbitBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub size: u32,
    pub max_dim: u32,
    /// Frames that build the cache from the first view, each at plain MCVR's frame time there.
    pub build_frames: u32,
    /// Frames measured after the orbit, at equal time per frame.
    pub frames: u32,
    /// Samples per pixel of each new view's reference.
    pub reference_spp: u32,
    pub lights: &'a [u32],
    pub datasets: &'a [String],
    /// Orbits, in degrees about the camera's up axis through the volume's centre.
    pub angles: &'a [f32],
    /// Most scattering events on a camera path.
    pub bounces: u32,
    /// The cache's configuration (the kept and the cleared cache alike).
    pub config: IrradianceConfig,
}

/// Frames of plain MCVR that time a frame at the first view (their median).
const PROBE_FRAMES: u32 = 8;

/// One run after the orbit, all at the new view.
struct OrbitRun {
    name: &'static str,
    technique: Irradiance,
    errors: Errors,
    times: Vec<Duration>,
}

impl OrbitRun {
    fn new(name: &'static str, technique: Irradiance) -> Self {
        Self {
            name,
            technique,
            errors: Errors::default(),
            times: Vec::new(),
        }
    }

    /// What the run left after its last frame, for the JSON and the summary line.
    fn report(
        &self,
        engine: &Engine,
        reference: &Reference,
    ) -> anyhow::Result<(f64, serde_json::Value)> {
        let errors = &self.errors.reference;
        let at = |frame: usize| {
            errors
                .get(frame.min(errors.len().saturating_sub(1)))
                .copied()
        };
        let (picture, _) = self.technique.read_estimate(engine)?;
        let bias = reference.bias(&picture);
        let stats = self.technique.cache_stats();
        let seconds: f64 = self.times.iter().map(Duration::as_secs_f64).sum();
        let mut value = json!({
            "final_error": at(usize::MAX),
            "error_at_frame_1": at(0),
            "error_at_frame_10": at(9),
            "mean_bias": bias,
            "seconds": seconds,
            "frame_ms": median(self.times.clone()).as_secs_f64() * 1e3,
            "samples_per_pixel": self.technique.iteration(),
            "errors": errors,
        });
        if self.technique.config().cache {
            value["cache_entries"] = json!(stats.entries);
            value["hit_rate"] = json!(stats.hit_rate);
        }
        Ok((bias, value))
    }
}

/// `bench orbit`: the irradiance cache across camera moves (the paper's Fig. 10: object-space
/// entries reused after an orbit). For each dataset and light setup a cache is built from the
/// first view; then, for each orbit angle, against a long plain-MCVR reference of the turned
/// view, four runs go on from the orbit, interleaved frame by frame at equal time per frame
/// (each cache frame given the time plain MCVR's frame just before it took, as in
/// `convergence`):
/// - `kept`: a copy of the built cache, then a camera edit to the new view (`Change::Camera`,
///   which keeps the entries and restarts the picture; the copy drops pending requests);
/// - `cleared`: a fresh technique at the new view (an empty cache);
/// - `plain`: plain MCVR (no cache, no priorities; its frames set the time);
/// - `control`: plain MCVR with Eq. 12's priorities and no cache.
///
/// The error is `convergence`'s (relative RMS of the luminance against the reference, its own
/// noise taken out); the bias is the mean luminance against the reference's, less 1.
pub fn orbit(options: &OrbitBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let config = IrradianceConfig {
        bounces: options.bounces,
        ..options.config
    };
    let cases = Cases {
        bench: "orbit",
        data_dir: options.data_dir,
        datasets: options.datasets,
        lights: options.lights,
        size: options.size,
        max_dim: options.max_dim,
    };
    let mut rows = Vec::new();
    for_each_case(&cases, &engine, |name, lights, gpu_volume, scene| {
        warm_up(&engine, gpu_volume, scene)?;
        // The cache is built at plain MCVR's frame time at the first view, as `convergence`
        // runs it.
        let mut probe = Irradiance::new(&engine, Arc::clone(gpu_volume), scene, plain(&config))?;
        let mut probe_times = Vec::new();
        for _ in 0..PROBE_FRAMES {
            let started = Instant::now();
            probe.frame(&engine, scene, true)?;
            probe_times.push(started.elapsed());
        }
        drop(probe);
        let build_frame = median(probe_times);
        let mut builder = Irradiance::new(
            &engine,
            Arc::clone(gpu_volume),
            scene,
            IrradianceConfig {
                frame_time: Some(build_frame),
                ..config
            },
        )?;
        let started = Instant::now();
        for _ in 0..options.build_frames {
            builder.frame(&engine, scene, true)?;
        }
        let build_s = started.elapsed().as_secs_f64();
        let built = builder.cache_stats();
        let snapshot = builder.snapshot(&engine)?;
        drop(builder);
        eprintln!(
            "{name}, {lights} light(s): built {} entries in {} frames of {:.1} ms ({build_s:.1} s), \
             hit rate {:.2} at the first view",
            built.entries,
            options.build_frames,
            build_frame.as_secs_f64() * 1e3,
            built.hit_rate,
        );
        for &angle in options.angles {
            let turned = Scene {
                camera: orbit_camera(&scene.camera, angle),
                ..scene.clone()
            };
            let started = Instant::now();
            let reference =
                reference(&engine, gpu_volume, &turned, options.reference_spp, &config)?;
            eprintln!(
                "{name}, {lights} light(s), {angle}°: reference {} spp in {:.1} s (its own \
                 relative noise {:.4})",
                options.reference_spp,
                started.elapsed().as_secs_f64(),
                reference.relative_noise()
            );
            let timed = IrradianceConfig {
                frame_time: Some(Duration::from_millis(1)),
                ..config
            };
            let mut kept = Irradiance::new(&engine, Arc::clone(gpu_volume), scene, timed)?;
            kept.restore(&engine, scene, &snapshot)?;
            let entries_before = kept.cache_stats().entries;
            kept.apply(&engine, &turned, &Change::Camera)?;
            let entries_after = kept.cache_stats().entries;
            let cleared = Irradiance::new(&engine, Arc::clone(gpu_volume), &turned, timed)?;
            let control = Irradiance::new(
                &engine,
                Arc::clone(gpu_volume),
                &turned,
                IrradianceConfig {
                    priorities: true,
                    frame_time: timed.frame_time,
                    ..plain(&config)
                },
            )?;
            let mut plain_run = OrbitRun::new(
                "plain",
                Irradiance::new(&engine, Arc::clone(gpu_volume), &turned, plain(&config))?,
            );
            let mut runs = [
                OrbitRun::new("kept", kept),
                OrbitRun::new("cleared", cleared),
                OrbitRun::new("control", control),
            ];
            for _ in 0..options.frames {
                let (t, _) = timed_frame(
                    &engine,
                    &mut plain_run.technique,
                    &turned,
                    &reference,
                    &mut plain_run.errors,
                )?;
                plain_run.times.push(t);
                for run in &mut runs {
                    run.technique.set_frame_time(Some(t));
                    let (elapsed, _) = timed_frame(
                        &engine,
                        &mut run.technique,
                        &turned,
                        &reference,
                        &mut run.errors,
                    )?;
                    run.times.push(elapsed);
                }
            }
            let [kept, cleared, control] = &runs;
            let final_error = |run: &OrbitRun| run.errors.reference.last().copied().unwrap_or(0.0);
            let ratio = |run: &OrbitRun| final_error(run) / final_error(kept).max(1e-12);
            let mean = |run: &OrbitRun| mean_ratio(&run.errors.reference, &kept.errors.reference);
            let mut row = json!({
                "dataset": name,
                "lights": lights,
                "angle_deg": angle,
                "build_frames": options.build_frames,
                "build_frame_ms": build_frame.as_secs_f64() * 1e3,
                "build_s": build_s,
                "built_entries": built.entries,
                "built_hit_rate": built.hit_rate,
                "entries_before_camera_edit": entries_before,
                "entries_after_camera_edit": entries_after,
                "reference_noise": reference.relative_noise(),
                "final_error_ratio_cleared_over_kept": ratio(cleared),
                "final_error_ratio_plain_over_kept": ratio(&plain_run),
                "final_error_ratio_control_over_kept": ratio(control),
                "mean_error_ratio_cleared_over_kept": mean(cleared),
                "mean_error_ratio_plain_over_kept": mean(&plain_run),
                "mean_error_ratio_control_over_kept": mean(control),
            });
            let mut line = Vec::new();
            for run in [kept, cleared, &plain_run, control] {
                let (bias, value) = run.report(&engine, &reference)?;
                line.push(format!(
                    "{} {:.4} (bias {:+.2}%, {:.1} s, {} spp)",
                    run.name,
                    final_error(run),
                    100.0 * bias,
                    run.times.iter().map(Duration::as_secs_f64).sum::<f64>(),
                    run.technique.iteration(),
                ));
                row[run.name] = value;
            }
            eprintln!(
                "{name}, {lights} light(s), {angle}°: entries {entries_before} → {entries_after} \
                 across the camera edit; error after {} frames: {}; cleared/kept {:.2} (mean \
                 over frames {:.2}), plain/kept {:.2} ({:.2}), control/kept {:.2} ({:.2})",
                options.frames,
                line.join(", "),
                ratio(cleared),
                mean(cleared),
                ratio(&plain_run),
                mean(&plain_run),
                ratio(control),
                mean(control),
            );
            rows.push(row);
        }
        Ok(())
    })?;
    let mean_of = |key: &str| mean_over(&rows, |r| r[key].as_f64());
    Ok(json!({
        "bench": "orbit",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "width": options.size,
        "height": options.size,
        "max_dim": options.max_dim,
        "build_frames": options.build_frames,
        "frames": options.frames,
        "reference_spp": options.reference_spp,
        "bounces": options.bounces,
        "cached_light": cached_light_name(options.config.cached_light),
        "view_event": view_event_name(options.config.view_event),
        "view_picks": options.config.view_picks,
        "max_radius_voxels": options.config.max_radius_voxels,
        "priorities": options.config.priorities,
        "mean_final_error_ratio_cleared_over_kept": mean_of("final_error_ratio_cleared_over_kept"),
        "mean_final_error_ratio_plain_over_kept": mean_of("final_error_ratio_plain_over_kept"),
        "mean_error_ratio_cleared_over_kept": mean_of("mean_error_ratio_cleared_over_kept"),
        "mean_error_ratio_plain_over_kept": mean_of("mean_error_ratio_plain_over_kept"),
        "cases": rows,
    }))
}

/// Options of `bench tf-edit --technique irradiance`.
pub struct IrradianceTfEditBench<'a> {
    pub scenarios: crate::engine::TfEditBench<'a>,
    /// Frames that build the cache before the edit.
    pub build_frames: u32,
    /// Frames measured after it.
    pub frames: u32,
    pub reference_spp: u32,
    pub historygrams: Historygrams,
    pub config: IrradianceConfig,
}

/// `bench tf-edit --technique irradiance`: a cache built with one TF, then each edit applied
/// three ways from the same state (historygram invalidation, a cleared cache, plain MCVR), each
/// followed by the same frames at equal time per frame; entries kept and errors per frame
/// against a long plain run with the new TF.
pub fn tf_edit(options: &IrradianceTfEditBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let mut rows = Vec::new();
    for scenario in crate::engine::tf_edit_scenarios(&options.scenarios)? {
        let gpu_volume = engine.upload_volume(&scenario.volume)?;
        let base = Scene {
            camera: scenario.camera,
            tf: scenario.tf.clone(),
            lights: voxlight_app::datasets::default_lights_for(&scenario.volume),
            viewport: Viewport {
                width: options.scenarios.size,
                height: options.scenarios.size,
            },
            target_iterations: u32::MAX,
            seed: 11,
            ..Scene::default()
        };
        let config = IrradianceConfig {
            historygrams: options.historygrams,
            bounces: options.scenarios.bounces,
            ..options.config
        };
        warm_up(&engine, &gpu_volume, &base)?;
        let mut builder = Irradiance::new(&engine, Arc::clone(&gpu_volume), &base, config)?;
        let started = Instant::now();
        for _ in 0..options.build_frames {
            builder.frame(&engine, &base, true)?;
        }
        let build_s = started.elapsed().as_secs_f64();
        let snapshot = builder.snapshot(&engine)?;
        let built = builder.cache_stats();
        eprintln!(
            "{}: {} entries after {} frames ({build_s:.1} s)",
            scenario.name, built.entries, options.build_frames
        );
        for edit in &scenario.edits {
            let scene = Scene {
                tf: edit.tf.clone(),
                ..base.clone()
            };
            let reference =
                reference(&engine, &gpu_volume, &scene, options.reference_spp, &config)?;
            let mut baseline =
                Irradiance::new(&engine, Arc::clone(&gpu_volume), &scene, plain(&config))?;
            let (plain, plain_times) =
                run_frames(&engine, &mut baseline, &scene, options.frames, &reference)?;
            let plain_errors = plain.reference;
            let frame_time = median(plain_times);
            let change = Change::tf(&base.tf, &scene.tf);
            let mut runs = Vec::new();
            for invalidation in [Invalidation::Historygram, Invalidation::Clear] {
                let config = IrradianceConfig {
                    invalidation,
                    frame_time: Some(frame_time),
                    ..config
                };
                let mut technique =
                    Irradiance::new(&engine, Arc::clone(&gpu_volume), &base, config)?;
                technique.restore(&engine, &base, &snapshot)?;
                let started = Instant::now();
                technique.apply(&engine, &scene, &change)?;
                let edit_ms = started.elapsed().as_secs_f64() * 1e3;
                let kept = technique.cache_stats().entries;
                let (errors, _) =
                    run_frames(&engine, &mut technique, &scene, options.frames, &reference)?;
                runs.push((kept, edit_ms, errors.reference));
            }
            let (kept, edit_ms, hist_errors) = &runs[0];
            let (_, _, clear_errors) = &runs[1];
            let at = |errors: &[f64], frame: usize| errors[frame.min(errors.len() - 1)];
            let kept_pct = 100.0 * *kept as f64 / built.entries.max(1) as f64;
            let ratio = mean_ratio(clear_errors, hist_errors);
            eprintln!(
                "{} / {}: kept {kept} of {} entries ({kept_pct:.1}%), edit {edit_ms:.1} ms; \
                 error after 1 / 10 / {} frames: historygram {:.4} / {:.4} / {:.4}, \
                 cleared {:.4} / {:.4} / {:.4}, plain {:.4} / {:.4} / {:.4}; cleared/historygram {ratio:.2}",
                scenario.name,
                edit.name,
                built.entries,
                options.frames,
                at(hist_errors, 0),
                at(hist_errors, 9),
                at(hist_errors, usize::MAX),
                at(clear_errors, 0),
                at(clear_errors, 9),
                at(clear_errors, usize::MAX),
                at(&plain_errors, 0),
                at(&plain_errors, 9),
                at(&plain_errors, usize::MAX),
            );
            rows.push(json!({
                "name": scenario.name,
                "dataset": scenario.dataset,
                "edit": edit.name,
                "entries": built.entries,
                "kept": kept,
                "kept_pct": kept_pct,
                "edit_ms": edit_ms,
                "frame_ms": frame_time.as_secs_f64() * 1e3,
                "error_historygram": hist_errors,
                "error_cleared": clear_errors,
                "error_plain": plain_errors,
                "mean_error_ratio_cleared_over_historygram": ratio,
                "mean_error_ratio_plain_over_historygram": mean_ratio(&plain_errors, hist_errors),
            }));
        }
    }
    Ok(json!({
        "bench": "tf-edit",
        "technique": "irradiance",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "width": options.scenarios.size,
        "height": options.scenarios.size,
        "build_frames": options.build_frames,
        "frames": options.frames,
        "reference_spp": options.reference_spp,
        "historygrams": match options.historygrams {
            Historygrams::Samples => "samples",
            Historygrams::Cells => "cells",
        },
        "cached_light": cached_light_name(options.config.cached_light),
        "view_picks": options.config.view_picks,
        "scenarios": rows,
    }))
}

#[cfg(test)]
mod tests {
    use super::{orbit_camera, ramp_ratio};
    use voxlight_protocol::Camera;

    #[test]
    fn an_orbit_turns_the_eye_about_the_up_axis_through_the_target() {
        let camera = Camera::default();
        let near = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        // From −y, a quarter turn about +z (counter-clockwise seen from above) looks from +x.
        let turned = orbit_camera(&camera, 90.0);
        assert!(near(turned.eye, [2.4, 0.0, 0.0]), "{:?}", turned.eye);
        assert_eq!((turned.target, turned.up), (camera.target, camera.up));
        assert!(near(orbit_camera(&camera, 360.0).eye, camera.eye));
        // About a target off the origin and a tilted eye: the distance and the height along up
        // stay.
        let camera = Camera {
            eye: [1.0, -2.0, 0.5],
            target: [1.0, 0.0, -0.5],
            ..camera
        };
        let turned = orbit_camera(&camera, 30.0);
        let offset = |c: &Camera| std::array::from_fn::<f32, 3, _>(|i| c.eye[i] - c.target[i]);
        let length = |v: [f32; 3]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((length(offset(&turned)) - length(offset(&camera))).abs() < 1e-5);
        assert!((offset(&turned)[2] - offset(&camera)[2]).abs() < 1e-5);
    }

    #[test]
    fn a_cache_complete_from_the_start_gives_the_ceiling_and_one_never_complete_gives_one() {
        // Twice plain's samples per frame at half the variance each: four times the efficiency.
        let (a, b) = (2.0, 0.5);
        assert!((ramp_ratio(a, b, 0, 200) - 2.0).abs() < 1e-12);
        assert!((ramp_ratio(a, b, 200, 200) - 1.0).abs() < 1e-12);
        assert!((ramp_ratio(a, b, 500, 200) - 1.0).abs() < 1e-12);
        // Completed later, less of the average is won, and never less than without the cache.
        let ratios: Vec<f64> = [0, 1, 5, 10, 20, 50]
            .map(|f| ramp_ratio(a, b, f, 200))
            .to_vec();
        assert!(
            ratios.windows(2).all(|w| w[0] > w[1] && w[1] > 1.0),
            "{ratios:?}"
        );
        // Complete after one frame, over three: after frame n the cache run has 1 + 2(n − 1)
        // samples, with variance 1 + 2(n − 1)·0.5 in plain's units, against n plain samples, so
        // the ratios are 1, √(9 / 4) and √(25 / 9).
        let expected = (1.0 + 1.5 + (25.0_f64 / 9.0).sqrt()) / 3.0;
        assert!((ramp_ratio(a, b, 1, 3) - expected).abs() < 1e-12);
    }
}
