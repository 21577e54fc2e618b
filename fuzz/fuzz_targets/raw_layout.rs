//! How the `load_raw` fuzz target reads its input: the first 16 bytes choose the layout the
//! caller of `load_raw_file` passes (dims, sample type, byte order, spacing, header bytes), the
//! rest is the file. Shared with `tests/hostile_input.rs`, which replays the kept inputs.

use voxlight_volumes::{Endian, SampleType};

/// `load_raw_file`'s arguments besides the path.
pub struct RawLayout {
    pub dims: [u32; 3],
    pub sample: SampleType,
    pub endian: Endian,
    pub spacing: [f32; 3],
    pub header_bytes: u64,
}

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

/// The layout chosen by `data`'s first 16 bytes, and the file's bytes (None: too short).
pub fn raw_layout(data: &[u8]) -> Option<(RawLayout, &[u8])> {
    let (params, body) = data.split_first_chunk::<16>()?;
    let u16_at = |i: usize| u16::from_le_bytes([params[i], params[i + 1]]) as u32;
    // Any u32 is a legal argument; small values keep most runs about the data.
    let wide = params[15] & 0x80 != 0;
    let dim = |i: usize| {
        if wide {
            (u16_at(i) << 16) | u16_at(i)
        } else {
            u16_at(i)
        }
    };
    let layout = RawLayout {
        dims: [dim(0), dim(2), dim(4)],
        sample: TYPES[(params[6] & 7) as usize],
        endian: if params[6] & 8 == 0 {
            Endian::Little
        } else {
            Endian::Big
        },
        spacing: [
            f32::from_le_bytes([params[7], params[8], params[9], params[10]]),
            1.0,
            if params[15] & 1 == 0 { 1.0 } else { f32::NAN },
        ],
        // Mostly small; sometimes near u64::MAX (the loader must not overflow adding it).
        header_bytes: if params[15] & 2 == 0 {
            u16_at(11) as u64
        } else {
            u64::MAX - u16_at(11) as u64
        },
    };
    Some((layout, body))
}
