//! `voxlight bench preview-vtk`: the interactive preview on the scenes of VTK's baseline
//! (../shared/baselines/vtk/bench_vtk.py): the same volumes, viewport, transfer functions,
//! camera and 5° orbit, so that `scripts/bench_vs_vtk.sh` can put the two side by side.
//!
//! VTK's opacity α is per unit of its world distance (`ScalarOpacityUnitDistance` 1: one voxel
//! of the bonsai, one millimetre of the CT); our extinction is per unit of a world whose longest
//! box edge is 1. So each TF sample's σ = −ln(1 − α) · (VTK units per our unit). Colours become
//! albedos. The lighting differs on purpose: VTK shades with gradients and a headlight, the
//! preview with the scene's default lights through a light volume (shadows and the sky).

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use serde_json::json;
use voxlight_engine::Engine;
use voxlight_engine::preview::LightDetail;
use voxlight_protocol::{Camera, TfPoint, TransferFunction};
use voxlight_volumes::Volume;

/// One of bench_vtk.py's transfer functions: (data value, α) and (data value, rgb), piecewise
/// linear.
struct VtkTf {
    opacity: &'static [(f64, f64)],
    color: &'static [(f64, [f64; 3])],
}

/// bench_vtk.py's CT_TF (3D Slicer's CT-Bone preset), in HU.
const CT_TF: VtkTf = VtkTf {
    opacity: &[
        (-3024.0, 0.0),
        (-16.4458, 0.0),
        (641.385, 0.715686),
        (3071.0, 0.705882),
    ],
    color: &[
        (-3024.0, [0.0, 0.0, 0.0]),
        (-16.4458, [0.729412, 0.254902, 0.301961]),
        (641.385, [0.905882, 0.815686, 0.552941]),
        (3071.0, [1.0, 1.0, 1.0]),
    ],
};

/// bench_vtk.py's BONSAI_TF: the CT-Bone shape on 0..255.
const BONSAI_TF: VtkTf = VtkTf {
    opacity: &[
        (0.0, 0.0),
        (50.0, 0.0),
        (150.0, 0.715686),
        (255.0, 0.705882),
    ],
    color: &[
        (0.0, [0.0, 0.0, 0.0]),
        (50.0, [0.729412, 0.254902, 0.301961]),
        (150.0, [0.905882, 0.815686, 0.552941]),
        (255.0, [1.0, 1.0, 1.0]),
    ],
};

/// Piecewise-linear lookup, clamped at both ends (as VTK's transfer functions clamp).
fn piecewise<const N: usize>(points: &[(f64, [f64; N])], x: f64) -> [f64; N] {
    let Some(first) = points.first() else {
        return [0.0; N];
    };
    if x <= first.0 {
        return first.1;
    }
    for pair in points.windows(2) {
        let ((x0, y0), (x1, y1)) = (pair[0], pair[1]);
        if x <= x1 {
            let t = if x1 > x0 { (x - x0) / (x1 - x0) } else { 1.0 };
            return std::array::from_fn(|i| y0[i] + t * (y1[i] - y0[i]));
        }
    }
    points[points.len() - 1].1
}

/// Samples of our TF: enough that linear interpolation in σ follows VTK's linear α closely.
const TF_SAMPLES: usize = 64;

/// The TF and density scale that give `volume` VTK's opacity per distance and colours.
/// `vtk_units_per_world`: VTK world units (voxels, mm) per unit of our world.
fn matched_tf(tf: &VtkTf, volume: &Volume, vtk_units_per_world: f64) -> (TransferFunction, f32) {
    let opacity: Vec<(f64, [f64; 1])> = tf.opacity.iter().map(|&(x, a)| (x, [a])).collect();
    let range = (volume.value_max - volume.value_min).max(f64::EPSILON);
    // Data values at the samples, plus every breakpoint inside the volume's range, so that
    // corners of the TF are kept exactly.
    let mut values: Vec<f64> = (0..TF_SAMPLES)
        .map(|i| i as f64 / (TF_SAMPLES - 1) as f64)
        .collect();
    for &(x, _) in tf.opacity.iter() {
        let v = (x - volume.value_min) / range;
        if (0.0..=1.0).contains(&v) {
            values.push(v);
        }
    }
    values.sort_by(f64::total_cmp);
    values.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let sigma = |v: f64| {
        let raw = volume.value_min + v * range;
        let alpha = piecewise(&opacity, raw)[0].clamp(0.0, 0.999_999);
        -(1.0 - alpha).ln() * vtk_units_per_world
    };
    let max_sigma = values.iter().map(|&v| sigma(v)).fold(0.0, f64::max);
    let density_scale = max_sigma.max(f64::EPSILON);
    let points = values
        .iter()
        .map(|&v| {
            let raw = volume.value_min + v * range;
            let rgb = piecewise(tf.color, raw);
            TfPoint {
                value: v as f32,
                color: rgb.map(|c| c as f32),
                opacity: (sigma(v) / density_scale) as f32,
            }
        })
        .collect();
    (TransferFunction { points }, density_scale as f32)
}

/// VTK's `ResetCamera` (view angle 30°, distance = bounding-sphere radius / sin 15°) followed by
/// bench_vtk.py's turn: the bonsai from +z with y up, turned by azimuth 30° and elevation 15°;
/// the CT from anterior (−y), head (+z) up. Returns the camera and the orbit axis.
fn vtk_camera(dataset: &str, extent: [f32; 3]) -> (Camera, [f32; 3]) {
    let radius = 0.5 * extent.iter().map(|e| e * e).sum::<f32>().sqrt();
    let distance = radius / 15f32.to_radians().sin();
    if dataset == "bonsai" {
        let (az, el) = (30f32.to_radians(), 15f32.to_radians());
        let eye = [
            distance * el.cos() * az.sin(),
            distance * el.sin(),
            distance * el.cos() * az.cos(),
        ];
        // View up (0, 1, 0) turned with the elevation (OrthogonalizeViewUp).
        let up = [-el.sin() * az.sin(), el.cos(), -el.sin() * az.cos()];
        let camera = Camera {
            eye,
            target: [0.0; 3],
            up,
            fov_deg: 30.0,
        };
        (camera, up)
    } else {
        let camera = Camera {
            eye: [0.0, -distance, 0.0],
            target: [0.0; 3],
            up: [0.0, 0.0, 1.0],
            fov_deg: 30.0,
        };
        (camera, [0.0, 0.0, 1.0])
    }
}

/// `v` turned by `angle` about the unit `axis` (Rodrigues).
fn rotate(v: [f32; 3], axis: [f32; 3], angle: f32) -> [f32; 3] {
    let (s, c) = angle.sin_cos();
    let dot = v[0] * axis[0] + v[1] * axis[1] + v[2] * axis[2];
    let cross = [
        axis[1] * v[2] - axis[2] * v[1],
        axis[2] * v[0] - axis[0] * v[2],
        axis[0] * v[1] - axis[1] * v[0],
    ];
    std::array::from_fn(|i| v[i] * c + cross[i] * s + axis[i] * dot * (1.0 - c))
}

/// Options of `bench preview-vtk`.
pub struct PreviewVtkBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub sizes: &'a [u32],
    /// Timed frames per size and divisor (bench_vtk.py times 20).
    pub frames: u32,
    /// `bonsai`, `ct` (bench_vtk.py's names).
    pub datasets: &'a [String],
}

/// A VTK-baseline dataset: its folder or file under ../shared/data and its TF.
fn vtk_dataset(name: &str) -> anyhow::Result<(&'static str, &'static VtkTf)> {
    match name {
        "bonsai" => Ok(("vti/bonsai.vti", &BONSAI_TF)),
        "ct" | "chest" => Ok(("ct-chest-lidc", &CT_TF)),
        other => anyhow::bail!("preview-vtk: unknown dataset `{other}` (bonsai, ct)"),
    }
}

pub fn preview_vtk(options: &PreviewVtkBench) -> anyhow::Result<serde_json::Value> {
    let dir = options
        .data_dir
        .context("preview-vtk needs ../shared/data (or --data) for VTK's volumes")?;
    let engine = Engine::new()?;
    let frames = options.frames.max(1);
    let mut results = Vec::new();
    for name in options.datasets {
        let (rel, vtk_tf) = vtk_dataset(name)?;
        let path = dir.join(rel);
        let mut volume =
            voxlight_volumes::load(&path).with_context(|| format!("loading {}", path.display()))?;
        volume.name = rel.to_owned();
        let vtk_units_per_world = (0..3)
            .map(|i| volume.spacing[i] as f64 * volume.dims[i] as f64)
            .fold(0.0, f64::max);
        let (tf, density_scale) = matched_tf(vtk_tf, &volume, vtk_units_per_world);
        let gpu_volume = engine.upload_volume(&volume)?;
        let dataset = if name == "chest" { "ct" } else { name.as_str() };
        let (camera, axis) = vtk_camera(dataset, volume.world_extent());
        for &size in options.sizes {
            let mut scene = crate::engine::timed_scene(camera, tf.clone(), size);
            scene.params.density_scale = density_scale;
            let mut renderer =
                engine.create_renderer("raymarch", Arc::clone(&gpu_volume), &scene)?;
            // Builds the light volume (pipelines exist already).
            let (_, first) = renderer.preview_frame(&engine, &scene, 1, LightDetail::Full)?;
            let light_ms = first.light_time.as_secs_f64() * 1000.0;
            let medians = crate::engine::orbit_previews(
                &engine,
                &mut renderer,
                &mut scene,
                frames,
                |scene, angle| {
                    scene.camera.eye = rotate(camera.eye, axis, angle);
                    scene.camera.up = rotate(camera.up, axis, angle);
                },
            )?;
            let per_divisor = crate::engine::report_divisors(
                &format!("preview-vtk {dataset} {size}x{size}"),
                &format!("light volume {light_ms:.0} ms"),
                &medians,
                frames,
            );
            results.push(json!({
                "dataset": dataset,
                "path": rel,
                "dims": volume.dims,
                "width": size,
                "height": size,
                "density_scale": density_scale,
                "light_volume_ms": light_ms,
                "previews": per_divisor,
            }));
        }
    }
    Ok(json!({
        "bench": "preview-vtk",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "results": results,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn piecewise_interpolates_and_clamps() {
        let points = [(0.0, [0.0]), (10.0, [1.0]), (20.0, [0.5])];
        assert_eq!(piecewise(&points, -5.0), [0.0]);
        assert_eq!(piecewise(&points, 5.0), [0.5]);
        assert_eq!(piecewise(&points, 15.0), [0.75]);
        assert_eq!(piecewise(&points, 99.0), [0.5]);
    }

    #[test]
    fn matched_tf_gives_vtk_opacity_per_voxel() {
        // A 256-voxel cube of spacing 1 (as the bonsai): one voxel is 1/256 of our world.
        let mut volume =
            Volume::from_normalized("cube", [4, 4, 4], [1.0; 3], vec![0; 64]).expect("volume");
        volume.value_min = 0.0;
        volume.value_max = 255.0;
        let (tf, density) = matched_tf(&BONSAI_TF, &volume, 256.0);
        // At data value 150, α per voxel is 0.715686: σ·(1/256) = −ln(1 − α).
        let at = tf
            .points
            .iter()
            .find(|p| (p.value as f64 - 150.0 / 255.0).abs() < 1e-6)
            .expect("breakpoint kept");
        let alpha = 1.0 - (-(at.opacity * density) as f64 / 256.0).exp();
        assert!((alpha - 0.715686).abs() < 1e-4, "alpha {alpha}");
        // Below 50, transparent.
        assert!(
            tf.points
                .iter()
                .filter(|p| p.value < 0.19)
                .all(|p| p.opacity == 0.0)
        );
    }

    #[test]
    fn vtk_bonsai_camera_matches_the_baseline() {
        // bench_vtk.py's first bonsai camera: position − focal point = (412.09, 220.84, 713.75)
        // voxels at distance 853.7 (results.json), one voxel = 1/256. VTK's bounds span the
        // voxel centres (255 voxels), our box the whole voxels (256): 0.4% farther.
        let (camera, _) = vtk_camera("bonsai", [1.0; 3]);
        let expected = [412.09 / 256.0, 220.84 / 256.0, 713.75 / 256.0];
        for (got, want) in camera.eye.iter().zip(expected) {
            assert!((got - want).abs() / want < 0.006, "{:?}", camera.eye);
        }
        let turned = rotate([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], 90f32.to_radians());
        assert!((turned[1] - 1.0).abs() < 1e-6 && turned[0].abs() < 1e-6);
    }
}
