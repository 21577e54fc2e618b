//! DICOM series assembly: sorting independent of file names, duplicates, gaps, junk files,
//! mixed sizes, several series, signed / 8-bit / fractional rescale, oblique normals.

use std::path::{Path, PathBuf};

use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use voxlight_volumes::testdata::require_shared_data_dir;
use voxlight_volumes::{SampleType, Samples, VolumeError, load, load_raw};

fn lidc(file: &str) -> PathBuf {
    require_shared_data_dir().join("ct-chest-lidc").join(file)
}

fn slice_values(path: &Path) -> Vec<f64> {
    let r = load_raw(path).unwrap();
    (0..r.voxel_count())
        .map(|i| r.samples.get(i).unwrap())
        .collect()
}

#[test]
fn sort_ignores_file_names_and_reports_gaps_duplicates_and_junk() {
    let tmp = tempfile::tempdir().unwrap();
    // z = 0, 1, 2, 3, 5 of the real series (z = 4 missing), named so that name order is reversed.
    let picks = [
        ("000111.dcm", "e.dcm"), // z=0
        ("000124.dcm", "d.dcm"), // z=1
        ("000203.dcm", "c.dcm"), // z=2
        ("000223.dcm", "b.dcm"), // z=3
        ("000217.dcm", "a.dcm"), // z=5
    ];
    for (src, dst) in picks {
        std::fs::copy(lidc(src), tmp.path().join(dst)).unwrap();
    }
    // Same slice twice, a text file, a truncated non-DICOM file, a hidden file.
    std::fs::copy(lidc("000203.dcm"), tmp.path().join("f_copy.dcm")).unwrap();
    std::fs::write(tmp.path().join("notes.txt"), b"not an image").unwrap();
    std::fs::write(tmp.path().join("broken.dcm"), [0u8; 40]).unwrap();
    std::fs::write(tmp.path().join(".hidden"), b"x").unwrap();

    let r = load_raw(tmp.path()).unwrap();
    assert_eq!(r.dims, [512, 512, 5]);
    assert_eq!(
        r.spacing,
        [0.78125, 0.78125, 1.0],
        "median spacing ignores the gap"
    );
    assert_eq!(r.units, "HU");
    let n = 512 * 512;
    for (z, (src, _)) in picks.iter().enumerate() {
        let expect = slice_values(&lidc(src));
        let got: Vec<f64> = (z * n..(z + 1) * n)
            .map(|i| r.samples.get(i).unwrap())
            .collect();
        assert!(got == expect, "slice z={z} should come from {src}");
    }
    let w = r.warnings.join("\n");
    assert!(
        w.contains("missing slices") && w.contains("z=3") && w.contains("z=4"),
        "{w}"
    );
    assert!(w.contains("duplicate") && w.contains("f_copy.dcm"), "{w}");
    assert!(w.contains("notes.txt") && w.contains("broken.dcm"), "{w}");
    assert!(!w.contains(".hidden"), "{w}");
    assert!(!w.contains("LIDC"), "no patient id in warnings: {w}");
    assert!(!r.format.contains("LIDC"));
}

struct Synth {
    series: &'static str,
    rows: u16,
    cols: u16,
    bits: u16,
    stored: u16,
    signed: bool,
    ipp: [f64; 3],
    iop: [f64; 6],
    slope: &'static str,
    intercept: &'static str,
    instance: i32,
    pixels: Vec<u16>,
}

impl Synth {
    fn new(z: f64, pixels: Vec<u16>) -> Synth {
        Synth {
            series: "1.2.3.4",
            rows: 2,
            cols: 3,
            bits: 16,
            stored: 16,
            signed: false,
            ipp: [0.0, 0.0, z],
            iop: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            slope: "1",
            intercept: "0",
            instance: 1,
            pixels,
        }
    }

    fn write(&self, path: &Path) {
        let mut o = InMemDicomObject::new_empty();
        let s = |v: String| PrimitiveValue::from(v.as_str());
        let ds = |v: &[f64]| {
            PrimitiveValue::Strs(v.iter().map(|x| x.to_string()).collect::<Vec<_>>().into())
        };
        let us = |v: u16| PrimitiveValue::U16(vec![v].into());
        let uid = format!("{}.{}", self.series, self.instance);
        o.put(DataElement::new(
            tags::SOP_CLASS_UID,
            VR::UI,
            s("1.2.840.10008.5.1.4.1.1.2".into()),
        ));
        o.put(DataElement::new(tags::SOP_INSTANCE_UID, VR::UI, s(uid)));
        o.put(DataElement::new(
            tags::PATIENT_NAME,
            VR::PN,
            s("Secret^Person".into()),
        ));
        o.put(DataElement::new(tags::MODALITY, VR::CS, s("CT".into())));
        o.put(DataElement::new(
            tags::SERIES_INSTANCE_UID,
            VR::UI,
            s(self.series.into()),
        ));
        o.put(DataElement::new(
            tags::INSTANCE_NUMBER,
            VR::IS,
            s(self.instance.to_string()),
        ));
        o.put(DataElement::new(
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            ds(&self.ipp),
        ));
        o.put(DataElement::new(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            ds(&self.iop),
        ));
        o.put(DataElement::new(tags::SAMPLES_PER_PIXEL, VR::US, us(1)));
        o.put(DataElement::new(
            tags::PHOTOMETRIC_INTERPRETATION,
            VR::CS,
            s("MONOCHROME2".into()),
        ));
        o.put(DataElement::new(tags::ROWS, VR::US, us(self.rows)));
        o.put(DataElement::new(tags::COLUMNS, VR::US, us(self.cols)));
        o.put(DataElement::new(
            tags::PIXEL_SPACING,
            VR::DS,
            ds(&[0.5, 0.25]),
        ));
        o.put(DataElement::new(
            tags::BITS_ALLOCATED,
            VR::US,
            us(self.bits),
        ));
        o.put(DataElement::new(tags::BITS_STORED, VR::US, us(self.stored)));
        o.put(DataElement::new(
            tags::HIGH_BIT,
            VR::US,
            us(self.stored - 1),
        ));
        o.put(DataElement::new(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            us(self.signed as u16),
        ));
        o.put(DataElement::new(
            tags::RESCALE_INTERCEPT,
            VR::DS,
            s(self.intercept.into()),
        ));
        o.put(DataElement::new(
            tags::RESCALE_SLOPE,
            VR::DS,
            s(self.slope.into()),
        ));
        if self.bits == 8 {
            let mut b: Vec<u8> = self.pixels.iter().map(|&p| p as u8).collect();
            if b.len() % 2 == 1 {
                b.push(0);
            }
            o.put(DataElement::new(
                tags::PIXEL_DATA,
                VR::OB,
                PrimitiveValue::U8(b.into()),
            ));
        } else {
            o.put(DataElement::new(
                tags::PIXEL_DATA,
                VR::OW,
                PrimitiveValue::U16(self.pixels.clone().into()),
            ));
        }
        let f = o
            .with_meta(FileMetaTableBuilder::new().transfer_syntax("1.2.840.10008.1.2.1"))
            .unwrap();
        f.write_to_file(path).unwrap();
    }
}

#[test]
fn synthetic_series_sorted_by_ipp_with_rescale() {
    let tmp = tempfile::tempdir().unwrap();
    // Positions 2, 0, 1 (instance numbers deliberately unrelated), slope 2, intercept -10.
    for (name, z, inst) in [("s1.dcm", 2.0, 1), ("s2.dcm", 0.0, 3), ("s3.dcm", 1.0, 2)] {
        let mut s = Synth::new(z, vec![z as u16 * 10; 6]);
        s.instance = inst;
        s.slope = "2";
        s.intercept = "-10";
        s.stored = 12; // 2 × 4095 − 10 fits int16
        s.write(&tmp.path().join(name));
    }
    let r = load_raw(tmp.path()).unwrap();
    assert_eq!(r.dims, [3, 2, 3]);
    assert_eq!(
        r.spacing,
        [0.25, 0.5, 1.0],
        "x from column spacing, y from row spacing"
    );
    assert_eq!(r.samples.sample_type(), SampleType::I16);
    assert_eq!(r.value(0, 0, 0), -10.0);
    assert_eq!(r.value(2, 1, 1), 10.0);
    assert_eq!(r.value(1, 1, 2), 30.0);
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    let v = load(tmp.path()).unwrap();
    assert_eq!((v.value_min, v.value_max), (-10.0, 30.0));
    assert!(!format!("{v:?}").contains("Secret"));
}

#[test]
fn synthetic_oblique_normal_and_nonuniform_spacing() {
    let tmp = tempfile::tempdir().unwrap();
    // Sagittal: rows along +y, columns along -z → normal = (0,1,0)×(0,0,-1) = (-1,0,0).
    // Sorting by dot(IPP, n) ascending therefore orders by x descending.
    for (name, x) in [
        ("a.dcm", 0.0),
        ("b.dcm", 5.0),
        ("c.dcm", 10.0),
        ("d.dcm", 12.0),
    ] {
        let mut s = Synth::new(0.0, vec![x as u16; 6]);
        s.ipp = [x, 0.0, 0.0];
        s.iop = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
        s.write(&tmp.path().join(name));
    }
    let r = load_raw(tmp.path()).unwrap();
    assert_eq!(r.dims[2], 4);
    let order: Vec<f64> = (0..4).map(|z| r.value(0, 0, z)).collect();
    assert_eq!(order, vec![12.0, 10.0, 5.0, 0.0]);
    // Differences along the normal are 2, 5, 5: median 5, and the 2 is reported.
    assert_eq!(r.spacing[2], 5.0);
    let w = r.warnings.join("\n");
    assert!(
        w.contains("non-uniform slice spacing") && w.contains("2.000 mm"),
        "{w}"
    );
}

#[test]
fn synthetic_signed_12bit_and_8bit() {
    let tmp = tempfile::tempdir().unwrap();
    // Signed, 12 bits stored: 0x0FFF is -1, 0x0800 is -2048, high bits are garbage to be ignored.
    let mut s = Synth::new(0.0, vec![0x0FFF, 0x0800, 0x07FF, 0xF001, 0, 5]);
    s.signed = true;
    s.stored = 12;
    s.write(&tmp.path().join("x.dcm"));
    let r = load_raw(&tmp.path().join("x.dcm")).unwrap();
    assert_eq!(r.samples, Samples::I16(vec![-1, -2048, 2047, 1, 0, 5]));

    let dir8 = tmp.path().join("eight");
    std::fs::create_dir(&dir8).unwrap();
    for z in 0..2 {
        let mut s = Synth::new(z as f64, vec![200, 1, 2, 3, 4, 255]);
        s.bits = 8;
        s.stored = 8;
        s.instance = z;
        s.write(&dir8.join(format!("{z}.dcm")));
    }
    let r = load_raw(&dir8).unwrap();
    assert_eq!(r.samples.sample_type(), SampleType::U8);
    assert_eq!(r.value(0, 0, 1), 200.0);
    assert_eq!(r.value(2, 1, 0), 255.0);
}

#[test]
fn synthetic_fractional_rescale_gives_f32() {
    let tmp = tempfile::tempdir().unwrap();
    for z in 0..2 {
        let mut s = Synth::new(z as f64, vec![0, 1, 2, 3, 4, 5]);
        s.slope = "0.5";
        s.intercept = "-1.25";
        s.instance = z;
        s.write(&tmp.path().join(format!("{z}.dcm")));
    }
    let r = load_raw(tmp.path()).unwrap();
    assert_eq!(r.samples.sample_type(), SampleType::F32);
    assert_eq!(r.value(2, 1, 1), 1.25);
}

#[test]
fn synthetic_mixed_sizes_and_series() {
    let tmp = tempfile::tempdir().unwrap();
    for z in 0..3 {
        let mut s = Synth::new(z as f64, vec![7; 6]);
        s.instance = z;
        s.write(&tmp.path().join(format!("ok{z}.dcm")));
    }
    // Odd size in the same series.
    let mut s = Synth::new(3.0, vec![1; 12]);
    s.rows = 3;
    s.cols = 4;
    s.instance = 9;
    s.write(&tmp.path().join("odd.dcm"));
    // A second, smaller series.
    let mut s = Synth::new(0.0, vec![9; 6]);
    s.series = "9.9.9";
    s.write(&tmp.path().join("other.dcm"));
    let r = load_raw(tmp.path()).unwrap();
    assert_eq!(r.dims, [3, 2, 3]);
    let w = r.warnings.join("\n");
    assert!(w.contains("odd.dcm") && w.contains("4×3"), "{w}");
    assert!(w.contains("2 series"), "{w}");
    assert!(r.value(0, 0, 0) == 7.0);
}

#[test]
fn dicom_errors_are_clear() {
    let tmp = tempfile::tempdir().unwrap();
    // Empty folder.
    let e = load_raw(tmp.path()).unwrap_err().to_string();
    assert!(e.contains("no files"), "{e}");
    // Only junk.
    std::fs::write(tmp.path().join("a.dcm"), b"garbage garbage").unwrap();
    let e = load_raw(tmp.path()).unwrap_err().to_string();
    assert!(
        e.contains("no DICOM image files") && e.contains("a.dcm"),
        "{e}"
    );
    // Truncated pixel data: header intact, pixel data cut.
    let bytes = std::fs::read(lidc("000111.dcm")).unwrap();
    let d2 = tmp.path().join("trunc");
    std::fs::create_dir(&d2).unwrap();
    std::fs::write(d2.join("t.dcm"), &bytes[..bytes.len() - 1000]).unwrap();
    let e = load_raw(&d2).unwrap_err();
    assert!(matches!(e, VolumeError::Format { .. }), "{e}");
    assert!(
        e.to_string().contains("t.dcm") && e.to_string().contains("(7FE0,0010)"),
        "{e}"
    );

    // A small file whose PixelData claims 2 GiB: refused before any allocation.
    let d3 = tmp.path().join("huge");
    std::fs::create_dir(&d3).unwrap();
    let good = d3.join("good.dcm");
    Synth::new(0.0, vec![1; 6]).write(&good);
    let mut b = std::fs::read(&good).unwrap();
    let at = b
        .windows(8)
        .position(|w| w == [0xE0, 0x7F, 0x10, 0x00, b'O', b'W', 0, 0])
        .unwrap();
    b[at + 8..at + 12].copy_from_slice(&0x7FFF_FFF0u32.to_le_bytes());
    std::fs::write(&good, &b).unwrap();
    let e = load_raw(&d3).unwrap_err().to_string();
    assert!(
        e.contains("good.dcm") && e.contains("2147483632 bytes"),
        "{e}"
    );

    // An invalid value representation is reported, not guessed at.
    let bad_vr = tmp.path().join("badvr.dcm");
    Synth::new(0.0, vec![1; 6]).write(&bad_vr);
    let mut b = std::fs::read(&bad_vr).unwrap();
    let at = b
        .windows(6)
        .position(|w| w == [0x08, 0x00, 0x60, 0x00, b'C', b'S'])
        .unwrap();
    b[at + 4] = 0xD7;
    std::fs::write(&bad_vr, &b).unwrap();
    let e = load_raw(&bad_vr).unwrap_err().to_string();
    assert!(
        e.contains("(0008,0060)") && e.contains("value representation"),
        "{e}"
    );

    // A compressed transfer syntax over native pixel data: a format error naming both.
    let rle = tmp.path().join("rle.dcm");
    Synth::new(0.0, vec![1; 6]).write(&rle);
    let mut b = std::fs::read(&rle).unwrap();
    let at = b
        .windows(20)
        .position(|w| w == b"1.2.840.10008.1.2.1\0")
        .unwrap();
    b[at..at + 20].copy_from_slice(b"1.2.840.10008.1.2.5\0");
    std::fs::write(&rle, &b).unwrap();
    let e = load_raw(&rle).unwrap_err();
    assert!(matches!(e, VolumeError::Format { .. }), "{e}");
    assert!(
        e.to_string().contains("RLE Lossless") && e.to_string().contains("native"),
        "{e}"
    );
}
