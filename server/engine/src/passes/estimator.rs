//! The binding layout shared by the progressive per-pixel estimators (`raymarch.wgsl`,
//! `pathtrace.wgsl`): each dispatch adds one radiance sample per pixel to the HDR accumulation
//! buffer. Binds `SceneUniforms` and `GpuLight` (crate::scene_gpu), the volume texture, the TF
//! lookup table, the accumulation buffer and the macrocells' largest opacity (crate::macrocell).

use super::builder::{Binding, Layout, buffer, texture};
use super::dispatch_image;
use crate::Gpu;

/// What bindings 0–5 hold (the techniques that build on an estimator bind these first).
pub const BINDINGS: [Binding; 6] = {
    use Binding::*;
    [Uniform, Volume, Lut, Uniform, ReadWrite, Read]
};

pub struct EstimatorPass {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: Layout,
    pub label: &'static str,
}

/// The buffers and texture one dispatch reads and writes.
pub struct EstimatorBindings<'a> {
    pub scene: &'a wgpu::Buffer,
    pub volume: &'a wgpu::TextureView,
    pub tf_lut: &'a wgpu::TextureView,
    pub lights: &'a wgpu::Buffer,
    pub accum: &'a wgpu::Buffer,
    pub cell_max_opacity: &'a wgpu::Buffer,
}

impl<'a> EstimatorBindings<'a> {
    /// Bind group entries 0–5 (`BINDINGS`).
    pub fn entries(&self) -> [wgpu::BindGroupEntry<'a>; 6] {
        [
            buffer(0, self.scene),
            texture(1, self.volume),
            texture(2, self.tf_lut),
            buffer(3, self.lights),
            buffer(4, self.accum),
            buffer(5, self.cell_max_opacity),
        ]
    }
}

impl EstimatorPass {
    /// A pipeline for `source` (entry point `main`) with the estimator bindings.
    pub fn new(gpu: &Gpu, label: &'static str, source: &str) -> Self {
        let layout = Layout::new(gpu, label, &BINDINGS);
        Self {
            pipeline: layout.pipeline(gpu, label, source),
            layout,
            label,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &EstimatorBindings) -> wgpu::BindGroup {
        self.layout.bind_group(gpu, self.label, &b.entries())
    }

    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        width: u32,
        height: u32,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        dispatch_image(
            encoder,
            self.label,
            &self.pipeline,
            bind_group,
            (width, height),
            timestamp_writes,
        );
    }
}
