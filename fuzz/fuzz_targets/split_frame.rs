//! Binary frame messages as a client splits them: 4-byte length, JSON metadata, image.

#![no_main]

use libfuzzer_sys::fuzz_target;
use voxlight_protocol::split_frame;

fuzz_target!(|data: &[u8]| {
    if let Some((meta, image)) = split_frame(data) {
        let len = u32::from_le_bytes([data[0], data[1], data[2], data[3]]) as usize;
        assert_eq!(image.len(), data.len() - 4 - len);
        // Metadata the server wrote (finite numbers) goes through a join and a split unchanged.
        let finite = [meta.resolution_scale, meta.render_ms, meta.encode_ms]
            .iter()
            .all(|x| x.is_finite());
        if finite && meta.preview_match.is_none() && meta.details == Default::default() {
            let joined = voxlight_protocol::join_frame(&meta, image);
            let (again, image_again) = split_frame(&joined).expect("a joined frame splits");
            assert_eq!(again, meta);
            assert_eq!(image_again, image);
        }
    }
});
