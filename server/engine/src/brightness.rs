//! How bright an interactive preview is against the technique's refined picture: the preview's
//! measured means (`PreviewMeans`) and the per-channel match fitted to them
//! (`BrightnessMatch`), carried by every preview `Frame`.

/// Means over a preview image, per channel (linear radiance).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PreviewMeans {
    /// Single scattering toward the camera, before the brightness match's gain.
    pub single: [f64; 3],
    /// The approximate multiple scattering, before its weight (zero where not computed).
    pub multiple: [f64; 3],
    /// The environment seen through the volume (its radiance × the view ray's transmittance),
    /// which the preview and every technique agree on.
    pub background: [f64; 3],
}

/// The preview's brightness match to the session's technique (docs/architecture.md,
/// "Interaction mode"). The preview's single scattering is lit from a coarse light volume,
/// and a GI technique's still adds multiple scattering, so their means differed by a few
/// percent (raymarch) up to tens of percent (GI), which showed as a brightness step when input
/// stopped. The preview is `background + gain · single + multiple_weight · multiple`, where
/// `multiple` is an approximation of multiple scattering computed for GI techniques only
/// (preview/view.wgsl); `gain` or `multiple_weight` is fitted per channel so that a
/// full-resolution preview's mean meets the technique's refined picture of the same view and
/// scene, measured when the next edit arrives. The fit holds the scale; how the ratio moves
/// over one drag (view, TF) is what is left, and the picture's structure is not matched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BrightnessMatch {
    /// Gain on the single scattering.
    pub gain: [f32; 3],
    /// Weight of the approximate multiple scattering (zero without it).
    pub multiple_weight: [f32; 3],
    /// The technique scatters more than once: the preview computes `multiple`.
    pub multiple_scattering: bool,
}

impl BrightnessMatch {
    /// Range of the single-scattering gain (a measurement outside it is a broken one).
    pub const GAIN_RANGE: (f32, f32) = (0.25, 4.0);
    /// Largest multiple-scattering weight.
    pub const MAX_MULTIPLE_WEIGHT: f32 = 8.0;
    /// The multiple-scattering weight before a still was measured, about what the fit gives on
    /// the test scenes (docs/benchmarks.md).
    pub const PRIOR_MULTIPLE_WEIGHT: f32 = 0.4;
    /// A channel whose single scattering is below this share of the picture's mean keeps its
    /// match (there is nothing to match, and noise would set it).
    const MIN_SHARE: f64 = 1e-3;

    pub fn new(multiple_scattering: bool) -> Self {
        let weight = if multiple_scattering {
            Self::PRIOR_MULTIPLE_WEIGHT
        } else {
            0.0
        };
        Self {
            gain: [1.0; 3],
            multiple_weight: [weight; 3],
            multiple_scattering,
        }
    }

    /// Fits the match to a full-resolution preview's means and the technique's mean radiance
    /// over the same view and scene; returns whether any channel changed. A GI technique's
    /// light beyond the preview's single scattering goes to the multiple-scattering weight;
    /// otherwise (raymarch, or a still darker than the single scattering) the gain takes it.
    pub fn update(&mut self, preview: &PreviewMeans, technique: [f64; 3]) -> bool {
        let mut changed = false;
        for (c, &technique) in technique.iter().enumerate() {
            let single = preview.single[c];
            if !(single > 0.0 && single > Self::MIN_SHARE * (single + preview.background[c])) {
                continue;
            }
            let scattered = technique - preview.background[c];
            let multiple = preview.multiple[c];
            let weight = (scattered - single) / multiple;
            if self.multiple_scattering && multiple > Self::MIN_SHARE * single && weight >= 0.0 {
                self.gain[c] = 1.0;
                self.multiple_weight[c] = (weight as f32).min(Self::MAX_MULTIPLE_WEIGHT);
                changed = true;
                continue;
            }
            let gain = (scattered / single) as f32;
            if gain.is_finite() {
                self.gain[c] = gain.clamp(Self::GAIN_RANGE.0, Self::GAIN_RANGE.1);
                self.multiple_weight[c] = 0.0;
                changed = true;
            }
        }
        changed
    }
}

/// Mean of rgb pixels, per channel.
pub fn mean_rgb(pixels: &[[f32; 3]]) -> [f64; 3] {
    let mut sum = [0.0f64; 3];
    for p in pixels {
        for c in 0..3 {
            sum[c] += f64::from(p[c]);
        }
    }
    let n = pixels.len().max(1) as f64;
    sum.map(|s| s / n)
}
