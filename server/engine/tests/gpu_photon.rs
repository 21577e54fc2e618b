//! Technique `photon` on whatever adapter exists (lavapipe in CI): incremental TF updates equal
//! a full recompute bit for bit, and the photon map agrees with `raymarch` where both compute
//! single scattering.

mod common;

use std::sync::Arc;
use std::time::Duration;

use common::*;
use voxlight_engine::techniques::photon::{
    Invalidation, Photon, PhotonBudget, PhotonParams, PhotonState, UpdateReport, WorkBound,
};
use voxlight_engine::{Change, GpuVolume, Scene, Technique};
use voxlight_protocol::{Camera, Light, TransferFunction};

/// The Cornell materials' TF of these tests; `edit` changes one material.
fn cornell_tf(edit: impl Fn(&str, &mut [f32; 3], &mut f32)) -> TransferFunction {
    cornell_materials_tf(0.02, edit)
}

/// A change to one material of the Cornell TF (`cornell_with`).
#[derive(Debug, Clone, Copy)]
enum Set {
    Colour([f32; 3]),
    Opacity(f32),
    OpacityTimes(f32),
}

const SPHERE_RED: (&str, Set) = ("sphere", Set::Colour([0.9, 0.1, 0.1]));
const SPHERE_GREEN: (&str, Set) = ("sphere", Set::Colour([0.1, 0.9, 0.1]));
const TALL_BLOCK_HALF: (&str, Set) = ("tall block", Set::OpacityTimes(0.5));
const TALL_BLOCK_GONE: (&str, Set) = ("tall block", Set::Opacity(0.0));

/// The Cornell TF of these tests with `sets` applied to their materials, in order.
fn cornell_with(sets: &[(&str, Set)]) -> TransferFunction {
    cornell_tf(|name, colour, opacity| {
        for &(material, set) in sets {
            if material == name {
                match set {
                    Set::Colour(c) => *colour = c,
                    Set::Opacity(o) => *opacity = o,
                    Set::OpacityTimes(f) => *opacity *= f,
                }
            }
        }
    })
}

/// The Cornell phantom at `size`³, uploaded.
fn cornell_volume(size: u32) -> Arc<GpuVolume> {
    engine()
        .upload_volume(&voxlight_volumes::phantom("cornell", size).expect("cornell"))
        .expect("upload")
}

fn cornell_scene(size: u32, tf: TransferFunction) -> Scene {
    let mut s = scene(
        tf,
        vec![
            Light::Point {
                position: [0.0, -0.05, 0.3],
                intensity: [0.9, 0.85, 0.8],
            },
            Light::Directional {
                direction: [0.3, 0.2, -1.0],
                irradiance: [1.0, 1.0, 1.0],
            },
            Light::Environment {
                radiance: [0.08, 0.08, 0.09],
            },
        ],
        30.0,
        size,
        2,
    );
    // Look into the open front of the box (z = max).
    s.camera = Camera {
        eye: [0.0, 0.0, 2.6],
        target: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_deg: 28.0,
    };
    s
}

fn params(invalidation: Invalidation) -> PhotonParams {
    PhotonParams {
        photons_per_pass: 4096,
        max_passes: 2,
        bounces: 3,
        radius: 0.0,
        segments: 6,
        gather_step_voxels: 1.0,
        invalidation,
        gather_budget: 0,
        change_list: 0,
        ..PhotonParams::default()
    }
}

fn converge(photon: &mut Photon, scene: &Scene) {
    let engine = engine();
    while photon.iteration() < photon.target_iterations(scene) {
        photon
            .step(engine, scene, Duration::from_secs(60))
            .expect("step");
    }
}

/// A new photon map of `scene`, converged by `step`.
fn converged(volume: &Arc<GpuVolume>, scene: &Scene, p: PhotonParams) -> Photon {
    let mut photon = Photon::new(engine(), volume.clone(), scene, p).expect("photon");
    converge(&mut photon, scene);
    photon
}

fn full_recompute(volume: &Arc<GpuVolume>, scene: &Scene, p: PhotonParams) -> PhotonState {
    let engine = engine();
    let mut full = Photon::new(engine, volume.clone(), scene, p).expect("photon");
    full.recompute(engine, scene, p.max_passes)
        .expect("recompute");
    full.read_state(engine).expect("read")
}

fn bytes<T: bytemuck::Pod>(x: &[T]) -> Vec<u8> {
    bytemuck::cast_slice::<T, u8>(x).to_vec()
}

/// Where the arrays named `what` first differ bit for bit, with both entries there (a length
/// difference counts, at the shorter one's end); None when they are identical.
fn differ<T: bytemuck::Pod + std::fmt::Debug>(what: &str, a: &[T], b: &[T]) -> Option<String> {
    if bytes(a) == bytes(b) {
        return None;
    }
    let n = a.len().min(b.len());
    let i = (0..n)
        .find(|&i| bytemuck::bytes_of(&a[i]) != bytemuck::bytes_of(&b[i]))
        .unwrap_or(n);
    let (x, y) = (a.get(i), b.get(i));
    Some(format!("{what} differ first at {i}: {x:?} vs {y:?}"))
}

fn first_difference(a: &PhotonState, b: &PhotonState) -> Option<String> {
    differ("paths", &a.paths, &b.paths)
        .or_else(|| differ("records", &a.records, &b.records))
        .or_else(|| differ("grid cell starts", &a.grid_cells, &b.grid_cells))
        .or_else(|| differ("grid orders", &a.grid_sorted, &b.grid_sorted))
        .or_else(|| differ("segments", &a.segments, &b.segments))
        .or_else(|| differ("images", &a.hdr, &b.hdr))
}

/// Fails with the first difference unless the states are bit-identical.
fn assert_same(a: &PhotonState, b: &PhotonState, what: &str) {
    if let Some(diff) = first_difference(a, b) {
        panic!("{what}: {diff}");
    }
}

/// Fails unless `photon`'s state is bit for bit a full recompute's of `scene`.
fn assert_equals_full(
    photon: &Photon,
    volume: &Arc<GpuVolume>,
    scene: &Scene,
    p: PhotonParams,
    what: &str,
) {
    let state = photon.read_state(engine()).expect("read");
    assert_same(
        &state,
        &full_recompute(volume, scene, p),
        &format!("{what}: incremental != full"),
    );
}

/// Edits `scene`'s TF to `tf` through `photon`'s update, checks the result against a full
/// recompute bit for bit, and returns the update's report.
fn edit_equals_full(
    photon: &mut Photon,
    volume: &Arc<GpuVolume>,
    scene: &mut Scene,
    tf: TransferFunction,
    p: PhotonParams,
    what: &str,
) -> UpdateReport {
    let change = Change::tf(&scene.tf, &tf);
    scene.tf = tf;
    photon.apply(engine(), scene, &change).expect("apply");
    assert_equals_full(photon, volume, scene, p, what);
    photon.last_update().expect("report")
}

#[test]
fn incremental_tf_edits_equal_a_full_recompute_bit_for_bit() {
    let size = 40;
    let volume = cornell_volume(40);
    // (name, new TF, local: must reuse part of the work)
    let edit = |name, sets: &[(&str, Set)], local| (name, cornell_with(sets), local);
    let edits: Vec<(&str, TransferFunction, bool)> = vec![
        edit("colour only: sphere red", &[SPHERE_RED], true),
        // Paths recoloured at the sphere and retraced from the tall block on.
        edit(
            "mixed: sphere green, tall block half as opaque",
            &[SPHERE_GREEN, TALL_BLOCK_HALF],
            true,
        ),
        // A black albedo ends the paths there (they trace on no further)...
        edit(
            "to black: sphere black",
            &[("sphere", Set::Colour([0.0; 3]))],
            true,
        ),
        // ...and a colour again lets them go on: traced from the sphere on.
        edit("from black: sphere red again", &[SPHERE_RED], true),
        edit(
            "opacity only: tall block removed",
            &[SPHERE_RED, TALL_BLOCK_GONE],
            true,
        ),
        // Only opacity rises: the rejection query alone.
        edit("opacity rise: tall block back", &[SPHERE_RED], true),
        edit(
            "opacity fall: tall block removed again",
            &[SPHERE_RED, TALL_BLOCK_GONE],
            true,
        ),
        // Most paths cross the thin medium without a collision in it.
        edit(
            "colour only: thin medium recoloured",
            &[
                SPHERE_RED,
                TALL_BLOCK_GONE,
                ("medium", Set::Colour([0.5, 0.8, 0.9])),
            ],
            true,
        ),
        edit(
            "local: thicker medium",
            &[SPHERE_RED, TALL_BLOCK_GONE, ("medium", Set::Opacity(0.05))],
            false,
        ),
        (
            "global: every colour darker",
            cornell_tf(|n, c, o| {
                *c = c.map(|x| x * 0.7);
                if n == "tall block" {
                    *o = 0.0;
                }
                if n == "medium" {
                    *o = 0.05;
                }
            }),
            false,
        ),
    ];
    // The default (dirty cells, per-sample photon sums that the changes are scattered into);
    // the same where the sums take the changes from the gather at the dirty samples (a loop
    // budget too small for the scatter); segments that sum every photon's weighted term, with
    // the delta scatter and without it (every delta segment gathered from the change grid);
    // and the other segment tests, with sums and without.
    let dirty = params(Invalidation::DirtyCells);
    let configurations = [
        ("dirty cells", dirty),
        (
            "dirty cells, sums from the gather",
            PhotonParams {
                gather_budget: 100,
                ..dirty
            },
        ),
        (
            "dirty cells, segment sums",
            PhotonParams {
                sample_cache_bytes: 0,
                ..dirty
            },
        ),
        (
            "dirty cells, no scatter",
            PhotonParams {
                scatter_bytes: 0,
                ..dirty
            },
        ),
        ("spatial 3x64", params(Invalidation::SpatialHistogram)),
        (
            "spatial 3x64, segment sums",
            PhotonParams {
                sample_cache_bytes: 0,
                ..params(Invalidation::SpatialHistogram)
            },
        ),
        ("any photon", params(Invalidation::AnyPhoton)),
    ];
    for (spatial, p) in configurations {
        let mut s = cornell_scene(size, cornell_with(&[]));
        let mut photon = converged(&volume, &s, p);
        // Every configuration but those that turn them off keeps per-sample sums.
        let sums = p.sample_cache_bytes > 0;
        assert_eq!(photon.budget().sample_cache_samples > 0, sums, "{spatial}");
        for (name, tf, local) in &edits {
            // The paths whose historygram meets the whole query: what the paper retraces.
            let query = voxlight_engine::tf::query_historygram(&s.tf, tf);
            let widened = query | (query << 1) | (query >> 1);
            let opacity_rises = voxlight_engine::tf::opacity_rise_historygram(&s.tf, tf) != 0;
            let meeting_query = photon
                .read_state(engine())
                .expect("read")
                .paths
                .iter()
                .filter(|p| (p.end_lo as u64 | (p.end_hi as u64) << 32) & widened != 0)
                .count() as u64;
            let what = format!("{spatial}, edit `{name}`");
            let report = edit_equals_full(&mut photon, &volume, &mut s, tf.clone(), p, &what);
            eprintln!(
                "{spatial}, {name}: query {query:064b}, retraced {:.1}% of {} paths ({} recoloured), {} records changed \
                 ({} change-list entries; {meeting_query} paths meet the query), segments {:.1}% ({} from \
                 the changes alone, {} by the scatter)",
                report.photons_retraced_pct(),
                report.paths,
                report.paths_recoloured,
                report.records_changed,
                report.changes,
                report.segments_recomputed_pct(),
                report.segments_delta,
                report.segments_scattered,
            );
            if name.starts_with("colour only") {
                // A colour edit moves no photon: the paths it reaches are only recoloured.
                assert_eq!(report.paths_retraced, 0, "{name}");
                assert!(report.paths_recoloured > 0, "{name}: nothing recoloured");
            } else {
                assert!(report.paths_retraced > 0, "{name}: nothing retraced");
            }
            if name.contains("thin medium") {
                // No opacity rose, so a path that only passed through the edited bins without
                // a collision there is not retraced.
                assert!(!opacity_rises, "{name}");
                assert!(
                    2 * report.paths_retraced < meeting_query,
                    "{name}: retraced {} of the {meeting_query} paths meeting the query",
                    report.paths_retraced
                );
            }
            if name.starts_with("colour only") {
                // No opacity changed: every stale segment is updated from the changed photons.
                assert!(
                    report.segments_delta > 0,
                    "{name}: no segment updated by the changes"
                );
                assert_eq!(report.segments_delta, report.segments_recomputed, "{name}");
                // The scatter takes them all (it has room; with per-sample sums it needs no
                // slots), or none where it is off or where every change is too wide for it
                // (the loop budget of 100).
                let scattered = if (sums || p.scatter_bytes > 0) && p.gather_budget == 0 {
                    report.segments_delta
                } else {
                    0
                };
                assert_eq!(report.segments_scattered, scattered, "{spatial}, {name}");
                // Nothing moved: every changed record is one entry that replaces its power.
                assert_eq!(report.changes, report.records_changed, "{name}");
            }
            if *local {
                assert!(
                    report.photons_retraced_pct() < 90.0,
                    "{name}: a local edit retraced {:.1}% of the photons",
                    report.photons_retraced_pct()
                );
            }
        }
    }
}

#[test]
fn camera_edit_keeps_photons_and_matches_a_full_recompute() {
    let volume = cornell_volume(32);
    let p = params(Invalidation::DirtyCells);
    let mut s = cornell_scene(32, cornell_with(&[]));
    let mut photon = converged(&volume, &s, p);
    let traced = photon.stats().details.photons_traced;
    s.camera.eye = [0.3, 0.2, 2.5];
    photon.apply(engine(), &s, &Change::Camera).expect("apply");
    // The segments are gathered again for the new view (by `step`, in parts); no photon is
    // traced again.
    converge(&mut photon, &s);
    assert_eq!(photon.passes(), p.max_passes, "photons were kept");
    assert_eq!(
        photon.stats().details.photons_traced,
        traced,
        "no photon traced again"
    );
    assert_equals_full(&photon, &volume, &s, p, "camera edit");
}

#[test]
fn the_hash_grid_holds_every_photon_in_its_own_cell() {
    // The grid's prefix sum runs over blocks of 4096 cells (photon/grid.wgsl); with more than
    // two blocks, each cell's range of the sorted slots must hold exactly its records.
    let volume = cornell_volume(32);
    let p = params(Invalidation::DirtyCells);
    let photon = converged(&volume, &cornell_scene(32, cornell_with(&[])), p);
    let cells = photon.budget().cells as usize;
    assert!(cells > 2 * 4096, "{cells} cells: fewer than three blocks");
    let state = photon.read_state(engine()).expect("read");
    let mut counts = vec![0u32; cells];
    for r in state.records.iter().filter(|r| r.cell != u32::MAX) {
        counts[r.cell as usize] += 1;
    }
    let stored: u32 = counts.iter().sum();
    assert!(stored > 1000, "{stored} photons stored");
    let mut start = 0u32;
    for (c, &count) in counts.iter().enumerate() {
        assert_eq!(state.grid_cells[c], start, "start of cell {c}");
        for &i in &state.grid_sorted[start as usize..(start + count) as usize] {
            assert_eq!(
                state.records[i as usize].cell, c as u32,
                "a slot of cell {c}"
            );
        }
        start += count;
    }
    assert_eq!(state.grid_cells[cells], stored, "the grid's total");
}

#[test]
fn single_scattering_agrees_with_raymarch() {
    // A white-ish scattering ball lit by a directional light and the environment. With one
    // stored bounce the photon map estimates exactly what `raymarch` does (single scattering);
    // it differs by kernel blur (radius 1.5 voxels) and noise. Mean radiance over the ball
    // within 8%.
    let size = 48;
    let (_, volume) = sphere(48);
    let lights = vec![
        Light::Directional {
            direction: [0.35, 0.75, -0.55],
            irradiance: [3.0, 3.0, 3.0],
        },
        Light::Environment {
            radiance: [0.2, 0.2, 0.2],
        },
    ];
    let s = scene(ramp_tf(0.8), lights, 3.0, size, 8);
    let (_, reference) = render_with("raymarch", volume.clone(), &s);
    let p = PhotonParams {
        photons_per_pass: 65536,
        max_passes: 8,
        bounces: 1,
        ..PhotonParams::default()
    };
    let mut photon = Photon::new(engine(), volume, &s, p).expect("photon");
    converge(&mut photon, &s);
    let state = photon.read_state(engine()).expect("read");
    let env = 0.2;
    // Pixels that see the ball: the raymarch differs from the bare environment there.
    let (mut got, mut want, mut n) = (0.0f64, 0.0f64, 0);
    for (i, r) in reference.iter().enumerate() {
        if (r[1] - env).abs() > 0.02 {
            got += state.hdr[i][1] as f64;
            want += r[1] as f64;
            n += 1;
        }
    }
    assert!(n > 200, "the ball covers {n} pixels");
    let ratio = got / want;
    eprintln!("photon / raymarch over {n} pixels: {ratio:.4}");
    assert!(
        (ratio - 1.0).abs() < 0.08,
        "photon mean {:.4} vs raymarch {:.4} (ratio {ratio:.4})",
        got / n as f64,
        want / n as f64
    );
}

/// The 32³ sphere phantom and a 32² scene of it (default lights, opacity ramp) for
/// `iterations`.
fn sphere_scene(iterations: u32) -> (Arc<GpuVolume>, Scene) {
    let (_, volume) = sphere(32);
    let lights = voxlight_protocol::default_lights();
    (volume, scene(ramp_tf(0.8), lights, 3.0, 32, iterations))
}

#[test]
fn selectable_by_name_and_reports_stats() {
    let (volume, s) = sphere_scene(2);
    let (renderer, hdr) = render_with("photon", volume, &s);
    assert_eq!(renderer.technique_name(), "photon");
    assert!(
        hdr.iter()
            .all(|p| p.iter().all(|c| c.is_finite() && *c >= 0.0))
    );
    let stats = renderer.stats();
    assert_eq!(stats.iteration, 2);
    let (in_map, traced) = (stats.details.photons_in_map, stats.details.photons_traced);
    assert!(
        in_map.is_some_and(|n| n > 0) && traced >= in_map,
        "{stats:?}"
    );
    assert!(stats.memory_bytes > 0);
    assert!(engine().techniques().iter().any(|t| t.name == "photon"));
}

#[test]
fn oversized_photon_map_is_refused_before_allocation() {
    let (volume, s) = sphere_scene(64);
    let p = PhotonParams {
        photons_per_pass: 1 << 22,
        max_passes: 64,
        ..PhotonParams::default()
    };
    match Photon::new(engine(), volume, &s, p) {
        Err(voxlight_engine::EngineError::OutOfMemory { needed, available }) => {
            assert!(needed > available)
        }
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("a 2^28-record photon map was accepted"),
    }
}

/// At the benchmark's size the fullest hash cells hold thousands of photons, so the gather
/// runs in several chunks on lavapipe (its loop limit); before chunking, the limit cut full
/// and incremental gathers off at different points and this failed.
#[test]
fn bench_sized_cornell_edit_is_bit_exact() {
    let volume = cornell_volume(64);
    let p = PhotonParams {
        photons_per_pass: 16384,
        max_passes: 4,
        bounces: 2,
        segments: 8,
        ..PhotonParams::default()
    };
    let mut s = cornell_scene(96, cornell_with(&[]));
    s.target_iterations = 4;
    s.params.density_scale = 60.0;
    s.lights = vec![
        Light::Point {
            position: [0.0, -0.05, 0.36],
            intensity: [0.9, 0.85, 0.8],
        },
        Light::Environment {
            radiance: [0.08, 0.08, 0.09],
        },
    ];
    let tf = cornell_with(&[("sphere", Set::Colour([0.2, 0.35, 0.9]))]);
    let mut photon = Photon::new(engine(), volume.clone(), &s, p).expect("photon");
    photon.recompute(engine(), &s, 4).expect("recompute");
    assert_same(
        &photon.read_state(engine()).unwrap(),
        &full_recompute(&volume, &s, p),
        "full recompute is not reproducible",
    );
    edit_equals_full(&mut photon, &volume, &mut s, tf, p, "bench-sized edit");
    // The device's own round budget cuts nothing short: a far smaller one (many more rounds,
    // far below any loop limit) gives the same bits.
    let small = PhotonParams {
        gather_budget: 1000,
        ..p
    };
    let full = photon.read_state(engine()).unwrap();
    assert_same(
        &full_recompute(&volume, &s, small),
        &full,
        "gather budget 1000",
    );
}

/// The work census (`bench tf-edit --census`) counts a full recompute's work per record without
/// changing it, and tells the edits apart by what they move: a colour edit only recolours photons
/// (delta tracking against a TF-independent majorant never reads the albedo), a removed
/// material moves the paths that collided in it.
#[test]
fn the_work_census_counts_a_full_recompute_without_changing_it() {
    let volume = cornell_volume(40);
    let p = params(Invalidation::DirtyCells);
    let mut s = cornell_scene(40, cornell_with(&[]));
    let mut photon = Photon::new(engine(), volume.clone(), &s, p).expect("photon");
    let old = photon.census(engine(), &s, p.max_passes).expect("census");
    let state = photon.read_state(engine()).expect("read");
    let full = full_recompute(&volume, &s, p);
    assert_same(&state, &full, "a census is not a full recompute");
    assert_eq!(old.records, state.records);
    for (i, r) in old.records.iter().enumerate() {
        if r.cell == u32::MAX {
            assert_eq!(old.terms[i], 0, "slot {i} holds no photon but gave terms");
        } else {
            assert!(
                old.steps[i] >= 1,
                "slot {i} holds a photon its flight never reached"
            );
        }
    }
    let total: u64 = old.terms.iter().map(|&t| t as u64).sum();
    assert!(total > 0, "the gather formed no term");

    let census_with = |photon: &mut Photon, tf: &TransferFunction| {
        let scene = Scene {
            tf: tf.clone(),
            ..s.clone()
        };
        photon
            .census(engine(), &scene, p.max_passes)
            .expect("census")
    };
    let recoloured = cornell_with(&[SPHERE_RED]);
    let colour = census_with(&mut photon, &recoloured);
    let bound = WorkBound::between(&old, &colour);
    assert!(bound.records_changed > 0, "the sphere holds no photon");
    assert_eq!(bound.records_power_only, bound.records_changed, "{bound:?}");
    assert_eq!(
        (bound.paths_moved, bound.steps_resumed),
        (0, 0),
        "{bound:?}"
    );
    assert!(
        bound.terms_changed > 0 && bound.terms_changed < bound.terms,
        "{bound:?}"
    );
    assert_eq!(
        colour.steps, old.steps,
        "a colour edit changed the tracking"
    );

    let removed = cornell_with(&[TALL_BLOCK_GONE]);
    let removal = census_with(&mut photon, &removed);
    let bound = WorkBound::between(&old, &removal);
    assert!(
        bound.paths_moved > 0 && bound.steps_resumed > 0,
        "{bound:?}"
    );
    assert!(bound.steps_resumed <= bound.steps_retracked, "{bound:?}");
    assert!(
        bound.terms_moved_old > 0,
        "the tall block's photons gave no terms: {bound:?}"
    );
    assert!(bound.speedup_bound(0.5) > 1.0, "{bound:?}");

    // An update from a census's map (the census borrowed the delta scatter's buffer) still
    // equals a full recompute.
    // The map now holds the last census's TF.
    s.tf = removed;
    let what = "an update after a census";
    let report = edit_equals_full(&mut photon, &volume, &mut s, recoloured, p, what);
    assert!(
        report.segments_scattered > 0,
        "the update did not use the scatter: {report:?}"
    );
}

/// An update that changes more records than the change list holds gathers its photon-stale
/// segments afresh: still bit for bit the full recompute.
#[test]
fn an_overflowing_change_list_still_equals_a_full_recompute() {
    let volume = cornell_volume(32);
    let p = PhotonParams {
        change_list: 64,
        ..params(Invalidation::DirtyCells)
    };
    let mut s = cornell_scene(32, cornell_with(&[]));
    let mut photon = converged(&volume, &s, p);
    let tf = cornell_with(&[SPHERE_RED]);
    let report = edit_equals_full(&mut photon, &volume, &mut s, tf, p, "overflowing list");
    assert!(
        report.changes > 64,
        "{} changes fit the list",
        report.changes
    );
    assert!(report.segments_recomputed > 0);
    assert_eq!(report.segments_delta, 0, "an overflowing list was used");
}

/// The delta scatter's two ways out are exact too: with room for fewer segments than an edit
/// changes, the rest are gathered from the change grid; where a change reaches more pixels than
/// one invocation may visit (here a tiny loop budget), every delta segment is gathered instead.
#[test]
fn delta_scatter_capacity_and_overflow_still_equal_a_full_recompute() {
    let volume = cornell_volume(32);
    let base = cornell_scene(40, cornell_with(&[]));
    let defaults = params(Invalidation::DirtyCells);
    let segments = 40 * 40 * defaults.segments as u64;
    // The slot map (4 bytes per segment) and room for about a hundred segments (a slot is 22
    // words here): fewer than the edit's (~250 at the default radius of 1.5 voxels), but
    // enough that the changes (about one per segment) are worth scattering.
    // Slots are the delta scatter's where segments sum every photon's weighted term.
    let few_slots = PhotonParams {
        scatter_bytes: segments * 4 + 100 * 4 * 22,
        sample_cache_bytes: 0,
        ..defaults
    };
    let overflowing = PhotonParams {
        gather_budget: 100,
        ..defaults
    };
    // With per-sample sums: the marks (which add the changes to the sums as they go) or,
    // without the marks, the scatter find the wide changes after adding some, and the sums
    // start anew.
    let overflowing_unmarked = PhotonParams {
        invalidation: Invalidation::SpatialHistogram,
        ..overflowing
    };
    let segment_sums = PhotonParams {
        sample_cache_bytes: 0,
        ..overflowing
    };
    // Some changes fit the marks and some do not: the marks add the first to the sums before
    // they meet the others.
    let partly = PhotonParams {
        gather_budget: 400,
        ..defaults
    };
    for (name, p) in [
        ("few slots", few_slots),
        ("overflow", overflowing),
        ("overflow, partly", partly),
        ("overflow without marks", overflowing_unmarked),
        ("overflow, segment sums", segment_sums),
    ] {
        let mut s = base.clone();
        let mut photon = converged(&volume, &s, p);
        let tf = cornell_with(&[SPHERE_RED]);
        let report = edit_equals_full(&mut photon, &volume, &mut s, tf, p, name);
        eprintln!(
            "{name}: {} segments from the changes, {} by the scatter, {} changes",
            report.segments_delta, report.segments_scattered, report.changes
        );
        assert!(report.segments_delta > 0, "{name}");
        if name == "few slots" {
            assert!(report.segments_scattered > 0, "{name}: nothing scattered");
            assert!(
                report.segments_scattered < report.segments_delta,
                "{name}: the scatter had room for all"
            );
        } else {
            assert_eq!(report.segments_scattered, 0, "{name}: the scatter was used");
        }
        // A second edit starts from what the first left in the sums.
        let tf = cornell_with(&[SPHERE_GREEN, TALL_BLOCK_HALF]);
        edit_equals_full(
            &mut photon,
            &volume,
            &mut s,
            tf,
            p,
            &format!("{name}, again"),
        );
    }
}

/// The delta scatter only saves time: where its state would not fit (here a storage binding
/// larger than the device allows), the session is made without it instead of refused.
#[test]
fn a_delta_scatter_that_does_not_fit_is_left_out() {
    let volume = cornell_volume(32);
    let s = cornell_scene(1024, cornell_with(&[]));
    let p = PhotonParams {
        segments: 2,
        scatter_bytes: 1 << 40,
        ..params(Invalidation::DirtyCells)
    };
    let budget = PhotonBudget::new(&p, &volume, 1024, 1024, p.max_passes).expect("budget");
    assert!(
        budget.check(engine()).is_err(),
        "the scatter's {} bytes fit; the test needs a larger one",
        budget.scatter_bytes
    );
    let photon = Photon::new(engine(), volume, &s, p).expect("fits without the scatter");
    assert_eq!(photon.params().scatter_bytes, 0);
    assert_eq!(photon.budget().scatter_capacity, 0);
}

/// The per-sample sums only save time too: at the default budget they are left out of a view
/// that needs more (1024² here), and where a larger budget asks for more than the device's
/// storage binding holds, the session is made without them instead of refused (and keeps the
/// delta scatter).
#[test]
fn per_sample_sums_that_do_not_fit_are_left_out() {
    let volume = cornell_volume(32);
    let s = cornell_scene(1024, cornell_with(&[]));
    let defaults = PhotonParams {
        segments: 2,
        ..params(Invalidation::DirtyCells)
    };
    let budget =
        |p: &PhotonParams| PhotonBudget::new(p, &volume, 1024, 1024, p.max_passes).expect("budget");
    assert_eq!(budget(&defaults).sample_cache_samples, 0);
    let asking = PhotonParams {
        sample_cache_bytes: 1 << 40,
        ..defaults
    };
    let wanted = budget(&asking);
    assert!(wanted.sample_cache_samples > 0);
    assert!(
        wanted.check(engine()).is_err(),
        "the sums' {} bytes fit; the test needs a larger view",
        wanted.sample_cache_bytes
    );
    let photon = Photon::new(engine(), volume.clone(), &s, asking).expect("fits without the sums");
    assert_eq!(photon.params().sample_cache_bytes, 0);
    assert_eq!(photon.budget().sample_cache_samples, 0);
    assert!(photon.budget().scatter_capacity > 0);
    // At the tests' sizes they are on.
    let small = cornell_scene(40, cornell_with(&[]));
    let photon = Photon::new(engine(), volume, &small, defaults).expect("photon");
    assert!(photon.budget().sample_cache_samples > 0);
}

/// A gather cut into many small rounds (what lavapipe's loop limit needs at larger sizes)
/// forms the same fixed-point sums as one unbounded round: the states are bit-identical.
#[test]
fn gather_rounds_do_not_change_a_bit() {
    let volume = cornell_volume(32);
    let s = cornell_scene(40, cornell_with(&[]));
    let one = PhotonParams {
        gather_budget: u32::MAX,
        ..params(Invalidation::DirtyCells)
    };
    let small = PhotonParams {
        gather_budget: 200,
        ..one
    };
    let mut a = Photon::new(engine(), volume.clone(), &s, one).expect("photon");
    a.recompute(engine(), &s, one.max_passes)
        .expect("recompute");
    let mut b = Photon::new(engine(), volume, &s, small).expect("photon");
    b.recompute(engine(), &s, small.max_passes)
        .expect("recompute");
    assert_eq!(a.gather_rounds(), 1);
    assert!(b.gather_rounds() >= 4, "{} rounds", b.gather_rounds());
    let (a, b) = (
        a.read_state(engine()).unwrap(),
        b.read_state(engine()).unwrap(),
    );
    assert!(a.hdr.iter().any(|p| p[0] > 0.0));
    assert_same(&a, &b, "budget 200 against one round");
}

/// Where the device cuts long shader loops short (lavapipe), a density scale whose photon
/// tracking would exceed that is refused with a clear error instead of silently wrong photons;
/// elsewhere it is rendered.
#[test]
fn dense_media_are_refused_where_tracking_would_be_cut_short() {
    let volume = cornell_volume(32);
    let mut s = cornell_scene(24, cornell_with(&[]));
    s.params.density_scale = 100_000.0;
    let p = params(Invalidation::DirtyCells);
    let mut photon = Photon::new(engine(), volume, &s, p).expect("photon");
    let result = photon.recompute(engine(), &s, 1);
    match engine().gpu.loop_limit() {
        Some(_) => match result {
            Err(voxlight_engine::EngineError::InvalidScene(m)) => {
                assert!(m.contains("density scale"), "{m}")
            }
            other => panic!("density 100000 accepted on a loop-limited device: {other:?}"),
        },
        None => assert!(result.is_ok(), "{result:?}"),
    }
}

/// A pass's gather (and a camera edit's) runs as parts, one submission each, so that `step`
/// returns between them: a pass counts once its gather is done, a camera edit drops the
/// gather under way, a TF edit finishes it before its update. The result is a full
/// recompute's, bit for bit.
#[test]
fn gathers_in_parts_equal_a_full_recompute_bit_for_bit() {
    let engine = engine();
    let volume = cornell_volume(32);
    let p = params(Invalidation::DirtyCells);
    let s = cornell_scene(24, cornell_with(&[]));
    // 24² pixels × 6 segments, at most 3456 list slots: parts of 1000 take up to four steps.
    let mut photon = Photon::new(engine, volume.clone(), &s, p).expect("photon");
    photon.fix_gather_part(1000);
    let mut done = Vec::new();
    loop {
        let report = photon.step(engine, &s, Duration::ZERO).expect("step");
        done.push((report.iterations_done, report.iteration));
        if report.converged {
            break;
        }
    }
    // Per pass: the trace and the gather's start, then the parts, the last with the
    // composite: a pass counts only then.
    let completed: Vec<usize> = (0..done.len()).filter(|&i| done[i].0 == 1).collect();
    assert_eq!(completed.len(), 2, "{done:?}");
    assert_eq!(completed[1], done.len() - 1, "{done:?}");
    for (i, &(_, iteration)) in done.iter().enumerate() {
        assert_eq!(
            iteration,
            completed.iter().filter(|&&c| c <= i).count() as u32
        );
    }
    assert!(
        completed[0] >= 2 && completed[1] - completed[0] >= 3,
        "a gather of up to 3456 slots in parts of 1000 took one step: {done:?}"
    );

    // A camera edit: the gather starts again for the new view; one part in, a second camera
    // edit drops it for its own.
    let mut turned = s.clone();
    turned.camera.eye = [0.4, 0.2, 2.5];
    photon
        .apply(engine, &turned, &Change::Camera)
        .expect("apply");
    assert_eq!(
        photon.iteration(),
        0,
        "the old view's picture is not this view's"
    );
    photon.step(engine, &turned, Duration::ZERO).expect("step");
    let mut turned_again = turned.clone();
    turned_again.camera.eye = [-0.3, 0.1, 2.6];
    photon
        .apply(engine, &turned_again, &Change::Camera)
        .expect("apply");
    converge(&mut photon, &turned_again);
    assert_equals_full(&photon, &volume, &turned_again, p, "two camera edits");

    // A TF edit while a camera edit's gather is under way: the photons are updated and the
    // gather starts again with the new TF.
    photon.apply(engine, &s, &Change::Camera).expect("apply");
    photon.step(engine, &s, Duration::ZERO).expect("step");
    let mut edited = s.clone();
    edited.tf = cornell_with(&[
        ("tall block", Set::Colour([0.2, 0.7, 0.2])),
        TALL_BLOCK_HALF,
    ]);
    let edit = Change::tf(&s.tf, &edited.tf);
    photon.apply(engine, &edited, &edit).expect("apply");
    let update = photon.last_update().expect("an update");
    assert!(update.paths_retraced > 0 && update.paths_retraced < update.paths);
    converge(&mut photon, &edited);
    assert_equals_full(&photon, &volume, &edited, p, "a TF edit during a gather");

    // A TF edit with no gather under way: the incremental update, as before (finished at
    // once, no part left for `step`).
    let mut back = edited.clone();
    back.tf = s.tf.clone();
    photon
        .apply(engine, &back, &Change::tf(&edited.tf, &back.tf))
        .expect("apply");
    assert_eq!(photon.iteration(), p.max_passes);
    assert_equals_full(
        &photon,
        &volume,
        &back,
        p,
        "a TF edit with no gather under way",
    );
}

/// Makes each edit in turn through `photon`'s update, each equal to a full recompute bit for
/// bit and each redoing only part of the paths.
fn local_edits_equal_full<const N: usize>(
    photon: &mut Photon,
    volume: &Arc<GpuVolume>,
    scene: &mut Scene,
    edits: [TransferFunction; N],
    p: PhotonParams,
) {
    for (i, tf) in edits.into_iter().enumerate() {
        let what = format!("edit {i}");
        let report = edit_equals_full(photon, volume, scene, tf, p, &what);
        assert!(
            report.paths_retraced + report.paths_recoloured < report.paths,
            "edit {i} redid every path: {report:?}"
        );
    }
}

/// Per-sample photon sums that take an update's changes from its gather (at the dirty samples of
/// the segments it recomposites), not from the scatter, stay exact over edits that hide samples
/// and show them again: a sample whose opacity fell to zero, or that fell past its segment's
/// transmittance cut-off, forgets its sum when a change lies near it, so that a later edit
/// gathers it afresh instead of reading a sum that missed the change. The scatter's wide-change
/// limit, met after it added some changes, starts a new generation of sums instead.
#[test]
fn per_sample_sums_stay_exact_when_samples_hide_and_show_again() {
    let volume = cornell_volume(32);
    let p = params(Invalidation::DirtyCells);
    let hide_and_show = || {
        [
            cornell_with(&[TALL_BLOCK_GONE]),
            cornell_with(&[]),
            cornell_with(&[TALL_BLOCK_HALF]),
            cornell_with(&[]),
            cornell_with(&[TALL_BLOCK_HALF]),
            cornell_with(&[SPHERE_RED, TALL_BLOCK_HALF]),
        ]
    };
    let mut s = cornell_scene(40, cornell_with(&[]));
    // Dense enough that the blocks end a segment's march (transmittance below its cut-off)
    // within a few samples, fewer at full opacity than at half.
    s.params.density_scale = 100.0;
    let mut photon = converged(&volume, &s, p);
    assert!(photon.budget().sample_cache_samples > 0);
    photon.sum_changes_in_gather();
    local_edits_equal_full(&mut photon, &volume, &mut s, hide_and_show(), p);
    // Without the dirty cells' marks the scatter adds the changes (they are few for the
    // segments the spatial historygram lists) until it meets one too wide for its loop budget.
    for budget in [150, 400] {
        let p = PhotonParams {
            gather_budget: budget,
            ..params(Invalidation::SpatialHistogram)
        };
        let mut s = cornell_scene(40, cornell_with(&[]));
        let mut photon = converged(&volume, &s, p);
        local_edits_equal_full(&mut photon, &volume, &mut s, hide_and_show(), p);
    }
}

/// A segment whose opacity an edit did not change recomposites from its samples' kept sums and
/// the weights its last march gave them (recomposite_from_sums). Colour edits follow edits that
/// end the tall block's marches earlier at their transmittance cut-off (half its opacity, then
/// all of it again) and that empty its samples (the block gone): the weights past the new
/// cut-off and of the emptied samples are no longer those of the first march. Then, with a
/// change list too short for one edit, colour edits follow an update that started a new
/// generation of sums, some of which no gather has formed yet (those segments are gathered).
#[test]
fn colour_edits_recomposite_from_the_weights_of_each_segments_last_march() {
    let volume = cornell_volume(32);
    let p = params(Invalidation::DirtyCells);
    let mut s = cornell_scene(40, cornell_with(&[TALL_BLOCK_HALF]));
    // Dense enough that the blocks end a segment's march within a few samples.
    s.params.density_scale = 100.0;
    let mut photon = converged(&volume, &s, p);
    assert!(photon.budget().sample_cache_samples > 0);
    let edits = [
        cornell_with(&[]),
        cornell_with(&[SPHERE_RED]),
        cornell_with(&[SPHERE_RED, TALL_BLOCK_GONE]),
        cornell_with(&[SPHERE_GREEN, TALL_BLOCK_GONE]),
    ];
    for (i, tf) in edits.into_iter().enumerate() {
        let what = format!("edit {i}");
        let report = edit_equals_full(&mut photon, &volume, &mut s, tf, p, &what);
        eprintln!("{what}: {report:?}");
        if i % 2 == 1 {
            // A colour edit: segments recomposited by the changes alone, which the marks
            // added to the sums (recomposite_touched).
            assert!(report.segments_scattered > 0, "{what}: {report:?}");
        }
    }
    // A small loop budget leaves segments' gathers in rounds, so a segment's kept gather state
    // is not its start.
    let p = PhotonParams {
        change_list: 64,
        gather_budget: 300,
        ..params(Invalidation::DirtyCells)
    };
    let mut s = cornell_scene(40, cornell_with(&[]));
    s.params.density_scale = 100.0;
    let mut photon = converged(&volume, &s, p);
    let edits = [
        cornell_with(&[TALL_BLOCK_GONE]),
        cornell_with(&[SPHERE_RED, TALL_BLOCK_GONE]),
        cornell_with(&[SPHERE_GREEN, TALL_BLOCK_GONE]),
    ];
    for (i, tf) in edits.into_iter().enumerate() {
        let what = format!("short list, edit {i}");
        let report = edit_equals_full(&mut photon, &volume, &mut s, tf, p, &what);
        eprintln!("{what}: {report:?}");
        if i == 0 {
            assert!(report.changes > 64, "{what}: {report:?}");
        } else {
            // The marks stood and added the changes to the sums (recomposite_touched).
            assert!(report.changes <= 64, "{what}: {report:?}");
            assert!(report.segments_scattered > 0, "{what}: {report:?}");
        }
    }
}

/// An opacity edit with few changes (the marks stand for the dirty cells) still recomputes every
/// segment whose opacity changed, also where no change lies near it: the sphere made slightly
/// thinner changes the transmittance of every segment that sees it, but moves only the photons
/// whose paths met it. Both formulations.
#[test]
fn a_small_opacity_edit_recomputes_every_segment_it_changes() {
    let volume = cornell_volume(32);
    for sums in [true, false] {
        let p = PhotonParams {
            sample_cache_bytes: if sums { 256 << 20 } else { 0 },
            ..params(Invalidation::DirtyCells)
        };
        let mut s = cornell_scene(40, cornell_with(&[]));
        let mut photon = converged(&volume, &s, p);
        let thinner = cornell_with(&[("sphere", Set::OpacityTimes(0.9))]);
        let report = edit_equals_full(&mut photon, &volume, &mut s, thinner, p, "sphere thinner");
        eprintln!("sums {sums}: {report:?}");
        // The marks ran (few changes for the segments), and some segments changed by their
        // opacity alone.
        assert!(report.changes * 16 <= report.segments, "{report:?}");
        assert!(
            report.segments_recomputed > report.segments_delta,
            "{report:?}"
        );
    }
}

/// After an update starts a new generation of per-sample sums, a segment whose opacity did not
/// change holds no valid sums and gathers its samples afresh: from a records' grid rebuilt for
/// the photons the update moved. Here the camera sees only the left half of the box, so an
/// opacity edit of the sphere (at the right; no other material's values interpolate to its)
/// moves photons without changing any segment's opacity.
#[test]
fn segments_gathered_afresh_after_the_sums_start_anew_read_a_current_grid() {
    let volume = cornell_volume(32);
    // A loop budget too small for some changes: the scatter starts the sums anew.
    let p = PhotonParams {
        gather_budget: 150,
        ..params(Invalidation::SpatialHistogram)
    };
    let mut s = cornell_scene(40, cornell_with(&[]));
    s.camera = Camera {
        eye: [-0.3, 0.0, 2.6],
        target: [-0.3, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_deg: 8.0,
    };
    let mut photon = converged(&volume, &s, p);
    let seen = cornell_with(&[TALL_BLOCK_HALF]);
    edit_equals_full(&mut photon, &volume, &mut s, seen, p, "tall block half");
    let unseen = cornell_with(&[TALL_BLOCK_HALF, ("sphere", Set::Opacity(0.3))]);
    let report = edit_equals_full(&mut photon, &volume, &mut s, unseen, p, "sphere thinner");
    assert!(report.paths_retraced > 0, "{report:?}");
    assert!(report.segments_delta > 0, "{report:?}");
    assert_eq!(
        report.segments_delta, report.segments_recomputed,
        "a segment's opacity changed: {report:?}"
    );
}

/// Issue 25's consistency machinery under updates: long paths with Russian roulette (up to 12
/// scatterings, roulette from the second) and four passes, each gathered with its own, shrinking
/// radius (Knaus–Zwicker). Colour, mixed and opacity edits in a row still equal a full recompute
/// bit for bit: the roulette never reads the TF, and every photon (also in the change list) is
/// gathered with its own pass's radius.
#[test]
fn roulette_and_shrinking_radii_keep_updates_bit_exact() {
    let volume = cornell_volume(32);
    let p = PhotonParams {
        photons_per_pass: 2048,
        max_passes: 4,
        bounces: 12,
        ..params(Invalidation::DirtyCells)
    };
    assert!(p.roulette_survival < 1.0 && p.radius_alpha < 1.0);
    let mut s = cornell_scene(32, cornell_with(&[]));
    s.target_iterations = 4;
    let mut photon = converged(&volume, &s, p);
    let edits = [
        cornell_with(&[SPHERE_RED]),
        cornell_with(&[SPHERE_GREEN, TALL_BLOCK_HALF]),
        cornell_with(&[SPHERE_GREEN]),
    ];
    local_edits_equal_full(&mut photon, &volume, &mut s, edits, p);
}

/// Paths longer than their own slots take chunks from their pass's pool (issue 25: no fixed
/// cap on a path's length), and updates stay bit-exact although an updated path keeps its
/// chunks and takes new ones in another order than a full recompute does: the state is read
/// in path order, and the gather's sums do not depend on where a record lies. Roulette rarely
/// ends a path here (survival 0.95), so many paths grow past their 4 own slots and some past 8.
#[test]
fn long_paths_take_chunks_and_keep_updates_bit_exact() {
    let volume = cornell_volume(32);
    let p = PhotonParams {
        photons_per_pass: 2048,
        max_passes: 2,
        bounces: 256,
        record_slots: 8,
        roulette_survival: 0.95,
        ..params(Invalidation::DirtyCells)
    };
    let mut s = cornell_scene(32, cornell_with(&[]));
    let mut photon = converged(&volume, &s, p);
    assert!(!photon.chunks_exhausted(engine()).expect("read"));
    let longest = |photon: &Photon| {
        let state = photon.read_state(engine()).expect("read");
        state.paths.iter().map(|p| p.count).max().unwrap_or(0)
    };
    let before = longest(&photon);
    assert!(before > 8, "no path took two chunks (longest {before})");
    let edits = [
        cornell_with(&[SPHERE_RED]),
        // Paths lose the tall block and run further, then find it again.
        cornell_with(&[SPHERE_RED, TALL_BLOCK_GONE]),
        cornell_with(&[SPHERE_GREEN, TALL_BLOCK_HALF]),
        cornell_with(&[SPHERE_GREEN]),
    ];
    local_edits_equal_full(&mut photon, &volume, &mut s, edits, p);
}

/// A pass whose paths need more chunks than its pool holds would cut the last ones short:
/// the session doubles its record slots and recomputes, until none is cut, and its updates
/// stay bit-exact (the reference, made with the small slots too, grows alike).
#[test]
fn a_map_that_runs_out_of_chunks_grows_and_stays_exact() {
    let volume = cornell_volume(32);
    let p = PhotonParams {
        photons_per_pass: 1024,
        max_passes: 2,
        bounces: 32,
        record_slots: 8,
        // No roulette: every path runs until it leaves the box or reaches the cap.
        roulette_survival: 1.0,
        ..params(Invalidation::DirtyCells)
    };
    let mut s = cornell_scene(32, cornell_with(&[]));
    let mut photon = converged(&volume, &s, p);
    assert!(
        photon.params().record_slots > p.record_slots,
        "the slots did not grow"
    );
    assert!(!photon.chunks_exhausted(engine()).expect("read"));
    let edits = [
        cornell_with(&[SPHERE_RED]),
        cornell_with(&[TALL_BLOCK_GONE]),
    ];
    local_edits_equal_full(&mut photon, &volume, &mut s, edits, p);
}

/// A pass's trace runs in parts too (`step` returns between them, so that an edit waits for a
/// part of the trace, not for the pass): a camera edit and a TF edit that arrive while passes
/// are being traced still leave a picture that converges to a full recompute's bits (the TF
/// edit finishes the trace with the TF it started with, then updates the whole map).
#[test]
fn passes_traced_in_parts_with_edits_between_equal_a_full_recompute() {
    let engine = engine();
    let volume = cornell_volume(32);
    let p = PhotonParams {
        max_passes: 3,
        ..params(Invalidation::DirtyCells)
    };
    let mut s = cornell_scene(24, cornell_with(&[]));
    s.target_iterations = 3;
    let mut photon = Photon::new(engine, volume.clone(), &s, p).expect("photon");
    // Passes of 4096 paths in parts of 1000.
    photon.fix_trace_part(1000);
    let step = |photon: &mut Photon, scene: &Scene| {
        photon.step(engine, scene, Duration::ZERO).expect("step");
    };
    // Into the second pass's trace: it starts, then one part.
    let mut traced_in_parts = false;
    while photon.iteration() < 1 {
        step(&mut photon, &s);
        traced_in_parts |= photon.tracing().is_some_and(|t| t > 0);
    }
    assert!(traced_in_parts, "the first pass was traced in one step");
    step(&mut photon, &s);
    step(&mut photon, &s);
    assert!(
        photon
            .tracing()
            .is_some_and(|t| t > 0 && t < p.photons_per_pass)
    );
    let mut turned = s.clone();
    turned.camera.eye = [0.4, 0.2, 2.5];
    photon
        .apply(engine, &turned, &Change::Camera)
        .expect("apply");
    while photon.iteration() < 2 {
        step(&mut photon, &turned);
    }
    // Two passes, both gathered in the new view.
    let mut two = turned.clone();
    two.target_iterations = 2;
    let p2 = PhotonParams { max_passes: 2, ..p };
    assert_equals_full(
        &photon,
        &volume,
        &two,
        p2,
        "a camera edit between trace parts",
    );
    // Into the third pass's trace, then a TF edit.
    step(&mut photon, &turned);
    step(&mut photon, &turned);
    assert!(
        photon
            .tracing()
            .is_some_and(|t| t > 0 && t < p.photons_per_pass)
    );
    let mut edited = turned.clone();
    edited.tf = cornell_with(&[SPHERE_RED, TALL_BLOCK_HALF]);
    let edit = Change::tf(&turned.tf, &edited.tf);
    photon.apply(engine, &edited, &edit).expect("apply");
    assert_eq!(photon.tracing(), None, "a TF edit left a pass half traced");
    converge(&mut photon, &edited);
    assert_equals_full(&photon, &volume, &edited, p, "edits between trace parts");
}
