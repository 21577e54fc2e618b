//! The `#[repr(C)]` structs of technique `photon` (server/engine/src/techniques/photon/gpu.rs) have the
//! same layout as their WGSL twins in shaders/photon_common.wgsl.

use std::mem::{offset_of, size_of};

use voxlight_engine::shaders;
use voxlight_engine::techniques::photon::gpu::{
    CHANGE_ADD, CHANGE_REPLACE, CHANGE_SUBTRACT, CHUNK_NONE, CHUNK_SLOTS, COUNTER_CHANGED,
    COUNTER_CHANGES, COUNTER_CUT, COUNTER_DEFERRED, COUNTER_DELTA, COUNTER_LIST,
    COUNTER_RECOLOURED, COUNTER_RETRACED, COUNTER_SCATTER, COUNTER_SCATTER_OVERFLOW,
    COUNTER_SEGMENTS, COUNTER_SPATIAL, COUNTER_TOUCH, COUNTER_WORDS, GRID_CHANGES, GRID_RECORDS,
    GatherState, MODE_FULL, MODE_UPDATE, PATH_QUERY_ROW, PhotonChange, PhotonEmitter, PhotonPath,
    PhotonRecord, PhotonUniforms, RecordResume, SAMPLE_WORDS, SLOT_WORDS, SPATIAL_AXES,
    SPATIAL_CELLS, SPATIAL_NONE, Segment,
};

fn assert_layout(module: &naga::Module, name: &str, size: usize, fields: &[(&str, usize)]) {
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("struct {name} not found in WGSL"));
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{name} is not a struct");
    };
    assert_eq!(
        *span as usize, size,
        "{name}: WGSL size {span} != Rust {size}"
    );
    assert_eq!(members.len(), fields.len(), "{name}: field count differs");
    for (member, (field, offset)) in members.iter().zip(fields) {
        assert_eq!(member.name.as_deref(), Some(*field), "{name}: field order");
        assert_eq!(member.offset as usize, *offset, "{name}.{field}: offset");
    }
}

macro_rules! fields {
    ($ty:ty: $($f:ident),* $(,)?) => {
        &[$((stringify!($f), offset_of!($ty, $f))),*]
    };
}

#[test]
fn photon_structs_match_wgsl() {
    for (name, source) in [
        ("photon_trace", shaders::photon_trace()),
        ("photon_grid", shaders::photon_grid()),
        ("photon_gather", shaders::photon_gather()),
        ("photon_scatter", shaders::photon_scatter()),
    ] {
        let module = naga::front::wgsl::parse_str(&source)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(&source)));
        assert_layout(
            &module,
            "PhotonUniforms",
            size_of::<PhotonUniforms>(),
            fields!(PhotonUniforms: grid_dims, cell_count, radius, kernel_norm, majorant,
                gather_step, photons_per_pass, path_count, record_count, bounces, path_offset,
                dispatch_paths, mode, segments, rejection_query_lo, rejection_query_hi,
                emitter_count, spatial, round_input, round_budget, round_stride,
                opacity_query_lo, opacity_query_hi, grid_pass, change_capacity,
                record_capacity, collision_query_lo, collision_query_hi, scatter_capacity,
                scatter_samples, census, round_first, roulette_survival, roulette_from,
                path_slots, inline_slots, chunks_per_pass, chunk_counts_at, sample_cache_samples,
                cache_generation, sums_applied, marks_stand, pass_kernels),
        );
        assert_layout(
            &module,
            "PhotonRecord",
            size_of::<PhotonRecord>(),
            fields!(PhotonRecord: position, cell, power, hist_lo, direction, hist_hi),
        );
        assert_layout(
            &module,
            "RecordResume",
            size_of::<RecordResume>(),
            fields!(RecordResume: t, draws),
        );
        assert_layout(
            &module,
            "PhotonPath",
            size_of::<PhotonPath>(),
            fields!(PhotonPath: count, end_lo, end_hi, collisions_lo, collisions_hi, chunk, pad1,
                pad2),
        );
        assert_layout(
            &module,
            "PhotonEmitter",
            size_of::<PhotonEmitter>(),
            fields!(PhotonEmitter: vector, kind, power, cdf),
        );
        assert_layout(
            &module,
            "PhotonChange",
            size_of::<PhotonChange>(),
            fields!(PhotonChange: position, cell, power, kind, direction, pass_index, old_power, pad1),
        );
        assert_layout(
            &module,
            "Segment",
            size_of::<Segment>(),
            fields!(Segment: color_lo, transmittance, color_hi, hist_lo, hist_hi, cut_off, pixel_hist_lo, pixel_hist_hi),
        );
        assert_layout(
            &module,
            "GatherState",
            size_of::<GatherState>(),
            fields!(GatherState: color_lo, k, color_hi, transmit, hist_lo, hist_hi, cell, rank),
        );
    }
}

/// The value of the WGSL `const name: u32`.
fn wgsl_u32(module: &naga::Module, name: &str) -> u32 {
    let (_, constant) = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("const {name} not found in WGSL"));
    match module.global_expressions[constant.init] {
        naga::Expression::Literal(naga::Literal::U32(v)) => v,
        ref other => panic!("const {name} is not a u32 literal: {other:?}"),
    }
}

#[test]
fn photon_constants_match_wgsl() {
    let source = shaders::photon_gather();
    let module = naga::front::wgsl::parse_str(&source)
        .unwrap_or_else(|e| panic!("photon_gather: {}", e.emit_to_string(&source)));
    for (name, value) in [
        ("MODE_FULL", MODE_FULL),
        ("MODE_UPDATE", MODE_UPDATE),
        ("SPATIAL_NONE", SPATIAL_NONE),
        ("SPATIAL_AXES", SPATIAL_AXES),
        ("SPATIAL_CELLS", SPATIAL_CELLS),
        ("COUNTER_RETRACED", COUNTER_RETRACED as u32),
        ("COUNTER_CHANGED", COUNTER_CHANGED as u32),
        ("COUNTER_SEGMENTS", COUNTER_SEGMENTS as u32),
        ("COUNTER_SPATIAL", COUNTER_SPATIAL as u32),
        ("COUNTER_LIST", COUNTER_LIST as u32),
        ("COUNTER_CHANGES", COUNTER_CHANGES as u32),
        ("COUNTER_DELTA", COUNTER_DELTA as u32),
        ("COUNTER_SCATTER", COUNTER_SCATTER as u32),
        ("COUNTER_SCATTER_OVERFLOW", COUNTER_SCATTER_OVERFLOW as u32),
        ("COUNTER_TOUCH", COUNTER_TOUCH as u32),
        ("COUNTER_RECOLOURED", COUNTER_RECOLOURED as u32),
        ("COUNTER_CUT", COUNTER_CUT as u32),
        ("COUNTER_DEFERRED", COUNTER_DEFERRED as u32),
        ("SLOT_WORDS", SLOT_WORDS as u32),
        ("SAMPLE_WORDS", SAMPLE_WORDS as u32),
        ("GRID_RECORDS", GRID_RECORDS),
        ("GRID_CHANGES", GRID_CHANGES),
        ("CHANGE_ADD", CHANGE_ADD),
        ("CHANGE_SUBTRACT", CHANGE_SUBTRACT),
        ("CHANGE_REPLACE", CHANGE_REPLACE),
        ("CHUNK_SLOTS", CHUNK_SLOTS),
        ("CHUNK_NONE", CHUNK_NONE),
        // The dirty-cell bits start right after the counters.
        ("COUNTER_DIRTY", COUNTER_WORDS as u32),
        ("PATH_QUERY_ROW", PATH_QUERY_ROW),
    ] {
        assert_eq!(wgsl_u32(&module, name), value, "{name}");
    }
}
