//! NRRD loader: attached `.nrrd` and detached `.nhdr` headers; raw, gzip and ascii encodings.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use flate2::bufread::MultiGzDecoder;

use crate::raw::{
    Decoded, RawVolume, SampleMode, SampleType, Samples, Streamed, byte_count, check_dims,
    check_spacing, read_samples_as, read_samples_mode,
};
use crate::{Endian, VolumeError};

/// Largest header we accept (headers are text; this bounds memory on garbage input).
const MAX_HEADER: u64 = 1 << 20;

/// Maps an NRRD type name (any of the spec's aliases) to a sample type.
fn parse_type(s: &str) -> Option<SampleType> {
    let s = s.trim().to_ascii_lowercase();
    Some(match s.as_str() {
        "signed char" | "int8" | "int8_t" => SampleType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => SampleType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            SampleType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => {
            SampleType::U16
        }
        "int" | "signed int" | "int32" | "int32_t" => SampleType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => SampleType::U32,
        "float" => SampleType::F32,
        "double" => SampleType::F64,
        _ => return None,
    })
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Encoding {
    Raw,
    Gzip,
    Ascii,
}

struct Header {
    fields: Vec<(String, String)>,
    /// Byte offset just past the blank line that ends the header (attached data start).
    data_offset: u64,
    /// Whether a blank line terminated the header (otherwise EOF did).
    terminated: bool,
}

impl Header {
    fn get(&self, key: &str) -> Option<&str> {
        self.fields
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

fn read_header(path: &Path, file: &mut File) -> Result<Header, VolumeError> {
    let mut r = BufReader::new(file.take(MAX_HEADER));
    let mut line = Vec::new();
    let mut offset: u64 = 0;
    let mut fields = Vec::new();
    let mut first = true;
    let mut terminated = false;
    loop {
        line.clear();
        let n = r
            .read_until(b'\n', &mut line)
            .map_err(|e| VolumeError::io(path, "reading the NRRD header", e))?;
        if n == 0 {
            break;
        }
        offset += n as u64;
        if offset >= MAX_HEADER && line.last() != Some(&b'\n') {
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD header is longer than {MAX_HEADER} bytes without a blank line ending it"
                ),
            ));
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim_end_matches(['\n', '\r']);
        if first {
            first = false;
            if !text.starts_with("NRRD000") {
                let shown: String = text.chars().take(16).collect();
                return Err(VolumeError::format(
                    path,
                    format!(
                        "not a NRRD file: expected magic \"NRRD000x\" on the first line, found {shown:?}"
                    ),
                ));
            }
            continue;
        }
        if text.is_empty() {
            terminated = true;
            break;
        }
        if text.starts_with('#') {
            continue;
        }
        if let Some((k, v)) = text.split_once(": ") {
            fields.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
        } else if text.contains(":=") {
            // key/value pair (free-form metadata), ignored
        } else {
            let shown: String = text.chars().take(60).collect();
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD header line {shown:?} is neither a \"field: value\" line nor a comment"
                ),
            ));
        }
    }
    if first {
        return Err(VolumeError::format(
            path,
            "file is empty; expected a NRRD header",
        ));
    }
    Ok(Header {
        fields,
        data_offset: offset,
        terminated,
    })
}

fn field<'a>(path: &Path, h: &'a Header, key: &str) -> Result<&'a str, VolumeError> {
    h.get(key).ok_or_else(|| {
        VolumeError::format(path, format!("NRRD header has no required field \"{key}\""))
    })
}

fn parse_num<T: std::str::FromStr>(path: &Path, key: &str, s: &str) -> Result<T, VolumeError> {
    s.trim().parse::<T>().map_err(|_| {
        VolumeError::format(
            path,
            format!(
                "NRRD field \"{key}\": cannot parse {s:?} as a {}",
                std::any::type_name::<T>()
            ),
        )
    })
}

/// Parses `(1,0,0) (0,1,0) none` into vectors (None for `none`).
fn parse_vectors(path: &Path, s: &str) -> Result<Vec<Option<Vec<f64>>>, VolumeError> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if let Some(r) = rest.strip_prefix("none") {
            out.push(None);
            rest = r.trim_start();
            continue;
        }
        let (Some(open), Some(close)) = (rest.find('('), rest.find(')')) else {
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD field \"space directions\": expected \"(x,y,z)\" vectors or \"none\", found {s:?}"
                ),
            ));
        };
        if open != 0 || close < open {
            return Err(VolumeError::format(
                path,
                format!("NRRD field \"space directions\": malformed vector list {s:?}"),
            ));
        }
        let comps = rest[1..close]
            .split(',')
            .map(|c| parse_num::<f64>(path, "space directions", c))
            .collect::<Result<Vec<_>, _>>()?;
        out.push(Some(comps));
        rest = rest[close + 1..].trim_start();
    }
    Ok(out)
}

/// A 2D image is one voxel thick: as thick as its finer in-plane spacing (so that the box
/// of an image in metres is not a needle of unit height).
fn flat_spacing(spacing: &mut [f64; 3], spatial_axes: usize) {
    if spatial_axes == 2 {
        spacing[2] = spacing[0].min(spacing[1]);
    }
}

/// Loads a `.nrrd` or `.nhdr` file.
pub fn load_nrrd(path: &Path) -> Result<RawVolume, VolumeError> {
    load_nrrd_with(path, false).map(|(raw, _)| raw)
}

/// [`load_nrrd`]; with `streaming`, binary samples that are not 16-bit are read straight to 16
/// bits ([`read_streamed`]; the [`RawVolume`] then holds none).
pub(crate) fn load_nrrd_with(
    path: &Path,
    streaming: bool,
) -> Result<(RawVolume, Option<Streamed>), VolumeError> {
    let mut file =
        File::open(path).map_err(|e| VolumeError::io(path, "opening the NRRD file", e))?;
    let header = read_header(path, &mut file)?;
    let mut warnings = Vec::new();

    let type_s = field(path, &header, "type")?;
    let ty = parse_type(type_s).ok_or_else(|| {
        VolumeError::unsupported(
            path,
            format!(
                "NRRD type {type_s:?}; supported: int8, uint8, int16, uint16, int32, uint32, float, \
                 double (and their aliases)"
            ),
        )
    })?;
    let dimension: u64 = parse_num(path, "dimension", field(path, &header, "dimension")?)?;
    let sizes_s = field(path, &header, "sizes")?;
    let sizes = sizes_s
        .split_whitespace()
        .map(|s| parse_num::<u64>(path, "sizes", s))
        .collect::<Result<Vec<_>, _>>()?;
    if sizes.len() as u64 != dimension {
        return Err(VolumeError::format(
            path,
            format!(
                "NRRD field \"sizes\" has {} values but \"dimension\" is {dimension}",
                sizes.len()
            ),
        ));
    }
    // Accept 3D, 2D (nz = 1), and 4D with a leading axis of size 1.
    let (spatial_axes, dims3): (Vec<usize>, [u64; 3]) = match sizes.as_slice() {
        [x, y, z] => (vec![0, 1, 2], [*x, *y, *z]),
        [x, y] => (vec![0, 1], [*x, *y, 1]),
        [1, x, y, z] => (vec![1, 2, 3], [*x, *y, *z]),
        _ => {
            return Err(VolumeError::unsupported(
                path,
                format!(
                    "NRRD with dimension {dimension} and sizes {sizes_s:?}; expected a 3D scalar \
                     volume (2D, or 4D with a first axis of size 1, also accepted)"
                ),
            ));
        }
    };
    let dims = check_dims(path, "NRRD field \"sizes\"", dims3)?;

    let enc_s = field(path, &header, "encoding")?.to_ascii_lowercase();
    let encoding = match enc_s.as_str() {
        "raw" => Encoding::Raw,
        "gz" | "gzip" => Encoding::Gzip,
        "ascii" | "text" | "txt" => Encoding::Ascii,
        other => {
            return Err(VolumeError::unsupported(
                path,
                format!("NRRD encoding {other:?}; supported: raw, gzip, ascii"),
            ));
        }
    };

    let endian = match header.get("endian").map(|s| s.to_ascii_lowercase()) {
        Some(e) if e == "little" => Endian::Little,
        Some(e) if e == "big" => Endian::Big,
        Some(e) => {
            return Err(VolumeError::format(
                path,
                format!("NRRD field \"endian\": expected \"little\" or \"big\", found {e:?}"),
            ));
        }
        None if ty.size() == 1 || encoding == Encoding::Ascii => Endian::Little,
        None => {
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD field \"endian\" is required for {}-byte type {ty}",
                    ty.size()
                ),
            ));
        }
    };
    // Spacing: "spacings" or norms of "space directions"; 1.0 when absent.
    let mut spacing = [1.0f64; 3];
    if let Some(s) = header.get("space directions") {
        let vecs = parse_vectors(path, s)?;
        if vecs.len() != sizes.len() {
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD field \"space directions\" has {} entries but there are {} axes",
                    vecs.len(),
                    sizes.len()
                ),
            ));
        }
        for (k, &ax) in spatial_axes.iter().enumerate() {
            match &vecs[ax] {
                Some(v) => spacing[k] = v.iter().map(|c| c * c).sum::<f64>().sqrt(),
                None => {
                    return Err(VolumeError::format(
                        path,
                        format!("NRRD field \"space directions\": spatial axis {ax} is \"none\""),
                    ));
                }
            }
        }
        flat_spacing(&mut spacing, spatial_axes.len());
        spacing = check_spacing(path, "NRRD field \"space directions\"", spacing)?.map(f64::from);
    } else if let Some(s) = header.get("spacings") {
        let vals: Vec<&str> = s.split_whitespace().collect();
        if vals.len() != sizes.len() {
            return Err(VolumeError::format(
                path,
                format!(
                    "NRRD field \"spacings\" has {} values but there are {} axes",
                    vals.len(),
                    sizes.len()
                ),
            ));
        }
        for (k, &ax) in spatial_axes.iter().enumerate() {
            spacing[k] = if vals[ax].eq_ignore_ascii_case("nan") {
                f64::NAN
            } else {
                parse_num(path, "spacings", vals[ax])?
            };
        }
        flat_spacing(&mut spacing, spatial_axes.len());
        spacing = check_spacing(path, "NRRD field \"spacings\"", spacing)?.map(f64::from);
    }
    let spacing = spacing.map(|s| s as f32);

    let line_skip: u64 = match header.get("line skip").or(header.get("lineskip")) {
        Some(s) => parse_num(path, "line skip", s)?,
        None => 0,
    };
    let byte_skip: i64 = match header.get("byte skip").or(header.get("byteskip")) {
        Some(s) => parse_num(path, "byte skip", s)?,
        None => 0,
    };
    if byte_skip < -1 {
        return Err(VolumeError::format(
            path,
            format!(
                "NRRD field \"byte skip\" is {byte_skip}; expected -1 or a non-negative number"
            ),
        ));
    }
    if byte_skip == -1 && encoding != Encoding::Raw {
        return Err(VolumeError::unsupported(
            path,
            "NRRD \"byte skip: -1\" is only meaningful with raw encoding",
        ));
    }

    // Data source: detached file or the bytes after the header.
    let (data_path, data_file, data_start): (PathBuf, File, u64) = match header
        .get("data file")
        .or(header.get("datafile"))
    {
        Some(df) => {
            if df.starts_with("LIST") || df.split_whitespace().count() > 1 {
                return Err(VolumeError::unsupported(
                    path,
                    format!(
                        "NRRD \"data file: {df}\" (multiple data files); only a single data file is supported"
                    ),
                ));
            }
            let dir = path.parent().unwrap_or(Path::new("."));
            let p = dir.join(df);
            let f = File::open(&p).map_err(|e| {
                VolumeError::io(
                    &p,
                    format!(
                        "opening the data file named by {}",
                        path.file_name().unwrap_or_default().to_string_lossy()
                    ),
                    e,
                )
            })?;
            // A device or pipe (`data file: /dev/zero`) has no end: ascii data and line skips
            // would read it forever.
            let is_file = f
                .metadata()
                .map_err(|e| VolumeError::io(&p, "reading the data file's type", e))?
                .is_file();
            if !is_file {
                return Err(VolumeError::unsupported(
                    &p,
                    "the NRRD data file is not a regular file",
                ));
            }
            (p, f, 0)
        }
        None => {
            if !header.terminated {
                return Err(VolumeError::format(
                    path,
                    "NRRD header has no \"data file\" field and no blank line before attached data",
                ));
            }
            (path.to_path_buf(), file, header.data_offset)
        }
    };
    let mut data_file = data_file;
    let count = dims.iter().map(|&d| d as usize).product::<usize>();
    let nbytes = byte_count(dims, ty);
    let file_len = data_file
        .metadata()
        .map_err(|e| VolumeError::io(&data_path, "reading the file size", e))?
        .len();

    let mut start = data_start;
    if line_skip > 0 {
        data_file
            .seek(SeekFrom::Start(start))
            .map_err(|e| VolumeError::io(&data_path, "seeking to the data", e))?;
        let mut r = BufReader::new(&mut data_file);
        let mut skipped = 0u64;
        let mut buf = Vec::new();
        for _ in 0..line_skip {
            buf.clear();
            let n = r
                .by_ref()
                .take(MAX_HEADER)
                .read_until(b'\n', &mut buf)
                .map_err(|e| VolumeError::io(&data_path, "skipping lines", e))?;
            if n == 0 {
                return Err(VolumeError::format(
                    &data_path,
                    format!("NRRD \"line skip: {line_skip}\" runs past the end of the data file"),
                ));
            }
            skipped += n as u64;
        }
        start += skipped;
    }

    let what = format!("NRRD data ({}×{}×{} {ty})", dims[0], dims[1], dims[2]);
    let raw_offset = if encoding == Encoding::Raw {
        let offset = if byte_skip == -1 {
            file_len.checked_sub(nbytes).ok_or_else(|| {
                VolumeError::format(
                    &data_path,
                    format!("data file is {file_len} bytes, smaller than the {nbytes} bytes the header declares"),
                )
            })?
        } else {
            start.saturating_add(byte_skip as u64)
        };
        let available = file_len.saturating_sub(offset);
        if available < nbytes {
            return Err(VolumeError::format(
                &data_path,
                format!(
                    "{what} is truncated: expected {nbytes} bytes at offset {offset}, the file has only {available}"
                ),
            ));
        }
        if available > nbytes && byte_skip != -1 {
            warnings.push(format!(
                "{}: {} bytes after the NRRD data were ignored",
                data_path.display(),
                available - nbytes
            ));
        }
        offset
    } else {
        0
    };
    // Each pass seeks to the data again (the streaming passes of `load` read twice).
    let read = |mode: SampleMode| -> Result<Decoded, VolumeError> {
        match encoding {
            Encoding::Raw => {
                data_file
                    .seek(SeekFrom::Start(raw_offset))
                    .map_err(|e| VolumeError::io(&data_path, "seeking to the data", e))?;
                read_samples_mode(
                    BufReader::new(&mut data_file),
                    ty,
                    endian,
                    count,
                    &data_path,
                    &what,
                    mode,
                )
            }
            Encoding::Gzip => {
                data_file
                    .seek(SeekFrom::Start(start))
                    .map_err(|e| VolumeError::io(&data_path, "seeking to the gzip data", e))?;
                let mut dec = MultiGzDecoder::new(BufReader::new(&mut data_file));
                if byte_skip > 0 {
                    let skipped =
                        std::io::copy(&mut (&mut dec).take(byte_skip as u64), &mut std::io::sink())
                            .map_err(|e| {
                                VolumeError::io(
                                    &data_path,
                                    "decompressing gzip data (byte skip)",
                                    e,
                                )
                            })?;
                    if skipped < byte_skip as u64 {
                        return Err(VolumeError::format(
                            &data_path,
                            format!("gzip data ends within the {byte_skip} bytes of \"byte skip\""),
                        ));
                    }
                }
                read_samples_mode(
                    dec,
                    ty,
                    endian,
                    count,
                    &data_path,
                    &format!("{what}, gzip-decompressed"),
                    mode,
                )
            }
            Encoding::Ascii => {
                data_file
                    .seek(SeekFrom::Start(start))
                    .map_err(|e| VolumeError::io(&data_path, "seeking to the ascii data", e))?;
                read_ascii(BufReader::new(&mut data_file), ty, count, &data_path)
                    .map(Decoded::Samples)
            }
        }
    };
    // ASCII data is small and parsed once, into samples.
    let (samples, streamed) =
        read_samples_as(ty, None, streaming && encoding != Encoding::Ascii, read)?;

    let enc_name = match encoding {
        Encoding::Raw => "raw",
        Encoding::Gzip => "gzip",
        Encoding::Ascii => "ascii",
    };
    let attached = if header.get("data file").or(header.get("datafile")).is_some() {
        "detached header"
    } else {
        "attached header"
    };
    let endian_s = if ty.size() > 1 {
        format!(" {}", endian.name())
    } else {
        String::new()
    };
    Ok((
        RawVolume::unlabelled(
            dims,
            spacing,
            samples,
            format!("NRRD ({enc_name}, {ty}{endian_s}, {attached})"),
            warnings,
        ),
        streamed,
    ))
}

/// Longest value accepted in ascii data: a double needs at most ~25 characters.
const MAX_ASCII_TOKEN: usize = 64;

/// Parses whitespace/comma-separated numbers into samples, streaming: memory grows with the
/// values actually read (never with what the header declares), and a value longer than
/// [`MAX_ASCII_TOKEN`] is an error rather than an endless read. Anything after `count` values
/// is ignored.
fn read_ascii(
    mut r: impl Read,
    ty: SampleType,
    count: usize,
    path: &Path,
) -> Result<Samples, VolumeError> {
    let mut vals: Vec<f64> = Vec::with_capacity(count.min(1 << 16));
    let mut token: Vec<u8> = Vec::with_capacity(MAX_ASCII_TOKEN);
    let mut lineno = 1usize;
    let mut buf = vec![0u8; 1 << 16];
    let push = |token: &[u8], lineno: usize, vals: &mut Vec<f64>| {
        let v = std::str::from_utf8(token)
            .ok()
            .and_then(|t| t.parse::<f64>().ok())
            .ok_or_else(|| {
                let shown = String::from_utf8_lossy(token);
                VolumeError::format(
                    path,
                    format!("ascii data line {lineno}: {shown:?} is not a number"),
                )
            })?;
        vals.push(v);
        Ok::<(), VolumeError>(())
    };
    'read: while vals.len() < count {
        let n = match r.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(VolumeError::io(path, "reading ascii data", e)),
        };
        for &c in &buf[..n] {
            if c.is_ascii_whitespace() || c == b',' {
                if !token.is_empty() {
                    push(&token, lineno, &mut vals)?;
                    token.clear();
                    if vals.len() == count {
                        break 'read;
                    }
                }
                if c == b'\n' {
                    lineno += 1;
                }
            } else if token.len() == MAX_ASCII_TOKEN {
                return Err(VolumeError::format(
                    path,
                    format!(
                        "ascii data line {lineno}: a value longer than {MAX_ASCII_TOKEN} characters"
                    ),
                ));
            } else {
                token.push(c);
            }
        }
    }
    if vals.len() < count && !token.is_empty() {
        push(&token, lineno, &mut vals)?;
    }
    if vals.len() < count {
        return Err(VolumeError::format(
            path,
            format!(
                "ascii data is truncated: expected {count} values, found {}",
                vals.len()
            ),
        ));
    }
    Ok(Samples::from_f64(ty, vals))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_aliases() {
        for s in ["uchar", "unsigned char", "uint8", "uint8_t"] {
            assert_eq!(parse_type(s), Some(SampleType::U8), "{s}");
        }
        for s in [
            "short",
            "short int",
            "signed short",
            "signed short int",
            "int16",
            "int16_t",
        ] {
            assert_eq!(parse_type(s), Some(SampleType::I16), "{s}");
        }
        for s in [
            "ushort",
            "unsigned short",
            "unsigned short int",
            "uint16",
            "uint16_t",
        ] {
            assert_eq!(parse_type(s), Some(SampleType::U16), "{s}");
        }
        for s in ["int", "signed int", "int32", "int32_t"] {
            assert_eq!(parse_type(s), Some(SampleType::I32), "{s}");
        }
        for s in ["uint", "unsigned int", "uint32", "uint32_t"] {
            assert_eq!(parse_type(s), Some(SampleType::U32), "{s}");
        }
        assert_eq!(parse_type("signed char"), Some(SampleType::I8));
        assert_eq!(parse_type("float"), Some(SampleType::F32));
        assert_eq!(parse_type("double"), Some(SampleType::F64));
        assert_eq!(parse_type("block"), None);
    }

    #[test]
    fn vectors() {
        let p = Path::new("t");
        let v = parse_vectors(p, "(1,0,0) (0,2.5,0) none").unwrap();
        assert_eq!(
            v,
            vec![Some(vec![1.0, 0.0, 0.0]), Some(vec![0.0, 2.5, 0.0]), None]
        );
        assert!(parse_vectors(p, "(1,0,0").is_err());
        assert!(parse_vectors(p, "x(1,0,0)").is_err());
    }
}
