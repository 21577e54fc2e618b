//! Physics of the `raymarch` technique on whatever adapter exists (lavapipe in CI). A missing
//! adapter fails these tests loudly.

mod common;

use common::*;
use voxlight_protocol::{Light, TransferFunction, Viewport};

#[test]
fn empty_tf_shows_exactly_the_environment() {
    let (_, volume) = sphere(32);
    let env = [0.2, 0.45, 0.7];
    let lights = vec![
        Light::Environment { radiance: env },
        Light::Directional {
            direction: [0.0, 1.0, 0.0],
            irradiance: [5.0; 3],
        },
    ];
    let scene = scene(TransferFunction::default(), lights, 50.0, 64, 3);
    let (renderer, hdr) = render(volume, &scene);
    for (i, px) in hdr.iter().enumerate() {
        let close = px.iter().zip(&env).all(|(a, b)| (a - b).abs() <= 1e-6 * b);
        assert!(close, "pixel {i} is {px:?}, not the environment {env:?}");
    }
    let frame = renderer.frame(engine(), &scene).unwrap();
    assert_eq!(frame.rgba.len(), 64 * 64 * 4);
    let expected = [srgb_byte(env[0]), srgb_byte(env[1]), srgb_byte(env[2]), 255];
    for px in frame.rgba.chunks(4) {
        assert_eq!(px, expected);
    }
    assert!(frame.converged);
}

#[test]
fn absorbing_sphere_matches_beer_lambert() {
    let size = 64;
    let (cpu_volume, volume) = sphere(64);
    let density = 2.0;
    let scene = scene(
        ramp_tf(0.0),
        vec![Light::Environment { radiance: [1.0; 3] }],
        density,
        size,
        128,
    );
    let (_, hdr) = render(volume, &scene);
    // Through the centre the chord is the sphere's diameter, 0.8 world units.
    let centre = hdr[(size / 2 * size + size / 2) as usize][0];
    let analytic = (-density * 0.8f32).exp();
    assert!(
        (centre / analytic - 1.0).abs() < 0.01,
        "centre transmittance {centre} vs exp(-sigma_t * chord) = {analytic}"
    );
    // Everywhere: the same trilinear field integrated finely on the CPU.
    let mut worst = 0.0f32;
    for y in (4..size).step_by(6) {
        for x in (4..size).step_by(6) {
            let tau = reference_optical_depth(
                &cpu_volume,
                &scene.camera,
                size,
                x as f32 + 0.5,
                y as f32 + 0.5,
                density,
            );
            let expected = (-tau).exp();
            let got = hdr[(y * size + x) as usize];
            assert_eq!(got[0], got[1]);
            assert_eq!(got[1], got[2]);
            // The pixel averages over its footprint; where the chord changes fast (the rim) a
            // 1% bound on the centre ray would test pixel size, not physics.
            let rel = (got[0] / expected - 1.0).abs();
            if tau > 0.05 && tau < 1.55 {
                if rel > worst {
                    eprintln!(
                        "pixel ({x}, {y}): tau {tau:.4} got {:.5} expected {expected:.5} rel {rel:.4}",
                        got[0]
                    );
                }
                worst = worst.max(rel);
            }
        }
    }
    assert!(worst < 0.01, "worst relative transmittance error {worst}");
}

#[test]
fn thin_white_medium_in_uniform_light_is_nearly_the_furnace() {
    // Albedo 1, optical depth ≤ 0.1: single scattering alone must give back all but O(τ²) of
    // the environment. Without in-scattering the centre would show exp(−0.1) ≈ 0.905.
    let size = 48;
    let (_, volume) = sphere(48);
    let density = 0.125;
    let scene = scene(
        ramp_tf(1.0),
        vec![Light::Environment { radiance: [1.0; 3] }],
        density,
        size,
        64,
    );
    let (_, hdr) = render(volume, &scene);
    let mean: f32 = hdr.iter().map(|p| p[1]).sum::<f32>() / hdr.len() as f32;
    assert!((mean - 1.0).abs() < 0.01, "mean radiance {mean}");
    let centre = hdr[(size / 2 * size + size / 2) as usize][1];
    assert!(centre > 0.98 && centre < 1.01, "centre {centre}");
}

#[test]
fn directional_light_lights_the_near_side() {
    // Light travels along +x: the −x side of a scattering sphere is lit, the +x side shadowed.
    let size = 48;
    let (_, volume) = sphere(48);
    let lights = vec![Light::Directional {
        direction: [1.0, 0.0, 0.0],
        irradiance: [4.0; 3],
    }];
    let scene = scene(ramp_tf(0.9), lights, 30.0, size, 8);
    let (_, hdr) = render(volume, &scene);
    let row = size / 2;
    let left = hdr[(row * size + size / 2 - 12) as usize][0];
    let right = hdr[(row * size + size / 2 + 12) as usize][0];
    let corner = hdr[0][0];
    assert_eq!(corner, 0.0, "no environment: the background is black");
    assert!(left > 0.05, "lit side {left}");
    assert!(
        left > 5.0 * right,
        "lit side {left} vs shadowed side {right}"
    );
}

#[test]
fn same_seed_same_picture_other_seed_other_noise() {
    let size = 32;
    let (_, volume) = sphere(32);
    let lights = vec![
        Light::Environment { radiance: [0.5; 3] },
        Light::Point {
            position: [0.0, -1.0, 1.0],
            intensity: [2.0; 3],
        },
    ];
    let a = scene(ramp_tf(0.8), lights, 20.0, size, 4);
    let (_, first) = render(volume.clone(), &a);
    let (_, second) = render(volume.clone(), &a);
    assert_eq!(
        first, second,
        "counter-based randomness must make renders reproducible"
    );
    let mut b = a.clone();
    b.seed += 1;
    let (_, other) = render(volume, &b);
    assert_ne!(first, other);
}

#[test]
fn step_reports_gpu_time() {
    let (_, volume) = sphere(32);
    let s = scene(
        ramp_tf(0.5),
        vec![Light::Environment { radiance: [1.0; 3] }],
        10.0,
        32,
        2,
    );
    let engine = engine();
    let mut renderer = engine.create_renderer("raymarch", volume, &s).unwrap();
    let started = std::time::Instant::now();
    let report = renderer
        .step(engine, &s, std::time::Duration::from_secs(5))
        .unwrap();
    let wall = started.elapsed();
    assert_eq!(report.iteration, 2);
    assert!(report.converged);
    assert!(report.gpu_time > std::time::Duration::ZERO);
    assert!(
        report.gpu_time <= wall,
        "GPU time {:?} exceeds the wall time {wall:?}",
        report.gpu_time
    );
    eprintln!(
        "timestamps: {}, gpu {:?}, wall {wall:?}",
        engine.gpu.has_timestamps, report.gpu_time
    );
}

#[test]
fn oversized_viewport_is_refused() {
    let (_, volume) = sphere(16);
    let mut s = scene(ramp_tf(1.0), vec![], 1.0, 64, 1);
    s.viewport = Viewport {
        width: 5000,
        height: 64,
    };
    let err = engine()
        .create_renderer("raymarch", volume.clone(), &s)
        .err()
        .expect("must fail");
    assert!(err.to_string().contains("viewport"), "{err}");
    let s = scene(ramp_tf(1.0), vec![], 1.0, 64, 1);
    let err = engine()
        .create_renderer("nope", volume, &s)
        .err()
        .expect("must fail");
    assert!(err.to_string().contains("nope"));
}

/// A long iteration runs in bands of interleaved 8-row blocks (techniques::progressive), so
/// that the render thread can serve an edit between them: each band is a step with no iteration done
/// until the last one, and the picture is bit for bit the one whole dispatches render, for
/// both estimators.
#[test]
fn banded_iterations_equal_whole_ones_bit_for_bit() {
    use voxlight_engine::Renderer;
    use voxlight_engine::techniques::progressive::{Estimator, Progressive};
    let engine = engine();
    let (_, volume) = sphere(32);
    let mut s = scene(
        ramp_tf(0.7),
        vec![
            Light::Point {
                position: [0.8, -0.9, 0.7],
                intensity: [2.0; 3],
            },
            Light::Environment { radiance: [0.2; 3] },
        ],
        8.0,
        40,
        3,
    );
    s.viewport.height = 36;
    for estimator in [Estimator::Raymarch, Estimator::Pathtrace] {
        let whole = Progressive::new(engine, estimator, volume.clone(), &s).unwrap();
        let mut whole =
            Renderer::with_technique(engine, Box::new(whole), volume.clone(), &s).unwrap();
        let mut banded = Progressive::new(engine, estimator, volume.clone(), &s).unwrap();
        banded.fix_bands(3);
        let mut banded =
            Renderer::with_technique(engine, Box::new(banded), volume.clone(), &s).unwrap();
        // 36 rows, 5 blocks of 8 (the last half full), in 3 bands (blocks 0 and 3, 1 and 4,
        // 2): three steps per iteration, the last completes it.
        let mut done = Vec::new();
        while !banded.converged(&s) {
            let report = banded.step(engine, &s, std::time::Duration::ZERO).unwrap();
            done.push(report.iterations_done);
        }
        assert_eq!(done, [0, 0, 1].repeat(3), "{estimator:?}");
        while !whole.converged(&s) {
            whole
                .step(engine, &s, std::time::Duration::from_secs(10))
                .unwrap();
        }
        let (a, b) = (
            whole.read_hdr(engine).unwrap(),
            banded.read_hdr(engine).unwrap(),
        );
        assert!(
            a.iter().any(|p| p[0] > 0.0),
            "{estimator:?}: a black picture"
        );
        assert_eq!(a, b, "{estimator:?}: banded and whole iterations differ");
    }
}
