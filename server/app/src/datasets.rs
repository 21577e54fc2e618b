//! The datasets a server offers: built-in phantoms plus the volumes found in `--data DIR`.
//! Clients name datasets; they never see server paths.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, Weak};

use voxlight_protocol::{
    DatasetDetails, DatasetInfo, Light, TfPoint, TransferFunction, default_lights,
};
use voxlight_volumes::{DatasetEntry, Volume, VolumeError};

/// Edge length of the built-in phantoms served to clients.
pub const PHANTOM_SIZE: u32 = 128;

/// The dataset opened when a client names none.
pub const DEFAULT_DATASET: &str = "phantom:cornell";

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("unknown dataset `{0}`")]
    Unknown(String),
    #[error("dataset `{name}` could not be loaded: {source}")]
    Load { name: String, source: VolumeError },
    #[error("data folder {0} does not exist or is not a folder")]
    NoDataDir(PathBuf),
    #[error(transparent)]
    DicomWeb(#[from] crate::dicomweb::DicomWebError),
}

/// What a volume must fit to be uploaded: the GPU's largest 3D texture edge and a share of the
/// GPU memory budget. A volume that does not fit is rendered from a box-filtered copy reduced
/// by the smallest integer factor that fits, and the viewer is told (`details.downsampled`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpuFit {
    pub max_dim: u32,
    pub max_bytes: u64,
    pub bytes_per_voxel: u64,
}

impl GpuFit {
    /// No limit (tests and tools that never upload).
    pub const UNLIMITED: GpuFit = GpuFit {
        max_dim: u32::MAX,
        max_bytes: u64::MAX,
        bytes_per_voxel: 1,
    };

    /// The smallest per-axis factor that makes `dims` fit, with what it did not fit; None when
    /// the volume fits as it is.
    pub fn reduction(&self, dims: [u32; 3]) -> Option<(u32, String)> {
        let bytes = |f: u32| {
            dims.iter()
                .map(|&d| d.div_ceil(f) as u64)
                .product::<u64>()
                .saturating_mul(self.bytes_per_voxel)
        };
        let fits = |f: u32| {
            dims.iter().all(|&d| d.div_ceil(f) <= self.max_dim) && bytes(f) <= self.max_bytes
        };
        if fits(1) {
            return None;
        }
        let reason = if dims.iter().any(|&d| d > self.max_dim) {
            format!(
                "this GPU takes 3D textures of at most {} per axis",
                self.max_dim
            )
        } else {
            format!(
                "it needs {} MiB of GPU memory and one volume may use {} MiB",
                bytes(1) >> 20,
                self.max_bytes >> 20
            )
        };
        let largest = dims.iter().copied().max().unwrap_or(1);
        (2..=largest.max(2)).find(|&f| fits(f)).map(|f| (f, reason))
    }
}

struct Entry {
    info: DatasetInfo,
    /// None for phantoms and remote series.
    path: Option<PathBuf>,
    /// A series of the DICOMweb source.
    remote: Option<crate::dicomweb::RemoteSeries>,
}

/// Every dataset by name, with loaded volumes shared while anyone uses them.
pub struct Catalog {
    entries: Vec<Entry>,
    fit: GpuFit,
    dicomweb: Option<crate::dicomweb::DicomWeb>,
    loaded: Mutex<HashMap<String, Weak<Volume>>>,
    details: Mutex<HashMap<String, DatasetDetails>>,
}

impl Catalog {
    /// The phantoms plus every volume under `data_dir`.
    pub fn new(data_dir: Option<&Path>, fit: GpuFit) -> Result<Self, DatasetError> {
        let mut entries: Vec<Entry> = voxlight_volumes::phantom_names()
            .iter()
            .map(|name| Entry {
                info: DatasetInfo {
                    name: format!("phantom:{name}"),
                    kind: "phantom".into(),
                    details: None,
                },
                path: None,
                remote: None,
            })
            .collect();
        if let Some(dir) = data_dir {
            if !dir.is_dir() {
                return Err(DatasetError::NoDataDir(dir.to_owned()));
            }
            let found =
                voxlight_volumes::scan_catalog(dir).map_err(|source| DatasetError::Load {
                    name: dir.display().to_string(),
                    source,
                })?;
            for DatasetEntry { name, path, kind } in found {
                entries.push(Entry {
                    info: DatasetInfo {
                        name,
                        kind,
                        details: None,
                    },
                    path: Some(path),
                    remote: None,
                });
            }
        }
        Ok(Self {
            entries,
            fit,
            dicomweb: None,
            loaded: Mutex::new(HashMap::new()),
            details: Mutex::new(HashMap::new()),
        })
    }

    /// Adds every series a DICOMweb endpoint lists (QIDO-RS, now; not refreshed later).
    pub fn with_dicomweb(
        mut self,
        source: crate::dicomweb::DicomWeb,
    ) -> Result<Self, DatasetError> {
        let series = source.list_series()?;
        tracing::info!(series = series.len(), "DICOMweb series listed");
        for remote in series {
            self.entries.push(Entry {
                info: DatasetInfo {
                    name: remote.dataset_name(),
                    kind: "dicomweb".into(),
                    details: None,
                },
                path: None,
                remote: Some(remote),
            });
        }
        self.dicomweb = Some(source);
        Ok(self)
    }

    pub fn contains(&self, name: &str) -> bool {
        self.entries.iter().any(|e| e.info.name == name)
    }

    /// Every dataset, with details for those loaded so far.
    pub fn list(&self) -> Vec<DatasetInfo> {
        self.entries
            .iter()
            .filter_map(|e| self.info(&e.info.name))
            .collect()
    }

    pub fn info(&self, name: &str) -> Option<DatasetInfo> {
        let entry = self.entries.iter().find(|e| e.info.name == name)?;
        let mut info = entry.info.clone();
        info.details = self.details.lock().ok().and_then(|d| d.get(name).cloned());
        Some(info)
    }

    /// Loads every dataset once (one at a time, dropping each volume again) so that its details
    /// are known. Blocking: run on its own thread.
    pub fn preload(&self) {
        // Remote series are fetched when someone opens them, never all at start-up.
        for entry in self.entries.iter().filter(|e| e.remote.is_none()) {
            let name = &entry.info.name;
            let known = self
                .details
                .lock()
                .map(|d| d.contains_key(name))
                .unwrap_or(true);
            if known {
                continue;
            }
            if let Err(e) = self.load(name) {
                tracing::warn!(dataset = %name, error = %e, "dataset could not be preloaded");
            }
        }
        tracing::info!(datasets = self.entries.len(), "dataset details preloaded");
    }

    /// Loads (or shares the already loaded) volume. Blocking: call from `spawn_blocking`.
    pub fn load(&self, name: &str) -> Result<Arc<Volume>, DatasetError> {
        self.load_with_progress(name, &|_, _| {})
    }

    /// Fetches a remote series into a private temporary folder (reporting instances fetched
    /// of the total) and reads it as a local series; the folder goes when this returns.
    fn load_remote(
        &self,
        remote: &crate::dicomweb::RemoteSeries,
        name: &str,
        progress: &(dyn Fn(u32, u32) + Sync),
    ) -> Result<Volume, DatasetError> {
        let source = self
            .dicomweb
            .as_ref()
            .ok_or_else(|| DatasetError::Unknown(name.to_owned()))?;
        let load_error = |source| DatasetError::Load {
            name: name.to_owned(),
            source,
        };
        let folder = tempfile::Builder::new()
            .prefix("voxlight-dicomweb-")
            .tempdir()
            .map_err(|e| {
                load_error(VolumeError::Io {
                    path: std::env::temp_dir(),
                    what: "making a folder for the fetched series".into(),
                    source: e,
                })
            })?;
        let started = std::time::Instant::now();
        let files = source.fetch_series(remote, folder.path(), progress)?;
        tracing::info!(
            dataset = name,
            files,
            ms = started.elapsed().as_millis() as u64,
            "DICOMweb series fetched"
        );
        let mut volume = voxlight_volumes::load(folder.path()).map_err(load_error)?;
        without_folder(&mut volume.warnings, folder.path());
        Ok(volume)
    }

    /// `load`, calling `progress(done, total)` while a remote series arrives (instances).
    pub fn load_with_progress(
        &self,
        name: &str,
        progress: &(dyn Fn(u32, u32) + Sync),
    ) -> Result<Arc<Volume>, DatasetError> {
        let entry = self
            .entries
            .iter()
            .find(|e| e.info.name == name)
            .ok_or_else(|| DatasetError::Unknown(name.to_owned()))?;
        if let Some(volume) = self
            .loaded
            .lock()
            .ok()
            .and_then(|l| l.get(name).and_then(Weak::upgrade))
        {
            return Ok(volume);
        }
        let started = std::time::Instant::now();
        let load_error = |source| DatasetError::Load {
            name: name.to_owned(),
            source,
        };
        let mut volume = match (&entry.path, &entry.remote) {
            (Some(path), _) => {
                let mut volume = voxlight_volumes::load(path).map_err(load_error)?;
                if let Some(folder) = path.parent() {
                    without_folder(&mut volume.warnings, folder);
                }
                volume
            }
            (None, Some(remote)) => self.load_remote(remote, name, progress)?,
            (None, None) => {
                voxlight_volumes::phantom(name.trim_start_matches("phantom:"), PHANTOM_SIZE)
                    .map_err(load_error)?
            }
        };
        volume.name = name.to_owned();
        let downsampled = self.fit.reduction(volume.dims).map(|(factor, reason)| {
            let original_dims = volume.dims;
            let mut reduced = volume.downsampled_by(factor);
            reduced.format = volume.format.clone();
            let [a, b, c] = original_dims;
            let [x, y, z] = reduced.dims;
            reduced.warnings.push(format!(
                "shown downsampled {factor}× per axis, {a}×{b}×{c} → {x}×{y}×{z} voxels: {reason}; \
                 detail finer than {factor} voxels is averaged away"
            ));
            tracing::warn!(dataset = name, factor, ?original_dims, %reason, "volume downsampled to fit the GPU");
            volume = reduced;
            voxlight_protocol::Downsampled {
                factor,
                original_dims,
                reason,
            }
        });
        tracing::info!(
            dataset = name,
            dims = ?volume.dims,
            ms = started.elapsed().as_millis() as u64,
            warnings = volume.warnings.len(),
            "dataset loaded"
        );
        let volume = Arc::new(volume);
        if let Ok(mut details) = self.details.lock() {
            let mut info = details_of(&volume);
            info.downsampled = downsampled;
            details.insert(name.to_owned(), info);
        }
        if let Ok(mut loaded) = self.loaded.lock() {
            loaded.insert(name.to_owned(), Arc::downgrade(&volume));
        }
        Ok(volume)
    }
}

/// Loader warnings as viewers may read them: `folder` (a server path) left out of every file
/// path, the names below it kept (clients never see server paths).
fn without_folder(warnings: &mut [String], folder: &Path) {
    let prefix = format!("{}{}", folder.display(), std::path::MAIN_SEPARATOR);
    for warning in warnings.iter_mut().filter(|w| w.contains(&prefix)) {
        *warning = warning.replace(&prefix, "");
    }
}

pub fn details_of(volume: &Volume) -> DatasetDetails {
    DatasetDetails {
        dims: volume.dims,
        spacing: volume.spacing,
        value_min: volume.value_min,
        value_max: volume.value_max,
        units: volume.units.clone(),
        modality: volume.modality.clone(),
        format: volume.format.clone(),
        world_extent: volume.world_extent(),
        histogram: volume.histogram.clone(),
        warnings: volume.warnings.clone(),
        downsampled: None,
    }
}

fn point(value: f64, color: [f32; 3], opacity: f32) -> TfPoint {
    TfPoint {
        value: value.clamp(0.0, 1.0) as f32,
        color,
        opacity,
    }
}

/// A transfer function that shows something sensible for a dataset before anyone edits it.
pub fn default_tf(volume: &Volume) -> TransferFunction {
    let range = (volume.value_max - volume.value_min).max(f64::EPSILON);
    let norm = |raw: f64| (raw - volume.value_min) / range;
    if volume.units == "HU" {
        // Soft tissue faint and reddish, bone dense and ivory.
        let points = vec![
            point(norm(-200.0), [0.8, 0.5, 0.4], 0.0),
            point(norm(0.0), [0.85, 0.45, 0.38], 0.012),
            point(norm(150.0), [0.9, 0.6, 0.5], 0.03),
            point(norm(300.0), [0.95, 0.9, 0.8], 0.35),
            point(norm(1200.0), [1.0, 0.97, 0.9], 1.0),
        ];
        return TransferFunction { points };
    }
    if volume.name == "phantom:cornell" {
        return cornell_tf();
    }
    // Generic: ramp over the upper half of the non-background values.
    let hist = &volume.histogram;
    let background = hist.iter().take(13).map(|&c| c as u64).sum::<u64>();
    let total: u64 = hist.iter().map(|&c| c as u64).sum();
    let foreground = total - background;
    let mut seen = 0u64;
    let mut median_bin = 128;
    for (bin, &count) in hist.iter().enumerate().skip(13) {
        seen += count as u64;
        if seen * 2 >= foreground {
            median_bin = bin;
            break;
        }
    }
    let start = median_bin as f64 / 256.0 * 0.8;
    TransferFunction {
        points: vec![
            point(start, [0.9, 0.8, 0.7], 0.0),
            point(1.0, [1.0, 0.95, 0.9], 0.8),
        ],
    }
}

/// Colours the Cornell phantom's materials like Fig. 4 of the historygram paper.
pub fn cornell_tf() -> TransferFunction {
    let mut points = Vec::new();
    for (name, value) in voxlight_volumes::CORNELL_MATERIALS {
        let name = name.to_ascii_lowercase();
        let (color, opacity) = if name.contains("red") || name.contains("left") {
            ([0.85, 0.1, 0.08], 1.0)
        } else if name.contains("green") || name.contains("right") {
            ([0.1, 0.75, 0.12], 1.0)
        } else if name.contains("medium") || name.contains("fog") || name.contains("air") {
            ([0.9, 0.9, 0.9], 0.008)
        } else if name.contains("empty") || name.contains("vacuum") {
            ([0.0, 0.0, 0.0], 0.0)
        } else {
            ([0.85, 0.85, 0.85], 1.0)
        };
        let v = *value as f64;
        // A narrow plateau per material so trilinear blends between materials stay distinct.
        points.push(point(v - 0.03, color, opacity));
        points.push(point(v + 0.03, color, opacity));
    }
    points.sort_by(|a, b| a.value.total_cmp(&b.value));
    // Transparent below the first material (the empty value 0 never occurs inside the box).
    if let Some(&first) = points.first().filter(|p| p.value > 0.0) {
        points.splice(
            0..0,
            [
                point(0.0, [0.0; 3], 0.0),
                TfPoint {
                    opacity: 0.0,
                    ..first
                },
            ],
        );
    }
    TransferFunction { points }
}

/// Lights that show a dataset well: the default key light and environment, except for the
/// Cornell box, whose ceiling would shadow a light from above: it gets a point light under
/// the ceiling, as in the historygram paper's Cornell scene.
pub fn default_lights_for(volume: &Volume) -> Vec<Light> {
    if volume.name.starts_with("phantom:cornell") {
        let extent = volume.world_extent();
        return vec![
            Light::Point {
                position: [0.0, -0.05 * extent[1], 0.36 * extent[2]],
                intensity: [0.9, 0.85, 0.8],
            },
            Light::Environment {
                radiance: [0.08, 0.08, 0.09],
            },
        ];
    }
    default_lights()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_lose_the_server_folder_and_keep_file_names() {
        let mut warnings = vec![
            "skipped 1 file: /srv/data/ct/notes.txt: not DICOM".to_owned(),
            "spacing not uniform".to_owned(),
        ];
        without_folder(&mut warnings, Path::new("/srv/data"));
        assert_eq!(warnings[0], "skipped 1 file: ct/notes.txt: not DICOM");
        assert_eq!(warnings[1], "spacing not uniform");
    }

    #[test]
    fn a_volume_that_fits_is_left_alone() {
        let fit = GpuFit {
            max_dim: 2048,
            max_bytes: 1 << 30,
            bytes_per_voxel: 2,
        };
        assert_eq!(fit.reduction([512, 512, 128]), None);
        assert_eq!(GpuFit::UNLIMITED.reduction([100_000, 3, 3]), None);
    }

    #[test]
    fn the_smallest_factor_that_fits_is_chosen() {
        let edge = GpuFit {
            max_dim: 2048,
            max_bytes: u64::MAX,
            bytes_per_voxel: 2,
        };
        let (f, why) = edge.reduction([512, 512, 4097]).unwrap();
        assert_eq!(f, 3, "4097 / 2 rounds up to 2049 > 2048");
        assert!(why.contains("2048 per axis"), "{why}");
        // 1024³ × 2 B = 2 GiB; half a GiB allowed: 2× per axis (256 MiB) is the first fit.
        let budget = GpuFit {
            max_dim: 4096,
            max_bytes: 512 << 20,
            bytes_per_voxel: 2,
        };
        let (f, why) = budget.reduction([1024, 1024, 1024]).unwrap();
        assert_eq!(f, 2);
        assert!(why.contains("2048 MiB") && why.contains("512 MiB"), "{why}");
        let (f, _) = budget.reduction([1025, 1024, 1024]).unwrap();
        assert_eq!(f, 2, "ceil(1025 / 2) = 513: 513×512×512×2 B still fits");
    }
}
