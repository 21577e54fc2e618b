//! Every WGSL file is validated with naga, and the Rust structs each pass binds have the same
//! layout as their WGSL twins.

use std::mem::{offset_of, size_of};

use voxlight_engine::passes::preview::PreviewParams;
use voxlight_engine::passes::tonemap::ToneParams;
use voxlight_engine::scene_gpu::{GpuLight, SceneUniforms};
use voxlight_engine::shaders;
use voxlight_engine::techniques::irradiance::gpu::{
    CacheEntry, DispatchInfo, IrradianceParams, Request,
};
use voxlight_engine::techniques::manylight::gpu::{ManylightParams, VirtualLight};

fn parse_and_validate(name: &str, source: &str) -> naga::Module {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("{name}: WGSL parse error:\n{}", e.emit_to_string(source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{name}: validation error:\n{}", e.emit_to_string(source)));
    module
}

#[test]
fn every_composed_shader_validates() {
    for (name, source) in shaders::all() {
        parse_and_validate(name, &source);
    }
}

#[test]
fn imports_compose_each_file_once_before_its_importers() {
    let source = shaders::compose("irradiance/render");
    assert!(!source.contains("#import"), "import lines are dropped");
    // `common` is imported by several pieces of this pass and appears once.
    let first_line = shaders::COMMON.lines().next().unwrap();
    assert_eq!(source.matches(first_line).count(), 1);
    // Imports come before the file that imports them.
    let render_line = shaders::IRRADIANCE_RENDER
        .lines()
        .find(|l| !l.is_empty() && !l.starts_with("//") && !l.starts_with("#import"))
        .unwrap();
    let common_at = source.find(first_line).unwrap();
    let irradiance_common_at = source
        .find(shaders::IRRADIANCE_COMMON.lines().next().unwrap())
        .unwrap();
    let render_at = source.find(render_line).unwrap();
    assert!(common_at < irradiance_common_at && irradiance_common_at < render_at);
    assert_eq!(
        shaders::imports(shaders::IRRADIANCE_RENDER).collect::<Vec<_>>(),
        vec!["irradiance/common"]
    );
}

#[test]
#[should_panic(expected = "unknown file")]
fn an_unknown_import_is_refused() {
    shaders::compose("no_such_shader");
}

#[test]
fn every_wgsl_file_is_part_of_a_validated_shader() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders");
    let composed: Vec<String> = shaders::all().into_iter().map(|(_, s)| s).collect();
    let mut count = 0;
    // `shaders/` and its folders (shared/, one per technique).
    let mut files = Vec::new();
    let mut folders = vec![dir.clone()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else {
                files.push(path);
            }
        }
    }
    for path in files {
        if path.extension().is_some_and(|e| e == "wgsl") {
            // A file appears in the composed source without its `#import` lines.
            let text: String = std::fs::read_to_string(&path)
                .unwrap()
                .lines()
                .filter(|l| !l.trim_start().starts_with("#import "))
                .flat_map(|l| [l, "\n"])
                .collect();
            assert!(
                composed.iter().any(|s| s.contains(&text)),
                "{} is not used by any shader in shaders::all()",
                path.display()
            );
            count += 1;
        }
    }
    assert!(
        count >= 25,
        "found only {count} WGSL files in {}",
        dir.display()
    );
}

/// Asserts that the WGSL struct `name` has the Rust struct's size and field offsets.
fn assert_layout(
    module: &naga::Module,
    name: &str,
    rust_size: usize,
    rust_fields: &[(&str, usize)],
) {
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("struct {name} not found in WGSL"));
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{name} is not a struct");
    };
    assert_eq!(
        *span as usize, rust_size,
        "{name}: WGSL size {span} != Rust size {rust_size}"
    );
    assert_eq!(
        members.len(),
        rust_fields.len(),
        "{name}: field count differs"
    );
    for (member, (field, offset)) in members.iter().zip(rust_fields) {
        assert_eq!(
            member.name.as_deref(),
            Some(*field),
            "{name}: field order/name differs"
        );
        assert_eq!(
            member.offset as usize, *offset,
            "{name}.{field}: WGSL offset {} != Rust {offset}",
            member.offset
        );
    }
}

macro_rules! fields {
    ($ty:ty: $($f:ident),* $(,)?) => {
        &[$((stringify!($f), offset_of!($ty, $f))),*]
    };
}

#[test]
fn rust_and_wgsl_layouts_agree() {
    let raymarch = parse_and_validate("raymarch", &shaders::raymarch());
    assert_layout(
        &raymarch,
        "SceneUniforms",
        size_of::<SceneUniforms>(),
        fields!(SceneUniforms: eye, tan_half_fov, right, aspect, up, step, forward, density_scale, box_min, g,
            box_max, light_count, env_radiance, seed, width, height, iteration, row_offset, cell_dims,
            cell_voxels, row_stride, pad0, pad1, pad2),
    );
    assert_layout(
        &raymarch,
        "GpuLight",
        size_of::<GpuLight>(),
        fields!(GpuLight: vector, kind, color, pad0),
    );
    let tonemap = parse_and_validate("tonemap", &shaders::tonemap());
    assert_layout(
        &tonemap,
        "ToneParams",
        size_of::<ToneParams>(),
        fields!(ToneParams: width, height, exposure, pad0),
    );
    let preview = parse_and_validate("preview_view", &shaders::preview(shaders::PREVIEW_VIEW));
    assert_layout(
        &preview,
        "PreviewParams",
        size_of::<PreviewParams>(),
        fields!(PreviewParams: light_dims, channels, width, height, row_offset, row_stride, gain,
            multiple, multiple_weight, z_offset),
    );
    let gather = parse_and_validate("manylight_gather", &shaders::manylight_gather());
    assert_layout(
        &gather,
        "ManylightParams",
        size_of::<ManylightParams>(),
        fields!(ManylightParams: capacity, count, first_path, max_bounces, face_res, nodes, mode, seed,
            vsl_radius, built_density, power_scale, list_count, fixed_majorant, pad0, pad1,
            pad2),
    );
    assert_layout(
        &gather,
        "VirtualLight",
        size_of::<VirtualLight>(),
        fields!(VirtualLight: position, tau, power, vertices, direction, path, opacity_lo,
            opacity_hi, colour_lo, colour_hi, value, pad0, pad1, pad2),
    );
    for pass in [
        shaders::IRRADIANCE_RENDER,
        shaders::IRRADIANCE_CREATE,
        shaders::IRRADIANCE_REQUESTS,
        shaders::IRRADIANCE_UPDATE,
        shaders::IRRADIANCE_PRIORITY,
    ] {
        let module = parse_and_validate("irradiance", &shaders::irradiance(pass));
        assert_layout(
            &module,
            "IrradianceParams",
            size_of::<IrradianceParams>(),
            fields!(IrradianceParams: root_min, root_edge, delta, gamma, epsilon, min_radius,
                max_radius, update_threshold, frame, flags, blocks_x, blocks_y, block_count,
                node_count, refs_offset, node_claim_offset, node_held_offset, block_claim_offset,
                block_held_offset, entry_capacity, max_pending, pending, min_samples, max_samples,
                bounces, priority_offset, voxel, dark_floor, delta_free_paths, view_picks),
        );
        assert_layout(
            &module,
            "CacheEntry",
            size_of::<CacheEntry>(),
            fields!(CacheEntry: position, key, normal, samples, irradiance, opacity_lo, sigma,
                opacity_hi, colour_lo, colour_hi, delta),
        );
        assert_layout(
            &module,
            "Request",
            size_of::<Request>(),
            fields!(Request: position, key, normal, lock, sums, count, state, opacity_lo,
                opacity_hi, colour_lo, colour_hi, delta, direct_sum, entry),
        );
        assert_layout(
            &module,
            "DispatchInfo",
            size_of::<DispatchInfo>(),
            fields!(DispatchInfo: first, count, round, pad0),
        );
    }
}

/// Every pass binds the lights as a uniform array (shared/scene.wgsl's MAX_LIGHTS) that holds as many
/// as the protocol allows.
#[test]
fn lights_are_a_uniform_array_of_max_lights() {
    for (name, source) in shaders::all() {
        let module = parse_and_validate(name, &source);
        let Some((_, lights)) = module
            .global_variables
            .iter()
            .find(|(_, v)| v.name.as_deref() == Some("lights"))
        else {
            continue;
        };
        assert_eq!(lights.space, naga::AddressSpace::Uniform, "{name}");
        let naga::TypeInner::Array { size, .. } = module.types[lights.ty].inner else {
            panic!("{name}: lights is not an array");
        };
        let naga::ArraySize::Constant(count) = size else {
            panic!("{name}: lights has no fixed size");
        };
        assert_eq!(
            count.get() as usize,
            voxlight_protocol::MAX_LIGHTS,
            "{name}"
        );
    }
}
