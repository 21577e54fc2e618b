//! WGSL sources: one file per pass under `shaders/`, composed with the shared pieces it uses
//! (WGSL has no includes; module-scope declarations are order independent).

pub const COMMON: &str = include_str!("../../../shaders/common.wgsl");
pub const VOLUME: &str = include_str!("../../../shaders/volume.wgsl");
pub const SCENE: &str = include_str!("../../../shaders/scene.wgsl");
pub const LIGHTS: &str = include_str!("../../../shaders/lights.wgsl");
pub const MACROCELL: &str = include_str!("../../../shaders/macrocell.wgsl");
pub const RAYMARCH: &str = include_str!("../../../shaders/raymarch.wgsl");
pub const PATHTRACE: &str = include_str!("../../../shaders/pathtrace.wgsl");
pub const TONEMAP: &str = include_str!("../../../shaders/tonemap.wgsl");

/// The raymarch pass with its shared pieces.
pub fn raymarch() -> String {
    [COMMON, VOLUME, SCENE, MACROCELL, LIGHTS, RAYMARCH].concat()
}

/// The path tracer with its shared pieces.
pub fn pathtrace() -> String {
    [COMMON, VOLUME, SCENE, MACROCELL, LIGHTS, PATHTRACE].concat()
}

pub fn tonemap() -> String {
    TONEMAP.to_owned()
}

/// Every composed shader by pass name, for validation.
pub fn all() -> Vec<(&'static str, String)> {
    vec![
        ("raymarch", raymarch()),
        ("pathtrace", pathtrace()),
        ("tonemap", tonemap()),
    ]
}
