//! Image statistics that the engine's tests and the benchmarks share (one copy each):
//!
//! - `luminance`: Rec. 709 luminance of linear RGB.
//! - `mean`, `relative_rms`: over all three channels; `relative_rms_luminance` over luminance.
//! - `median` of measured times.

/// Rec. 709 luminance of a linear RGB value.
pub fn luminance(c: [f32; 3]) -> f64 {
    0.2126 * c[0] as f64 + 0.7152 * c[1] as f64 + 0.0722 * c[2] as f64
}

/// Mean over all pixels and channels (0 for no pixels).
pub fn mean(image: &[[f32; 3]]) -> f64 {
    let n = 3 * image.len();
    if n == 0 {
        return 0.0;
    }
    image.iter().flatten().map(|&v| v as f64).sum::<f64>() / n as f64
}

/// Relative RMS error over all pixels and channels: the RMS of the difference over the
/// reference's mean (a reference mean of 0 counts as 1e-12).
pub fn relative_rms(image: &[[f32; 3]], reference: &[[f32; 3]]) -> f64 {
    let n = (3 * reference.len()).max(1) as f64;
    let sq: f64 = image
        .iter()
        .flatten()
        .zip(reference.iter().flatten())
        .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
        .sum();
    (sq / n).sqrt() / mean(reference).max(1e-12)
}

/// Relative RMS error of the pixels' luminance: the RMS of the difference over the reference's
/// mean luminance.
pub fn relative_rms_luminance(image: &[[f32; 3]], reference: &[[f32; 3]]) -> f64 {
    let n = reference.len().max(1) as f64;
    let (mut sq, mut sum) = (0.0, 0.0);
    for (a, b) in image.iter().zip(reference) {
        sq += (luminance(*a) - luminance(*b)).powi(2);
        sum += luminance(*b);
    }
    (sq / n).sqrt() / (sum / n).max(1e-12)
}

/// The median (the mean of the middle two for an even count); NaN for none.
pub fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => 0.5 * (values[n / 2 - 1] + values[n / 2]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        assert!((luminance([1.0, 1.0, 1.0]) - 1.0).abs() < 1e-12);
        assert_eq!(mean(&[[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]]), 2.0);
        let reference = [[1.0f32; 3]; 4];
        let image = [[1.1f32; 3]; 4];
        assert!((relative_rms(&image, &reference) - 0.1).abs() < 1e-6);
        assert!((relative_rms_luminance(&image, &reference) - 0.1).abs() < 1e-6);
        assert_eq!(relative_rms(&reference, &reference), 0.0);
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(Vec::new()).is_nan());
    }
}
