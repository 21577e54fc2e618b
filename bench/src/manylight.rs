//! `voxlight bench manylight`: the paper's Table 2 experiment (Weber et al. 2013) on the adapter
//! at hand. For each virtual-light count: the time to trace the lights and build their shadow
//! maps, the time of one multiple-scattering gather with ray-marched transmittance and with
//! AVSM point and trilinear lookups, and each one's error against a `pathtrace` reference; then
//! the time from a TF edit to the first frame that shows it.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::json;
use voxlight_engine::Technique;
use voxlight_engine::image_stats::relative_rms;
use voxlight_engine::techniques::manylight::gpu::TransmittanceMode;
use voxlight_engine::techniques::manylight::{Manylight, ManylightConfig};
use voxlight_engine::{Change, Engine, GpuVolume, Renderer, Scene};
use voxlight_protocol::{Camera, TfPoint, TransferFunction, Viewport, default_lights};

pub struct ManylightBench<'a> {
    pub data_dir: Option<&'a Path>,
    /// Image edge in pixels (the paper: 800).
    pub size: u32,
    /// Virtual-light counts to measure.
    pub vls: &'a [u32],
    /// AVSM texels per cube-face edge (the paper: 40–48) and nodes per texel (8–12).
    pub face_res: u32,
    pub nodes: u32,
    /// Gather passes timed per mode.
    pub iterations: u32,
    /// Samples per pixel of the `pathtrace` reference.
    pub reference_spp: u32,
}

/// Most virtual lights one light path leaves.
const MAX_BOUNCES: u32 = 8;
/// Progressive iterations of the images compared with the reference.
const IMAGE_ITERATIONS: u32 = 4;

fn render(
    engine: &Engine,
    renderer: &mut Renderer,
    scene: &Scene,
) -> anyhow::Result<Vec<[f32; 3]>> {
    while !renderer.converged(scene) {
        renderer.step(engine, scene, Duration::from_secs(5))?;
    }
    Ok(renderer.read_hdr(engine)?)
}

fn manylight_renderer(
    engine: &Engine,
    volume: &Arc<GpuVolume>,
    scene: &Scene,
    config: ManylightConfig,
) -> anyhow::Result<Renderer> {
    let technique = Manylight::new(engine, volume.clone(), scene, config)?;
    Ok(Renderer::with_technique(
        engine,
        Box::new(technique),
        volume.clone(),
        scene,
    )?)
}

pub fn manylight(options: &ManylightBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let (dataset, volume) = crate::engine::ct_256(options.data_dir)?;
    let gpu_volume = engine.upload_volume(&volume)?;
    let scene = Scene {
        camera: Camera::default(),
        tf: voxlight_app::datasets::default_tf(&volume),
        lights: default_lights(),
        viewport: Viewport {
            width: options.size,
            height: options.size,
        },
        target_iterations: IMAGE_ITERATIONS,
        seed: 3,
        ..Scene::default()
    };

    let reference_scene = Scene {
        target_iterations: options.reference_spp,
        ..scene.clone()
    };
    let started = Instant::now();
    let mut reference_renderer =
        engine.create_renderer("pathtrace", gpu_volume.clone(), &reference_scene)?;
    let reference = render(&engine, &mut reference_renderer, &reference_scene)?;
    eprintln!(
        "manylight: pathtrace reference, {} spp, {:.1} s",
        options.reference_spp,
        started.elapsed().as_secs_f64()
    );

    let mut rows = Vec::new();
    for &slots in options.vls {
        let config = ManylightConfig {
            vls: slots.max(1),
            max_bounces: MAX_BOUNCES,
            face_res: options.face_res,
            nodes: options.nodes,
            mode: TransmittanceMode::AvsmPoint,
            ..ManylightConfig::default()
        };
        let mut technique = Manylight::new(&engine, gpu_volume.clone(), &scene, config)?;
        technique.rebuild(&engine, &scene)?; // warm-up
        let build = technique.rebuild(&engine, &scene)?;
        let (live, paths) = technique.virtual_light_count();
        let mut gather_ms = |mode| -> anyhow::Result<f64> {
            technique.set_mode(&engine, &scene, mode);
            technique.time_gather(&engine, &scene, 1)?; // warm-up
            let elapsed = technique.time_gather(&engine, &scene, options.iterations)?;
            Ok(elapsed.as_secs_f64() * 1000.0 / options.iterations as f64)
        };
        let rm_ms = gather_ms(TransmittanceMode::RayMarched)?;
        let point_ms = gather_ms(TransmittanceMode::AvsmPoint)?;
        let trilinear_ms = gather_ms(TransmittanceMode::AvsmTrilinear)?;
        let error = |mode| -> anyhow::Result<f64> {
            let mut renderer = manylight_renderer(
                &engine,
                &gpu_volume,
                &scene,
                ManylightConfig { mode, ..config },
            )?;
            Ok(relative_rms(
                &render(&engine, &mut renderer, &scene)?,
                &reference,
            ))
        };
        let row = json!({
            "vls": config.vl_count(),
            "vls_stored": live,
            "light_paths": paths,
            "vl_build_ms": build.vls.as_secs_f64() * 1000.0,
            "avsm_build_ms": build.avsm.as_secs_f64() * 1000.0,
            "rm_ms": rm_ms,
            "avsm_point_ms": point_ms,
            "avsm_trilinear_ms": trilinear_ms,
            "speedup": rm_ms / point_ms,
            "speedup_trilinear": rm_ms / trilinear_ms,
            "error_rm": error(TransmittanceMode::RayMarched)?,
            "error_avsm_point": error(TransmittanceMode::AvsmPoint)?,
            "error_avsm_trilinear": error(TransmittanceMode::AvsmTrilinear)?,
        });
        eprintln!("manylight: {row}");
        rows.push(row);
    }

    // From a TF edit to the first frame that shows it (one iteration with the previous lights,
    // tone map, readback), then the frame that starts the rebuild, then an ordinary frame; with the
    // largest VL count and trilinear lookups.
    let largest = options.vls.iter().copied().max().unwrap_or(256);
    let config = ManylightConfig {
        vls: largest.max(1),
        max_bounces: MAX_BOUNCES,
        face_res: options.face_res,
        nodes: options.nodes,
        mode: TransmittanceMode::AvsmTrilinear,
        ..ManylightConfig::default()
    };
    let mut renderer = manylight_renderer(&engine, &gpu_volume, &scene, config)?;
    render(&engine, &mut renderer, &scene)?;
    let mut edited = scene.clone();
    for point in &mut edited.tf.points {
        point.opacity *= 0.7;
    }
    let change = Change::tf(&scene.tf, &edited.tf);
    let started = Instant::now();
    renderer.apply(&engine, &edited, &change)?;
    next_picture(&engine, &mut renderer, &edited)?;
    let first_frame_ms = started.elapsed().as_secs_f64() * 1000.0;
    // Then the partial rebuild (the affected paths traced again, the maps built in parts of a
    // step each, no picture meanwhile) up to the first picture with the rebuilt lights.
    let started = Instant::now();
    next_picture(&engine, &mut renderer, &edited)?;
    let rebuild_frame_ms = started.elapsed().as_secs_f64() * 1000.0;
    // Then an ordinary frame (an iteration, tone map, readback) for comparison.
    let started = Instant::now();
    next_picture(&engine, &mut renderer, &edited)?;
    let frame_ms = started.elapsed().as_secs_f64() * 1000.0;

    let tf_edits = tf_edit_rows(&engine, &gpu_volume, &scene, config)?;

    Ok(json!({
        "bench": "manylight",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "dataset": dataset,
        "dims": volume.dims,
        "size": options.size,
        "face_res": options.face_res,
        "nodes": options.nodes,
        "max_bounces": MAX_BOUNCES,
        "reference_spp": options.reference_spp,
        "image_iterations": IMAGE_ITERATIONS,
        "rows": rows,
        "tf_edit_first_frame_ms": first_frame_ms,
        "rebuild_frame_ms": rebuild_frame_ms,
        "frame_ms": frame_ms,
        "tf_edits": tf_edits,
    }))
}

/// Zero-budget steps up to the next completed iteration (a long one runs in bands, a TF edit's
/// rebuild in parts), then its frame.
fn next_picture(engine: &Engine, renderer: &mut Renderer, scene: &Scene) -> anyhow::Result<()> {
    loop {
        let report = renderer.step(engine, scene, Duration::ZERO)?;
        if report.iterations_done > 0 || report.converged {
            break;
        }
    }
    renderer.frame(engine, scene)?;
    Ok(())
}

/// `tf` with the points at or above `from` changed by `edit`, and knots at `from` so that
/// nothing below it changes (a local edit of the densest values).
fn edit_above(tf: &TransferFunction, from: f32, edit: impl Fn(&mut TfPoint)) -> TransferFunction {
    let at = |v: f32| -> TfPoint {
        let p = &tf.points;
        let i = p.iter().position(|q| q.value >= v).unwrap_or(p.len() - 1);
        if i == 0 {
            return TfPoint { value: v, ..p[0] };
        }
        let (a, b) = (&p[i - 1], &p[i]);
        let f = ((v - a.value) / (b.value - a.value).max(1e-9)).clamp(0.0, 1.0);
        let mix = |x: f32, y: f32| x + (y - x) * f;
        TfPoint {
            value: v,
            color: [0, 1, 2].map(|k| mix(a.color[k], b.color[k])),
            opacity: mix(a.opacity, b.opacity),
        }
    };
    let mut points: Vec<TfPoint> = tf
        .points
        .iter()
        .filter(|p| p.value < from)
        .cloned()
        .collect();
    points.push(at(from));
    let mut above = vec![at(from + 1e-3)];
    above.extend(tf.points.iter().filter(|p| p.value > from + 1e-3).copied());
    for p in &mut above {
        edit(p);
    }
    points.extend(above);
    TransferFunction { points }
}

/// Beyond the paper: a TF edit retraces only the light paths and rebuilds only the shadow
/// maps whose historygrams meet it (`Manylight::update_tf`), against a full rebuild of the
/// same light paths with the new TF: the time of each, what was redone, and the RMS
/// difference of the two pictures (the saving's cost in error).
fn tf_edit_rows(
    engine: &Engine,
    volume: &Arc<GpuVolume>,
    scene: &Scene,
    config: ManylightConfig,
) -> anyhow::Result<Vec<serde_json::Value>> {
    let first = scene.tf.points.first().map_or(0.0, |p| p.value);
    let dense = first + 0.75 * (1.0 - first);
    // The knots of the local edits are in the TF before the edit too, so that the table below
    // them is computed from the same points (bit for bit the same).
    let scene = &Scene {
        tf: edit_above(&scene.tf, dense, |_| {}),
        ..scene.clone()
    };
    let edits = [
        (
            "colour of the densest quarter",
            edit_above(&scene.tf, dense, |p| p.color = [0.3, 0.5, 0.95]),
        ),
        (
            "densest quarter removed",
            edit_above(&scene.tf, dense, |p| p.opacity = 0.0),
        ),
        (
            "global opacity x0.7",
            TransferFunction {
                points: scene
                    .tf
                    .points
                    .iter()
                    .map(|p| TfPoint {
                        opacity: p.opacity * 0.7,
                        ..*p
                    })
                    .collect(),
            },
        ),
    ];
    let mut rows = Vec::new();
    for (name, tf) in edits {
        let edited = Scene {
            tf,
            ..scene.clone()
        };
        let mut incremental = Manylight::new(engine, volume.clone(), scene, config)?;
        incremental.rebuild(engine, scene)?;
        let (_, paths) = incremental.virtual_light_count();
        incremental.apply(engine, &edited, &Change::tf(&scene.tf, &edited.tf))?;
        let update = incremental.update_tf(engine, &edited)?;
        let mut full = Manylight::new(engine, volume.clone(), &edited, config)?;
        let started = Instant::now();
        full.rebuild_paths(engine, &edited, Some(paths))?;
        let full_ms = started.elapsed().as_secs_f64() * 1000.0;
        let picture = |technique: Manylight| -> anyhow::Result<Vec<[f32; 3]>> {
            let mut renderer =
                Renderer::with_technique(engine, Box::new(technique), volume.clone(), &edited)?;
            render(engine, &mut renderer, &edited)
        };
        let (a, b) = (picture(incremental)?, picture(full)?);
        let incremental_ms = update.time.as_secs_f64() * 1000.0;
        let row = json!({
            "edit": name,
            "light_paths": update.paths,
            "paths_retraced_pct": 100.0 * update.paths_retraced as f64 / update.paths.max(1) as f64,
            "lights": update.lights,
            "lights_replaced": update.lights_replaced,
            "maps_rebuilt_pct": 100.0 * update.maps_rebuilt as f64 / update.lights.max(1) as f64,
            "full_rebuild_fallback": update.full_rebuild,
            "incremental_ms": incremental_ms,
            "full_ms": full_ms,
            "speedup": full_ms / incremental_ms.max(1e-6),
            "relative_rms_vs_full": relative_rms(&a, &b),
        });
        eprintln!("manylight tf edit: {row}");
        rows.push(row);
    }
    Ok(rows)
}
