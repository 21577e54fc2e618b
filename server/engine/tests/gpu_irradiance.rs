//! Technique `irradiance` on whatever adapter exists (lavapipe in CI): the cached picture is
//! exact where the irradiance is known, converges to `pathtrace` (and, single scattering only,
//! to `raymarch`), tracing the lights' direct light keeps shadow edges that caching it blurs,
//! validation rounds of their own reduce (not remove) the bias a cache of all the light has at a
//! shadow edge, the 7-point estimate recovers the extinction of a homogeneous medium, TF edits
//! keep exactly the entries their historygrams say they cannot change, and a run with a fixed
//! schedule repeats bit for bit.

mod common;

use std::sync::Arc;

use common::*;
use voxlight_engine::brightness::mean_rgb as mean;
use voxlight_engine::image_stats::{luminance, relative_rms_luminance};
use voxlight_engine::techniques::irradiance::{
    CachedLight, Irradiance, IrradianceConfig, Locking, ViewEvent,
};
use voxlight_engine::{GpuVolume, Renderer, Scene, Technique};
use voxlight_protocol::{Light, TfPoint, TransferFunction};
use voxlight_volumes::Volume;

/// A repeatable configuration: fixed creation and update rounds per frame.
fn fixed(config: IrradianceConfig) -> IrradianceConfig {
    IrradianceConfig {
        fixed_rounds: Some((4, 1)),
        ..config
    }
}

fn irradiance(volume: Arc<GpuVolume>, scene: &Scene, config: IrradianceConfig) -> Renderer {
    let engine = engine();
    let technique = Irradiance::new(engine, volume.clone(), scene, config).expect("irradiance");
    Renderer::with_technique(engine, Box::new(technique), volume, scene).expect("renderer")
}

/// Runs `frames` frames (no time budget: each renders the image once plus fixed rounds).
fn run(renderer: &mut Renderer, scene: &Scene, frames: u32) -> Vec<[f32; 3]> {
    let engine = engine();
    for _ in 0..frames {
        renderer
            .step(engine, scene, std::time::Duration::from_nanos(1))
            .expect("step");
    }
    renderer.read_hdr(engine).expect("hdr")
}

fn details(renderer: &Renderer) -> voxlight_engine::TechniqueStats {
    renderer.stats()
}

#[test]
fn white_furnace_is_exact_through_the_cache() {
    // Albedo 1 in a uniform environment: every irradiance sample is exactly 4πL, so entries
    // converge at once with flat zones and every cached pixel is exactly L.
    let (_, volume) = sphere(32);
    let env = [0.7, 0.5, 0.3];
    let s = scene(
        ramp_tf(1.0),
        vec![Light::Environment { radiance: env }],
        20.0,
        32,
        1000,
    );
    let mut renderer = irradiance(volume, &s, fixed(IrradianceConfig::default()));
    let hdr = run(&mut renderer, &s, 16);
    let stats = details(&renderer);
    assert!(stats.details.cache_entries.unwrap() > 0, "{stats:?}");
    assert!(stats.details.cache_hit_rate.unwrap() > 0.25, "{stats:?}");
    for (i, px) in hdr.iter().enumerate() {
        for k in 0..3 {
            assert!(
                (px[k] / env[k] - 1.0).abs() < 1e-4,
                "pixel {i} is {px:?}, not {env:?} ({stats:?})"
            );
        }
    }
}

fn lit_sphere(size: u32) -> Scene {
    scene(
        ramp_tf(0.8),
        vec![
            Light::Directional {
                direction: [0.3, -1.0, -0.4],
                irradiance: [3.0, 2.6, 2.2],
            },
            Light::Environment {
                radiance: [0.3, 0.32, 0.36],
            },
        ],
        10.0,
        size,
        1000,
    )
}

fn reference(technique: &str, volume: Arc<GpuVolume>, s: &Scene, spp: u32) -> Vec<[f32; 3]> {
    let mut s = s.clone();
    s.target_iterations = spp;
    render_with(technique, volume, &s).1
}

#[test]
fn multiple_scattering_converges_to_pathtrace() {
    let (_, volume) = sphere(40);
    let s = lit_sphere(48);
    let mut renderer = irradiance(volume.clone(), &s, fixed(IrradianceConfig::default()));
    let hdr = run(&mut renderer, &s, 40);
    let stats = details(&renderer);
    let want = reference("pathtrace", volume, &s, 256);
    let (got, exp) = (mean(&hdr), mean(&want));
    for k in 0..3 {
        assert!(
            (got[k] / exp[k] - 1.0).abs() < 0.02,
            "mean {got:?} vs pathtrace {exp:?} ({stats:?})"
        );
    }
    let rms = relative_rms_luminance(&hdr, &want);
    assert!(rms < 0.06, "relative RMS {rms} ({stats:?})");
    assert!(stats.details.cache_entries.unwrap() >= 30, "{stats:?}");
    assert!(stats.details.cache_hit_rate.unwrap() > 0.3, "{stats:?}");
    assert!(
        stats.details.octree_references.unwrap() >= stats.details.cache_entries.unwrap() as u64
    );
}

#[test]
fn several_events_per_sample_and_delta_tracking_converge_to_pathtrace_too() {
    let (_, volume) = sphere(40);
    let s = lit_sphere(48);
    let want = reference("pathtrace", volume.clone(), &s, 256);
    for config in [
        IrradianceConfig {
            view_picks: 8,
            ..Default::default()
        },
        IrradianceConfig {
            view_event: ViewEvent::DeltaTracking,
            ..Default::default()
        },
    ] {
        let mut renderer = irradiance(volume.clone(), &s, fixed(config));
        let hdr = run(&mut renderer, &s, 32);
        let (got, exp) = (lum_of(mean(&hdr)), lum_of(mean(&want)));
        assert!(
            (got / exp - 1.0).abs() < 0.02,
            "{:?}/{}: mean {got} vs pathtrace {exp} ({:?})",
            config.view_event,
            config.view_picks,
            details(&renderer)
        );
    }
}

#[test]
fn single_scattering_cache_agrees_with_raymarch() {
    let (_, volume) = sphere(40);
    let s = lit_sphere(48);
    let config = fixed(IrradianceConfig {
        bounces: 1,
        ..Default::default()
    });
    let mut renderer = irradiance(volume.clone(), &s, config);
    let hdr = run(&mut renderer, &s, 40);
    let want = reference("raymarch", volume, &s, 256);
    let (got, exp) = (mean(&hdr), mean(&want));
    for k in 0..3 {
        assert!(
            (got[k] / exp[k] - 1.0).abs() < 0.02,
            "mean {got:?} vs raymarch {exp:?} ({:?})",
            details(&renderer)
        );
    }
}

#[test]
fn screen_space_locking_builds_a_cache_that_converges_too() {
    let (_, volume) = sphere(40);
    let s = lit_sphere(48);
    let config = fixed(IrradianceConfig {
        locking: Locking::Screen,
        priorities: false,
        ..Default::default()
    });
    let mut renderer = irradiance(volume.clone(), &s, config);
    let hdr = run(&mut renderer, &s, 40);
    let stats = details(&renderer);
    assert!(stats.details.cache_entries.unwrap() >= 20, "{stats:?}");
    let want = reference("pathtrace", volume, &s, 256);
    let (got, exp) = (mean(&hdr), mean(&want));
    assert!(
        (luminance(got.map(|x| x as f32)) / luminance(exp.map(|x| x as f32)) - 1.0).abs() < 0.02,
        "mean {got:?} vs pathtrace {exp:?} ({stats:?})"
    );
}

/// A homogeneous cube: every voxel at 0.5.
fn homogeneous(size: u32) -> Arc<GpuVolume> {
    let data = vec![32768u16; (size * size * size) as usize];
    let volume = Volume::from_normalized("homogeneous", [size; 3], [1.0; 3], data).unwrap();
    engine().upload_volume(&volume).unwrap()
}

#[test]
fn seven_point_estimate_recovers_the_extinction_of_a_homogeneous_medium() {
    // Direct light falling straight down (−y) through extinction σ: E = E_L·exp(−σ·depth), so
    // along +y (the local frame's b axis where the medium is flat) the virtual extinction
    // coefficient is −σ and along −y it is +σ; sideways it is zero.
    let size = 32;
    let volume = homogeneous(size);
    let density = 4.0;
    let sigma = density * 32768.0 / 65535.0;
    let s = scene(
        ramp_tf(0.5),
        vec![Light::Directional {
            direction: [0.0, -1.0, 0.0],
            irradiance: [1.0; 3],
        }],
        density,
        32,
        1000,
    );
    let config = fixed(IrradianceConfig {
        bounces: 1,
        ..Default::default()
    });
    let engine = engine();
    let mut technique = Irradiance::new(engine, volume, &s, config).unwrap();
    for _ in 0..40 {
        technique.frame(engine, &s, true).unwrap();
    }
    let delta = 2.0 / size as f32;
    let inner: Vec<_> = technique
        .entries()
        .into_iter()
        .filter(|e| e.position.iter().all(|&c| c.abs() < 0.5 - 1.1 * delta))
        .collect();
    assert!(
        inner.len() >= 5,
        "only {} of {} entries inside: {:?}",
        inner.len(),
        technique.entries().len(),
        technique.cache_stats()
    );
    for e in &inner {
        assert_eq!(e.normal, [0.0, 0.0, 1.0], "flat medium: the fallback frame");
        // Half-axes +t, −t, +b, −b, +n, −n; b is +y.
        let up = e.sigma[2][3];
        let down = e.sigma[3][3];
        assert!(
            (up + sigma).abs() < 0.1 * sigma,
            "σ(+y) = {up}, want −{sigma}"
        );
        assert!(
            (down - sigma).abs() < 0.1 * sigma,
            "σ(−y) = {down}, want {sigma}"
        );
        for h in [0, 1, 4, 5] {
            assert!(
                e.sigma[h][3].abs() < 0.1 * sigma,
                "σ sideways = {}",
                e.sigma[h][3]
            );
        }
        // The estimate itself: E_L·exp(−σ·depth below the top face).
        let depth = 0.5 - e.position[1];
        let want = (-sigma * depth).exp();
        assert!(
            (e.irradiance[0] / want - 1.0).abs() < 0.12,
            "E = {} at depth {depth}, want {want}",
            e.irradiance[0]
        );
    }
}

/// The Cornell phantom's materials, looking into the box.
fn cornell(size: u32, tf: TransferFunction) -> Scene {
    let mut s = scene(
        tf,
        vec![
            Light::Point {
                position: [0.0, 0.3, 0.1],
                intensity: [0.5, 0.48, 0.45],
            },
            Light::Environment {
                radiance: [0.1, 0.1, 0.11],
            },
        ],
        30.0,
        size,
        1000,
    );
    s.camera = voxlight_protocol::Camera {
        eye: [0.0, 0.0, 2.6],
        target: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_deg: 28.0,
    };
    s
}

#[test]
fn tf_edits_keep_exactly_the_entries_their_historygrams_exclude() {
    let engine = engine();
    let volume = engine
        .upload_volume(&voxlight_volumes::phantom("cornell", 40).unwrap())
        .unwrap();
    let before_tf = cornell_materials_tf(0.02, |_, _, _| {});
    // Single scattering from the point light only: an entry depends on the values along its
    // shadow rays to the light (and not on any albedo).
    let mut s = cornell(40, before_tf.clone());
    s.lights.retain(|l| matches!(l, Light::Point { .. }));
    let config = fixed(IrradianceConfig {
        bounces: 1,
        ..Default::default()
    });
    let mut technique = Irradiance::new(engine, volume.clone(), &s, config).unwrap();
    for _ in 0..24 {
        technique.frame(engine, &s, true).unwrap();
    }
    let built = technique.entries();
    assert!(built.len() >= 20, "{:?}", technique.cache_stats());

    let edits: [(&str, TransferFunction); 3] = [
        (
            "recolour the right wall",
            cornell_materials_tf(0.02, |n, c, _| {
                if n == "right wall" {
                    *c = [0.2, 0.2, 0.9];
                }
            }),
        ),
        (
            "remove the tall block",
            cornell_materials_tf(0.02, |n, _, o| {
                if n == "tall block" {
                    *o = 0.0;
                }
            }),
        ),
        (
            "every bin",
            TransferFunction {
                points: before_tf
                    .points
                    .iter()
                    .map(|p| TfPoint {
                        opacity: (p.opacity * 0.5).max(0.01),
                        ..*p
                    })
                    .collect(),
            },
        ),
    ];
    let snapshot = technique.snapshot(engine).unwrap();
    let mut kept_counts = Vec::new();
    for (name, tf) in edits {
        technique.restore(engine, &s, &snapshot).unwrap();
        let mut edited = s.clone();
        edited.tf = tf;
        let change = voxlight_engine::Change::tf(&s.tf, &edited.tf);
        let voxlight_engine::Change::Tf {
            query_historygram, ..
        } = change.clone()
        else {
            unreachable!()
        };
        let opacity_query = voxlight_engine::tf::opacity_query_historygram(&s.tf, &edited.tf);
        technique.apply(engine, &edited, &change).unwrap();
        let kept = technique.entries();
        let want: Vec<_> = built
            .iter()
            .filter(|e| !e.meets(query_historygram, opacity_query))
            .copied()
            .collect();
        assert_eq!(
            kept, want,
            "{name}: kept entries differ from the historygram test"
        );
        let stats = technique.cache_stats();
        assert_eq!(
            stats.last_edit,
            Some((built.len() as u32, kept.len() as u32))
        );
        kept_counts.push((name, kept.len()));
        // A fresh picture with the kept cache still comes out right.
        if name == "remove the tall block" {
            for _ in 0..16 {
                technique.frame(engine, &edited, true).unwrap();
            }
            let got = read(&technique);
            let want = reference("raymarch", volume.clone(), &edited, 128);
            let (g, w) = (lum_of(mean(&got)), lum_of(mean(&want)));
            assert!(
                (g / w - 1.0).abs() < 0.04,
                "{name}: mean {g} vs raymarch {w}"
            );
        }
    }
    let n = built.len();
    assert_eq!(
        kept_counts[0].1, n,
        "single scattering does not depend on albedo: {kept_counts:?} of {n}"
    );
    assert!(
        kept_counts[1].1 < n,
        "removing a block drops some: {kept_counts:?}"
    );
    assert_eq!(
        kept_counts[2].1, 0,
        "an edit of every bin drops all: {kept_counts:?}"
    );
}

fn lum_of(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

fn read(technique: &Irradiance) -> Vec<[f32; 3]> {
    let engine = engine();
    let bytes = engine.gpu.read_buffer(technique.output()).unwrap();
    let sums: &[[f32; 4]] = bytemuck::cast_slice(&bytes);
    sums.iter()
        .map(|s| {
            let n = s[3].max(1.0);
            [s[0] / n, s[1] / n, s[2] / n]
        })
        .collect()
}

#[test]
fn a_fixed_schedule_repeats_bit_for_bit() {
    let (_, volume) = sphere(32);
    let s = lit_sphere(32);
    let engine = engine();
    let mut runs = Vec::new();
    for _ in 0..2 {
        let mut t = Irradiance::new(engine, volume.clone(), &s, fixed(Default::default())).unwrap();
        for _ in 0..12 {
            t.frame(engine, &s, true).unwrap();
        }
        let bytes = engine.gpu.read_buffer(t.output()).unwrap();
        runs.push((bytes, t.entries(), t.cache_stats()));
    }
    assert!(runs[0].2.entries > 0);
    assert_eq!(runs[0].1, runs[1].1, "entries differ");
    assert!(runs[0].0 == runs[1].0, "pictures differ");
}

/// The 40³ sphere lit by one directional light only (no environment): a hard shadow edge.
fn shadow_edge_scene() -> (Arc<GpuVolume>, Scene) {
    let (_, volume) = sphere(40);
    let s = scene(
        ramp_tf(0.8),
        vec![Light::Directional {
            direction: [1.0, -0.2, -0.3],
            irradiance: [4.0; 3],
        }],
        25.0,
        48,
        1000,
    );
    (volume, s)
}

#[test]
fn the_update_shrinks_zones_where_entries_disagree() {
    // A hard shadow edge (directional light only, no environment): entries on either side of
    // it disagree where their zones overlap.
    let (volume, s) = shadow_edge_scene();
    let config = IrradianceConfig {
        fixed_rounds: Some((4, 4)),
        bounces: 1,
        ..Default::default()
    };
    let engine = engine();
    let mut t = Irradiance::new(engine, volume, &s, config).unwrap();
    for _ in 0..30 {
        t.frame(engine, &s, true).unwrap();
    }
    let stats = t.cache_stats();
    assert!(stats.radius_reductions > 0, "{stats:?}");
    let snapshot = t.snapshot(engine).unwrap();
    let voxel = 1.0 / 40.0;
    let mut shrunk = 0;
    for (e, r) in snapshot.entries.iter().zip(snapshot.radii.chunks_exact(6)) {
        for (h, &radius) in r.iter().enumerate() {
            let initial = voxlight_engine::techniques::irradiance::validity_radius(
                e.sigma[h][3],
                e.delta,
                0.1,
                0.01 * voxel,
                IrradianceConfig::default().max_radius_voxels * voxel,
            );
            assert!(
                radius <= initial * 1.0001,
                "a radius grew: {} > {initial}",
                radius
            );
            assert!(
                radius >= 0.01 * voxel * 0.999,
                "a radius fell below the minimum"
            );
            if radius < initial * 0.999 {
                shrunk += 1;
            }
        }
    }
    assert!(shrunk > 0, "no radius shrank ({stats:?})");
}

#[test]
fn validating_hits_shrinks_zones_a_fresh_estimate_contradicts() {
    // The same hard shadow edge: with validation the update also shrinks single entries that
    // reach across it (no second entry needed), so more radii shrink under the same schedule.
    let (volume, s) = shadow_edge_scene();
    let engine = engine();
    let reductions = |validate_hits: bool| {
        let config = IrradianceConfig {
            fixed_rounds: Some((4, 4)),
            bounces: 1,
            validate_hits,
            ..Default::default()
        };
        let mut t = Irradiance::new(engine, volume.clone(), &s, config).unwrap();
        for _ in 0..30 {
            t.frame(engine, &s, true).unwrap();
        }
        t.cache_stats().radius_reductions
    };
    let (without, with) = (reductions(false), reductions(true));
    assert!(
        with > without,
        "validated {with} reductions, pairwise alone {without}"
    );
}

#[test]
fn tracing_the_direct_light_keeps_shadow_edges_where_caching_it_blurs_them() {
    // The hard shadow edge under single scattering, with a dim sky so that there is indirect
    // light to cache: a cache of all the light carries the lit side's irradiance across the
    // edge (a zone sees only its own stencil); one that holds only the sky's leaves the edge
    // to shadow rays. Built, then rendered long with the cache fixed, so that what is left
    // against raymarch's converged picture is the cache's bias, not noise.
    let (volume, mut s) = shadow_edge_scene();
    s.lights.push(Light::Environment {
        radiance: [0.05; 3],
    });
    let want = reference("raymarch", volume.clone(), &s, 1024);
    let engine = engine();
    let error = |cache, cached_light| {
        let config = fixed(IrradianceConfig {
            cache,
            cached_light,
            bounces: 1,
            // The paper's largest zones.
            max_radius_voxels: 16.0,
            ..Default::default()
        });
        let mut t = Irradiance::new(engine, volume.clone(), &s, config).unwrap();
        for _ in 0..40 {
            t.frame(engine, &s, true).unwrap();
        }
        let stats = t.cache_stats();
        assert!(
            !cache || stats.hit_rate > 0.25,
            "{cached_light:?}: {stats:?}"
        );
        t.apply(engine, &s, &voxlight_engine::Change::Camera)
            .unwrap();
        for _ in 0..256 {
            t.frame(engine, &s, false).unwrap();
        }
        let (hdr, _) = t.read_estimate(engine).unwrap();
        (
            relative_rms_luminance(&hdr, &want),
            lum_of(mean(&hdr)) / lum_of(mean(&want)),
        )
    };
    // What noise alone leaves: plain Monte Carlo, the same frames.
    let (plain, _) = error(false, CachedLight::Indirect);
    let (all, all_mean) = error(true, CachedLight::All);
    let (indirect, indirect_mean) = error(true, CachedLight::Indirect);
    let report = format!(
        "relative RMS against raymarch: plain {plain}, indirect cache {indirect} (mean {indirect_mean}), all {all} (mean {all_mean})"
    );
    eprintln!("{report}");
    assert!((indirect_mean - 1.0).abs() < 0.01, "{report}");
    assert!(indirect < 1.15 * plain, "{report}");
    assert!(all > 1.4 * plain, "{report}");
}

#[test]
fn validation_rounds_of_their_own_reduce_the_all_light_caches_shadow_edge_bias() {
    // The hard shadow edge under single scattering with no environment: the cache holds all the
    // light (the paper's configuration), and zones of the paper's 16 voxels carry each side's
    // irradiance across the edge, which their own stencils cannot see (Eq. 11's log-space
    // average then darkens the picture). Validation rounds with a budget of their own check
    // enough points, with estimates tight enough, to shrink many of those zones; the update's
    // pairwise comparison alone, or with its own validation at one round per frame, does not.
    // They do not remove the bias: what is left still errs more than plain Monte Carlo. Built,
    // then rendered long with the cache fixed, so that what is left against raymarch's
    // converged picture is the cache's error, not noise; plain Monte Carlo's own offset from
    // raymarch (0.994–0.996 of its mean here, seeds 7–9) is taken out of the bias.
    //
    // Measured on lavapipe with seeds 7, 8, 9 (this test runs 7), bias against plain's mean:
    // pairwise −0.91 / −0.60 / −0.87%, validating update −0.73 / −0.69 / −1.03%, 32
    // validation rounds −0.42 / −0.43 / −0.32%; relative RMS ÷ plain's: 1.53 / 1.50 / 1.54,
    // 1.51 / 1.47 / 1.51 and 1.24 / 1.23 / 1.32 (hit rates 0.56–0.60 and 0.31–0.32). The
    // bounds below sit between those with margins.
    let (volume, s) = shadow_edge_scene();
    let want = reference("raymarch", volume.clone(), &s, 1024);
    let engine = engine();
    let run = |cache: bool, validate_hits: bool, validation_rounds: u32| {
        let config = IrradianceConfig {
            cache,
            cached_light: CachedLight::All,
            bounces: 1,
            max_radius_voxels: 16.0,
            fixed_rounds: Some((4, 1)),
            validate_hits,
            validation_rounds: Some(validation_rounds),
            validation_threshold: 0.01,
            validation_samples: 32,
            ..Default::default()
        };
        let mut t = Irradiance::new(engine, volume.clone(), &s, config).unwrap();
        for _ in 0..40 {
            t.frame(engine, &s, true).unwrap();
        }
        // Every frame once there are entries.
        let (rounds, most) = (
            t.cache_stats().validation_rounds,
            40 * validation_rounds as u64,
        );
        assert!(
            rounds <= most
                && (cache || rounds == 0)
                && rounds + 4 * validation_rounds as u64 >= most,
            "{rounds} validation rounds"
        );
        t.apply(engine, &s, &voxlight_engine::Change::Camera)
            .unwrap();
        for _ in 0..256 {
            t.frame(engine, &s, false).unwrap();
        }
        let (hdr, _) = t.read_estimate(engine).unwrap();
        (
            relative_rms_luminance(&hdr, &want),
            lum_of(mean(&hdr)) / lum_of(mean(&want)),
            t.cache_stats().hit_rate,
        )
    };
    let (plain, plain_mean, _) = run(false, false, 0);
    let (pairwise, pairwise_mean, _) = run(true, false, 0);
    let (update, update_mean, _) = run(true, true, 0);
    let (validated, validated_mean, hit_rate) = run(true, false, 32);
    let bias = |m: f64| m / plain_mean - 1.0;
    let report = format!(
        "relative RMS against raymarch (mean against plain Monte Carlo's, less 1): plain \
         {plain:.4} (mean {plain_mean:.4} of raymarch's), pairwise update {pairwise:.4} \
         ({:+.4}), validating update {update:.4} ({:+.4}), 32 validation rounds \
         {validated:.4} ({:+.4}, hit rate {hit_rate:.2})",
        bias(pairwise_mean),
        bias(update_mean),
        bias(validated_mean),
    );
    eprintln!("{report}");
    // Without validation rounds the cache is dark by more than 0.45%; with them by less than
    // 0.6% and by at most 80% of the better run without them.
    let unvalidated = bias(pairwise_mean).abs().min(bias(update_mean).abs());
    assert!(unvalidated > 0.0045, "{report}");
    assert!(bias(validated_mean).abs() < 0.006, "{report}");
    assert!(bias(validated_mean).abs() < 0.8 * unvalidated, "{report}");
    // They remove at least a quarter of the error the cache adds to plain Monte Carlo's (not
    // all of it today: 1.23–1.32× plain's), and the cache is still used.
    let excess = pairwise.min(update) - plain;
    assert!(validated - plain < 0.75 * excess, "{report}");
    assert!(hit_rate > 0.2, "{report}");
}

#[test]
fn plain_monte_carlo_with_the_direct_light_at_every_event_stays_unbiased_and_gets_less_noisy() {
    // Without a cache the render pass traces the lights at each of `view_picks` events and one
    // path on from one of them. Single scattering under one hard light (where the event's
    // place along the ray is most of the noise): raymarch's mean, and far less variance with
    // four events than with one; multiple scattering with an environment: pathtrace's mean.
    let engine = engine();
    let plain = |volume: &Arc<GpuVolume>, s: &Scene, bounces, view_picks| {
        let config = IrradianceConfig {
            cache: false,
            priorities: false,
            bounces,
            view_picks,
            ..Default::default()
        };
        let mut t = Irradiance::new(engine, volume.clone(), s, config).unwrap();
        for _ in 0..64 {
            t.frame(engine, s, true).unwrap();
        }
        let (hdr, variance) = t.read_estimate(engine).unwrap();
        (
            lum_of(mean(&hdr)),
            variance.iter().map(|&v| v as f64).sum::<f64>(),
        )
    };
    let (volume, s) = shadow_edge_scene();
    let want = lum_of(mean(&reference("raymarch", volume.clone(), &s, 256)));
    let (one, one_noise) = plain(&volume, &s, 1, 1);
    let (four, four_noise) = plain(&volume, &s, 1, 4);
    for (events, got) in [(1, one), (4, four)] {
        assert!(
            (got / want - 1.0).abs() < 0.02,
            "{events} events: mean {got} vs raymarch {want}"
        );
    }
    assert!(
        four_noise < 0.6 * one_noise,
        "variance of the pixel means: 1 event {one_noise}, 4 events {four_noise}"
    );
    let (_, volume) = sphere(40);
    let s = lit_sphere(48);
    let want = lum_of(mean(&reference("pathtrace", volume.clone(), &s, 256)));
    let (got, _) = plain(&volume, &s, IrradianceConfig::default().bounces, 4);
    assert!(
        (got / want - 1.0).abs() < 0.02,
        "mean {got} vs pathtrace {want}"
    );
}

#[test]
fn an_anisotropic_phase_function_renders_plain_monte_carlo() {
    let (_, volume) = sphere(32);
    let mut s = lit_sphere(32);
    s.params.g = 0.5;
    let mut renderer = irradiance(volume.clone(), &s, fixed(IrradianceConfig::default()));
    let hdr = run(&mut renderer, &s, 64);
    let stats = details(&renderer);
    assert_eq!(stats.details.cache_active, Some(false));
    assert_eq!(stats.details.cache_entries, Some(0));
    let want = reference("pathtrace", volume, &s, 256);
    let (g, w) = (lum_of(mean(&hdr)), lum_of(mean(&want)));
    assert!((g / w - 1.0).abs() < 0.02, "mean {g} vs pathtrace {w}");
}

#[test]
fn a_cache_larger_than_the_session_budget_is_refused() {
    let (_, volume) = sphere(16);
    let s = lit_sphere(16);
    let config = IrradianceConfig {
        entry_capacity: u32::MAX / 4,
        ..Default::default()
    };
    match Irradiance::new(engine(), volume, &s, config) {
        Err(voxlight_engine::EngineError::OutOfMemory { needed, available }) => {
            assert!(needed > available)
        }
        Err(other) => panic!("wrong error {other}"),
        Ok(_) => panic!("a huge cache was allocated"),
    }
}

/// Frames of fewer blocks than the image (`frame_time`, or the render service's part time
/// where whole frames take long) cover the image in turn after a restart: the first picture
/// (`iteration` 1) has no pixel without a sample, and the picture counts only then.
#[test]
fn frames_of_a_few_blocks_cover_the_image_before_its_first_picture() {
    let engine = engine();
    let (_, volume) = sphere(32);
    let s = scene(
        ramp_tf(0.8),
        vec![Light::Directional {
            direction: [0.3, 0.8, -0.5],
            irradiance: [3.0; 3],
        }],
        10.0,
        48,
        2,
    );
    // A frame time nothing fits in: one block per frame.
    let config = IrradianceConfig {
        frame_time: Some(std::time::Duration::from_nanos(1)),
        ..fixed(IrradianceConfig::default())
    };
    let mut technique = Irradiance::new(engine, volume, &s, config).expect("irradiance");
    // The first frame, before a block's cost is known, renders the whole image.
    technique
        .step(engine, &s, std::time::Duration::ZERO)
        .expect("step");
    assert_eq!(technique.iteration(), 1);
    let mut s = s;
    s.camera.eye[1] += 0.1;
    technique
        .apply(engine, &s, &voxlight_engine::Change::Camera)
        .expect("apply");
    for round in 0..2 {
        let mut frames = 0;
        while technique.iteration() == 0 {
            let report = technique
                .step(engine, &s, std::time::Duration::ZERO)
                .expect("step");
            frames += 1;
            assert_eq!(report.iterations_done, technique.iteration());
            assert!(frames <= 1000, "no picture after {frames} frames");
        }
        assert!(frames > 1, "one frame rendered the whole image");
        let accum = engine.gpu.read_buffer(technique.output()).expect("read");
        let unsampled = bytemuck::cast_slice::<u8, [f32; 4]>(&accum)
            .iter()
            .filter(|p| p[3] == 0.0)
            .count();
        assert_eq!(unsampled, 0, "round {round}: pixels without a sample");
        // A camera edit restarts the picture: covered again before it counts.
        s.camera.eye[0] += 0.2;
        technique
            .apply(engine, &s, &voxlight_engine::Change::Camera)
            .expect("apply");
        assert_eq!(technique.iteration(), 0);
    }
}
