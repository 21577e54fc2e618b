//! Helpers shared by the GPU tests: the engine on whatever adapter exists (lavapipe in CI; a
//! missing adapter fails loudly), phantoms, scenes, rendering to convergence and a CPU
//! reference for optical depth.

#![allow(dead_code)]

use std::sync::{Arc, OnceLock};
use std::time::Duration;

use voxlight_engine::camera::CameraBasis;
use voxlight_engine::{Engine, GpuVolume, Renderer, Scene};
use voxlight_protocol::{Camera, Light, RenderParams, TfPoint, TransferFunction, Viewport};
use voxlight_volumes::Volume;

pub fn engine() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| {
        Engine::new().unwrap_or_else(|e| {
            panic!("GPU tests need an adapter (lavapipe: apt-get install mesa-vulkan-drivers): {e}")
        })
    })
}

pub fn sphere(size: u32) -> (Volume, Arc<GpuVolume>) {
    let volume = voxlight_volumes::phantom("sphere", size).expect("sphere phantom");
    let gpu_volume = engine().upload_volume(&volume).expect("upload");
    (volume, gpu_volume)
}

/// Opacity = v, constant albedo.
pub fn ramp_tf(albedo: f32) -> TransferFunction {
    TransferFunction {
        points: vec![
            TfPoint {
                value: 0.0,
                color: [albedo; 3],
                opacity: 0.0,
            },
            TfPoint {
                value: 1.0,
                color: [albedo; 3],
                opacity: 1.0,
            },
        ],
    }
}

pub fn scene(
    tf: TransferFunction,
    lights: Vec<Light>,
    density_scale: f32,
    size: u32,
    iterations: u32,
) -> Scene {
    Scene {
        camera: Camera::default(),
        tf,
        lights,
        params: RenderParams {
            density_scale,
            g: 0.0,
            exposure: 1.0,
        },
        viewport: Viewport {
            width: size,
            height: size,
        },
        seed: 7,
        target_iterations: iterations,
        ..Scene::default()
    }
}

pub fn render(volume: Arc<GpuVolume>, scene: &Scene) -> (Renderer, Vec<[f32; 3]>) {
    render_with("raymarch", volume, scene)
}

pub fn render_with(
    technique: &str,
    volume: Arc<GpuVolume>,
    scene: &Scene,
) -> (Renderer, Vec<[f32; 3]>) {
    let engine = engine();
    let mut renderer = engine
        .create_renderer(technique, volume, scene)
        .expect("renderer");
    while !renderer.converged(scene) {
        renderer
            .step(engine, scene, Duration::from_secs(10))
            .expect("step");
    }
    let hdr = renderer.read_hdr(engine).expect("hdr");
    (renderer, hdr)
}

/// Trilinear sample of the normalized volume at box-relative u (the CPU twin of
/// sample_volume in shared/volume.wgsl).
pub fn trilinear(volume: &Volume, u: [f32; 3]) -> f32 {
    let d = volume.dims;
    let mut i0 = [0usize; 3];
    let mut i1 = [0usize; 3];
    let mut f = [0f32; 3];
    for k in 0..3 {
        let p = u[k] * d[k] as f32 - 0.5;
        let base = p.floor();
        f[k] = p - base;
        i0[k] = (base as i64).clamp(0, d[k] as i64 - 1) as usize;
        i1[k] = (base as i64 + 1).clamp(0, d[k] as i64 - 1) as usize;
    }
    let at = |x: usize, y: usize, z: usize| volume.normalized(x as u32, y as u32, z as u32);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(at(i0[0], i0[1], i0[2]), at(i1[0], i0[1], i0[2]), f[0]);
    let x10 = lerp(at(i0[0], i1[1], i0[2]), at(i1[0], i1[1], i0[2]), f[0]);
    let x01 = lerp(at(i0[0], i0[1], i1[2]), at(i1[0], i0[1], i1[2]), f[0]);
    let x11 = lerp(at(i0[0], i1[1], i1[2]), at(i1[0], i1[1], i1[2]), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}

/// Optical depth ∫ density·v along the ray through pixel (x, y)'s centre, by fine quadrature.
pub fn reference_optical_depth(
    volume: &Volume,
    camera: &Camera,
    size: u32,
    x: f32,
    y: f32,
    density: f32,
) -> f32 {
    let basis = CameraBasis::new(camera).unwrap();
    let dir = basis.ray_dir(x, y, size, size);
    let ext = volume.world_extent();
    let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
    for k in 0..3 {
        let (a, b) = (
            (-ext[k] / 2.0 - basis.eye[k]) / dir[k],
            (ext[k] / 2.0 - basis.eye[k]) / dir[k],
        );
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    if t0 >= t1 {
        return 0.0;
    }
    let n = 4000;
    let dt = (t1 - t0) / n as f32;
    let mut tau = 0.0f64;
    for i in 0..n {
        let t = t0 + (i as f32 + 0.5) * dt;
        let u: [f32; 3] =
            std::array::from_fn(|k| (basis.eye[k] + dir[k] * t + ext[k] / 2.0) / ext[k]);
        tau += (density * trilinear(volume, u) * dt) as f64;
    }
    tau as f32
}

pub fn srgb_byte(x: f32) -> u8 {
    let x = x.clamp(0.0, 1.0);
    let s = if x <= 0.0031308 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (s.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// The Cornell phantom's materials (voxlight_volumes::CORNELL_MATERIALS) with a narrow plateau
/// each, like the app's cornell TF; `edit` may change a material's colour and opacity.
pub fn cornell_materials_tf(
    medium_opacity: f32,
    edit: impl Fn(&str, &mut [f32; 3], &mut f32),
) -> TransferFunction {
    let point = |value: f32, color: [f32; 3], opacity: f32| TfPoint {
        value,
        color,
        opacity,
    };
    let mut points = vec![point(0.0, [0.0; 3], 0.0), point(0.05, [0.0; 3], 0.0)];
    for (name, value) in voxlight_volumes::CORNELL_MATERIALS {
        let (mut color, mut opacity) = match *name {
            "medium" => ([0.9, 0.9, 0.9], medium_opacity),
            "left wall" => ([0.85, 0.1, 0.08], 1.0),
            "right wall" => ([0.1, 0.75, 0.12], 1.0),
            _ => ([0.85, 0.85, 0.85], 1.0),
        };
        edit(name, &mut color, &mut opacity);
        points.push(point(value - 0.03, color, opacity));
        points.push(point((value + 0.03).min(1.0), color, opacity));
    }
    TransferFunction { points }
}
