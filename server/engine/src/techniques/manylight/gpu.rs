//! The three passes of technique `manylight` (shaders/manylight/*.wgsl): virtual lights,
//! their adaptive volumetric shadow maps, and gathering. One bind group layout (`BINDINGS`)
//! serves all three: the estimator's bindings 0–5 (crate::passes::estimator) and the
//! technique's (6–13); each pass's WGSL declares the ones it reads.

use bytemuck::{Pod, Zeroable};

use crate::Gpu;
use crate::passes::builder::{Binding, Layout};

/// Matches `ManylightParams` in manylight/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct ManylightParams {
    pub capacity: u32,
    pub count: u32,
    pub first_path: u32,
    pub max_bounces: u32,
    pub face_res: u32,
    pub nodes: u32,
    pub mode: u32,
    pub seed: u32,
    pub vsl_radius: f32,
    pub built_density: f32,
    pub power_scale: f32,
    pub list_count: u32,
    pub fixed_majorant: u32,
    pub pad0: u32,
    pub pad1: u32,
    pub pad2: u32,
}

/// Matches `VirtualLight` in manylight/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct VirtualLight {
    pub position: [f32; 3],
    /// Optical depth of its path from the light, per unit density scale.
    pub tau: f32,
    pub power: [f32; 3],
    /// Scattering events on its path, this one included.
    pub vertices: f32,
    pub direction: [f32; 3],
    /// The light path it belongs to (`u32::MAX`: an empty slot).
    pub path: u32,
    /// The path's historygrams: bins of the macrocells it crossed, and at its vertices.
    pub opacity_lo: u32,
    pub opacity_hi: u32,
    pub colour_lo: u32,
    pub colour_hi: u32,
    /// The data value at this vertex (for re-weighting after a TF edit).
    pub value: f32,
    pub pad0: u32,
    pub pad1: u32,
    pub pad2: u32,
}

impl VirtualLight {
    /// Whether a TF edit with these (widened) queries can change the light's path.
    pub fn path_meets(&self, query: u64, opacity_query: u64) -> bool {
        let opacity = self.opacity_lo as u64 | (self.opacity_hi as u64) << 32;
        let colour = self.colour_lo as u64 | (self.colour_hi as u64) << 32;
        (opacity & opacity_query) | (colour & query) != 0
    }

    /// True when the slot holds a light (a path's unused slots and holes have no power).
    pub fn is_live(&self) -> bool {
        self.power.iter().any(|&p| p > 0.0)
    }
}

/// Matches `GatherChunk` in manylight/gather.wgsl: the virtual lights one gather dispatch
/// covers, bound with a dynamic offset (one `CHUNK_STRIDE` slot per chunk).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct GatherChunk {
    pub first: u32,
    pub count: u32,
    pub pad0: u32,
    pub pad1: u32,
}

/// Bytes between chunk descriptors (the uniform dynamic-offset alignment).
pub const CHUNK_STRIDE: u64 = 256;

/// Virtual lights per gather dispatch: llvmpipe ends a shader invocation's loops after 65535
/// iterations in all, and each light costs a shadow-map lookup (≤ 4 × nodes iterations) or a
/// ray march (up to ~2 iterations per voxel edge).
pub fn gather_chunk(mode: TransmittanceMode) -> u32 {
    match mode {
        TransmittanceMode::RayMarched => 64,
        TransmittanceMode::AvsmPoint | TransmittanceMode::AvsmTrilinear => 512,
    }
}

/// Transmittance from the virtual lights (ManylightParams::mode).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TransmittanceMode {
    AvsmPoint = 0,
    AvsmTrilinear = 1,
    RayMarched = 2,
}

/// Most nodes per AVSM texel (MAX_NODES in the WGSL).
pub const MAX_NODES: u32 = 12;

/// Bytes of the shadow maps of `vls` virtual lights.
pub fn avsm_bytes(vls: u32, face_res: u32, nodes: u32) -> u64 {
    vls as u64 * 6 * face_res as u64 * face_res as u64 * nodes as u64 * 4
}

/// What bindings 0–13 hold: the estimator's (0–5), then the parameters, virtual lights and
/// shadow maps (6–8), the gather's chunk (9), the tracing batch's scratch lights (10), the
/// macrocells' data bins (11), the work list (12) and the maps' historygrams (13).
pub const BINDINGS: [Binding; 14] = {
    use Binding::*;
    let chunk = Dynamic(size_of::<GatherChunk>() as u64);
    [
        Uniform, Volume, Lut, Uniform, ReadWrite, Read, Uniform, ReadWrite, ReadWrite, chunk,
        ReadWrite, Read, Read, ReadWrite,
    ]
};

pub struct ManylightPasses {
    pub layout: Layout,
    pub vls: wgpu::ComputePipeline,
    pub avsm: wgpu::ComputePipeline,
    pub gather: wgpu::ComputePipeline,
}

impl ManylightPasses {
    pub fn new(gpu: &Gpu) -> Self {
        let layout = Layout::new(gpu, "manylight", &BINDINGS);
        let pipeline = |label: &str, source: String| layout.pipeline(gpu, label, &source);
        Self {
            vls: pipeline("manylight vls", crate::shaders::manylight_vls()),
            avsm: pipeline("manylight avsm", crate::shaders::manylight_avsm()),
            gather: pipeline("manylight gather", crate::shaders::manylight_gather()),
            layout,
        }
    }
}
