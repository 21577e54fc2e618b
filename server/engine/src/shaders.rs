//! WGSL sources: one file per pass under `shaders/`, composed with the shared pieces it
//! imports (WGSL has no includes; module-scope declarations are order independent).
//!
//! - A file states what it needs with `#import <name>` lines (the name of another file under
//!   `shaders/`, without `.wgsl`: `shared/common`, `photon/common`); `compose` puts every
//!   imported file once, before the first file that imports it, and drops the `#import` lines.
//! - An entry file is a pass; its composed source is what the pipeline compiles and what the
//!   naga tests validate (`tests/shaders.rs`).

pub const COMMON: &str = include_str!("../../../shaders/shared/common.wgsl");
pub const VOLUME: &str = include_str!("../../../shaders/shared/volume.wgsl");
pub const SCENE: &str = include_str!("../../../shaders/shared/scene.wgsl");
pub const LIGHTS: &str = include_str!("../../../shaders/shared/lights.wgsl");
pub const MEDIUM: &str = include_str!("../../../shaders/shared/medium.wgsl");
pub const MACROCELL: &str = include_str!("../../../shaders/shared/macrocell.wgsl");
pub const TRACKING: &str = include_str!("../../../shaders/shared/tracking.wgsl");
pub const PATH: &str = include_str!("../../../shaders/shared/path.wgsl");
pub const MARCH: &str = include_str!("../../../shaders/shared/march.wgsl");
pub const MANYLIGHT_COMMON: &str = include_str!("../../../shaders/manylight/common.wgsl");
pub const MANYLIGHT_VLS: &str = include_str!("../../../shaders/manylight/vls.wgsl");
pub const MANYLIGHT_AVSM: &str = include_str!("../../../shaders/manylight/avsm.wgsl");
pub const MANYLIGHT_GATHER: &str = include_str!("../../../shaders/manylight/gather.wgsl");
pub const RAYMARCH: &str = include_str!("../../../shaders/raymarch.wgsl");
pub const PATHTRACE: &str = include_str!("../../../shaders/pathtrace.wgsl");
pub const PHOTON_COMMON: &str = include_str!("../../../shaders/photon/common.wgsl");
pub const PHOTON_TRACE: &str = include_str!("../../../shaders/photon/trace.wgsl");
pub const PHOTON_GRID: &str = include_str!("../../../shaders/photon/grid.wgsl");
pub const PHOTON_GATHER: &str = include_str!("../../../shaders/photon/gather.wgsl");
pub const PHOTON_SCATTER: &str = include_str!("../../../shaders/photon/scatter.wgsl");
pub const IRRADIANCE_COMMON: &str = include_str!("../../../shaders/irradiance/common.wgsl");
pub const IRRADIANCE_CACHE: &str = include_str!("../../../shaders/irradiance/cache.wgsl");
pub const IRRADIANCE_PATHS: &str = include_str!("../../../shaders/irradiance/paths.wgsl");
pub const IRRADIANCE_RENDER: &str = include_str!("../../../shaders/irradiance/render.wgsl");
pub const IRRADIANCE_CREATE: &str = include_str!("../../../shaders/irradiance/create.wgsl");
pub const IRRADIANCE_REQUESTS: &str = include_str!("../../../shaders/irradiance/requests.wgsl");
pub const IRRADIANCE_UPDATE: &str = include_str!("../../../shaders/irradiance/update.wgsl");
pub const IRRADIANCE_PRIORITY: &str = include_str!("../../../shaders/irradiance/priority.wgsl");
pub const PREVIEW_COMMON: &str = include_str!("../../../shaders/preview/common.wgsl");
pub const PREVIEW_LIGHT: &str = include_str!("../../../shaders/preview/light.wgsl");
pub const PREVIEW_VIEW: &str = include_str!("../../../shaders/preview/view.wgsl");
pub const TONEMAP: &str = include_str!("../../../shaders/tonemap.wgsl");

/// Every WGSL file by its name under `shaders/`.
const FILES: &[(&str, &str)] = &[
    ("shared/common", COMMON),
    ("shared/volume", VOLUME),
    ("shared/scene", SCENE),
    ("shared/lights", LIGHTS),
    ("shared/medium", MEDIUM),
    ("shared/macrocell", MACROCELL),
    ("shared/tracking", TRACKING),
    ("shared/path", PATH),
    ("shared/march", MARCH),
    ("manylight/common", MANYLIGHT_COMMON),
    ("manylight/vls", MANYLIGHT_VLS),
    ("manylight/avsm", MANYLIGHT_AVSM),
    ("manylight/gather", MANYLIGHT_GATHER),
    ("raymarch", RAYMARCH),
    ("pathtrace", PATHTRACE),
    ("photon/common", PHOTON_COMMON),
    ("photon/trace", PHOTON_TRACE),
    ("photon/grid", PHOTON_GRID),
    ("photon/gather", PHOTON_GATHER),
    ("photon/scatter", PHOTON_SCATTER),
    ("irradiance/common", IRRADIANCE_COMMON),
    ("irradiance/cache", IRRADIANCE_CACHE),
    ("irradiance/paths", IRRADIANCE_PATHS),
    ("irradiance/render", IRRADIANCE_RENDER),
    ("irradiance/create", IRRADIANCE_CREATE),
    ("irradiance/requests", IRRADIANCE_REQUESTS),
    ("irradiance/update", IRRADIANCE_UPDATE),
    ("irradiance/priority", IRRADIANCE_PRIORITY),
    ("preview/common", PREVIEW_COMMON),
    ("preview/light", PREVIEW_LIGHT),
    ("preview/view", PREVIEW_VIEW),
    ("tonemap", TONEMAP),
];

/// The `#import` directive.
const IMPORT: &str = "#import ";

/// A file's imports, in order.
pub fn imports(source: &str) -> impl Iterator<Item = &str> {
    source
        .lines()
        .filter_map(|l| l.trim_start().strip_prefix(IMPORT))
        .map(str::trim)
}

/// `entry` with everything it imports, each file once, imports first.
///
/// Panics on an unknown name or an import circle: the sources are part of the binary, and
/// `tests/shaders.rs` composes every entry.
pub fn compose(entry: &str) -> String {
    fn visit(name: &str, path: &mut Vec<String>, done: &mut Vec<String>, out: &mut String) {
        if done.iter().any(|d| d == name) {
            return;
        }
        assert!(
            !path.iter().any(|p| p == name),
            "WGSL import circle: {} → {name}",
            path.join(" → ")
        );
        let source = FILES
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, s)| *s)
            .unwrap_or_else(|| {
                panic!(
                    "WGSL import of unknown file `{name}` ({})",
                    path.join(" → ")
                )
            });
        path.push(name.to_owned());
        for import in imports(source) {
            visit(import, path, done, out);
        }
        path.pop();
        for line in source.lines() {
            if !line.trim_start().starts_with(IMPORT) {
                out.push_str(line);
                out.push('\n');
            }
        }
        done.push(name.to_owned());
    }
    let mut out = String::new();
    visit(entry, &mut Vec::new(), &mut Vec::new(), &mut out);
    out
}

/// The raymarch pass.
pub fn raymarch() -> String {
    compose("raymarch")
}

/// The path tracer.
pub fn pathtrace() -> String {
    compose("pathtrace")
}

/// `manylight`, pass 1: virtual lights by random walks from the lights.
pub fn manylight_vls() -> String {
    compose("manylight/vls")
}

/// `manylight`, pass 2: one adaptive volumetric shadow map per virtual light.
pub fn manylight_avsm() -> String {
    compose("manylight/avsm")
}

/// `manylight`, pass 3: multiple scattering gathered from the virtual lights.
pub fn manylight_gather() -> String {
    compose("manylight/gather")
}

/// Photon tracing (technique `photon`).
pub fn photon_trace() -> String {
    compose("photon/trace")
}

/// The photon hash-grid build (technique `photon`).
pub fn photon_grid() -> String {
    compose("photon/grid")
}

/// Radiance gathering along view-ray segments and compositing (technique `photon`).
pub fn photon_gather() -> String {
    compose("photon/gather")
}

/// The photon delta scatter: an update's changed photons added to the segments they reach
/// (technique `photon`).
pub fn photon_scatter() -> String {
    compose("photon/scatter")
}

/// The passes of technique `irradiance`: `pass` is one of its entry sources
/// (`IRRADIANCE_RENDER`, `_CREATE`, `_REQUESTS`, `_UPDATE`, `_PRIORITY`), composed with what it
/// imports.
pub fn irradiance(pass: &str) -> String {
    compose(entry_name(pass))
}

/// The interactive preview's passes (`PREVIEW_LIGHT`: the light volume; `PREVIEW_VIEW`: the
/// composited view rays), composed with what they import.
pub fn preview(pass: &str) -> String {
    compose(entry_name(pass))
}

/// The name of a file given by its source (the `pub const`s above).
fn entry_name(source: &str) -> &'static str {
    FILES
        .iter()
        .find(|(_, s)| *s == source)
        .map(|(n, _)| *n)
        .unwrap_or_else(|| panic!("not a WGSL file of shaders/"))
}

pub fn tonemap() -> String {
    TONEMAP.to_owned()
}

/// Every composed shader by pass name, for validation.
pub fn all() -> Vec<(&'static str, String)> {
    vec![
        ("raymarch", raymarch()),
        ("pathtrace", pathtrace()),
        ("photon/trace", photon_trace()),
        ("photon/grid", photon_grid()),
        ("photon/gather", photon_gather()),
        ("photon/scatter", photon_scatter()),
        ("tonemap", tonemap()),
        ("preview/light", preview(PREVIEW_LIGHT)),
        ("preview/view", preview(PREVIEW_VIEW)),
        ("manylight/vls", manylight_vls()),
        ("manylight/avsm", manylight_avsm()),
        ("manylight/gather", manylight_gather()),
        ("irradiance/render", irradiance(IRRADIANCE_RENDER)),
        ("irradiance/create", irradiance(IRRADIANCE_CREATE)),
        ("irradiance/requests", irradiance(IRRADIANCE_REQUESTS)),
        ("irradiance/update", irradiance(IRRADIANCE_UPDATE)),
        ("irradiance/priority", irradiance(IRRADIANCE_PRIORITY)),
    ]
}
