//! The interactive preview (engine::preview): its single scattering against converged
//! `raymarch` on the same scene, the light volume's reuse across camera moves and colour edits,
//! and the resolution divisor. A missing adapter fails these tests loudly.

mod common;

use std::sync::Arc;

use common::*;
use voxlight_engine::image_stats::{luminance, relative_rms_luminance};
use voxlight_engine::preview::{BrightnessMatch, LightDetail, PreviewMeans};
use voxlight_engine::{Change, GpuVolume, Scene};
use voxlight_protocol::{Camera, Light};

/// Mean ratio (preview / reference) of the image's luminance, and the relative RMS error of
/// the pixels' luminance (RMS of the difference over the reference's mean).
fn compare(preview: &[[f32; 3]], reference: &[[f32; 3]]) -> (f64, f64) {
    assert_eq!(preview.len(), reference.len());
    let n = reference.len() as f64;
    let mean_ref = reference.iter().map(|c| luminance(*c)).sum::<f64>() / n;
    let mean_pre = preview.iter().map(|c| luminance(*c)).sum::<f64>() / n;
    (
        mean_pre / mean_ref,
        relative_rms_luminance(preview, reference),
    )
}

fn preview_hdr(volume: Arc<GpuVolume>, scene: &Scene, divisor: u32) -> Vec<[f32; 3]> {
    let engine = engine();
    let mut renderer = engine
        .create_renderer("raymarch", volume, scene)
        .expect("renderer");
    let (frame, _) = renderer
        .preview_frame(engine, scene, divisor, LightDetail::Full)
        .expect("preview");
    assert!(frame.preview);
    let preview = renderer.preview().expect("a preview was made");
    preview.read_hdr(engine, divisor).expect("hdr")
}

fn cornell_scene(size: u32, iterations: u32) -> (Arc<GpuVolume>, Scene) {
    let volume = voxlight_volumes::phantom("cornell", 64).expect("cornell phantom");
    let gpu_volume = engine().upload_volume(&volume).expect("upload");
    let tf = cornell_materials_tf(0.02, |_, _, _| {});
    let lights = voxlight_protocol::default_lights();
    let mut scene = scene(tf, lights, 60.0, size, iterations);
    scene.camera = Camera {
        eye: [0.6, -2.2, 0.5],
        ..Camera::default()
    };
    (gpu_volume, scene)
}

fn sphere_scene(size: u32, iterations: u32) -> (Arc<GpuVolume>, Scene) {
    let (_, volume) = sphere(64);
    let lights = vec![
        Light::Point {
            position: [0.8, -0.9, 0.7],
            intensity: [2.5, 2.4, 2.2],
        },
        Light::Environment {
            radiance: [0.15, 0.18, 0.22],
        },
    ];
    let mut scene = scene(ramp_tf(0.8), lights, 8.0, size, iterations);
    scene.params.g = 0.4;
    (volume, scene)
}

/// Tolerances around what lavapipe measured: the sphere (smooth medium, point light, environment,
/// g = 0.4) 0.3% in the mean and 1.9% RMS; the Cornell phantom (walls two voxels thick,
/// as thin as the light volume's cell, and labelled materials) 1.9% and 27% RMS (its
/// reference is still noisy at 128 iterations).
#[test]
fn preview_agrees_with_converged_raymarch() {
    let mut results = Vec::new();
    for (name, (volume, scene), mean_tolerance, rms_tolerance) in [
        ("sphere", sphere_scene(96, 128), 0.01, 0.05),
        ("cornell", cornell_scene(96, 128), 0.03, 0.3),
    ] {
        let (_, reference) = render(volume.clone(), &scene);
        let preview = preview_hdr(volume, &scene, 1);
        let (mean_ratio, rel_rms) = compare(&preview, &reference);
        eprintln!("{name}: mean ratio {mean_ratio:.4}, relative RMS {rel_rms:.4}");
        if let Ok(dir) = std::env::var("VOXLIGHT_PREVIEW_DUMP") {
            dump(
                &format!("{dir}/{name}_preview.ppm"),
                &preview,
                scene.viewport.width,
            );
            dump(
                &format!("{dir}/{name}_raymarch.ppm"),
                &reference,
                scene.viewport.width,
            );
        }
        results.push((name, mean_ratio, rel_rms, mean_tolerance, rms_tolerance));
    }
    for (name, mean_ratio, rel_rms, mean_tolerance, rms_tolerance) in results {
        assert!(
            (mean_ratio - 1.0).abs() < mean_tolerance,
            "{name}: mean ratio {mean_ratio} (tolerance {mean_tolerance})"
        );
        assert!(
            rel_rms < rms_tolerance,
            "{name}: relative RMS {rel_rms} (tolerance {rms_tolerance})"
        );
    }
}

/// Writes an HDR image as an 8-bit sRGB PPM (for looking at a failure).
fn dump(path: &str, hdr: &[[f32; 3]], width: u32) {
    let height = hdr.len() as u32 / width;
    let mut bytes = format!("P6 {width} {height} 255\n").into_bytes();
    for p in hdr {
        bytes.extend(p.iter().map(|&c| srgb_byte(c)));
    }
    std::fs::write(path, bytes).expect("dump");
}

/// Camera moves and colour-only TF edits reuse the light volume; opacity edits rebuild it. While
/// edits stream in (`LightDetail::Interactive`) it is rebuilt at half the grid points per axis,
/// close to the full one, and the next full-detail preview rebuilds it in full (an interactive
/// one after that reuses the full one). The divisor sets the image size.
#[test]
fn light_volume_is_rebuilt_only_when_it_must() {
    let engine = engine();
    let (volume, mut scene) = sphere_scene(64, 1);
    let mut renderer = engine
        .create_renderer("raymarch", volume, &scene)
        .expect("renderer");
    let mut render = |scene: &Scene, divisor: u32, detail: LightDetail| {
        let (frame, report) = renderer
            .preview_frame(engine, scene, divisor, detail)
            .expect("preview");
        let preview = renderer.preview().expect("a preview");
        let hdr = preview.read_hdr(engine, divisor).expect("hdr");
        (
            frame,
            report.light_rebuilt,
            preview.built_light_dims(),
            preview.light_rebuilds(),
            hdr,
        )
    };
    let (frame, rebuilt, full_dims, rebuilds, full) = render(&scene, 1, LightDetail::Full);
    assert!(rebuilt && rebuilds == 1);
    assert_eq!((frame.width, frame.height), (64, 64));

    scene.camera.eye = [0.9, -2.2, 0.4];
    let (frame, rebuilt, ..) = render(&scene, 4, LightDetail::Interactive);
    assert!(!rebuilt, "a camera move reuses the light volume");
    assert_eq!((frame.width, frame.height), (16, 16));
    for point in &mut scene.tf.points {
        point.color = [0.3, 0.6, 0.9];
    }
    let (_, rebuilt, dims, ..) = render(&scene, 2, LightDetail::Interactive);
    assert!(!rebuilt, "a colour edit reuses the light volume");
    assert_eq!(
        dims, full_dims,
        "an interactive preview keeps a full light volume"
    );

    // Back to the first scene's camera and colours, with the opacities halved and back.
    let (_, first_scene) = sphere_scene(64, 1);
    scene = first_scene.clone();
    for point in &mut scene.tf.points {
        point.opacity *= 0.5;
    }
    let (_, rebuilt, dims, ..) = render(&scene, 1, LightDetail::Interactive);
    assert!(rebuilt, "an opacity edit rebuilds the light volume");
    assert_eq!(
        dims,
        full_dims.map(|d| d.div_ceil(2)),
        "coarse while interacting"
    );
    let (_, rebuilt, dims, _, coarse) = render(&first_scene, 1, LightDetail::Interactive);
    assert!(rebuilt && dims != full_dims);
    let (coarse_mean, coarse_rms) = compare(&coarse, &full);
    eprintln!(
        "coarse light volume vs full: mean ratio {coarse_mean:.4}, relative RMS {coarse_rms:.4}"
    );
    assert!(
        (coarse_mean - 1.0).abs() < 0.02,
        "coarse mean ratio {coarse_mean}"
    );
    let (_, rebuilt, dims, rebuilds, again) = render(&first_scene, 1, LightDetail::Full);
    assert!(
        rebuilt && dims == full_dims,
        "at rest the light volume is rebuilt in full"
    );
    assert_eq!(rebuilds, 4);
    assert_eq!(again, full, "the same inputs give the same picture");
}

/// Mean luminance of a preview with its means matched by `brightness`.
fn preview_luminance(means: &PreviewMeans, brightness: &BrightnessMatch) -> f64 {
    let c: [f32; 3] = std::array::from_fn(|k| {
        (means.background[k]
            + f64::from(brightness.gain[k]) * means.single[k]
            + f64::from(brightness.multiple_weight[k]) * means.multiple[k]) as f32
    });
    luminance(c)
}

fn converge(renderer: &mut voxlight_engine::Renderer, scene: &Scene) -> Vec<[f32; 3]> {
    let engine = engine();
    while !renderer.converged(scene) {
        renderer
            .step(engine, scene, std::time::Duration::from_secs(10))
            .expect("step");
    }
    renderer.read_hdr(engine).expect("hdr")
}

/// Moving → still without a brightness step (issue 20): a session converges, is dragged (an
/// orbit and an opacity edit, shown by previews), comes to rest and converges again. The last
/// preview, a full-resolution one at rest, carries the brightness match fitted to the first
/// still; its mean must meet the second still's within 1%. Without the match the GI
/// techniques' stills are brighter by their multiple scattering and raymarch's differs by the
/// light volume's coarseness, so the test also checks that the match is what closes the gap.
#[test]
fn brightness_is_continuous_from_the_last_preview_to_the_still() {
    let engine = engine();
    let mut failures = Vec::new();
    for technique in ["raymarch", "photon", "irradiance", "manylight"] {
        let (volume, mut scene) = sphere_scene(64, 64);
        let mut renderer = engine
            .create_renderer(technique, volume, &scene)
            .expect("renderer");
        let prior = renderer.brightness_match();
        // Session start: a preview, then at rest the full-resolution one and the still.
        renderer
            .preview_frame(engine, &scene, 4, LightDetail::Interactive)
            .expect("preview");
        renderer
            .preview_frame(engine, &scene, 1, LightDetail::Full)
            .expect("preview");
        converge(&mut renderer, &scene);
        assert_eq!(
            renderer.brightness_match(),
            prior,
            "fitted only when an edit comes"
        );

        // The drag: a 15° orbit and the opacities at 80%, each shown by a reduced preview.
        let old_tf = scene.tf.clone();
        scene.camera.eye = [
            scene.camera.eye[0] * 0.966 - scene.camera.eye[1] * 0.259,
            scene.camera.eye[0] * 0.259 + scene.camera.eye[1] * 0.966,
            scene.camera.eye[2],
        ];
        renderer
            .defer(engine, &scene, &Change::Camera)
            .expect("defer");
        let fitted = renderer.brightness_match();
        renderer
            .preview_frame(engine, &scene, 4, LightDetail::Interactive)
            .expect("preview");
        for point in &mut scene.tf.points {
            point.opacity *= 0.8;
        }
        renderer
            .defer(engine, &scene, &Change::tf(&old_tf, &scene.tf))
            .expect("defer");
        assert_eq!(
            renderer.brightness_match(),
            fitted,
            "fitted once per rest, not against a moving scene"
        );
        let (frame, _) = renderer
            .preview_frame(engine, &scene, 4, LightDetail::Interactive)
            .expect("preview");
        assert_eq!(frame.preview_match, Some(fitted));

        // At rest: the full-resolution preview, then the technique converges.
        renderer
            .preview_frame(engine, &scene, 1, LightDetail::Full)
            .expect("preview");
        let means = renderer
            .preview()
            .expect("a preview")
            .means(engine, 1)
            .expect("means");
        let still = converge(&mut renderer, &scene);
        let still_mean = still.iter().map(|c| luminance(*c)).sum::<f64>() / still.len() as f64;
        let matched = preview_luminance(&means, &fitted) / still_mean - 1.0;
        let unmatched = preview_luminance(&means, &BrightnessMatch::new(false)) / still_mean - 1.0;
        eprintln!(
            "{technique}: {fitted:?}; last preview vs still {:+.2}% (single scattering alone {:+.2}%)",
            100.0 * matched,
            100.0 * unmatched
        );
        if matched.abs() >= 0.01 {
            failures.push(format!(
                "{technique}: {:+.2}% with the match, {:+.2}% without",
                100.0 * matched,
                100.0 * unmatched
            ));
        }
        if technique != "raymarch" && unmatched.abs() < 0.03 {
            failures.push(format!(
                "{technique}: the single scattering alone is within {:+.2}%: the scene does not \
                 test the match",
                100.0 * unmatched
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// A long preview (the full-resolution one at rest takes seconds on lavapipe) runs in parts:
/// grid planes of the light volume, then interleaved bands of rows, with a question between
/// them whether to give way to an edit. Stopped during the light volume, it leaves the volume
/// stale (rebuilt next time); in parts it is bit for bit the picture of one dispatch.
#[test]
fn a_long_preview_runs_in_parts_and_gives_way() {
    let engine = engine();
    let (volume, mut scene) = sphere_scene(64, 1);
    let mut renderer = engine
        .create_renderer("raymarch", volume.clone(), &scene)
        .expect("renderer");
    renderer
        .preview_frame(engine, &scene, 1, LightDetail::Full)
        .expect("preview");
    let dims = renderer.preview().expect("a preview").built_light_dims();
    // Every part as small as it can be: one grid plane, one 8-row block.
    renderer
        .preview_mut()
        .expect("a preview")
        .set_part_time(std::time::Duration::from_nanos(1));
    for point in &mut scene.tf.points {
        point.opacity *= 0.5;
    }
    let mut asked = 0;
    let stopped = renderer
        .preview_frame_until(
            engine,
            &scene,
            1,
            LightDetail::Full,
            Some(&mut || {
                asked += 1;
                asked == 3
            }),
        )
        .expect("preview");
    assert!(stopped.is_none(), "stopped at the third question");
    let rebuilds = renderer.preview().expect("a preview").light_rebuilds();
    let mut asked = 0;
    let (frame, report) = renderer
        .preview_frame_until(
            engine,
            &scene,
            1,
            LightDetail::Full,
            Some(&mut || {
                asked += 1;
                false
            }),
        )
        .expect("preview")
        .expect("not stopped");
    assert!(report.light_rebuilt, "a partly built light volume is stale");
    assert_eq!(
        renderer.preview().expect("a preview").light_rebuilds(),
        rebuilds + 1
    );
    // Asked between the planes and between the blocks, not after the last of either.
    assert_eq!(asked, (dims[2] - 1) + (frame.height.div_ceil(8) - 1));
    let parts = renderer
        .preview()
        .expect("a preview")
        .read_hdr(engine, 1)
        .expect("hdr");
    let whole = preview_hdr(volume, &scene, 1);
    assert_eq!(parts, whole, "a preview in parts differs from a whole one");
}
