//! Headerless raw files (`load_raw_file`): the first 16 bytes choose the layout the caller
//! passes (dims, sample type, byte order, spacing, header bytes), the rest is the file.

#![no_main]

#[path = "common.rs"]
mod common;
#[path = "raw_layout.rs"]
mod raw_layout;

use libfuzzer_sys::fuzz_target;
use voxlight_volumes::load_raw_file;

fuzz_target!(|data: &[u8]| {
    let Some((layout, body)) = raw_layout::raw_layout(data) else {
        return;
    };
    let path = common::write("input.raw", body);
    match load_raw_file(
        &path,
        layout.dims,
        layout.sample,
        layout.endian,
        layout.spacing,
        layout.header_bytes,
    ) {
        Ok(raw) => {
            assert_eq!(raw.samples.len(), raw.voxel_count());
            common::check_volume(&raw.normalize("fuzz"));
        }
        Err(error) => common::check_error(&error),
    }
});
