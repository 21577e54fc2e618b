//! GPU time of a run of compute passes from timestamp queries, where the adapter has them
//! (DESIGN.md "GPU conventions").

use std::time::Duration;

use crate::{EngineError, Gpu};

/// Two timestamps: the beginning of the first pass and the end of the last pass of a batch.
pub struct GpuTimer {
    query_set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
}

impl GpuTimer {
    /// None when the adapter has no timestamp queries.
    pub fn new(gpu: &Gpu, label: &str) -> Option<Self> {
        if !gpu.has_timestamps {
            return None;
        }
        let query_set = gpu.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some(label),
            ty: wgpu::QueryType::Timestamp,
            count: 2,
        });
        let resolved = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: 16,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Some(Self {
            query_set,
            resolved,
        })
    }

    /// Timestamp writes for a pass that is the first and/or the last of the batch.
    pub fn writes(&self, first: bool, last: bool) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        (first || last).then_some(wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: first.then_some(0),
            end_of_pass_write_index: last.then_some(1),
        })
    }

    /// Resolves both timestamps; encode after the last pass.
    pub fn resolve(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.resolve_query_set(&self.query_set, 0..2, &self.resolved, 0);
    }

    /// Time between the two timestamps. Blocks until the GPU is done.
    pub fn read(&self, gpu: &Gpu) -> Result<Duration, EngineError> {
        let bytes = gpu.read_buffer(&self.resolved)?;
        let ticks: &[u64] = bytemuck::try_cast_slice(&bytes)
            .map_err(|e| EngineError::Gpu(format!("timestamp readback: {e}")))?;
        let elapsed =
            ticks[1].saturating_sub(ticks[0]) as f64 * gpu.queue.get_timestamp_period() as f64;
        Ok(Duration::from_nanos(elapsed as u64))
    }
}
