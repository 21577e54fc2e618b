//! Transfer functions: validation, baking into the GPU lookup table, and the query
//! historygram of an edit (which data-value bins changed their optical properties).

use voxlight_protocol::{MAX_TF_POINTS, TfPoint, TransferFunction};

/// Entries of the baked lookup table (`TF_LUT_SIZE` in shared/volume.wgsl).
pub const TF_LUT_SIZE: usize = 1024;

/// Data-value bins of a historygram (p = 64 in the historygram paper).
pub const HISTOGRAM_BINS: usize = 64;

/// Checks a transfer function from a client.
pub fn validate(tf: &TransferFunction) -> Result<(), String> {
    if tf.points.len() > MAX_TF_POINTS {
        return Err(format!(
            "a transfer function has at most {MAX_TF_POINTS} points, got {}",
            tf.points.len()
        ));
    }
    for (i, p) in tf.points.iter().enumerate() {
        let in_unit = |x: f32| x.is_finite() && (0.0..=1.0).contains(&x);
        if !in_unit(p.value) {
            return Err(format!(
                "tf point {i}: value must be in [0, 1], got {}",
                p.value
            ));
        }
        if !in_unit(p.opacity) {
            return Err(format!(
                "tf point {i}: opacity must be in [0, 1], got {}",
                p.opacity
            ));
        }
        if !p.color.iter().all(|&c| in_unit(c)) {
            return Err(format!(
                "tf point {i}: color components must be in [0, 1], got {:?}",
                p.color
            ));
        }
    }
    Ok(())
}

/// Evaluates the piecewise-linear TF at v: (albedo rgb, opacity). Constant beyond the first
/// and last point; fully transparent with no points.
pub fn evaluate(points: &[TfPoint], v: f32) -> [f32; 4] {
    let mut sorted: Vec<&TfPoint> = points.iter().collect();
    sorted.sort_by(|a, b| a.value.total_cmp(&b.value));
    evaluate_sorted(&sorted, v)
}

fn evaluate_sorted(sorted: &[&TfPoint], v: f32) -> [f32; 4] {
    let rgba = |p: &TfPoint| [p.color[0], p.color[1], p.color[2], p.opacity];
    let (Some(first), Some(last)) = (sorted.first(), sorted.last()) else {
        return [0.0; 4];
    };
    if v <= first.value {
        return rgba(first);
    }
    if v >= last.value {
        return rgba(last);
    }
    let upper = sorted.partition_point(|p| p.value <= v);
    let (a, b) = (sorted[upper - 1], sorted[upper]);
    let span = b.value - a.value;
    let f = if span > 0.0 {
        (v - a.value) / span
    } else {
        1.0
    };
    let (ca, cb) = (rgba(a), rgba(b));
    std::array::from_fn(|k| ca[k] + (cb[k] - ca[k]) * f)
}

/// The TF sampled at `TF_LUT_SIZE` evenly spaced values in [0, 1].
pub fn bake(tf: &TransferFunction) -> Vec<[f32; 4]> {
    let mut sorted: Vec<&TfPoint> = tf.points.iter().collect();
    sorted.sort_by(|a, b| a.value.total_cmp(&b.value));
    (0..TF_LUT_SIZE)
        .map(|i| evaluate_sorted(&sorted, i as f32 / (TF_LUT_SIZE - 1) as f32))
        .collect()
}

/// What the shaders' `classify` returns for v: linear between the two nearest LUT entries.
pub fn classify(lut: &[[f32; 4]], v: f32) -> [f32; 4] {
    let x = v.clamp(0.0, 1.0) * (TF_LUT_SIZE - 1) as f32;
    let i = (x as usize).min(TF_LUT_SIZE - 2);
    let f = x - i as f32;
    std::array::from_fn(|k| lut[i][k] + (lut[i + 1][k] - lut[i][k]) * f)
}

/// Bin of data value v: floor(v·(p−1)) as in the historygram paper's d(x) (p = 64).
pub fn value_bin(v: f32) -> usize {
    ((v.clamp(0.0, 1.0) * (HISTOGRAM_BINS - 1) as f32) as usize).min(HISTOGRAM_BINS - 1)
}

/// Query historygram (paper 1, eq. 11): bit b is set when bin b's optical properties differ
/// between the two baked tables. Compares what the GPU actually uses, so an edit that leaves
/// every LUT entry unchanged yields 0.
pub fn query_historygram(old: &TransferFunction, new: &TransferFunction) -> u64 {
    changed_bins(old, new, |x, y| x != y)
}

/// The bins whose opacity (extinction) changed: what a quantity that depends on the TF only
/// through extinction, such as a view-ray segment's transmittance, needs to be recomputed for.
/// A subset of `query_historygram`.
pub fn opacity_query_historygram(old: &TransferFunction, new: &TransferFunction) -> u64 {
    changed_bins(old, new, |x, y| x[3] != y[3])
}

/// The bins whose opacity rose: where a rejected tentative collision of delta tracking may
/// become a real one. With `collision_query_historygram`, a split of `query_historygram`.
pub fn opacity_rise_historygram(old: &TransferFunction, new: &TransferFunction) -> u64 {
    changed_bins(old, new, |x, y| y[3] > x[3])
}

/// The bins whose colour changed or opacity fell: where a real collision may change its albedo
/// or be rejected. A rejected tentative collision there stays rejected and its colour is never
/// used, so a path that only passed through these bins is unaffected.
pub fn collision_query_historygram(old: &TransferFunction, new: &TransferFunction) -> u64 {
    changed_bins(old, new, |x, y| y[3] < x[3] || x[..3] != y[..3])
}

/// The bins where the shaders can find a non-zero opacity under `tf` (an entry they
/// interpolate at some value of the bin is not transparent): delta tracking collides only
/// there.
pub fn opaque_bins(tf: &TransferFunction) -> u64 {
    let transparent = TransferFunction { points: Vec::new() };
    changed_bins(&transparent, tf, |_, y| y[3] > 0.0)
}

/// Bins whose LUT entries `differ` between the two tables.
fn changed_bins(
    old: &TransferFunction,
    new: &TransferFunction,
    differ: impl Fn(&[f32; 4], &[f32; 4]) -> bool,
) -> u64 {
    let (a, b) = (bake(old), bake(new));
    let mut mask = 0u64;
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        if differ(x, y) {
            // The shader interpolates between entries i and i + 1, so entry i influences the
            // values from (i − 1)/(N − 1) to (i + 1)/(N − 1).
            let lo = (i.saturating_sub(1)) as f32 / (TF_LUT_SIZE - 1) as f32;
            let hi = ((i + 1).min(TF_LUT_SIZE - 1)) as f32 / (TF_LUT_SIZE - 1) as f32;
            for bin in value_bin(lo)..=value_bin(hi) {
                mask |= 1 << bin;
            }
        }
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(value: f32, color: [f32; 3], opacity: f32) -> TfPoint {
        TfPoint {
            value,
            color,
            opacity,
        }
    }

    #[test]
    fn opaque_bins_are_those_an_opaque_entry_reaches() {
        let tf = TransferFunction {
            points: vec![
                point(0.0, [1.0; 3], 0.0),
                point(0.5, [1.0; 3], 0.0),
                point(0.75, [1.0; 3], 1.0),
                point(1.0, [1.0; 3], 1.0),
            ],
        };
        let bins = opaque_bins(&tf);
        // Entries above 0.5 are opaque; the shaders interpolate the last transparent entry
        // with the first opaque one, so the bin of 0.5 counts and those well below do not.
        assert_ne!(bins & (1 << value_bin(0.5)), 0);
        assert_ne!(bins & (1 << value_bin(0.9)), 0);
        assert_eq!(bins & ((1 << value_bin(0.45)) | 1), 0);
        assert_eq!(opaque_bins(&TransferFunction { points: Vec::new() }), 0);
    }

    #[test]
    fn piecewise_linear_and_constant_beyond_ends() {
        let pts = [
            point(0.75, [0.0, 1.0, 0.0], 1.0),
            point(0.25, [1.0, 0.0, 0.0], 0.0),
        ];
        assert_eq!(evaluate(&pts, 0.0), [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(evaluate(&pts, 1.0), [0.0, 1.0, 0.0, 1.0]);
        let mid = evaluate(&pts, 0.5);
        assert!((mid[3] - 0.5).abs() < 1e-6 && (mid[0] - 0.5).abs() < 1e-6);
        assert_eq!(evaluate(&[], 0.3), [0.0; 4]);
    }

    #[test]
    fn lut_matches_evaluate_at_entries() {
        let tf = TransferFunction {
            points: vec![
                point(0.1, [0.2, 0.3, 0.4], 0.0),
                point(0.9, [1.0, 1.0, 1.0], 0.8),
            ],
        };
        let lut = bake(&tf);
        assert_eq!(lut.len(), TF_LUT_SIZE);
        for i in [0, 100, 511, 1023] {
            let v = i as f32 / (TF_LUT_SIZE - 1) as f32;
            assert_eq!(lut[i], evaluate(&tf.points, v));
        }
    }

    #[test]
    fn rise_and_collision_queries_split_the_query() {
        let base = TransferFunction {
            points: vec![
                point(0.0, [1.0; 3], 0.0),
                point(0.3, [1.0; 3], 0.0),
                point(0.4, [1.0; 3], 0.5),
                point(0.6, [1.0; 3], 0.5),
                point(0.7, [1.0; 3], 0.0),
                point(1.0, [1.0; 3], 0.0),
            ],
        };
        let edit = |f: &dyn Fn(&mut TfPoint)| {
            let mut tf = base.clone();
            tf.points[2..4].iter_mut().for_each(f);
            tf
        };
        let recoloured = edit(&|p| p.color = [0.2, 0.4, 0.9]);
        let fainter = edit(&|p| p.opacity = 0.1);
        let denser = edit(&|p| p.opacity = 0.9);
        for (name, tf, rises, collides) in [
            ("colour", &recoloured, false, true),
            ("fainter", &fainter, false, true),
            ("denser", &denser, true, false),
        ] {
            let all = query_historygram(&base, tf);
            let rise = opacity_rise_historygram(&base, tf);
            let collision = collision_query_historygram(&base, tf);
            assert_ne!(all, 0, "{name}");
            assert_eq!(rise | collision, all, "{name}: the split covers the query");
            assert_eq!(rise != 0, rises, "{name}: {rise:064b}");
            assert_eq!(collision != 0, collides, "{name}: {collision:064b}");
        }
    }

    #[test]
    fn query_historygram_marks_only_changed_bins() {
        let base = TransferFunction {
            points: vec![
                point(0.0, [1.0; 3], 0.0),
                point(0.5, [1.0; 3], 0.0),
                point(0.6, [1.0; 3], 1.0),
                point(1.0, [1.0; 3], 1.0),
            ],
        };
        assert_eq!(query_historygram(&base, &base), 0);
        let mut recoloured = base.clone();
        recoloured.points[2].color = [1.0, 0.0, 0.0];
        recoloured.points[3].color = [1.0, 0.0, 0.0];
        let mask = query_historygram(&base, &recoloured);
        assert_ne!(mask, 0);
        assert_eq!(
            opacity_query_historygram(&base, &recoloured),
            0,
            "colour only"
        );
        assert_eq!(mask & 1, 0, "bin 0 (v < 1/63) did not change");
        assert_ne!(mask & (1 << 63), 0, "v = 1 changed");
        assert!(
            mask.count_ones() < 40,
            "only the upper half changed: {mask:064b}"
        );
    }

    #[test]
    fn validation_rejects_out_of_range() {
        assert!(
            validate(&TransferFunction {
                points: vec![point(1.5, [0.0; 3], 0.0)]
            })
            .is_err()
        );
        assert!(
            validate(&TransferFunction {
                points: vec![point(0.5, [0.0; 3], f32::NAN)]
            })
            .is_err()
        );
        assert!(
            validate(&TransferFunction {
                points: vec![point(0.5, [2.0, 0.0, 0.0], 0.5)]
            })
            .is_err()
        );
        assert!(
            validate(&TransferFunction {
                points: vec![point(0.5, [0.1; 3], 0.5)]
            })
            .is_ok()
        );
    }
}
