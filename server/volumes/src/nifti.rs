//! NIfTI-1 loader (`.nii`, `.nii.gz`, and `.hdr`/`.img` pairs), hand-parsed 348-byte header.

use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use flate2::bufread::MultiGzDecoder;

use crate::raw::{
    Affine, Decoded, RawVolume, SampleMode, SampleType, Streamed, byte_count, check_dims,
    check_spacing, read_samples_as, read_samples_mode,
};
use crate::{Endian, VolumeError};

const HEADER_SIZE: usize = 348;

fn is_gz(path: &Path) -> bool {
    path.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.to_ascii_lowercase().ends_with(".gz"))
}

fn open_maybe_gz(path: &Path) -> Result<Box<dyn Read>, VolumeError> {
    let f = File::open(path).map_err(|e| VolumeError::io(path, "opening the NIfTI file", e))?;
    let r = BufReader::new(f);
    Ok(if is_gz(path) {
        Box::new(MultiGzDecoder::new(r))
    } else {
        Box::new(r)
    })
}

/// Fills `buf` completely; returns how many bytes were read before EOF.
fn read_full(r: &mut dyn Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

struct Hdr<'a> {
    b: &'a [u8],
    e: Endian,
}

impl Hdr<'_> {
    fn i16(&self, off: usize) -> i16 {
        let a = [self.b[off], self.b[off + 1]];
        match self.e {
            Endian::Little => i16::from_le_bytes(a),
            Endian::Big => i16::from_be_bytes(a),
        }
    }
    fn f32(&self, off: usize) -> f32 {
        let a = [
            self.b[off],
            self.b[off + 1],
            self.b[off + 2],
            self.b[off + 3],
        ];
        match self.e {
            Endian::Little => f32::from_le_bytes(a),
            Endian::Big => f32::from_be_bytes(a),
        }
    }
}

fn datatype(code: i16) -> Result<SampleType, String> {
    Ok(match code {
        2 => SampleType::U8,
        4 => SampleType::I16,
        8 => SampleType::I32,
        16 => SampleType::F32,
        64 => SampleType::F64,
        256 => SampleType::I8,
        512 => SampleType::U16,
        768 => SampleType::U32,
        1 => return Err("datatype 1 (binary, 1 bit per voxel)".into()),
        32 => return Err("datatype 32 (complex64)".into()),
        128 => return Err("datatype 128 (RGB24)".into()),
        1024 => return Err("datatype 1024 (int64)".into()),
        1280 => return Err("datatype 1280 (uint64)".into()),
        1536 => return Err("datatype 1536 (float128)".into()),
        1792 => return Err("datatype 1792 (complex128)".into()),
        2048 => return Err("datatype 2048 (complex256)".into()),
        2304 => return Err("datatype 2304 (RGBA32)".into()),
        other => return Err(format!("unknown datatype code {other}")),
    })
}

/// Loads a NIfTI-1 file.
pub fn load_nifti(path: &Path) -> Result<RawVolume, VolumeError> {
    load_nifti_with(path, false).map(|(raw, _)| raw)
}

/// [`load_nifti`]; with `streaming`, samples that are not 16-bit (or are rescaled) are read
/// straight to 16 bits ([`read_streamed`]; the [`RawVolume`] then holds none).
pub(crate) fn load_nifti_with(
    path: &Path,
    streaming: bool,
) -> Result<(RawVolume, Option<Streamed>), VolumeError> {
    let mut r = open_maybe_gz(path)?;
    let mut hb = [0u8; HEADER_SIZE];
    let got = read_full(&mut r, &mut hb).map_err(|e| {
        VolumeError::io(
            path,
            if is_gz(path) {
                "decompressing the NIfTI header (gzip)"
            } else {
                "reading the NIfTI header"
            },
            e,
        )
    })?;
    if got < HEADER_SIZE {
        return Err(VolumeError::format(
            path,
            format!("NIfTI header is truncated: expected {HEADER_SIZE} bytes, found {got}"),
        ));
    }
    let le = i32::from_le_bytes([hb[0], hb[1], hb[2], hb[3]]);
    let be = i32::from_be_bytes([hb[0], hb[1], hb[2], hb[3]]);
    let e = if le == 348 {
        Endian::Little
    } else if be == 348 {
        Endian::Big
    } else if le == 540 || be == 540 {
        return Err(VolumeError::unsupported(
            path,
            "NIfTI-2 (sizeof_hdr 540); only NIfTI-1 is supported",
        ));
    } else {
        return Err(VolumeError::format(
            path,
            format!(
                "not a NIfTI-1 file: sizeof_hdr is {le} (little-endian) / {be} (big-endian), expected 348"
            ),
        ));
    };
    let h = Hdr { b: &hb, e };
    let magic = &hb[344..348];
    let single_file = match magic {
        b"n+1\0" => true,
        b"ni1\0" => false,
        _ => {
            return Err(VolumeError::unsupported(
                path,
                format!(
                    "NIfTI magic {:?}: expected \"n+1\" (single file) or \"ni1\" (.hdr/.img pair); \
                     ANALYZE 7.5 files are not supported",
                    String::from_utf8_lossy(&magic[..3])
                ),
            ));
        }
    };

    let dim: [i16; 8] = std::array::from_fn(|i| h.i16(40 + 2 * i));
    let ndim = dim[0];
    if !(1..=7).contains(&ndim) {
        return Err(VolumeError::format(
            path,
            format!("NIfTI dim[0] (number of dimensions) is {ndim}; expected 1..7"),
        ));
    }
    for i in 1..=ndim as usize {
        if dim[i] <= 0 {
            return Err(VolumeError::format(
                path,
                format!(
                    "NIfTI dim[{i}] is {}; expected a positive size (dims are {:?})",
                    dim[i],
                    &dim[1..=ndim as usize]
                ),
            ));
        }
    }
    let d = |i: usize| if (i as i16) <= ndim { dim[i] as u64 } else { 1 };
    let dims = check_dims(path, "NIfTI dim[1..3]", [d(1), d(2), d(3)])?;
    let mut warnings = Vec::new();
    let extra: u64 = (4..=7).map(d).product();
    if extra > 1 {
        warnings.push(format!(
            "{}: NIfTI has {extra} volumes (dim[4..7] = {:?}); only the first is loaded",
            path.display(),
            &dim[4..=ndim.max(4) as usize]
        ));
    }

    let dt_code = h.i16(70);
    let ty = datatype(dt_code).map_err(|m| {
        VolumeError::unsupported(
            path,
            format!(
                "NIfTI {m}; supported: uint8, int8, int16, uint16, int32, uint32, float32, float64"
            ),
        )
    })?;
    let bitpix = h.i16(72);
    if bitpix as usize != ty.size() * 8 {
        warnings.push(format!(
            "{}: NIfTI bitpix is {bitpix} but datatype {dt_code} ({ty}) has {} bits; using the datatype",
            path.display(),
            ty.size() * 8
        ));
    }

    let pixdim: [f32; 8] = std::array::from_fn(|i| h.f32(76 + 4 * i));
    let mut spacing = [1.0f32; 3];
    for k in 0..3 {
        let p = pixdim[k + 1];
        if (k as i16) >= ndim {
            continue;
        }
        if p.is_nan() || p.is_infinite() {
            return Err(VolumeError::format(
                path,
                format!(
                    "NIfTI pixdim[{}] is {p}; expected a finite voxel size",
                    k + 1
                ),
            ));
        }
        if p == 0.0 {
            warnings.push(format!(
                "{}: NIfTI pixdim[{}] is 0; using spacing 1",
                path.display(),
                k + 1
            ));
        } else if p < 0.0 {
            warnings.push(format!(
                "{}: NIfTI pixdim[{}] is negative ({p}); using its absolute value",
                path.display(),
                k + 1
            ));
            spacing[k] = -p;
        } else {
            spacing[k] = p;
        }
    }

    // Axes the image does not have are as thick as its finest voxel edge.
    let finest = spacing[..(ndim as usize).min(3)]
        .iter()
        .copied()
        .fold(f32::INFINITY, f32::min);
    for s in spacing.iter_mut().skip(ndim as usize) {
        *s = finest;
    }
    let spacing = check_spacing(path, "NIfTI pixdim[1..3]", spacing.map(f64::from))?;

    let vox_offset = h.f32(108);
    let slope = h.f32(112);
    let inter = h.f32(116);
    let count = dims.iter().map(|&d| d as usize).product::<usize>();
    let nbytes = byte_count(dims, ty);
    let what = format!(
        "NIfTI voxel data ({}×{}×{} {ty})",
        dims[0], dims[1], dims[2]
    );

    // Where the voxel data starts: the file (or `.img`) and the bytes before it.
    let (data_path, offset) = if single_file {
        if !vox_offset.is_finite() || vox_offset < HEADER_SIZE as f32 || vox_offset > 1e12 {
            return Err(VolumeError::format(
                path,
                format!(
                    "NIfTI vox_offset is {vox_offset}; expected at least {HEADER_SIZE} for a single-file (n+1) NIfTI"
                ),
            ));
        }
        if !is_gz(path) {
            let len = std::fs::metadata(path)
                .map_err(|e| VolumeError::io(path, "reading the file size", e))?
                .len();
            let available = len.saturating_sub(vox_offset as u64);
            if available < nbytes {
                return Err(VolumeError::format(
                    path,
                    format!(
                        "{what} is truncated: expected {nbytes} bytes from vox_offset {vox_offset}, \
                         the file has only {available}"
                    ),
                ));
            }
        }
        (path.to_path_buf(), vox_offset as u64)
    } else {
        let img = companion_image(path)?;
        let offset = if vox_offset.is_finite() && vox_offset > 0.0 {
            vox_offset as u64
        } else {
            0
        };
        (img, offset)
    };
    // Each pass reads from the start again (the streaming passes of `load` read twice).
    let read = |mode: SampleMode| -> Result<Decoded, VolumeError> {
        let mut r = open_maybe_gz(&data_path)?;
        let skipped = std::io::copy(&mut (&mut r).take(offset), &mut std::io::sink())
            .map_err(|e| VolumeError::io(&data_path, "skipping to vox_offset", e))?;
        if skipped < offset {
            return Err(VolumeError::format(
                &data_path,
                format!("file ends at byte {skipped} before vox_offset {offset}"),
            ));
        }
        read_samples_mode(r, ty, e, count, &data_path, &what, mode)
    };

    // Apply scl_slope / scl_inter when they are not the identity.
    let scaled =
        slope != 0.0 && slope.is_finite() && inter.is_finite() && !(slope == 1.0 && inter == 0.0);
    if !scaled && (slope.is_nan() || inter.is_nan() || slope.is_infinite() || inter.is_infinite()) {
        warnings.push(format!(
            "{}: NIfTI scl_slope/scl_inter ({slope}, {inter}) are not finite; ignored",
            path.display()
        ));
    }
    let affine = scaled.then_some(Affine {
        slope: slope as f64,
        inter: inter as f64,
    });
    let (samples, streamed) = read_samples_as(ty, affine, streaming, read)?;

    let mut fmt = format!(
        "NIfTI-1 ({}{ty} {}",
        if is_gz(path) { "gzip, " } else { "" },
        e.name()
    );
    if !single_file {
        fmt.push_str(", .hdr/.img pair");
    }
    if scaled {
        fmt.push_str(&format!(", scaled ×{slope} + {inter}"));
    }
    fmt.push(')');
    Ok((
        RawVolume::unlabelled(dims, spacing, samples, fmt, warnings),
        streamed,
    ))
}

/// The `.img` (or `.img.gz`) file beside a `.hdr` header.
fn companion_image(path: &Path) -> Result<PathBuf, VolumeError> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let lower = name.to_ascii_lowercase();
    let stem = if let Some(s) = lower.strip_suffix(".hdr.gz") {
        &name[..s.len()]
    } else if let Some(s) = lower.strip_suffix(".hdr") {
        &name[..s.len()]
    } else {
        return Err(VolumeError::format(
            path,
            "NIfTI magic \"ni1\" says the data is in a separate .img file, but this file is not a .hdr",
        ));
    };
    for ext in [".img", ".img.gz"] {
        let p = path.with_file_name(format!("{stem}{ext}"));
        if p.is_file() {
            return Ok(p);
        }
    }
    Err(VolumeError::format(
        path,
        format!(
            "NIfTI header (magic \"ni1\") needs {stem}.img or {stem}.img.gz beside it; neither exists"
        ),
    ))
}
