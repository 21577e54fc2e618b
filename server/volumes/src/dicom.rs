//! DICOM series loader (one slice per file, uncompressed transfer syntaxes), built on
//! `dicom-object`. Slices are grouped by SeriesInstanceUID and sorted along the slice normal.
//!
//! Privacy: warnings and format strings name files and geometry only, never patient data.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::file::ReadPreamble;
use dicom_object::{DefaultDicomObject, OpenFileOptions};

use crate::VolumeError;
use crate::raw::{RawVolume, Samples, check_dims, check_spacing};

/// Most individual problems listed in one warning before it says "and N more".
const MAX_LISTED: usize = 5;

/// True when the file looks like DICOM: `.dcm` extension or `DICM` at byte 128.
pub(crate) fn looks_like_dicom(path: &Path) -> bool {
    let ext_dcm = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("dcm"));
    ext_dcm || has_dicm_magic(path)
}

/// True when bytes 128..132 of the file are `DICM`.
pub(crate) fn has_dicm_magic(path: &Path) -> bool {
    let Ok(f) = std::fs::File::open(path) else {
        return false;
    };
    let mut b = [0u8; 132];
    let mut r = f.take(132);
    let mut got = 0;
    while got < 132 {
        match r.read(&mut b[got..]) {
            Ok(0) | Err(_) => break,
            Ok(n) => got += n,
        }
    }
    got == 132 && &b[128..132] == b"DICM"
}

fn ts_name(uid: &str) -> Option<&'static str> {
    Some(match uid {
        "1.2.840.10008.1.2" => "Implicit VR Little Endian",
        "1.2.840.10008.1.2.1" => "Explicit VR Little Endian",
        "1.2.840.10008.1.2.2" => "Explicit VR Big Endian",
        "1.2.840.10008.1.2.1.99" => "Deflated Explicit VR Little Endian",
        _ => return None,
    })
}

fn compressed_ts_name(uid: &str) -> &'static str {
    match uid {
        "1.2.840.10008.1.2.4.50" => "JPEG Baseline",
        "1.2.840.10008.1.2.4.51" => "JPEG Extended",
        "1.2.840.10008.1.2.4.57" | "1.2.840.10008.1.2.4.70" => "JPEG Lossless",
        "1.2.840.10008.1.2.4.80" | "1.2.840.10008.1.2.4.81" => "JPEG-LS",
        "1.2.840.10008.1.2.4.90" | "1.2.840.10008.1.2.4.91" => "JPEG 2000",
        "1.2.840.10008.1.2.5" => "RLE Lossless",
        _ => "unknown or compressed",
    }
}

/// Header facts of one slice file (no pixel data).
#[derive(Debug, Clone)]
struct SliceInfo {
    path: PathBuf,
    series: String,
    ts: String,
    rows: u32,
    cols: u32,
    bits_alloc: u16,
    bits_stored: u16,
    signed: bool,
    ipp: Option<[f64; 3]>,
    iop: Option<[f64; 6]>,
    pixel_spacing: Option<[f64; 2]>,
    slice_thickness: Option<f64>,
    slope: f64,
    intercept: f64,
    modality: String,
    instance: Option<i64>,
    samples_per_pixel: u16,
    frames: u32,
    pixel: PixelData,
}

/// Where a file's PixelData element is, as found by [`prescan`].
#[derive(Debug, Clone, Copy, PartialEq)]
enum PixelData {
    Absent,
    /// Native pixel data: byte offset and length of the value.
    Native {
        offset: usize,
        len: usize,
    },
    /// Encapsulated (compressed) fragments.
    Encapsulated,
}

struct Prescan {
    ts: String,
    pixel: PixelData,
}

const UNDEFINED: u32 = 0xFFFF_FFFF;

fn rd16(b: &[u8], at: usize, big: bool) -> Option<u16> {
    let s = b.get(at..at + 2)?;
    Some(if big {
        u16::from_be_bytes([s[0], s[1]])
    } else {
        u16::from_le_bytes([s[0], s[1]])
    })
}

fn rd32(b: &[u8], at: usize, big: bool) -> Option<u32> {
    let s = b.get(at..at + 4)?;
    let a = [s[0], s[1], s[2], s[3]];
    Some(if big {
        u32::from_be_bytes(a)
    } else {
        u32::from_le_bytes(a)
    })
}

/// Explicit-VR codes whose header has 2 reserved bytes and a 4-byte length.
const LONG_VRS: &[&[u8; 2]] = &[
    b"OB", b"OD", b"OF", b"OL", b"OV", b"OW", b"SQ", b"SV", b"UC", b"UN", b"UR", b"UT", b"UV",
];
const SHORT_VRS: &[&[u8; 2]] = &[
    b"AE", b"AS", b"AT", b"CS", b"DA", b"DS", b"DT", b"FL", b"FD", b"IS", b"LO", b"LT", b"PN",
    b"SH", b"SL", b"SS", b"ST", b"TM", b"UI", b"UL", b"US",
];

/// Walks every element header of a Part-10 file (descending into sequences and items) and
/// checks that each declared length fits in the file, so that the DICOM parser is never asked
/// to allocate for data that is not there. Also locates the PixelData value.
fn prescan(b: &[u8]) -> Result<Prescan, String> {
    use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry, VirtualVr};
    if b.len() < 132 || &b[128..132] != b"DICM" {
        return Err("not a DICOM file (no DICM marker at byte 128)".into());
    }
    let trunc = |pos: usize| format!("truncated element header at byte {pos}");
    let mut pos = 132;
    let mut ts: Option<String> = None;
    // File meta group: always explicit VR little endian.
    while rd16(b, pos, false) == Some(0x0002) {
        let elem = rd16(b, pos + 2, false).ok_or_else(|| trunc(pos))?;
        let vr = b.get(pos + 4..pos + 6).ok_or_else(|| trunc(pos))?;
        let (len, hdr) = if LONG_VRS.iter().any(|v| &v[..] == vr) {
            (
                rd32(b, pos + 8, false).ok_or_else(|| trunc(pos))? as usize,
                12,
            )
        } else {
            (
                rd16(b, pos + 6, false).ok_or_else(|| trunc(pos))? as usize,
                8,
            )
        };
        let start = pos + hdr;
        let val = b.get(start..start.saturating_add(len)).ok_or_else(|| {
            format!("file meta element (0002,{elem:04X}) declares {len} bytes at byte {start}, beyond the end of the file ({} bytes)", b.len())
        })?;
        if elem == 0x0010 {
            ts = Some(
                String::from_utf8_lossy(val)
                    .trim_end_matches(['\0', ' '])
                    .to_string(),
            );
        }
        pos = start + len;
    }
    let ts = ts.ok_or("file meta information has no TransferSyntaxUID")?;
    let (implicit, big) = match ts.as_str() {
        "1.2.840.10008.1.2" => (true, false),
        "1.2.840.10008.1.2.2" => (false, true),
        "1.2.840.10008.1.2.1.99" => return Err("deflated transfer syntax is not supported".into()),
        _ => (false, false),
    };
    let dict = dicom_dictionary_std::StandardDataDictionary;
    let mut pixel = PixelData::Absent;
    let mut encapsulated = false;
    while pos < b.len() {
        let g = rd16(b, pos, big).ok_or_else(|| trunc(pos))?;
        let e = rd16(b, pos + 2, big).ok_or_else(|| trunc(pos))?;
        if g == 0xFFFE {
            let len = rd32(b, pos + 4, big).ok_or_else(|| trunc(pos))?;
            pos += 8;
            if e == 0xE000 && len != UNDEFINED {
                let end = pos.checked_add(len as usize).filter(|&x| x <= b.len()).ok_or_else(|| {
                    format!("item at byte {pos} declares {len} bytes, beyond the end of the file ({} bytes)", b.len())
                })?;
                if encapsulated {
                    pos = end;
                }
            } else if e == 0xE0DD {
                encapsulated = false;
            }
            continue;
        }
        let (len, hdr, is_sq) = if implicit {
            let len = rd32(b, pos + 4, big).ok_or_else(|| trunc(pos))?;
            let sq = dict
                .by_tag(Tag(g, e))
                .map(|d| d.vr() == VirtualVr::Exact(dicom_core::VR::SQ))
                .unwrap_or(false)
                || (len != UNDEFINED
                    && rd16(b, pos + 8, big) == Some(0xFFFE)
                    && rd16(b, pos + 10, big) == Some(0xE000));
            (len, 8, sq)
        } else {
            let vr = b.get(pos + 4..pos + 6).ok_or_else(|| trunc(pos))?;
            if LONG_VRS.iter().any(|v| &v[..] == vr) {
                let len = rd32(b, pos + 8, big).ok_or_else(|| trunc(pos))?;
                if vr == b"UN" && len == UNDEFINED {
                    return Err(format!(
                        "element ({g:04X},{e:04X}) is UN with undefined length; not supported"
                    ));
                }
                (len, 12, vr == b"SQ")
            } else if SHORT_VRS.iter().any(|v| &v[..] == vr) {
                (
                    rd16(b, pos + 6, big).ok_or_else(|| trunc(pos))? as u32,
                    8,
                    false,
                )
            } else {
                return Err(format!(
                    "element ({g:04X},{e:04X}) at byte {pos} has an invalid value representation {:?}",
                    String::from_utf8_lossy(vr)
                ));
            }
        };
        pos += hdr;
        let is_pixel = g == 0x7FE0 && e == 0x0010;
        if len == UNDEFINED {
            if is_pixel {
                encapsulated = true;
                pixel = PixelData::Encapsulated;
            }
            continue;
        }
        let end = pos.checked_add(len as usize).filter(|&x| x <= b.len()).ok_or_else(|| {
            format!(
                "element ({g:04X},{e:04X}) declares {len} bytes at byte {pos}, but the file has only {} left",
                b.len() - pos.min(b.len())
            )
        })?;
        if is_pixel {
            pixel = PixelData::Native {
                offset: pos,
                len: len as usize,
            };
        }
        if !is_sq {
            pos = end;
        }
    }
    Ok(Prescan { ts, pixel })
}

fn fname(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

fn get_str(obj: &DefaultDicomObject, tag: Tag) -> Option<String> {
    let e = obj.element_opt(tag).ok()??;
    let s = e.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    Some(s.to_string())
}

fn get_f64s(obj: &DefaultDicomObject, tag: Tag) -> Option<Vec<f64>> {
    let e = obj.element_opt(tag).ok()??;
    e.to_multi_float64().ok()
}

fn get_int(obj: &DefaultDicomObject, tag: Tag) -> Option<i64> {
    let e = obj.element_opt(tag).ok()??;
    e.to_int::<i64>().ok()
}

fn short_err(e: impl std::fmt::Display) -> String {
    let s = e.to_string();
    if s.len() > 160 {
        let mut cut = 160;
        while !s.is_char_boundary(cut) {
            cut -= 1;
        }
        format!("{}…", &s[..cut])
    } else {
        s
    }
}

/// Reads the header of one file; `Err(reason)` means "skip this file".
fn read_info(path: &Path) -> Result<SliceInfo, String> {
    if !has_dicm_magic(path) {
        return Err("not a DICOM file (no DICM marker at byte 128)".into());
    }
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read: {e}"))?;
    let scan = prescan(&bytes)?;
    let obj = OpenFileOptions::new()
        .read_preamble(ReadPreamble::Always)
        .read_until(tags::PIXEL_DATA)
        .from_reader(&bytes[..])
        .map_err(|e| format!("not a readable DICOM file ({})", short_err(e)))?;
    drop(bytes);
    let ts = scan.ts;
    let rows = get_int(&obj, tags::ROWS);
    let cols = get_int(&obj, tags::COLUMNS);
    let (Some(rows), Some(cols)) = (rows, cols) else {
        return Err("no image (Rows/Columns missing)".into());
    };
    if rows <= 0 || cols <= 0 || rows > u32::MAX as i64 || cols > u32::MAX as i64 {
        return Err(format!("invalid image size Rows={rows} Columns={cols}"));
    }
    let arr3 = |v: Vec<f64>| -> Option<[f64; 3]> { (v.len() >= 3).then(|| [v[0], v[1], v[2]]) };
    let finite = |v: &Vec<f64>| v.iter().all(|x| x.is_finite());
    Ok(SliceInfo {
        path: path.to_path_buf(),
        series: get_str(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default(),
        ts,
        rows: rows as u32,
        cols: cols as u32,
        bits_alloc: get_int(&obj, tags::BITS_ALLOCATED)
            .unwrap_or(16)
            .clamp(0, 64) as u16,
        bits_stored: get_int(&obj, tags::BITS_STORED).unwrap_or(0).clamp(0, 64) as u16,
        signed: get_int(&obj, tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1,
        ipp: get_f64s(&obj, tags::IMAGE_POSITION_PATIENT)
            .filter(finite)
            .and_then(arr3),
        iop: get_f64s(&obj, tags::IMAGE_ORIENTATION_PATIENT)
            .filter(finite)
            .and_then(|v| (v.len() >= 6).then(|| [v[0], v[1], v[2], v[3], v[4], v[5]])),
        pixel_spacing: get_f64s(&obj, tags::PIXEL_SPACING)
            .and_then(|v| (v.len() >= 2).then(|| [v[0], v[1]])),
        slice_thickness: get_f64s(&obj, tags::SLICE_THICKNESS).and_then(|v| v.first().copied()),
        slope: get_f64s(&obj, tags::RESCALE_SLOPE)
            .and_then(|v| v.first().copied())
            .filter(|s| s.is_finite() && *s != 0.0)
            .unwrap_or(1.0),
        intercept: get_f64s(&obj, tags::RESCALE_INTERCEPT)
            .and_then(|v| v.first().copied())
            .filter(|s| s.is_finite())
            .unwrap_or(0.0),
        modality: get_str(&obj, tags::MODALITY).unwrap_or_default(),
        instance: get_int(&obj, tags::INSTANCE_NUMBER),
        samples_per_pixel: get_int(&obj, tags::SAMPLES_PER_PIXEL)
            .unwrap_or(1)
            .clamp(0, 16) as u16,
        frames: get_int(&obj, tags::NUMBER_OF_FRAMES)
            .unwrap_or(1)
            .clamp(0, u32::MAX as i64) as u32,
        pixel: scan.pixel,
    })
}

fn list_some(items: &[String]) -> String {
    let mut s = items
        .iter()
        .take(MAX_LISTED)
        .cloned()
        .collect::<Vec<_>>()
        .join("; ");
    if items.len() > MAX_LISTED {
        s.push_str(&format!("; and {} more", items.len() - MAX_LISTED));
    }
    s
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    let n = s.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        s[n / 2]
    } else {
        (s[n / 2 - 1] + s[n / 2]) / 2.0
    }
}

/// Loads the largest DICOM series found directly in `dir`.
pub fn load_dicom_dir(dir: &Path) -> Result<RawVolume, VolumeError> {
    let rd =
        std::fs::read_dir(dir).map_err(|e| VolumeError::io(dir, "listing the DICOM folder", e))?;
    let mut files = Vec::new();
    for ent in rd {
        let ent = ent.map_err(|e| VolumeError::io(dir, "listing the DICOM folder", e))?;
        let p = ent.path();
        let hidden = ent.file_name().to_string_lossy().starts_with('.');
        if !hidden && p.is_file() {
            files.push(p);
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(VolumeError::format(
            dir,
            "folder contains no files; expected a DICOM series",
        ));
    }
    load_dicom_files(dir, &files)
}

/// The chosen series' slices sorted by position along the normal, the slice spacing and
/// the warnings so far.
struct SeriesPlan {
    slices: Vec<(f64, SliceInfo)>,
    dz: f64,
    warnings: Vec<String>,
}

/// Reads every header, picks the largest series, checks it and sorts it.
fn plan_series(label: &Path, files: &[PathBuf]) -> Result<SeriesPlan, VolumeError> {
    let mut warnings = Vec::new();
    let mut skipped = Vec::new();
    let mut infos = Vec::new();
    for p in files {
        match read_info(p) {
            Ok(i) => infos.push(i),
            Err(why) => skipped.push(format!("{}: {why}", fname(p))),
        }
    }
    if infos.is_empty() {
        return Err(VolumeError::format(
            label,
            format!(
                "no DICOM image files found among {} files ({})",
                files.len(),
                list_some(&skipped)
            ),
        ));
    }
    if !skipped.is_empty() {
        warnings.push(format!(
            "skipped {} non-image or non-DICOM files: {}",
            skipped.len(),
            list_some(&skipped)
        ));
    }

    // Group by series; keep the one with the most slices.
    let mut series: BTreeMap<String, Vec<SliceInfo>> = BTreeMap::new();
    for i in infos {
        series.entry(i.series.clone()).or_default().push(i);
    }
    let best_key = series
        .iter()
        .max_by(|a, b| a.1.len().cmp(&b.1.len()).then_with(|| b.0.cmp(a.0)))
        .map(|(k, _)| k.clone())
        .unwrap_or_default();
    let others: Vec<usize> = series
        .iter()
        .filter(|(k, _)| **k != best_key)
        .map(|(_, v)| v.len())
        .collect();
    let mut slices = series.remove(&best_key).unwrap_or_default();
    if !others.is_empty() {
        warnings.push(format!(
            "folder holds {} series; loaded the one with {} slices, ignored others with {:?} slices",
            others.len() + 1,
            slices.len(),
            others
        ));
    }

    // Per-slice checks: transfer syntax, pixel format.
    for s in &slices {
        if ts_name(&s.ts).is_none() {
            return Err(VolumeError::unsupported(
                &s.path,
                format!(
                    "transfer syntax {} ({}); only uncompressed Implicit/Explicit VR Little Endian and \
                     Explicit VR Big Endian are supported",
                    s.ts,
                    compressed_ts_name(&s.ts)
                ),
            ));
        }
        if s.samples_per_pixel != 1 {
            return Err(VolumeError::unsupported(
                &s.path,
                format!(
                    "SamplesPerPixel is {}; only grayscale (1) is supported",
                    s.samples_per_pixel
                ),
            ));
        }
        if s.frames > 1 {
            return Err(VolumeError::unsupported(
                &s.path,
                format!(
                    "multi-frame image (NumberOfFrames {}); only one slice per file is supported",
                    s.frames
                ),
            ));
        }
        if s.bits_alloc != 8 && s.bits_alloc != 16 {
            return Err(VolumeError::unsupported(
                &s.path,
                format!("BitsAllocated is {}; supported: 8 or 16", s.bits_alloc),
            ));
        }
    }

    // Pixel data present and long enough.
    let mut bad_pixels = Vec::new();
    for s in &slices {
        if s.pixel == PixelData::Encapsulated {
            return Err(VolumeError::unsupported(
                &s.path,
                "PixelData is encapsulated (compressed); only native pixel data is supported",
            ));
        }
    }
    slices.retain(|s| {
        let need = (s.rows as u64)
            .saturating_mul(s.cols as u64)
            .saturating_mul(s.bits_alloc as u64 / 8);
        match s.pixel {
            PixelData::Native { len, .. } if len as u64 >= need => true,
            PixelData::Native { len, .. } => {
                bad_pixels.push(format!(
                    "{}: PixelData holds {len} bytes, Columns {} × Rows {} × {} bytes needs {need}",
                    fname(&s.path),
                    s.cols,
                    s.rows,
                    s.bits_alloc / 8
                ));
                false
            }
            _ => {
                bad_pixels.push(format!("{}: no PixelData element", fname(&s.path)));
                false
            }
        }
    });
    if slices.is_empty() {
        return Err(VolumeError::format(
            label,
            format!(
                "no DICOM slice has usable pixel data: {}",
                list_some(&bad_pixels)
            ),
        ));
    }
    if !bad_pixels.is_empty() {
        warnings.push(format!(
            "skipped {} slices with short or missing pixel data: {}",
            bad_pixels.len(),
            list_some(&bad_pixels)
        ));
    }

    // Mixed image sizes / pixel formats: keep the most common, skip the rest.
    let key = |s: &SliceInfo| (s.rows, s.cols, s.bits_alloc, s.signed);
    let mut counts: BTreeMap<(u32, u32, u16, bool), usize> = BTreeMap::new();
    for s in &slices {
        *counts.entry(key(s)).or_default() += 1;
    }
    if counts.len() > 1 {
        let common = counts
            .iter()
            .max_by_key(|(_, n)| **n)
            .map(|(k, _)| *k)
            .unwrap_or((0, 0, 16, false));
        let odd: Vec<String> = slices
            .iter()
            .filter(|s| key(s) != common)
            .map(|s| {
                format!(
                    "{} is {}×{} ({}-bit)",
                    fname(&s.path),
                    s.cols,
                    s.rows,
                    s.bits_alloc
                )
            })
            .collect();
        warnings.push(format!(
            "skipped {} slices whose size or pixel format differs from the majority ({}×{}, {}-bit): {}",
            odd.len(),
            common.1,
            common.0,
            common.2,
            list_some(&odd)
        ));
        slices.retain(|s| key(s) == common);
    }

    // Sort along the slice normal.
    let normal = slices.iter().find_map(|s| s.iop).and_then(|o| {
        let n = cross([o[0], o[1], o[2]], [o[3], o[4], o[5]]);
        let len = dot(n, n).sqrt();
        (len > 1e-6).then(|| n.map(|c| c / len))
    });
    let all_ipp = slices.iter().all(|s| s.ipp.is_some());
    let mut positioned: Vec<(f64, SliceInfo)> = match (normal, all_ipp) {
        (Some(n), true) => slices
            .into_iter()
            .map(|s| (s.ipp.map(|p| dot(p, n)).unwrap_or(0.0), s))
            .collect(),
        _ => {
            warnings.push(
                "ImagePositionPatient/ImageOrientationPatient missing: slices sorted by InstanceNumber, \
                 slice spacing from SliceThickness"
                    .to_string(),
            );
            let mut v: Vec<(f64, SliceInfo)> = slices
                .into_iter()
                .map(|s| {
                    (
                        s.instance.unwrap_or(0) as f64
                            * s.slice_thickness.unwrap_or(1.0).abs().max(1e-6),
                        s,
                    )
                })
                .collect();
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            v
        }
    };
    positioned.sort_by(|a, b| {
        a.0.total_cmp(&b.0)
            .then_with(|| a.1.instance.cmp(&b.1.instance))
            .then_with(|| a.1.path.cmp(&b.1.path))
    });
    if let Some(n) = normal {
        let tilted: Vec<String> = positioned
            .iter()
            .filter_map(|(_, s)| s.iop.map(|o| (s, o)))
            .filter(|(_, o)| {
                let m = cross([o[0], o[1], o[2]], [o[3], o[4], o[5]]);
                let l = dot(m, m).sqrt().max(1e-12);
                (dot(m, n) / l - 1.0).abs() > 1e-3
            })
            .map(|(s, _)| fname(&s.path))
            .collect();
        if !tilted.is_empty() {
            warnings.push(format!(
                "{} slices have an ImageOrientationPatient different from the first: {}",
                tilted.len(),
                list_some(&tilted)
            ));
        }
    }

    // Duplicate positions: keep the first.
    let mut dups = Vec::new();
    let mut kept: Vec<(f64, SliceInfo)> = Vec::with_capacity(positioned.len());
    for (pos, s) in positioned {
        if let Some((lp, ls)) = kept.last()
            && (pos - lp).abs() < 1e-3
        {
            dups.push(format!(
                "{} duplicates {} at position {pos:.3}",
                fname(&s.path),
                fname(&ls.path)
            ));
            continue;
        }
        kept.push((pos, s));
    }
    if !dups.is_empty() {
        warnings.push(format!(
            "skipped {} slices at duplicate positions: {}",
            dups.len(),
            list_some(&dups)
        ));
    }

    // Slice spacing: median of consecutive differences; report gaps and non-uniformity.
    let diffs: Vec<f64> = kept.windows(2).map(|w| w[1].0 - w[0].0).collect();
    let Some((_, first)) = kept.first() else {
        return Err(VolumeError::format(
            label,
            "no DICOM slices left after filtering",
        ));
    };
    let dz = if diffs.is_empty() {
        first
            .slice_thickness
            .filter(|t| t.is_finite() && *t > 0.0)
            .unwrap_or(1.0)
    } else {
        median(&diffs)
    };
    let mut gaps = Vec::new();
    let mut uneven = Vec::new();
    for (i, d) in diffs.iter().enumerate() {
        if *d > 1.5 * dz {
            gaps.push(format!(
                "{d:.3} mm between z={i} (position {:.3}) and z={} (position {:.3})",
                kept[i].0,
                i + 1,
                kept[i + 1].0
            ));
        } else if (d - dz).abs() > 0.01 * dz {
            uneven.push(format!(
                "{d:.3} mm between positions {:.3} and {:.3}",
                kept[i].0,
                kept[i + 1].0
            ));
        }
    }
    if !gaps.is_empty() {
        warnings.push(format!(
            "missing slices: {} gaps larger than 1.5 × the median slice spacing {dz:.3} mm: {}",
            gaps.len(),
            list_some(&gaps)
        ));
    }
    if !uneven.is_empty() {
        warnings.push(format!(
            "non-uniform slice spacing (median {dz:.3} mm): {}",
            list_some(&uneven)
        ));
    }

    Ok(SeriesPlan {
        slices: kept,
        dz,
        warnings,
    })
}

/// Loads a DICOM series from an explicit list of files (`label` names it in messages).
pub(crate) fn load_dicom_files(label: &Path, files: &[PathBuf]) -> Result<RawVolume, VolumeError> {
    let SeriesPlan {
        slices: kept,
        dz,
        mut warnings,
    } = plan_series(label, files)?;
    let Some((_, first)) = kept.first() else {
        return Err(VolumeError::format(
            label,
            "no DICOM slices left after filtering",
        ));
    };
    let (rows, cols) = (first.rows, first.cols);
    let ps = match first.pixel_spacing {
        Some(p) => p,
        None => {
            warnings.push("PixelSpacing missing: using 1 × 1".to_string());
            [1.0, 1.0]
        }
    };
    // PixelSpacing = [row spacing (between rows, y), column spacing (between columns, x)].
    let spacing = check_spacing(
        &first.path,
        "PixelSpacing / slice positions",
        [ps[1], ps[0], dz],
    )?;
    let nz = kept.len() as u64;
    let dims = check_dims(
        label,
        "DICOM Columns × Rows × slices",
        [cols as u64, rows as u64, nz],
    )?;

    // Output sample type.
    let bits_alloc = first.bits_alloc;
    let signed = first.signed;
    let bs = if first.bits_stored == 0 || first.bits_stored > bits_alloc {
        bits_alloc
    } else {
        first.bits_stored
    };
    let (smin, smax): (f64, f64) = if signed {
        (
            -((1i64 << (bs - 1)) as f64),
            ((1i64 << (bs - 1)) - 1) as f64,
        )
    } else {
        (0.0, ((1i64 << bs) - 1) as f64)
    };
    let identity = kept
        .iter()
        .all(|(_, s)| s.slope == 1.0 && s.intercept == 0.0);
    let integral = kept.iter().all(|(_, s)| {
        s.slope.fract() == 0.0
            && s.intercept.fract() == 0.0
            && s.slope.abs() < 1e6
            && s.intercept.abs() < 1e9
    });
    let (lo, hi) = kept
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, s)| {
            let a = smin * s.slope + s.intercept;
            let b = smax * s.slope + s.intercept;
            (lo.min(a.min(b)), hi.max(a.max(b)))
        });
    let count = dims.iter().map(|&d| d as usize).product::<usize>();
    #[derive(Clone, Copy, PartialEq)]
    enum Out {
        U8,
        I8,
        U16,
        I16,
        I32,
        F32,
    }
    let out = if identity {
        match (bits_alloc, signed) {
            (8, false) => Out::U8,
            (8, true) => Out::I8,
            (_, false) => Out::U16,
            (_, true) => Out::I16,
        }
    } else if integral && lo >= i16::MIN as f64 && hi <= i16::MAX as f64 {
        Out::I16
    } else if integral && lo >= i32::MIN as f64 && hi <= i32::MAX as f64 {
        Out::I32
    } else {
        Out::F32
    };
    let mut samples = match out {
        Out::U8 => Samples::U8(Vec::with_capacity(count)),
        Out::I8 => Samples::I8(Vec::with_capacity(count)),
        Out::U16 => Samples::U16(Vec::with_capacity(count)),
        Out::I16 => Samples::I16(Vec::with_capacity(count)),
        Out::I32 => Samples::I32(Vec::with_capacity(count)),
        Out::F32 => Samples::F32(Vec::with_capacity(count)),
    };

    // Pass 2: pixel data, slice by slice in sorted order.
    let per_slice = rows as usize * cols as usize;
    let mut stored: Vec<i32> = Vec::new();
    for (_, s) in &kept {
        read_pixels(s, per_slice, bs, &mut stored)?;
        let (m, c) = (s.slope, s.intercept);
        match &mut samples {
            Samples::U8(v) => v.extend(stored.iter().map(|&x| x as u8)),
            Samples::I8(v) => v.extend(stored.iter().map(|&x| x as i8)),
            Samples::U16(v) => v.extend(stored.iter().map(|&x| x as u16)),
            Samples::I16(v) => {
                let (m, c) = (m as i32, c as i32);
                v.extend(stored.iter().map(|&x| (x * m + c) as i16))
            }
            Samples::I32(v) => {
                let (m, c) = (m as i64, c as i64);
                v.extend(stored.iter().map(|&x| (x as i64 * m + c) as i32))
            }
            Samples::F32(v) => v.extend(stored.iter().map(|&x| (x as f64 * m + c) as f32)),
            Samples::U32(_) | Samples::F64(_) => {}
        }
    }

    let modality = first.modality.clone();
    let units = if modality.eq_ignore_ascii_case("CT") {
        "HU".to_string()
    } else {
        String::new()
    };
    let ts = ts_name(&first.ts).unwrap_or("uncompressed");
    Ok(RawVolume {
        dims,
        spacing,
        samples,
        units,
        modality,
        format: format!(
            "DICOM series ({} slice{}, {ts})",
            kept.len(),
            if kept.len() == 1 { "" } else { "s" }
        ),
        warnings,
    })
}

/// Reads one slice's pixel data into `out` as stored integer values (masked / sign-extended
/// to `bits_stored`). The file is re-validated, and the native PixelData value is read directly.
fn read_pixels(
    s: &SliceInfo,
    n: usize,
    bits_stored: u16,
    out: &mut Vec<i32>,
) -> Result<(), VolumeError> {
    out.clear();
    let bytes = std::fs::read(&s.path)
        .map_err(|e| VolumeError::io(&s.path, "reading the DICOM file", e))?;
    let scan = prescan(&bytes).map_err(|m| VolumeError::format(&s.path, m))?;
    let bytes_per = s.bits_alloc as usize / 8;
    let need = n * bytes_per;
    let data = match scan.pixel {
        PixelData::Native { offset, len } if len >= need => &bytes[offset..offset + need],
        PixelData::Native { len, .. } => {
            return Err(VolumeError::format(
                &s.path,
                format!(
                    "PixelData is truncated: expected Columns {} × Rows {} × {bytes_per} bytes = {need} bytes, found {len}",
                    s.cols, s.rows
                ),
            ));
        }
        PixelData::Encapsulated => {
            return Err(VolumeError::unsupported(
                &s.path,
                "PixelData is encapsulated (compressed); only native pixel data is supported",
            ));
        }
        PixelData::Absent => {
            return Err(VolumeError::format(
                &s.path,
                "DICOM file has no PixelData element",
            ));
        }
    };
    let big = scan.ts == "1.2.840.10008.1.2.2";
    let shift = 32 - bits_stored as u32;
    let fix = |raw: u32| -> i32 {
        if s.signed {
            ((raw << shift) as i32) >> shift
        } else {
            ((raw << shift) >> shift) as i32
        }
    };
    out.reserve_exact(n);
    if bytes_per == 1 {
        out.extend(data.iter().map(|&x| fix(x as u32)));
    } else if big {
        out.extend(
            data.chunks_exact(2)
                .map(|c| fix(u16::from_be_bytes([c[0], c[1]]) as u32)),
        );
    } else {
        out.extend(
            data.chunks_exact(2)
                .map(|c| fix(u16::from_le_bytes([c[0], c[1]]) as u32)),
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn real_series_sorted_by_position_not_name_or_instance() {
        let dir = crate::testdata::require_shared_data_dir().join("ct-chest-lidc");
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        let plan = plan_series(&dir, &files).unwrap();
        assert_eq!(plan.slices.len(), 128);
        assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);
        assert!((plan.dz - 1.0).abs() < 1e-6);
        let (p0, s0) = &plan.slices[0];
        assert_eq!(fname(&s0.path), "000111.dcm");
        assert!((p0 - -606.800049).abs() < 1e-6, "z=0 at {p0}");
        assert!((s0.ipp.unwrap()[2] - -606.800049).abs() < 1e-6);
        assert_eq!(fname(&plan.slices[1].1.path), "000124.dcm");
        let (p127, s127) = &plan.slices[127];
        assert_eq!(fname(&s127.path), "000182.dcm");
        assert!((p127 - -479.800049).abs() < 1e-6);
        for (z, (_, s)) in plan.slices.iter().enumerate() {
            assert_eq!(
                s.instance,
                Some(202 - z as i64),
                "InstanceNumber runs opposite to z"
            );
            assert_eq!(s.pixel_spacing, Some([0.78125, 0.78125]));
            assert_eq!((s.slope, s.intercept), (1.0, -1000.0));
        }
    }

    #[test]
    fn median_and_cross() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
    }
}
