//! VTK XML ImageData (`.vti`) loader: appended raw data (plain or zlib-compressed blocks),
//! inline base64 `binary` and inline `ascii` arrays. The XML head is scanned by hand.

use std::io::Read;
use std::path::Path;

use flate2::bufread::ZlibDecoder;

use crate::raw::{
    Decoded, RawVolume, SampleBuilder, SampleType, Samples, Streamed, byte_count, check_dims,
    check_spacing, read_samples_as,
};
use crate::{Endian, VolumeError};

#[derive(Debug)]
struct Tag {
    name: String,
    attrs: Vec<(String, String)>,
    closing: bool,
    /// Byte index just past the tag's `>`.
    end: usize,
}

impl Tag {
    fn attr(&self, k: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(a, _)| a == k)
            .map(|(_, v)| v.as_str())
    }
}

fn find(hay: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    if from >= hay.len() {
        return None;
    }
    hay[from..]
        .windows(needle.len())
        .position(|w| w == needle)
        .map(|p| p + from)
}

/// Scans XML tags in `b` (text between tags is skipped).
fn scan_tags(path: &Path, b: &[u8]) -> Result<Vec<Tag>, VolumeError> {
    let err =
        |pos: usize, m: &str| VolumeError::format(path, format!("VTK XML header, byte {pos}: {m}"));
    let mut tags = Vec::new();
    let mut i = 0;
    while let Some(lt) = b[i..].iter().position(|&c| c == b'<').map(|p| p + i) {
        let start = lt;
        i = lt + 1;
        if b[i..].starts_with(b"!--") {
            i = find(b, b"-->", i).ok_or_else(|| err(start, "unterminated comment"))? + 3;
            continue;
        }
        if b.get(i) == Some(&b'?') || b.get(i) == Some(&b'!') {
            i = find(b, b">", i).ok_or_else(|| err(start, "unterminated declaration"))? + 1;
            continue;
        }
        let closing = b.get(i) == Some(&b'/');
        if closing {
            i += 1;
        }
        let ns = i;
        while i < b.len() && !b[i].is_ascii_whitespace() && b[i] != b'>' && b[i] != b'/' {
            i += 1;
        }
        if i == ns {
            return Err(err(start, "tag without a name"));
        }
        let name = String::from_utf8_lossy(&b[ns..i]).into_owned();
        let mut attrs = Vec::new();
        loop {
            while i < b.len() && b[i].is_ascii_whitespace() {
                i += 1;
            }
            match b.get(i) {
                None => return Err(err(start, &format!("unterminated <{name}> tag"))),
                Some(b'>') => {
                    i += 1;
                    break;
                }
                Some(b'/') => {
                    if b.get(i + 1) != Some(&b'>') {
                        return Err(err(i, &format!("expected \"/>\" in <{name}>")));
                    }
                    i += 2;
                    break;
                }
                _ => {}
            }
            let an = i;
            while i < b.len() && b[i] != b'=' && !b[i].is_ascii_whitespace() && b[i] != b'>' {
                i += 1;
            }
            let aname = String::from_utf8_lossy(&b[an..i]).into_owned();
            while i < b.len() && b[i].is_ascii_whitespace() {
                i += 1;
            }
            if b.get(i) != Some(&b'=') {
                return Err(err(
                    i,
                    &format!("attribute {aname:?} of <{name}> has no value"),
                ));
            }
            i += 1;
            while i < b.len() && b[i].is_ascii_whitespace() {
                i += 1;
            }
            let q = match b.get(i) {
                Some(&c) if c == b'"' || c == b'\'' => c,
                _ => {
                    return Err(err(
                        i,
                        &format!("attribute {aname:?} of <{name}>: expected a quoted value"),
                    ));
                }
            };
            i += 1;
            let vs = i;
            while i < b.len() && b[i] != q {
                i += 1;
            }
            if i >= b.len() {
                return Err(err(
                    vs,
                    &format!("unterminated value of attribute {aname:?}"),
                ));
            }
            attrs.push((aname, String::from_utf8_lossy(&b[vs..i]).into_owned()));
            i += 1;
        }
        tags.push(Tag {
            name,
            attrs,
            closing,
            end: i,
        });
    }
    Ok(tags)
}

fn parse_list<T: std::str::FromStr>(
    path: &Path,
    what: &str,
    s: &str,
    n: usize,
) -> Result<Vec<T>, VolumeError> {
    let v: Vec<T> = s
        .split_whitespace()
        .map(|t| t.parse::<T>())
        .collect::<Result<_, _>>()
        .map_err(|_| {
            VolumeError::format(
                path,
                format!("VTK {what}: cannot parse {s:?} as {n} numbers"),
            )
        })?;
    if v.len() != n {
        return Err(VolumeError::format(
            path,
            format!(
                "VTK {what}: expected {n} numbers, found {} in {s:?}",
                v.len()
            ),
        ));
    }
    Ok(v)
}

fn vtk_type(s: &str) -> Option<SampleType> {
    Some(match s {
        "Int8" | "Char" => SampleType::I8,
        "UInt8" | "UnsignedChar" => SampleType::U8,
        "Int16" | "Short" => SampleType::I16,
        "UInt16" | "UnsignedShort" => SampleType::U16,
        "Int32" | "Int" => SampleType::I32,
        "UInt32" | "UnsignedInt" => SampleType::U32,
        "Float32" | "Float" => SampleType::F32,
        "Float64" | "Double" => SampleType::F64,
        _ => return None,
    })
}

/// Base64 decode, 4-character group by group, so that several separately padded streams
/// written back to back (as VTK does for compressed headers) decode correctly.
fn base64_decode(path: &Path, text: &[u8]) -> Result<Vec<u8>, VolumeError> {
    fn val(c: u8) -> Option<u8> {
        Some(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        })
    }
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let mut group = [0u8; 4];
    let mut n = 0;
    for (pos, &c) in text.iter().enumerate() {
        if c.is_ascii_whitespace() {
            continue;
        }
        if c != b'=' && val(c).is_none() {
            return Err(VolumeError::format(
                path,
                format!("inline binary data: byte {c:#04x} at offset {pos} is not base64"),
            ));
        }
        group[n] = c;
        n += 1;
        if n == 4 {
            n = 0;
            let pad = group.iter().filter(|&&c| c == b'=').count();
            if pad > 2 || group[..4 - pad].contains(&b'=') {
                return Err(VolumeError::format(
                    path,
                    "inline binary data: misplaced base64 padding",
                ));
            }
            let v: [u8; 4] = group.map(|c| val(c).unwrap_or(0));
            let bits = (v[0] as u32) << 18 | (v[1] as u32) << 12 | (v[2] as u32) << 6 | v[3] as u32;
            let bytes = [(bits >> 16) as u8, (bits >> 8) as u8, bits as u8];
            out.extend_from_slice(&bytes[..3 - pad]);
        }
    }
    if n != 0 {
        return Err(VolumeError::format(
            path,
            format!(
                "inline binary data: base64 text ends with an incomplete group of {n} characters"
            ),
        ));
    }
    Ok(out)
}

struct Layout {
    hsize: usize,
    endian: Endian,
    compressed: bool,
}

fn read_uint(b: &[u8], at: usize, l: &Layout) -> Option<u64> {
    let s = b.get(at..at.checked_add(l.hsize)?)?;
    Some(match (l.hsize, l.endian) {
        (4, Endian::Little) => u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as u64,
        (4, Endian::Big) => u32::from_be_bytes([s[0], s[1], s[2], s[3]]) as u64,
        (_, Endian::Little) => u64::from_le_bytes([s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]]),
        (_, Endian::Big) => u64::from_be_bytes([s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]]),
    })
}

/// Decodes one binary data block (header + payload) starting at `base` in `b`.
fn decode_block(
    path: &Path,
    b: &[u8],
    base: usize,
    l: &Layout,
    ty: SampleType,
    nbytes: u64,
    mut builder: SampleBuilder,
) -> Result<Decoded, VolumeError> {
    let trunc = |what: &str| {
        VolumeError::format(
            path,
            format!(
                "VTK data is truncated: {what} lies beyond the end of the file ({} bytes)",
                b.len()
            ),
        )
    };
    if !l.compressed {
        let declared =
            read_uint(b, base, l).ok_or_else(|| trunc("the array's byte-count header"))?;
        if declared != nbytes {
            return Err(VolumeError::format(
                path,
                format!(
                    "VTK array header says {declared} bytes, but WholeExtent × {ty} needs {nbytes}"
                ),
            ));
        }
        let start = base + l.hsize;
        let data = usize::try_from(nbytes)
            .ok()
            .and_then(|n| b.get(start..start.checked_add(n)?))
            .ok_or_else(|| trunc(&format!("{nbytes} bytes of array data at offset {start}")))?;
        builder.push(data);
        return Ok(builder.finish_decoded());
    }
    let nblocks = read_uint(b, base, l).ok_or_else(|| trunc("the compression header"))?;
    let blocksize =
        read_uint(b, base + l.hsize, l).ok_or_else(|| trunc("the compression header"))?;
    let last =
        read_uint(b, base + 2 * l.hsize, l).ok_or_else(|| trunc("the compression header"))?;
    if nblocks > (b.len() / l.hsize) as u64 {
        return Err(trunc(&format!(
            "the compression header for {nblocks} blocks"
        )));
    }
    let last_size = if last == 0 { blocksize } else { last };
    let total = if nblocks == 0 {
        Some(0)
    } else {
        (nblocks - 1)
            .checked_mul(blocksize)
            .and_then(|t| t.checked_add(last_size))
    };
    if total != Some(nbytes) || (last > blocksize) {
        return Err(VolumeError::format(
            path,
            format!(
                "VTK compression header ({nblocks} blocks of {blocksize} bytes, last {last}) does not \
                 add up to the {nbytes} bytes WholeExtent × {ty} needs"
            ),
        ));
    }
    let nblocks = nblocks as usize;
    let mut pos = base + (3 + nblocks) * l.hsize;
    let mut buf = vec![0u8; blocksize.min(1 << 20) as usize];
    for k in 0..nblocks {
        let csize = read_uint(b, base + (3 + k) * l.hsize, l)
            .ok_or_else(|| trunc("the compressed block sizes"))?;
        let comp = usize::try_from(csize)
            .ok()
            .and_then(|c| b.get(pos..pos.checked_add(c)?))
            .ok_or_else(|| {
                trunc(&format!(
                    "compressed block {k} ({csize} bytes at offset {pos})"
                ))
            })?;
        pos += comp.len();
        let want = if k + 1 == nblocks {
            last_size
        } else {
            blocksize
        };
        let mut dec = ZlibDecoder::new(comp).take(want);
        let mut got = 0u64;
        loop {
            let n = match dec.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    return Err(VolumeError::format(
                        path,
                        format!("zlib block {k} of {nblocks} is corrupt: {e}"),
                    ));
                }
            };
            got += n as u64;
            builder.push(&buf[..n]);
        }
        if got != want {
            return Err(VolumeError::format(
                path,
                format!("zlib block {k} of {nblocks} inflated to {got} bytes, expected {want}"),
            ));
        }
    }
    Ok(builder.finish_decoded())
}

/// The samples of the array at `base` in `b`: kept, or with `streaming` (and samples that are
/// not 16-bit) read straight to 16 bits ([`read_streamed`]).
fn decode_data(
    path: &Path,
    b: &[u8],
    base: usize,
    l: &Layout,
    (ty, count, nbytes): (SampleType, usize, u64),
    streaming: bool,
) -> Result<(Samples, Option<Streamed>), VolumeError> {
    let decode = |mode| {
        let builder = SampleBuilder::with_mode(ty, l.endian, count, mode);
        decode_block(path, b, base, l, ty, nbytes, builder)
    };
    read_samples_as(ty, None, streaming, decode)
}

fn parse_ascii(
    path: &Path,
    text: &[u8],
    ty: SampleType,
    count: usize,
) -> Result<Samples, VolumeError> {
    // Every value takes at least two bytes (digit and separator): no more can be in `text`.
    let mut vals = Vec::with_capacity(count.min(text.len() / 2 + 1));
    let text = String::from_utf8_lossy(text);
    for tok in text.split_whitespace() {
        let v: f64 = tok.parse().map_err(|_| {
            VolumeError::format(path, format!("ascii DataArray: {tok:?} is not a number"))
        })?;
        if vals.len() == count {
            return Err(VolumeError::format(
                path,
                format!("ascii DataArray has more than the {count} values WholeExtent needs"),
            ));
        }
        vals.push(v);
    }
    if vals.len() != count {
        return Err(VolumeError::format(
            path,
            format!(
                "ascii DataArray is truncated: expected {count} values, found {}",
                vals.len()
            ),
        ));
    }
    Ok(Samples::from_f64(ty, vals))
}

/// Loads a `.vti` file.
pub fn load_vti(path: &Path) -> Result<RawVolume, VolumeError> {
    load_vti_with(path, false).map(|(raw, _)| raw)
}

/// [`load_vti`]; with `streaming`, binary samples that are not 16-bit are read straight to 16
/// bits ([`read_streamed`]; the [`RawVolume`] then holds none).
pub(crate) fn load_vti_with(
    path: &Path,
    streaming: bool,
) -> Result<(RawVolume, Option<Streamed>), VolumeError> {
    let b = std::fs::read(path).map_err(|e| VolumeError::io(path, "reading the .vti file", e))?;
    let mut warnings = Vec::new();

    // The XML part ends at the '_' that starts raw appended data (if any).
    let (xml_end, appended_start) = match find(&b, b"<AppendedData", 0) {
        Some(p) => {
            let gt = find(&b, b">", p)
                .ok_or_else(|| VolumeError::format(path, "unterminated <AppendedData> tag"))?;
            let us = find(&b, b"_", gt).ok_or_else(|| {
                VolumeError::format(
                    path,
                    "<AppendedData> has no '_' marker before the binary data",
                )
            })?;
            (gt + 1, Some(us + 1))
        }
        None => (b.len(), None),
    };
    let tags = scan_tags(path, &b[..xml_end])?;
    fn open<'t>(tags: &'t [Tag], name: &'static str) -> impl Iterator<Item = &'t Tag> {
        tags.iter().filter(move |t| !t.closing && t.name == name)
    }

    let vtk = open(&tags, "VTKFile")
        .next()
        .ok_or_else(|| VolumeError::format(path, "not a VTK XML file: no <VTKFile> element"))?;
    if vtk.attr("type") != Some("ImageData") {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "VTK XML type {:?}; only \"ImageData\" (.vti) is supported",
                vtk.attr("type").unwrap_or("")
            ),
        ));
    }
    let endian = match vtk.attr("byte_order").unwrap_or("LittleEndian") {
        "LittleEndian" => Endian::Little,
        "BigEndian" => Endian::Big,
        o => {
            return Err(VolumeError::format(
                path,
                format!("VTKFile byte_order {o:?}; expected LittleEndian or BigEndian"),
            ));
        }
    };
    let hsize = match vtk.attr("header_type").unwrap_or("UInt32") {
        "UInt32" => 4,
        "UInt64" => 8,
        o => {
            return Err(VolumeError::format(
                path,
                format!("VTKFile header_type {o:?}; expected UInt32 or UInt64"),
            ));
        }
    };
    let compressed = match vtk.attr("compressor") {
        None | Some("") => false,
        Some("vtkZLibDataCompressor") => true,
        Some(o) => {
            return Err(VolumeError::unsupported(
                path,
                format!("VTK compressor {o:?}; only vtkZLibDataCompressor (or none) is supported"),
            ));
        }
    };
    let layout = Layout {
        hsize,
        endian,
        compressed,
    };

    let img = open(&tags, "ImageData")
        .next()
        .ok_or_else(|| VolumeError::format(path, "no <ImageData> element"))?;
    let ext: Vec<i64> = parse_list(
        path,
        "ImageData WholeExtent",
        img.attr("WholeExtent")
            .ok_or_else(|| VolumeError::format(path, "<ImageData> has no WholeExtent attribute"))?,
        6,
    )?;
    let mut d = [0u64; 3];
    for k in 0..3 {
        let n = ext[2 * k + 1] as i128 - ext[2 * k] as i128 + 1;
        if n <= 0 {
            return Err(VolumeError::format(
                path,
                format!(
                    "ImageData WholeExtent {ext:?}: axis {k} runs from {} to {}, i.e. 0 voxels",
                    ext[2 * k],
                    ext[2 * k + 1]
                ),
            ));
        }
        d[k] = u64::try_from(n).unwrap_or(u64::MAX);
    }
    let dims = check_dims(path, "ImageData WholeExtent", d)?;
    let spacing: Vec<f64> = match img.attr("Spacing") {
        Some(s) => parse_list(path, "ImageData Spacing", s, 3)?,
        None => vec![1.0; 3],
    };
    let spacing = check_spacing(
        path,
        "ImageData Spacing",
        [spacing[0], spacing[1], spacing[2]],
    )?;
    if let Some(dir) = img.attr("Direction") {
        let v: Vec<f64> = parse_list(path, "ImageData Direction", dir, 9)?;
        if v != [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
            warnings.push(format!(
                "{}: ImageData Direction {dir:?} is not identity; ignored",
                path.display()
            ));
        }
    }
    let pieces: Vec<&Tag> = open(&tags, "Piece").collect();
    if pieces.len() > 1 {
        return Err(VolumeError::unsupported(
            path,
            format!("{} <Piece> elements; only one is supported", pieces.len()),
        ));
    }
    if let Some(pe) = pieces.first().and_then(|p| p.attr("Extent")) {
        let pext: Vec<i64> = parse_list(path, "Piece Extent", pe, 6)?;
        if pext != ext {
            return Err(VolumeError::unsupported(
                path,
                format!(
                    "Piece Extent {pext:?} differs from WholeExtent {ext:?}; partial pieces are not supported"
                ),
            ));
        }
    }

    // Point data arrays.
    let pd_idx = tags
        .iter()
        .position(|t| !t.closing && t.name == "PointData")
        .ok_or_else(|| {
            VolumeError::format(path, "no <PointData> element (cell data is not supported)")
        })?;
    let scalars = tags[pd_idx].attr("Scalars");
    let arrays: Vec<&Tag> = tags[pd_idx + 1..]
        .iter()
        .take_while(|t| !(t.name == "PointData" && t.closing))
        .filter(|t| !t.closing && t.name == "DataArray")
        .collect();
    let arr = scalars
        .and_then(|s| arrays.iter().find(|a| a.attr("Name") == Some(s)))
        .or(arrays.first())
        .copied()
        .ok_or_else(|| VolumeError::format(path, "<PointData> has no <DataArray>"))?;
    if arrays.len() > 1 {
        warnings.push(format!(
            "{}: {} point data arrays; loaded {:?}",
            path.display(),
            arrays.len(),
            arr.attr("Name").unwrap_or("")
        ));
    }
    let type_s = arr.attr("type").unwrap_or("");
    let ty = vtk_type(type_s).ok_or_else(|| {
        VolumeError::unsupported(
            path,
            format!("DataArray type {type_s:?}; supported: Int8, UInt8, Int16, UInt16, Int32, UInt32, Float32, Float64"),
        )
    })?;
    let ncomp = arr.attr("NumberOfComponents").unwrap_or("1").trim();
    if ncomp != "1" {
        return Err(VolumeError::unsupported(
            path,
            format!(
                "DataArray NumberOfComponents {ncomp:?}; only scalar (1-component) arrays are supported"
            ),
        ));
    }
    let count = dims.iter().map(|&d| d as usize).product::<usize>();
    let nbytes = byte_count(dims, ty);
    let fmt_s = arr.attr("format").unwrap_or("");
    let (samples, streamed) = match fmt_s {
        "appended" => {
            let start = appended_start.ok_or_else(|| {
                VolumeError::format(
                    path,
                    "DataArray format=\"appended\" but there is no <AppendedData>",
                )
            })?;
            let app = tags
                .iter()
                .find(|t| t.name == "AppendedData" && !t.closing)
                .and_then(|t| t.attr("encoding"))
                .unwrap_or("raw");
            if app != "raw" {
                return Err(VolumeError::unsupported(
                    path,
                    format!("AppendedData encoding {app:?}; only \"raw\" is supported"),
                ));
            }
            let off: u64 = arr
                .attr("offset")
                .unwrap_or("0")
                .trim()
                .parse()
                .map_err(|_| {
                    VolumeError::format(path, "DataArray offset is not a non-negative integer")
                })?;
            let base = usize::try_from(off)
                .ok()
                .and_then(|o| start.checked_add(o))
                .filter(|&p| p <= b.len())
                .ok_or_else(|| {
                    VolumeError::format(
                        path,
                        format!("DataArray offset {off} lies beyond the end of the file"),
                    )
                })?;
            decode_data(path, &b, base, &layout, (ty, count, nbytes), streaming)?
        }
        "binary" | "ascii" => {
            let text_end = find(&b, b"</DataArray", arr.end)
                .filter(|&p| p <= xml_end)
                .ok_or_else(|| {
                    VolumeError::format(path, "inline DataArray has no closing </DataArray>")
                })?;
            let text = &b[arr.end..text_end];
            if fmt_s == "ascii" {
                (parse_ascii(path, text, ty, count)?, None)
            } else {
                let bytes = base64_decode(path, text)?;
                decode_data(path, &bytes, 0, &layout, (ty, count, nbytes), streaming)?
            }
        }
        o => {
            return Err(VolumeError::format(
                path,
                format!("DataArray format {o:?}; expected appended, binary or ascii"),
            ));
        }
    };
    let fmt = format!(
        "VTK ImageData ({}{}, {ty})",
        match fmt_s {
            "appended" => "appended raw",
            "binary" => "inline base64",
            _ => "inline ascii",
        },
        if compressed && fmt_s != "ascii" {
            ", zlib"
        } else {
            ""
        }
    );
    Ok((
        RawVolume::unlabelled(dims, spacing, samples, fmt, warnings),
        streamed,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_groups() {
        let p = Path::new("t");
        assert_eq!(base64_decode(p, b"TWFu").unwrap(), b"Man");
        assert_eq!(base64_decode(p, b"TWE=TQ==").unwrap(), b"MaM");
        assert!(base64_decode(p, b"TW").is_err());
        assert!(base64_decode(p, b"T*==").is_err());
    }

    #[test]
    fn tag_scanner() {
        let p = Path::new("t");
        let t = scan_tags(
            p,
            b"<?xml version='1.0'?><!-- c --><A x=\"1 2\" y = '3'><B/></A>",
        )
        .unwrap();
        assert_eq!(t.len(), 3);
        assert_eq!(t[0].attr("x"), Some("1 2"));
        assert_eq!(t[0].attr("y"), Some("3"));
        assert!(t[2].closing);
        assert!(scan_tags(p, b"<A x=1>").is_err());
        assert!(scan_tags(p, b"<A x=\"1>").is_err());
    }
}
