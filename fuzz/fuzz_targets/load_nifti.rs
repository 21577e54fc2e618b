//! NIfTI-1: `.nii` (or `.nii.gz` when the input starts with the gzip magic), and `.hdr` with
//! a companion `.img` when the header says `ni1`.

#![no_main]

#[path = "common.rs"]
mod common;

use std::sync::Once;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    static COMPANION: Once = Once::new();
    COMPANION.call_once(|| {
        let img: Vec<u8> = (0..8192u32).map(|i| (i * 31 % 253) as u8).collect();
        common::write("pair.img", &img);
    });
    let name = if data.starts_with(&[0x1f, 0x8b]) {
        "input.nii.gz"
    } else if data.get(344..348) == Some(b"ni1\0") {
        "pair.hdr"
    } else {
        "input.nii"
    };
    common::load_and_check(&common::write(name, data));
});
