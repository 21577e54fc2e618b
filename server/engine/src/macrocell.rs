//! Macrocells: the range of data values each 8³ block's trilinear samples can take, and from a
//! TF the largest opacity that range can classify to.
//!
//! - Empty-space skipping: a cell whose largest opacity is exactly zero contributes nothing and
//!   is skipped without changing any estimate.
//! - Majorants: delta tracking (`pathtrace`, `irradiance`; `manylight` in dense media) samples
//!   free flights against each cell's `density_scale · largest opacity`.
//! - Historygram bins (`bin_masks`): what a quantity that read a cell can depend on.

use voxlight_volumes::Volume;

use crate::tf::{TF_LUT_SIZE, value_bin};

/// Edge of a macrocell in voxels (`CELL_VOXELS` in the shaders' uniforms).
pub const CELL: u32 = 8;

/// Per-macrocell min and max of the normalized data (as stored, 0..=65535) over every voxel a
/// trilinear sample inside the cell can touch.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeGrid {
    pub dims: [u32; 3],
    pub min: Vec<u16>,
    pub max: Vec<u16>,
}

impl RangeGrid {
    pub fn build(volume: &Volume) -> Self {
        let n = volume.dims.map(|d| d as usize);
        let cells = volume.dims.map(|d| d.div_ceil(CELL));
        let c = cells.map(|d| d as usize);
        let count = c[0] * c[1] * c[2];
        // Exact range per block first ...
        let mut block_min = vec![u16::MAX; count];
        let mut block_max = vec![0u16; count];
        for z in 0..n[2] {
            let cz = z / CELL as usize;
            for y in 0..n[1] {
                let cy = y / CELL as usize;
                let row = &volume.data[(z * n[1] + y) * n[0]..(z * n[1] + y + 1) * n[0]];
                for (cx, chunk) in row.chunks(CELL as usize).enumerate() {
                    let cell = (cz * c[1] + cy) * c[0] + cx;
                    for &q in chunk {
                        block_min[cell] = block_min[cell].min(q);
                        block_max[cell] = block_max[cell].max(q);
                    }
                }
            }
        }
        // ... then widened by the neighbours: trilinear samples near a cell's faces read one
        // voxel of the next block.
        let mut min = vec![u16::MAX; count];
        let mut max = vec![0u16; count];
        for z in 0..c[2] {
            for y in 0..c[1] {
                for x in 0..c[0] {
                    let cell = (z * c[1] + y) * c[0] + x;
                    for nz in z.saturating_sub(1)..(z + 2).min(c[2]) {
                        for ny in y.saturating_sub(1)..(y + 2).min(c[1]) {
                            for nx in x.saturating_sub(1)..(x + 2).min(c[0]) {
                                let other = (nz * c[1] + ny) * c[0] + nx;
                                min[cell] = min[cell].min(block_min[other]);
                                max[cell] = max[cell].max(block_max[other]);
                            }
                        }
                    }
                }
            }
        }
        Self {
            dims: cells,
            min,
            max,
        }
    }

    pub fn cell_count(&self) -> usize {
        self.min.len()
    }

    /// Largest opacity the baked TF `lut` gives any value in each cell's range.
    pub fn max_opacity(&self, lut: &[[f32; 4]]) -> Vec<f32> {
        let range_max = RangeMax::new(lut.iter().map(|e| e[3]).collect());
        self.lut_ranges()
            .map(|(first, end)| range_max.query(first, end))
            .collect()
    }

    /// Per cell, the first and last LUT entries any value in its range reads: the shader
    /// interpolates entries i and i + 1 around v·(N − 1); one more entry on each side covers
    /// rounding of v.
    fn lut_ranges(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        let last = (TF_LUT_SIZE - 1) as f32;
        self.min.iter().zip(&self.max).map(move |(&lo, &hi)| {
            let first = ((lo as f32 / 65535.0 * last) as usize).saturating_sub(1);
            let end = ((hi as f32 / 65535.0 * last) as usize + 2).min(TF_LUT_SIZE - 1);
            (first, end)
        })
    }

    /// Per cell, the historygram bins (as `tf::query_historygram` numbers them) of every LUT
    /// entry its largest opacity reads: a quantity that depended on a cell's majorant, or on
    /// any sample in it, can only change under a TF edit whose query meets these bins.
    pub fn bin_masks(&self) -> Vec<u64> {
        let last = (TF_LUT_SIZE - 1) as f32;
        self.lut_ranges()
            .map(|(first, end)| {
                let (a, b) = (value_bin(first as f32 / last), value_bin(end as f32 / last));
                (a..=b).fold(0u64, |mask, bin| mask | 1 << bin)
            })
            .collect()
    }
}

/// Range-maximum queries over a small array (sparse table).
struct RangeMax {
    levels: Vec<Vec<f32>>,
}

impl RangeMax {
    fn new(values: Vec<f32>) -> Self {
        let mut levels = vec![values];
        let mut width = 1;
        while width * 2 <= levels[0].len() {
            let prev = &levels[levels.len() - 1];
            let next: Vec<f32> = (0..prev.len() - width)
                .map(|i| prev[i].max(prev[i + width]))
                .collect();
            levels.push(next);
            width *= 2;
        }
        Self { levels }
    }

    /// Max over indices first..=last.
    fn query(&self, first: usize, last: usize) -> f32 {
        let len = last - first + 1;
        let level = (usize::BITS - 1 - len.leading_zeros()) as usize;
        let width = 1 << level;
        self.levels[level][first].max(self.levels[level][last + 1 - width])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tf::{bake, classify};
    use voxlight_protocol::{TfPoint, TransferFunction};

    fn volume(dims: [u32; 3], f: impl Fn(u32, u32, u32) -> u16) -> Volume {
        let mut data = Vec::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    data.push(f(x, y, z));
                }
            }
        }
        Volume::from_normalized("test", dims, [1.0; 3], data).unwrap()
    }

    /// A white TF through (value, opacity) points.
    fn white_tf(points: &[(f32, f32)]) -> TransferFunction {
        let point = |&(value, opacity): &(f32, f32)| TfPoint {
            value,
            color: [1.0; 3],
            opacity,
        };
        TransferFunction {
            points: points.iter().map(point).collect(),
        }
    }

    #[test]
    fn range_max_matches_brute_force() {
        let values: Vec<f32> = (0..100).map(|i| ((i * 37) % 101) as f32).collect();
        let rm = RangeMax::new(values.clone());
        for first in 0..100 {
            for last in first..100 {
                let brute = values[first..=last]
                    .iter()
                    .copied()
                    .fold(f32::MIN, f32::max);
                assert_eq!(rm.query(first, last), brute);
            }
        }
    }

    /// Every trilinear sample inside a cell classifies to at most the cell's max opacity.
    #[test]
    fn max_opacity_bounds_every_sample() {
        let dims = [19, 12, 17];
        let vol = volume(dims, |x, y, z| {
            (((x * 7919 + y * 104729 + z * 1299709) % 997) * 65) as u16
        });
        let grid = RangeGrid::build(&vol);
        assert_eq!(grid.dims, [3, 2, 3]);
        let tf = white_tf(&[(0.30, 0.0), (0.32, 0.9), (0.34, 0.0)]);
        let lut = bake(&tf);
        let bound = grid.max_opacity(&lut);
        let mut state = 12345u64;
        for _ in 0..20000 {
            let mut u = [0f32; 3];
            for value in &mut u {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                *value = (state >> 40) as f32 / (1u64 << 24) as f32;
            }
            // Trilinear sample, as in shared/volume.wgsl.
            let mut i0 = [0u32; 3];
            let mut i1 = [0u32; 3];
            let mut f = [0f32; 3];
            for k in 0..3 {
                let p = u[k] * dims[k] as f32 - 0.5;
                f[k] = p - p.floor();
                i0[k] = (p.floor() as i64).clamp(0, dims[k] as i64 - 1) as u32;
                i1[k] = (p.floor() as i64 + 1).clamp(0, dims[k] as i64 - 1) as u32;
            }
            let at = |x, y, z| vol.normalized(x, y, z);
            let l = |a: f32, b: f32, t: f32| a + (b - a) * t;
            let v = l(
                l(
                    l(at(i0[0], i0[1], i0[2]), at(i1[0], i0[1], i0[2]), f[0]),
                    l(at(i0[0], i1[1], i0[2]), at(i1[0], i1[1], i0[2]), f[0]),
                    f[1],
                ),
                l(
                    l(at(i0[0], i0[1], i1[2]), at(i1[0], i0[1], i1[2]), f[0]),
                    l(at(i0[0], i1[1], i1[2]), at(i1[0], i1[1], i1[2]), f[0]),
                    f[1],
                ),
                f[2],
            );
            let cell: [usize; 3] = std::array::from_fn(|k| {
                ((u[k] * dims[k] as f32) as u32 / CELL).min(grid.dims[k] - 1) as usize
            });
            let index =
                (cell[2] * grid.dims[1] as usize + cell[1]) * grid.dims[0] as usize + cell[0];
            let opacity = classify(&lut, v)[3];
            assert!(
                opacity <= bound[index] + 1e-6,
                "sample opacity {opacity} above the cell bound {}",
                bound[index]
            );
        }
    }

    #[test]
    fn empty_regions_get_zero() {
        // Data only in one corner block; a TF transparent at 0.
        let vol = volume([32, 32, 32], |x, y, z| {
            if x < 4 && y < 4 && z < 4 { 65535 } else { 0 }
        });
        let grid = RangeGrid::build(&vol);
        let tf = white_tf(&[(0.5, 0.0), (1.0, 1.0)]);
        let bound = grid.max_opacity(&bake(&tf));
        assert_eq!(bound[0], 1.0);
        assert_eq!(bound[1], 1.0, "the neighbour reads into the corner block");
        assert_eq!(bound[2], 0.0);
        assert_eq!(bound.iter().filter(|&&b| b > 0.0).count(), 8);
    }
}
