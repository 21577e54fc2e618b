//! The normalized [`Volume`], normalization, histograms and downsampling.

use std::fmt;

use crate::VolumeError;
use crate::raw::{Quantizer, RawVolume, Samples, ValueRange};

/// Number of histogram bins.
pub const HISTOGRAM_BINS: usize = 256;

/// A loaded volume, normalized to [0, 1]. Index (x, y, z), x fastest: `data[x + nx*(y + ny*z)]`.
#[derive(Clone)]
pub struct Volume {
    /// Dataset name (set by the caller or catalog; loaders use the file stem).
    pub name: String,
    /// Voxel counts along x, y, z.
    pub dims: [u32; 3],
    /// Physical voxel spacing (mm for medical data; 1.0 if unknown).
    pub spacing: [f32; 3],
    /// Normalized value `v = data / 65535.0`, where `v = (raw - value_min) / (value_max - value_min)`.
    pub data: Vec<u16>,
    /// Smallest original value (e.g. HU after rescale for CT).
    pub value_min: f64,
    /// Largest original value.
    pub value_max: f64,
    /// `"HU"` for CT, `""` if unknown.
    pub units: String,
    /// E.g. `"CT"`, `""` if unknown.
    pub modality: String,
    /// Human-readable source format.
    pub format: String,
    /// 256 bins over normalized v in [0, 1]; `bin = min(255, floor(v*256))`.
    pub histogram: Vec<u32>,
    /// Non-fatal problems (skipped files, etc.).
    pub warnings: Vec<String>,
}

impl fmt::Debug for Volume {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Volume")
            .field("name", &self.name)
            .field("dims", &self.dims)
            .field("spacing", &self.spacing)
            .field("data", &format_args!("[u16; {}]", self.data.len()))
            .field("value_min", &self.value_min)
            .field("value_max", &self.value_max)
            .field("units", &self.units)
            .field("modality", &self.modality)
            .field("format", &self.format)
            .field("warnings", &self.warnings)
            .finish()
    }
}

/// Histogram bin of a quantized normalized value: `min(255, floor(q/65535 * 256))`.
#[inline]
pub fn histogram_bin(q: u16) -> usize {
    ((q as usize * HISTOGRAM_BINS) / 65535).min(HISTOGRAM_BINS - 1)
}

/// 256-bin histogram of quantized normalized values.
pub fn compute_histogram(data: &[u16]) -> Vec<u32> {
    let mut h = vec![0u32; HISTOGRAM_BINS];
    for &q in data {
        let b = histogram_bin(q);
        h[b] = h[b].saturating_add(1);
    }
    h
}

impl Volume {
    /// Builds a volume from already-normalized data (`v = data / 65535`) with value range
    /// [0, 1] and no units; computes the histogram. Errors when `data.len()` does not match
    /// `dims`, a dim is 0, or a spacing is not finite and positive.
    pub fn from_normalized(
        name: &str,
        dims: [u32; 3],
        spacing: [f32; 3],
        data: Vec<u16>,
    ) -> Result<Volume, VolumeError> {
        let n: u64 = dims.iter().map(|&d| d as u64).product();
        if n == 0 || n != data.len() as u64 {
            return Err(VolumeError::InvalidArgument(format!(
                "volume {name:?}: dims {dims:?} need {n} voxels, data has {}",
                data.len()
            )));
        }
        if spacing.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(VolumeError::InvalidArgument(format!(
                "volume {name:?}: spacing {spacing:?} must be finite and positive"
            )));
        }
        let histogram = compute_histogram(&data);
        Ok(Volume {
            name: name.to_string(),
            dims,
            spacing,
            data,
            value_min: 0.0,
            value_max: 1.0,
            units: String::new(),
            modality: String::new(),
            format: String::from("generated"),
            histogram,
            warnings: Vec::new(),
        })
    }

    /// Number of voxels.
    pub fn voxel_count(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    fn index(&self, x: u32, y: u32, z: u32) -> Option<usize> {
        let [nx, ny, nz] = self.dims;
        if x >= nx || y >= ny || z >= nz {
            return None;
        }
        Some(x as usize + nx as usize * (y as usize + ny as usize * z as usize))
    }

    /// Original (raw, e.g. HU) value at a voxel, reconstructed from the normalized data;
    /// NaN outside the volume.
    pub fn raw_value(&self, x: u32, y: u32, z: u32) -> f64 {
        match self.index(x, y, z).and_then(|i| self.data.get(i)) {
            Some(&q) => self.value_min + (q as f64 / 65535.0) * (self.value_max - self.value_min),
            None => f64::NAN,
        }
    }

    /// Normalized value in [0, 1] at a voxel; NaN outside the volume.
    pub fn normalized(&self, x: u32, y: u32, z: u32) -> f32 {
        match self.index(x, y, z).and_then(|i| self.data.get(i)) {
            Some(&q) => q as f32 / 65535.0,
            None => f32::NAN,
        }
    }

    /// Box extent in world units: longest side 1, the others proportional to spacing × dims.
    pub fn world_extent(&self) -> [f32; 3] {
        let e: [f64; 3] = std::array::from_fn(|i| self.spacing[i] as f64 * self.dims[i] as f64);
        let m = e.iter().cloned().fold(0.0f64, f64::max);
        if !(m.is_finite() && m > 0.0) || e.iter().any(|v| !v.is_finite() || *v <= 0.0) {
            return [1.0; 3];
        }
        let extent = e.map(|v| (v / m) as f32);
        // A side that rounds to nothing (or next to it) would make a box without thickness;
        // loaders refuse such spacings, a volume built by hand gets the unit cube.
        if extent.iter().any(|v| !v.is_normal()) {
            return [1.0; 3];
        }
        extent
    }

    /// Box-filtered downsample so that no axis exceeds `max_dim` (0 is treated as 1). All axes
    /// are reduced by the same integer factor (partial blocks at the far edges are averaged
    /// over the voxels they hold); spacing grows so the world extent is preserved.
    pub fn downsampled(&self, max_dim: u32) -> Volume {
        let max_dim = max_dim.max(1);
        let largest = self.dims.iter().copied().max().unwrap_or(1);
        self.downsampled_by(largest.div_ceil(max_dim))
    }

    /// Box-filtered downsample by `factor` along every axis (1 or less: a copy), as
    /// [`Volume::downsampled`] describes.
    pub fn downsampled_by(&self, factor: u32) -> Volume {
        if factor <= 1 || self.data.len() != self.voxel_count() {
            return self.clone();
        }
        let f: [u32; 3] = [factor; 3];
        let nd: [u32; 3] = std::array::from_fn(|i| self.dims[i].div_ceil(f[i]));
        let [nx, ny, nz] = self.dims.map(|d| d as usize);
        let mut out = Vec::with_capacity(nd.iter().map(|&d| d as usize).product());
        for oz in 0..nd[2] as usize {
            let z0 = oz * f[2] as usize;
            let z1 = (z0 + f[2] as usize).min(nz);
            for oy in 0..nd[1] as usize {
                let y0 = oy * f[1] as usize;
                let y1 = (y0 + f[1] as usize).min(ny);
                for ox in 0..nd[0] as usize {
                    let x0 = ox * f[0] as usize;
                    let x1 = (x0 + f[0] as usize).min(nx);
                    let mut sum: u64 = 0;
                    for z in z0..z1 {
                        for y in y0..y1 {
                            let row = nx * (y + ny * z);
                            sum += self.data[row + x0..row + x1]
                                .iter()
                                .map(|&q| q as u64)
                                .sum::<u64>();
                        }
                    }
                    let count = ((z1 - z0) * (y1 - y0) * (x1 - x0)) as u64;
                    out.push(((sum + count / 2) / count.max(1)) as u16);
                }
            }
        }
        let spacing: [f32; 3] = std::array::from_fn(|i| {
            (self.spacing[i] as f64 * self.dims[i] as f64 / nd[i] as f64) as f32
        });
        Volume {
            name: self.name.clone(),
            dims: nd,
            spacing,
            histogram: compute_histogram(&out),
            data: out,
            value_min: self.value_min,
            value_max: self.value_max,
            units: self.units.clone(),
            modality: self.modality.clone(),
            format: format!(
                "{} (downsampled from {}×{}×{})",
                self.format, self.dims[0], self.dims[1], self.dims[2]
            ),
            warnings: self.warnings.clone(),
        }
    }
}

/// Quantizes through a lookup table indexed by the sample's bit pattern (8/16-bit types).
/// Takes the samples by value: 16-bit samples are rewritten in their own allocation (std's
/// in-place `collect` for same-size types), so a CT's peak memory is its volume once, not
/// twice (`voxlight bench load` measures it).
fn quantize_lut<T: Copy>(v: Vec<T>, lut: &[u16], idx: impl Fn(T) -> usize) -> Vec<u16> {
    v.into_iter().map(|x| lut[idx(x)]).collect()
}

impl RawVolume {
    /// Normalizes to a [`Volume`] (see [`Volume`] for the mapping).
    pub fn normalize(self, name: &str) -> Volume {
        normalize(self, name)
    }
}

pub(crate) fn normalize(raw: RawVolume, name: &str) -> Volume {
    let (min, max) = raw.min_max();
    let quantizer = Quantizer::new(min, max);
    let q = |x: f64| quantizer.quantize(x);
    let mut bad = 0usize;
    let data: Vec<u16> = match raw.samples {
        Samples::U8(v) => {
            let lut: Vec<u16> = (0..256).map(|i| q(i as f64)).collect();
            quantize_lut(v, &lut, |x| x as usize)
        }
        Samples::I8(v) => {
            let lut: Vec<u16> = (0..256).map(|i| q(i as u8 as i8 as f64)).collect();
            quantize_lut(v, &lut, |x| x as u8 as usize)
        }
        Samples::U16(v) => {
            let lut: Vec<u16> = (0..65536).map(|i| q(i as f64)).collect();
            quantize_lut(v, &lut, |x| x as usize)
        }
        Samples::I16(v) => {
            let lut: Vec<u16> = (0..65536).map(|i| q(i as u16 as i16 as f64)).collect();
            quantize_lut(v, &lut, |x| x as u16 as usize)
        }
        Samples::U32(v) => v.into_iter().map(|x| q(x as f64)).collect(),
        Samples::I32(v) => v.into_iter().map(|x| q(x as f64)).collect(),
        Samples::F32(v) => v
            .into_iter()
            .map(|x| {
                if x.is_nan() {
                    bad += 1;
                }
                q(x as f64)
            })
            .collect(),
        Samples::F64(v) => v
            .into_iter()
            .map(|x| {
                if x.is_nan() {
                    bad += 1;
                }
                q(x)
            })
            .collect(),
    };
    let range = ValueRange { min, max, nan: bad };
    assemble(
        RawVolume {
            samples: Samples::U8(Vec::new()),
            ..raw
        },
        data,
        range,
        name,
    )
}

/// The volume of `meta` (a [`RawVolume`] whose samples were read in two streaming passes, so it
/// holds none) from its 16-bit `data`, quantized against `range` by [`Quantizer`].
pub(crate) fn assemble(meta: RawVolume, data: Vec<u16>, range: ValueRange, name: &str) -> Volume {
    let mut warnings = meta.warnings;
    if range.nan > 0 {
        warnings.push(format!(
            "{} NaN samples were mapped to the minimum value {}",
            range.nan, range.min
        ));
    }
    let histogram = compute_histogram(&data);
    Volume {
        name: name.to_string(),
        dims: meta.dims,
        spacing: meta.spacing,
        data,
        value_min: range.min,
        value_max: range.max,
        units: meta.units,
        modality: meta.modality,
        format: meta.format,
        histogram,
        warnings,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sixteen_bit_samples_are_quantized_in_their_own_allocation() {
        let samples: Vec<i16> = (0..4096).map(|i| i as i16 - 1000).collect();
        let before = samples.as_ptr() as usize;
        let lut: Vec<u16> = (0..65536).map(|i| i as u16).collect();
        let out = quantize_lut(samples, &lut, |x| x as u16 as usize);
        assert_eq!(
            out.as_ptr() as usize,
            before,
            "a second 16-bit buffer was allocated"
        );
        assert_eq!(out[1000], 0);
    }

    fn raw(samples: Samples, dims: [u32; 3]) -> RawVolume {
        RawVolume {
            dims,
            spacing: [1.0, 2.0, 4.0],
            samples,
            units: "HU".into(),
            modality: "CT".into(),
            format: "test".into(),
            warnings: vec![],
        }
    }

    #[test]
    fn normalize_i16_roundtrip() {
        let vals: Vec<i16> = vec![-1000, -907, 0, 78, 906, 1766, 5, 6];
        let v = raw(Samples::I16(vals.clone()), [2, 2, 2]).normalize("t");
        assert_eq!(v.value_min, -1000.0);
        assert_eq!(v.value_max, 1766.0);
        assert_eq!(v.data[0], 0);
        assert_eq!(v.data[5], 65535);
        for (i, &x) in vals.iter().enumerate() {
            let (xx, yy, zz) = ((i % 2) as u32, ((i / 2) % 2) as u32, (i / 4) as u32);
            assert_eq!(v.raw_value(xx, yy, zz).round(), x as f64);
        }
        assert_eq!(v.histogram.iter().sum::<u32>(), 8);
        assert_eq!(v.histogram[0], 1);
        assert_eq!(v.histogram[255], 1);
        assert_eq!(v.units, "HU");
    }

    #[test]
    fn normalize_constant_and_nan() {
        let v = raw(Samples::F32(vec![3.0; 8]), [2, 2, 2]).normalize("c");
        assert!(v.data.iter().all(|&q| q == 0));
        assert_eq!((v.value_min, v.value_max), (3.0, 3.0));
        let v = raw(Samples::F32(vec![0.0, 1.0, f32::NAN, 0.5]), [4, 1, 1]).normalize("n");
        assert_eq!(v.data, vec![0, 65535, 0, 32768]);
        assert_eq!(v.warnings.len(), 1);
    }

    #[test]
    fn histogram_bins() {
        assert_eq!(histogram_bin(0), 0);
        assert_eq!(histogram_bin(65535), 255);
        assert_eq!(histogram_bin(255), 0);
        assert_eq!(histogram_bin(256), 1);
        assert_eq!(histogram_bin(32767), 127);
        assert_eq!(histogram_bin(32768), 128);
    }

    #[test]
    fn extent_and_downsample() {
        let data: Vec<u16> = (0..(8 * 4 * 2)).map(|i| (i * 1000) as u16).collect();
        let mut v = Volume::from_normalized("d", [8, 4, 2], [1.0, 1.0, 1.0], data).unwrap();
        v.spacing = [1.0, 1.0, 4.0];
        assert_eq!(v.world_extent(), [1.0, 0.5, 1.0]);
        let d = v.downsampled(4);
        assert_eq!(d.dims, [4, 2, 1]);
        assert_eq!(d.spacing, [2.0, 2.0, 8.0]);
        // Mean of voxels 0, 1, 8, 9, 32, 33, 40, 41 (× 1000).
        assert_eq!(d.data[0], 20500);
        assert_eq!(d.world_extent(), v.world_extent());
        assert_eq!(d.histogram.iter().sum::<u32>(), 8);
        let odd = v.downsampled(3);
        assert_eq!(odd.dims, [3, 2, 1]);
        assert_eq!(odd.world_extent(), v.world_extent());
        let same = v.downsampled(100);
        assert_eq!(same.dims, v.dims);
        let tiny = v.downsampled(0);
        assert_eq!(tiny.dims, [1, 1, 1]);
        assert!(v.raw_value(8, 0, 0).is_nan());
    }

    use crate::Endian;
    use crate::raw::{
        Affine, Decoded, PASS_CHUNK, SampleBuilder, SampleMode, SampleType, read_streamed,
    };
    use SampleMode::Keep;

    fn decode(
        ty: SampleType,
        e: Endian,
        bytes: &[u8],
        count: usize,
        mode: SampleMode,
        chunk: usize,
    ) -> Decoded {
        let mut b = SampleBuilder::with_mode(ty, e, count, mode);
        for c in bytes.chunks(chunk) {
            b.push(c);
        }
        b.finish_decoded()
    }

    /// The streaming passes (range, then quantization; chunks that split samples and flushes)
    /// give exactly what keeping the samples and normalizing them gives, for every type, with
    /// and without a rescale, NaN and infinities included.
    #[test]
    fn streaming_passes_equal_normalizing_kept_samples() {
        let n = PASS_CHUNK * 2 + 777;
        let values: Vec<f64> = (0..n)
            .map(|i| ((i as f64 * 0.618_034).fract() * 300.0 - 100.0).round())
            .collect();
        for ty in [
            SampleType::U8,
            SampleType::I8,
            SampleType::U16,
            SampleType::I16,
            SampleType::U32,
            SampleType::I32,
            SampleType::F32,
            SampleType::F64,
        ] {
            let mut samples = Samples::from_f64(ty, values.clone());
            if let Samples::F32(v) = &mut samples {
                v[3] = f32::NAN;
                v[5] = f32::INFINITY;
            }
            if let Samples::F64(v) = &mut samples {
                v[7] = f64::NAN;
                v[PASS_CHUNK + 1] = f64::NEG_INFINITY;
            }
            let bytes: Vec<u8> = (0..n)
                .flat_map(|i| {
                    let x = samples.get(i).unwrap_or(0.0);
                    match ty {
                        SampleType::U8 => vec![x as u8],
                        SampleType::I8 => (x as i8).to_be_bytes().to_vec(),
                        SampleType::U16 => (x as u16).to_be_bytes().to_vec(),
                        SampleType::I16 => (x as i16).to_be_bytes().to_vec(),
                        SampleType::U32 => (x as u32).to_be_bytes().to_vec(),
                        SampleType::I32 => (x as i32).to_be_bytes().to_vec(),
                        SampleType::F32 => (x as f32).to_be_bytes().to_vec(),
                        SampleType::F64 => x.to_be_bytes().to_vec(),
                    }
                })
                .collect();
            for affine in [
                None,
                Some(Affine {
                    slope: 0.37,
                    inter: -12.5,
                }),
            ] {
                let Decoded::Samples(kept) = decode(ty, Endian::Big, &bytes, n, Keep, 4093) else {
                    panic!("kept samples")
                };
                let same = |a: Option<f64>, b: Option<f64>| {
                    a == b || a.is_some_and(f64::is_nan) && b.is_some_and(f64::is_nan)
                };
                assert!((0..n).all(|i| same(kept.get(i), samples.get(i))), "{ty:?}");
                let kept = match affine {
                    Some(a) => Samples::F32(
                        (0..n)
                            .map(|i| a.apply(kept.get(i).unwrap_or(0.0)))
                            .collect(),
                    ),
                    None => kept,
                };
                let raw = RawVolume {
                    dims: [n as u32, 1, 1],
                    spacing: [1.0; 3],
                    samples: kept,
                    units: String::new(),
                    modality: String::new(),
                    format: String::new(),
                    warnings: vec![],
                };
                let expected = raw.clone().normalize("t");
                // Chunks of another size for each pass (they split samples differently).
                let mut chunk = 1 << 12;
                let streamed = read_streamed(ty, affine, |mode| {
                    chunk = chunk * 16 + 3;
                    Ok(decode(ty, Endian::Big, &bytes, n, mode, chunk))
                })
                .expect("streamed");
                let meta = RawVolume {
                    samples: Samples::empty(ty),
                    ..raw
                };
                let streamed = assemble(meta, streamed.data, streamed.range, "t");
                assert_eq!(streamed.data, expected.data, "{ty:?} {affine:?}");
                assert_eq!(
                    (streamed.value_min, streamed.value_max, &streamed.warnings),
                    (expected.value_min, expected.value_max, &expected.warnings),
                    "{ty:?} {affine:?}"
                );
            }
        }
    }
}
