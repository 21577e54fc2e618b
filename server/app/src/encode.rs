//! Frame encoding (JPEG while the picture changes, PNG once converged). CPU-bound: call from
//! `spawn_blocking`, never on the async runtime.

#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("JPEG encoding failed: {0}")]
    Jpeg(String),
    #[error("PNG encoding failed: {0}")]
    Png(String),
    #[error("image is {width}×{height} but has {len} bytes of RGBA")]
    Size { width: u32, height: u32, len: usize },
}

fn check(rgba: &[u8], width: u32, height: u32) -> Result<(), EncodeError> {
    if rgba.len() != width as usize * height as usize * 4
        || width > u16::MAX as u32
        || height > u16::MAX as u32
    {
        return Err(EncodeError::Size {
            width,
            height,
            len: rgba.len(),
        });
    }
    Ok(())
}

/// Baseline JPEG, 4:2:0 for quality below 90 (smaller), 4:4:4 above.
pub fn jpeg(rgba: &[u8], width: u32, height: u32, quality: u8) -> Result<Vec<u8>, EncodeError> {
    check(rgba, width, height)?;
    let mut out = Vec::with_capacity(rgba.len() / 8);
    let mut encoder = jpeg_encoder::Encoder::new(&mut out, quality.clamp(1, 100));
    encoder.set_sampling_factor(if quality >= 90 {
        jpeg_encoder::SamplingFactor::R_4_4_4
    } else {
        jpeg_encoder::SamplingFactor::R_4_2_0
    });
    encoder
        .encode(
            rgba,
            width as u16,
            height as u16,
            jpeg_encoder::ColorType::Rgba,
        )
        .map_err(|e| EncodeError::Jpeg(e.to_string()))?;
    Ok(out)
}

/// Lossless RGB PNG (alpha is always opaque, so it is dropped).
pub fn png(rgba: &[u8], width: u32, height: u32) -> Result<Vec<u8>, EncodeError> {
    check(rgba, width, height)?;
    let rgb: Vec<u8> = rgba
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder
        .write_header()
        .map_err(|e| EncodeError::Png(e.to_string()))?;
    writer
        .write_image_data(&rgb)
        .map_err(|e| EncodeError::Png(e.to_string()))?;
    writer
        .finish()
        .map_err(|e| EncodeError::Png(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodes_and_rejects_wrong_sizes() {
        let rgba: Vec<u8> = (0..16 * 8 * 4).map(|i| (i % 251) as u8).collect();
        let j = jpeg(&rgba, 16, 8, 80).unwrap();
        assert_eq!(&j[..2], &[0xFF, 0xD8]);
        let p = png(&rgba, 16, 8).unwrap();
        assert_eq!(&p[1..4], b"PNG");
        assert!(jpeg(&rgba, 17, 8, 80).is_err());
        assert!(png(&rgba[..10], 16, 8).is_err());
    }
}
