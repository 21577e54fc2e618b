//! The five passes of technique `irradiance` (shaders/irradiance/*.wgsl): rendering, cache-entry
//! creation rounds, the requests pass (claims → requests, finished requests → entries), the
//! cache update and the rendering priorities.
//!
//! - Bindings: the estimator's 0–5 (crate::passes::estimator) and the technique's 6–16, each
//!   under one number and kind in every pass (`binding`, `BINDINGS`; irradiance/common.wgsl
//!   says what each holds).
//! - Each pass declares only the bindings it reads (`Pass::bindings`, the same list as its
//!   WGSL's declarations; tests/shaders.rs compares them) and has a bind group layout and a
//!   bind group of exactly those.

use bytemuck::{Pod, Zeroable};

use crate::Gpu;
use crate::passes::builder::{self, Binding, Layout, buffer, record};
use crate::shaders::{
    IRRADIANCE_CREATE, IRRADIANCE_PRIORITY, IRRADIANCE_RENDER, IRRADIANCE_REQUESTS,
    IRRADIANCE_UPDATE,
};

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
    pub validation_threshold: f32,
    pub validation_samples: u32,
    pub pad0: u32,
    pub pad1: u32,
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
    /// Update dispatches: 1 for a validation round (only the check against fresh estimates).
    pub validate: u32,
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

/// The technique's bindings by number, the same in every pass that declares one.
pub mod binding {
    pub const SCENE: u32 = 0;
    pub const VOLUME: u32 = 1;
    pub const TF_LUT: u32 = 2;
    pub const LIGHTS: u32 = 3;
    pub const ACCUM: u32 = 4;
    /// The macrocells' largest opacity (`cell_max_opacity`).
    pub const MACROCELLS: u32 = 5;
    pub const PARAMS: u32 = 6;
    pub const DISPATCH: u32 = 7;
    pub const ENTRIES: u32 = 8;
    pub const RADII: u32 = 9;
    pub const OCTREE: u32 = 10;
    pub const WORDS: u32 = 11;
    pub const PIXEL_AUX: u32 = 12;
    pub const BLOCKS: u32 = 13;
    pub const REQUESTS: u32 = 14;
    pub const CELL_BINS: u32 = 15;
    pub const BOUNDS: u32 = 16;
}

/// What each binding holds, by number (`DispatchInfo` at a dynamic offset).
pub const BINDINGS: [Binding; 17] = {
    use Binding::*;
    let dispatch = Dynamic(size_of::<DispatchInfo>() as u64);
    [
        Uniform, Volume, Lut, Uniform, ReadWrite, Read, Uniform, dispatch, ReadWrite, ReadWrite,
        Read, ReadWrite, ReadWrite, ReadWrite, ReadWrite, Read, ReadWrite,
    ]
};

/// The five passes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    Render,
    Create,
    Requests,
    Update,
    Priority,
}

impl Pass {
    pub const ALL: [Pass; 5] = [
        Pass::Render,
        Pass::Create,
        Pass::Requests,
        Pass::Update,
        Pass::Priority,
    ];

    /// The label of its pipeline, layouts, bind group and compute passes.
    pub fn label(self) -> &'static str {
        match self {
            Pass::Render => "irradiance render",
            Pass::Create => "irradiance create",
            Pass::Requests => "irradiance requests",
            Pass::Update => "irradiance update",
            Pass::Priority => "irradiance priority",
        }
    }

    /// Its entry file (`crate::shaders::irradiance` composes it).
    pub fn source(self) -> &'static str {
        match self {
            Pass::Render => IRRADIANCE_RENDER,
            Pass::Create => IRRADIANCE_CREATE,
            Pass::Requests => IRRADIANCE_REQUESTS,
            Pass::Update => IRRADIANCE_UPDATE,
            Pass::Priority => IRRADIANCE_PRIORITY,
        }
    }

    /// The bindings its WGSL declares (those it reads), in order.
    pub fn bindings(self) -> &'static [u32] {
        use binding::*;
        match self {
            Pass::Render => &[
                SCENE, VOLUME, TF_LUT, LIGHTS, ACCUM, MACROCELLS, PARAMS, DISPATCH, ENTRIES, RADII,
                OCTREE, WORDS, PIXEL_AUX, BLOCKS, CELL_BINS, BOUNDS,
            ],
            Pass::Create => &[
                SCENE, VOLUME, TF_LUT, LIGHTS, MACROCELLS, PARAMS, REQUESTS, CELL_BINS,
            ],
            Pass::Requests => &[
                SCENE, VOLUME, TF_LUT, PARAMS, ENTRIES, RADII, WORDS, PIXEL_AUX, REQUESTS,
                CELL_BINS, BOUNDS,
            ],
            Pass::Update => &[
                SCENE, VOLUME, TF_LUT, LIGHTS, MACROCELLS, PARAMS, DISPATCH, ENTRIES, RADII,
                OCTREE, WORDS, CELL_BINS, BOUNDS,
            ],
            Pass::Priority => &[SCENE, ACCUM, PARAMS, DISPATCH, PIXEL_AUX, BLOCKS],
        }
    }

    /// Its bindings with what each holds.
    pub fn layout(self) -> impl Iterator<Item = (u32, Binding)> {
        self.bindings().iter().map(|&n| (n, BINDINGS[n as usize]))
    }
}

/// One pass's pipeline and the bind group layout of its bindings.
pub struct PassPipeline {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: Layout,
}

pub struct IrradiancePasses {
    /// By `Pass`.
    passes: [PassPipeline; 5],
}

/// The bind group of each pass, by `Pass`.
pub struct IrradianceBindGroups([wgpu::BindGroup; 5]);

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

impl<'a> IrradianceBindings<'a> {
    /// The bind group entry of binding `n`.
    fn entry(&self, n: u32) -> wgpu::BindGroupEntry<'a> {
        use binding::*;
        let resource = match n {
            SCENE..=MACROCELLS => return self.estimator.entries()[n as usize].clone(),
            DISPATCH => return record(n, self.dispatch, size_of::<DispatchInfo>() as u64),
            PARAMS => self.params,
            ENTRIES => self.entries,
            RADII => self.radii,
            OCTREE => self.octree,
            WORDS => self.words,
            PIXEL_AUX => self.pixel_aux,
            BLOCKS => self.blocks,
            REQUESTS => self.requests,
            CELL_BINS => self.cell_bins,
            BOUNDS => self.bounds,
            _ => panic!("technique irradiance has no binding {n}"),
        };
        buffer(n, resource)
    }
}

impl IrradiancePasses {
    pub fn new(gpu: &Gpu) -> Self {
        let passes = Pass::ALL.map(|pass| {
            let layout = Layout::numbered(gpu, pass.label(), pass.layout());
            let source = crate::shaders::irradiance(pass.source());
            PassPipeline {
                pipeline: layout.pipeline(gpu, pass.label(), &source),
                layout,
            }
        });
        Self { passes }
    }

    pub fn pass(&self, pass: Pass) -> &PassPipeline {
        &self.passes[pass as usize]
    }

    pub fn bind_groups(&self, gpu: &Gpu, b: &IrradianceBindings) -> IrradianceBindGroups {
        IrradianceBindGroups(Pass::ALL.map(|pass| {
            let entries: Vec<_> = pass.bindings().iter().map(|&n| b.entry(n)).collect();
            self.pass(pass)
                .layout
                .bind_group(gpu, pass.label(), &entries)
        }))
    }

    /// Encodes one compute pass of `pass` with dispatch descriptor `slot` (where it reads one)
    /// over `workgroups`, with optional timestamps.
    pub fn encode_timed(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pass: Pass,
        bind_groups: &IrradianceBindGroups,
        slot: u32,
        workgroups: u32,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        if workgroups == 0 {
            return;
        }
        let offset = [(slot as u64 * DISPATCH_STRIDE) as u32];
        let offsets: &[u32] = if pass.bindings().contains(&binding::DISPATCH) {
            &offset
        } else {
            &[]
        };
        builder::dispatch(
            encoder,
            pass.label(),
            &self.pass(pass).pipeline,
            (&bind_groups.0[pass as usize], offsets),
            [workgroups, 1, 1],
            timestamp_writes,
        );
    }
}
