//! `voxlight bench load`: time and peak host memory of loading each dataset from disk, against
//! the volume's own size (the 16-bit samples the server keeps). No GPU is involved.
//!
//! - Every load runs in a fresh child process (`voxlight bench load` again, one dataset), so
//!   memory freed by an earlier load and kept by the allocator cannot hide a later peak.
//! - Peak memory is the child's resident high-water mark (`VmHWM`) minus its resident size just
//!   before the load (Linux `/proc/self/status`).
//! - Each dataset is loaded `repeats` times; the median time and the largest peak are reported.

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use serde_json::json;

pub struct LoadBench<'a> {
    pub data_dir: &'a Path,
    /// Dataset paths relative to `data_dir` (a DICOM series folder, or a file).
    pub datasets: &'a [String],
    pub repeats: u32,
}

/// Resident and peak-resident bytes of this process (Linux `/proc/self/status`).
fn resident() -> anyhow::Result<(u64, u64)> {
    let status =
        std::fs::read_to_string("/proc/self/status").context("reading /proc/self/status")?;
    let field = |name: &str| -> anyhow::Result<u64> {
        let line = status
            .lines()
            .find(|l| l.starts_with(name))
            .with_context(|| format!("no {name} in /proc/self/status"))?;
        let kib: u64 = line
            .split_whitespace()
            .nth(1)
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("unreadable {line}"))?;
        Ok(kib * 1024)
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

/// Set in the child that loads one dataset once and prints one JSON line.
const CHILD_ENV: &str = "VOXLIGHT_BENCH_LOAD_CHILD";

/// In the child: one load, measured.
fn measure_once(path: &Path) -> anyhow::Result<serde_json::Value> {
    let (before, _) = resident()?;
    let started = Instant::now();
    let volume =
        voxlight_volumes::load(path).with_context(|| format!("loading {}", path.display()))?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let (_, high) = resident()?;
    Ok(json!({
        "load_ms": ms,
        "peak_bytes": high.saturating_sub(before),
        "volume_bytes": (volume.data.len() * std::mem::size_of::<u16>()) as u64,
        "dims": volume.dims,
    }))
}

/// Runs `voxlight bench load` for one dataset in a fresh process and reads its measurement.
fn measure_in_child(data_dir: &Path, name: &str) -> anyhow::Result<serde_json::Value> {
    let exe = std::env::current_exe().context("finding the voxlight binary")?;
    let output = std::process::Command::new(exe)
        .args([
            "bench",
            "load",
            "--repeats",
            "1",
            "--datasets",
            name,
            "--data",
        ])
        .arg(data_dir)
        .env(CHILD_ENV, "1")
        .output()
        .context("starting the measuring process")?;
    let stdout = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        anyhow::bail!(
            "loading {name} failed: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    let line = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(line).with_context(|| format!("unreadable measurement `{line}`"))
}

fn bytes_on_disk(path: &Path) -> u64 {
    if path.is_dir() {
        std::fs::read_dir(path)
            .map(|entries| {
                entries
                    .filter_map(Result::ok)
                    .filter_map(|e| e.metadata().ok())
                    .filter(|m| m.is_file())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0)
    } else {
        std::fs::metadata(path).map_or(0, |m| m.len())
    }
}

/// Prints the child's one-line measurement; true when this process is such a child.
pub fn child(bench: &LoadBench) -> anyhow::Result<bool> {
    if std::env::var_os(CHILD_ENV).is_none() {
        return Ok(false);
    }
    let name = bench.datasets.first().context("no dataset to load")?;
    println!("{}", measure_once(&bench.data_dir.join(name))?);
    Ok(true)
}

pub fn load(bench: &LoadBench) -> anyhow::Result<serde_json::Value> {
    let mut rows = Vec::new();
    for name in bench.datasets {
        let path = bench.data_dir.join(name);
        let mut times = Vec::new();
        let mut peak = 0u64;
        let mut volume_bytes = 0u64;
        let mut dims = serde_json::Value::Null;
        for _ in 0..bench.repeats.max(1) {
            let m = measure_in_child(bench.data_dir, name)?;
            times.push(m["load_ms"].as_f64().unwrap_or(f64::NAN));
            peak = peak.max(m["peak_bytes"].as_u64().unwrap_or(0));
            volume_bytes = m["volume_bytes"].as_u64().unwrap_or(0);
            dims = m["dims"].clone();
        }
        times.sort_by(f64::total_cmp);
        let median = times[times.len() / 2];
        let ratio = peak as f64 / volume_bytes.max(1) as f64;
        let on_disk = bytes_on_disk(&path);
        eprintln!(
            "{name}: {} ms, peak +{} MiB for a {} MiB volume ({ratio:.2}×), {} MiB on disk",
            median.round(),
            peak >> 20,
            volume_bytes >> 20,
            on_disk >> 20
        );
        rows.push(json!({
            "dataset": name,
            "dims": dims,
            "load_ms": median,
            "peak_bytes": peak,
            "volume_bytes": volume_bytes,
            "peak_over_volume": ratio,
            "bytes_on_disk": on_disk,
        }));
    }
    Ok(json!({ "bench": "load", "repeats": bench.repeats.max(1), "datasets": rows }))
}
