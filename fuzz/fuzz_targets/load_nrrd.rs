//! NRRD headers with attached or detached data. Detached headers can name `tooth.raw` (the
//! first 8 KiB of the real big-endian tooth volume) or `data.raw.gz` (gzip) beside them.

#![no_main]

#[path = "common.rs"]
mod common;

use std::sync::Once;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    static COMPANIONS: Once = Once::new();
    COMPANIONS.call_once(|| {
        common::write("tooth.raw", include_bytes!("../seeds/companions/tooth.raw"));
        common::write(
            "data.raw.gz",
            include_bytes!("../seeds/companions/data.raw.gz"),
        );
    });
    common::load_and_check(&common::write("input.nrrd", data));
});
