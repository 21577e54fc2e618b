//! `Frame`: a tone-mapped picture read back from the GPU, as the renderer and the preview hand
//! it to the server.

use crate::brightness::BrightnessMatch;

/// A tone-mapped picture read back from the GPU.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Row-major RGBA8, row 0 at the top, sRGB.
    pub rgba: Vec<u8>,
    pub iteration: u32,
    pub target_iterations: u32,
    pub converged: bool,
    /// Resolution divisor per axis: 1 for the full viewport, 2, 4 or 8 for a reduced preview.
    pub divisor: u32,
    /// An interactive preview (passes::preview), not the technique's estimate.
    pub preview: bool,
    /// A preview's brightness match (`preview::BrightnessMatch`).
    pub preview_match: Option<BrightnessMatch>,
}
