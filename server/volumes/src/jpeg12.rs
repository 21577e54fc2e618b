//! 12-bit lossy JPEG (ISO 10918-1 extended sequential, process 4; DICOM JPEG Extended with
//! 12 bits stored), which jpeg-decoder, dicom-rs's JPEG codec, cannot decode: libjpeg-turbo 3's
//! TurboJPEG API (`tj3Decompress12`), built from source by `turbojpeg-sys` and linked
//! statically.
//!
//! One grayscale frame in, its samples out. The stream's size, precision and colour space are
//! checked against what the DICOM header declares before anything is decoded into the caller's
//! buffer, and libjpeg-turbo's warnings (corrupt or truncated entropy-coded data, which it would
//! otherwise fill in with grey) are errors.

use std::ffi::{CStr, c_void};
use std::ptr::NonNull;

use turbojpeg_sys as tj;

/// Most scans accepted in one stream. Progressive streams (not part of this transfer syntax, but
/// libjpeg-turbo would read them) can hold thousands of tiny scans that each cost a pass over the
/// image; libjpeg-turbo's documentation advises a limit for untrusted input.
const MAX_SCANS: i32 = 500;

/// A TurboJPEG decompressor instance (`tjhandle`, an opaque pointer), destroyed on drop.
struct Decompressor(NonNull<c_void>);

impl Decompressor {
    fn new() -> Result<Self, String> {
        // SAFETY: tj3Init takes no pointers; it returns a new instance or null.
        let handle = unsafe { tj::tj3Init(tj::TJINIT_TJINIT_DECOMPRESS as i32) };
        NonNull::new(handle)
            .map(Decompressor)
            .ok_or_else(|| "libjpeg-turbo could not create a decompressor".to_string())
    }

    fn handle(&self) -> tj::tjhandle {
        self.0.as_ptr()
    }

    /// The instance's last error message.
    fn error(&self) -> String {
        // SAFETY: the handle is live; tj3GetErrorStr returns a NUL-terminated string owned by
        // the instance (valid until its next call), copied out here at once.
        let msg = unsafe { CStr::from_ptr(tj::tj3GetErrorStr(self.handle())) };
        msg.to_string_lossy().trim().to_string()
    }

    fn set(&self, param: tj::TJPARAM, value: i32) -> Result<(), String> {
        // SAFETY: the handle is live; tj3Set takes plain integers.
        if unsafe { tj::tj3Set(self.handle(), param as i32, value) } == 0 {
            Ok(())
        } else {
            Err(self.error())
        }
    }

    fn get(&self, param: tj::TJPARAM) -> i32 {
        // SAFETY: the handle is live; tj3Get takes plain integers (-1 for an unknown value).
        unsafe { tj::tj3Get(self.handle(), param as i32) }
    }
}

impl Drop for Decompressor {
    fn drop(&mut self) {
        // SAFETY: the handle came from tj3Init and is destroyed exactly once, here.
        unsafe { tj::tj3Destroy(self.handle()) }
    }
}

/// Decodes one 12-bit (9 to 12 bits of precision) grayscale JPEG stream of `cols` × `rows`
/// samples into a row-major buffer of `cols * rows` samples (0..=4095 for 12 bits).
/// `Ok(None)` means the stream has 8-bit samples, for an 8-bit decoder. Any mismatch with the
/// declared size, another precision, more than one component, a damaged stream or a
/// libjpeg-turbo warning is an `Err` with a message for the caller to wrap.
pub(crate) fn decode_gray12(
    stream: &[u8],
    cols: u32,
    rows: u32,
) -> Result<Option<Vec<i16>>, String> {
    let d = Decompressor::new()?;
    let size = tj::size_t::try_from(stream.len())
        .map_err(|_| format!("JPEG stream of {} bytes is too large", stream.len()))?;
    // SAFETY: the handle is live and `stream` is a valid slice of `size` bytes that libjpeg-turbo
    // only reads during this call.
    if unsafe { tj::tj3DecompressHeader(d.handle(), stream.as_ptr(), size) } != 0 {
        return Err(format!(
            "libjpeg-turbo cannot read the JPEG header: {}",
            d.error()
        ));
    }
    let width = d.get(tj::TJPARAM_TJPARAM_JPEGWIDTH);
    let height = d.get(tj::TJPARAM_TJPARAM_JPEGHEIGHT);
    if width <= 0 || height <= 0 {
        return Err("the JPEG stream holds no image (no frame header)".to_string());
    }
    // An 8-bit stream is left whole to the caller's 8-bit decoder, checks included.
    let precision = d.get(tj::TJPARAM_TJPARAM_PRECISION);
    if precision == 8 {
        return Ok(None);
    }
    if u32::try_from(width) != Ok(cols) || u32::try_from(height) != Ok(rows) {
        return Err(format!(
            "the JPEG stream is {width} × {height} samples; Columns × Rows is {cols} × {rows}"
        ));
    }
    if !(9..=12).contains(&precision) {
        return Err(format!(
            "the JPEG stream has {precision}-bit samples; lossy JPEG has 8 or 12 (9 to 12 \
             read here)"
        ));
    }
    if d.get(tj::TJPARAM_TJPARAM_COLORSPACE) != tj::TJCS_TJCS_GRAY as i32 {
        return Err("the JPEG stream is not single-component grayscale".to_string());
    }
    // Warnings (corrupt entropy-coded data, a premature end) stop the decoder instead of being
    // filled in with grey.
    d.set(tj::TJPARAM_TJPARAM_STOPONWARNING, 1)?;
    d.set(tj::TJPARAM_TJPARAM_SCANLIMIT, MAX_SCANS)?;
    let (w, h) = (cols as usize, rows as usize);
    let n = w
        .checked_mul(h)
        .ok_or_else(|| format!("{cols} × {rows} samples overflow"))?;
    let mut out = vec![0i16; n];
    // SAFETY: the handle is live and has read this stream's header, which declared
    // `width` × `height` = `w` × `h` one-component samples (checked above, as are the precision
    // and colour space tj3Decompress12 needs). `out` holds exactly `w * h` i16 samples, so the
    // destination of pitch `width` (samples per row, TJPF_GRAY: one sample per pixel) and
    // `height` rows fits it; libjpeg-turbo reads `stream` and writes `out` only during the call.
    let rc = unsafe {
        tj::tj3Decompress12(
            d.handle(),
            stream.as_ptr(),
            size,
            out.as_mut_ptr(),
            width,
            tj::TJPF_TJPF_GRAY,
        )
    };
    if rc != 0 {
        return Err(format!("libjpeg-turbo: {}", d.error()));
    }
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_and_empty_streams_are_errors() {
        assert!(decode_gray12(&[], 8, 8).is_err());
        // SOI, EOI: a "tables only" stream without an image.
        let e = decode_gray12(&[0xFF, 0xD8, 0xFF, 0xD9], 8, 8).unwrap_err();
        assert!(e.contains("no image"), "{e}");
        let e = decode_gray12(b"not a JPEG stream at all", 8, 8).unwrap_err();
        assert!(e.contains("header"), "{e}");
    }
}
