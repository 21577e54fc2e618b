//! Shared by the loader targets: a scratch folder (in memory where possible), the checks every
//! loaded volume must pass, and what the server derives from a volume before a viewer sees it.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use voxlight_protocol::DatasetDetails;
use voxlight_volumes::{Volume, VolumeError};

/// A folder for the files a target writes, made once per process: `voxlight-fuzz-*` in
/// /dev/shm (or the temp folder). libFuzzer exits without dropping it: remove them after a
/// campaign.
pub fn scratch() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let shm = Path::new("/dev/shm");
        let parent = if shm.is_dir() {
            shm.to_owned()
        } else {
            std::env::temp_dir()
        };
        tempfile::Builder::new()
            .prefix("voxlight-fuzz-")
            .tempdir_in(parent)
            .expect("scratch folder")
    })
    .path()
}

/// Writes `bytes` to `name` in the scratch folder.
pub fn write(name: &str, bytes: &[u8]) -> PathBuf {
    let path = scratch().join(name);
    std::fs::write(&path, bytes).expect("writing a scratch file");
    path
}

/// Loads `path` the way the server does and checks what it got.
pub fn load_and_check(path: &Path) {
    match voxlight_volumes::load(path) {
        Ok(volume) => check_volume(&volume),
        Err(error) => check_error(&error),
    }
}

pub fn check_error(error: &VolumeError) {
    assert!(!error.to_string().is_empty());
}

/// Invariants of a loaded volume, and of what the server makes of it (default TF and lights,
/// the details sent in `welcome`).
pub fn check_volume(volume: &Volume) {
    let voxels: u64 = volume.dims.iter().map(|&d| d as u64).product();
    assert!(voxels > 0 && voxels <= voxlight_volumes::MAX_VOXELS);
    assert_eq!(volume.data.len() as u64, voxels);
    assert_eq!(
        volume.histogram.iter().map(|&c| c as u64).sum::<u64>(),
        voxels
    );
    assert!(
        volume.spacing.iter().all(|s| s.is_finite() && *s > 0.0),
        "spacing {:?}",
        volume.spacing
    );
    assert!(volume.value_min.is_finite() && volume.value_max.is_finite());
    assert!(volume.value_min <= volume.value_max);
    assert!(
        volume
            .world_extent()
            .iter()
            .all(|e| e.is_finite() && *e > 0.0 && *e <= 1.0),
        "world extent {:?}",
        volume.world_extent()
    );
    let tf = voxlight_app::datasets::default_tf(volume);
    voxlight_engine::tf::validate(&tf).expect("the default TF of a loaded volume is valid");
    let lights = voxlight_app::datasets::default_lights_for(volume);
    voxlight_engine::scene::validate_lights(&lights).expect("default lights are valid");
    // What a viewer receives must parse again.
    let details = voxlight_app::datasets::details_of(volume);
    let json = serde_json::to_string(&details).expect("details serialize");
    let back: DatasetDetails = serde_json::from_str(&json).expect("details parse back");
    assert_eq!(back.dims, details.dims);
    // A reduced copy keeps the invariants.
    let small = volume.downsampled(8);
    assert!(small.dims.iter().all(|&d| (1..=8).contains(&d)));
    assert_eq!(
        small.data.len(),
        small.dims.iter().map(|&d| d as usize).product::<usize>()
    );
}
