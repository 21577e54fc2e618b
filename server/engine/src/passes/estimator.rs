//! The binding layout shared by the progressive per-pixel estimators (`raymarch.wgsl`,
//! `pathtrace.wgsl`): each dispatch adds one radiance sample per pixel to the HDR accumulation
//! buffer. Binds `SceneUniforms` and `GpuLight` (crate::scene_gpu), the volume texture, the TF
//! lookup table, the accumulation buffer and the macrocells' largest opacity (crate::macrocell).

use super::{compute_pipeline, dispatch_image, storage_entry, uniform_entry, volume_entry};
use crate::Gpu;

pub struct EstimatorPass {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
    pub label: &'static str,
}

/// The buffers and texture one dispatch reads and writes.
pub struct EstimatorBindings<'a> {
    pub scene: &'a wgpu::Buffer,
    pub volume: &'a wgpu::TextureView,
    pub tf_lut: &'a wgpu::Buffer,
    pub lights: &'a wgpu::Buffer,
    pub accum: &'a wgpu::Buffer,
    pub cell_max_opacity: &'a wgpu::Buffer,
}

impl EstimatorPass {
    /// A pipeline for `source` (entry point `main`) with the estimator bindings.
    pub fn new(gpu: &Gpu, label: &'static str, source: &str) -> Self {
        let (pipeline, layout) = compute_pipeline(
            gpu,
            label,
            source,
            &[
                uniform_entry(0),
                volume_entry(1),
                storage_entry(2, true),
                uniform_entry(3),
                storage_entry(4, false),
                storage_entry(5, true),
            ],
        );
        Self {
            pipeline,
            layout,
            label,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &EstimatorBindings) -> wgpu::BindGroup {
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.label),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: b.scene.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(b.volume),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: b.tf_lut.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: b.lights.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: b.accum.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: b.cell_max_opacity.as_entire_binding(),
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
