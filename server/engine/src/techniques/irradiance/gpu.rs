//! The five passes of technique `irradiance` (shaders/irradiance/*.wgsl): rendering, cache-entry
//! creation rounds, the requests pass (claims → requests, finished requests → entries), the
//! cache update and the rendering priorities. All bind the estimator's bindings 0–5
//! (crate::passes::estimator) plus the technique's (6–16), through one bind group layout.

use bytemuck::{Pod, Zeroable};

use crate::Gpu;
use crate::passes::{layout_pipeline, storage_entry, uniform_entry, volume_entry};

/// Matches `IrradianceParams` in irradiance/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct IrradianceParams {
    pub root_min: [f32; 3],
    pub root_edge: f32,
    pub delta: f32,
    pub gamma: f32,
    pub epsilon: f32,
    pub min_radius: f32,
    pub max_radius: f32,
    pub update_threshold: f32,
    pub frame: u32,
    pub flags: u32,
    pub blocks_x: u32,
    pub blocks_y: u32,
    pub block_count: u32,
    pub node_count: u32,
    pub refs_offset: u32,
    pub node_claim_offset: u32,
    pub node_held_offset: u32,
    pub block_claim_offset: u32,
    pub block_held_offset: u32,
    pub entry_capacity: u32,
    pub max_pending: u32,
    pub pending: u32,
    pub min_samples: u32,
    pub max_samples: u32,
    pub bounces: u32,
    pub priority_offset: u32,
    pub voxel: f32,
    pub dark_floor: f32,
    pub delta_free_paths: f32,
    pub view_picks: u32,
}

/// Matches `CacheEntry` in irradiance/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct CacheEntry {
    pub position: [f32; 3],
    pub key: u32,
    /// The local frame's third axis (along the extinction gradient).
    pub normal: [f32; 3],
    /// Samples per estimation point the estimate took.
    pub samples: u32,
    pub irradiance: [f32; 3],
    pub opacity_lo: u32,
    /// Per half-axis (+t, −t, +b, −b, +n, −n): rgb virtual extinction, w for the luminance.
    pub sigma: [[f32; 4]; 6],
    pub opacity_hi: u32,
    pub colour_lo: u32,
    pub colour_hi: u32,
    /// The entry's Δ (world units).
    pub delta: f32,
}

impl CacheEntry {
    /// Bins the estimate depended on through extinction, and through albedo.
    pub fn historygrams(&self) -> (u64, u64) {
        (
            self.opacity_lo as u64 | (self.opacity_hi as u64) << 32,
            self.colour_lo as u64 | (self.colour_hi as u64) << 32,
        )
    }

    /// Whether a TF edit with these queries (all changed bins; bins whose opacity changed)
    /// can change the entry's irradiance.
    pub fn meets(&self, query: u64, opacity_query: u64) -> bool {
        let (opacity, colour) = self.historygrams();
        (opacity & opacity_query) | (colour & query) != 0
    }
}

/// Matches `Request` in irradiance/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct Request {
    pub position: [f32; 3],
    pub key: u32,
    pub normal: [f32; 3],
    pub lock: u32,
    pub sums: [[f32; 4]; 7],
    pub count: u32,
    pub state: u32,
    pub opacity_lo: u32,
    pub opacity_hi: u32,
    pub colour_lo: u32,
    pub colour_hi: u32,
    pub delta: f32,
    /// Indirect caches: the sum of the centre's direct irradiance luminance (Eq. 5's bound).
    pub direct_sum: f32,
    pub entry: CacheEntry,
}

/// Matches `DispatchInfo` in irradiance/common.wgsl; one per `DISPATCH_STRIDE` bytes, bound
/// with a dynamic offset.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct DispatchInfo {
    pub first: u32,
    pub count: u32,
    pub round: u32,
    pub pad0: u32,
}

/// Bytes between dispatch descriptors (the uniform dynamic-offset alignment).
pub const DISPATCH_STRIDE: u64 = 256;

pub const FLAG_CACHE: u32 = 1;
pub const FLAG_SCREEN_LOCKING: u32 = 2;
pub const FLAG_NO_CREATION: u32 = 4;
pub const FLAG_SAMPLED_HISTORYGRAMS: u32 = 8;
pub const FLAG_MARCHED_VIEW: u32 = 16;
pub const FLAG_VALIDATE_HITS: u32 = 32;
pub const FLAG_TRACED_DIRECT: u32 = 64;

pub const COUNTER_HITS: usize = 0;
pub const COUNTER_MISSES: usize = 1;
pub const COUNTER_PENDING: usize = 2;
pub const COUNTER_ENTRIES: usize = 3;
pub const COUNTER_CREATED: usize = 4;
pub const COUNTER_ISSUED: usize = 5;
pub const COUNTER_DROPPED: usize = 6;
pub const COUNTER_REDUCTIONS: usize = 7;
pub const COUNTER_LOST: usize = 8;
/// Words of `words` before the claims and locks.
pub const COUNTER_WORDS: usize = 16;

/// Pixels of a block (the rendering workgroup and the screen-space lock).
pub const BLOCK_WIDTH: u32 = 16;
pub const BLOCK_HEIGHT: u32 = 8;

/// Irradiance samples per estimation point and creation round (SAMPLES_PER_ROUND).
pub const SAMPLES_PER_ROUND: u32 = 9;

/// `blocks` priority of a block with a pixel of fewer than two samples (PRIORITY_UNSAMPLED).
pub const PRIORITY_UNSAMPLED: f32 = 1e30;

/// Threads per workgroup of the update pass (one per block).
pub const UPDATE_WORKGROUP: u32 = 64;

pub struct IrradiancePasses {
    pub layout: wgpu::BindGroupLayout,
    pub render: wgpu::ComputePipeline,
    pub create: wgpu::ComputePipeline,
    pub requests: wgpu::ComputePipeline,
    pub update: wgpu::ComputePipeline,
    pub priority: wgpu::ComputePipeline,
}

/// The buffers and texture the passes bind.
pub struct IrradianceBindings<'a> {
    pub estimator: crate::passes::estimator::EstimatorBindings<'a>,
    pub params: &'a wgpu::Buffer,
    pub dispatch: &'a wgpu::Buffer,
    pub entries: &'a wgpu::Buffer,
    pub radii: &'a wgpu::Buffer,
    pub octree: &'a wgpu::Buffer,
    pub words: &'a wgpu::Buffer,
    pub pixel_aux: &'a wgpu::Buffer,
    pub blocks: &'a wgpu::Buffer,
    pub requests: &'a wgpu::Buffer,
    pub cell_bins: &'a wgpu::Buffer,
    pub bounds: &'a wgpu::Buffer,
}

impl IrradiancePasses {
    pub fn new(gpu: &Gpu) -> Self {
        let device = &gpu.device;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("irradiance"),
            entries: &[
                uniform_entry(0),
                volume_entry(1),
                storage_entry(2, true),
                uniform_entry(3),
                storage_entry(4, false),
                storage_entry(5, true),
                uniform_entry(6),
                wgpu::BindGroupLayoutEntry {
                    binding: 7,
                    visibility: wgpu::ShaderStages::COMPUTE,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: true,
                        min_binding_size: wgpu::BufferSize::new(size_of::<DispatchInfo>() as u64),
                    },
                    count: None,
                },
                storage_entry(8, false),
                storage_entry(9, false),
                storage_entry(10, true),
                storage_entry(11, false),
                storage_entry(12, false),
                storage_entry(13, false),
                storage_entry(14, false),
                storage_entry(15, true),
                storage_entry(16, false),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("irradiance"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        use crate::shaders::{
            IRRADIANCE_CREATE, IRRADIANCE_PRIORITY, IRRADIANCE_RENDER, IRRADIANCE_REQUESTS,
            IRRADIANCE_UPDATE, irradiance,
        };
        let pipeline = |label: &str, pass: &str| {
            layout_pipeline(gpu, label, &irradiance(pass), &pipeline_layout)
        };
        Self {
            render: pipeline("irradiance render", IRRADIANCE_RENDER),
            create: pipeline("irradiance create", IRRADIANCE_CREATE),
            requests: pipeline("irradiance requests", IRRADIANCE_REQUESTS),
            update: pipeline("irradiance update", IRRADIANCE_UPDATE),
            priority: pipeline("irradiance priority", IRRADIANCE_PRIORITY),
            layout,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &IrradianceBindings) -> wgpu::BindGroup {
        let e = &b.estimator;
        fn buffer(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
            wgpu::BindGroupEntry {
                binding,
                resource: buffer.as_entire_binding(),
            }
        }
        gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("irradiance"),
            layout: &self.layout,
            entries: &[
                buffer(0, e.scene),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(e.volume),
                },
                buffer(2, e.tf_lut),
                buffer(3, e.lights),
                buffer(4, e.accum),
                buffer(5, e.cell_max_opacity),
                buffer(6, b.params),
                wgpu::BindGroupEntry {
                    binding: 7,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: b.dispatch,
                        offset: 0,
                        size: wgpu::BufferSize::new(size_of::<DispatchInfo>() as u64),
                    }),
                },
                buffer(8, b.entries),
                buffer(9, b.radii),
                buffer(10, b.octree),
                buffer(11, b.words),
                buffer(12, b.pixel_aux),
                buffer(13, b.blocks),
                buffer(14, b.requests),
                buffer(15, b.cell_bins),
                buffer(16, b.bounds),
            ],
        })
    }

    /// Encodes one pass of `pipeline` with dispatch descriptor `slot` over `workgroups`, with
    /// optional timestamps.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_timed(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        bind_group: &wgpu::BindGroup,
        slot: u32,
        workgroups: u32,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        if workgroups == 0 {
            return;
        }
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes,
        });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[(slot as u64 * DISPATCH_STRIDE) as u32]);
        pass.dispatch_workgroups(workgroups, 1, 1);
    }
}
