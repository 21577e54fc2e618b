// Shared pieces of the interactive preview (preview/light.wgsl, preview/view.wgsl): the
// bindings both passes use and the light volume's layout. Rust twin: server/engine/src/passes/preview.rs.
//
// The light volume holds, on a coarse cell-centred grid over the box, the transmittance from
// each grid point to every directional/point light (channel l < light_count) and its mean over
// ENV_DIRECTIONS directions to the environment (channel light_count). It depends on the
// opacity, the density scale and the lights only, never on the camera or the colours.

#import shared/common
#import shared/volume
#import shared/scene
#import shared/macrocell
#import shared/march

struct PreviewParams {
    light_dims: vec3<u32>,
    // light_count + ENV_CHANNELS.
    channels: u32,
    // Preview image size (the viewport divided by the resolution divisor, rounded up).
    width: u32,
    height: u32,
    // A view dispatch is band row_offset of row_stride (shared/common.wgsl band_row) and a
    // light-volume dispatch covers grid planes z_offset, z_offset + 1, …: a long preview runs
    // in parts between which an edit can stop it (engine::preview).
    row_offset: u32,
    row_stride: u32,
    // Brightness match (engine::preview::BrightnessMatch): the single scattering's gain and
    // the approximate multiple scattering's weight, fitted so that the preview's mean meets the
    // technique's last still.
    gain: vec3<f32>,
    // Nonzero: compute the approximate multiple scattering (for a GI technique's preview).
    multiple: u32,
    multiple_weight: vec3<f32>,
    z_offset: u32,
}

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
// Uniform, not storage (shared/scene.wgsl, MAX_LIGHTS): from storage the chest CT's light volume took
// ~90 s on lavapipe, from a uniform ~3 s.
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(4) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(5) var<uniform> params: PreviewParams;
@group(0) @binding(6) var<storage, read_write> light_volume: array<f32>;
// rgb: radiance; w: the view ray's transmittance (the brightness match separates the
// background seen through the volume from the scattered light with it). The tone map divides
// by max(w, 1), so a w in [0, 1] leaves the picture as it is.
@group(0) @binding(7) var<storage, read_write> image: array<vec4<f32>>;
// The approximate multiple scattering before its weight, rgb as f16 (for the brightness
// match's fit; written only when params.multiple is set).
@group(0) @binding(8) var<storage, read_write> image_multiple: array<vec2<u32>>;

fn light_index(c: u32, i: vec3<u32>) -> u32 {
    let d = params.light_dims;
    return ((c * d.z + i.z) * d.y + i.y) * d.x + i.x;
}
