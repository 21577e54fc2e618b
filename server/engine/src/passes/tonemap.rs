//! The tone-map pass (shaders/tonemap.wgsl): accumulated HDR mean × exposure → sRGB RGBA8.

use bytemuck::{Pod, Zeroable};

use super::builder::{Binding, Layout, buffer};
use super::dispatch_image;
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

/// What bindings 0–2 hold: the parameters, the HDR accumulation, the RGBA8 output.
pub const BINDINGS: [Binding; 3] = [Binding::Uniform, Binding::Read, Binding::ReadWrite];

pub struct TonemapPass {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: Layout,
}

impl TonemapPass {
    pub fn new(gpu: &Gpu) -> Self {
        let layout = Layout::new(gpu, "tonemap", &BINDINGS);
        let pipeline = layout.pipeline(gpu, "tonemap", &crate::shaders::tonemap());
        Self { pipeline, layout }
    }

    pub fn bind_group(
        &self,
        gpu: &Gpu,
        params: &wgpu::Buffer,
        accum: &wgpu::Buffer,
        rgba: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let entries = [buffer(0, params), buffer(1, accum), buffer(2, rgba)];
        self.layout.bind_group(gpu, "tonemap", &entries)
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
