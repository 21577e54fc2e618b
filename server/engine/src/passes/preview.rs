//! The interactive preview's two passes (shaders/preview_light.wgsl, shaders/preview_view.wgsl,
//! declarations in shaders/preview_common.wgsl): the light volume, then one composited view ray
//! per preview pixel. Both share one bind group layout: the estimator's scene, volume, TF,
//! lights and macrocells, plus `PreviewParams`, the light volume and the preview image (with
//! its approximate multiple scattering kept apart for the brightness match).

use bytemuck::{Pod, Zeroable};

use super::{TILE, layout_pipeline, storage_entry, uniform_entry, volume_entry};
use crate::Gpu;

/// Matches `PreviewParams` in preview/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PreviewParams {
    pub light_dims: [u32; 3],
    pub channels: u32,
    pub width: u32,
    pub height: u32,
    pub row_offset: u32,
    pub row_stride: u32,
    pub gain: [f32; 3],
    pub multiple: u32,
    pub multiple_weight: [f32; 3],
    pub z_offset: u32,
}

/// Workgroup of the light-volume pass (`@workgroup_size(8, 8, 1)`: one grid plane per layer).
const LIGHT_TILE: u32 = 8;

pub struct PreviewPasses {
    pub light: wgpu::ComputePipeline,
    pub view: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
}

/// The buffers and texture both passes bind.
pub struct PreviewBindings<'a> {
    pub scene: &'a wgpu::Buffer,
    pub volume: &'a wgpu::TextureView,
    pub tf_lut: &'a wgpu::Buffer,
    pub lights: &'a wgpu::Buffer,
    pub cell_max_opacity: &'a wgpu::Buffer,
    pub params: &'a wgpu::Buffer,
    pub light_volume: &'a wgpu::Buffer,
    pub image: &'a wgpu::Buffer,
    pub image_multiple: &'a wgpu::Buffer,
}

impl PreviewPasses {
    pub fn new(gpu: &Gpu) -> Self {
        let layout = gpu
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some("preview"),
                entries: &[
                    uniform_entry(0),
                    volume_entry(1),
                    storage_entry(2, true),
                    uniform_entry(3),
                    storage_entry(4, true),
                    uniform_entry(5),
                    storage_entry(6, false),
                    storage_entry(7, false),
                    storage_entry(8, false),
                ],
            });
        let pipeline_layout = gpu
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("preview"),
                bind_group_layouts: &[Some(&layout)],
                immediate_size: 0,
            });
        let shaders = crate::shaders::preview;
        Self {
            light: layout_pipeline(
                gpu,
                "preview light volume",
                &shaders(crate::shaders::PREVIEW_LIGHT),
                &pipeline_layout,
            ),
            view: layout_pipeline(
                gpu,
                "preview view",
                &shaders(crate::shaders::PREVIEW_VIEW),
                &pipeline_layout,
            ),
            layout,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &PreviewBindings) -> wgpu::BindGroup {
        fn buffer(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: buffer.as_entire_binding(),
            }
        }
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("preview"),
            layout: &self.layout,
            entries: &[
                buffer(0, b.scene),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(b.volume),
                },
                buffer(2, b.tf_lut),
                buffer(3, b.lights),
                buffer(4, b.cell_max_opacity),
                buffer(5, b.params),
                buffer(6, b.light_volume),
                buffer(7, b.image),
                buffer(8, b.image_multiple),
            ],
        })
    }

    /// `planes` grid planes of the light volume over `dims` grid points, from `params.z_offset`.
    pub fn encode_light(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        dims: [u32; 3],
        planes: u32,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("preview light volume"),
            timestamp_writes,
        });
        pass.set_pipeline(&self.light);
        pass.set_bind_group(0, bind_group, &[]);
        pass.dispatch_workgroups(
            dims[0].div_ceil(LIGHT_TILE),
            dims[1].div_ceil(LIGHT_TILE),
            planes,
        );
    }

    /// The view rays of `rows` rows (from `params.row_offset`, every `params.row_stride`-th)
    /// of a width-wide preview image.
    pub fn encode_view(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        (width, rows): (u32, u32),
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("preview view"),
            timestamp_writes,
        });
        pass.set_pipeline(&self.view);
        pass.set_bind_group(0, bind_group, &[]);
        pass.dispatch_workgroups(width.div_ceil(TILE), rows.div_ceil(TILE), 1);
    }
}
