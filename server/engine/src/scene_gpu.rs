//! GPU twins of the shared scene structs in shaders/shared/scene.wgsl (identical field names).

use bytemuck::{Pod, Zeroable};
use voxlight_protocol::Light;

use crate::camera::CameraBasis;
use crate::scene::Scene;
use crate::volume::GpuVolume;

/// Matches `SceneUniforms` in shared/scene.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct SceneUniforms {
    pub eye: [f32; 3],
    pub tan_half_fov: f32,
    pub right: [f32; 3],
    pub aspect: f32,
    pub up: [f32; 3],
    pub step: f32,
    pub forward: [f32; 3],
    pub density_scale: f32,
    pub box_min: [f32; 3],
    pub g: f32,
    pub box_max: [f32; 3],
    pub light_count: u32,
    pub env_radiance: [f32; 3],
    pub seed: u32,
    pub width: u32,
    pub height: u32,
    pub iteration: u32,
    /// Band and band count of a banded dispatch (shared/common.wgsl `band_row`,
    /// techniques::progressive); 0 and 1 otherwise.
    pub row_offset: u32,
    pub cell_dims: [u32; 3],
    pub cell_voxels: u32,
    pub row_stride: u32,
    pub pad0: u32,
    pub pad1: u32,
    pub pad2: u32,
}

pub const LIGHT_DIRECTIONAL: u32 = 0;
pub const LIGHT_POINT: u32 = 1;

/// Matches `GpuLight` in shared/scene.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct GpuLight {
    pub vector: [f32; 3],
    pub kind: u32,
    pub color: [f32; 3],
    pub pad0: f32,
}

/// Directional and point lights for the GPU, and the summed environment radiance.
pub fn gpu_lights(lights: &[Light]) -> (Vec<GpuLight>, [f32; 3]) {
    let mut out = Vec::new();
    let mut env = [0.0f32; 3];
    for light in lights {
        match *light {
            Light::Directional {
                direction,
                irradiance,
            } => out.push(GpuLight {
                vector: crate::camera::normalize(direction).unwrap_or([0.0, 0.0, -1.0]),
                kind: LIGHT_DIRECTIONAL,
                color: irradiance,
                pad0: 0.0,
            }),
            Light::Point {
                position,
                intensity,
            } => out.push(GpuLight {
                vector: position,
                kind: LIGHT_POINT,
                color: intensity,
                pad0: 0.0,
            }),
            Light::Environment { radiance } => {
                for k in 0..3 {
                    env[k] += radiance[k];
                }
            }
        }
    }
    (out, env)
}

/// Most march steps along the box's diagonal (a 2048³ volume, the usual 3D-texture limit,
/// takes ~7100 at half a voxel).
const MAX_STEPS_PER_DIAGONAL: f32 = 8192.0;

/// Default march step: half the smallest voxel edge in world units.
pub fn default_step(volume: &GpuVolume) -> f32 {
    march_step(volume.extent, volume.dims)
}

/// Half the smallest voxel edge of a box of `extent` with `dims` voxels, but no less than
/// [`MAX_STEPS_PER_DIAGONAL`] steps along the diagonal: a very uneven spacing (a thin slab of a
/// few thick slices) would otherwise march the long axes at the thin axis's step, tens of
/// thousands of steps a ray.
pub fn march_step(extent: [f32; 3], dims: [u32; 3]) -> f32 {
    let voxel = (0..3)
        .map(|k| extent[k] / dims[k].max(1) as f32)
        .fold(f32::INFINITY, f32::min);
    let diagonal = extent.iter().map(|e| e * e).sum::<f32>().sqrt();
    (0.5 * voxel).max(diagonal / MAX_STEPS_PER_DIAGONAL)
}

impl SceneUniforms {
    /// The uniforms of `scene` on `volume` for progressive iteration `iteration`.
    pub fn new(scene: &Scene, volume: &GpuVolume, iteration: u32) -> Result<Self, String> {
        let basis = CameraBasis::new(&scene.camera)?;
        let (lights, env) = gpu_lights(&scene.lights);
        let half = volume.extent.map(|e| e * 0.5);
        Ok(Self {
            eye: basis.eye,
            tan_half_fov: basis.tan_half_fov,
            right: basis.right,
            aspect: scene.viewport.width as f32 / scene.viewport.height as f32,
            up: basis.up,
            step: default_step(volume),
            forward: basis.forward,
            density_scale: scene.params.density_scale,
            box_min: half.map(|h| -h),
            g: scene.params.g,
            box_max: half,
            light_count: lights.len() as u32,
            env_radiance: env,
            seed: scene.seed,
            width: scene.viewport.width,
            height: scene.viewport.height,
            iteration,
            row_offset: 0,
            cell_dims: volume.ranges.dims,
            cell_voxels: crate::macrocell::CELL,
            row_stride: 1,
            pad0: 0,
            pad1: 0,
            pad2: 0,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::march_step;

    #[test]
    fn march_step_is_half_a_voxel() {
        assert_eq!(march_step([1.0, 1.0, 1.0], [256, 256, 256]), 0.5 / 256.0);
        // Anisotropic CT: the thinnest voxel edge sets the step.
        let step = march_step([1.0, 1.0, 0.5], [512, 512, 100]);
        assert_eq!(step, 0.5 / 512.0);
    }

    #[test]
    fn a_thin_slab_is_not_marched_at_its_thin_axis_step() {
        // 3 slices 0.0001 thick under a 1×1 face: half a slice would be 1.7e-5, 83 000 steps
        // across the diagonal.
        let extent = [1.0, 1.0, 1e-4];
        let step = march_step(extent, [256, 256, 3]);
        let diagonal = (2.0f32 + 1e-8).sqrt();
        assert!(
            (diagonal / step - 8192.0).abs() < 1.0,
            "{}",
            diagonal / step
        );
        assert!(step > 0.5 * 1e-4 / 3.0);
    }
}
