//! The contract every rendering technique implements (DESIGN.md "The engine contract").

use std::time::Duration;
use voxlight_protocol::TechniqueDetails;

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

/// Counters shown to clients in `stats` messages: the technique, its progress and memory, and
/// its own counters in the protocol's form (`TechniqueDetails`, sent as they are).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TechniqueStats {
    pub name: &'static str,
    pub iteration: u32,
    /// GPU bytes this session's technique allocated (not counting the shared volume).
    pub memory_bytes: u64,
    pub details: TechniqueDetails,
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
    /// The HDR estimate: width × height `vec4<f32>` whose rgb / w is the mean radiance (rgb the
    /// sum of samples and w their count, or, as `photon` composites, one estimate and w = 1).
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
