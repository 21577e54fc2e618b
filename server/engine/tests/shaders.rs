//! Every WGSL file is validated with naga, and the Rust structs each pass binds have the same
//! layout as their WGSL twins.

use std::mem::{offset_of, size_of};

use voxlight_engine::passes::builder::Binding;
use voxlight_engine::passes::preview::PreviewParams;
use voxlight_engine::passes::tonemap::ToneParams;
use voxlight_engine::passes::{estimator, preview, tonemap};
use voxlight_engine::scene_gpu::{GpuLight, SceneUniforms};
use voxlight_engine::shaders;
use voxlight_engine::techniques::irradiance::gpu::{
    CacheEntry, DispatchInfo, IrradianceParams, Pass, Request,
};
use voxlight_engine::techniques::manylight::gpu::{ManylightParams, VirtualLight};
use voxlight_engine::techniques::{manylight, photon};

fn parse_and_validate(name: &str, source: &str) -> naga::Module {
    validate(name, source).0
}

fn validate(name: &str, source: &str) -> (naga::Module, naga::valid::ModuleInfo) {
    let module = naga::front::wgsl::parse_str(source)
        .unwrap_or_else(|e| panic!("{name}: WGSL parse error:\n{}", e.emit_to_string(source)));
    let info = naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{name}: validation error:\n{}", e.emit_to_string(source)));
    (module, info)
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
        vec!["irradiance/paths", "irradiance/cache"]
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
                bounces, priority_offset, voxel, dark_floor, delta_free_paths, view_picks,
                validation_threshold, validation_samples, pad0, pad1),
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
            fields!(DispatchInfo: first, count, round, validate),
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

/// What a WGSL global of group 0 holds, in the terms of `Binding` (a dynamic offset is not
/// WGSL's to say: `Binding::Dynamic` declares a uniform).
fn declared_kind(module: &naga::Module, var: &naga::GlobalVariable) -> &'static str {
    match var.space {
        naga::AddressSpace::Uniform => "uniform",
        naga::AddressSpace::Storage { access } if access.contains(naga::StorageAccess::STORE) => {
            "read_write"
        }
        naga::AddressSpace::Storage { .. } => "read",
        naga::AddressSpace::Handle => match module.types[var.ty].inner {
            // The volume (3D) and the TF lookup table (one 2D row), read with `textureLoad`.
            naga::TypeInner::Image {
                dim: dim @ (naga::ImageDimension::D3 | naga::ImageDimension::D2),
                arrayed: false,
                class:
                    naga::ImageClass::Sampled {
                        kind: naga::ScalarKind::Float,
                        multi: false,
                    },
            } => {
                if dim == naga::ImageDimension::D3 {
                    "volume"
                } else {
                    "lut"
                }
            }
            naga::TypeInner::Image {
                dim: naga::ImageDimension::D2,
                arrayed: false,
                class:
                    naga::ImageClass::Storage {
                        format: naga::StorageFormat::R32Uint,
                        access,
                    },
            } if access.contains(naga::StorageAccess::LOAD | naga::StorageAccess::STORE) => "words",
            ref other => panic!("{:?}: unexpected handle {other:?}", var.name),
        },
        other => panic!("{:?}: unexpected address space {other:?}", var.name),
    }
}

fn rust_kind(binding: Binding) -> &'static str {
    match binding {
        Binding::Uniform | Binding::Dynamic(_) => "uniform",
        Binding::Read => "read",
        Binding::ReadWrite => "read_write",
        Binding::Volume => "volume",
        Binding::Lut => "lut",
        Binding::Words => "words",
    }
}

/// Each binding a composed shader declares: its number, what it holds and its global.
fn declared_bindings(
    name: &str,
    module: &naga::Module,
) -> Vec<(u32, &'static str, naga::Handle<naga::GlobalVariable>)> {
    let mut declared: Vec<_> = module
        .global_variables
        .iter()
        .filter_map(|(handle, var)| {
            let binding = var.binding.as_ref()?;
            assert_eq!(binding.group, 0, "{name}: {:?} is not in group 0", var.name);
            Some((binding.binding, declared_kind(module, var), handle))
        })
        .collect();
    declared.sort_by_key(|d| d.0);
    declared
}

/// The WGSL struct size of a `Binding::Dynamic` record is the one the layout gives.
fn assert_record_size(
    name: &str,
    module: &naga::Module,
    global: naga::Handle<naga::GlobalVariable>,
    size: u64,
) {
    let ty = &module.types[module.global_variables[global].ty];
    assert_eq!(
        ty.inner.size(module.to_ctx()) as u64,
        size,
        "{name}: record size of {:?}",
        ty.name
    );
}

/// Every shader's bindings are in its Rust bind group layout, with the same numbers and
/// kinds: where one layout serves several passes, each declares a part of it.
#[test]
fn every_declared_binding_is_in_its_rust_layout() {
    let shared: [(&str, &[Binding]); 12] = [
        ("raymarch", &estimator::BINDINGS),
        ("pathtrace", &estimator::BINDINGS),
        ("tonemap", &tonemap::BINDINGS),
        ("preview/light", &preview::BINDINGS),
        ("preview/view", &preview::BINDINGS),
        ("manylight/vls", &manylight::gpu::BINDINGS),
        ("manylight/avsm", &manylight::gpu::BINDINGS),
        ("manylight/gather", &manylight::gpu::BINDINGS),
        ("photon/trace", &photon::gpu::BINDINGS),
        ("photon/grid", &photon::gpu::BINDINGS),
        ("photon/gather", &photon::gpu::BINDINGS),
        ("photon/scatter", &photon::gpu::BINDINGS),
    ];
    for (name, source) in shaders::all() {
        if name.starts_with("irradiance/") {
            continue; // one layout per pass: the next test
        }
        let (_, layout) = shared
            .iter()
            .find(|(n, _)| *n == name)
            .unwrap_or_else(|| panic!("{name}: no Rust binding table in this test"));
        let module = parse_and_validate(name, &source);
        for (number, kind, global) in declared_bindings(name, &module) {
            let binding = *layout
                .get(number as usize)
                .unwrap_or_else(|| panic!("{name}: binding {number} is not in the layout"));
            assert_eq!(kind, rust_kind(binding), "{name}: binding {number}");
            if let Binding::Dynamic(size) = binding {
                assert_record_size(name, &module, global, size);
            }
        }
    }
}

/// Each pass of `irradiance` declares exactly the bindings of its own layout
/// (`Pass::layout`), and reads every one of them.
#[test]
fn each_irradiance_pass_declares_and_reads_exactly_its_bindings() {
    let mut names: Vec<_> = shaders::all()
        .into_iter()
        .map(|(n, _)| n)
        .filter(|n| n.starts_with("irradiance/"))
        .collect();
    for pass in Pass::ALL {
        let name = pass.label();
        let (module, info) = validate(name, &shaders::irradiance(pass.source()));
        let declared = declared_bindings(name, &module);
        let expected: Vec<_> = pass.layout().map(|(n, b)| (n, rust_kind(b))).collect();
        assert_eq!(
            declared.iter().map(|d| (d.0, d.1)).collect::<Vec<_>>(),
            expected,
            "{name}: WGSL bindings vs Pass::layout"
        );
        let main = module
            .entry_points
            .iter()
            .position(|e| e.name == "main")
            .unwrap_or_else(|| panic!("{name}: no entry point main"));
        for &(number, _, global) in &declared {
            assert!(
                !info.get_entry_point(main)[global].is_empty(),
                "{name}: binding {number} ({:?}) is declared but never read",
                module.global_variables[global].name
            );
        }
        for (number, binding) in pass.layout() {
            if let Binding::Dynamic(size) = binding {
                let global = declared.iter().find(|d| d.0 == number).unwrap().2;
                assert_record_size(name, &module, global, size);
            }
        }
        let file = format!("irradiance/{}", name.trim_start_matches("irradiance "));
        names.retain(|n| *n != file);
    }
    assert!(
        names.is_empty(),
        "irradiance shaders without a Pass: {names:?}"
    );
}
