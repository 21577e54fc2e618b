//! The builder of the compute passes' wgpu objects, so that a pass states only what is its
//! own: what each binding holds, its WGSL and entry points, and the resources it binds.
//!
//! - `Binding`: what one binding holds, as the pass's WGSL declares it; `entry` is its layout
//!   entry (compute stage). `tests/shaders.rs` compares each pass's table with its WGSL.
//! - `Layout`: a bind group layout and the pipeline layout of it alone (group 0), with the
//!   `pipeline`s and `bind_group`s made from it.
//! - `buffer`, `texture`, `record`: bind group entries; `encoder`: a command encoder;
//!   `dispatch`: one compute pass of one pipeline.
//! - Every object gets the label it is given.

use crate::Gpu;

/// What one binding holds, as the pass's WGSL declares it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Binding {
    /// `var<uniform>`.
    Uniform,
    /// `var<uniform>` read at a dynamic offset: one record of this many bytes per dispatch.
    Dynamic(u64),
    /// `var<storage, read>`.
    Read,
    /// `var<storage, read_write>`.
    ReadWrite,
    /// The volume: `texture_3d<f32>`, read with `textureLoad`.
    Volume,
    /// The TF lookup table: `texture_2d<f32>` (`gpu::TfTexture`, one row), read with
    /// `textureLoad`.
    Lut,
    /// `texture_storage_2d<r32uint, read_write>`: words that hot kernels read. llvmpipe (the CI's
    /// adapter) loads a storage buffer's word lane by lane, each behind a bounds check, and a
    /// storage texture's as one gather, several times faster.
    Words,
}

impl Binding {
    /// The layout entry of this binding under number `binding`.
    pub fn entry(self, binding: u32) -> wgpu::BindGroupLayoutEntry {
        use wgpu::BufferBindingType::{Storage, Uniform};
        let buffer = |ty, size: Option<u64>| wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: size.is_some(),
            min_binding_size: size.and_then(wgpu::BufferSize::new),
        };
        let ty = match self {
            Binding::Uniform => buffer(Uniform, None),
            Binding::Dynamic(size) => buffer(Uniform, Some(size)),
            Binding::Read => buffer(Storage { read_only: true }, None),
            Binding::ReadWrite => buffer(Storage { read_only: false }, None),
            Binding::Volume => wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D3,
                multisampled: false,
            },
            Binding::Lut => wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            Binding::Words => wgpu::BindingType::StorageTexture {
                access: wgpu::StorageTextureAccess::ReadWrite,
                format: wgpu::TextureFormat::R32Uint,
                view_dimension: wgpu::TextureViewDimension::D2,
            },
        };
        wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        }
    }
}

/// A bind group layout and the pipeline layout that holds it alone, as group 0.
pub struct Layout {
    pub bind_group: wgpu::BindGroupLayout,
    pipeline: wgpu::PipelineLayout,
}

impl Layout {
    /// Bindings 0, 1, … holding `bindings` in order.
    pub fn new(gpu: &Gpu, label: &str, bindings: &[Binding]) -> Self {
        let numbered = (0..).zip(bindings.iter().copied());
        Self::numbered(gpu, label, numbered)
    }

    /// The given bindings under the given numbers (gaps allowed).
    pub fn numbered(
        gpu: &Gpu,
        label: &str,
        bindings: impl IntoIterator<Item = (u32, Binding)>,
    ) -> Self {
        let entries: Vec<_> = bindings.into_iter().map(|(n, b)| b.entry(n)).collect();
        let device = &gpu.device;
        let bind_group = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some(label),
            entries: &entries,
        });
        let pipeline = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(label),
            bind_group_layouts: &[Some(&bind_group)],
            immediate_size: 0,
        });
        Self {
            bind_group,
            pipeline,
        }
    }

    /// A pipeline of the composed WGSL `source` with entry point `main`.
    pub fn pipeline(&self, gpu: &Gpu, label: &str, source: &str) -> wgpu::ComputePipeline {
        self.entry_pipeline(gpu, label, &module(gpu, label, source), "main")
    }

    /// A pipeline of `module`'s entry point `entry`.
    pub fn entry_pipeline(
        &self,
        gpu: &Gpu,
        label: &str,
        module: &wgpu::ShaderModule,
        entry: &str,
    ) -> wgpu::ComputePipeline {
        self.specialized_pipeline(gpu, label, module, entry, &[])
    }

    /// A pipeline of `module`'s entry point `entry` with its pipeline-overridable constants
    /// (WGSL `override`) set by name.
    pub fn specialized_pipeline(
        &self,
        gpu: &Gpu,
        label: &str,
        module: &wgpu::ShaderModule,
        entry: &str,
        constants: &[(&str, f64)],
    ) -> wgpu::ComputePipeline {
        gpu.device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: Some(&self.pipeline),
                module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants,
                    ..Default::default()
                },
                cache: None,
            })
    }

    /// A bind group of this layout.
    pub fn bind_group(
        &self,
        gpu: &Gpu,
        label: &str,
        entries: &[wgpu::BindGroupEntry],
    ) -> wgpu::BindGroup {
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &self.bind_group,
            entries,
        })
    }
}

/// A shader module of composed WGSL.
pub fn module(gpu: &Gpu, label: &str, source: &str) -> wgpu::ShaderModule {
    gpu.device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        })
}

/// A whole buffer under `binding`.
pub fn buffer(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

/// A texture view under `binding`.
pub fn texture(binding: u32, view: &wgpu::TextureView) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::TextureView(view),
    }
}

/// The first `size` bytes of `buffer` under `binding`: a `Binding::Dynamic` of records, one
/// chosen per dispatch by its offset.
pub fn record(binding: u32, buffer: &wgpu::Buffer, size: u64) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer,
            offset: 0,
            size: wgpu::BufferSize::new(size),
        }),
    }
}

/// A command encoder.
pub fn encoder(gpu: &Gpu, label: &str) -> wgpu::CommandEncoder {
    gpu.device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
}

/// One compute pass: `pipeline` with `bind_group` (at these dynamic `offsets`) over
/// `workgroups`, with optional timestamps.
pub fn dispatch(
    encoder: &mut wgpu::CommandEncoder,
    label: &str,
    pipeline: &wgpu::ComputePipeline,
    (bind_group, offsets): (&wgpu::BindGroup, &[u32]),
    [x, y, z]: [u32; 3],
    timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
) {
    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(label),
        timestamp_writes,
    });
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind_group, offsets);
    pass.dispatch_workgroups(x, y, z);
}
