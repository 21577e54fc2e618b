//! The interactive preview every technique shows while edits stream in (docs/architecture.md
//! "Interaction mode"): single scattering composited front to back along one ray per pixel of a
//! reduced-resolution image, lit from a light volume (passes::preview). One per session.
//!
//! - The light volume is rebuilt only when what it depends on changed: the TF's opacities, the
//!   density scale, the lights or the volume. Camera moves and colour-only TF edits reuse it.
//! - The image is the viewport divided by a resolution divisor (1, 2, 4, 8 per axis), rounded
//!   up; the client scales it to its canvas.
//! - Its scattered light is scaled by a per-session brightness match (`BrightnessMatch`) so that
//!   its mean meets the technique's still: no brightness step when input stops.

use std::sync::Arc;
use std::time::{Duration, Instant};

use voxlight_protocol::MAX_LIGHTS;

use crate::frame::Frame;
use crate::gpu::TfTexture;
use crate::passes::preview::{PreviewBindings, PreviewParams};
use crate::passes::tonemap::ToneParams;
use crate::scene_gpu::{GpuLight, SceneUniforms, gpu_lights};
use crate::techniques::progressive::band_rows;
use crate::tf::bake;
use crate::{Engine, EngineError, GpuVolume, Scene};

pub use crate::brightness::{BrightnessMatch, PreviewMeans, mean_rgb};

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

/// Light-volume channels of the environment (preview/light.wgsl: its transmittance's mean and
/// first moment over directions).
pub const ENV_CHANNELS: u32 = 4;

/// Bytes per viewport pixel the preview holds: its HDR image, its multiple scattering (f16) and
/// its RGBA8 copy.
pub const BYTES_PER_PIXEL: u64 = 16 + 8 + 4;

/// A preview runs in parts of about this long (`Preview::render_until`) when it is expected to
/// take longer.
pub const PART_TIME: Duration = Duration::from_millis(25);

/// Parts of about `part` for work expected to take `expected` (one when unknown), at most
/// `most`.
fn parts_of(expected: Option<Duration>, part: Duration, most: u32) -> u32 {
    match expected {
        None => 1,
        Some(t) => {
            let parts = (t.as_secs_f64() / part.as_secs_f64().max(1e-12)).ceil();
            (parts.min(f64::from(u32::MAX)) as u32).clamp(1, most.max(1))
        }
    }
}

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
    tf_lut: TfTexture,
    lights: wgpu::Buffer,
    cell_max_opacity: wgpu::Buffer,
    light_volume: wgpu::Buffer,
    image: wgpu::Buffer,
    image_multiple: wgpu::Buffer,
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
    /// Brightness match and environment radiance of the last render (to split its image into
    /// single and multiple scattering and background).
    rendered_with: Option<(BrightnessMatch, [f32; 3])>,
    multiple_scattering: bool,
    /// Measured time per light-volume grid point and per view pixel (with tone mapping and
    /// readback) of the last build and view pass: how many parts the next ones run in.
    light_cost: Option<Duration>,
    view_cost: Option<Duration>,
    /// How long a part of a preview may take (`PART_TIME`).
    part_time: Duration,
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
    /// `multiple_scattering`: the session's technique scatters more than once, so the preview
    /// computes its approximate multiple scattering (`BrightnessMatch`).
    pub fn new(
        engine: &Engine,
        volume: Arc<GpuVolume>,
        scene: &Scene,
        multiple_scattering: bool,
    ) -> Self {
        let gpu = &engine.gpu;
        let storage = wgpu::BufferUsages::STORAGE;
        let uniform =
            |label, size: usize| gpu.buffer(label, size as u64, wgpu::BufferUsages::UNIFORM);
        // What the CPU reads back (or copies) too.
        let readable =
            |label, size| gpu.buffer(label, size, storage | wgpu::BufferUsages::COPY_SRC);
        let scene_buf = uniform("preview scene", size_of::<SceneUniforms>());
        let params_buf = uniform("preview params", size_of::<PreviewParams>());
        let tf_lut = gpu.tf_texture("preview tf lut");
        let lights = uniform("preview lights", MAX_LIGHTS * size_of::<GpuLight>());
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
        let image = readable("preview image", pixels * 16);
        // Only a GI technique's preview writes it (a placeholder binding otherwise).
        let image_multiple = readable(
            "preview image multiple scattering",
            if multiple_scattering { pixels * 8 } else { 8 },
        );
        let tone_params = uniform("preview tone params", size_of::<ToneParams>());
        let rgba = readable("preview rgba8", pixels * 4);
        let bind_group = engine.preview.bind_group(
            gpu,
            &PreviewBindings {
                scene: &scene_buf,
                volume: &volume.view,
                tf_lut: &tf_lut.view,
                lights: &lights,
                cell_max_opacity: &cell_max_opacity,
                params: &params_buf,
                light_volume: &light_volume,
                image: &image,
                image_multiple: &image_multiple,
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
            image_multiple,
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
            rendered_with: None,
            multiple_scattering,
            light_cost: None,
            view_cost: None,
            part_time: PART_TIME,
        }
    }

    /// GPU bytes this preview holds.
    pub fn bytes(&self) -> u64 {
        [
            &self.scene_buf,
            &self.params_buf,
            &self.lights,
            &self.cell_max_opacity,
            &self.light_volume,
            &self.image,
            &self.image_multiple,
            &self.tone_params,
            &self.rgba,
        ]
        .iter()
        .map(|b| b.size())
        .sum::<u64>()
            + TfTexture::BYTES
    }

    /// How many times the light volume was built (for tests: camera moves never rebuild it).
    pub fn light_rebuilds(&self) -> u64 {
        self.light_rebuilds
    }

    /// Sets how long a part of a long preview may take (`PART_TIME` by default; tests use a
    /// tiny one to split every preview into as many parts as it has rows and grid planes).
    pub fn set_part_time(&mut self, part_time: Duration) {
        self.part_time = part_time;
    }

    /// Grid points of the light volume last built.
    pub fn built_light_dims(&self) -> [u32; 3] {
        self.built_dims
    }

    /// Renders one preview of `scene` at `divisor` with its brightness matched by `brightness`
    /// and reads it back tone-mapped; a stale light volume is rebuilt at `detail`.
    ///
    /// With `stop`, a preview expected to take longer than a part's time (`PART_TIME`) runs in
    /// parts (grid planes of the light volume, interleaved bands of image rows) and `stop` is
    /// asked between them: when it says so the preview is abandoned (None; a partly rebuilt
    /// light volume counts as stale), so that an edit that came meanwhile waits for one part,
    /// not for a full-resolution preview (seconds on a software adapter). Parts cost
    /// throughput (a submission and a wait each), so a preview nobody may stop runs whole (and
    /// always returns Some).
    pub fn render_until(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        divisor: u32,
        detail: LightDetail,
        brightness: &BrightnessMatch,
        mut stop: Option<&mut dyn FnMut() -> bool>,
    ) -> Result<Option<(Frame, PreviewReport)>, EngineError> {
        let (lights, env) = gpu_lights(&scene.lights);
        if (scene.viewport.width, scene.viewport.height) != (self.width, self.height)
            || lights.len() as u32 + ENV_CHANNELS > self.light_channels
        {
            *self = Preview::new(engine, self.volume.clone(), scene, self.multiple_scattering);
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
            self.tf_lut.write(&gpu.queue, &lut);
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
        let light_rebuilt = self.built_from.as_ref() != Some(&inputs)
            || (detail == LightDetail::Full && self.built_dims != self.light_dims);
        if light_rebuilt {
            self.built_dims = match detail {
                LightDetail::Full => self.light_dims,
                LightDetail::Interactive => self.light_dims.map(|d| d.div_ceil(2).max(2)),
            };
        }
        let mut params = PreviewParams {
            light_dims: self.built_dims,
            channels,
            width,
            height,
            row_offset: 0,
            row_stride: 1,
            gain: brightness.gain,
            multiple: u32::from(self.multiple_scattering),
            multiple_weight: if self.multiple_scattering {
                brightness.multiple_weight
            } else {
                [0.0; 3]
            },
            z_offset: 0,
        };
        let brightness = BrightnessMatch {
            multiple_weight: params.multiple_weight,
            multiple_scattering: self.multiple_scattering,
            ..*brightness
        };
        let mut light_time = Duration::ZERO;
        if light_rebuilt {
            // Until every plane is written it is stale.
            self.built_from = None;
            let points_per_plane = u64::from(self.built_dims[0] * self.built_dims[1]);
            let depth = self.built_dims[2];
            // As many planes as fit in a part at the last build's cost (one at first); all of
            // them when nobody may stop it.
            let part_time = self.part_time;
            let planes_per_part = match (&stop, self.light_cost) {
                (None, _) => depth,
                (Some(_), None) => 1,
                (Some(_), Some(c)) => {
                    let per_plane = c.as_secs_f64() * points_per_plane as f64;
                    ((part_time.as_secs_f64() / per_plane.max(1e-12)) as u32).clamp(1, depth)
                }
            };
            let mut z = 0;
            while z < depth {
                let planes = planes_per_part.min(depth - z);
                params.z_offset = z;
                let started = Instant::now();
                self.submit_with(engine, &params, "preview light volume", |encoder| {
                    let group = &self.bind_group;
                    engine
                        .preview
                        .encode_light(encoder, group, self.built_dims, planes, None);
                });
                gpu.wait_idle()?;
                let took = started.elapsed();
                light_time += took;
                self.light_cost = Some(took / (planes * points_per_plane as u32).max(1));
                z += planes;
                if z < depth && stop.as_mut().is_some_and(|stop| stop()) {
                    return Ok(None);
                }
            }
            params.z_offset = 0;
            self.built_from = Some(inputs);
            self.light_rebuilds += 1;
        }
        self.rendered_with = Some((brightness, env));
        let started = Instant::now();
        // Interleaved bands of 8-row blocks (shared/common.wgsl band_row), as many as the last view
        // pass's cost per pixel predicts for this image at a part's time each.
        let pixels = width * height;
        let bands = match stop {
            None => 1,
            Some(_) => parts_of(
                self.view_cost.map(|c| c * pixels),
                self.part_time,
                height.div_ceil(8),
            ),
        };
        for band in 0..bands {
            if band > 0 && stop.as_mut().is_some_and(|stop| stop()) {
                return Ok(None);
            }
            params.row_offset = band;
            params.row_stride = bands;
            self.submit_with(engine, &params, "preview view", |encoder| {
                let rows = band_rows(height, band, bands);
                let group = &self.bind_group;
                engine
                    .preview
                    .encode_view(encoder, group, (width, rows), None);
            });
            if bands > 1 {
                gpu.wait_idle()?;
            }
        }
        let tone = ToneParams {
            width,
            height,
            exposure: scene.params.exposure,
            pad0: 0,
        };
        gpu.queue
            .write_buffer(&self.tone_params, 0, bytemuck::bytes_of(&tone));
        let mut encoder = encoder(engine, "preview tone map");
        engine
            .tonemap
            .encode(&mut encoder, &self.tone_bind_group, width, height);
        gpu.queue.submit([encoder.finish()]);
        let rgba = gpu.read_buffer_range(&self.rgba, 0, u64::from(pixels) * 4)?;
        gpu.check()?;
        let view_time = started.elapsed();
        self.view_cost = Some(view_time / pixels.max(1));
        let frame = Frame {
            width,
            height,
            rgba,
            iteration: 0,
            target_iterations: scene.target_iterations,
            converged: false,
            divisor,
            preview: true,
            preview_match: Some(brightness),
        };
        let report = PreviewReport {
            view_time,
            light_time,
            light_rebuilt,
        };
        Ok(Some((frame, report)))
    }

    /// Writes `params` and submits what `encode` records, on its own.
    fn submit_with(
        &self,
        engine: &Engine,
        params: &PreviewParams,
        label: &str,
        encode: impl FnOnce(&mut wgpu::CommandEncoder),
    ) {
        let queue = &engine.gpu.queue;
        queue.write_buffer(&self.params_buf, 0, bytemuck::bytes_of(params));
        let mut encoder = encoder(engine, label);
        encode(&mut encoder);
        queue.submit([encoder.finish()]);
    }

    /// The linear radiance of the last preview (row 0 at the top), for tests and benchmarks.
    pub fn read_hdr(&self, engine: &Engine, divisor: u32) -> Result<Vec<[f32; 3]>, EngineError> {
        let (width, height) = preview_size(self.width, self.height, divisor);
        let bytes =
            engine
                .gpu
                .read_buffer_range(&self.image, 0, width as u64 * height as u64 * 16)?;
        let pixels: &[[f32; 4]] = cast_readback(&bytes)?;
        Ok(pixels.iter().map(|p| [p[0], p[1], p[2]]).collect())
    }

    /// Means of the last preview's single and multiple scattering (before the brightness
    /// match) and background, over its `divisor`'s image.
    pub fn means(&self, engine: &Engine, divisor: u32) -> Result<PreviewMeans, EngineError> {
        let Some((brightness, env)) = self.rendered_with else {
            return Err(EngineError::Gpu("no preview was rendered".into()));
        };
        let (width, height) = preview_size(self.width, self.height, divisor);
        let pixels = width as u64 * height as u64;
        let bytes = engine.gpu.read_buffer_range(&self.image, 0, pixels * 16)?;
        let image: &[[f32; 4]] = cast_readback(&bytes)?;
        let multiple = if self.multiple_scattering {
            let bytes = engine
                .gpu
                .read_buffer_range(&self.image_multiple, 0, pixels * 8)?;
            // pack2x16float: the low half of each u32 is the first value.
            let halves: &[[u16; 4]] = cast_readback(&bytes)?;
            let f = |bits: u16| half::f16::from_bits(bits).to_f32();
            halves.iter().map(|h| [f(h[0]), f(h[1]), f(h[2])]).collect()
        } else {
            vec![[0.0; 3]; image.len()]
        };
        Ok(split_means(image, &multiple, &brightness, env))
    }
}

fn encoder(engine: &Engine, label: &str) -> wgpu::CommandEncoder {
    let descriptor = wgpu::CommandEncoderDescriptor { label: Some(label) };
    engine.gpu.device.create_command_encoder(&descriptor)
}

/// Read-back bytes as pixels.
fn cast_readback<T: bytemuck::Pod>(bytes: &[u8]) -> Result<&[T], EngineError> {
    bytemuck::try_cast_slice(bytes)
        .map_err(|e| EngineError::Gpu(format!("preview readback has an odd size: {e}")))
}

/// Splits preview pixels (rgb = gain · single + multiple_weight · multiple + env · T, w = T)
/// and their `multiple` into the means of the single and multiple scattering before the match
/// and of the background.
fn split_means(
    image: &[[f32; 4]],
    multiple: &[[f32; 3]],
    brightness: &BrightnessMatch,
    env: [f32; 3],
) -> PreviewMeans {
    let mut single = [0.0f64; 3];
    let mut multiples = [0.0f64; 3];
    let mut background = [0.0f64; 3];
    for (p, m) in image.iter().zip(multiple) {
        let transmit = f64::from(p[3]);
        for c in 0..3 {
            let bg = f64::from(env[c]) * transmit;
            let ms = f64::from(m[c]);
            background[c] += bg;
            multiples[c] += ms;
            single[c] += (f64::from(p[c]) - bg - f64::from(brightness.multiple_weight[c]) * ms)
                / f64::from(brightness.gain[c]);
        }
    }
    let n = image.len().max(1) as f64;
    PreviewMeans {
        single: single.map(|s| s / n),
        multiple: multiples.map(|s| s / n),
        background: background.map(|b| b / n),
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
    fn means_split_single_and_multiple_scattering_from_background() {
        let env = [0.2, 0.1, 0.0];
        let brightness = BrightnessMatch {
            gain: [2.0, 1.0, 0.5],
            multiple_weight: [0.5, 0.0, 1.0],
            multiple_scattering: true,
        };
        // Single 0.3/0.4/0.5 and multiple 0.2/0.2/0.2 behind transmittance 0.5, then a clear
        // pixel.
        let mixed = |c: usize, single: f32| {
            single * brightness.gain[c] + 0.2 * brightness.multiple_weight[c] + env[c] * 0.5
        };
        let image = [
            [mixed(0, 0.3), mixed(1, 0.4), mixed(2, 0.5), 0.5],
            [env[0], env[1], env[2], 1.0],
        ];
        let multiple = [[0.2; 3], [0.0; 3]];
        let means = split_means(&image, &multiple, &brightness, env);
        let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
        assert!(close(means.single, [0.15, 0.2, 0.25]), "{means:?}");
        assert!(close(means.multiple, [0.1; 3]), "{means:?}");
        assert!(close(means.background, [0.15, 0.075, 0.0]), "{means:?}");
    }

    #[test]
    fn single_scattering_techniques_match_by_gain() {
        let preview = PreviewMeans {
            single: [0.2, 0.1, 1e-7],
            multiple: [0.0; 3],
            background: [0.3, 0.3, 0.3],
        };
        let mut brightness = BrightnessMatch::new(false);
        // The technique is 0.1 brighter in red, 0.02 darker in green; in blue the volume shows
        // next to nothing, so its match stays.
        assert!(brightness.update(&preview, [0.6, 0.38, 0.31]));
        let g = brightness.gain;
        assert!(
            (g[0] - 1.5).abs() < 1e-6 && (g[1] - 0.8).abs() < 1e-6,
            "{g:?}"
        );
        assert_eq!(g[2], 1.0);
        assert_eq!(brightness.multiple_weight, [0.0; 3]);
        // A broken measurement is clamped, not taken.
        assert!(brightness.update(&preview, [100.0, -5.0, 0.3]));
        let (low, high) = BrightnessMatch::GAIN_RANGE;
        assert_eq!(brightness.gain, [high, low, 1.0]);
        // Nothing to match: an empty picture changes nothing.
        let empty = PreviewMeans {
            single: [0.0; 3],
            multiple: [0.0; 3],
            background: [0.3; 3],
        };
        assert!(!brightness.update(&empty, [0.3; 3]));
    }

    #[test]
    fn gi_techniques_match_by_the_multiple_scattering_weight() {
        let preview = PreviewMeans {
            single: [0.2, 0.2, 0.2],
            multiple: [0.4, 0.4, 0.0],
            background: [0.1; 3],
        };
        let mut brightness = BrightnessMatch::new(true);
        assert_eq!(
            brightness.multiple_weight,
            [BrightnessMatch::PRIOR_MULTIPLE_WEIGHT; 3]
        );
        // Red: 0.2 beyond the single scattering, half the approximation. Green: darker than
        // the single scattering, so the gain takes it. Blue: no multiple scattering computed.
        assert!(brightness.update(&preview, [0.5, 0.25, 0.4]));
        let close = |a: f32, b: f32| (a - b).abs() < 1e-6;
        assert!(close(brightness.multiple_weight[0], 0.5) && close(brightness.gain[0], 1.0));
        assert!(close(brightness.multiple_weight[1], 0.0) && close(brightness.gain[1], 0.75));
        assert!(close(brightness.multiple_weight[2], 0.0) && close(brightness.gain[2], 1.5));
        // The preview's mean then meets the technique's in every channel.
        for (c, want) in [0.5, 0.25, 0.4].into_iter().enumerate() {
            let mean = preview.background[c]
                + f64::from(brightness.gain[c]) * preview.single[c]
                + f64::from(brightness.multiple_weight[c]) * preview.multiple[c];
            assert!((mean - want).abs() < 1e-6, "channel {c}: {mean}");
        }
    }

    #[test]
    fn preview_sizes_round_up() {
        assert_eq!(preview_size(512, 512, 1), (512, 512));
        assert_eq!(preview_size(968, 774, 8), (121, 97));
        assert_eq!(preview_size(1, 1, 8), (1, 1));
    }
}
