//! One DICOM file through the public loader (`load` of a `.dcm`). Findings here are reported,
//! not fixed in this crate's harness: dicom.rs has its own owner.

#![no_main]

#[path = "common.rs"]
mod common;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    common::load_and_check(&common::write("input.dcm", data));
});
