//! A volume on the GPU: one 3D texture shared by every session that views the dataset.

use voxlight_volumes::Volume;

use crate::macrocell::RangeGrid;
use crate::{EngineError, Gpu};

pub struct GpuVolume {
    pub name: String,
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub dims: [u32; 3],
    /// World-space box size, longest side 1 (DESIGN.md).
    pub extent: [f32; 3],
    pub bytes: u64,
    /// Data range per macrocell (empty-space skipping, majorants, historygram bins).
    pub ranges: RangeGrid,
}

/// Slices uploaded per `write_texture` call, so staging memory stays small for big volumes.
const SLAB_SLICES: u32 = 32;

impl GpuVolume {
    /// Bytes a volume of these dimensions needs on this GPU.
    pub fn bytes_needed(gpu: &Gpu, dims: [u32; 3]) -> u64 {
        let texel = if gpu.volume_format == wgpu::TextureFormat::R16Unorm {
            2
        } else {
            4
        };
        dims.iter().map(|&d| d as u64).product::<u64>() * texel
    }

    pub fn upload(gpu: &Gpu, volume: &Volume) -> Result<Self, EngineError> {
        let dims = volume.dims;
        let max = gpu.limits.max_texture_dimension_3d;
        if dims.iter().any(|&d| d == 0 || d > max) {
            return Err(EngineError::InvalidScene(format!(
                "volume `{}` is {}×{}×{}; this GPU takes 3D textures up to {max} per axis",
                volume.name, dims[0], dims[1], dims[2]
            )));
        }
        let expected = dims.iter().map(|&d| d as usize).product::<usize>();
        if volume.data.len() != expected {
            return Err(EngineError::InvalidScene(format!(
                "volume `{}` has {} samples, dims say {expected}",
                volume.name,
                volume.data.len()
            )));
        }
        let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(&format!("volume {}", volume.name)),
            size: wgpu::Extent3d {
                width: dims[0],
                height: dims[1],
                depth_or_array_layers: dims[2],
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: gpu.volume_format,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let slice_len = (dims[0] * dims[1]) as usize;
        let mut z = 0;
        while z < dims[2] {
            let depth = SLAB_SLICES.min(dims[2] - z);
            let samples = &volume.data[z as usize * slice_len..(z + depth) as usize * slice_len];
            let (bytes, texel): (Vec<u8>, u32) =
                if gpu.volume_format == wgpu::TextureFormat::R16Unorm {
                    (bytemuck::cast_slice(samples).to_vec(), 2)
                } else {
                    let floats: Vec<f32> = samples.iter().map(|&q| q as f32 / 65535.0).collect();
                    (bytemuck::cast_slice(&floats).to_vec(), 4)
                };
            gpu.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d { x: 0, y: 0, z },
                    aspect: wgpu::TextureAspect::All,
                },
                &bytes,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(dims[0] * texel),
                    rows_per_image: Some(dims[1]),
                },
                wgpu::Extent3d {
                    width: dims[0],
                    height: dims[1],
                    depth_or_array_layers: depth,
                },
            );
            z += depth;
        }
        gpu.check()?;
        let view = texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some(&format!("volume {} view", volume.name)),
            ..Default::default()
        });
        Ok(Self {
            name: volume.name.clone(),
            texture,
            view,
            dims,
            extent: volume.world_extent(),
            bytes: Self::bytes_needed(gpu, dims),
            ranges: RangeGrid::build(volume),
        })
    }
}
