//! The wgpu device shared by every session: adapter choice, features, loss and error tracking.

use std::sync::Arc;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use crate::EngineError;
use crate::tf::TF_LUT_SIZE;

/// One GPU (or lavapipe) with its queue. Cheap to share behind an `Arc`.
pub struct Gpu {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// Format of volume textures: `R16Unorm` when the adapter has it (exact 16-bit values at
    /// half the memory), else `R32Float`. Shaders read both with `textureLoad`.
    pub volume_format: wgpu::TextureFormat,
    pub has_timestamps: bool,
    lost: Arc<AtomicBool>,
    last_error: Arc<Mutex<Option<String>>>,
}

/// What to do when no adapter exists: the message names the package to install.
pub const NO_ADAPTER_HELP: &str = "no GPU adapter found. On a machine without a GPU install Mesa's \
software Vulkan driver (Debian/Ubuntu package `mesa-vulkan-drivers`, which provides lavapipe); \
on a GPU machine install the vendor's Vulkan driver (e.g. the NVIDIA driver with its Vulkan ICD)";

impl Gpu {
    /// Picks a discrete GPU when present, else the best other adapter (lavapipe on CPU-only
    /// machines), and opens a device on it.
    pub fn new() -> Result<Self, EngineError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        let adapter = adapters
            .into_iter()
            .filter(|a| {
                a.get_downlevel_capabilities()
                    .flags
                    .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
            })
            .max_by_key(|a| adapter_rank(&a.get_info()))
            .ok_or_else(|| EngineError::NoAdapter(NO_ADAPTER_HELP.to_owned()))?;
        let info = adapter.get_info();
        let available = adapter.features();
        let mut features = wgpu::Features::empty();
        for wanted in [
            wgpu::Features::TEXTURE_FORMAT_16BIT_NORM,
            wgpu::Features::TIMESTAMP_QUERY,
        ] {
            if available.contains(wanted) {
                features |= wanted;
            }
        }
        let adapter_limits = adapter.limits();
        let limits = wgpu::Limits {
            max_texture_dimension_3d: adapter_limits.max_texture_dimension_3d,
            max_storage_buffer_binding_size: adapter_limits.max_storage_buffer_binding_size,
            max_buffer_size: adapter_limits.max_buffer_size,
            max_storage_buffers_per_shader_stage: adapter_limits
                .max_storage_buffers_per_shader_stage
                .min(16),
            ..wgpu::Limits::default()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("voxlight device"),
            required_features: features,
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| EngineError::Gpu(format!("cannot open device on {}: {e}", info.name)))?;

        let lost = Arc::new(AtomicBool::new(false));
        let lost_flag = lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            tracing::error!(?reason, %message, "GPU device lost");
            lost_flag.store(true, Ordering::SeqCst);
        });
        let last_error = Arc::new(Mutex::new(None));
        let error_slot = last_error.clone();
        device.on_uncaptured_error(Arc::new(move |error: wgpu::Error| {
            tracing::error!(%error, "uncaptured GPU error");
            if let Ok(mut slot) = error_slot.lock() {
                *slot = Some(error.to_string());
            }
        }));

        let volume_format = if features.contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM) {
            wgpu::TextureFormat::R16Unorm
        } else {
            wgpu::TextureFormat::R32Float
        };
        tracing::info!(
            adapter = %info.name,
            backend = ?info.backend,
            device_type = ?info.device_type,
            driver = %info.driver,
            driver_info = %info.driver_info,
            ?volume_format,
            "GPU adapter selected"
        );
        Ok(Self {
            device,
            queue,
            has_timestamps: features.contains(wgpu::Features::TIMESTAMP_QUERY),
            info,
            limits,
            volume_format,
            lost,
            last_error,
        })
    }

    /// A one-line description of the adapter, e.g. for `/healthz` and `welcome`.
    pub fn adapter_name(&self) -> String {
        format!(
            "{} ({:?}, {})",
            self.info.name, self.info.backend, self.info.driver_info
        )
    }

    /// True when the adapter is a CPU rasterizer such as lavapipe/llvmpipe.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
            || self.info.name.to_ascii_lowercase().contains("llvmpipe")
    }

    /// Fails once the device is lost or a GPU error went uncaptured.
    pub fn check(&self) -> Result<(), EngineError> {
        if self.lost.load(Ordering::SeqCst) {
            return Err(EngineError::DeviceLost);
        }
        if let Some(error) = self.last_error.lock().ok().and_then(|mut slot| slot.take()) {
            return Err(EngineError::Gpu(error));
        }
        Ok(())
    }

    /// Blocks until the queue is idle. Only for render threads and tests, never async tasks.
    pub fn wait_idle(&self) -> Result<(), EngineError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: Some(Duration::from_secs(120)),
            })
            .map_err(|e| EngineError::Gpu(format!("waiting for the GPU failed: {e}")))?;
        self.check()
    }

    /// The most loop iterations one shader invocation may run in all, where the driver has
    /// such a limit: llvmpipe (lavapipe) silently ends every loop of an invocation once 65535
    /// iterations have run, so results go missing without an error. Passes whose work grows
    /// with the data split it into dispatches that stay below this.
    pub fn loop_limit(&self) -> Option<u32> {
        self.is_software().then_some(LLVMPIPE_LOOP_LIMIT)
    }

    /// One SIMD lane's safe share of `loop_limit`, less a tenth for the rest of the
    /// invocation: llvmpipe counts the limit per batch of lanes run in lockstep, and with
    /// nested loops a batch can run up to the sum of its lanes' counts.
    pub fn lane_loop_budget(&self) -> Option<u32> {
        let lanes = self.info.subgroup_max_size.clamp(1, 64);
        self.loop_limit().map(|limit| (limit - limit / 10) / lanes)
    }

    /// A per-session TF lookup table the queue can write (`TfTexture::write`).
    pub fn tf_texture(&self, label: &str) -> TfTexture {
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d {
                width: TF_LUT_SIZE as u32,
                height: 1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba32Float,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some(label),
            ..Default::default()
        });
        TfTexture { texture, view }
    }

    /// A per-session buffer the queue can write (COPY_DST added), at least 16 bytes.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(16),
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Reads a whole buffer back (it must have `COPY_SRC` usage). Blocks.
    pub fn read_buffer(&self, buffer: &wgpu::Buffer) -> Result<Vec<u8>, EngineError> {
        self.read_buffer_range(buffer, 0, buffer.size())
    }

    /// Reads `size` bytes from `offset` back (both multiples of 4). Blocks.
    pub fn read_buffer_range(
        &self,
        buffer: &wgpu::Buffer,
        offset: u64,
        size: u64,
    ) -> Result<Vec<u8>, EngineError> {
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback staging"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("readback"),
            });
        encoder.copy_buffer_to_buffer(buffer, offset, &staging, 0, size);
        self.queue.submit([encoder.finish()]);
        let (sender, receiver) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |result| {
            let _ = sender.send(result);
        });
        self.wait_idle()?;
        receiver
            .recv_timeout(Duration::from_secs(5))
            .map_err(|_| EngineError::Gpu("readback never completed".into()))?
            .map_err(|e| EngineError::Gpu(format!("readback failed: {e}")))?;
        let bytes = staging
            .get_mapped_range(..)
            .map_err(|e| EngineError::Gpu(format!("readback mapping failed: {e}")))?
            .to_vec();
        staging.unmap();
        Ok(bytes)
    }
}

/// llvmpipe's LP_MAX_TGSI_LOOP_ITERATIONS.
const LLVMPIPE_LOOP_LIMIT: u32 = 65535;

/// Higher is better: discrete > integrated > virtual > CPU; Vulkan preferred among equals.
fn adapter_rank(info: &wgpu::AdapterInfo) -> (u8, u8) {
    let kind = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 4,
        wgpu::DeviceType::IntegratedGpu => 3,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 1,
        wgpu::DeviceType::Other => 0,
    };
    let backend = u8::from(info.backend == wgpu::Backend::Vulkan);
    (kind, backend)
}

/// The TF lookup table on the GPU: `TF_LUT_SIZE` rgba32float texels in one row (`tf_lut:
/// texture_2d<f32>` in shaders/shared/volume.wgsl, read with `textureLoad`). A texture, not a
/// storage buffer: llvmpipe loads a buffer's `vec4` lane by lane, each behind a bounds check,
/// and a texel of every lane in one gather (stop 44, docs/benchmarks.md).
pub struct TfTexture {
    texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl TfTexture {
    pub const BYTES: u64 = (TF_LUT_SIZE * 16) as u64;

    /// Uploads a baked table (`tf::bake`, `TF_LUT_SIZE` entries).
    pub fn write(&self, queue: &wgpu::Queue, lut: &[[f32; 4]]) {
        debug_assert_eq!(lut.len(), TF_LUT_SIZE);
        queue.write_texture(
            self.texture.as_image_copy(),
            bytemuck::cast_slice(lut),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some((lut.len() * 16) as u32),
                rows_per_image: None,
            },
            wgpu::Extent3d {
                width: lut.len() as u32,
                height: 1,
                depth_or_array_layers: 1,
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(device_type: wgpu::DeviceType, backend: wgpu::Backend) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo::new(device_type, backend)
    }

    #[test]
    fn discrete_beats_cpu() {
        let gpu = info(wgpu::DeviceType::DiscreteGpu, wgpu::Backend::Gl);
        let cpu = info(wgpu::DeviceType::Cpu, wgpu::Backend::Vulkan);
        assert!(adapter_rank(&gpu) > adapter_rank(&cpu));
    }
}
