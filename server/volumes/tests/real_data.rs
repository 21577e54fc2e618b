//! Loader tests against the real volumes in `../shared/data` (see its README.md for the
//! reference values used here). These fail loudly when the data folder is missing.

use std::path::{Path, PathBuf};

use voxlight_volumes::testdata::require_shared_data_dir;
use voxlight_volumes::{DatasetEntry, RawVolume, SampleType, load, load_raw, scan_catalog};

type Voxel = ([u32; 3], f64);

struct Expect {
    path: &'static str,
    dims: [u32; 3],
    spacing: [f32; 3],
    ty: SampleType,
    min: f64,
    max: f64,
    sum: i128,
    voxels: [Voxel; 4],
}

fn data(rel: &str) -> PathBuf {
    require_shared_data_dir().join(rel)
}

/// First voxel in file order holding the maximum.
fn first_max(r: &RawVolume) -> [u32; 3] {
    let (_, max) = r.min_max();
    let [nx, ny, _] = r.dims;
    let i = (0..r.voxel_count())
        .find(|&i| r.samples.get(i) == Some(max))
        .expect("max present");
    let (x, y, z) = (
        i % nx as usize,
        (i / nx as usize) % ny as usize,
        i / (nx as usize * ny as usize),
    );
    [x as u32, y as u32, z as u32]
}

fn check(e: &Expect) -> RawVolume {
    let path = data(e.path);
    let r = load_raw(&path).unwrap_or_else(|err| panic!("{}: {err}", e.path));
    assert_eq!(r.dims, e.dims, "{}: dims", e.path);
    assert_eq!(r.spacing, e.spacing, "{}: spacing", e.path);
    assert_eq!(r.samples.sample_type(), e.ty, "{}: sample type", e.path);
    assert_eq!(r.samples.len(), r.voxel_count(), "{}: sample count", e.path);
    assert_eq!(r.min_max(), (e.min, e.max), "{}: min/max", e.path);
    assert_eq!(r.sum_exact(), Some(e.sum), "{}: exact sum", e.path);
    assert_eq!(r.sum(), e.sum as f64, "{}: sum", e.path);
    for (k, ([x, y, z], v)) in e.voxels.iter().enumerate() {
        assert_eq!(
            r.value(*x, *y, *z),
            *v,
            "{}: voxel #{k} ({x},{y},{z})",
            e.path
        );
    }
    assert_eq!(first_max(&r), e.voxels[3].0, "{}: first max", e.path);
    assert!(
        r.warnings.is_empty(),
        "{}: unexpected warnings {:?}",
        e.path,
        r.warnings
    );

    // Normalize and reconstruct the known voxels.
    let v = r.clone().normalize("t");
    assert_eq!((v.value_min, v.value_max), (e.min, e.max));
    assert_eq!(v.dims, e.dims);
    assert_eq!(
        v.histogram.iter().map(|&h| h as u64).sum::<u64>(),
        v.voxel_count() as u64
    );
    for ([x, y, z], val) in &e.voxels {
        assert_eq!(
            v.raw_value(*x, *y, *z).round(),
            *val,
            "{}: raw_value({x},{y},{z})",
            e.path
        );
    }
    let [mx, my, mz] = e.voxels[3].0;
    assert_eq!(v.normalized(mx, my, mz), 1.0);
    r
}

#[test]
fn dicom_ct_chest_series() {
    let r = check(&Expect {
        path: "ct-chest-lidc",
        dims: [512, 512, 128],
        spacing: [0.78125, 0.78125, 1.0],
        ty: SampleType::I16,
        min: -1000.0,
        max: 1766.0,
        sum: -21_278_658_688,
        voxels: [
            ([160, 444, 54], -907.0),
            ([153, 212, 103], 78.0),
            ([261, 170, 23], 906.0),
            ([416, 319, 116], 1766.0),
        ],
    });
    assert_eq!(r.units, "HU");
    assert_eq!(r.modality, "CT");
    assert!(
        r.format.contains("DICOM series (128 slices"),
        "{}",
        r.format
    );
    // Corners are outside the reconstruction circle: stored 0 → -1000 HU.
    assert_eq!(r.value(0, 0, 0), -1000.0);
    let v = load(&data("ct-chest-lidc")).unwrap();
    assert_eq!(v.name, "ct-chest-lidc");
    assert_eq!(v.units, "HU");
    assert_eq!(v.world_extent(), [1.0, 1.0, 0.32]);
}

/// Each known voxel's source file, loaded on its own, holds the voxel in its only slice:
/// this pins the series' slice order (z = 54 is 000170.dcm, ...).
#[test]
fn dicom_single_files_match_sorted_series_positions() {
    for (file, [x, y], hu) in [
        ("000170.dcm", [160, 444], -907.0),
        ("000045.dcm", [153, 212], 78.0),
        ("000038.dcm", [261, 170], 906.0),
        ("000261.dcm", [416, 319], 1766.0),
    ] {
        let r = load_raw(&data("ct-chest-lidc").join(file)).unwrap();
        assert_eq!(r.dims, [512, 512, 1], "{file}");
        assert_eq!(r.value(x, y, 0), hu, "{file}");
        assert_eq!(r.units, "HU");
    }
}

#[test]
fn vti_bonsai() {
    check(&Expect {
        path: "vti/bonsai.vti",
        dims: [256, 256, 256],
        spacing: [1.0; 3],
        ty: SampleType::U8,
        min: 0.0,
        max: 255.0,
        sum: 230_038_784,
        voxels: [
            ([100, 214, 85], 39.0),
            ([81, 70, 161], 29.0),
            ([66, 214, 91], 47.0),
            ([120, 21, 107], 255.0),
        ],
    });
}

#[test]
fn vti_engine() {
    check(&Expect {
        path: "vti/engine.vti",
        dims: [256, 256, 128],
        spacing: [1.0; 3],
        ty: SampleType::U8,
        min: 0.0,
        max: 255.0,
        sum: 187_475_057,
        voxels: [
            ([187, 170, 17], 146.0),
            ([138, 139, 32], 134.0),
            ([81, 70, 80], 5.0),
            ([181, 133, 1], 255.0),
        ],
    });
}

#[test]
fn vti_aneurism() {
    check(&Expect {
        path: "vti/aneurism.vti",
        dims: [256, 256, 256],
        spacing: [1.0; 3],
        ty: SampleType::U8,
        min: 0.0,
        max: 255.0,
        sum: 17_938_365,
        voxels: [
            ([123, 120, 119], 14.0),
            ([85, 167, 61], 74.0),
            ([174, 101, 112], 18.0),
            ([120, 82, 7], 255.0),
        ],
    });
}

#[test]
fn nrrd_tooth_attached() {
    let r = check(&Expect {
        path: "nrrd/tooth.nrrd",
        dims: [103, 94, 161],
        spacing: [1.0; 3],
        ty: SampleType::U8,
        min: 0.0,
        max: 255.0,
        sum: 160_814_065,
        voxels: [
            ([65, 63, 158], 103.0),
            ([40, 78, 53], 81.0),
            ([58, 56, 34], 152.0),
            ([38, 69, 131], 255.0),
        ],
    });
    assert!(r.format.starts_with("NRRD (raw"), "{}", r.format);
}

#[test]
fn nrrd_tooth_detached_big_endian() {
    let r = check(&Expect {
        path: "nrrd/tooth.nhdr",
        dims: [103, 94, 161],
        spacing: [1.0; 3],
        ty: SampleType::U16,
        min: 0.0,
        max: 1300.0,
        sum: 821_287_590,
        voxels: [
            ([65, 63, 158], 526.0),
            ([40, 78, 53], 416.0),
            ([58, 56, 34], 774.0),
            ([38, 69, 131], 1300.0),
        ],
    });
    assert!(r.format.contains("big-endian"), "{}", r.format);
}

#[test]
fn nifti_example_ct() {
    let r = check(&Expect {
        path: "nifti/example_ct.nii.gz",
        dims: [122, 101, 112],
        spacing: [3.0; 3],
        ty: SampleType::I32,
        min: -1207.0,
        max: 3382.0,
        sum: -496_851_173,
        voxels: [
            ([84, 23, 87], -19.0),
            ([39, 21, 88], 21.0),
            ([78, 67, 109], 53.0),
            ([15, 36, 2], 3382.0),
        ],
    });
    assert_eq!(r.value(28, 42, 5), -1207.0, "first min");
    assert_eq!(r.value(84, 23, 105), -755.0);
    let v = load(&data("nifti/example_ct.nii.gz")).unwrap();
    assert_eq!(v.name, "example_ct");
}

#[test]
fn nifti_example_ct_small_int16() {
    let r = check(&Expect {
        path: "nifti/example_ct_sm.nii.gz",
        dims: [122, 101, 30],
        spacing: [3.0; 3],
        ty: SampleType::I16,
        min: -1100.0,
        max: 1207.0,
        sum: -130_894_872,
        voxels: [
            ([84, 23, 23], -755.0),
            ([39, 21, 23], -598.0),
            ([78, 67, 28], 44.0),
            ([63, 35, 2], 1207.0),
        ],
    });
    assert_eq!(r.value(43, 77, 6), -1100.0, "first min");
}

#[test]
fn nrrd_two_quantisations_agree_on_first_max() {
    let a = load_raw(&data("nrrd/tooth.nrrd")).unwrap();
    let b = load_raw(&data("nrrd/tooth.nhdr")).unwrap();
    assert_eq!(first_max(&a), first_max(&b));
}

#[test]
fn catalog_of_shared_data() {
    let dir = require_shared_data_dir();
    let entries = scan_catalog(&dir).unwrap();
    let names: Vec<(&str, &str)> = entries
        .iter()
        .map(|e| (e.name.as_str(), e.kind.as_str()))
        .collect();
    assert_eq!(
        names,
        vec![
            ("ct-chest-lidc", "dicom"),
            ("nifti/example_ct.nii.gz", "nifti"),
            ("nifti/example_ct_sm.nii.gz", "nifti"),
            ("nrrd/tooth.nhdr", "nrrd"),
            ("nrrd/tooth.nrrd", "nrrd"),
            ("vti/aneurism.vti", "vti"),
            ("vti/bonsai.vti", "vti"),
            ("vti/engine.vti", "vti"),
        ]
    );
    let e: &DatasetEntry = &entries[3];
    assert!(e.path.ends_with(Path::new("nrrd/tooth.nhdr")));
}

#[test]
fn downsampled_real_volume_keeps_extent_and_range() {
    let v = load(&data("vti/engine.vti")).unwrap();
    let d = v.downsampled(64);
    assert_eq!(d.dims, [64, 64, 32]);
    assert_eq!(d.world_extent(), v.world_extent());
    assert_eq!((d.value_min, d.value_max), (0.0, 255.0));
    assert_eq!(
        d.histogram.iter().map(|&h| h as usize).sum::<usize>(),
        d.voxel_count()
    );
}
