//! DICOM as hospitals export it: compressed transfer syntaxes, MONOCHROME1, signed and 8-bit
//! data, enhanced multi-frame files. The files are made from the real chest CT series with real
//! encoders (dcmtk, GDCM) by `scripts/make_dicom_fixtures.py` and compared with the uncompressed
//! original as voxlight's native path decodes it: exactly for lossless codecs, within stated
//! bounds for lossy ones.
//!
//! The fixtures are made once per script version under Cargo's test tmp dir. Making them needs
//! dcmtk, GDCM's tools (libgdcm-tools) and Python 3 with pydicom 3 and numpy; without them these
//! tests fail with a message naming what to install.
//!
//! `load_time_per_codec` (ignored) times loading the whole series per codec; run it with
//! `cargo test --release -p voxlight-volumes --test dicom_codecs -- --ignored --nocapture`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use voxlight_volumes::testdata::require_shared_data_dir;
use voxlight_volumes::{RawVolume, SampleType, Samples, VolumeError, load_raw, scan_catalog};

/// Sorted slices z = 50..57 of the chest series: 8 slices, holding known voxel A (z = 54).
const SUBSET_FIRST_Z: u32 = 50;
const SUBSET: &str = "50:58";
/// Must match JPEGLS_NEAR in the script: the largest error of a stored value.
const JPEGLS_NEAR: f64 = 3.0;
/// 12-bit lossy JPEG (dcmcjpeg +ee +bt, IJG quality 90) against the original, in HU (slope 1:
/// one stored step is 1 HU). Measured: the 8-slice subset max 21 HU, RMS 3.4 HU (its enhanced
/// multi-frame copy max 22 HU); the whole series max 27 HU, RMS 3.4 HU. The bounds leave room for
/// another IDCT's rounding, not for a wrong decode (a lost rescale is 1023 HU off, 8-bit data
/// 16 HU steps everywhere).
const JPEG12_MAX_HU: f64 = 40.0;
const JPEG12_RMS_HU: f64 = 5.0;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/make_dicom_fixtures.py")
}

/// FNV-1a: a cache key that is stable across Rust versions.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Runs the fixture script (unless its output for this script version exists) and returns the
/// folder holding one sub-folder per variant.
fn make_fixtures(name: &str, args: &[&str]) -> PathBuf {
    let script = script();
    let text = std::fs::read(&script)
        .unwrap_or_else(|e| panic!("cannot read the fixture script {}: {e}", script.display()));
    let key = fnv1a(&[text.as_slice(), args.join(" ").as_bytes()].concat());
    let out = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("dicom-fixtures")
        .join(format!("{name}-{key:016x}"));
    if out.is_dir() {
        return out;
    }
    // Fixtures of earlier script versions are dead weight (the whole series is 165 MB).
    if let Ok(entries) = std::fs::read_dir(out.parent().expect("fixture folder has a parent")) {
        for entry in entries.flatten() {
            let stale = entry.file_name().to_str().is_some_and(|n| {
                n.strip_prefix(name)
                    .and_then(|rest| rest.strip_prefix('-'))
                    .is_some_and(|key| {
                        key.len() == 16 && key.chars().all(|c| c.is_ascii_hexdigit())
                    })
            });
            if stale {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
    }
    let source = require_shared_data_dir().join("ct-chest-lidc");
    let result = Command::new("python3")
        .arg(&script)
        .arg("--source")
        .arg(&source)
        .arg("--out")
        .arg(&out)
        .args(args)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "cannot run python3 for {}: {e}. The DICOM fixtures need Python 3 with pydicom 3 \
                 and numpy, dcmtk and libgdcm-tools",
                script.display()
            )
        });
    assert!(
        result.status.success(),
        "making the DICOM fixtures failed ({}):\n{}{}\nThey need dcmtk and libgdcm-tools \
         (apt-get install dcmtk libgdcm-tools) and Python 3 with pydicom 3 and numpy \
         (pip install 'pydicom>=3' numpy).",
        result.status,
        String::from_utf8_lossy(&result.stdout),
        String::from_utf8_lossy(&result.stderr)
    );
    out
}

/// Every variant of the 8-slice subset.
fn subset(variant: &str) -> PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| make_fixtures("subset", &["--z-range", SUBSET]))
        .join(variant)
}

/// The whole series (128 slices) as RLE Lossless files, as one enhanced multi-frame file and as
/// 12-bit lossy JPEG files.
fn full_series(variant: &str) -> PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| make_fixtures("full", &["--variants", "rle,enhanced,jpeg-extended-12bit"]))
        .join(variant)
}

fn load(dir: &Path) -> RawVolume {
    load_raw(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()))
}

/// The uncompressed original subset, decoded by voxlight's native path (HU, int16).
fn original() -> &'static RawVolume {
    static ORIGINAL: OnceLock<RawVolume> = OnceLock::new();
    ORIGINAL.get_or_init(|| {
        let r = load(&subset("native"));
        assert_eq!(r.dims, [512, 512, 8]);
        assert_eq!(r.samples.sample_type(), SampleType::I16);
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        // Known voxel A of the README, at z = 54 of the whole series.
        assert_eq!(r.value(160, 444, 54 - SUBSET_FIRST_Z), -907.0);
        r
    })
}

fn values(r: &RawVolume) -> Vec<f64> {
    (0..r.voxel_count())
        .map(|i| r.samples.get(i).expect("index below voxel_count"))
        .collect()
}

/// Geometry equal to the original's: dims, spacing and slice order (checked by the values).
fn assert_same_geometry(r: &RawVolume, what: &str) {
    let o = original();
    assert_eq!(r.dims, o.dims, "{what}: dims");
    assert_eq!(r.spacing, o.spacing, "{what}: spacing");
    assert_eq!(r.units, "HU", "{what}: units");
}

/// Loads a lossless variant and checks that it equals the original voxel for voxel.
fn assert_lossless(variant: &str, format_names: &str) -> RawVolume {
    let r = load(&subset(variant));
    assert_same_geometry(&r, variant);
    assert!(
        r.format.contains(format_names),
        "{variant}: format {:?} should name {format_names:?}",
        r.format
    );
    assert!(r.warnings.is_empty(), "{variant}: {:?}", r.warnings);
    assert_eq!(
        r.samples.sample_type(),
        SampleType::I16,
        "{variant}: HU as int16"
    );
    let (got, want) = (values(&r), values(original()));
    let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
    assert_eq!(
        differ, 0,
        "{variant}: {differ} voxels differ from the original"
    );
    r
}

fn assert_lossy_warning(r: &RawVolume, variant: &str) {
    assert!(
        r.warnings.iter().any(|w| w.contains("compressed lossily")),
        "{variant}: lossy compression should be reported: {:?}",
        r.warnings
    );
}

#[test]
fn explicit_vr_little_endian_equals_the_original() {
    assert_lossless("explicit", "Explicit VR Little Endian");
}

#[test]
fn rle_lossless_equals_the_original() {
    assert_lossless("rle", "RLE Lossless");
}

#[test]
fn jpeg_lossless_first_order_prediction_equals_the_original() {
    assert_lossless(
        "jpeg-lossless-sv1",
        "JPEG Lossless, Non-Hierarchical, First-Order Prediction",
    );
}

#[test]
fn jpeg_lossless_process_14_selection_value_6_equals_the_original() {
    assert_lossless(
        "jpeg-lossless-p14",
        "JPEG Lossless, Non-Hierarchical (Process 14)",
    );
}

#[test]
fn jpeg_ls_lossless_from_dcmtk_and_gdcm_equals_the_original() {
    assert_lossless("jpegls-lossless", "JPEG-LS Lossless");
    assert_lossless("gdcm-jpegls-lossless", "JPEG-LS Lossless");
}

#[test]
fn jpeg_2000_lossless_equals_the_original() {
    assert_lossless(
        "j2k-lossless",
        "JPEG 2000 Image Compression (Lossless Only)",
    );
}

/// GDCM 3.0 writes the standard attributes of Implicit VR input as UN; the rescale must still
/// be read (as the dictionary VR's text), or every value would be off by 1000 HU.
#[test]
fn jpeg_2000_with_attributes_encoded_as_un_equals_the_original() {
    assert_lossless("j2k-lossless-un", "JPEG 2000");
}

/// Largest absolute difference between two volumes' values.
fn max_difference(a: &RawVolume, b: &RawVolume) -> f64 {
    values(a)
        .iter()
        .zip(&values(b))
        .fold(0.0, |max, (x, y)| max.max((x - y).abs()))
}

/// A lossy variant: same geometry, reported as lossy, and equal (within `reference_tolerance` HU
/// per voxel, and without bias) to `reference`, the same files decoded to native by the
/// encoder's own decoder. Returns (max, rms) error against the original in HU.
fn check_lossy(variant: &str, name: &str, reference: &str, reference_tolerance: f64) -> (f64, f64) {
    let r = load(&subset(variant));
    assert_same_geometry(&r, variant);
    assert!(r.format.contains(name), "{variant}: {}", r.format);
    assert_lossy_warning(&r, variant);
    let reference_values = values(&load(&subset(reference)));
    let ours = values(&r);
    let off = ours
        .iter()
        .zip(&reference_values)
        .fold(0.0f64, |max, (a, b)| max.max((a - b).abs()));
    let off_mean = ours
        .iter()
        .zip(&reference_values)
        .map(|(a, b)| a - b)
        .sum::<f64>()
        / ours.len() as f64;
    assert!(
        off <= reference_tolerance,
        "{variant}: differs from {reference} by up to {off} HU (tolerance {reference_tolerance})"
    );
    assert!(
        off_mean.abs() < 0.5,
        "{variant}: differs from {reference} by {off_mean} HU on average"
    );
    let (got, want) = (values(&r), values(original()));
    let n = got.len() as f64;
    let (max, sq, sum) =
        got.iter()
            .zip(&want)
            .fold((0.0f64, 0.0f64, 0.0f64), |(max, sq, sum), (a, b)| {
                let d = a - b;
                (max.max(d.abs()), sq + d * d, sum + d)
            });
    let (rms, mean) = ((sq / n).sqrt(), sum / n);
    // The encoders' own bias (dcmtk's 8-bit mapping truncates) is reported, not asserted.
    eprintln!(
        "{variant}: vs original max {max:.1} HU, rms {rms:.2} HU, mean {mean:+.2} HU; \
         vs reference decoder max {off:.1} HU, mean {off_mean:+.3} HU"
    );
    (max, rms)
}

/// Near-lossless JPEG-LS: every stored value within NEAR (slope 1: the same bound in HU), and
/// exactly what dcmtk's decoder (CharLS) gives.
#[test]
fn jpeg_ls_near_lossless_stays_within_near() {
    let (max, _) = check_lossy(
        "jpegls-near",
        "JPEG-LS Lossy",
        "jpegls-near-dcmtk-decoded",
        0.0,
    );
    assert!(
        max <= JPEGLS_NEAR,
        "max error {max} HU > NEAR {JPEGLS_NEAR}"
    );
    assert!(max >= 1.0, "near-lossless coding should change some values");
}

/// dcmtk maps the 12-bit values onto 8 bits for baseline JPEG (RescaleSlope ≈ 16.06, intercept
/// −2023): one stored step is 16 HU before the DCT's own error. IDCTs may round differently
/// from libjpeg's by one step.
#[test]
fn jpeg_baseline_is_close_to_the_original() {
    let (max, rms) = check_lossy(
        "jpeg-baseline",
        "JPEG Baseline",
        "jpeg-baseline-dcmtk-decoded",
        16.1,
    );
    assert!(
        rms < 30.0,
        "rms error {rms} HU (PSNR over 4096 HU ≥ 42.7 dB)"
    );
    assert!(max < 300.0, "max error {max} HU");
}

/// 8 bits stored (the original >> 4, RescaleSlope 16): natively exact, and through 8-bit JPEG
/// Extended (process 2) close.
#[test]
fn eight_bit_native_and_jpeg_extended() {
    let native = load(&subset("native-8bit"));
    assert_same_geometry(&native, "native-8bit");
    let want: Vec<f64> = values(original())
        .iter()
        .map(|hu| 16.0 * ((*hu as i64 + 1000) >> 4) as f64 - 1000.0)
        .collect();
    assert!(values(&native) == want, "8-bit values × 16 − 1000");

    let (max, rms) = check_lossy(
        "jpeg-extended-8bit",
        "JPEG Extended",
        "jpeg-extended-8bit-dcmtk-decoded",
        16.1,
    );
    assert!(rms < 30.0, "rms error {rms} HU");
    assert!(max < 300.0, "max error {max} HU");
}

/// Lossy JPEG 2000 at 10:1 (irreversible wavelet: floating point, so GDCM's OpenJPEG and the
/// Rust port may differ by a unit).
#[test]
fn jpeg_2000_lossy_is_close_to_the_original() {
    let (max, rms) = check_lossy(
        "j2k-lossy",
        "JPEG 2000 Image Compression",
        "j2k-lossy-gdcm-decoded",
        1.0,
    );
    assert!(
        rms < 20.0,
        "rms error {rms} HU (PSNR over 4096 HU ≥ 46.2 dB)"
    );
    assert!(max < 300.0, "max error {max} HU");
}

/// GDCM codes 12-bit data as 16-bit JPEG 2000; near a plateau at 4095 the lossy reconstruction
/// overshoots. Those values are clamped to 4095, not wrapped (masking to 12 bits would turn
/// 4100 into 4, i.e. bone into air).
#[test]
fn jpeg_2000_lossy_overshoot_above_bits_stored_is_clamped() {
    let bright = load(&subset("bright"));
    assert_same_geometry(&bright, "bright");
    let r = load(&subset("bright-j2k-lossy"));
    assert_same_geometry(&r, "bright-j2k-lossy");
    let max = max_difference(&r, &bright);
    // GDCM's own decoding keeps the 16-bit values (it rewrites BitsStored to 16): proof that
    // the stream does reconstruct values above 4095.
    let unclamped = load(&subset("bright-j2k-lossy-gdcm-decoded"));
    let (_, top) = bright.min_max();
    let (_, unclamped_top) = unclamped.min_max();
    let (lo, hi) = r.min_max();
    eprintln!(
        "bright-j2k-lossy: max error {max:.1} HU; top {top} HU, GDCM decodes up to \
         {unclamped_top} HU, voxlight {lo}..{hi} HU"
    );
    assert!(unclamped_top > top, "the fixture should overshoot 4095");
    assert_eq!(hi, top, "clamped at 4095 stored");
    assert!(max < 300.0, "max error {max} HU: wrapped values?");
}

/// 12-bit lossy JPEG (process 4, which jpeg-decoder cannot read) through libjpeg-turbo: close to
/// the original, and what dcmtk's own decoder (IJG libjpeg, the same integer IDCT) makes of the
/// same files, within a rounding step (measured: identical). dcmtk stored the values shifted by
/// 1023 with RescaleIntercept −2023: the HU come out right only with the file's own rescale.
#[test]
fn jpeg_extended_12_bit_is_close_to_the_original() {
    let (max, rms) = check_lossy(
        "jpeg-extended-12bit",
        "JPEG Extended",
        "jpeg-extended-12bit-dcmtk-decoded",
        1.0,
    );
    assert!(
        rms < JPEG12_RMS_HU,
        "rms error {rms} HU (bound {JPEG12_RMS_HU})"
    );
    assert!(
        max < JPEG12_MAX_HU,
        "max error {max} HU (bound {JPEG12_MAX_HU})"
    );
    assert!(max >= 1.0, "lossy coding should change some values");
    let r = load(&subset("jpeg-extended-12bit"));
    assert_eq!(r.samples.sample_type(), SampleType::I16, "HU as int16");
    // Known voxel A of the README (−907 HU), within the bound.
    let a = r.value(160, 444, 54 - SUBSET_FIRST_Z);
    assert!((a + 907.0).abs() < JPEG12_MAX_HU, "voxel A: {a} HU");
}

/// The same 12-bit streams cut into 16 kB fragments (each frame over ~8 fragments), as single
/// files and as one enhanced multi-frame file whose frames are found through the basic offset
/// table: identical to the one-fragment files, and to the original within the bound.
#[test]
fn jpeg_extended_12_bit_frames_split_over_fragments() {
    let whole = load(&subset("jpeg-extended-12bit"));
    let split = load(&subset("jpeg-extended-12bit-fragmented"));
    assert_same_geometry(&split, "jpeg-extended-12bit-fragmented");
    assert!(
        split.samples == whole.samples,
        "fragmented files decode differently"
    );
    let r = load(&subset("enhanced-jpeg-extended-12bit"));
    assert_same_geometry(&r, "enhanced-jpeg-extended-12bit");
    assert!(
        r.format.starts_with("DICOM multi-frame image (8 frames")
            && r.format.contains("JPEG Extended"),
        "{}",
        r.format
    );
    assert_lossy_warning(&r, "enhanced-jpeg-extended-12bit");
    let max = max_difference(&r, original());
    eprintln!("enhanced-jpeg-extended-12bit: max error {max:.1} HU");
    assert!(max < JPEG12_MAX_HU, "max error {max} HU");
}

/// Damage inside a 12-bit JPEG stream that keeps the DICOM structure intact: a premature end
/// (EOI) in the entropy-coded data, corrupt entropy-coded data, and a frame header that
/// disagrees with Rows. Each is an error naming the file and the decoder's complaint, never a
/// panic or grey-filled voxels.
#[test]
fn damaged_12_bit_jpeg_stream_is_an_error() {
    let dir = tempfile::tempdir().expect("temp dir");
    let src = std::fs::read_dir(subset("jpeg-extended-12bit"))
        .expect("listing the 12-bit JPEG fixtures")
        .map(|e| e.expect("folder entry").path())
        .min()
        .expect("one file");
    let seed = std::fs::read(&src).expect("reading a fixture");
    let find = |pat: &[u8]| {
        seed.windows(pat.len())
            .position(|w| w == pat)
            .expect("pattern in the JPEG stream")
    };
    // SOF1 (extended sequential), 12-bit precision, then height and width.
    let sof = find(&[0xFF, 0xC1, 0x00, 0x0B, 0x0C]);
    let sos = find(&[0xFF, 0xDA]);
    let middle = sos + (seed.len() - sos) / 2;
    let mut cases: Vec<(&str, Vec<u8>)> = Vec::new();
    let mut b = seed.clone();
    b[middle..middle + 2].copy_from_slice(&[0xFF, 0xD9]);
    cases.push(("premature end", b));
    let mut b = seed.clone();
    for (i, x) in b[middle..middle + 64].iter_mut().enumerate() {
        *x = if i % 2 == 0 { 0xFF } else { 0x00 };
    }
    cases.push(("corrupt entropy-coded data", b));
    let mut b = seed.clone();
    b[sof + 5..sof + 7].copy_from_slice(&256u16.to_be_bytes());
    cases.push(("height 256", b));
    for (i, (what, bytes)) in cases.into_iter().enumerate() {
        let path = dir.path().join(format!("damaged-{i}.dcm"));
        std::fs::write(&path, bytes).expect("writing a damaged file");
        let e = match std::panic::catch_unwind(|| load_raw(&path)) {
            Ok(Ok(r)) => panic!("{what}: loaded {:?} without an error", r.dims),
            Ok(Err(e)) => e,
            Err(_) => panic!("{what}: the loader panicked"),
        };
        assert!(matches!(e, VolumeError::Format { .. }), "{what}: {e}");
        let msg = e.to_string();
        eprintln!("{what}: {msg}");
        assert!(
            msg.contains(&format!("damaged-{i}.dcm")) && msg.contains("JPEG Extended"),
            "{what}: {msg}"
        );
    }
}

/// Signed 12-bit stored values that are the HU themselves, native and through four codecs.
#[test]
fn signed_12_bit_through_codecs_equals_the_original() {
    for (variant, name) in [
        ("signed", "Explicit VR Little Endian"),
        ("signed-rle", "RLE Lossless"),
        ("signed-jpeg-lossless-sv1", "First-Order Prediction"),
        ("signed-jpegls-lossless", "JPEG-LS Lossless"),
        ("signed-j2k-lossless", "JPEG 2000"),
    ] {
        assert_lossless(variant, name);
    }
}

/// MONOCHROME1 without a rescale is mirrored in the stored range, so values mean what they
/// would under MONOCHROME2 (here: the original stored values, HU + 1000).
#[test]
fn monochrome1_without_rescale_is_inverted() {
    let want: Vec<f64> = values(original()).iter().map(|hu| hu + 1000.0).collect();
    for (variant, name) in [
        ("monochrome1", "Explicit VR Little Endian"),
        ("monochrome1-jpegls-lossless", "JPEG-LS Lossless"),
    ] {
        let r = load(&subset(variant));
        assert_same_geometry(&r, variant);
        assert!(r.format.contains(name), "{variant}: {}", r.format);
        assert_eq!(r.samples.sample_type(), SampleType::U16, "{variant}");
        assert!(values(&r) == want, "{variant}: 4095 − stored′ = stored");
    }
}

/// MONOCHROME1 with a rescale keeps the rescaled values: the inversion is a display step after
/// the Modality LUT (PS3.4 N.2), and HU mean the same under either polarity.
#[test]
fn monochrome1_with_rescale_keeps_the_rescaled_values() {
    assert_lossless("monochrome1-rescaled", "Explicit VR Little Endian");
}

/// One Enhanced CT file, frames shuffled, each frame's position and rescale only in its
/// functional groups (and the rescale differing per frame), native and through four codecs.
#[test]
fn enhanced_multi_frame_equals_the_original() {
    for (variant, name) in [
        ("enhanced", "Explicit VR Little Endian"),
        ("enhanced-rle", "RLE Lossless"),
        ("enhanced-jpeg-lossless-sv1", "First-Order Prediction"),
        ("enhanced-jpegls-lossless", "JPEG-LS Lossless"),
        ("enhanced-j2k-lossless", "JPEG 2000"),
    ] {
        let r = assert_lossless(variant, name);
        assert!(
            r.format.starts_with("DICOM multi-frame image (8 frames"),
            "{variant}: {}",
            r.format
        );
        // A folder holding the one file is one dataset.
        let dir = subset(variant);
        let entries = scan_catalog(&dir).expect("scanning the fixture folder");
        assert_eq!(entries.len(), 1, "{variant}: {entries:?}");
        assert_eq!(entries[0].kind, "dicom");
        // The file on its own loads the same volume.
        let file = std::fs::read_dir(&dir)
            .expect("listing the fixture folder")
            .map(|e| e.expect("folder entry").path())
            .next()
            .expect("one file");
        assert!(load(&file).samples == r.samples, "{variant}: file alone");
    }
}

/// A transfer syntax dicom-rs knows but has no decoder for here (JPEG XL): a clear error.
#[test]
fn codec_not_built_in_is_named() {
    let dir = tempfile::tempdir().expect("temp dir");
    let src = std::fs::read_dir(subset("rle"))
        .expect("listing the RLE fixtures")
        .map(|e| e.expect("folder entry").path())
        .next()
        .expect("one RLE file");
    let mut obj = dicom_object::open_file(&src).expect("opening the RLE fixture");
    obj.meta_mut().transfer_syntax = "1.2.840.10008.1.2.4.110".to_string();
    obj.meta_mut().update_information_group_length();
    let jxl = dir.path().join("jxl.dcm");
    obj.write_to_file(&jxl).expect("writing the JPEG XL file");
    let e = load_raw(&jxl).unwrap_err();
    assert!(matches!(e, VolumeError::Unsupported { .. }), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("1.2.840.10008.1.2.4.110")
            && msg.contains("JPEG XL Lossless")
            && msg.contains("no decoder"),
        "{msg}"
    );
}

/// Damaged compressed data gives errors (or, where the damage is invisible to the codec,
/// values), never a panic out of the loader: flipped, overwritten and cut bytes in the pixel
/// data of one file per codec.
#[test]
fn damaged_compressed_pixel_data_never_panics() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut rng = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move |n: usize| {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng % n.max(1) as u64) as usize
    };
    let mut outcomes = [0usize; 2];
    for variant in [
        "rle",
        "jpeg-lossless-sv1",
        "jpeg-baseline",
        "jpegls-lossless",
        "jpegls-near",
        "j2k-lossless",
        "j2k-lossy",
        "jpeg-extended-12bit",
    ] {
        let src = std::fs::read_dir(subset(variant))
            .expect("listing a fixture folder")
            .map(|e| e.expect("folder entry").path())
            .min()
            .expect("one file");
        let seed = std::fs::read(&src).expect("reading a fixture");
        // Damage only the encapsulated pixel data (after the last PixelData tag).
        let pixel_start = seed
            .windows(4)
            .rposition(|w| w == [0xE0, 0x7F, 0x10, 0x00])
            .expect("a PixelData element");
        for i in 0..40 {
            let mut b = seed.clone();
            let span = b.len() - pixel_start;
            match i % 4 {
                0 => {
                    for _ in 0..1 + next(8) {
                        let at = pixel_start + next(span);
                        b[at] ^= 1 << next(8);
                    }
                }
                1 => {
                    let at = pixel_start + next(span);
                    for x in b.iter_mut().skip(at).take(64) {
                        *x = next(256) as u8;
                    }
                }
                2 => b.truncate(pixel_start + next(span)),
                _ => {
                    // Fragment headers and the codec's own headers are near the start.
                    let at = pixel_start + next(span.min(200));
                    for x in b.iter_mut().skip(at).take(4) {
                        *x = [0x00, 0xFF, 0x7F][next(3)];
                    }
                }
            }
            let path = dir.path().join(format!("{variant}-{i}.dcm"));
            std::fs::write(&path, &b).expect("writing a damaged file");
            match std::panic::catch_unwind(|| load_raw(&path).map(|r| r.voxel_count())) {
                Ok(Ok(_)) => outcomes[0] += 1,
                Ok(Err(e)) => {
                    assert!(e.to_string().contains(&format!("{variant}-{i}.dcm")), "{e}");
                    outcomes[1] += 1;
                }
                Err(_) => panic!("the loader panicked on damaged {variant} #{i}"),
            }
        }
    }
    eprintln!(
        "damaged files: {} loaded, {} refused",
        outcomes[0], outcomes[1]
    );
    assert!(
        outcomes[1] > 50,
        "damage should mostly be refused: {outcomes:?}"
    );
}

/// The README's known values of the whole series, through RLE files and one enhanced
/// multi-frame file.
#[test]
fn full_series_rle_and_enhanced_match_the_readme() {
    for variant in ["rle", "enhanced"] {
        let r = load(&full_series(variant));
        assert_eq!(r.dims, [512, 512, 128], "{variant}");
        assert_eq!(r.spacing, [0.78125, 0.78125, 1.0], "{variant}");
        assert_eq!(r.samples.sample_type(), SampleType::I16, "{variant}");
        assert!(r.warnings.is_empty(), "{variant}: {:?}", r.warnings);
        for ([x, y, z], hu) in [
            ([160, 444, 54], -907.0),
            ([153, 212, 103], 78.0),
            ([261, 170, 23], 906.0),
            ([416, 319, 116], 1766.0),
        ] {
            assert_eq!(r.value(x, y, z), hu, "{variant}: ({x}, {y}, {z})");
        }
        assert_eq!(r.sum_exact(), Some(-21_278_658_688), "{variant}: sum of HU");
        assert_eq!(r.min_max(), (-1000.0, 1766.0), "{variant}");
        if let Samples::I16(v) = &r.samples {
            let first_max = v.iter().position(|&h| h == 1766).expect("a maximum");
            assert_eq!(first_max, 416 + 512 * (319 + 512 * 116), "{variant}");
        }
    }
}

/// The README's known values of the whole series through 12-bit lossy JPEG: each within the
/// lossy bound, and the whole volume within the bounds of the original.
#[test]
fn full_series_jpeg_extended_12_bit_matches_the_readme_within_the_bound() {
    let r = load(&full_series("jpeg-extended-12bit"));
    assert_eq!(r.dims, [512, 512, 128]);
    assert_eq!(r.spacing, [0.78125, 0.78125, 1.0]);
    assert_eq!(r.samples.sample_type(), SampleType::I16);
    assert_lossy_warning(&r, "jpeg-extended-12bit");
    let rle = load(&full_series("rle"));
    for ([x, y, z], hu) in [
        ([160, 444, 54], -907.0),
        ([153, 212, 103], 78.0),
        ([261, 170, 23], 906.0),
        ([416, 319, 116], 1766.0),
    ] {
        let got = r.value(x, y, z);
        eprintln!("({x}, {y}, {z}): {got} HU, README {hu} HU");
        assert!(
            (got - hu).abs() < JPEG12_MAX_HU,
            "({x}, {y}, {z}): {got} HU, README {hu} HU"
        );
        assert_eq!(rle.value(x, y, z), hu, "RLE ({x}, {y}, {z})");
    }
    let (got, want) = (values(&r), values(&rle));
    let n = got.len() as f64;
    let (max, sq) = got
        .iter()
        .zip(&want)
        .fold((0.0f64, 0.0f64), |(max, sq), (a, b)| {
            let d = a - b;
            (max.max(d.abs()), sq + d * d)
        });
    let rms = (sq / n).sqrt();
    eprintln!("jpeg-extended-12bit, whole series: vs original max {max:.1} HU, rms {rms:.2} HU");
    assert!(max < JPEG12_MAX_HU, "max error {max} HU");
    assert!(rms < JPEG12_RMS_HU, "rms error {rms} HU");
}

/// Load time of the whole series per transfer syntax (release build; nothing asserted about
/// speed). Prints a table: ms (median of 3) and MB on disk. `VOXLIGHT_BENCH_ONLY=a,b` times
/// only those variants.
#[test]
#[ignore = "benchmark: run explicitly with --release -- --ignored --nocapture"]
fn load_time_per_codec() {
    let variants = [
        "rle",
        "jpeg-lossless-sv1",
        "jpegls-lossless",
        "j2k-lossless",
        "jpeg-baseline",
        "jpeg-extended-12bit",
        "jpegls-near",
        "j2k-lossy",
        "enhanced",
        "enhanced-rle",
        "enhanced-jpeg-lossless-sv1",
        "enhanced-jpegls-lossless",
        "enhanced-j2k-lossless",
    ];
    let dir = make_fixtures("bench", &["--variants", &variants.join(",")]);
    println!("| variant | transfer syntax | MB on disk | load ms (median of 3) |");
    println!("|---|---|---|---|");
    let only = std::env::var("VOXLIGHT_BENCH_ONLY").ok();
    let timed = std::iter::once("native")
        .chain(variants)
        .filter(|v| only.as_ref().is_none_or(|o| o.split(',').any(|x| x == *v)));
    for variant in timed {
        let path = dir.join(variant);
        let bytes: u64 = std::fs::read_dir(&path)
            .expect("listing a fixture folder")
            .map(|e| e.expect("folder entry").metadata().expect("metadata").len())
            .sum();
        let mut times = Vec::new();
        let mut format = String::new();
        for _ in 0..3 {
            let started = std::time::Instant::now();
            let r = load(&path);
            times.push(started.elapsed().as_secs_f64() * 1e3);
            assert_eq!(r.dims, [512, 512, 128], "{variant}");
            format = r.format;
        }
        times.sort_by(f64::total_cmp);
        println!(
            "| {variant} | {format} | {:.1} | {:.0} |",
            bytes as f64 / 1e6,
            times[1]
        );
    }
}
