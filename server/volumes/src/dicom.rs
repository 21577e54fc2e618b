//! DICOM loader, built on `dicom-object`: series of single-frame files and (enhanced)
//! multi-frame files, uncompressed or compressed with any codec dicom-rs's transfer syntax
//! registry decodes here (RLE Lossless, JPEG baseline / 8-bit extended / lossless, JPEG-LS,
//! JPEG 2000), and 12-bit lossy JPEG (extended) with libjpeg-turbo ([`crate::jpeg12`]). Every
//! frame becomes one slice; slices are grouped by SeriesInstanceUID and sorted along the slice
//! normal.
//!
//! Privacy: warnings and format strings name files and geometry only, never patient data.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry, VirtualVr};
use dicom_core::{Tag, VR};
use dicom_dictionary_std::{StandardDataDictionary, tags};
use dicom_encoding::adapters::{PixelDataObject, RawPixelData};
use dicom_encoding::transfer_syntax::{Codec, TransferSyntaxIndex};
use dicom_object::file::ReadPreamble;
use dicom_object::{DefaultDicomObject, InMemDicomObject, OpenFileOptions};
use dicom_transfer_syntax_registry::TransferSyntaxRegistry;

use crate::raw::{RawVolume, Samples, check_dims, check_spacing};
use crate::{MAX_VOXELS, VolumeError, jpeg12};

/// Most individual problems listed in one warning before it says "and N more".
const MAX_LISTED: usize = 5;

/// Most frames accepted in one file. Each frame costs a slice record before any voxel is
/// allocated, so a small file must not be able to declare millions of them.
const MAX_FRAMES_PER_FILE: i64 = 1 << 16;

const EXPLICIT_VR_BIG_ENDIAN: &str = "1.2.840.10008.1.2.2";
const JPEG_BASELINE: &str = "1.2.840.10008.1.2.4.50";
const JPEG_EXTENDED: &str = "1.2.840.10008.1.2.4.51";

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

/// The transfer syntax's name from dicom-rs's registry, or the UID when it is unknown.
fn ts_name(uid: &str) -> String {
    TransferSyntaxRegistry
        .get(uid)
        .map_or_else(|| uid.to_string(), |ts| ts.name().to_string())
}

/// "UID (name)" for messages.
fn ts_label(uid: &str) -> String {
    match TransferSyntaxRegistry.get(uid) {
        Some(ts) => format!("{uid} ({})", ts.name()),
        None => format!("{uid} (not a transfer syntax dicom-rs knows)"),
    }
}

/// Whether this slice's frames go to libjpeg-turbo ([`jpeg12`]) rather than dicom-rs: lossy JPEG
/// with more than 8 bits stored, i.e. a 12-bit stream (PS3.5 Table 8.2.1-1), which jpeg-decoder,
/// dicom-rs's JPEG codec, cannot decode (it reads DCT-based JPEG at 8-bit precision only). JPEG
/// Baseline is 8-bit by definition, but a file marked so with 12 bits stored may hold a 12-bit
/// stream all the same. A stream that turns out to be 8-bit still goes to dicom-rs, as do files
/// whose BitsStored exceeds an 8-bit BitsAllocated (read as 8 bits stored).
fn uses_jpeg12(s: &SliceInfo) -> bool {
    (s.ts == JPEG_EXTENDED || s.ts == JPEG_BASELINE) && s.bits_stored > 8 && s.bits_alloc == 16
}

/// Why this slice's pixel data cannot be decoded here, or `None` when it can.
fn transfer_syntax_problem(s: &SliceInfo) -> Option<String> {
    let Some(ts) = TransferSyntaxRegistry.get(&s.ts) else {
        return Some(format!("transfer syntax {}", ts_label(&s.ts)));
    };
    match ts.codec() {
        Codec::None => None,
        Codec::EncapsulatedPixelData(Some(_), _) => None,
        _ => Some(format!(
            "transfer syntax {}: no decoder for it is built in (supported: uncompressed, \
             RLE Lossless, JPEG Baseline, 8- and 12-bit JPEG Extended, JPEG Lossless, JPEG-LS \
             and JPEG 2000)",
            ts_label(&s.ts)
        )),
    }
}

/// Header facts of one slice: one frame of one file (no pixel data).
#[derive(Debug, Clone)]
struct SliceInfo {
    path: PathBuf,
    /// Index of the frame within its file (0 for single-frame files).
    frame: u32,
    /// NumberOfFrames of the file.
    frames: u32,
    series: String,
    ts: String,
    rows: u32,
    cols: u32,
    bits_alloc: u16,
    bits_stored: u16,
    signed: bool,
    /// PhotometricInterpretation MONOCHROME1: the minimum value is displayed as white.
    monochrome1: bool,
    ipp: Option<[f64; 3]>,
    iop: Option<[f64; 6]>,
    pixel_spacing: Option<[f64; 2]>,
    slice_thickness: Option<f64>,
    slope: f64,
    intercept: f64,
    /// Whether RescaleSlope or RescaleIntercept is present (top level or functional group).
    has_rescale: bool,
    /// LossyImageCompression is "01", or the transfer syntax is always lossy.
    lossy: bool,
    modality: String,
    instance: Option<i64>,
    samples_per_pixel: u16,
    pixel: PixelData,
}

impl SliceInfo {
    /// The file name, with the 1-based frame number for multi-frame files.
    fn name(&self) -> String {
        if self.frames > 1 {
            format!("{} frame {}", fname(&self.path), self.frame + 1)
        } else {
            fname(&self.path)
        }
    }

    fn bytes_per_sample(&self) -> usize {
        self.bits_alloc as usize / 8
    }

    fn frame_bytes(&self) -> u64 {
        (self.rows as u64)
            .saturating_mul(self.cols as u64)
            .saturating_mul(self.bytes_per_sample() as u64)
    }
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
    /// Encapsulated (compressed) data: the number of fragments after the basic offset table.
    Encapsulated {
        fragments: usize,
    },
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
        // dicom-object reads an unknown VR in long form and reserves the 4-byte "length" it
        // finds there before failing (775 MB for a 1 KiB file): refuse it here.
        if !LONG_VRS.iter().chain(SHORT_VRS).any(|v| &v[..] == vr) {
            return Err(format!(
                "file meta element (0002,{elem:04X}) at byte {pos} has an invalid value representation {:02X} {:02X}",
                vr[0], vr[1]
            ));
        }
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
        if vr == b"UI" && len > 64 {
            return Err(format!(
                "file meta element (0002,{elem:04X}) is a UID of {len} bytes (at most 64)"
            ));
        }
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
    let dict = StandardDataDictionary;
    let mut pixel = PixelData::Absent;
    let mut encapsulated = false;
    // Items of the encapsulated PixelData: the basic offset table, then one per fragment.
    let mut pixel_items = 0usize;
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
                    pixel_items += 1;
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
                pixel_items = 0;
                pixel = PixelData::Encapsulated { fragments: 0 };
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
    if let PixelData::Encapsulated { fragments } = &mut pixel {
        *fragments = pixel_items.saturating_sub(1);
    }
    Ok(Prescan { ts, pixel })
}

fn fname(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| p.display().to_string())
}

/// The dictionary VR of a standard tag, for elements a writer encoded as UN.
fn dictionary_vr(tag: Tag) -> Option<VR> {
    match StandardDataDictionary.by_tag(tag)?.vr() {
        VirtualVr::Exact(vr) => Some(vr),
        _ => None,
    }
}

/// An element's value as text. Elements encoded as UN (GDCM 3.0 writes standard attributes of
/// Implicit VR input as UN when it compresses to JPEG 2000) hold the bytes their dictionary VR
/// would, so those are read as that VR's text.
fn get_str(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let e = obj.element_opt(tag).ok()??;
    let text = if e.vr() == VR::UN {
        String::from_utf8_lossy(&e.to_bytes().ok()?).into_owned()
    } else {
        e.to_str().ok()?.into_owned()
    };
    Some(
        text.trim_matches(|c: char| c.is_whitespace() || c == '\0')
            .to_string(),
    )
}

fn get_f64s(obj: &InMemDicomObject, tag: Tag) -> Option<Vec<f64>> {
    let e = obj.element_opt(tag).ok()??;
    if e.vr() == VR::UN {
        let text = get_str(obj, tag)?;
        return text
            .split('\\')
            .map(|v| v.trim().parse::<f64>().ok())
            .collect();
    }
    e.to_multi_float64().ok()
}

fn get_f64(obj: &InMemDicomObject, tag: Tag) -> Option<f64> {
    get_f64s(obj, tag).and_then(|v| v.first().copied())
}

fn get_int(obj: &InMemDicomObject, tag: Tag) -> Option<i64> {
    let e = obj.element_opt(tag).ok()??;
    if e.vr() == VR::UN {
        return match dictionary_vr(tag) {
            Some(VR::US) => {
                let b = e.to_bytes().ok()?;
                Some(u16::from_le_bytes([*b.first()?, *b.get(1)?]) as i64)
            }
            _ => get_str(obj, tag)?.parse().ok(),
        };
    }
    e.to_int::<i64>().ok()
}

/// The first item of a sequence element.
fn first_item(obj: &InMemDicomObject, tag: Tag) -> Option<&InMemDicomObject> {
    obj.element_opt(tag).ok()??.items()?.first()
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

/// Opens a whole Part-10 file from bytes already checked by [`prescan`].
fn parse_file(bytes: &[u8], until_pixel_data: bool) -> Result<DefaultDicomObject, String> {
    let mut options = OpenFileOptions::new().read_preamble(ReadPreamble::Always);
    if until_pixel_data {
        options = options.read_until(tags::PIXEL_DATA);
    }
    options
        .from_reader(bytes)
        .map_err(|e| format!("not a readable DICOM file ({})", short_err(e)))
}

/// Reads the header of one file: one [`SliceInfo`] per frame. `Err(reason)` means "skip this
/// file".
///
/// Multi-frame (enhanced) files keep their geometry and rescale in functional groups: each
/// frame's PerFrameFunctionalGroupsSequence item overrides the SharedFunctionalGroupsSequence,
/// which overrides the top-level attributes (PS3.3 C.7.6.16).
fn read_file_slices(path: &Path) -> Result<Vec<SliceInfo>, String> {
    if !has_dicm_magic(path) {
        return Err("not a DICOM file (no DICM marker at byte 128)".into());
    }
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read: {e}"))?;
    let scan = prescan(&bytes)?;
    let obj = parse_file(&bytes, true)?;
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
    let frames = get_int(&obj, tags::NUMBER_OF_FRAMES).unwrap_or(1);
    if frames < 1 {
        return Err(format!("invalid NumberOfFrames {frames}"));
    }
    if frames > MAX_FRAMES_PER_FILE || (frames as u64) * (rows as u64) * (cols as u64) > MAX_VOXELS
    {
        return Err(format!(
            "NumberOfFrames {frames} × Rows {rows} × Columns {cols} is more than supported \
             (at most {MAX_FRAMES_PER_FILE} frames and {MAX_VOXELS} voxels)"
        ));
    }

    let arr2 = |v: Vec<f64>| -> Option<[f64; 2]> { (v.len() >= 2).then(|| [v[0], v[1]]) };
    let arr3 = |v: Vec<f64>| -> Option<[f64; 3]> { (v.len() >= 3).then(|| [v[0], v[1], v[2]]) };
    let arr6 = |v: Vec<f64>| -> Option<[f64; 6]> {
        (v.len() >= 6).then(|| [v[0], v[1], v[2], v[3], v[4], v[5]])
    };
    let finite = |v: &Vec<f64>| v.iter().all(|x| x.is_finite());
    let shared = first_item(&obj, tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE);
    let per_frame: &[InMemDicomObject] = obj
        .element_opt(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .ok()
        .flatten()
        .and_then(|e| e.items())
        .unwrap_or(&[]);
    // What every frame shares; the frame loop fills in geometry and rescale.
    let photometric = get_str(&obj, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_default();
    let lossy = ts == JPEG_BASELINE
        || ts == JPEG_EXTENDED
        || get_str(&obj, tags::LOSSY_IMAGE_COMPRESSION).as_deref() == Some("01");
    let file = SliceInfo {
        path: path.to_path_buf(),
        frame: 0,
        frames: frames as u32,
        series: get_str(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default(),
        ts,
        rows: rows as u32,
        cols: cols as u32,
        bits_alloc: get_int(&obj, tags::BITS_ALLOCATED)
            .unwrap_or(16)
            .clamp(0, 64) as u16,
        bits_stored: get_int(&obj, tags::BITS_STORED).unwrap_or(0).clamp(0, 64) as u16,
        signed: get_int(&obj, tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1,
        monochrome1: photometric == "MONOCHROME1",
        ipp: None,
        iop: None,
        pixel_spacing: None,
        slice_thickness: None,
        slope: 1.0,
        intercept: 0.0,
        has_rescale: false,
        lossy,
        modality: get_str(&obj, tags::MODALITY).unwrap_or_default(),
        instance: get_int(&obj, tags::INSTANCE_NUMBER),
        samples_per_pixel: get_int(&obj, tags::SAMPLES_PER_PIXEL)
            .unwrap_or(1)
            .clamp(0, 16) as u16,
        pixel: scan.pixel,
    };

    let mut slices = Vec::with_capacity(frames as usize);
    for frame in 0..frames as usize {
        // The functional group macro `seq` for this frame: its own item, else the shared one.
        let group = |seq: Tag| {
            per_frame
                .get(frame)
                .and_then(|item| first_item(item, seq))
                .or_else(|| shared.and_then(|item| first_item(item, seq)))
        };
        let position = group(tags::PLANE_POSITION_SEQUENCE);
        let orientation = group(tags::PLANE_ORIENTATION_SEQUENCE).unwrap_or(&obj);
        let measures = group(tags::PIXEL_MEASURES_SEQUENCE).unwrap_or(&obj);
        let transform = group(tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE).unwrap_or(&obj);
        // A top-level ImagePositionPatient locates the first frame only.
        let ipp = match position {
            Some(item) => get_f64s(item, tags::IMAGE_POSITION_PATIENT),
            None if frames == 1 => get_f64s(&obj, tags::IMAGE_POSITION_PATIENT),
            None => None,
        };
        let slope = get_f64(transform, tags::RESCALE_SLOPE);
        let intercept = get_f64(transform, tags::RESCALE_INTERCEPT);
        slices.push(SliceInfo {
            frame: frame as u32,
            ipp: ipp.filter(finite).and_then(arr3),
            iop: get_f64s(orientation, tags::IMAGE_ORIENTATION_PATIENT)
                .filter(finite)
                .and_then(arr6),
            pixel_spacing: get_f64s(measures, tags::PIXEL_SPACING).and_then(arr2),
            slice_thickness: get_f64(measures, tags::SLICE_THICKNESS),
            slope: slope.filter(|s| s.is_finite() && *s != 0.0).unwrap_or(1.0),
            intercept: intercept.filter(|s| s.is_finite()).unwrap_or(0.0),
            has_rescale: slope.is_some() || intercept.is_some(),
            ..file.clone()
        });
    }
    Ok(slices)
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
        match read_file_slices(p) {
            Ok(frames) => infos.extend(frames),
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
        if let Some(problem) = transfer_syntax_problem(s) {
            return Err(VolumeError::unsupported(&s.path, problem));
        }
        let compressed = TransferSyntaxRegistry
            .get(&s.ts)
            .is_some_and(|ts| ts.is_encapsulated_pixel_data());
        let encapsulated = matches!(s.pixel, PixelData::Encapsulated { .. });
        if s.pixel != PixelData::Absent && compressed != encapsulated {
            return Err(VolumeError::format(
                &s.path,
                format!(
                    "PixelData is {} but transfer syntax {} stores it {}",
                    if encapsulated {
                        "encapsulated (compressed)"
                    } else {
                        "native (uncompressed)"
                    },
                    ts_label(&s.ts),
                    if compressed { "encapsulated" } else { "native" }
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
        if s.bits_alloc != 8 && s.bits_alloc != 16 {
            return Err(VolumeError::unsupported(
                &s.path,
                format!("BitsAllocated is {}; supported: 8 or 16", s.bits_alloc),
            ));
        }
    }

    // Pixel data present and long enough (native), or one fragment per frame at least
    // (encapsulated: PS3.5 A.4 puts every frame in its own fragments).
    let mut bad_pixels = Vec::new();
    slices.retain(|s| {
        let need = s.frame_bytes().saturating_mul(s.frame as u64 + 1);
        match s.pixel {
            PixelData::Native { len, .. } if len as u64 >= need => true,
            PixelData::Native { len, .. } => {
                bad_pixels.push(format!(
                    "{}: PixelData holds {len} bytes, Columns {} × Rows {} × {} bytes{} needs {need}",
                    s.name(),
                    s.cols,
                    s.rows,
                    s.bytes_per_sample(),
                    if s.frames > 1 {
                        format!(" × {} frames", s.frame + 1)
                    } else {
                        String::new()
                    }
                ));
                false
            }
            PixelData::Encapsulated { fragments } if fragments >= s.frames as usize => true,
            PixelData::Encapsulated { fragments } => {
                bad_pixels.push(format!(
                    "{}: encapsulated PixelData holds {fragments} fragments for {} frames",
                    s.name(),
                    s.frames
                ));
                false
            }
            PixelData::Absent => {
                bad_pixels.push(format!("{}: no PixelData element", s.name()));
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
                    s.name(),
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
                "ImagePositionPatient/ImageOrientationPatient missing: slices sorted by InstanceNumber \
                 and frame number, slice spacing from SliceThickness"
                    .to_string(),
            );
            slices.sort_by(|a, b| {
                a.instance
                    .cmp(&b.instance)
                    .then_with(|| a.frame.cmp(&b.frame))
                    .then_with(|| a.path.cmp(&b.path))
            });
            // Single-frame files keep InstanceNumber steps, so that missing instances show as
            // gaps; frames of multi-frame files are stacked in order.
            let single_frame_files = slices.iter().all(|s| s.frames == 1);
            slices
                .into_iter()
                .enumerate()
                .map(|(rank, s)| {
                    let step = s.slice_thickness.unwrap_or(1.0).abs().max(1e-6);
                    let ordinal = if single_frame_files {
                        s.instance.unwrap_or(0) as f64
                    } else {
                        rank as f64
                    };
                    (ordinal * step, s)
                })
                .collect()
        }
    };
    positioned.sort_by(|a, b| {
        a.0.total_cmp(&b.0)
            .then_with(|| a.1.instance.cmp(&b.1.instance))
            .then_with(|| a.1.path.cmp(&b.1.path))
            .then_with(|| a.1.frame.cmp(&b.1.frame))
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
            .map(|(s, _)| s.name())
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
                s.name(),
                ls.name()
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
    // Native pixel data is in the files already checked, so the whole volume is reserved at
    // once. Compressed frames may declare far more than they hold: those grow as they decode.
    let all_native = kept
        .iter()
        .all(|(_, s)| matches!(s.pixel, PixelData::Native { .. }));
    let reserve = if all_native {
        count
    } else {
        count.min(rows as usize * cols as usize)
    };
    let mut samples = match out {
        Out::U8 => Samples::U8(Vec::with_capacity(reserve)),
        Out::I8 => Samples::I8(Vec::with_capacity(reserve)),
        Out::U16 => Samples::U16(Vec::with_capacity(reserve)),
        Out::I16 => Samples::I16(Vec::with_capacity(reserve)),
        Out::I32 => Samples::I32(Vec::with_capacity(reserve)),
        Out::F32 => Samples::F32(Vec::with_capacity(reserve)),
    };

    // Pass 2: pixel data, slice by slice in sorted order. Compressed single-frame files are
    // decoded a few at a time in parallel (JPEG 2000 takes ~30 ms a slice on one core); their
    // samples are appended in order, so memory grows by one decoded slice per worker only.
    let per_slice = rows as usize * cols as usize;
    let workers = decode_workers(&kept);
    let mut stored: Vec<Vec<i32>> = vec![Vec::new(); workers];
    let mut reader = FrameReader::default();
    for wave in kept.chunks(workers) {
        if let [(_, s)] = wave {
            reader.read(s, per_slice, bs, &mut stored[0])?;
        } else {
            decode_in_parallel(wave, per_slice, bs, &mut stored)?;
        }
        for ((_, s), stored) in wave.iter().zip(&stored) {
            append_rescaled(&mut samples, stored, s.slope, s.intercept);
        }
    }

    let modality = first.modality.clone();
    let units = if modality.eq_ignore_ascii_case("CT") {
        "HU".to_string()
    } else {
        String::new()
    };
    let codecs: BTreeSet<String> = kept.iter().map(|(_, s)| ts_name(&s.ts)).collect();
    let codecs = codecs.into_iter().collect::<Vec<_>>().join(" + ");
    let lossy: BTreeSet<String> = kept
        .iter()
        .filter(|(_, s)| s.lossy)
        .map(|(_, s)| ts_name(&s.ts))
        .collect();
    if !lossy.is_empty() {
        warnings.push(format!(
            "pixel data was compressed lossily ({}): values are approximations of the original",
            lossy.into_iter().collect::<Vec<_>>().join(", ")
        ));
    }
    let one_file = kept.iter().all(|(_, s)| s.path == first.path);
    let (what, unit) = if one_file && first.frames > 1 {
        ("DICOM multi-frame image", "frame")
    } else {
        ("DICOM series", "slice")
    };
    Ok(RawVolume {
        dims,
        spacing,
        samples,
        units,
        modality,
        format: format!(
            "{what} ({} {unit}{}, {codecs})",
            kept.len(),
            if kept.len() == 1 { "" } else { "s" }
        ),
        warnings,
    })
}

/// The file pass 2 is reading, kept across its frames so that a multi-frame file is read and
/// parsed once.
struct OpenPixelFile {
    path: PathBuf,
    content: PixelContent,
}

enum PixelContent {
    /// The whole file and where its native PixelData value lies.
    Native {
        bytes: Vec<u8>,
        offset: usize,
        len: usize,
        big_endian: bool,
    },
    /// The parsed file, fragments included, for the transfer syntax's decoder.
    Encapsulated(Box<DefaultDicomObject>),
}

/// Environment variable that caps the decoder threads of one DICOM load (default: one per core,
/// at most 8); `1` decodes on the loading thread only.
pub(crate) const DECODE_THREADS_ENV: &str = "VOXLIGHT_DECODE_THREADS";

/// How many slices decode at once: one per core (at most 8, or [`DECODE_THREADS_ENV`]) for a
/// series of compressed single-frame files, one otherwise (uncompressed data is read, not
/// decoded; the frames of a multi-frame file share one parsed file).
fn decode_workers(kept: &[(f64, SliceInfo)]) -> usize {
    let parallel = kept
        .iter()
        .all(|(_, s)| s.frames <= 1 && matches!(s.pixel, PixelData::Encapsulated { .. }));
    if !parallel {
        return 1;
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let cap = std::env::var(DECODE_THREADS_ENV)
        .ok()
        .and_then(|v| v.trim().parse::<usize>().ok())
        .unwrap_or(8);
    cores.min(cap).clamp(1, 8).min(kept.len().max(1))
}

/// Decodes the slices of `wave` (each its own file) on one thread each, into `stored[k]`.
fn decode_in_parallel(
    wave: &[(f64, SliceInfo)],
    per_slice: usize,
    bits_stored: u16,
    stored: &mut [Vec<i32>],
) -> Result<(), VolumeError> {
    std::thread::scope(|scope| {
        let decoders: Vec<_> = wave
            .iter()
            .zip(stored.iter_mut())
            .map(|((_, s), out)| {
                let decoder = std::thread::Builder::new()
                    .name("dicom-decode".into())
                    .spawn_scoped(scope, move || {
                        FrameReader::default().read(s, per_slice, bits_stored, out)
                    });
                (s, decoder)
            })
            .collect();
        // Every thread joined before the first error is returned: a scope whose unjoined
        // thread panicked would panic itself.
        let results: Vec<Result<(), VolumeError>> = decoders
            .into_iter()
            .map(|(s, decoder)| {
                decoder
                    .map_err(|e| VolumeError::io(&s.path, "starting a decoder thread", e))?
                    .join()
                    .map_err(|_| VolumeError::format(&s.path, "the pixel data decoder panicked"))?
            })
            .collect();
        results.into_iter().collect()
    })
}

/// Appends one slice's stored values, rescaled, to `samples` (of the type chosen for the series).
fn append_rescaled(samples: &mut Samples, stored: &[i32], slope: f64, intercept: f64) {
    let (m, c) = (slope, intercept);
    match samples {
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

#[derive(Default)]
struct FrameReader {
    open: Option<OpenPixelFile>,
}

impl FrameReader {
    /// Reads one slice's pixel data into `out` as stored integer values: sign-extended from
    /// `bits_stored` (signed), masked to it (native unsigned) or clamped to it (decoded
    /// unsigned), and MONOCHROME1 turned around when there is no rescale. The file is
    /// re-validated before its pixel data is read or decoded.
    fn read(
        &mut self,
        s: &SliceInfo,
        n: usize,
        bits_stored: u16,
        out: &mut Vec<i32>,
    ) -> Result<(), VolumeError> {
        out.clear();
        let content = self.open(s)?;
        let bytes_per = s.bytes_per_sample();
        let need = n * bytes_per;
        let (data, big_endian, decoded): (Cow<[u8]>, bool, bool) = match content {
            PixelContent::Native {
                bytes,
                offset,
                len,
                big_endian,
            } => {
                let start = s.frame as usize * need;
                if start + need > *len {
                    return Err(VolumeError::format(
                        &s.path,
                        format!(
                            "PixelData is truncated: expected Columns {} × Rows {} × {bytes_per} bytes = \
                             {need} bytes{}, found {}",
                            s.cols,
                            s.rows,
                            if s.frames > 1 {
                                format!(" for frame {}", s.frame + 1)
                            } else {
                                String::new()
                            },
                            len.saturating_sub(start)
                        ),
                    ));
                }
                let at = offset + start;
                (Cow::Borrowed(&bytes[at..at + need]), *big_endian, false)
            }
            PixelContent::Encapsulated(object) => {
                (Cow::Owned(decode_frame(s, object, need)?), false, true)
            }
        };
        let shift = 32 - bits_stored as u32;
        let max_unsigned = (1u32 << bits_stored) - 1;
        let fix = |raw: u32| -> i32 {
            if s.signed {
                ((raw << shift) as i32) >> shift
            } else if decoded {
                // Codecs may code at more bits than stored (GDCM writes 12-bit data as 16-bit
                // JPEG 2000), and lossy ones then overshoot: clamp, as masking would wrap
                // 4096 to 0. Only native data has unused high bits to mask (PS3.5 8.1.1).
                raw.min(max_unsigned) as i32
            } else {
                ((raw << shift) >> shift) as i32
            }
        };
        out.reserve_exact(n);
        let data = &data[..need];
        if bytes_per == 1 {
            out.extend(data.iter().map(|&x| fix(x as u32)));
        } else if big_endian {
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
        if s.monochrome1 && !s.has_rescale {
            invert_monochrome1(out, bits_stored, s.signed);
        }
        Ok(())
    }

    /// The pixel content of `s`'s file, reading and checking the file unless it is open.
    fn open(&mut self, s: &SliceInfo) -> Result<&PixelContent, VolumeError> {
        // Taking the previous file out drops it before the next one is read.
        let open = match self.open.take().filter(|open| open.path == s.path) {
            Some(open) => open,
            None => OpenPixelFile {
                path: s.path.clone(),
                content: read_pixel_content(&s.path)?,
            },
        };
        Ok(&self.open.insert(open).content)
    }
}

/// Reads and checks a whole file for its pixel data.
fn read_pixel_content(path: &Path) -> Result<PixelContent, VolumeError> {
    let bytes =
        std::fs::read(path).map_err(|e| VolumeError::io(path, "reading the DICOM file", e))?;
    let scan = prescan(&bytes).map_err(|m| VolumeError::format(path, m))?;
    match scan.pixel {
        PixelData::Native { offset, len } => Ok(PixelContent::Native {
            bytes,
            offset,
            len,
            big_endian: scan.ts == EXPLICIT_VR_BIG_ENDIAN,
        }),
        PixelData::Encapsulated { .. } => {
            let object = parse_file(&bytes, false).map_err(|m| VolumeError::format(path, m))?;
            Ok(PixelContent::Encapsulated(Box::new(object)))
        }
        PixelData::Absent => Err(VolumeError::format(
            path,
            "DICOM file has no PixelData element",
        )),
    }
}

/// Decodes frame `s.frame` of an encapsulated file with dicom-rs's decoder for its transfer
/// syntax, or libjpeg-turbo's for 12-bit lossy JPEG: `need` bytes of little-endian samples,
/// BitsAllocated wide.
fn decode_frame(
    s: &SliceInfo,
    object: &DefaultDicomObject,
    need: usize,
) -> Result<Vec<u8>, VolumeError> {
    let ts = object.meta().transfer_syntax();
    let what = if s.frames > 1 {
        format!("frame {} of {}", s.frame + 1, s.frames)
    } else {
        "the image".to_string()
    };
    // The frame's fragments, joined when it spans several (found by the basic offset table).
    let Some(data) = object.frame_pixel_data(s.frame) else {
        return Err(VolumeError::format(
            &s.path,
            format!("{what} has no pixel data fragment (or no offset table entry)"),
        ));
    };
    if uses_jpeg12(s) {
        match jpeg12::decode_gray12(&data, s.cols, s.rows) {
            Ok(Some(samples)) if samples.len() * 2 == need => {
                let mut buf = Vec::with_capacity(need);
                buf.extend(samples.iter().flat_map(|v| v.to_le_bytes()));
                return Ok(buf);
            }
            Ok(Some(samples)) => {
                return Err(VolumeError::format(
                    &s.path,
                    format!(
                        "decoding {what} ({}) gave {} 16-bit samples; Columns {} × Rows {} × {} \
                         bytes needs {need} bytes",
                        ts_label(ts),
                        samples.len(),
                        s.cols,
                        s.rows,
                        s.bytes_per_sample()
                    ),
                ));
            }
            // An 8-bit stream despite the bits stored: jpeg-decoder reads it below.
            Ok(None) => {}
            Err(why) => {
                return Err(VolumeError::format(
                    &s.path,
                    format!("decoding {what} ({}) failed: {why}", ts_label(ts)),
                ));
            }
        }
    }
    let reader = TransferSyntaxRegistry
        .get(ts)
        .and_then(|t| t.pixel_data_reader())
        .ok_or_else(|| {
            VolumeError::unsupported(
                &s.path,
                format!(
                    "transfer syntax {}: no decoder for it is built in",
                    ts_label(ts)
                ),
            )
        })?;
    let frame = OneFrame {
        file: object,
        data: &data,
    };
    // The codecs index buffers with sizes taken from the stream and can panic on malformed
    // input; a damaged file must give an error, not bring the server down.
    let decoded = catch_unwind(AssertUnwindSafe(|| {
        let mut buf = Vec::new();
        reader.decode_frame(&frame, 0, &mut buf).map(|()| buf)
    }));
    let buf = match decoded {
        Ok(Ok(buf)) => buf,
        Ok(Err(e)) => {
            return Err(VolumeError::format(
                &s.path,
                format!(
                    "decoding {what} ({}) failed: {}",
                    ts_label(ts),
                    short_err(e)
                ),
            ));
        }
        Err(panic) => {
            let why = panic
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| panic.downcast_ref::<&str>().copied())
                .unwrap_or("no message");
            return Err(VolumeError::format(
                &s.path,
                format!(
                    "decoding {what} ({}) failed: the decoder crashed ({})",
                    ts_label(ts),
                    short_err(why)
                ),
            ));
        }
    };
    if buf.len() < need {
        return Err(VolumeError::format(
            &s.path,
            format!(
                "decoding {what} ({}) gave {} bytes; Columns {} × Rows {} × {} bytes needs {need}",
                ts_label(ts),
                buf.len(),
                s.cols,
                s.rows,
                s.bytes_per_sample()
            ),
        ));
    }
    Ok(buf)
}

/// One frame of an encapsulated file, presented to a decoder as a single-frame object. The JPEG
/// decoder copies all of an object's fragments for every frame it decodes, which would make a
/// multi-frame file cost frames × file size.
struct OneFrame<'a> {
    file: &'a DefaultDicomObject,
    data: &'a [u8],
}

impl PixelDataObject for OneFrame<'_> {
    fn transfer_syntax_uid(&self) -> &str {
        self.file.transfer_syntax_uid()
    }

    fn rows(&self) -> Option<u16> {
        self.file.rows()
    }

    fn cols(&self) -> Option<u16> {
        self.file.cols()
    }

    fn samples_per_pixel(&self) -> Option<u16> {
        self.file.samples_per_pixel()
    }

    fn bits_allocated(&self) -> Option<u16> {
        self.file.bits_allocated()
    }

    fn bits_stored(&self) -> Option<u16> {
        self.file.bits_stored()
    }

    fn photometric_interpretation(&self) -> Option<&str> {
        self.file.photometric_interpretation()
    }

    fn number_of_frames(&self) -> Option<u32> {
        Some(1)
    }

    fn number_of_fragments(&self) -> Option<u32> {
        Some(1)
    }

    fn fragment(&self, fragment: usize) -> Option<Cow<'_, [u8]>> {
        (fragment == 0).then_some(Cow::Borrowed(self.data))
    }

    fn offset_table(&self) -> Option<Cow<'_, [u32]>> {
        Some(Cow::Borrowed(&[]))
    }

    fn raw_pixel_data(&self) -> Option<RawPixelData> {
        Some(RawPixelData {
            fragments: vec![self.data.to_vec()].into(),
            offset_table: Default::default(),
        })
    }
}

/// MONOCHROME1 (PS3.3 C.7.6.3.1.2) displays the minimum as white. PS3.4 N.2 applies that
/// inversion last, after the Modality LUT (rescale), so rescaled values such as HU mean the same
/// under MONOCHROME1 and MONOCHROME2 and are left alone. Without a rescale the values carry no
/// units, only their display polarity, so they are mirrored within the stored range (unsigned:
/// (2^BitsStored − 1) − v; signed: −1 − v): larger then means brighter, as in MONOCHROME2.
fn invert_monochrome1(values: &mut [i32], bits_stored: u16, signed: bool) {
    let max_unsigned = ((1i64 << bits_stored) - 1) as i32;
    for v in values {
        *v = if signed { -1 - *v } else { max_unsigned - *v };
    }
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
    fn monochrome1_is_mirrored_within_the_stored_range() {
        let mut unsigned = vec![0, 1, 4094, 4095];
        invert_monochrome1(&mut unsigned, 12, false);
        assert_eq!(unsigned, vec![4095, 4094, 1, 0]);
        let mut signed = vec![-128, -1, 0, 127];
        invert_monochrome1(&mut signed, 8, true);
        assert_eq!(signed, vec![127, 0, -1, -128]);
    }

    #[test]
    fn attributes_encoded_as_un_are_read_by_their_dictionary_vr() {
        use dicom_core::{DataElement, PrimitiveValue};
        let mut obj = InMemDicomObject::new_empty();
        let un = |bytes: &[u8]| PrimitiveValue::U8(bytes.to_vec().into());
        obj.put(DataElement::new(
            tags::RESCALE_INTERCEPT,
            VR::UN,
            un(b"-1000 "),
        ));
        obj.put(DataElement::new(
            tags::PIXEL_SPACING,
            VR::UN,
            un(b"0.5\\0.25"),
        ));
        obj.put(DataElement::new(tags::INSTANCE_NUMBER, VR::UN, un(b"42")));
        obj.put(DataElement::new(
            tags::ROWS,
            VR::UN,
            un(&512u16.to_le_bytes()),
        ));
        assert_eq!(get_f64(&obj, tags::RESCALE_INTERCEPT), Some(-1000.0));
        assert_eq!(get_f64s(&obj, tags::PIXEL_SPACING), Some(vec![0.5, 0.25]));
        assert_eq!(get_int(&obj, tags::INSTANCE_NUMBER), Some(42));
        assert_eq!(get_int(&obj, tags::ROWS), Some(512));
    }

    #[test]
    fn median_and_cross() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert_eq!(cross([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0]);
    }
}
