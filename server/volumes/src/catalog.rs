//! Cheap discovery of datasets under a folder (no decoding).

use std::path::{Path, PathBuf};

use crate::VolumeError;
use crate::dicom::looks_like_dicom;

/// How deep [`scan_catalog`] descends below the root folder.
pub const MAX_SCAN_DEPTH: usize = 4;

/// One dataset found by [`scan_catalog`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetEntry {
    /// Path relative to the scanned folder, with forward slashes (e.g. `vti/bonsai.vti`).
    pub name: String,
    /// Absolute or caller-relative path to pass to [`crate::load`].
    pub path: PathBuf,
    /// `"dicom"`, `"nrrd"`, `"nifti"` or `"vti"`.
    pub kind: String,
}

/// Kind of a volume file by its name (`None` for anything else, including `.raw`).
pub(crate) fn kind_by_name(path: &Path) -> Option<&'static str> {
    let name = path.file_name()?.to_str()?.to_ascii_lowercase();
    if name.ends_with(".nrrd") || name.ends_with(".nhdr") {
        Some("nrrd")
    } else if name.ends_with(".nii") || name.ends_with(".nii.gz") {
        Some("nifti")
    } else if name.ends_with(".vti") {
        Some("vti")
    } else {
        None
    }
}

fn rel_name(root: &Path, p: &Path) -> String {
    let rel = p.strip_prefix(root).unwrap_or(p);
    let parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if parts.is_empty() {
        root.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| ".".to_string())
    } else {
        parts.join("/")
    }
}

/// Lists the datasets under `dir` (recursively, at most [`MAX_SCAN_DEPTH`] levels, hidden
/// entries skipped): each folder holding DICOM files is one `dicom` dataset (not descended
/// further); every `.nrrd`, `.nhdr`, `.nii`, `.nii.gz` and `.vti` file is one dataset.
/// Sorted by name.
pub fn scan_catalog(dir: &Path) -> Result<Vec<DatasetEntry>, VolumeError> {
    let meta = std::fs::metadata(dir)
        .map_err(|e| VolumeError::io(dir, "opening the catalog folder", e))?;
    if !meta.is_dir() {
        return Err(VolumeError::format(dir, "catalog path is not a folder"));
    }
    let mut out = Vec::new();
    scan(dir, dir, 0, &mut out)?;
    out.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(out)
}

fn scan(
    root: &Path,
    dir: &Path,
    depth: usize,
    out: &mut Vec<DatasetEntry>,
) -> Result<(), VolumeError> {
    let rd = match std::fs::read_dir(dir) {
        Ok(rd) => rd,
        Err(e) if depth == 0 => return Err(VolumeError::io(dir, "listing the catalog folder", e)),
        Err(e) => {
            tracing::warn!("catalog: cannot list {}: {e}", dir.display());
            return Ok(());
        }
    };
    let mut files = Vec::new();
    let mut dirs = Vec::new();
    for ent in rd.flatten() {
        if ent.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        let p = ent.path();
        match std::fs::metadata(&p) {
            Ok(m) if m.is_dir() => dirs.push(p),
            Ok(m) if m.is_file() => files.push(p),
            _ => {}
        }
    }
    files.sort();
    dirs.sort();
    let mut volume_files = Vec::new();
    let mut has_dicom = false;
    for f in &files {
        if let Some(kind) = kind_by_name(f) {
            volume_files.push((f, kind));
        } else if !has_dicom && looks_like_dicom(f) {
            has_dicom = true;
        }
    }
    if has_dicom {
        out.push(DatasetEntry {
            name: rel_name(root, dir),
            path: dir.to_path_buf(),
            kind: "dicom".to_string(),
        });
    }
    for (f, kind) in volume_files {
        out.push(DatasetEntry {
            name: rel_name(root, f),
            path: f.clone(),
            kind: kind.to_string(),
        });
    }
    if has_dicom || depth >= MAX_SCAN_DEPTH {
        return Ok(());
    }
    for d in dirs {
        scan(root, &d, depth + 1, out)?;
    }
    Ok(())
}
