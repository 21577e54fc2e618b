//! Hostile and malformed input: every case must give a `VolumeError` whose message says what
//! is wrong (never a panic, never a huge allocation). Ends with a mutation fuzz over every
//! format.

use std::io::Write;
use std::path::{Path, PathBuf};

use flate2::Compression;
use flate2::write::{GzEncoder, ZlibEncoder};
use voxlight_volumes::{
    Endian, SampleType, Samples, VolumeError, load, load_raw, load_raw_file, scan_catalog,
};

struct Tmp(tempfile::TempDir);

impl Tmp {
    fn new() -> Tmp {
        Tmp(tempfile::tempdir().unwrap())
    }
    fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.0.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

fn gz(b: &[u8]) -> Vec<u8> {
    let mut e = GzEncoder::new(Vec::new(), Compression::fast());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

fn zlib(b: &[u8]) -> Vec<u8> {
    let mut e = ZlibEncoder::new(Vec::new(), Compression::fast());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

/// Asserts an error whose message contains every one of `needles`.
fn expect_err(r: Result<impl std::fmt::Debug, VolumeError>, needles: &[&str]) -> VolumeError {
    let e = match r {
        Ok(v) => panic!("expected an error containing {needles:?}, got Ok({v:?})"),
        Err(e) => e,
    };
    let msg = e.to_string();
    for n in needles {
        assert!(msg.contains(n), "error {msg:?} should mention {n:?}");
    }
    e
}

// ---------- NRRD ----------

fn nrrd(fields: &str, data: &[u8]) -> Vec<u8> {
    let mut v = format!("NRRD0004\n# test\n{}\n\n", fields.trim_end()).into_bytes();
    v.extend_from_slice(data);
    v
}

const U16_222: &str = "type: uint16\ndimension: 3\nsizes: 2 2 2\nendian: little\nencoding: raw\n";

fn u16_bytes(v: &[u16], e: Endian) -> Vec<u8> {
    v.iter()
        .flat_map(|x| match e {
            Endian::Little => x.to_le_bytes(),
            Endian::Big => x.to_be_bytes(),
        })
        .collect()
}

#[test]
fn nrrd_valid_variants() {
    let t = Tmp::new();
    let vals: Vec<u16> = (0..8).map(|i| i * 100 + 7).collect();
    // Big endian, spacings, byte skip.
    let f = "type: unsigned short\ndimension: 3\nsizes: 2 2 2\nendian: big\nencoding: raw\nspacings: 0.5 2 3\nbyte skip: 4";
    let mut data = vec![9, 9, 9, 9];
    data.extend(u16_bytes(&vals, Endian::Big));
    let r = load_raw(&t.write("a.nrrd", &nrrd(f, &data))).unwrap();
    assert_eq!(r.samples, Samples::U16(vals.clone()));
    assert_eq!(r.spacing, [0.5, 2.0, 3.0]);
    // gzip, space directions with a non-unit vector.
    let f = "type: ushort\ndimension: 3\nsizes: 2 2 2\nendian: little\nencoding: gzip\nspace directions: (0,0.5,0) (3,4,0) (0,0,2)";
    let r = load_raw(&t.write("b.nrrd", &nrrd(f, &gz(&u16_bytes(&vals, Endian::Little))))).unwrap();
    assert_eq!(r.samples, Samples::U16(vals.clone()));
    assert_eq!(r.spacing, [0.5, 5.0, 2.0]);
    // ascii
    let f = "type: float\ndimension: 3\nsizes: 2 2 2\nencoding: ascii";
    let r = load_raw(&t.write("c.nrrd", &nrrd(f, b"1 2 3\n4 5 6 7 8.5\n"))).unwrap();
    assert_eq!(r.value(1, 1, 1), 8.5);
    // Detached header with line skip.
    t.write("d.raw", b"skip me\nABCDEFGH");
    let hdr = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: d.raw\nline skip: 1\n";
    let r = load_raw(&t.write("d.nhdr", hdr.as_bytes())).unwrap();
    assert_eq!(r.samples, Samples::U8(b"ABCDEFGH".to_vec()));
    // int8 and float64 types.
    let f = "type: signed char\ndimension: 3\nsizes: 2 1 1\nencoding: raw";
    let r = load_raw(&t.write("e.nrrd", &nrrd(f, &[0xFF, 0x01]))).unwrap();
    assert_eq!(r.samples, Samples::I8(vec![-1, 1]));
    let f = "type: double\ndimension: 3\nsizes: 1 1 1\nendian: little\nencoding: raw";
    let r = load_raw(&t.write("f.nrrd", &nrrd(f, &2.5f64.to_le_bytes()))).unwrap();
    assert_eq!(r.samples, Samples::F64(vec![2.5]));
}

#[test]
fn nrrd_hostile() {
    let t = Tmp::new();
    let ok_data = u16_bytes(&[1; 8], Endian::Little);
    // Data shorter than the dims say.
    expect_err(
        load_raw(&t.write("a.nrrd", &nrrd(U16_222, &ok_data[..10]))),
        &["a.nrrd", "truncated", "16 bytes", "10"],
    );
    // Zero dims.
    let f = U16_222.replace("sizes: 2 2 2", "sizes: 2 0 2");
    expect_err(
        load_raw(&t.write("b.nrrd", &nrrd(&f, &ok_data))),
        &["b.nrrd", "sizes", "is 0"],
    );
    // Absurd dims: must fail before allocating.
    let f = U16_222.replace("sizes: 2 2 2", "sizes: 100000 100000 100000");
    let e = expect_err(
        load_raw(&t.write("c.nrrd", &nrrd(&f, &ok_data))),
        &["c.nrrd", "too large", "limit"],
    );
    assert!(matches!(e, VolumeError::TooLarge { .. }));
    // Product overflows u64.
    let f = U16_222.replace(
        "sizes: 2 2 2",
        "sizes: 18446744073709551615 18446744073709551615 2",
    );
    expect_err(
        load_raw(&t.write("d.nrrd", &nrrd(&f, &ok_data))),
        &["too large"],
    );
    // Number too large for u64.
    let f = U16_222.replace("sizes: 2 2 2", "sizes: 2 2 99999999999999999999999");
    expect_err(
        load_raw(&t.write("d2.nrrd", &nrrd(&f, &ok_data))),
        &["sizes", "99999999999999999999999"],
    );
    // Negative and NaN spacing.
    let f = format!("{U16_222}spacings: -1 1 1");
    expect_err(
        load_raw(&t.write("e.nrrd", &nrrd(&f, &ok_data))),
        &["spacings", "-1", "positive"],
    );
    let f = format!("{U16_222}spacings: nan 1 1");
    expect_err(
        load_raw(&t.write("f.nrrd", &nrrd(&f, &ok_data))),
        &["spacings", "NaN"],
    );
    let f = format!("{U16_222}space directions: (0,0,0) (0,1,0) (0,0,1)");
    expect_err(
        load_raw(&t.write("f2.nrrd", &nrrd(&f, &ok_data))),
        &["space directions", "positive"],
    );
    // Unsupported type and encoding.
    let f = U16_222.replace("uint16", "block");
    let e = expect_err(
        load_raw(&t.write("g.nrrd", &nrrd(&f, &ok_data))),
        &["type", "block"],
    );
    assert!(matches!(e, VolumeError::Unsupported { .. }));
    let f = U16_222.replace("encoding: raw", "encoding: bzip2");
    expect_err(
        load_raw(&t.write("h.nrrd", &nrrd(&f, &ok_data))),
        &["encoding", "bzip2"],
    );
    // Missing endian for a 2-byte type.
    let f = U16_222.replace("endian: little\n", "");
    expect_err(
        load_raw(&t.write("i.nrrd", &nrrd(&f, &ok_data))),
        &["endian"],
    );
    // Missing required field.
    let f = U16_222.replace("sizes: 2 2 2\n", "");
    expect_err(
        load_raw(&t.write("j.nrrd", &nrrd(&f, &ok_data))),
        &["sizes"],
    );
    // Wrong magic and garbage.
    expect_err(
        load_raw(&t.write("k.nrrd", b"NOPE0004\n\n")),
        &["k.nrrd", "magic"],
    );
    expect_err(load_raw(&t.write("l.nrrd", &[0xFFu8; 64])), &["l.nrrd"]);
    expect_err(load_raw(&t.write("l2.nrrd", b"")), &["empty"]);
    // Detached data file missing.
    let hdr = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: nothere.raw\n";
    expect_err(
        load_raw(&t.write("m.nhdr", hdr.as_bytes())),
        &["nothere.raw"],
    );
    // Gzip stream that is corrupt, and one that is short.
    let f = U16_222.replace("encoding: raw", "encoding: gzip");
    expect_err(
        load_raw(&t.write("n.nrrd", &nrrd(&f, b"\x1f\x8b\x08\x00garbage"))),
        &["n.nrrd"],
    );
    expect_err(
        load_raw(&t.write("o.nrrd", &nrrd(&f, &gz(&ok_data[..9])))),
        &["truncated", "16 bytes"],
    );
    // Unsupported dimension.
    let f = U16_222.replace("dimension: 3\nsizes: 2 2 2", "dimension: 4\nsizes: 3 2 2 2");
    expect_err(
        load_raw(&t.write("p.nrrd", &nrrd(&f, &ok_data))),
        &["dimension 4"],
    );
}

#[test]
fn gzip_bomb_is_bounded() {
    // 64 MiB of zeros compresses to ~64 KiB; the header wants 8 bytes. Only the needed part
    // is inflated.
    let t = Tmp::new();
    let big = gz(&vec![0u8; 64 << 20]);
    let f = "type: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: gzip";
    let r = load_raw(&t.write("bomb.nrrd", &nrrd(f, &big))).unwrap();
    assert_eq!(r.samples, Samples::U8(vec![0; 8]));
    let mut nii = nifti_header(Endian::Little, [2, 2, 2], 2, 8, [1.0; 3]);
    nii.extend(vec![0u8; 64 << 20]);
    let r = load_raw(&t.write("bomb.nii.gz", &gz(&nii))).unwrap();
    assert_eq!(r.samples, Samples::U8(vec![0; 8]));
}

// ---------- NIfTI ----------

fn nifti_header(
    e: Endian,
    dims: [i16; 3],
    datatype: i16,
    bitpix: i16,
    pixdim: [f32; 3],
) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    let i32b = |v: i32| {
        if e == Endian::Little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        }
    };
    let i16b = |v: i16| {
        if e == Endian::Little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        }
    };
    let f32b = |v: f32| {
        if e == Endian::Little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        }
    };
    h[0..4].copy_from_slice(&i32b(348));
    let dim = [3, dims[0], dims[1], dims[2], 1, 1, 1, 1];
    for (i, d) in dim.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&i16b(*d));
    }
    h[70..72].copy_from_slice(&i16b(datatype));
    h[72..74].copy_from_slice(&i16b(bitpix));
    let pd = [1.0, pixdim[0], pixdim[1], pixdim[2], 0.0, 0.0, 0.0, 0.0];
    for (i, p) in pd.iter().enumerate() {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&f32b(*p));
    }
    h[108..112].copy_from_slice(&f32b(352.0));
    h[112..116].copy_from_slice(&f32b(1.0));
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

fn set_f32(h: &mut [u8], off: usize, v: f32) {
    h[off..off + 4].copy_from_slice(&v.to_le_bytes());
}

fn set_i16(h: &mut [u8], off: usize, v: i16) {
    h[off..off + 2].copy_from_slice(&v.to_le_bytes());
}

#[test]
fn nifti_valid_variants() {
    let t = Tmp::new();
    let vals: Vec<u16> = (0..8).map(|i| 1000 + i * 3).collect();
    // Big endian uint16.
    let mut b = nifti_header(Endian::Big, [2, 2, 2], 512, 16, [0.5, 1.5, 2.0]);
    b.extend(u16_bytes(&vals, Endian::Big));
    let r = load_raw(&t.write("be.nii", &b)).unwrap();
    assert_eq!(r.samples, Samples::U16(vals.clone()));
    assert_eq!(r.spacing, [0.5, 1.5, 2.0]);
    // Scaling: slope 2, intercept -1 → float32.
    let mut b = nifti_header(Endian::Little, [2, 2, 2], 512, 16, [1.0; 3]);
    set_f32(&mut b, 112, 2.0);
    set_f32(&mut b, 116, -1.0);
    b.extend(u16_bytes(&vals, Endian::Little));
    let r = load_raw(&t.write("s.nii.gz", &gz(&b))).unwrap();
    assert_eq!(r.samples.sample_type(), SampleType::F32);
    assert_eq!(r.value(1, 1, 1), 2.0 * 1021.0 - 1.0);
    // 4D with 3 volumes: first volume, with a warning.
    let mut b = nifti_header(Endian::Little, [2, 1, 1], 2, 8, [1.0; 3]);
    set_i16(&mut b, 40, 4);
    set_i16(&mut b, 48, 3);
    b.extend([1, 2, 3, 4, 5, 6]);
    let r = load_raw(&t.write("4d.nii", &b)).unwrap();
    assert_eq!(r.samples, Samples::U8(vec![1, 2]));
    assert!(
        r.warnings.iter().any(|w| w.contains("3 volumes")),
        "{:?}",
        r.warnings
    );
    // float64.
    let mut b = nifti_header(Endian::Little, [1, 1, 1], 64, 64, [1.0; 3]);
    b.extend((-3.5f64).to_le_bytes());
    let v = load(&t.write("f64.nii", &b)).unwrap();
    assert_eq!((v.value_min, v.value_max), (-3.5, -3.5));
    assert_eq!(v.name, "f64");
}

#[test]
fn nifti_hostile() {
    let t = Tmp::new();
    let good = {
        let mut b = nifti_header(Endian::Little, [2, 2, 2], 4, 16, [1.0; 3]);
        b.extend([0u8; 16]);
        b
    };
    assert!(load_raw(&t.write("good.nii", &good)).is_ok());
    // Truncated header / data (plain and gzip).
    expect_err(
        load_raw(&t.write("a.nii", &good[..100])),
        &["a.nii", "header is truncated", "348", "100"],
    );
    expect_err(
        load_raw(&t.write("b.nii", &good[..360])),
        &["b.nii", "truncated", "16 bytes"],
    );
    expect_err(
        load_raw(&t.write("b.nii.gz", &gz(&good[..360]))),
        &["b.nii.gz", "truncated", "16 bytes", "found only 8"],
    );
    // Garbage gzip.
    expect_err(
        load_raw(&t.write("c.nii.gz", b"\x1f\x8b\x08\x00\x00\x00\x00\x00garbage")),
        &["c.nii.gz"],
    );
    // Wrong sizeof_hdr.
    let mut b = good.clone();
    b[0] = 7;
    expect_err(load_raw(&t.write("d.nii", &b)), &["sizeof_hdr", "348"]);
    // dims 0, negative, huge.
    let mut b = good.clone();
    set_i16(&mut b, 44, 0);
    expect_err(load_raw(&t.write("e.nii", &b)), &["dim[2]", "0"]);
    let mut b = good.clone();
    set_i16(&mut b, 42, -5);
    expect_err(load_raw(&t.write("e2.nii", &b)), &["dim[1]", "-5"]);
    let mut b = good.clone();
    for off in [42, 44, 46] {
        set_i16(&mut b, off, 32767);
    }
    let e = expect_err(load_raw(&t.write("f.nii.gz", &gz(&b))), &["too large"]);
    assert!(matches!(e, VolumeError::TooLarge { .. }));
    let mut b = good.clone();
    set_i16(&mut b, 40, 9);
    expect_err(load_raw(&t.write("f2.nii", &b)), &["dim[0]", "9"]);
    // Unsupported datatypes.
    let mut b = good.clone();
    set_i16(&mut b, 70, 128);
    let e = expect_err(load_raw(&t.write("g.nii", &b)), &["RGB24"]);
    assert!(matches!(e, VolumeError::Unsupported { .. }));
    let mut b = good.clone();
    set_i16(&mut b, 70, 77);
    expect_err(load_raw(&t.write("g2.nii", &b)), &["datatype code 77"]);
    // NaN spacing, bad vox_offset, bad magic.
    let mut b = good.clone();
    set_f32(&mut b, 80, f32::NAN);
    expect_err(load_raw(&t.write("h.nii", &b)), &["pixdim[1]", "NaN"]);
    let mut b = good.clone();
    set_f32(&mut b, 108, 12.0);
    expect_err(load_raw(&t.write("i.nii", &b)), &["vox_offset", "12"]);
    let mut b = good.clone();
    set_f32(&mut b, 108, 1e9);
    expect_err(load_raw(&t.write("i2.nii", &b)), &["truncated"]);
    let mut b = good.clone();
    b[344..348].copy_from_slice(b"abc\0");
    expect_err(load_raw(&t.write("j.nii", &b)), &["magic"]);
    // NIfTI-2 is reported as unsupported.
    let mut b = good.clone();
    b[0..4].copy_from_slice(&540i32.to_le_bytes());
    expect_err(load_raw(&t.write("k.nii", &b)), &["NIfTI-2"]);
}

// ---------- VTI ----------

fn vti(
    header_type: &str,
    compressed: bool,
    ty: &str,
    extent: &str,
    spacing: &str,
    payload: &[u8],
) -> Vec<u8> {
    let comp = if compressed {
        " compressor=\"vtkZLibDataCompressor\""
    } else {
        ""
    };
    let mut v = format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\" byte_order=\"LittleEndian\" \
         header_type=\"{header_type}\"{comp}>\n  <ImageData WholeExtent=\"{extent}\" Origin=\"0 0 0\" Spacing=\"{spacing}\">\n\
         <Piece Extent=\"{extent}\">\n<PointData Scalars=\"v\">\n<DataArray type=\"{ty}\" Name=\"v\" format=\"appended\" offset=\"0\"/>\n\
         </PointData>\n<CellData>\n</CellData>\n</Piece>\n</ImageData>\n<AppendedData encoding=\"raw\">\n   _"
    )
    .into_bytes();
    v.extend_from_slice(payload);
    v.extend_from_slice(b"\n</AppendedData>\n</VTKFile>\n");
    v
}

fn uint(hsize: usize, v: u64) -> Vec<u8> {
    if hsize == 4 {
        (v as u32).to_le_bytes().to_vec()
    } else {
        v.to_le_bytes().to_vec()
    }
}

/// zlib multi-block payload: header [nblocks, blocksize, last, sizes...] + blocks.
fn zlib_payload(hsize: usize, data: &[u8], blocksize: usize) -> Vec<u8> {
    let blocks: Vec<Vec<u8>> = data.chunks(blocksize).map(zlib).collect();
    let last = data.len() % blocksize;
    let mut p = uint(hsize, blocks.len() as u64);
    p.extend(uint(hsize, blocksize as u64));
    p.extend(uint(hsize, last as u64));
    for b in &blocks {
        p.extend(uint(hsize, b.len() as u64));
    }
    for b in &blocks {
        p.extend(b);
    }
    p
}

fn base64(b: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in b.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

#[test]
fn vti_valid_variants() {
    let t = Tmp::new();
    let vals: Vec<i16> = (0..24).map(|i| i * 37 - 300).collect();
    let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    // Uncompressed appended, UInt32 header.
    let mut p = uint(4, bytes.len() as u64);
    p.extend(&bytes);
    let r = load_raw(&t.write(
        "a.vti",
        &vti("UInt32", false, "Int16", "0 3 0 2 0 1", "1 2 3", &p),
    ))
    .unwrap();
    assert_eq!(r.dims, [4, 3, 2]);
    assert_eq!(r.spacing, [1.0, 2.0, 3.0]);
    assert_eq!(r.samples, Samples::I16(vals.clone()));
    // zlib, several blocks with a partial last block, UInt64 header, non-zero extent origin.
    let p = zlib_payload(8, &bytes, 10);
    let r = load_raw(&t.write(
        "b.vti",
        &vti("UInt64", true, "Int16", "5 8 0 2 -1 0", "1 1 1", &p),
    ))
    .unwrap();
    assert_eq!(r.samples, Samples::I16(vals.clone()));
    // Inline base64 (compressed: header and data encoded separately, as VTK does).
    let p = zlib_payload(4, &bytes, 16);
    let nb = bytes.len().div_ceil(16);
    let (h, d) = p.split_at(4 * (3 + nb));
    let text = format!("{}{}", base64(h), base64(d));
    let xml = format!(
        "<VTKFile type=\"ImageData\" byte_order=\"LittleEndian\" compressor=\"vtkZLibDataCompressor\">\
         <ImageData WholeExtent=\"0 3 0 2 0 1\" Spacing=\"1 1 1\"><Piece Extent=\"0 3 0 2 0 1\"><PointData>\
         <DataArray type=\"Int16\" Name=\"v\" format=\"binary\">\n {text}\n </DataArray></PointData></Piece></ImageData></VTKFile>"
    );
    let r = load_raw(&t.write("c.vti", xml.as_bytes())).unwrap();
    assert_eq!(r.samples, Samples::I16(vals.clone()));
    // Inline ascii floats.
    let xml = "<VTKFile type=\"ImageData\"><ImageData WholeExtent=\"0 1 0 0 0 0\" Spacing=\"1 1 1\">\
               <Piece Extent=\"0 1 0 0 0 0\"><PointData><DataArray type=\"Float32\" format=\"ascii\">1.5 -2\
               </DataArray></PointData></Piece></ImageData></VTKFile>";
    let r = load_raw(&t.write("d.vti", xml.as_bytes())).unwrap();
    assert_eq!(r.samples, Samples::F32(vec![1.5, -2.0]));
}

#[test]
fn vti_hostile() {
    let t = Tmp::new();
    let data = vec![7u8; 64];
    let p = zlib_payload(8, &data, 16);
    let good = vti("UInt64", true, "UInt8", "0 3 0 3 0 3", "1 1 1", &p);
    assert!(load_raw(&t.write("good.vti", &good)).is_ok());
    // Truncated file.
    let cut = good.len() - 40;
    expect_err(load_raw(&t.write("a.vti", &good[..cut])), &["a.vti"]);
    let cut = good.windows(4).position(|w| w == b"   _").unwrap() + 4 + 12;
    expect_err(
        load_raw(&t.write("a2.vti", &good[..cut])),
        &["a2.vti", "truncated", "compression header"],
    );
    // Header lies: extent needs more data than the blocks hold.
    let lie = vti("UInt64", true, "UInt8", "0 3 0 3 0 4", "1 1 1", &p);
    expect_err(
        load_raw(&t.write("b.vti", &lie)),
        &["does not add up", "80 bytes"],
    );
    // Huge and empty extents.
    let huge = vti(
        "UInt64",
        true,
        "UInt8",
        "0 99999 0 99999 0 99999",
        "1 1 1",
        &p,
    );
    let e = expect_err(load_raw(&t.write("c.vti", &huge)), &["too large"]);
    assert!(matches!(e, VolumeError::TooLarge { .. }));
    let empty = vti("UInt64", true, "UInt8", "0 3 5 3 0 3", "1 1 1", &p);
    expect_err(
        load_raw(&t.write("d.vti", &empty)),
        &["WholeExtent", "0 voxels"],
    );
    let overflow = vti(
        "UInt64",
        true,
        "UInt8",
        "-9223372036854775808 9223372036854775807 0 0 0 0",
        "1 1 1",
        &p,
    );
    expect_err(load_raw(&t.write("d2.vti", &overflow)), &["too large"]);
    // Absurd block count.
    let mut bad = p.clone();
    bad[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    expect_err(
        load_raw(&t.write(
            "e.vti",
            &vti("UInt64", true, "UInt8", "0 3 0 3 0 3", "1 1 1", &bad),
        )),
        &["e.vti"],
    );
    // Corrupt zlib block.
    let mut bad = p.clone();
    let n = bad.len();
    for b in &mut bad[n - 20..] {
        *b ^= 0x5A;
    }
    expect_err(
        load_raw(&t.write(
            "f.vti",
            &vti("UInt64", true, "UInt8", "0 3 0 3 0 3", "1 1 1", &bad),
        )),
        &["zlib block"],
    );
    // Negative / NaN spacing, unsupported type, wrong file type, garbage.
    expect_err(
        load_raw(&t.write(
            "g.vti",
            &vti("UInt64", true, "UInt8", "0 3 0 3 0 3", "1 -1 1", &p),
        )),
        &["Spacing", "-1"],
    );
    expect_err(
        load_raw(&t.write(
            "g2.vti",
            &vti("UInt64", true, "UInt8", "0 3 0 3 0 3", "1 nan 1", &p),
        )),
        &["Spacing", "NaN"],
    );
    let e = expect_err(
        load_raw(&t.write(
            "h.vti",
            &vti("UInt64", true, "Int64", "0 3 0 3 0 3", "1 1 1", &p),
        )),
        &["Int64"],
    );
    assert!(matches!(e, VolumeError::Unsupported { .. }));
    expect_err(
        load_raw(&t.write("i.vti", b"<VTKFile type=\"PolyData\"></VTKFile>")),
        &["PolyData"],
    );
    expect_err(
        load_raw(&t.write("j.vti", &[0xAB; 300])),
        &["j.vti", "VTKFile"],
    );
    expect_err(
        load_raw(&t.write("k.vti", b"<VTKFile type=\"ImageData\" <<<")),
        &["k.vti"],
    );
    // Uncompressed size header that disagrees with the extent.
    let mut q = uint(4, 63);
    q.extend(&data);
    expect_err(
        load_raw(&t.write(
            "l.vti",
            &vti("UInt32", false, "UInt8", "0 3 0 3 0 3", "1 1 1", &q),
        )),
        &["63 bytes", "64"],
    );
}

// ---------- raw ----------

#[test]
fn raw_file_loading() {
    let t = Tmp::new();
    let vals: Vec<u16> = (0..24).map(|i| i * 11).collect();
    let mut b = vec![0xEE; 5];
    b.extend(u16_bytes(&vals, Endian::Big));
    let p = t.write("x.raw", &b);
    let r = load_raw_file(
        &p,
        [2, 3, 4],
        SampleType::U16,
        Endian::Big,
        [1.0, 1.0, 2.5],
        5,
    )
    .unwrap();
    assert_eq!(r.samples, Samples::U16(vals));
    assert_eq!(r.spacing, [1.0, 1.0, 2.5]);
    expect_err(
        load_raw_file(&p, [2, 3, 5], SampleType::U16, Endian::Big, [1.0; 3], 5),
        &["x.raw", "53 bytes", "65"],
    );
    expect_err(
        load_raw_file(&p, [0, 3, 5], SampleType::U16, Endian::Big, [1.0; 3], 0),
        &["is 0"],
    );
    expect_err(
        load_raw_file(
            &p,
            [u32::MAX, u32::MAX, u32::MAX],
            SampleType::F64,
            Endian::Big,
            [1.0; 3],
            0,
        ),
        &["too large"],
    );
    expect_err(
        load_raw_file(
            &p,
            [2, 3, 4],
            SampleType::U8,
            Endian::Big,
            [1.0, f32::NAN, 1.0],
            0,
        ),
        &["spacing", "NaN"],
    );
    expect_err(
        load_raw_file(
            &t.0.path().join("none.raw"),
            [1, 1, 1],
            SampleType::U8,
            Endian::Big,
            [1.0; 3],
            0,
        ),
        &["none.raw", "opening"],
    );
    // A bare .raw through load_raw is refused with a pointer to load_raw_file.
    expect_err(load_raw(&p), &["load_raw_file"]);
}

#[test]
fn unknown_and_missing_paths() {
    let t = Tmp::new();
    expect_err(
        load_raw(&t.write("what.xyz", b"hello world")),
        &["what.xyz", "unknown volume format"],
    );
    expect_err(
        load_raw(&t.0.path().join("missing.nrrd")),
        &["missing.nrrd"],
    );
    // Sniffing by content: an NRRD with an odd extension.
    let p = t.write(
        "vol.dat",
        &nrrd(
            "type: uint8\ndimension: 3\nsizes: 1 1 1\nencoding: raw",
            &[42],
        ),
    );
    assert_eq!(load_raw(&p).unwrap().samples, Samples::U8(vec![42]));
    let e = expect_err(scan_catalog(&t.0.path().join("nope")), &["nope", "catalog"]);
    assert!(matches!(e, VolumeError::Io { .. }));
}

#[test]
fn catalog_rules() {
    let t = Tmp::new();
    let root = t.0.path();
    for d in ["a/series", "a/series/sub", "b/c/d/e/f", ".hidden", "vols"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let mut dicm = vec![0u8; 200];
    dicm[128..132].copy_from_slice(b"DICM");
    std::fs::write(root.join("a/series/IM0001"), &dicm).unwrap();
    std::fs::write(root.join("a/series/sub/x.nrrd"), b"").unwrap();
    std::fs::write(root.join("b/c/d/e/deep.vti"), b"").unwrap();
    std::fs::write(root.join("b/c/d/e/f/too_deep.vti"), b"").unwrap();
    std::fs::write(root.join(".hidden/h.nrrd"), b"").unwrap();
    std::fs::write(root.join("vols/x.nii.gz"), b"").unwrap();
    std::fs::write(root.join("vols/x.raw"), b"").unwrap();
    std::fs::write(root.join("vols/.y.nrrd"), b"").unwrap();
    std::fs::write(root.join("vols/z.NHDR"), b"").unwrap();
    let names: Vec<(String, String)> = scan_catalog(root)
        .unwrap()
        .into_iter()
        .map(|e| (e.name, e.kind))
        .collect();
    let expect: Vec<(String, String)> = [
        ("a/series", "dicom"),
        ("b/c/d/e/deep.vti", "vti"),
        ("vols/x.nii.gz", "nifti"),
        ("vols/z.NHDR", "nrrd"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(names, expect);
}

// ---------- mutation fuzz ----------

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn mutate(rng: &mut Rng, src: &[u8], hot: usize) -> Vec<u8> {
    let mut b = src.to_vec();
    for _ in 0..1 + rng.below(6) {
        // Bias mutations towards the header region.
        let span = if rng.below(4) == 0 {
            b.len()
        } else {
            hot.min(b.len())
        };
        let i = rng.below(span);
        match rng.below(7) {
            0 => {
                if let Some(x) = b.get_mut(i) {
                    *x ^= 1 << rng.below(8);
                }
            }
            1 => {
                if let Some(x) = b.get_mut(i) {
                    *x = [0x00, 0xFF, 0x7F, 0x80, b'9', b'-', b' '][rng.below(7)];
                }
            }
            2 => b.truncate(i),
            3 => {
                let n = rng.below(8);
                let junk: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
                let at = i.min(b.len());
                b.splice(at..at, junk);
            }
            4 => {
                if i < b.len() {
                    b.remove(i);
                }
            }
            5 => {
                // Overwrite 4 bytes with a large little-endian number.
                for (k, v) in [0xF0u8, 0xFF, 0xFF, 0x7F].iter().enumerate() {
                    if let Some(x) = b.get_mut(i + k) {
                        *x = *v;
                    }
                }
            }
            _ => {
                for x in b.iter_mut().skip(i).take(8) {
                    *x = rng.next() as u8;
                }
            }
        }
    }
    b
}

fn synthetic_dicom(path: &Path) {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
    let mut o = InMemDicomObject::new_empty();
    let s = |v: &str| PrimitiveValue::from(v);
    let us = |v: u16| PrimitiveValue::U16(vec![v].into());
    o.put(DataElement::new(
        tags::SOP_CLASS_UID,
        VR::UI,
        s("1.2.840.10008.5.1.4.1.1.2"),
    ));
    o.put(DataElement::new(
        tags::SOP_INSTANCE_UID,
        VR::UI,
        s("1.2.3.4.5"),
    ));
    o.put(DataElement::new(tags::MODALITY, VR::CS, s("CT")));
    o.put(DataElement::new(
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        s("1.2.3"),
    ));
    o.put(DataElement::new(
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        PrimitiveValue::Strs(vec!["0".to_string(), "0".into(), "1.5".into()].into()),
    ));
    o.put(DataElement::new(
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        PrimitiveValue::Strs(
            vec![
                "1".to_string(),
                "0".into(),
                "0".into(),
                "0".into(),
                "1".into(),
                "0".into(),
            ]
            .into(),
        ),
    ));
    o.put(DataElement::new(tags::SAMPLES_PER_PIXEL, VR::US, us(1)));
    o.put(DataElement::new(tags::ROWS, VR::US, us(4)));
    o.put(DataElement::new(tags::COLUMNS, VR::US, us(4)));
    o.put(DataElement::new(
        tags::PIXEL_SPACING,
        VR::DS,
        PrimitiveValue::Strs(vec!["1".to_string(), "1".into()].into()),
    ));
    o.put(DataElement::new(tags::BITS_ALLOCATED, VR::US, us(16)));
    o.put(DataElement::new(tags::BITS_STORED, VR::US, us(12)));
    o.put(DataElement::new(tags::PIXEL_REPRESENTATION, VR::US, us(0)));
    o.put(DataElement::new(
        tags::RESCALE_INTERCEPT,
        VR::DS,
        s("-1024"),
    ));
    o.put(DataElement::new(tags::RESCALE_SLOPE, VR::DS, s("1")));
    o.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OW,
        PrimitiveValue::U16((0..16u16).collect::<Vec<_>>().into()),
    ));
    o.with_meta(FileMetaTableBuilder::new().transfer_syntax("1.2.840.10008.1.2.1"))
        .unwrap()
        .write_to_file(path)
        .unwrap();
}

#[test]
fn mutation_fuzz_never_panics() {
    let t = Tmp::new();
    let vals: Vec<u8> = (0..64u8).map(|i| i.wrapping_mul(7)).collect();
    let u16s: Vec<u16> = (0..64u16).map(|i| i * 300).collect();
    let mut nii = nifti_header(Endian::Little, [4, 4, 4], 512, 16, [1.0, 2.0, 3.0]);
    nii.extend(u16_bytes(&u16s, Endian::Little));
    let vti_z = vti(
        "UInt64",
        true,
        "UInt8",
        "0 3 0 3 0 3",
        "1 1 1",
        &zlib_payload(8, &vals, 16),
    );
    let mut raw_payload = uint(4, 64);
    raw_payload.extend(&vals);
    let vti_r = vti(
        "UInt32",
        false,
        "UInt8",
        "0 3 0 3 0 3",
        "1 1 1",
        &raw_payload,
    );
    let dcm_path = t.0.path().join("seed.dcm");
    synthetic_dicom(&dcm_path);
    let dcm = std::fs::read(&dcm_path).unwrap();
    assert!(load_raw(&dcm_path).is_ok());
    let seeds: Vec<(&str, Vec<u8>, usize)> = vec![
        (
            "nrrd",
            nrrd(
                "type: uint8\ndimension: 3\nsizes: 4 4 4\nspacings: 1 1 2\nencoding: raw",
                &vals,
            ),
            120,
        ),
        (
            "nrrd",
            nrrd(
                "type: ushort\ndimension: 3\nsizes: 4 4 4\nendian: big\nencoding: gzip",
                &gz(&u16_bytes(&u16s, Endian::Big)),
            ),
            140,
        ),
        ("nii", nii.clone(), 352),
        ("nii.gz", gz(&nii), 400),
        ("vti", vti_z.clone(), vti_z.len()),
        ("vti", vti_r.clone(), vti_r.len()),
        ("dcm", dcm.clone(), dcm.len()),
    ];
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let mut outcomes = [0usize; 2];
    for (k, (ext, seed, hot)) in seeds.iter().enumerate() {
        assert!(
            load_raw(&t.write(&format!("seed{k}.{ext}"), seed)).is_ok(),
            "seed {k} ({ext}) must load"
        );
        for i in 0..300 {
            let m = mutate(&mut rng, seed, *hot);
            let p = t.write(&format!("m{k}_{i}.{ext}"), &m);
            let res = std::panic::catch_unwind(|| load(&p).map(|v| v.voxel_count()));
            match res {
                Ok(Ok(_)) => outcomes[0] += 1,
                Ok(Err(e)) => {
                    assert!(!e.to_string().is_empty());
                    outcomes[1] += 1;
                }
                Err(_) => panic!(
                    "loader panicked on mutated {ext} #{i} (seed {k}, {} bytes)",
                    m.len()
                ),
            }
            let _ = std::fs::remove_file(&p);
        }
    }
    assert!(
        outcomes[1] > 300,
        "many mutations should produce errors: {outcomes:?}"
    );
}

// ---------- devices, pipes and endless data ----------

/// Runs `f` on a thread and fails if it takes longer than `secs` (a hang is a failure, not a
/// stuck test run).
fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(std::time::Duration::from_secs(secs))
        .expect("the loader hung (or used all memory) on endless input")
}

#[cfg(unix)]
#[test]
fn a_device_as_nrrd_data_file_is_refused() {
    // `data file: /dev/zero` with ascii encoding read lines that never end (unbounded
    // memory); with `line skip` it skipped endless 1 MiB "lines" (a hang).
    let t = Tmp::new();
    for fields in [
        "type: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: ascii\ndata file: /dev/zero",
        "type: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\nline skip: 1000000000\ndata file: /dev/zero",
        "type: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: gzip\ndata file: /dev/zero",
        "type: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: /dev/zero",
        "type: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: .",
    ] {
        let p = t.write("dev.nhdr", format!("NRRD0004\n{fields}\n").as_bytes());
        let e = within(20, move || {
            load_raw(&p).map(|r| r.voxel_count()).unwrap_err()
        });
        assert!(e.to_string().contains("regular file"), "{e}");
    }
}

#[cfg(unix)]
#[test]
fn a_link_to_a_device_is_not_a_volume() {
    let t = Tmp::new();
    for name in [
        "zero.vti",
        "zero.nrrd",
        "zero.nii",
        "zero.nii.gz",
        "zero.dcm",
        "zero.bin",
    ] {
        let link = t.0.path().join(name);
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let e = within(20, move || {
            load_raw(&link).map(|r| r.voxel_count()).unwrap_err()
        });
        assert!(e.to_string().contains("regular file"), "{name}: {e}");
    }
}

#[test]
fn ascii_data_is_bounded_by_what_is_there() {
    // A token that never ends, and a header that declares 2³¹ values over a few bytes.
    let t = Tmp::new();
    let long = "7".repeat(100_000);
    let f = "type: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: ascii";
    expect_err(
        load_raw(&t.write("long.nrrd", &nrrd(f, long.as_bytes()))),
        &["ascii data", "longer than"],
    );
    let f = "type: double\ndimension: 3\nsizes: 2048 1024 1024\nencoding: ascii";
    expect_err(
        load_raw(&t.write("few.nrrd", &nrrd(f, b"1 2 3\n4, 5\n"))),
        &["truncated", "found 5"],
    );
    // Values split across lines, commas and blank lines still parse; extra ones are ignored.
    let f = "type: int16\ndimension: 3\nsizes: 2 2 2\nencoding: ascii";
    let r = load_raw(&t.write("ok.nrrd", &nrrd(f, b"1 2,3\n\n4\t5 6\r\n7 8 9 junk"))).unwrap();
    assert_eq!(r.samples, Samples::I16(vec![1, 2, 3, 4, 5, 6, 7, 8]));
}

// ---------- degenerate geometry ----------

#[test]
fn spacings_that_flatten_the_box_are_refused() {
    // Found by the load_raw fuzz target: a subnormal spacing (1e-45) passed the checks, and
    // the volume's world extent rounded to 0 on that axis (a box without thickness, a march
    // step of 0 on the GPU).
    let t = Tmp::new();
    let p = t.write("r.raw", &[7u8; 36]);
    for spacing in [[1e-45, 1.0, 1.0], [1.0, 1e-30, 1e30], [1.0, 1.0, 2e6]] {
        expect_err(
            load_raw_file(&p, [1, 9, 4], SampleType::U8, Endian::Little, spacing, 0),
            &["spacing"],
        );
    }
    let ok = load_raw_file(
        &p,
        [1, 9, 4],
        SampleType::U8,
        Endian::Little,
        [1e-3, 1.0, 900.0],
        0,
    )
    .unwrap()
    .normalize("ok");
    assert!(ok.world_extent().iter().all(|e| e.is_normal()));
    // The same through every format's header.
    let f = "type: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nspacings: 1e-45 1 1";
    expect_err(
        load_raw(&t.write("s.nrrd", &nrrd(f, &[1; 8]))),
        &["spacing"],
    );
    let f = "type: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nspace directions: (1e-30,0,0) (0,1e30,0) (0,0,1)";
    expect_err(
        load_raw(&t.write("d.nrrd", &nrrd(f, &[1; 8]))),
        &["spacing"],
    );
    let mut nii = nifti_header(Endian::Little, [2, 2, 2], 2, 8, [1e-45, 1.0, 1.0]);
    nii.extend([1u8; 8]);
    expect_err(load_raw(&t.write("s.nii", &nii)), &["pixdim"]);
    let v = vti(
        "UInt32",
        false,
        "UInt8",
        "0 1 0 1 0 1",
        "1 1e-38 1",
        &[uint(4, 8), vec![1; 8]].concat(),
    );
    expect_err(load_raw(&t.write("s.vti", &v)), &["Spacing"]);
    // A 2D image is as thick as its finer pixel edge, not 1 (an image in metres stays flat).
    let f = "type: uint8\ndimension: 2\nsizes: 4 4\nencoding: raw\nspacings: 0.001 0.002";
    let r = load_raw(&t.write("2d.nrrd", &nrrd(f, &[1; 16]))).unwrap();
    assert_eq!(r.spacing, [0.001, 0.002, 0.001]);
}
