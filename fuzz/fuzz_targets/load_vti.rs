//! VTK XML ImageData: appended raw (plain or zlib blocks), inline base64 and ascii arrays.

#![no_main]

#[path = "common.rs"]
mod common;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    common::load_and_check(&common::write("input.vti", data));
});
