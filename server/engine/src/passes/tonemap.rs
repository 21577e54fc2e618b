//! The tone-map pass (shaders/tonemap.wgsl): accumulated HDR mean × exposure → sRGB RGBA8.

use bytemuck::{Pod, Zeroable};

use super::{compute_pipeline, dispatch_image, storage_entry, uniform_entry};
use crate::Gpu;

/// Matches `ToneParams` in tonemap.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct ToneParams {
    pub width: u32,
    pub height: u32,
    pub exposure: f32,
    pub pad0: u32,
}

pub struct TonemapPass {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
}

impl TonemapPass {
    pub fn new(gpu: &Gpu) -> Self {
        let (pipeline, layout) = compute_pipeline(
            gpu,
            "tonemap",
            &crate::shaders::tonemap(),
            &[
                uniform_entry(0),
                storage_entry(1, true),
                storage_entry(2, false),
            ],
        );
        Self { pipeline, layout }
    }

    pub fn bind_group(
        &self,
        gpu: &Gpu,
        params: &wgpu::Buffer,
        accum: &wgpu::Buffer,
        rgba: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("tonemap"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: accum.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: rgba.as_entire_binding(),
                },
            ],
        })
    }

    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        width: u32,
        height: u32,
    ) {
        dispatch_image(
            encoder,
            "tonemap",
            &self.pipeline,
            bind_group,
            (width, height),
            None,
        );
    }
}
