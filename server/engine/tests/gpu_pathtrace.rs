//! Physics of the `pathtrace` reference on whatever adapter exists (lavapipe in CI).

mod common;

use common::*;
use voxlight_protocol::Light;

#[test]
fn white_furnace_returns_the_environment_at_any_density() {
    // Albedo 1 in a uniform environment: whatever the density and phase function, every path
    // escapes with its full weight, so every pixel is the environment radiance.
    let size = 40;
    let (_, volume) = sphere(40);
    let env = [0.7, 0.5, 0.3];
    for (density, g) in [(2.0, 0.0), (10.0, 0.0), (10.0, 0.7), (25.0, -0.4)] {
        let mut s = scene(
            ramp_tf(1.0),
            vec![Light::Environment { radiance: env }],
            density,
            size,
            4,
        );
        s.params.g = g;
        let (_, hdr) = render_with("pathtrace", volume.clone(), &s);
        for (i, px) in hdr.iter().enumerate() {
            for k in 0..3 {
                assert!(
                    (px[k] / env[k] - 1.0).abs() < 1e-5,
                    "density {density}, g {g}: pixel {i} is {px:?}, not {env:?}"
                );
            }
        }
    }
}

#[test]
fn absorbing_sphere_transmittance_is_unbiased() {
    // Albedo 0: a path either escapes (radiance = environment) or is absorbed, so each sample
    // is a Bernoulli draw with mean exp(−τ). Check the sum over pixels against the CPU
    // reference within 1%, and that per-pixel deviations are the size the variance predicts.
    let size = 48;
    let iterations = 64;
    let (cpu_volume, volume) = sphere(48);
    let density = 2.0;
    let s = scene(
        ramp_tf(0.0),
        vec![Light::Environment { radiance: [1.0; 3] }],
        density,
        size,
        iterations,
    );
    let (_, hdr) = render_with("pathtrace", volume, &s);
    let (mut got_sum, mut want_sum, mut z_sum, mut z2_sum, mut count) =
        (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0);
    for y in 0..size {
        for x in 0..size {
            let tau = reference_optical_depth(
                &cpu_volume,
                &s.camera,
                size,
                x as f32 + 0.5,
                y as f32 + 0.5,
                density,
            );
            let expected = (-tau).exp() as f64;
            if !(0.05..0.95).contains(&expected) {
                continue;
            }
            let got = hdr[(y * size + x) as usize][0] as f64;
            let sigma = (expected * (1.0 - expected) / iterations as f64).sqrt();
            let z = (got - expected) / sigma;
            got_sum += got;
            want_sum += expected;
            z_sum += z;
            z2_sum += z * z;
            count += 1;
        }
    }
    assert!(count > 500, "too few pixels through the sphere: {count}");
    let ratio = got_sum / want_sum;
    assert!(
        (ratio - 1.0).abs() < 0.01,
        "mean transmittance off by {:.2}%",
        (ratio - 1.0) * 100.0
    );
    let mean_z = z_sum / count as f64;
    let mean_z2 = z2_sum / count as f64;
    assert!(
        mean_z.abs() < 4.0 / (count as f64).sqrt(),
        "biased: mean z {mean_z}"
    );
    // The pixel footprint adds a little variance beyond the Bernoulli variance of its centre.
    assert!(
        (0.7..1.4).contains(&mean_z2),
        "variance off: mean z² {mean_z2}"
    );
}

#[test]
fn agrees_with_raymarch_where_single_scattering_dominates() {
    // Optically thin (τ ≤ 0.1 through the centre), low albedo: multiple scattering is a few
    // tenths of a percent, so the unbiased path tracer and the single-scattering ray marcher
    // must agree on the light scattered toward the camera.
    let size = 40;
    let (_, volume) = sphere(40);
    let lights = vec![Light::Directional {
        direction: [0.6, 0.8, 0.0],
        irradiance: [20.0; 3],
    }];
    let s = scene(ramp_tf(0.3), lights, 0.125, size, 192);
    let (_, traced) = render_with("pathtrace", volume.clone(), &s);
    let (_, marched) = render_with("raymarch", volume, &s);
    let mean = |img: &[[f32; 3]]| img.iter().map(|p| p[0] as f64).sum::<f64>() / img.len() as f64;
    let (t, m) = (mean(&traced), mean(&marched));
    eprintln!("pathtrace mean {t}, raymarch mean {m}");
    assert!(m > 0.002, "the thin sphere should scatter visibly: {m}");
    assert!(
        (t / m - 1.0).abs() < 0.04,
        "pathtrace mean {t} vs raymarch mean {m}"
    );
}

#[test]
fn multiple_scattering_brightens_a_dense_white_medium() {
    // Dense albedo-1 sphere in a uniform environment: the path tracer gives the environment
    // back (furnace), single scattering alone cannot.
    let size = 32;
    let (_, volume) = sphere(32);
    let s = scene(
        ramp_tf(1.0),
        vec![Light::Environment { radiance: [1.0; 3] }],
        20.0,
        size,
        8,
    );
    let (_, traced) = render_with("pathtrace", volume.clone(), &s);
    let (_, marched) = render_with("raymarch", volume, &s);
    let centre = (size / 2 * size + size / 2) as usize;
    assert!((traced[centre][0] - 1.0).abs() < 1e-5);
    assert!(
        marched[centre][0] < 0.9,
        "single scattering at the centre: {}",
        marched[centre][0]
    );
}

#[test]
fn reproducible_with_the_same_seed() {
    let size = 24;
    let (_, volume) = sphere(24);
    let lights = vec![
        Light::Environment { radiance: [0.3; 3] },
        Light::Point {
            position: [0.3, -0.8, 0.6],
            intensity: [1.5; 3],
        },
    ];
    let s = scene(ramp_tf(0.9), lights, 15.0, size, 3);
    let (_, a) = render_with("pathtrace", volume.clone(), &s);
    let (_, b) = render_with("pathtrace", volume.clone(), &s);
    assert_eq!(a, b);
    let mut other = s.clone();
    other.seed += 1;
    let (_, c) = render_with("pathtrace", volume, &other);
    assert_ne!(a, c);
}
