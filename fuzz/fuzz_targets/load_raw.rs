//! Headerless raw files (`load_raw_file`): the first 16 bytes choose the layout the caller
//! passes (dims, sample type, byte order, spacing, header bytes), the rest is the file.

#![no_main]

#[path = "common.rs"]
mod common;

use libfuzzer_sys::fuzz_target;
use voxlight_volumes::{Endian, SampleType, load_raw_file};

const TYPES: [SampleType; 8] = [
    SampleType::U8,
    SampleType::I8,
    SampleType::U16,
    SampleType::I16,
    SampleType::U32,
    SampleType::I32,
    SampleType::F32,
    SampleType::F64,
];

fuzz_target!(|data: &[u8]| {
    let Some((params, body)) = data.split_first_chunk::<16>() else {
        return;
    };
    let u16_at = |i: usize| u16::from_le_bytes([params[i], params[i + 1]]) as u32;
    // Any u32 is a legal argument; small values keep most runs about the data.
    let wide = params[15] & 0x80 != 0;
    let dim = |i: usize| {
        if wide {
            u16_at(i) << 16 | u16_at(i)
        } else {
            u16_at(i)
        }
    };
    let dims = [dim(0), dim(2), dim(4)];
    let sample = TYPES[(params[6] & 7) as usize];
    let endian = if params[6] & 8 == 0 {
        Endian::Little
    } else {
        Endian::Big
    };
    let spacing = [
        f32::from_le_bytes([params[7], params[8], params[9], params[10]]),
        1.0,
        if params[15] & 1 == 0 { 1.0 } else { f32::NAN },
    ];
    // Mostly small; sometimes near u64::MAX (the loader must not overflow adding it).
    let header_bytes = if params[15] & 2 == 0 {
        u16_at(11) as u64
    } else {
        u64::MAX - u16_at(11) as u64
    };
    let path = common::write("input.raw", body);
    match load_raw_file(&path, dims, sample, endian, spacing, header_bytes) {
        Ok(raw) => {
            assert_eq!(raw.samples.len(), raw.voxel_count());
            common::check_volume(&raw.normalize("fuzz"));
        }
        Err(error) => common::check_error(&error),
    }
});
