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
}

pub trait Technique: Send {
    fn name(&self) -> &'static str;
    /// Reacts to an edit; `scene` already holds the new state.
    fn apply(&mut self, engine: &Engine, scene: &Scene, change: &Change)
    -> Result<(), EngineError>;
    /// Progressive work for about `budget` (at least one iteration unless converged; a zero
    /// budget means exactly one, for the first frame after an edit).
    fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError>;
    /// The HDR estimate: width × height `vec4<f32>`, rgb = sum of samples, w = sample count.
    fn output(&self) -> &wgpu::Buffer;
    fn iteration(&self) -> u32;
    fn stats(&self) -> TechniqueStats;
}
