//! WGSL sources: one file per pass under `shaders/`, composed with the shared pieces it uses
//! (WGSL has no includes; module-scope declarations are order independent).

pub const COMMON: &str = include_str!("../../../shaders/common.wgsl");
pub const VOLUME: &str = include_str!("../../../shaders/volume.wgsl");
pub const SCENE: &str = include_str!("../../../shaders/scene.wgsl");
pub const LIGHTS: &str = include_str!("../../../shaders/lights.wgsl");
pub const MACROCELL: &str = include_str!("../../../shaders/macrocell.wgsl");
pub const TRACKING: &str = include_str!("../../../shaders/tracking.wgsl");
pub const PATH: &str = include_str!("../../../shaders/path.wgsl");
pub const MARCH: &str = include_str!("../../../shaders/march.wgsl");
pub const MANYLIGHT_COMMON: &str = include_str!("../../../shaders/manylight_common.wgsl");
pub const MANYLIGHT_VLS: &str = include_str!("../../../shaders/manylight_vls.wgsl");
pub const MANYLIGHT_AVSM: &str = include_str!("../../../shaders/manylight_avsm.wgsl");
pub const MANYLIGHT_GATHER: &str = include_str!("../../../shaders/manylight_gather.wgsl");
pub const RAYMARCH: &str = include_str!("../../../shaders/raymarch.wgsl");
pub const PATHTRACE: &str = include_str!("../../../shaders/pathtrace.wgsl");
pub const PHOTON_COMMON: &str = include_str!("../../../shaders/photon_common.wgsl");
pub const PHOTON_TRACE: &str = include_str!("../../../shaders/photon_trace.wgsl");
pub const PHOTON_GRID: &str = include_str!("../../../shaders/photon_grid.wgsl");
pub const PHOTON_GATHER: &str = include_str!("../../../shaders/photon_gather.wgsl");
pub const PHOTON_SCATTER: &str = include_str!("../../../shaders/photon_scatter.wgsl");
pub const IRRADIANCE_COMMON: &str = include_str!("../../../shaders/irradiance_common.wgsl");
pub const IRRADIANCE_RENDER: &str = include_str!("../../../shaders/irradiance_render.wgsl");
pub const IRRADIANCE_CREATE: &str = include_str!("../../../shaders/irradiance_create.wgsl");
pub const IRRADIANCE_REQUESTS: &str = include_str!("../../../shaders/irradiance_requests.wgsl");
pub const IRRADIANCE_UPDATE: &str = include_str!("../../../shaders/irradiance_update.wgsl");
pub const IRRADIANCE_PRIORITY: &str = include_str!("../../../shaders/irradiance_priority.wgsl");
pub const PREVIEW_COMMON: &str = include_str!("../../../shaders/preview_common.wgsl");
pub const PREVIEW_LIGHT: &str = include_str!("../../../shaders/preview_light.wgsl");
pub const PREVIEW_VIEW: &str = include_str!("../../../shaders/preview_view.wgsl");
pub const TONEMAP: &str = include_str!("../../../shaders/tonemap.wgsl");

/// The raymarch pass with its shared pieces.
pub fn raymarch() -> String {
    [COMMON, VOLUME, SCENE, MACROCELL, MARCH, LIGHTS, RAYMARCH].concat()
}

/// The path tracer with its shared pieces.
pub fn pathtrace() -> String {
    [
        COMMON, VOLUME, SCENE, MACROCELL, TRACKING, LIGHTS, PATH, PATHTRACE,
    ]
    .concat()
}

/// `manylight`, pass 1: virtual lights by random walks from the lights.
pub fn manylight_vls() -> String {
    [
        COMMON,
        VOLUME,
        SCENE,
        MACROCELL,
        TRACKING,
        MANYLIGHT_COMMON,
        MANYLIGHT_VLS,
    ]
    .concat()
}

/// `manylight`, pass 2: one adaptive volumetric shadow map per virtual light.
pub fn manylight_avsm() -> String {
    [
        COMMON,
        VOLUME,
        SCENE,
        MACROCELL,
        MANYLIGHT_COMMON,
        MANYLIGHT_AVSM,
    ]
    .concat()
}

/// `manylight`, pass 3: multiple scattering gathered from the virtual lights.
pub fn manylight_gather() -> String {
    [
        COMMON,
        VOLUME,
        SCENE,
        MACROCELL,
        MARCH,
        MANYLIGHT_COMMON,
        MANYLIGHT_GATHER,
    ]
    .concat()
}

/// Photon tracing (technique `photon`).
pub fn photon_trace() -> String {
    [COMMON, VOLUME, SCENE, PHOTON_COMMON, PHOTON_TRACE].concat()
}

/// The photon hash-grid build (technique `photon`).
pub fn photon_grid() -> String {
    [COMMON, VOLUME, SCENE, PHOTON_COMMON, PHOTON_GRID].concat()
}

/// Radiance gathering along view-ray segments and compositing (technique `photon`).
pub fn photon_gather() -> String {
    [COMMON, VOLUME, SCENE, PHOTON_COMMON, PHOTON_GATHER].concat()
}

/// The photon delta scatter: an update's changed photons added to the segments they reach
/// (technique `photon`).
pub fn photon_scatter() -> String {
    [COMMON, VOLUME, SCENE, PHOTON_COMMON, PHOTON_SCATTER].concat()
}

/// The passes of technique `irradiance`: each is the shared pieces, the technique's common
/// declarations and the pass (`IRRADIANCE_RENDER`, `_CREATE`, `_REQUESTS`, `_UPDATE`,
/// `_PRIORITY`).
pub fn irradiance(pass: &str) -> String {
    [
        COMMON,
        VOLUME,
        SCENE,
        MACROCELL,
        TRACKING,
        MARCH,
        LIGHTS,
        PATH,
        IRRADIANCE_COMMON,
        pass,
    ]
    .concat()
}

/// The interactive preview's passes (`PREVIEW_LIGHT`: the light volume; `PREVIEW_VIEW`: the
/// composited view rays), each with the shared pieces and the preview's bindings.
pub fn preview(pass: &str) -> String {
    [
        COMMON,
        VOLUME,
        SCENE,
        MACROCELL,
        MARCH,
        PREVIEW_COMMON,
        pass,
    ]
    .concat()
}

pub fn tonemap() -> String {
    TONEMAP.to_owned()
}

/// Every composed shader by pass name, for validation.
pub fn all() -> Vec<(&'static str, String)> {
    vec![
        ("raymarch", raymarch()),
        ("pathtrace", pathtrace()),
        ("photon_trace", photon_trace()),
        ("photon_grid", photon_grid()),
        ("photon_gather", photon_gather()),
        ("photon_scatter", photon_scatter()),
        ("tonemap", tonemap()),
        ("preview_light", preview(PREVIEW_LIGHT)),
        ("preview_view", preview(PREVIEW_VIEW)),
        ("manylight_vls", manylight_vls()),
        ("manylight_avsm", manylight_avsm()),
        ("manylight_gather", manylight_gather()),
        ("irradiance_render", irradiance(IRRADIANCE_RENDER)),
        ("irradiance_create", irradiance(IRRADIANCE_CREATE)),
        ("irradiance_requests", irradiance(IRRADIANCE_REQUESTS)),
        ("irradiance_update", irradiance(IRRADIANCE_UPDATE)),
        ("irradiance_priority", irradiance(IRRADIANCE_PRIORITY)),
    ]
}
