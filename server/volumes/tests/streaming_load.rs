//! `load` reads samples that are not 16-bit (and rescaled NIfTI) in two streaming passes
//! straight to 16 bits; these tests hold it to exactly what `load_raw` + `normalize` give, on
//! the shared volumes and on files of every sample type, encoding and rescale.

use std::io::Write;
use std::path::Path;

use voxlight_volumes::testdata::require_shared_data_dir;
use voxlight_volumes::{Volume, load, load_raw};

fn assert_same(path: &Path) -> Volume {
    let streamed = load(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let name = voxlight_volumes::default_name(path);
    let kept = load_raw(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .normalize(&name);
    assert!(
        streamed.data == kept.data,
        "{}: 16-bit data differ",
        path.display()
    );
    assert_eq!(
        (
            streamed.dims,
            streamed.spacing,
            streamed.value_min,
            streamed.value_max,
            &streamed.histogram,
            &streamed.format,
            &streamed.warnings,
        ),
        (
            kept.dims,
            kept.spacing,
            kept.value_min,
            kept.value_max,
            &kept.histogram,
            &kept.format,
            &kept.warnings,
        ),
        "{}",
        path.display()
    );
    streamed
}

#[test]
fn shared_volumes_load_the_same_streamed() {
    let dir = require_shared_data_dir();
    for rel in [
        "nifti/example_ct.nii.gz",
        "nifti/example_ct_sm.nii.gz",
        "nrrd/tooth.nhdr",
        "nrrd/tooth.nrrd",
        "vti/bonsai.vti",
        "vti/engine.vti",
        "vti/aneurism.vti",
    ] {
        assert_same(&dir.join(rel));
    }
}

/// Values of every sample type: a ramp with negative values, NaN and ±∞ for floats.
fn values(n: usize, float: bool) -> Vec<f64> {
    (0..n)
        .map(|i| {
            if float && i == 5 {
                f64::NAN
            } else if float && i == 9 {
                f64::INFINITY
            } else {
                ((i as f64 * 0.618_034).fract() * 200.0 - 50.0).round()
                    + if float { 0.25 } else { 0.0 }
            }
        })
        .collect()
}

const TYPES: [(&str, &str, i16, usize); 8] = [
    // (NRRD type, VTK type, NIfTI datatype code, bytes)
    ("uchar", "UInt8", 2, 1),
    ("signed char", "Int8", 256, 1),
    ("ushort", "UInt16", 512, 2),
    ("short", "Int16", 4, 2),
    ("uint", "UInt32", 768, 4),
    ("int", "Int32", 8, 4),
    ("float", "Float32", 16, 4),
    ("double", "Float64", 64, 8),
];

fn le_bytes(nrrd_type: &str, v: &[f64]) -> Vec<u8> {
    v.iter()
        .flat_map(|&x| match nrrd_type {
            "uchar" => vec![x as u8],
            "signed char" => vec![x as i8 as u8],
            "ushort" => (x as u16).to_le_bytes().to_vec(),
            "short" => (x as i16).to_le_bytes().to_vec(),
            "uint" => (x as u32).to_le_bytes().to_vec(),
            "int" => (x as i32).to_le_bytes().to_vec(),
            "float" => (x as f32).to_le_bytes().to_vec(),
            _ => x.to_le_bytes().to_vec(),
        })
        .collect()
}

const DIMS: [usize; 3] = [37, 29, 23];

fn gzip(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(b).expect("gzip");
    e.finish().expect("gzip")
}

fn zlib(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(b).expect("zlib");
    e.finish().expect("zlib")
}

#[test]
fn nrrd_of_every_type_and_encoding_loads_the_same_streamed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let n = DIMS.iter().product::<usize>();
    for (ty, _, _, _) in TYPES {
        let data = le_bytes(ty, &values(n, ty == "float" || ty == "double"));
        for encoding in ["raw", "gzip"] {
            let header = format!(
                "NRRD0004\ntype: {ty}\ndimension: 3\nsizes: {} {} {}\nspacings: 1 2 3\nendian: little\nencoding: {encoding}\n\n",
                DIMS[0], DIMS[1], DIMS[2]
            );
            let path = dir
                .path()
                .join(format!("{}-{encoding}.nrrd", ty.replace(' ', "_")));
            let body = if encoding == "gzip" {
                gzip(&data)
            } else {
                data.clone()
            };
            std::fs::write(&path, [header.as_bytes(), &body].concat()).expect("write");
            assert_same(&path);
        }
    }
}

fn nifti_header(code: i16, bitpix: i16, slope: f32, inter: f32) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim: [i16; 8] = [
        3,
        DIMS[0] as i16,
        DIMS[1] as i16,
        DIMS[2] as i16,
        1,
        1,
        1,
        1,
    ];
    for (k, d) in dim.iter().enumerate() {
        h[40 + 2 * k..42 + 2 * k].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&code.to_le_bytes());
    h[72..74].copy_from_slice(&bitpix.to_le_bytes());
    for (k, p) in [1.0f32, 0.5, 0.5, 2.0].iter().enumerate() {
        h[76 + 4 * k..80 + 4 * k].copy_from_slice(&p.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352f32.to_le_bytes());
    h[112..116].copy_from_slice(&slope.to_le_bytes());
    h[116..120].copy_from_slice(&inter.to_le_bytes());
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

#[test]
fn nifti_of_every_type_and_rescale_loads_the_same_streamed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let n = DIMS.iter().product::<usize>();
    for (ty, _, code, size) in TYPES {
        let data = le_bytes(ty, &values(n, ty == "float" || ty == "double"));
        for (slope, inter) in [(0.0f32, 0.0f32), (1.0, 0.0), (0.37, -1024.0)] {
            let file = [
                nifti_header(code, 8 * size as i16, slope, inter),
                data.clone(),
            ]
            .concat();
            for gz in [false, true] {
                let path = dir.path().join(format!(
                    "{}-{slope}-{}.nii{}",
                    ty.replace(' ', "_"),
                    gz as u8,
                    if gz { ".gz" } else { "" }
                ));
                std::fs::write(&path, if gz { gzip(&file) } else { file.clone() }).expect("write");
                let v = assert_same(&path);
                if slope == 0.37 {
                    assert!(v.format.contains("scaled"), "{}", v.format);
                }
            }
        }
    }
}

#[test]
fn vti_of_every_type_and_layout_loads_the_same_streamed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let n = DIMS.iter().product::<usize>();
    for (ty, vtk, _, _) in TYPES {
        let data = le_bytes(ty, &values(n, ty == "float" || ty == "double"));
        // Two zlib blocks (the second one short), as VTK writes them with a UInt32 header.
        let block = data.len().div_ceil(2);
        let parts: Vec<Vec<u8>> = data.chunks(block).map(zlib).collect();
        let mut header = Vec::new();
        for x in [parts.len(), block, data.len() - block] {
            header.extend_from_slice(&(x as u32).to_le_bytes());
        }
        for p in &parts {
            header.extend_from_slice(&(p.len() as u32).to_le_bytes());
        }
        let appended = [header, parts.concat()].concat();
        let extent = format!("0 {} 0 {} 0 {}", DIMS[0] - 1, DIMS[1] - 1, DIMS[2] - 1);
        let xml = format!(
            "<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\" compressor=\"vtkZLibDataCompressor\">\n<ImageData WholeExtent=\"{extent}\" Origin=\"0 0 0\" Spacing=\"1 1 2\">\n<Piece Extent=\"{extent}\">\n<PointData Scalars=\"s\">\n<DataArray type=\"{vtk}\" Name=\"s\" format=\"appended\" offset=\"0\"/>\n</PointData>\n</Piece>\n</ImageData>\n<AppendedData encoding=\"raw\">\n_"
        );
        let path = dir.path().join(format!("{vtk}.vti"));
        let tail = b"\n</AppendedData>\n</VTKFile>\n";
        std::fs::write(&path, [xml.as_bytes(), &appended, tail].concat()).expect("write");
        assert_same(&path);
    }
}
