//! `voxlight bench NAME [--json]`: speed measured in one run on the adapter at hand.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use serde_json::json;
use voxlight_engine::{Engine, Scene};
use voxlight_protocol::{Camera, Viewport, default_lights};

/// Options of `bench raymarch`.
pub struct RaymarchBench<'a> {
    pub data_dir: Option<&'a Path>,
    pub sizes: &'a [u32],
    pub iterations: u32,
}

/// ms per progressive `raymarch` iteration at each size on a 256³ CT (the bonsai CT of
/// ../shared/data when found, else a 256³ Cornell phantom). Returns the JSON result.
pub fn raymarch(options: &RaymarchBench) -> anyhow::Result<serde_json::Value> {
    let engine = Engine::new()?;
    let (dataset, mut volume) = match options.data_dir.map(|d| d.join("vti/bonsai.vti")) {
        Some(path) if path.is_file() => (
            "vti/bonsai.vti".to_owned(),
            voxlight_volumes::load(&path).with_context(|| format!("loading {}", path.display()))?,
        ),
        _ => (
            "phantom:cornell@256".to_owned(),
            voxlight_volumes::phantom("cornell", 256)?,
        ),
    };
    volume.name = dataset.clone();
    let gpu_volume = engine.upload_volume(&volume)?;
    let mut results = Vec::new();
    for &size in options.sizes {
        let scene = Scene {
            camera: Camera::default(),
            tf: crate::datasets::default_tf(&volume),
            lights: default_lights(),
            viewport: Viewport {
                width: size,
                height: size,
            },
            target_iterations: u32::MAX,
            ..Scene::default()
        };
        let mut renderer = engine.create_renderer("raymarch", Arc::clone(&gpu_volume), &scene)?;
        // Warm up (pipeline compilation, first touches), then time whole iterations.
        renderer.step(&engine, &scene, Duration::ZERO)?;
        let before = renderer.iteration();
        let started = Instant::now();
        while renderer.iteration() - before < options.iterations {
            renderer.step(&engine, &scene, Duration::ZERO)?;
        }
        let elapsed = started.elapsed();
        let done = renderer.iteration() - before;
        let ms = elapsed.as_secs_f64() * 1000.0 / done as f64;
        eprintln!("raymarch {size}x{size}: {ms:.1} ms/iteration over {done} iterations");
        results.push(
            json!({"width": size, "height": size, "iterations": done, "ms_per_iteration": ms}),
        );
    }
    Ok(json!({
        "bench": "raymarch",
        "adapter": engine.gpu.adapter_name(),
        "software_renderer": engine.gpu.is_software(),
        "dataset": dataset,
        "dims": volume.dims,
        "results": results,
    }))
}
