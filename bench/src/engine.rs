//! `voxlight bench NAME [--json]`: speed measured in one run on the adapter at hand.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use serde_json::json;
use voxlight_engine::image_stats::median;
use voxlight_engine::preview::LightDetail;
use voxlight_engine::{Engine, Scene};
use voxlight_protocol::{Camera, TfPoint, TransferFunction, Viewport, default_lights};

/// The 256³ CT the speed benchmarks use: the bonsai of ../shared/data when found, else a
/// 256³ Cornell phantom. Returns its name and the volume.
pub fn ct_256(data_dir: Option<&Path>) -> anyhow::Result<(String, voxlight_volumes::Volume)> {
    let (dataset, mut volume) = match data_dir.map(|d| d.join("vti/bonsai.vti")) {
        Some(path) if path.is_file() => (
            "vti/bonsai.vti".to_owned(),
            voxlight_volumes::load(&path).with_context(|| format!("loading {}", path.display()))?,
        ),
        _ => (
            "phantom:cornell@256".to_owned(),
            voxlight_volumes::phantom("cornell", 256)?,
        ),
    };
    volume.name = dataset.clone();
    Ok((dataset, volume))
}

/// The scene `bench raymarch` and `bench preview` time: the dataset's default TF, the default
/// camera and lights, a size² viewport, no convergence.
fn speed_scene(volume: &voxlight_volumes::Volume, size: u32) -> Scene {
    let tf = voxlight_app::datasets::default_tf(volume);
    timed_scene(Camera::default(), tf, size)
}

/// A speed benchmark's scene: `camera` and `tf` under the default lights, a size² viewport,
/// never converged.
pub(crate) fn timed_scene(camera: Camera, tf: TransferFunction, size: u32) -> Scene {
    Scene {
        camera,
        tf,
        lights: default_lights(),
        viewport: Viewport {
            width: size,
            height: size,
        },
        target_iterations: u32::MAX,
        ..Scene::default()
    }
}

/// Options of `bench raymarch`.
pub struct RaymarchBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub sizes: &'a [u32],
    pub iterations: u32,
}

/// ms per progressive `raymarch` iteration at each size on a 256³ CT (the bonsai CT of
/// ../shared/data when found, else a 256³ Cornell phantom). Returns the JSON result.
pub fn raymarch(options: &RaymarchBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let (dataset, volume) = ct_256(options.data_dir)?;
    let gpu_volume = engine.upload_volume(&volume)?;
    let mut results = Vec::new();
    for &size in options.sizes {
        let scene = speed_scene(&volume, size);
        let mut renderer = engine.create_renderer("raymarch", Arc::clone(&gpu_volume), &scene)?;
        // Warm up (pipeline compilation, first touches), then time whole iterations.
        renderer.step(&engine, &scene, Duration::ZERO)?;
        let before = renderer.iteration();
        let started = Instant::now();
        while renderer.iteration() - before < options.iterations {
            renderer.step(&engine, &scene, Duration::ZERO)?;
        }
        let elapsed = started.elapsed();
        let done = renderer.iteration() - before;
        let ms = elapsed.as_secs_f64() * 1000.0 / done as f64;
        eprintln!("raymarch {size}x{size}: {ms:.1} ms/iteration over {done} iterations");
        results.push(
            json!({"width": size, "height": size, "iterations": done, "ms_per_iteration": ms}),
        );
    }
    Ok(json!({
        "bench": "raymarch",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "dataset": dataset,
        "dims": volume.dims,
        "results": results,
    }))
}

/// Options of `bench tf-edit`.
pub struct TfEditBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub technique: &'a str,
    /// Image edge in pixels.
    pub size: u32,
    /// Largest volume edge after downsampling (keeps lavapipe runs short).
    pub max_dim: u32,
    pub photons_per_pass: u32,
    pub passes: u32,
    pub bounces: u32,
    pub segments: u32,
    /// Timed repetitions of each edit; the medians are reported.
    pub repeats: u32,
    /// `photon`: measure the work census (`tf_edit_census`) instead of the update's speed.
    pub census: bool,
    /// `photon`: without per-sample photon sums (`PhotonParams::sample_cache_bytes` 0).
    pub segment_sums: bool,
    /// The scenarios to measure by name (empty: all).
    pub scenarios: &'a [String],
}

/// One TF edit of a scenario: a name and the edited TF.
pub(crate) struct Edit {
    pub name: &'static str,
    pub tf: TransferFunction,
}

/// The engine CT's two materials (histogram of engine.vti): the block around v ≈ 0.5–0.63 and
/// the dense parts above 0.75; below 0.4 is air and partial volume.
pub(crate) fn engine_tf() -> TransferFunction {
    TransferFunction {
        points: vec![
            tf_point(0.0, [0.0; 3], 0.0),
            tf_point(0.45, [0.6, 0.65, 0.75], 0.0),
            tf_point(0.50, [0.6, 0.65, 0.75], 0.25),
            tf_point(0.62, [0.6, 0.65, 0.75], 0.25),
            tf_point(0.68, [0.6, 0.65, 0.75], 0.0),
            tf_point(0.72, [0.9, 0.55, 0.25], 0.0),
            tf_point(0.78, [0.9, 0.55, 0.25], 1.0),
            tf_point(1.0, [0.9, 0.55, 0.25], 1.0),
        ],
    }
}

pub(crate) fn tf_point(value: f32, color: [f32; 3], opacity: f32) -> TfPoint {
    TfPoint {
        value,
        color,
        opacity,
    }
}

fn scaled_colors(
    tf: &TransferFunction,
    f: impl Fn(usize, &TfPoint) -> Option<TfPoint>,
) -> TransferFunction {
    TransferFunction {
        points: tf
            .points
            .iter()
            .enumerate()
            .map(|(i, p)| f(i, p).unwrap_or(*p))
            .collect(),
    }
}

/// The four edits of the issue on a TF: one material's colour, one material removed, the
/// skin/outer layer, everything. `materials` lists the point index ranges of (densest
/// material, removable material, outer layer).
fn edits_for(
    tf: &TransferFunction,
    colour: std::ops::Range<usize>,
    removed: std::ops::Range<usize>,
    outer: std::ops::Range<usize>,
) -> Vec<Edit> {
    vec![
        Edit {
            name: "material colour",
            tf: scaled_colors(tf, |i, p| {
                colour.contains(&i).then_some(TfPoint {
                    color: [0.2, 0.35, 0.9],
                    ..*p
                })
            }),
        },
        Edit {
            name: "material removed",
            tf: scaled_colors(tf, |i, p| {
                removed
                    .contains(&i)
                    .then_some(TfPoint { opacity: 0.0, ..*p })
            }),
        },
        Edit {
            name: "outer layer",
            tf: scaled_colors(tf, |i, p| {
                outer.contains(&i).then_some(TfPoint {
                    color: p.color.map(|c| c * 0.6),
                    opacity: p.opacity * 0.5,
                    ..*p
                })
            }),
        },
        Edit {
            name: "global",
            tf: scaled_colors(tf, |_, p| {
                Some(TfPoint {
                    color: p.color.map(|c| c * 0.8),
                    opacity: p.opacity * 0.9,
                    ..*p
                })
            }),
        },
    ]
}

/// A volume, view and TF, with the edits `bench tf-edit` measures on it.
pub(crate) struct Scenario {
    pub name: &'static str,
    pub dataset: String,
    pub volume: voxlight_volumes::Volume,
    pub camera: Camera,
    pub tf: TransferFunction,
    pub edits: Vec<Edit>,
}

/// The scenarios in the spirit of the historygram paper's Table 1: the Cornell phantom, the
/// engine CT and the chest CT, each with a colour edit, a removed material, the outer layer
/// and a global edit.
pub(crate) fn tf_edit_scenarios(options: &TfEditBench) -> anyhow::Result<Vec<Scenario>> {
    const NAMES: [&str; 3] = ["cornell", "engine", "chest"];
    if let Some(unknown) = options
        .scenarios
        .iter()
        .find(|s| !NAMES.contains(&s.as_str()))
    {
        anyhow::bail!(
            "tf-edit: no scenario `{unknown}` (there are {})",
            NAMES.join(", ")
        );
    }
    let wanted =
        |name: &str| options.scenarios.is_empty() || options.scenarios.iter().any(|s| s == name);
    let mut out = Vec::new();
    if wanted("cornell") {
        out.push(cornell_scenario(options)?);
    }
    let Some(dir) = options.data_dir else {
        eprintln!("tf-edit: no data folder (../shared/data); only the Cornell phantom is measured");
        return Ok(out);
    };
    for (name, rel) in [("engine", "vti/engine.vti"), ("chest", "ct-chest-lidc")] {
        if !wanted(name) {
            continue;
        }
        let path = dir.join(rel);
        if !path.exists() {
            eprintln!(
                "tf-edit: {} is missing; scenario `{name}` skipped",
                path.display()
            );
            continue;
        }
        let mut volume = voxlight_volumes::load(&path)
            .with_context(|| format!("loading {}", path.display()))?
            .downsampled(options.max_dim);
        volume.name = rel.to_owned();
        let (tf, edits) = if name == "engine" {
            let tf = engine_tf();
            let edits = edits_for(&tf, 6..8, 6..8, 2..4);
            (tf, edits)
        } else {
            // HU default: [-200, 0, 150, 300, 1200]: bone 3..5, soft tissue 1..3, skin and
            // the outer soft layer 0..2.
            let tf = voxlight_app::datasets::default_tf(&volume);
            let n = tf.points.len();
            let edits = if n >= 5 {
                edits_for(&tf, 3..5, 1..3, 0..2)
            } else {
                edits_for(&tf, n - 1..n, 0..n, 0..1)
            };
            (tf, edits)
        };
        out.push(Scenario {
            name,
            dataset: format!(
                "{rel}@{}x{}x{}",
                volume.dims[0], volume.dims[1], volume.dims[2]
            ),
            volume,
            camera: Camera::default(),
            tf,
            edits,
        });
    }
    Ok(out)
}

/// The Cornell phantom's scenario.
fn cornell_scenario(options: &TfEditBench) -> anyhow::Result<Scenario> {
    let mut cornell = voxlight_volumes::phantom("cornell", options.max_dim.min(64))?;
    cornell.name = "phantom:cornell".to_owned();
    let tf = voxlight_app::datasets::cornell_tf();
    // cornell_tf: a leading transparent pair, then two points per material in
    // CORNELL_MATERIALS order (medium, left, right, white walls, tall block, sphere).
    let material = |name: &str| {
        let i = voxlight_volumes::CORNELL_MATERIALS
            .iter()
            .position(|(n, _)| *n == name)
            .unwrap_or(0);
        let first = tf.points.len() - 2 * (voxlight_volumes::CORNELL_MATERIALS.len() - i);
        first..first + 2
    };
    let edits = edits_for(
        &tf,
        material("sphere"),
        material("tall block"),
        material("white walls"),
    );
    Ok(Scenario {
        name: "cornell",
        dataset: format!("phantom:cornell@{}", cornell.dims[0]),
        volume: cornell,
        // Into the open front (z = max), y up.
        camera: Camera {
            eye: [0.0, 0.0, 2.6],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 28.0,
        },
        tf,
        edits,
    })
}

/// `bench tf-edit --technique photon`: for each scenario and edit, a full recompute with the
/// new TF vs the incremental (historygram) update of the old state, in the same run, with
/// the pictures compared (max_abs_diff) and every buffer compared bit for bit. Also measures
/// the update without the spatial historygram.
pub fn tf_edit(options: &TfEditBench) -> anyhow::Result<serde_json::Value> {
    use voxlight_engine::techniques::photon::{Invalidation, Photon, PhotonParams};
    if options.technique != "photon" {
        anyhow::bail!(
            "bench tf-edit measures incremental TF updates of `photon` and `irradiance` (got `{}`)",
            options.technique
        );
    }
    if options.census {
        return tf_edit_census(options);
    }
    let engine = Engine::new()?;
    let params = photon_params(options);
    // The same update with the paper's spatial historygram and with none (any changed photon
    // invalidates every segment), to measure what each saves, and with the delta scatter off
    // (every segment a change reaches gathered from the change grid).
    let variants = [
        (
            Invalidation::SpatialHistogram.name(),
            PhotonParams {
                invalidation: Invalidation::SpatialHistogram,
                ..params
            },
        ),
        (
            Invalidation::AnyPhoton.name(),
            PhotonParams {
                invalidation: Invalidation::AnyPhoton,
                ..params
            },
        ),
        (
            "no_scatter",
            PhotonParams {
                scatter_bytes: 0,
                ..params
            },
        ),
    ];
    let mut rows = Vec::new();
    for scenario in tf_edit_scenarios(options)? {
        let gpu_volume = engine.upload_volume(&scenario.volume)?;
        let base = scenario_scene(&scenario, options);
        let mut full = Photon::new(&engine, Arc::clone(&gpu_volume), &base, params)?;
        let mut incremental = Photon::new(&engine, Arc::clone(&gpu_volume), &base, params)?;
        let mut others = variants
            .iter()
            .map(|(_, p)| Photon::new(&engine, Arc::clone(&gpu_volume), &base, *p))
            .collect::<Result<Vec<_>, _>>()?;
        // Warm-up (first dispatches compile on some drivers).
        full.recompute(&engine, &base, options.passes)?;
        for edit in &scenario.edits {
            let scene = Scene {
                tf: edit.tf.clone(),
                ..base.clone()
            };
            let query = voxlight_engine::tf::query_historygram(&base.tf, &scene.tf);
            let (mut full_times, mut incremental_times) = (Vec::new(), Vec::new());
            let mut report = Default::default();
            for repeat in 0..options.repeats {
                incremental.recompute(&engine, &base, options.passes)?;
                // Alternate which runs first, so that neither always finds the caches warm.
                for run_full in [repeat % 2 == 0, repeat % 2 == 1] {
                    let started = Instant::now();
                    if run_full {
                        full.recompute(&engine, &scene, options.passes)?;
                        full_times.push(started.elapsed().as_secs_f64() * 1000.0);
                    } else {
                        report = incremental.update_tf(&engine, &scene, &base.tf)?;
                        incremental_times.push(started.elapsed().as_secs_f64() * 1000.0);
                    }
                }
            }
            let spread = |times: &[f64]| {
                let lo = times.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = times.iter().copied().fold(0.0, f64::max);
                [lo, hi]
            };
            let (full_range, incremental_range) = (spread(&full_times), spread(&incremental_times));
            let (full_ms, incremental_ms) = (median(full_times), median(incremental_times));
            for other in &mut others {
                other.recompute(&engine, &base, options.passes)?;
            }

            let a = incremental.read_state(&engine)?;
            let b = full.read_state(&engine)?;
            let mut bit_exact = a == b;
            let mut variant_rows = serde_json::Map::new();
            for (other, (variant, _)) in others.iter_mut().zip(&variants) {
                let started = Instant::now();
                let r = other.update_tf(&engine, &scene, &base.tf)?;
                let ms = started.elapsed().as_secs_f64() * 1000.0;
                bit_exact &= other.read_state(&engine)? == b;
                variant_rows.insert(
                    (*variant).to_owned(),
                    json!({
                        "incremental_ms": ms,
                        "speedup": full_ms / ms.max(1e-6),
                        "segments_recomputed_pct": r.segments_recomputed_pct(),
                    }),
                );
            }
            let max_abs_diff = a
                .hdr
                .iter()
                .zip(&b.hdr)
                .flat_map(|(x, y)| (0..3).map(move |k| (x[k] - y[k]).abs()))
                .fold(0.0f32, f32::max);
            let speedup = full_ms / incremental_ms.max(1e-6);
            eprintln!(
                "{} / {}: full {full_ms:.1} ms, incremental {incremental_ms:.1} ms ({speedup:.2}×; \
                 fastest {:.1} ms, slowest {:.1} ms), \
                 retraced {:.1}%, segments {:.1}%, query bins {}, max_abs_diff {max_abs_diff}, \
                 bit-exact {bit_exact}; other segment tests: {}",
                scenario.name,
                edit.name,
                incremental_range[0],
                incremental_range[1],
                report.photons_retraced_pct(),
                report.segments_recomputed_pct(),
                query.count_ones(),
                serde_json::Value::Object(variant_rows.clone()),
            );
            rows.push(json!({
                "name": scenario.name,
                "dataset": scenario.dataset,
                "edit": edit.name,
                "full_ms": full_ms,
                "incremental_ms": incremental_ms,
                "full_ms_range": full_range,
                "incremental_ms_range": incremental_range,
                "speedup": speedup,
                "photons_retraced_pct": report.photons_retraced_pct(),
                "segments_recomputed_pct": report.segments_recomputed_pct(),
                "segments_from_changes_pct": 100.0 * report.segments_delta as f64
                    / report.segments.max(1) as f64,
                "max_abs_diff": max_abs_diff,
                "bit_exact": bit_exact,
                "query_bins": query.count_ones(),
                "records_changed": report.records_changed,
                "segment_test": params.invalidation.name(),
                "per_sample_sums": incremental.budget().sample_cache_samples > 0,
                "other_segment_tests": variant_rows,
            }));
        }
    }
    let mut result = photon_bench_json("tf-edit", options, &engine, rows);
    result["invalidation"] = json!(params.invalidation.name());
    Ok(result)
}

/// What `bench tf-edit --technique photon` reports besides its rows.
fn photon_bench_json(
    bench: &str,
    options: &TfEditBench,
    engine: &Engine,
    rows: Vec<serde_json::Value>,
) -> serde_json::Value {
    json!({
        "bench": bench,
        "technique": options.technique,
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "width": options.size,
        "height": options.size,
        "photons": options.photons_per_pass as u64 * options.passes as u64,
        "passes": options.passes,
        "bounces": options.bounces,
        "segments": options.segments,
        "repeats": options.repeats,
        "scenarios": rows,
    })
}

/// The photon map `bench tf-edit` measures.
fn photon_params(options: &TfEditBench) -> voxlight_engine::techniques::photon::PhotonParams {
    use voxlight_engine::techniques::photon::{Invalidation, PhotonParams};
    PhotonParams {
        photons_per_pass: options.photons_per_pass,
        max_passes: options.passes,
        bounces: options.bounces,
        segments: options.segments,
        invalidation: Invalidation::DirtyCells,
        sample_cache_bytes: if options.segment_sums {
            0
        } else {
            PhotonParams::default().sample_cache_bytes
        },
        ..PhotonParams::default()
    }
}

/// A scenario's scene with its first TF.
fn scenario_scene(scenario: &Scenario, options: &TfEditBench) -> Scene {
    Scene {
        camera: scenario.camera,
        tf: scenario.tf.clone(),
        lights: voxlight_app::datasets::default_lights_for(&scenario.volume),
        viewport: Viewport {
            width: options.size,
            height: options.size,
        },
        target_iterations: options.passes,
        ..Scene::default()
    }
}

/// `bench tf-edit --technique photon --census`: what any bit-exact update could save. For
/// each scenario and edit, the work census of the full recompute with the old and with the new
/// TF (`Photon::census`), what it bounds (`WorkBound`: the least share of the new trace's
/// tracking steps and of the new gather's terms an exact update must redo) and the highest
/// speedup that leaves, with the trace's share of the full recompute's time measured in the
/// same run (median of `repeats`).
pub fn tf_edit_census(options: &TfEditBench) -> anyhow::Result<serde_json::Value> {
    use voxlight_engine::techniques::photon::{Photon, WorkBound};
    let engine = Engine::new()?;
    let params = photon_params(options);
    let ms = |d: Duration| d.as_secs_f64() * 1000.0;
    let mut rows = Vec::new();
    for scenario in tf_edit_scenarios(options)? {
        let gpu_volume = engine.upload_volume(&scenario.volume)?;
        let base = scenario_scene(&scenario, options);
        let mut photon = Photon::new(&engine, Arc::clone(&gpu_volume), &base, params)?;
        // Warm-up (first dispatches compile on some drivers).
        photon.recompute(&engine, &base, options.passes)?;
        let old = photon.census(&engine, &base, options.passes)?;
        for edit in &scenario.edits {
            let scene = Scene {
                tf: edit.tf.clone(),
                ..base.clone()
            };
            let query_bins =
                voxlight_engine::tf::query_historygram(&base.tf, &scene.tf).count_ones();
            let new = photon.census(&engine, &scene, options.passes)?;
            let bound = WorkBound::between(&old, &new);
            let (mut trace, mut rest) = (Vec::new(), Vec::new());
            for _ in 0..options.repeats {
                let (t, r) = photon.recompute_split(&engine, &scene, options.passes)?;
                trace.push(ms(t));
                rest.push(ms(r));
            }
            let (trace_ms, rest_ms) = (median(trace), median(rest));
            let trace_share = trace_ms / (trace_ms + rest_ms).max(1e-9);
            let speedup_bound = bound.speedup_bound(trace_share);
            let pct = |part: u64, whole: u64| 100.0 * part as f64 / whole.max(1) as f64;
            eprintln!(
                "{} / {} ({query_bins} bins): records changed {:.1}% ({:.1}% power only), their \
                 new terms {:.1}% of the gather's; paths moved {:.1}%, steps to track {:.1}% of \
                 the trace's ({:.1}% from their flights' start); trace {trace_ms:.1} ms of \
                 {:.1} ms: an exact update is at most {speedup_bound:.2}× faster",
                scenario.name,
                edit.name,
                pct(bound.records_changed, bound.records),
                pct(bound.records_power_only, bound.records),
                100.0 * bound.terms_share(),
                pct(bound.paths_moved, bound.paths),
                100.0 * bound.steps_share(),
                pct(bound.steps_retracked, bound.steps),
                trace_ms + rest_ms,
            );
            rows.push(json!({
                "name": scenario.name,
                "dataset": scenario.dataset,
                "edit": edit.name,
                "query_bins": query_bins,
                "records_changed_pct": pct(bound.records_changed, bound.records),
                "records_power_only_pct": pct(bound.records_power_only, bound.records),
                "paths_moved_pct": pct(bound.paths_moved, bound.paths),
                "terms": bound.terms,
                "changed_terms_pct": 100.0 * bound.terms_share(),
                "moved_old_terms_pct": pct(bound.terms_moved_old, bound.terms),
                "steps": bound.steps,
                "steps_to_track_pct": 100.0 * bound.steps_share(),
                "steps_from_flight_start_pct": pct(bound.steps_retracked, bound.steps),
                "full_trace_ms": trace_ms,
                "full_rest_ms": rest_ms,
                "trace_share": trace_share,
                "speedup_bound": speedup_bound,
            }));
        }
    }
    Ok(photon_bench_json("tf-edit-census", options, &engine, rows))
}

/// The median of some timings (the mean of the middle two for an even count).
/// The median preview time (ms) at each of `DIVISORS` over `frames` frames of an orbit 5° apart:
/// `turn(scene, angle)` places the camera `angle` radians along it. Fails when a camera move
/// rebuilt the light volume.
pub(crate) fn orbit_previews(
    engine: &Engine,
    renderer: &mut voxlight_engine::Renderer,
    scene: &mut Scene,
    frames: u32,
    mut turn: impl FnMut(&mut Scene, f32),
) -> anyhow::Result<Vec<(u32, f64)>> {
    let mut medians = Vec::new();
    for divisor in voxlight_engine::preview::DIVISORS {
        let mut times = Vec::new();
        for frame in 0..frames {
            turn(scene, (frame as f32 * 5.0).to_radians());
            let (_, report) = renderer.preview_frame(engine, scene, divisor, LightDetail::Full)?;
            anyhow::ensure!(
                !report.light_rebuilt,
                "a camera move rebuilt the light volume"
            );
            times.push(report.view_time.as_secs_f64() * 1000.0);
        }
        medians.push((divisor, median(times)));
    }
    Ok(medians)
}

/// Prints each divisor's median of `orbit_previews` (`label at 1/d: … ms/frame (note)`) and
/// returns them as the JSON results' `previews` list.
pub(crate) fn report_divisors(
    label: &str,
    note: &str,
    medians: &[(u32, f64)],
    frames: u32,
) -> Vec<serde_json::Value> {
    medians
        .iter()
        .map(|&(divisor, ms)| {
            eprintln!("{label} at 1/{divisor}: {ms:.1} ms/frame ({note})");
            json!({"divisor": divisor, "median_ms": ms, "frames": frames})
        })
        .collect()
}

/// ms per interactive preview frame (engine::preview: view rays, tone mapping and readback)
/// on the 256³ CT of `bench raymarch`, at each size and resolution divisor, over an orbit of
/// 5° per frame (as VTK's baseline turns its camera), with the light volume's build time and
/// one `raymarch` iteration at full resolution measured in the same run for the ratio.
pub fn preview(options: &RaymarchBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let (dataset, volume) = ct_256(options.data_dir)?;
    let gpu_volume = engine.upload_volume(&volume)?;
    let frames = options.iterations.max(1);
    let mut results = Vec::new();
    for &size in options.sizes {
        let mut scene = speed_scene(&volume, size);
        let mut renderer = engine.create_renderer("raymarch", Arc::clone(&gpu_volume), &scene)?;
        // One whole raymarch iteration (a long one runs in bands: step until it completes).
        let started = Instant::now();
        while renderer.iteration() == 0 {
            renderer.step(&engine, &scene, Duration::ZERO)?;
        }
        let raymarch_ms = started.elapsed().as_secs_f64() * 1000.0;
        // The first preview builds the light volume (and compiles nothing new: pipelines exist).
        let (_, first) = renderer.preview_frame(&engine, &scene, 1, LightDetail::Full)?;
        let light_ms = first.light_time.as_secs_f64() * 1000.0;
        let eye = scene.camera.eye;
        let medians = orbit_previews(
            &engine,
            &mut renderer,
            &mut scene,
            frames,
            |scene, angle| {
                let (sin, cos) = angle.sin_cos();
                scene.camera.eye = [
                    eye[0] * cos - eye[1] * sin,
                    eye[0] * sin + eye[1] * cos,
                    eye[2],
                ];
            },
        )?;
        let per_divisor = report_divisors(
            &format!("preview {size}x{size}"),
            &format!("raymarch iteration {raymarch_ms:.0} ms, light volume {light_ms:.0} ms"),
            &medians,
            frames,
        );
        results.push(json!({
            "width": size,
            "height": size,
            "raymarch_iteration_ms": raymarch_ms,
            "light_volume_ms": light_ms,
            "previews": per_divisor,
        }));
    }
    Ok(json!({
        "bench": "preview",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "dataset": dataset,
        "dims": volume.dims,
        "results": results,
    }))
}
