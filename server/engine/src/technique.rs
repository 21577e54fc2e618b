//! The contract every rendering technique implements (DESIGN.md "The engine contract").

use std::time::Duration;

use crate::{Change, Engine, EngineError, Scene};

/// Result of one `step`: how far the progressive picture got.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// Iterations rendered by this call.
    pub iterations_done: u32,
    /// Iterations accumulated in the current picture.
    pub iteration: u32,
    pub converged: bool,
    /// GPU time of this call's passes: from timestamp queries where the adapter has them,
    /// else the wall time from submission to completion.
    pub gpu_time: Duration,
}

/// Counters shown to clients in `stats` messages.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TechniqueStats {
    pub name: &'static str,
    pub iteration: u32,
    /// GPU bytes this session's technique allocated (not counting the shared volume).
    pub memory_bytes: u64,
    /// `photon`: photon paths traced since the session started (retraced ones included).
    pub photons_traced: u64,
    /// `photon`: photon paths in the current map.
    pub photons_in_map: u64,
    /// `photon`: share of the map's paths the last TF edit retraced (None before any edit).
    pub photons_retraced_pct: Option<f32>,
    /// `photon`: share of the view-ray segments the last TF edit gathered again.
    pub segments_recomputed_pct: Option<f32>,
    /// `manylight`: virtual lights held, their shadow maps' bytes, and how long the last
    /// tracing + map build took.
    pub virtual_lights: Option<u32>,
    pub shadow_map_bytes: Option<u64>,
    pub build_ms: Option<f32>,
    /// `manylight`: shares of the light paths traced again and of the shadow maps built
    /// again by the last TF edit (None before any).
    pub light_paths_retraced_pct: Option<f32>,
    pub shadow_maps_rebuilt_pct: Option<f32>,
    /// `irradiance`: cache entries, references in its octree, the recent cache hit rate (0–1),
    /// entries being created, whether the cache is in use (not with an anisotropic phase
    /// function), and the share of entries the last TF edit kept (None before any).
    pub cache_entries: Option<u32>,
    pub octree_references: Option<u64>,
    pub cache_hit_rate: Option<f32>,
    pub pending_entries: Option<u32>,
    pub cache_active: Option<bool>,
    pub cache_entries_kept_pct: Option<f32>,
}

pub trait Technique: Send {
    fn name(&self) -> &'static str;
    /// Reacts to an edit; `scene` already holds the new state.
    fn apply(&mut self, engine: &Engine, scene: &Scene, change: &Change)
    -> Result<(), EngineError>;
    /// Progressive work for about `budget` (at least one iteration unless converged; a zero
    /// budget means exactly one, for the first frame after an edit). A technique that splits a
    /// long iteration into parts (`raymarch`, `pathtrace`: bands of rows) may instead return
    /// after one part with `iterations_done` 0, so that an edit waits for a part only.
    fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError>;
    /// The longest one submission should take while the session may get edits (the render
    /// service sets it). `raymarch`, `pathtrace`, `manylight` (bands of rows) and `photon`
    /// (parts of its gather) split long work by themselves; `irradiance` sizes its frames to
    /// it where a whole image's worth of blocks would take longer (a frame of fewer blocks
    /// schedules its cache work differently, so it is not the default). Default: ignored.
    fn set_part_time(&mut self, _part: Option<Duration>) {}
    /// The HDR estimate: width × height `vec4<f32>`, rgb = sum of samples, w = sample count.
    fn output(&self) -> &wgpu::Buffer;
    fn iteration(&self) -> u32;
    /// Iterations after which the picture is converged (a technique may stop earlier than
    /// the scene asks, e.g. when its buffers hold only so many photon passes).
    fn target_iterations(&self, scene: &Scene) -> u32 {
        scene.target_iterations
    }
    fn stats(&self) -> TechniqueStats;
    /// Light scatters more than once in its picture (every technique but `raymarch`): the
    /// interactive preview then adds its approximate multiple scattering.
    fn multiple_scattering(&self) -> bool {
        true
    }
}
