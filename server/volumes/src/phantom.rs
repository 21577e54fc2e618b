//! Procedural test volumes ("phantoms"). Values are already normalized: value range [0, 1],
//! no units, spacing 1.

use crate::VolumeError;
use crate::volume::{Volume, compute_histogram};

/// Largest accepted phantom edge length.
pub const MAX_PHANTOM_SIZE: u32 = 1024;

/// Names accepted by [`phantom`] (without the `phantom:` prefix).
pub fn phantom_names() -> &'static [&'static str] {
    &["sphere", "cornell"]
}

/// Data value of each material in the `cornell` phantom, so that a transfer function can
/// colour them:
///
/// | material | value | suggested colour |
/// |---|---|---|
/// | `medium` (thin participating medium filling the interior) | 0.08 | faint grey |
/// | `left wall` (x = 0 side) | 0.2 | red |
/// | `right wall` (x = max side) | 0.4 | green |
/// | `white walls` (floor y = 0, ceiling y = max, back z = 0) | 0.6 | white |
/// | `tall block` (box rotated about y, standing on the floor) | 0.8 | white / any |
/// | `sphere` (ball on the floor, the object recoloured in Fig. 7 of the historygram paper) | 1.0 | any |
///
/// Empty space outside the box (the open front, z = max) is 0. Materials touch without
/// blending (nearest-voxel classification), so trilinear interpolation between, e.g., a
/// white wall (0.6) and the medium (0.08) passes through the red and green values over
/// less than one voxel.
pub const CORNELL_MATERIALS: &[(&str, f32)] = &[
    ("medium", 0.08),
    ("left wall", 0.2),
    ("right wall", 0.4),
    ("white walls", 0.6),
    ("tall block", 0.8),
    ("sphere", 1.0),
];

fn q(v: f32) -> u16 {
    (v.clamp(0.0, 1.0) * 65535.0).round() as u16
}

/// Generates a procedural phantom of `size`³ voxels (see [`phantom_names`]).
pub fn phantom(name: &str, size: u32) -> Result<Volume, VolumeError> {
    if size == 0 || size > MAX_PHANTOM_SIZE {
        return Err(VolumeError::InvalidArgument(format!(
            "phantom size {size}: expected 1..={MAX_PHANTOM_SIZE} voxels per edge"
        )));
    }
    let name = name.strip_prefix("phantom:").unwrap_or(name);
    let (data, what) = match name {
        "sphere" => (
            sphere(size),
            "homogeneous ball, radius 0.4, 4×4×4 supersampled edge",
        ),
        "cornell" => (
            cornell(size),
            "Cornell box: walls, tall block, sphere, thin medium",
        ),
        _ => {
            return Err(VolumeError::UnknownPhantom {
                name: name.to_string(),
                known: phantom_names().join(", "),
            });
        }
    };
    let histogram = compute_histogram(&data);
    Ok(Volume {
        name: format!("phantom:{name}"),
        dims: [size; 3],
        spacing: [1.0; 3],
        data,
        value_min: 0.0,
        value_max: 1.0,
        units: String::new(),
        modality: String::new(),
        format: format!("procedural phantom ({what})"),
        histogram,
        warnings: Vec::new(),
    })
}

/// Ball of radius 0.4·n centred in the box; boundary voxels hold their covered fraction
/// (4×4×4 supersampling).
fn sphere(n: u32) -> Vec<u16> {
    let nf = n as f64;
    let c = nf / 2.0;
    let r = 0.4 * nf;
    let r2 = r * r;
    let half_diag = 3f64.sqrt() / 2.0;
    let mut out = Vec::with_capacity((n as usize).pow(3));
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x as f64 + 0.5 - c, y as f64 + 0.5 - c, z as f64 + 0.5 - c];
                let d = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                let v = if d + half_diag <= r {
                    1.0
                } else if d - half_diag >= r {
                    0.0
                } else {
                    let mut inside = 0u32;
                    for k in 0..4 {
                        for j in 0..4 {
                            for i in 0..4 {
                                let sx = x as f64 + (i as f64 + 0.5) / 4.0 - c;
                                let sy = y as f64 + (j as f64 + 0.5) / 4.0 - c;
                                let sz = z as f64 + (k as f64 + 0.5) / 4.0 - c;
                                if sx * sx + sy * sy + sz * sz <= r2 {
                                    inside += 1;
                                }
                            }
                        }
                    }
                    inside as f32 / 64.0
                };
                out.push(q(v));
            }
        }
    }
    out
}

fn material(name: &str) -> f32 {
    CORNELL_MATERIALS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, v)| *v)
        .unwrap_or(0.0)
}

/// Cornell box in world orientation (DESIGN.md): +z up, open towards −y, where the default
/// camera looks from. Below, u runs along x (left → right), v is up (z) and w runs from the
/// back wall (w = 0, y = +1) towards the open side (w = 1, y = 0); units of the box edge.
fn cornell(n: u32) -> Vec<u16> {
    let nf = n as f32;
    let wall = (0.06 * nf).round().max(1.0) / nf;
    let (medium, left, right, white, block, ball) = (
        q(material("medium")),
        q(material("left wall")),
        q(material("right wall")),
        q(material("white walls")),
        q(material("tall block")),
        q(material("sphere")),
    );
    // Tall block: 0.26 × 0.55 × 0.26, rotated ~17° about y, standing on the floor at the back left.
    let (bcx, bcz, bhw, bh) = (0.36f32, 0.38f32, 0.13f32, 0.55f32);
    let (sin_a, cos_a) = 0.3f32.sin_cos();
    // Sphere resting on the floor, front right.
    let (scx, scz, sr) = (0.66f32, 0.62f32, 0.17f32);
    let scy = wall + sr;
    let mut out = Vec::with_capacity((n as usize).pow(3));
    for z in 0..n {
        let v = (z as f32 + 0.5) / nf;
        for y in 0..n {
            let w = 1.0 - (y as f32 + 0.5) / nf;
            for x in 0..n {
                let u = (x as f32 + 0.5) / nf;
                let val = if u < wall {
                    left
                } else if u > 1.0 - wall {
                    right
                } else if v < wall || v > 1.0 - wall || w < wall {
                    white
                } else {
                    let (dx, dz) = (u - bcx, w - bcz);
                    let (lx, lz) = (dx * cos_a - dz * sin_a, dx * sin_a + dz * cos_a);
                    let (sx, sy, sz) = (u - scx, v - scy, w - scz);
                    if lx.abs() <= bhw && lz.abs() <= bhw && v <= wall + bh {
                        block
                    } else if sx * sx + sy * sy + sz * sz <= sr * sr {
                        ball
                    } else {
                        medium
                    }
                };
                out.push(val);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_phantom() {
        let v = phantom("sphere", 64).unwrap();
        assert_eq!(v.dims, [64, 64, 64]);
        assert_eq!(v.normalized(32, 32, 32), 1.0);
        assert_eq!(v.normalized(0, 0, 0), 0.0);
        assert_eq!(v.normalized(63, 63, 63), 0.0);
        let frac: f64 =
            v.data.iter().map(|&q| q as f64 / 65535.0).sum::<f64>() / v.voxel_count() as f64;
        let expected = 4.0 / 3.0 * std::f64::consts::PI * 0.4f64.powi(3);
        assert!(
            (frac / expected - 1.0).abs() < 0.02,
            "fraction {frac} vs {expected}"
        );
        // Anti-aliased: some voxels are strictly between 0 and 1.
        assert!(v.data.iter().any(|&q| q > 0 && q < 65535));
        assert_eq!(
            v.histogram.iter().map(|&h| h as usize).sum::<usize>(),
            v.voxel_count()
        );
        assert_eq!(v.value_min, 0.0);
        assert_eq!(v.value_max, 1.0);
        assert_eq!(v.name, "phantom:sphere");
    }

    #[test]
    fn cornell_phantom() {
        let n = 64;
        let v = phantom("cornell", n).unwrap();
        let at = |x: u32, y: u32, z: u32| v.normalized(x, y, z);
        let near = |a: f32, b: f32| (a - b).abs() < 1e-4;
        // x left → right, z up, the open side towards −y (y = 0).
        assert!(near(at(0, 32, 32), 0.2), "left wall");
        assert!(near(at(n - 1, 32, 32), 0.4), "right wall");
        assert!(near(at(32, 32, 0), 0.6), "floor");
        assert!(near(at(32, 32, n - 1), 0.6), "ceiling");
        assert!(near(at(32, n - 1, 32), 0.6), "back wall");
        assert!(near(at(32, 0, 32), 0.08), "open front: medium, no wall");
        assert!(near(at(10, 3, 50), 0.08), "medium");
        // Sphere centre and tall block centre (w measured from the back wall).
        let from_back = |w: f32| n - 1 - (w * 64.0) as u32;
        let sz = ((0.17 + 4.0 / 64.0) * 64.0) as u32;
        assert!(
            near(at((0.66 * 64.0) as u32, from_back(0.62), sz), 1.0),
            "sphere"
        );
        assert!(
            near(at((0.36 * 64.0) as u32, from_back(0.38), 20), 0.8),
            "block"
        );
        // Every material is present.
        for (name, val) in CORNELL_MATERIALS {
            assert!(
                v.data.iter().any(|&q| near(q as f32 / 65535.0, *val)),
                "{name} missing"
            );
        }
    }

    #[test]
    fn phantom_errors() {
        assert!(matches!(
            phantom("nope", 8),
            Err(VolumeError::UnknownPhantom { .. })
        ));
        assert!(phantom("sphere", 0).is_err());
        assert!(phantom("sphere", 100_000).is_err());
        assert!(phantom("phantom:sphere", 4).is_ok());
        assert_eq!(phantom_names(), &["sphere", "cornell"]);
    }
}
