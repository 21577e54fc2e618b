//! The interactive preview every technique shows while edits stream in (docs/architecture.md
//! "Interaction mode"): single scattering composited front to back along one ray per pixel of a
//! reduced-resolution image, lit from a light volume (passes::preview). One per session.
//!
//! - The light volume is rebuilt only when what it depends on changed: the TF's opacities, the
//!   density scale, the lights or the volume. Camera moves and colour-only TF edits reuse it.
//! - The image is the viewport divided by a resolution divisor (1, 2, 4, 8 per axis), rounded
//!   up; the client scales it to its canvas.

use std::sync::Arc;
use std::time::{Duration, Instant};

use voxlight_protocol::MAX_LIGHTS;

use crate::passes::preview::{PreviewBindings, PreviewParams};
use crate::passes::tonemap::ToneParams;
use crate::renderer::Frame;
use crate::scene_gpu::{GpuLight, SceneUniforms, gpu_lights};
use crate::tf::{TF_LUT_SIZE, bake};
use crate::{Engine, EngineError, GpuVolume, Scene};

/// How fine a light volume the preview builds when it must rebuild it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightDetail {
    /// The full grid (`light_dims`).
    Full,
    /// Half the grid points per axis, about 16× cheaper to build (an eighth of the points, half
    /// the steps each): for edits that stream in, so that a TF drag is not held up by the
    /// light volume. A full one of the same inputs is reused rather than coarsened.
    Interactive,
}

/// Resolution divisors the preview may use, finest first.
pub const DIVISORS: [u32; 4] = [1, 2, 4, 8];

/// Light-volume grid points per axis: about one per `LIGHT_CELL_VOXELS` voxels, at most
/// `MAX_LIGHT_DIM`.
const LIGHT_CELL_VOXELS: u32 = 2;
const MAX_LIGHT_DIM: u32 = 32;

/// Light-volume channels of the environment (preview_light.wgsl: its transmittance's mean and
/// first moment over directions).
pub const ENV_CHANNELS: u32 = 4;

/// Bytes per viewport pixel the preview holds: its HDR image and its RGBA8 copy.
pub const BYTES_PER_PIXEL: u64 = 16 + 4;

/// What one preview took.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PreviewReport {
    /// Wall time of the view pass, tone mapping and readback.
    pub view_time: Duration,
    /// Wall time of rebuilding the light volume (zero when it was reused).
    pub light_time: Duration,
    pub light_rebuilt: bool,
}

pub struct Preview {
    volume: Arc<GpuVolume>,
    scene_buf: wgpu::Buffer,
    params_buf: wgpu::Buffer,
    tf_lut: wgpu::Buffer,
    lights: wgpu::Buffer,
    cell_max_opacity: wgpu::Buffer,
    light_volume: wgpu::Buffer,
    image: wgpu::Buffer,
    tone_params: wgpu::Buffer,
    rgba: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    tone_bind_group: wgpu::BindGroup,
    /// Grid points of the full light volume (its buffer's size).
    light_dims: [u32; 3],
    /// Grid points of the light volume as built (`light_dims`, or half of it per axis).
    built_dims: [u32; 3],
    /// Channels the light volume has room for (lights + the environment).
    light_channels: u32,
    /// Viewport size the image buffers were made for.
    width: u32,
    height: u32,
    /// What the light volume was built from; None: not built yet.
    built_from: Option<LightInputs>,
    /// The last LUT written (its opacities decide whether the light volume is stale).
    lut: Vec<[f32; 4]>,
    light_rebuilds: u64,
}

/// Everything the light volume depends on.
#[derive(Debug, Clone, PartialEq)]
struct LightInputs {
    opacities: Vec<f32>,
    density_scale: f32,
    lights: Vec<GpuLight>,
    env: [f32; 3],
}

/// Grid points per axis of the light volume for a volume of `dims` voxels.
pub fn light_dims(dims: [u32; 3]) -> [u32; 3] {
    dims.map(|d| d.div_ceil(LIGHT_CELL_VOXELS).clamp(2, MAX_LIGHT_DIM))
}

/// Preview image size for a viewport and divisor (rounded up, at least one pixel).
pub fn preview_size(width: u32, height: u32, divisor: u32) -> (u32, u32) {
    let d = divisor.max(1);
    (width.div_ceil(d).max(1), height.div_ceil(d).max(1))
}

impl Preview {
    pub fn new(engine: &Engine, volume: Arc<GpuVolume>, scene: &Scene) -> Self {
        let gpu = &engine.gpu;
        let storage = wgpu::BufferUsages::STORAGE;
        let scene_buf = gpu.buffer(
            "preview scene",
            size_of::<SceneUniforms>() as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let params_buf = gpu.buffer(
            "preview params",
            size_of::<PreviewParams>() as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let tf_lut = gpu.buffer("preview tf lut", (TF_LUT_SIZE * 16) as u64, storage);
        let lights = gpu.buffer(
            "preview lights",
            (MAX_LIGHTS * size_of::<GpuLight>()) as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let cell_max_opacity = gpu.buffer(
            "preview cell max opacity",
            (volume.ranges.cell_count() * 4) as u64,
            storage,
        );
        let light_dims = light_dims(volume.dims);
        let points: u64 = light_dims.iter().map(|&d| d as u64).product();
        // One channel per light plus the environment's.
        let light_channels = gpu_lights(&scene.lights).0.len() as u32 + ENV_CHANNELS;
        let light_volume = gpu.buffer(
            "preview light volume",
            points * light_channels as u64 * 4,
            storage,
        );
        let (width, height) = (scene.viewport.width, scene.viewport.height);
        let pixels = width as u64 * height as u64;
        let image = gpu.buffer(
            "preview image",
            pixels * 16,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let tone_params = gpu.buffer(
            "preview tone params",
            size_of::<ToneParams>() as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let rgba = gpu.buffer(
            "preview rgba8",
            pixels * 4,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let bind_group = engine.preview.bind_group(
            gpu,
            &PreviewBindings {
                scene: &scene_buf,
                volume: &volume.view,
                tf_lut: &tf_lut,
                lights: &lights,
                cell_max_opacity: &cell_max_opacity,
                params: &params_buf,
                light_volume: &light_volume,
                image: &image,
            },
        );
        let tone_bind_group = engine.tonemap.bind_group(gpu, &tone_params, &image, &rgba);
        Self {
            volume,
            scene_buf,
            params_buf,
            tf_lut,
            lights,
            cell_max_opacity,
            light_volume,
            image,
            tone_params,
            rgba,
            bind_group,
            tone_bind_group,
            light_dims,
            built_dims: light_dims,
            light_channels,
            width,
            height,
            built_from: None,
            lut: Vec::new(),
            light_rebuilds: 0,
        }
    }

    /// GPU bytes this preview holds.
    pub fn bytes(&self) -> u64 {
        [
            &self.scene_buf,
            &self.params_buf,
            &self.tf_lut,
            &self.lights,
            &self.cell_max_opacity,
            &self.light_volume,
            &self.image,
            &self.tone_params,
            &self.rgba,
        ]
        .iter()
        .map(|b| b.size())
        .sum()
    }

    /// How many times the light volume was built (for tests: camera moves never rebuild it).
    pub fn light_rebuilds(&self) -> u64 {
        self.light_rebuilds
    }

    /// Grid points of the light volume last built.
    pub fn built_light_dims(&self) -> [u32; 3] {
        self.built_dims
    }

    /// Renders one preview of `scene` at `divisor` and reads it back tone-mapped; a stale light
    /// volume is rebuilt at `detail`.
    pub fn render(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        divisor: u32,
        detail: LightDetail,
    ) -> Result<(Frame, PreviewReport), EngineError> {
        let (lights, env) = gpu_lights(&scene.lights);
        if (scene.viewport.width, scene.viewport.height) != (self.width, self.height)
            || lights.len() as u32 + ENV_CHANNELS > self.light_channels
        {
            *self = Preview::new(engine, self.volume.clone(), scene);
        }
        let (width, height) = preview_size(self.width, self.height, divisor);
        let gpu = &engine.gpu;
        let mut uniforms =
            SceneUniforms::new(scene, &self.volume, 0).map_err(EngineError::InvalidScene)?;
        uniforms.width = width;
        uniforms.height = height;
        gpu.queue
            .write_buffer(&self.scene_buf, 0, bytemuck::bytes_of(&uniforms));
        let lut = bake(&scene.tf);
        if lut != self.lut {
            gpu.queue
                .write_buffer(&self.tf_lut, 0, bytemuck::cast_slice(&lut));
            let cells = self.volume.ranges.max_opacity(&lut);
            gpu.queue
                .write_buffer(&self.cell_max_opacity, 0, bytemuck::cast_slice(&cells));
            self.lut = lut;
        }
        if !lights.is_empty() {
            gpu.queue
                .write_buffer(&self.lights, 0, bytemuck::cast_slice(&lights));
        }
        let inputs = LightInputs {
            opacities: self.lut.iter().map(|e| e[3]).collect(),
            density_scale: scene.params.density_scale,
            lights,
            env,
        };
        let channels = inputs.lights.len() as u32 + ENV_CHANNELS;
        let mut light_time = Duration::ZERO;
        let light_rebuilt = self.built_from.as_ref() != Some(&inputs)
            || (detail == LightDetail::Full && self.built_dims != self.light_dims);
        if light_rebuilt {
            self.built_dims = match detail {
                LightDetail::Full => self.light_dims,
                LightDetail::Interactive => self.light_dims.map(|d| d.div_ceil(2).max(2)),
            };
        }
        let params = PreviewParams {
            light_dims: self.built_dims,
            channels,
            width,
            height,
            pad0: 0,
            pad1: 0,
        };
        gpu.queue
            .write_buffer(&self.params_buf, 0, bytemuck::bytes_of(&params));
        if light_rebuilt {
            let started = Instant::now();
            let mut encoder = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("preview light volume"),
                });
            engine
                .preview
                .encode_light(&mut encoder, &self.bind_group, self.built_dims, None);
            gpu.queue.submit([encoder.finish()]);
            gpu.wait_idle()?;
            light_time = started.elapsed();
            self.built_from = Some(inputs);
            self.light_rebuilds += 1;
        }
        let started = Instant::now();
        let tone = ToneParams {
            width,
            height,
            exposure: scene.params.exposure,
            pad0: 0,
        };
        gpu.queue
            .write_buffer(&self.tone_params, 0, bytemuck::bytes_of(&tone));
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("preview view"),
            });
        engine
            .preview
            .encode_view(&mut encoder, &self.bind_group, (width, height), None);
        engine
            .tonemap
            .encode(&mut encoder, &self.tone_bind_group, width, height);
        gpu.queue.submit([encoder.finish()]);
        let rgba = gpu.read_buffer_range(&self.rgba, 0, width as u64 * height as u64 * 4)?;
        gpu.check()?;
        let frame = Frame {
            width,
            height,
            rgba,
            iteration: 0,
            target_iterations: scene.target_iterations,
            converged: false,
            divisor,
            preview: true,
        };
        let report = PreviewReport {
            view_time: started.elapsed(),
            light_time,
            light_rebuilt,
        };
        Ok((frame, report))
    }

    /// The linear radiance of the last preview (row 0 at the top), for tests and benchmarks.
    pub fn read_hdr(&self, engine: &Engine, divisor: u32) -> Result<Vec<[f32; 3]>, EngineError> {
        let (width, height) = preview_size(self.width, self.height, divisor);
        let bytes =
            engine
                .gpu
                .read_buffer_range(&self.image, 0, width as u64 * height as u64 * 16)?;
        let pixels: &[[f32; 4]] = bytemuck::try_cast_slice(&bytes)
            .map_err(|e| EngineError::Gpu(format!("preview readback has an odd size: {e}")))?;
        Ok(pixels.iter().map(|p| [p[0], p[1], p[2]]).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn light_grid_follows_the_volume_and_is_capped() {
        assert_eq!(light_dims([256, 256, 256]), [32, 32, 32]);
        assert_eq!(light_dims([512, 512, 128]), [32, 32, 32]);
        assert_eq!(light_dims([32, 32, 3]), [16, 16, 2]);
    }

    #[test]
    fn preview_sizes_round_up() {
        assert_eq!(preview_size(512, 512, 1), (512, 512));
        assert_eq!(preview_size(968, 774, 8), (121, 97));
        assert_eq!(preview_size(1, 1, 8), (1, 1));
    }
}
