//! `voxlight render`: an offline still of a scene file, the tool every correctness
//! comparison uses. Writes a PNG (tone-mapped) and optionally a PFM of linear radiance.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use voxlight_engine::{Engine, Scene};
use voxlight_protocol::{RenderParams, Scene as SceneFile, Viewport};
use voxlight_volumes::Volume;

/// Opens `phantom:NAME` or a path (relative paths are relative to `base`, the scene file's folder).
pub fn open_dataset(spec: &str, base: &Path) -> anyhow::Result<Volume> {
    let mut volume = if let Some(name) = spec.strip_prefix("phantom:") {
        voxlight_volumes::phantom(name, crate::datasets::PHANTOM_SIZE)
            .with_context(|| format!("phantom `{name}`"))?
    } else {
        let path = Path::new(spec);
        let path: PathBuf = if path.is_absolute() {
            path.to_owned()
        } else {
            base.join(path)
        };
        voxlight_volumes::load(&path).with_context(|| format!("loading {}", path.display()))?
    };
    volume.name = spec.to_owned();
    Ok(volume)
}

/// The engine scene of a scene file, with the dataset's default TF when it has none.
pub fn engine_scene(file: &SceneFile, volume: &Volume) -> anyhow::Result<Scene> {
    let scene = Scene {
        camera: file.camera,
        tf: file
            .tf
            .clone()
            .unwrap_or_else(|| crate::datasets::default_tf(volume)),
        lights: file.lights.clone(),
        params: RenderParams {
            density_scale: file.density_scale,
            g: file.g,
            exposure: file.exposure,
        },
        viewport: Viewport {
            width: file.width,
            height: file.height,
        },
        seed: file.seed,
        target_iterations: file.iterations.max(1),
        technique_options: file.technique_options,
    };
    scene
        .validate()
        .map_err(|e| anyhow::anyhow!("invalid scene: {e}"))?;
    Ok(scene)
}

/// Renders `scene_path` to `out` (PNG) and optionally `pfm` (linear radiance).
pub fn render(scene_path: &Path, out: &Path, pfm: Option<&Path>) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(scene_path)
        .with_context(|| format!("reading {}", scene_path.display()))?;
    let file: SceneFile = serde_json::from_str(&text)
        .with_context(|| format!("parsing scene file {}", scene_path.display()))?;
    let base = scene_path.parent().unwrap_or(Path::new("."));
    let volume = open_dataset(&file.dataset, base)?;
    let scene = engine_scene(&file, &volume)?;
    let engine = Engine::new()?;
    tracing::info!(adapter = %engine.gpu.adapter_name(), "rendering {}", scene_path.display());
    let gpu_volume: Arc<_> = engine.upload_volume(&volume)?;
    let mut renderer = engine.create_renderer(&file.technique, gpu_volume, &scene)?;
    let started = Instant::now();
    while !renderer.converged(&scene) {
        renderer.step(&engine, &scene, Duration::from_millis(500))?;
    }
    let frame = renderer.frame(&engine, &scene)?;
    let png = crate::encode::png(&frame.rgba, frame.width, frame.height)?;
    std::fs::write(out, png).with_context(|| format!("writing {}", out.display()))?;
    if let Some(pfm) = pfm {
        let hdr = renderer.read_hdr(&engine)?;
        write_pfm(pfm, frame.width, frame.height, &hdr)?;
    }
    tracing::info!(
        iterations = frame.iteration,
        seconds = started.elapsed().as_secs_f32(),
        "wrote {}",
        out.display()
    );
    Ok(())
}

/// Portable float map, RGB, little endian; PFM stores the bottom row first.
pub fn write_pfm(path: &Path, width: u32, height: u32, rgb: &[[f32; 3]]) -> anyhow::Result<()> {
    if rgb.len() != width as usize * height as usize {
        bail!("PFM: {} pixels for a {width}×{height} image", rgb.len());
    }
    let mut bytes = format!("PF\n{width} {height}\n-1.0\n").into_bytes();
    for row in (0..height as usize).rev() {
        for px in &rgb[row * width as usize..(row + 1) * width as usize] {
            for c in px {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// Reads a PFM written by `write_pfm` (row 0 at the top in the result).
pub fn read_pfm(path: &Path) -> anyhow::Result<(u32, u32, Vec<[f32; 3]>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = 0;
    let mut header_end = 0;
    for (i, b) in bytes.iter().enumerate() {
        if *b == b'\n' {
            lines += 1;
            if lines == 3 {
                header_end = i + 1;
                break;
            }
        }
    }
    let header = std::str::from_utf8(&bytes[..header_end]).context("PFM header is not text")?;
    let mut parts = header.split_whitespace();
    if parts.next() != Some("PF") {
        bail!("not an RGB PFM");
    }
    let width: u32 = parts.next().context("PFM width")?.parse()?;
    let height: u32 = parts.next().context("PFM height")?.parse()?;
    let scale: f32 = parts.next().context("PFM scale")?.parse()?;
    if scale >= 0.0 {
        bail!("big-endian PFM is not supported");
    }
    let data = &bytes[header_end..];
    let n = width as usize * height as usize;
    if data.len() != n * 12 {
        bail!("PFM has {} data bytes, expected {}", data.len(), n * 12);
    }
    let mut rgb = vec![[0.0f32; 3]; n];
    for (i, chunk) in data.chunks_exact(12).enumerate() {
        let (row, col) = (i / width as usize, i % width as usize);
        let top_row = height as usize - 1 - row;
        rgb[top_row * width as usize + col] = std::array::from_fn(|k| {
            f32::from_le_bytes([
                chunk[4 * k],
                chunk[4 * k + 1],
                chunk[4 * k + 2],
                chunk[4 * k + 3],
            ])
        });
    }
    Ok((width, height, rgb))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pfm_round_trip_keeps_row_order() {
        let dir = std::env::temp_dir().join(format!("voxlight-pfm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.pfm");
        let rgb: Vec<[f32; 3]> = (0..6).map(|i| [i as f32, 0.5, -1.0]).collect();
        write_pfm(&path, 3, 2, &rgb).unwrap();
        let (w, h, back) = read_pfm(&path).unwrap();
        assert_eq!((w, h), (3, 2));
        assert_eq!(back, rgb);
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.starts_with(b"PF\n3 2\n-1.0\n"));
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn scene_files_carry_technique_options() {
        let file: SceneFile = serde_json::from_str(
            r#"{"dataset":"phantom:sphere","technique":"irradiance","width":16,"height":16,
                "technique_options":{"irradiance":{"locking":"screen","max_radius_voxels":2}}}"#,
        )
        .unwrap();
        let volume = open_dataset(&file.dataset, Path::new(".")).unwrap();
        let scene = engine_scene(&file, &volume).unwrap();
        let config = voxlight_engine::techniques::irradiance::IrradianceConfig::from_options(
            &scene.technique_options.irradiance,
        );
        assert_eq!(
            config.locking,
            voxlight_engine::techniques::irradiance::Locking::Screen
        );
        assert_eq!(config.max_radius_voxels, 2.0);
    }
}
