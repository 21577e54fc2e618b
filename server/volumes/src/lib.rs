//! voxlight-volumes: volume loaders (DICOM series, NRRD, NIfTI-1, VTK `.vti`, raw),
//! procedural phantoms, normalization to [0, 1] and histograms. CPU only.
//!
//! Every loader produces a [`RawVolume`] (samples in their stored type, x fastest), which
//! [`RawVolume::normalize`] turns into a [`Volume`] (`u16` normalized data plus the original
//! value range). Malformed input gives a [`VolumeError`], never a panic, and sizes are checked
//! against [`MAX_VOXELS`] before anything is allocated.

#![warn(missing_docs)]

mod catalog;
mod dicom;
mod error;
mod jpeg12;
mod nifti;
mod nrrd;
mod phantom;
mod raw;
pub mod testdata;
mod volume;
mod vti;

use std::io::Read;
use std::path::Path;

pub use catalog::{DatasetEntry, MAX_SCAN_DEPTH, scan_catalog};
pub use error::VolumeError;
pub use phantom::{CORNELL_MATERIALS, MAX_PHANTOM_SIZE, phantom, phantom_names};
pub use raw::{Endian, MAX_SPACING_RATIO, RawVolume, SampleType, Samples, load_raw_file};
pub use volume::{HISTOGRAM_BINS, Volume, compute_histogram, histogram_bin};

/// Largest number of voxels any loader accepts (2³¹, e.g. 2048 × 1024 × 1024). Checked
/// against the declared dimensions before allocating.
pub const MAX_VOXELS: u64 = 1 << 31;

/// Which loader handles a path.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    DicomDir,
    DicomFile,
    Nrrd,
    Nifti,
    Vti,
    Raw,
}

fn sniff(path: &Path) -> Option<Kind> {
    let mut b = [0u8; 348];
    let f = std::fs::File::open(path).ok()?;
    let mut r = f.take(b.len() as u64);
    let mut got = 0;
    while got < b.len() {
        match r.read(&mut b[got..]) {
            Ok(0) | Err(_) => break,
            Ok(n) => got += n,
        }
    }
    let b = &b[..got];
    if b.starts_with(b"NRRD000") {
        return Some(Kind::Nrrd);
    }
    if b.len() >= 132 && &b[128..132] == b"DICM" {
        return Some(Kind::DicomFile);
    }
    let head = String::from_utf8_lossy(&b[..b.len().min(256)]);
    if head.contains("<VTKFile") {
        return Some(Kind::Vti);
    }
    if b.len() >= 348 {
        let le = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let be = i32::from_be_bytes([b[0], b[1], b[2], b[3]]);
        if (le == 348 || be == 348) && (&b[344..348] == b"n+1\0" || &b[344..348] == b"ni1\0") {
            return Some(Kind::Nifti);
        }
    }
    None
}

fn detect(path: &Path) -> Result<Kind, VolumeError> {
    let meta =
        std::fs::metadata(path).map_err(|e| VolumeError::io(path, "opening the volume", e))?;
    if meta.is_dir() {
        return Ok(Kind::DicomDir);
    }
    if !meta.is_file() {
        // A device or pipe (e.g. a link to /dev/zero) never ends: reading it would not either.
        return Err(VolumeError::unsupported(
            path,
            "not a regular file or folder (a device or pipe cannot be a volume)",
        ));
    }
    if let Some(k) = catalog::kind_by_name(path) {
        return Ok(match k {
            "nrrd" => Kind::Nrrd,
            "nifti" => Kind::Nifti,
            _ => Kind::Vti,
        });
    }
    let lower = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if lower.ends_with(".dcm") {
        return Ok(Kind::DicomFile);
    }
    if lower.ends_with(".hdr") || lower.ends_with(".hdr.gz") {
        return Ok(Kind::Nifti);
    }
    if let Some(k) = sniff(path) {
        return Ok(k);
    }
    if lower.ends_with(".raw") {
        return Ok(Kind::Raw);
    }
    Err(VolumeError::UnknownFormat {
        path: path.to_path_buf(),
    })
}

/// Loads a volume without normalizing. The format is detected from the path: a directory is a
/// DICOM series; `.dcm` a single DICOM slice; `.nrrd` / `.nhdr` NRRD; `.nii` / `.nii.gz` (and
/// `.hdr`) NIfTI-1; `.vti` VTK ImageData; other names are recognised by their first bytes.
pub fn load_raw(path: &Path) -> Result<RawVolume, VolumeError> {
    match detect(path)? {
        Kind::DicomDir => dicom::load_dicom_dir(path),
        Kind::DicomFile => dicom::load_dicom_files(path, &[path.to_path_buf()]),
        Kind::Nrrd => nrrd::load_nrrd(path),
        Kind::Nifti => nifti::load_nifti(path),
        Kind::Vti => vti::load_vti(path),
        Kind::Raw => Err(VolumeError::unsupported(
            path,
            "a .raw file has no header: use load_raw_file with explicit dims and sample type, or \
             a .nhdr header that points to it",
        )),
    }
}

/// A dataset name for a path: the file name without volume extensions (`.nii.gz`, `.nrrd`, ...),
/// or the folder name for a DICOM series.
pub fn default_name(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string());
    let lower = name.to_ascii_lowercase();
    for ext in [
        ".nii.gz", ".hdr.gz", ".nrrd", ".nhdr", ".nii", ".vti", ".dcm", ".hdr", ".raw",
    ] {
        if lower.ends_with(ext) && lower.len() > ext.len() {
            return name[..name.len() - ext.len()].to_string();
        }
    }
    name
}

/// Loads and normalizes a volume ([`load_raw`] + [`RawVolume::normalize`]), named by
/// [`default_name`].
///
/// NRRD, NIfTI and VTI samples that are not 16-bit (and rescaled NIfTI) are read straight to 16
/// bits (8-bit ones widened in one pass, wider ones read twice: their range, then their
/// quantization), so the peak memory is the 16-bit volume and not the samples beside it; the
/// result equals [`load_raw`] + [`RawVolume::normalize`] exactly.
pub fn load(path: &Path) -> Result<Volume, VolumeError> {
    let name = default_name(path);
    let (raw, streamed) = match detect(path)? {
        Kind::Nrrd => nrrd::load_nrrd_with(path, true)?,
        Kind::Nifti => nifti::load_nifti_with(path, true)?,
        Kind::Vti => vti::load_vti_with(path, true)?,
        _ => (load_raw(path)?, None),
    };
    Ok(match streamed {
        Some(s) => volume::assemble(raw, s.data, s.range, &name),
        None => raw.normalize(&name),
    })
}
