//! The passes of technique `photon` (shaders/photon/*.wgsl): photon tracing
//! (`photon/trace.wgsl`: mark the paths an update retraces, trace), the hash-grid build
//! (`photon/grid.wgsl`: clear, count, scan, scatter; of the records or of an update's changes),
//! gathering + compositing (`photon/gather.wgsl`: mark, recomposite touched, gather in rounds,
//! composite) and the delta scatter of an update's changes (`photon/scatter.wgsl`: touch,
//! weights, changes, apply, fallback; with per-sample photon sums, sums). All share one binding
//! layout (`BINDINGS`, declared once in `photon/common.wgsl`) and the `#[repr(C)]` records
//! below.

use bytemuck::{Pod, Zeroable};

use crate::Gpu;
use crate::passes::builder::{Binding, Layout, buffer, dispatch, module, texture};

/// Matches `PhotonUniforms` in photon/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PhotonUniforms {
    pub grid_dims: [u32; 3],
    pub cell_count: u32,
    pub radius: f32,
    pub kernel_norm: f32,
    pub majorant: f32,
    pub gather_step: f32,
    pub photons_per_pass: u32,
    pub path_count: u32,
    pub record_count: u32,
    pub bounces: u32,
    pub path_offset: u32,
    pub dispatch_paths: u32,
    pub mode: u32,
    pub segments: u32,
    pub rejection_query_lo: u32,
    pub rejection_query_hi: u32,
    pub emitter_count: u32,
    pub spatial: u32,
    pub round_input: u32,
    pub round_budget: u32,
    pub round_stride: u32,
    pub opacity_query_lo: u32,
    pub opacity_query_hi: u32,
    pub grid_pass: u32,
    pub change_capacity: u32,
    pub record_capacity: u32,
    pub collision_query_lo: u32,
    pub collision_query_hi: u32,
    pub scatter_capacity: u32,
    pub scatter_samples: u32,
    pub census: u32,
    pub round_first: u32,
    pub roulette_survival: f32,
    pub roulette_from: u32,
    /// The record slots' layout (`RecordLayout`).
    pub path_slots: u32,
    pub inline_slots: u32,
    pub chunks_per_pass: u32,
    pub chunk_counts_at: u32,
    /// Per-sample photon sums (`sample_sums`): lattice samples kept per pixel (0: off), the
    /// generation a valid entry carries, whether the update's changes were added to them.
    pub sample_cache_samples: u32,
    pub cache_generation: u32,
    pub sums_applied: u32,
    /// Whether the update's marks stand for the dirty cells (`scatter_touch`).
    pub marks_stand: u32,
    /// Per pass (r_i², (r_0 / r_i)³), two passes per entry (`pass_kernels`).
    pub pass_kernels: [[f32; 4]; PASS_KERNEL_ENTRIES],
}

/// Entries of `PhotonUniforms::pass_kernels` (two passes each).
pub const PASS_KERNEL_ENTRIES: usize = 128;

/// Matches `PhotonRecord`: one stored photon interaction.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PhotonRecord {
    pub position: [f32; 3],
    pub cell: u32,
    pub power: [f32; 3],
    pub hist_lo: u32,
    pub direction: [f32; 3],
    pub hist_hi: u32,
}

/// Matches `RecordResume`: where a record's flight stood just before its collision point (t,
/// and the draws its random stream had taken), one per record slot.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct RecordResume {
    pub t: f32,
    pub draws: u32,
}

/// Matches `PhotonPath`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PhotonPath {
    pub count: u32,
    pub end_lo: u32,
    pub end_hi: u32,
    pub collisions_lo: u32,
    pub collisions_hi: u32,
    /// The first chunk of its slots past the inline ones (`CHUNK_NONE`: none).
    pub chunk: u32,
    pub pad1: u32,
    pub pad2: u32,
}

/// Matches `PhotonEmitter`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PhotonEmitter {
    pub vector: [f32; 3],
    pub kind: u32,
    pub power: [f32; 3],
    pub cdf: f32,
}

/// Matches `PhotonChange`: a changed record's old version (`CHANGE_SUBTRACT`), new version
/// (`CHANGE_ADD`), or both where only its power changed (`CHANGE_REPLACE`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PhotonChange {
    pub position: [f32; 3],
    pub cell: u32,
    pub power: [f32; 3],
    pub kind: u32,
    pub direction: [f32; 3],
    pub pass_index: u32,
    pub old_power: [f32; 3],
    pub pad1: u32,
}

/// Matches `Segment`: one view-ray segment (radiance in 64-bit fixed point, 40 fraction bits).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct Segment {
    pub color_lo: [u32; 3],
    pub transmittance: f32,
    pub color_hi: [u32; 3],
    pub hist_lo: u32,
    pub hist_hi: u32,
    /// 1 where the segment's march ended at its transmittance cut-off.
    pub cut_off: u32,
    /// In each pixel's first segment: the union of its segments' historygrams (`composite`).
    pub pixel_hist_lo: u32,
    pub pixel_hist_hi: u32,
}

/// Matches `GatherState`: where a segment's gather stands between rounds.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct GatherState {
    pub color_lo: [u32; 3],
    pub k: f32,
    pub color_hi: [u32; 3],
    pub transmit: f32,
    pub hist_lo: u32,
    pub hist_hi: u32,
    pub cell: u32,
    pub rank: u32,
}

pub const MODE_FULL: u32 = 0;
pub const MODE_UPDATE: u32 = 1;
pub const EMIT_DIRECTIONAL: u32 = 0;
pub const EMIT_POINT: u32 = 1;
pub const EMIT_ENVIRONMENT: u32 = 2;
/// `counters` words: retraced paths, changed records, recomputed segments, spatial 3×2,
/// listed segments (2), change-list entries, segments updated from the changes alone, delta
/// scatter slots taken, delta scatter overflows, whether the scatter's marks stand for the
/// dirty cells, listed paths only recoloured, opacity-stale segments whose march ended at its
/// cut-off, listed paths the walk left to the trace; the dirty-cell bits follow.
pub const COUNTER_WORDS: usize = 19;
pub const COUNTER_RETRACED: usize = 0;
pub const COUNTER_CHANGED: usize = 1;
pub const COUNTER_SEGMENTS: usize = 2;
pub const COUNTER_SPATIAL: usize = 3;
/// Segments in the two halves of the gather list (two words).
pub const COUNTER_LIST: usize = 9;
pub const COUNTER_CHANGES: usize = 11;
pub const COUNTER_DELTA: usize = 12;
pub const COUNTER_SCATTER: usize = 13;
pub const COUNTER_SCATTER_OVERFLOW: usize = 14;
pub const COUNTER_TOUCH: usize = 15;
pub const COUNTER_RECOLOURED: usize = 16;
pub const COUNTER_CUT: usize = 17;
pub const COUNTER_DEFERRED: usize = 18;
/// Words per kept sample sum (`SAMPLE_WORDS`: lo and hi words of three channels, generation,
/// weight).
pub const SAMPLE_WORDS: usize = 8;
/// Words per delta-scatter slot (photon/scatter.wgsl).
pub const SLOT_WORDS: usize = 8;
/// `grid_pass` uniform: which grid the grid kernels build.
pub const GRID_RECORDS: u32 = 0;
pub const GRID_CHANGES: u32 = 1;
/// `PhotonChange::kind`.
pub const CHANGE_ADD: u32 = 0;
pub const CHANGE_SUBTRACT: u32 = 1;
pub const CHANGE_REPLACE: u32 = 2;
/// `spatial` uniform: how segments learn of changed photons.
pub const SPATIAL_NONE: u32 = 0;
pub const SPATIAL_AXES: u32 = 1;
pub const SPATIAL_CELLS: u32 = 2;

/// Workgroup width of the 1D photon kernels.
pub const WORKGROUP: u32 = 64;

/// What bindings 0–20 hold (every pass of shaders/photon/ declares them all, in common.wgsl):
/// scene, volume, TF, `PhotonUniforms`, the emitters, then the technique's buffers, the paths'
/// query words (`path_queries`), the records' resumes.
pub const BINDINGS: [Binding; 21] = {
    use Binding::*;
    [
        Uniform, Volume, Lut, Uniform, Read, ReadWrite, ReadWrite, ReadWrite, ReadWrite, ReadWrite,
        ReadWrite, ReadWrite, ReadWrite, ReadWrite, ReadWrite, ReadWrite, ReadWrite, ReadWrite,
        ReadWrite, Words, ReadWrite,
    ]
};

/// Words per row of the `path_queries` texture (`PATH_QUERY_ROW` in photon/common.wgsl), and
/// per path (its end and collision historygrams, as in `PhotonPath`).
pub const PATH_QUERY_ROW: u32 = 4096;
pub const PATH_QUERY_WORDS: u32 = 4;

/// Slots per record chunk (`CHUNK_SLOTS` in photon/common.wgsl).
pub const CHUNK_SLOTS: u32 = 4;
/// The end of a path's chunk list (`CHUNK_NONE`).
pub const CHUNK_NONE: u32 = u32::MAX;

pub struct PhotonPass {
    pub layout: Layout,
    pub trace_mark: wgpu::ComputePipeline,
    pub trace_clear: wgpu::ComputePipeline,
    pub trace: wgpu::ComputePipeline,
    /// `trace` compiled for updates (TRACE_UPDATE).
    pub trace_update: wgpu::ComputePipeline,
    /// The update's walk (TRACE_UPDATE and TRACE_WALK), before `trace_update`.
    pub trace_walk: wgpu::ComputePipeline,
    pub trace_mark_changes: wgpu::ComputePipeline,
    pub grid_clear: wgpu::ComputePipeline,
    pub grid_count: wgpu::ComputePipeline,
    pub grid_scan_reduce: wgpu::ComputePipeline,
    pub grid_scan_blocks: wgpu::ComputePipeline,
    pub grid_scan_apply: wgpu::ComputePipeline,
    pub grid_scatter: wgpu::ComputePipeline,
    pub gather_mark: wgpu::ComputePipeline,
    pub gather_mark_touched: wgpu::ComputePipeline,
    pub gather_mark_stale: wgpu::ComputePipeline,
    pub remarch_from_sums: wgpu::ComputePipeline,
    pub recomposite_touched: wgpu::ComputePipeline,
    pub gather: wgpu::ComputePipeline,
    pub gather_sums: wgpu::ComputePipeline,
    pub composite: wgpu::ComputePipeline,
    /// `composite` of the pixels an update changed (COMPOSITE_CHANGED).
    pub composite_changed: wgpu::ComputePipeline,
    pub scatter_touch: wgpu::ComputePipeline,
    /// `scatter_touch` that also adds the changes to the per-sample sums (TOUCH_SUMS).
    pub scatter_touch_sums: wgpu::ComputePipeline,
    pub scatter_weights: wgpu::ComputePipeline,
    pub scatter_changes: wgpu::ComputePipeline,
    pub scatter_apply: wgpu::ComputePipeline,
    pub scatter_fallback: wgpu::ComputePipeline,
    pub scatter_sums: wgpu::ComputePipeline,
}

/// The buffers and texture of one session.
pub struct PhotonBindings<'a> {
    pub scene: &'a wgpu::Buffer,
    pub volume: &'a wgpu::TextureView,
    pub tf_lut: &'a wgpu::TextureView,
    pub uniforms: &'a wgpu::Buffer,
    pub emitters: &'a wgpu::Buffer,
    pub records: &'a wgpu::Buffer,
    pub paths: &'a wgpu::Buffer,
    pub grid_cells: &'a wgpu::Buffer,
    pub grid_sorted: &'a wgpu::Buffer,
    pub segments: &'a wgpu::Buffer,
    pub gather_list: &'a wgpu::Buffer,
    pub gather_state: &'a wgpu::Buffer,
    pub retrace_list: &'a wgpu::Buffer,
    pub changes: &'a wgpu::Buffer,
    pub scatter: &'a wgpu::Buffer,
    pub accum: &'a wgpu::Buffer,
    pub counters: &'a wgpu::Buffer,
    pub chunks: &'a wgpu::Buffer,
    pub sample_sums: &'a wgpu::Buffer,
    pub path_queries: &'a wgpu::TextureView,
    pub record_resumes: &'a wgpu::Buffer,
}

impl PhotonPass {
    pub fn new(gpu: &Gpu) -> Self {
        let layout = Layout::new(gpu, "photon", &BINDINGS);
        let trace = module(gpu, "photon trace", &crate::shaders::photon_trace());
        let grid = module(gpu, "photon grid", &crate::shaders::photon_grid());
        let gather = module(gpu, "photon gather", &crate::shaders::photon_gather());
        let scatter = module(gpu, "photon scatter", &crate::shaders::photon_scatter());
        let pipeline = |label: &str, module: &wgpu::ShaderModule, entry: &str| {
            layout.entry_pipeline(gpu, label, module, entry)
        };
        // One gather kernel, compiled per formulation (photon/gather.wgsl, SAMPLE_SUMS).
        let gather_pipeline = |label: &str, sums: bool| {
            let constants = [("SAMPLE_SUMS", f64::from(u8::from(sums)))];
            layout.specialized_pipeline(gpu, label, &gather, "gather", &constants)
        };
        Self {
            trace_mark: pipeline("photon trace mark", &trace, "trace_mark"),
            trace_clear: pipeline("photon trace clear", &trace, "trace_clear"),
            trace: pipeline("photon trace", &trace, "main"),
            trace_update: layout.specialized_pipeline(
                gpu,
                "photon trace update",
                &trace,
                "main",
                &[("TRACE_UPDATE", 1.0)],
            ),
            trace_walk: layout.specialized_pipeline(
                gpu,
                "photon trace walk",
                &trace,
                "main",
                &[("TRACE_UPDATE", 1.0), ("TRACE_WALK", 1.0)],
            ),
            trace_mark_changes: pipeline("photon trace mark changes", &trace, "trace_mark_changes"),
            grid_clear: pipeline("photon grid clear", &grid, "grid_clear"),
            grid_count: pipeline("photon grid count", &grid, "grid_count"),
            grid_scan_reduce: pipeline("photon grid scan reduce", &grid, "grid_scan_reduce"),
            grid_scan_blocks: pipeline("photon grid scan blocks", &grid, "grid_scan_blocks"),
            grid_scan_apply: pipeline("photon grid scan apply", &grid, "grid_scan_apply"),
            grid_scatter: pipeline("photon grid scatter", &grid, "grid_scatter"),
            gather_mark: pipeline("photon gather mark", &gather, "gather_mark"),
            gather_mark_touched: pipeline(
                "photon gather mark touched",
                &gather,
                "gather_mark_touched",
            ),
            gather_mark_stale: pipeline("photon gather mark stale", &gather, "gather_mark_stale"),
            remarch_from_sums: pipeline("photon remarch from sums", &gather, "remarch_from_sums"),
            recomposite_touched: pipeline(
                "photon recomposite touched",
                &gather,
                "recomposite_touched",
            ),
            gather: gather_pipeline("photon gather", false),
            gather_sums: gather_pipeline("photon gather sums", true),
            composite: pipeline("photon composite", &gather, "composite"),
            composite_changed: layout.specialized_pipeline(
                gpu,
                "photon composite changed",
                &gather,
                "composite",
                &[("COMPOSITE_CHANGED", 1.0)],
            ),
            scatter_touch: pipeline("photon scatter touch", &scatter, "scatter_touch"),
            scatter_touch_sums: layout.specialized_pipeline(
                gpu,
                "photon scatter touch sums",
                &scatter,
                "scatter_touch",
                &[("TOUCH_SUMS", 1.0)],
            ),
            scatter_weights: pipeline("photon scatter weights", &scatter, "scatter_weights"),
            scatter_changes: pipeline("photon scatter changes", &scatter, "scatter_changes"),
            scatter_apply: pipeline("photon scatter apply", &scatter, "scatter_apply"),
            scatter_fallback: pipeline("photon scatter fallback", &scatter, "scatter_fallback"),
            scatter_sums: pipeline("photon scatter sums", &scatter, "scatter_sums"),
            layout,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &PhotonBindings) -> wgpu::BindGroup {
        let entries = [
            buffer(0, b.scene),
            texture(1, b.volume),
            texture(2, b.tf_lut),
            buffer(3, b.uniforms),
            buffer(4, b.emitters),
            buffer(5, b.records),
            buffer(6, b.paths),
            buffer(7, b.grid_cells),
            buffer(8, b.grid_sorted),
            buffer(9, b.segments),
            buffer(10, b.accum),
            buffer(11, b.counters),
            buffer(12, b.gather_list),
            buffer(13, b.gather_state),
            buffer(14, b.retrace_list),
            buffer(15, b.changes),
            buffer(16, b.scatter),
            buffer(17, b.chunks),
            buffer(18, b.sample_sums),
            texture(19, b.path_queries),
            buffer(20, b.record_resumes),
        ];
        self.layout.bind_group(gpu, "photon", &entries)
    }
}

/// Workgroups for `n` invocations of a 64-wide kernel, as a 2D grid within the 65535 limit.
pub fn linear_groups(n: u32) -> (u32, u32) {
    let groups = n.div_ceil(WORKGROUP).max(1);
    let x = groups.min(65535);
    (x, groups.div_ceil(x))
}

/// One compute pass of `pipeline` over `n` invocations (1D kernels of shaders/photon/).
pub fn dispatch_linear(
    encoder: &mut wgpu::CommandEncoder,
    label: &str,
    pipeline: &wgpu::ComputePipeline,
    bind_group: &wgpu::BindGroup,
    n: u32,
) {
    let (x, y) = linear_groups(n);
    dispatch(encoder, label, pipeline, (bind_group, &[]), [x, y, 1], None);
}

/// `groups` workgroups of `pipeline` along x (the grid scan's steps, one per block of cells).
pub fn dispatch_groups(
    encoder: &mut wgpu::CommandEncoder,
    label: &str,
    pipeline: &wgpu::ComputePipeline,
    bind_group: &wgpu::BindGroup,
    groups: u32,
) {
    dispatch(
        encoder,
        label,
        pipeline,
        (bind_group, &[]),
        [groups, 1, 1],
        None,
    );
}
