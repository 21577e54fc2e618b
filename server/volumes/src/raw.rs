//! Raw decoded samples ([`RawVolume`]), sample types, size checks and the streaming sample decoder
//! every loader shares.

use std::fmt;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use crate::{MAX_VOXELS, VolumeError};

/// Scalar type of the samples stored in a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SampleType {
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 8-bit integer.
    I8,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 16-bit integer.
    I16,
    /// Unsigned 32-bit integer.
    U32,
    /// Signed 32-bit integer.
    I32,
    /// 32-bit IEEE float.
    F32,
    /// 64-bit IEEE float.
    F64,
}

impl SampleType {
    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::F64 => 8,
        }
    }

    /// Short lowercase name, e.g. `"uint16"`.
    pub fn name(self) -> &'static str {
        match self {
            SampleType::U8 => "uint8",
            SampleType::I8 => "int8",
            SampleType::U16 => "uint16",
            SampleType::I16 => "int16",
            SampleType::U32 => "uint32",
            SampleType::I32 => "int32",
            SampleType::F32 => "float32",
            SampleType::F64 => "float64",
        }
    }
}

impl fmt::Display for SampleType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Byte order of multi-byte samples in a file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Endian {
    /// Least significant byte first.
    Little,
    /// Most significant byte first.
    Big,
}

impl Endian {
    /// `"little-endian"` or `"big-endian"`.
    pub fn name(self) -> &'static str {
        match self {
            Endian::Little => "little-endian",
            Endian::Big => "big-endian",
        }
    }
}

/// Decoded samples in their stored type (after any rescale a format mandates).
#[derive(Clone, PartialEq)]
pub enum Samples {
    /// Unsigned 8-bit.
    U8(Vec<u8>),
    /// Signed 8-bit.
    I8(Vec<i8>),
    /// Unsigned 16-bit.
    U16(Vec<u16>),
    /// Signed 16-bit.
    I16(Vec<i16>),
    /// Unsigned 32-bit.
    U32(Vec<u32>),
    /// Signed 32-bit.
    I32(Vec<i32>),
    /// 32-bit float.
    F32(Vec<f32>),
    /// 64-bit float.
    F64(Vec<f64>),
}

macro_rules! each_samples {
    ($s:expr, $v:ident => $body:expr) => {
        match $s {
            Samples::U8($v) => $body,
            Samples::I8($v) => $body,
            Samples::U16($v) => $body,
            Samples::I16($v) => $body,
            Samples::U32($v) => $body,
            Samples::I32($v) => $body,
            Samples::F32($v) => $body,
            Samples::F64($v) => $body,
        }
    };
}

impl Samples {
    /// Samples of type `ty` from values parsed as f64 (ASCII encodings); values are cast.
    pub fn from_f64(ty: SampleType, vals: Vec<f64>) -> Self {
        match ty {
            SampleType::U8 => Samples::U8(vals.iter().map(|&v| v as u8).collect()),
            SampleType::I8 => Samples::I8(vals.iter().map(|&v| v as i8).collect()),
            SampleType::U16 => Samples::U16(vals.iter().map(|&v| v as u16).collect()),
            SampleType::I16 => Samples::I16(vals.iter().map(|&v| v as i16).collect()),
            SampleType::U32 => Samples::U32(vals.iter().map(|&v| v as u32).collect()),
            SampleType::I32 => Samples::I32(vals.iter().map(|&v| v as i32).collect()),
            SampleType::F32 => Samples::F32(vals.iter().map(|&v| v as f32).collect()),
            SampleType::F64 => Samples::F64(vals),
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        each_samples!(self, v => v.len())
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The scalar type.
    pub fn sample_type(&self) -> SampleType {
        match self {
            Samples::U8(_) => SampleType::U8,
            Samples::I8(_) => SampleType::I8,
            Samples::U16(_) => SampleType::U16,
            Samples::I16(_) => SampleType::I16,
            Samples::U32(_) => SampleType::U32,
            Samples::I32(_) => SampleType::I32,
            Samples::F32(_) => SampleType::F32,
            Samples::F64(_) => SampleType::F64,
        }
    }

    /// Sample `i` as `f64`, or `None` when out of range.
    pub fn get(&self, i: usize) -> Option<f64> {
        match self {
            Samples::U8(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::I8(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::U16(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::I16(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::U32(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::I32(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::F32(v) => v.get(i).map(|&x| f64::from(x)),
            Samples::F64(v) => v.get(i).copied(),
        }
    }

    /// No samples of type `ty`.
    pub(crate) fn empty(ty: SampleType) -> Samples {
        Samples::with_capacity(ty, 0)
    }

    fn with_capacity(ty: SampleType, n: usize) -> Samples {
        match ty {
            SampleType::U8 => Samples::U8(Vec::with_capacity(n)),
            SampleType::I8 => Samples::I8(Vec::with_capacity(n)),
            SampleType::U16 => Samples::U16(Vec::with_capacity(n)),
            SampleType::I16 => Samples::I16(Vec::with_capacity(n)),
            SampleType::U32 => Samples::U32(Vec::with_capacity(n)),
            SampleType::I32 => Samples::I32(Vec::with_capacity(n)),
            SampleType::F32 => Samples::F32(Vec::with_capacity(n)),
            SampleType::F64 => Samples::F64(Vec::with_capacity(n)),
        }
    }
}

impl fmt::Debug for Samples {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Samples::{:?}[{}]", self.sample_type(), self.len())
    }
}

/// A decoded volume before normalization: samples in their stored type, x fastest
/// (`x + nx*(y + ny*z)`).
#[derive(Clone)]
pub struct RawVolume {
    /// Voxel counts along x, y, z.
    pub dims: [u32; 3],
    /// Physical voxel spacing (mm for medical data, 1.0 when unknown).
    pub spacing: [f32; 3],
    /// The samples.
    pub samples: Samples,
    /// Value units, e.g. `"HU"`; empty when unknown.
    pub units: String,
    /// Modality, e.g. `"CT"`; empty when unknown.
    pub modality: String,
    /// Human-readable source format.
    pub format: String,
    /// Non-fatal problems met while loading.
    pub warnings: Vec<String>,
}

impl fmt::Debug for RawVolume {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RawVolume")
            .field("dims", &self.dims)
            .field("spacing", &self.spacing)
            .field("samples", &self.samples)
            .field("units", &self.units)
            .field("modality", &self.modality)
            .field("format", &self.format)
            .field("warnings", &self.warnings)
            .finish()
    }
}

impl RawVolume {
    /// A volume whose file names no units or modality (NRRD, NIfTI, VTI).
    pub(crate) fn unlabelled(
        dims: [u32; 3],
        spacing: [f32; 3],
        samples: Samples,
        format: String,
        warnings: Vec<String>,
    ) -> Self {
        RawVolume {
            dims,
            spacing,
            samples,
            units: String::new(),
            modality: String::new(),
            format,
            warnings,
        }
    }

    /// Number of voxels (`nx*ny*nz`).
    pub fn voxel_count(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    /// Sample value at `(x, y, z)`; NaN when the index is outside the volume.
    pub fn value(&self, x: u32, y: u32, z: u32) -> f64 {
        let [nx, ny, nz] = self.dims;
        if x >= nx || y >= ny || z >= nz {
            return f64::NAN;
        }
        let i = x as usize + nx as usize * (y as usize + ny as usize * z as usize);
        self.samples.get(i).unwrap_or(f64::NAN)
    }

    /// Exact sum of all samples for integer types, `None` for float types.
    pub fn sum_exact(&self) -> Option<i128> {
        fn s<T: Copy + Into<i128>>(v: &[T]) -> i128 {
            v.iter().map(|&x| x.into()).sum()
        }
        match &self.samples {
            Samples::U8(v) => Some(s(v)),
            Samples::I8(v) => Some(s(v)),
            Samples::U16(v) => Some(s(v)),
            Samples::I16(v) => Some(s(v)),
            Samples::U32(v) => Some(s(v)),
            Samples::I32(v) => Some(s(v)),
            Samples::F32(_) | Samples::F64(_) => None,
        }
    }

    /// Sum of all samples (exact for integer samples as long as it fits in 53 bits).
    pub fn sum(&self) -> f64 {
        match self.sum_exact() {
            Some(s) => s as f64,
            None => match &self.samples {
                Samples::F32(v) => v.iter().map(|&x| x as f64).sum(),
                Samples::F64(v) => v.iter().sum(),
                _ => 0.0,
            },
        }
    }

    /// Smallest and largest finite sample (NaN and infinities are ignored); `(0, 0)` if none.
    pub fn min_max(&self) -> (f64, f64) {
        fn ints<T: Copy + Ord + Into<f64>>(v: &[T]) -> (f64, f64) {
            match (v.iter().min(), v.iter().max()) {
                (Some(&a), Some(&b)) => (a.into(), b.into()),
                _ => (0.0, 0.0),
            }
        }
        fn floats(it: impl Iterator<Item = f64>) -> (f64, f64) {
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for x in it.filter(|x| x.is_finite()) {
                lo = lo.min(x);
                hi = hi.max(x);
            }
            if lo > hi { (0.0, 0.0) } else { (lo, hi) }
        }
        match &self.samples {
            Samples::U8(v) => ints(v),
            Samples::I8(v) => ints(v),
            Samples::U16(v) => ints(v),
            Samples::I16(v) => ints(v),
            Samples::U32(v) => ints(v),
            Samples::I32(v) => ints(v),
            Samples::F32(v) => floats(v.iter().map(|&x| x as f64)),
            Samples::F64(v) => floats(v.iter().copied()),
        }
    }
}

/// Validates dims (non-zero, each fits `u32`, product ≤ [`MAX_VOXELS`]) before anything is
/// allocated. `what` names the header field for the error message.
pub(crate) fn check_dims(path: &Path, what: &str, dims: [u64; 3]) -> Result<[u32; 3], VolumeError> {
    if let Some(axis) = dims.iter().position(|&d| d == 0) {
        return Err(VolumeError::format(
            path,
            format!(
                "{what}: dimension {} (axis {}) is 0 in {dims:?}; expected at least 1 voxel per axis",
                ["x", "y", "z"][axis],
                axis
            ),
        ));
    }
    let voxels = dims
        .iter()
        .try_fold(1u64, |acc, &d| acc.checked_mul(d))
        .unwrap_or(u64::MAX);
    if voxels > MAX_VOXELS || dims.iter().any(|&d| d > u32::MAX as u64) {
        return Err(VolumeError::TooLarge {
            path: path.to_path_buf(),
            dims,
            voxels,
            limit: MAX_VOXELS,
        });
    }
    Ok([dims[0] as u32, dims[1] as u32, dims[2] as u32])
}

/// Number of data bytes for `dims` of `ty` (dims must have passed [`check_dims`]).
pub(crate) fn byte_count(dims: [u32; 3], ty: SampleType) -> u64 {
    dims.iter().map(|&d| d as u64).product::<u64>() * ty.size() as u64
}

/// Largest ratio between two voxel spacings of a volume. Beyond it the volume's box is a
/// sheet whose thin side rounds to nothing in `f32` (a zero-width box, a zero march step)
/// or nearly so; no real scan comes close (CT slices are at most ~50× their pixel size).
pub const MAX_SPACING_RATIO: f64 = 1e6;

/// Checks that spacings are finite, positive, normal `f32` numbers within
/// [`MAX_SPACING_RATIO`] of each other.
pub(crate) fn check_spacing(path: &Path, what: &str, s: [f64; 3]) -> Result<[f32; 3], VolumeError> {
    for (i, &v) in s.iter().enumerate() {
        if !v.is_finite() || v <= 0.0 || !(v as f32).is_normal() {
            return Err(VolumeError::format(
                path,
                format!(
                    "{what}: spacing along {} is {v}; expected a finite positive number",
                    ["x", "y", "z"][i]
                ),
            ));
        }
    }
    let (lo, hi) = s.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
        (lo.min(v), hi.max(v))
    });
    if hi / lo > MAX_SPACING_RATIO {
        return Err(VolumeError::format(
            path,
            format!(
                "{what}: spacings {s:?} differ by more than a factor of {MAX_SPACING_RATIO:e}; \
                 the volume would be a sheet without thickness"
            ),
        ));
    }
    Ok([s[0] as f32, s[1] as f32, s[2] as f32])
}

/// Bytes of samples reserved before any data arrived (more as it is decoded): a header that
/// declares a large volume over a small or compressed input reserves no more than this.
const INITIAL_CAPACITY_BYTES: usize = 1 << 20;

/// Grows `v` geometrically for `k` more elements, never beyond `expected` in total.
fn grow<T>(v: &mut Vec<T>, k: usize, expected: usize) {
    let need = v.len() + k;
    if need > v.capacity() {
        let target = v
            .capacity()
            .saturating_mul(2)
            .max(need)
            .min(expected.max(need));
        v.reserve_exact(target - v.len());
    }
}

/// The mapping of original values to 16 bits: `(x - min) / (max - min)` scaled to 0..=65535,
/// rounded; a constant volume (or NaN) maps to 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Quantizer {
    min: f64,
    scale: f64,
}

impl Quantizer {
    pub(crate) fn new(min: f64, max: f64) -> Self {
        let range = max - min;
        let scale = if range > 0.0 && range.is_finite() {
            65535.0 / range
        } else {
            0.0
        };
        Quantizer { min, scale }
    }

    pub(crate) fn quantize(self, x: f64) -> u16 {
        if self.scale == 0.0 {
            0
        } else {
            ((x - self.min) * self.scale).round().clamp(0.0, 65535.0) as u16
        }
    }
}

/// What a [`SampleBuilder`] does with the samples it decodes.
#[derive(Clone, Copy, Debug)]
pub(crate) enum SampleMode {
    /// Keep them in their stored type ([`RawVolume`]: exact values).
    Keep,
    /// First of two streaming passes: only their range (after `affine`).
    Range { affine: Option<Affine> },
    /// Second pass: quantize them (after `affine`) to 16 bits against the first pass's range.
    Quantize {
        affine: Option<Affine>,
        quantizer: Quantizer,
    },
    /// 8-bit samples in one pass: their bit patterns widened to 16 bits, and their range (a
    /// 256-entry table then quantizes them in place).
    Widen,
}

/// A rescale `x * slope + inter` whose result is stored as `f32` (NIfTI's scl_slope/scl_inter).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Affine {
    pub slope: f64,
    pub inter: f64,
}

impl Affine {
    pub(crate) fn apply(self, x: f64) -> f32 {
        (x * self.slope + self.inter) as f32
    }
}

/// The finite range of a volume's values and how many were NaN ([`RawVolume::min_max`]'s rule).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct ValueRange {
    pub min: f64,
    pub max: f64,
    pub nan: usize,
}

impl ValueRange {
    fn empty() -> Self {
        ValueRange {
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            nan: 0,
        }
    }

    fn add(&mut self, x: f64) {
        if x.is_finite() {
            self.min = self.min.min(x);
            self.max = self.max.max(x);
        } else if x.is_nan() {
            self.nan += 1;
        }
    }

    fn finished(self) -> Self {
        if self.min > self.max {
            ValueRange {
                min: 0.0,
                max: 0.0,
                nan: self.nan,
            }
        } else {
            self
        }
    }
}

/// What a [`SampleBuilder`] produced, by its [`SampleMode`].
pub(crate) enum Decoded {
    Samples(Samples),
    Range(ValueRange),
    Quantized(Vec<u16>),
    Widened {
        patterns: Vec<u16>,
        range: ValueRange,
    },
}

/// Samples kept between flushes in the streaming modes (1 MiB of the widest type).
pub(crate) const PASS_CHUNK: usize = 1 << 17;

/// Streaming decoder: accepts byte chunks of any size and converts them to typed samples, or
/// (in the two-pass modes) to their range or their 16-bit quantization without keeping them.
pub(crate) struct SampleBuilder {
    ty: SampleType,
    endian: Endian,
    samples: Samples,
    carry: [u8; 8],
    carry_len: usize,
    expected: usize,
    mode: SampleMode,
    /// Samples already passed on to `range` or `quantized` (streaming modes).
    flushed: usize,
    range: ValueRange,
    quantized: Vec<u16>,
}

macro_rules! push_typed {
    ($v:expr, $t:ty, $n:expr, $bytes:expr, $endian:expr, $room:expr, $expected:expr) => {{
        let take = ($bytes.len() / $n).min($room);
        grow($v, take, $expected);
        let whole = &$bytes[..take * $n];
        match $endian {
            Endian::Little => $v.extend(whole.chunks_exact($n).map(|c| {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                <$t>::from_le_bytes(a)
            })),
            Endian::Big => $v.extend(whole.chunks_exact($n).map(|c| {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                <$t>::from_be_bytes(a)
            })),
        }
        take * $n
    }};
}

impl SampleBuilder {
    /// A builder expecting exactly `expected` samples (already validated against MAX_VOXELS),
    /// handling them as `mode` says.
    pub(crate) fn with_mode(
        ty: SampleType,
        endian: Endian,
        expected: usize,
        mode: SampleMode,
    ) -> Self {
        let kept = match mode {
            SampleMode::Keep => expected,
            _ => expected.min(PASS_CHUNK),
        };
        SampleBuilder {
            ty,
            endian,
            // Capacity grows with the data actually decoded, so a header that lies about the
            // size cannot make us reserve memory for data that never arrives.
            samples: Samples::with_capacity(ty, kept.min(INITIAL_CAPACITY_BYTES / ty.size())),
            carry: [0; 8],
            carry_len: 0,
            expected,
            mode,
            flushed: 0,
            range: ValueRange::empty(),
            // The quantizing pass follows a range pass that read every sample, so the size is
            // known to be real: reserve it once (growing would copy a volume-sized buffer).
            quantized: match mode {
                SampleMode::Quantize { .. } => Vec::with_capacity(expected),
                _ => Vec::new(),
            },
            // Widening is the only pass over the data: grow with it (see `grow`).
        }
    }

    /// Samples decoded so far.
    pub(crate) fn len(&self) -> usize {
        self.flushed + self.samples.len()
    }

    /// Passes the samples held so far on to the range or the quantization (streaming modes).
    // `x as f64` is the identity in the macro's f64 arm.
    #[allow(clippy::unnecessary_cast)]
    fn flush(&mut self) {
        let n = self.samples.len();
        let (affine, quantizer) = match self.mode {
            SampleMode::Keep => return,
            SampleMode::Range { affine } => (affine, None),
            SampleMode::Quantize { affine, quantizer } => (affine, Some(quantizer)),
            SampleMode::Widen => {
                grow(&mut self.quantized, n, self.expected);
                let (out, range) = (&mut self.quantized, &mut self.range);
                match &self.samples {
                    Samples::U8(v) => v.iter().for_each(|&x| {
                        range.add(x as f64);
                        out.push(x as u16);
                    }),
                    Samples::I8(v) => v.iter().for_each(|&x| {
                        range.add(x as f64);
                        out.push(x as u8 as u16);
                    }),
                    // `read_streamed` widens 8-bit samples only.
                    other => unreachable!("widening {:?}", other.sample_type()),
                }
                self.flushed += n;
                each_samples!(&mut self.samples, v => v.clear());
                return;
            }
        };
        let value = |x: f64| match affine {
            Some(a) => a.apply(x) as f64,
            None => x,
        };
        match quantizer {
            None => {
                let range = &mut self.range;
                each_samples!(&self.samples, v => v.iter().for_each(|&x| range.add(value(x as f64))));
            }
            Some(q) => {
                grow(&mut self.quantized, n, self.expected);
                let out = &mut self.quantized;
                each_samples!(&self.samples, v => out.extend(v.iter().map(|&x| q.quantize(value(x as f64)))));
            }
        }
        self.flushed += n;
        each_samples!(&mut self.samples, v => v.clear());
    }

    /// True once `expected` samples have been decoded.
    pub(crate) fn is_full(&self) -> bool {
        self.len() >= self.expected
    }

    /// Decodes `bytes`; bytes beyond the expected sample count are ignored.
    pub(crate) fn push(&mut self, mut bytes: &[u8]) {
        let n = self.ty.size();
        if self.carry_len > 0 {
            let need = n - self.carry_len;
            let k = need.min(bytes.len());
            self.carry[self.carry_len..self.carry_len + k].copy_from_slice(&bytes[..k]);
            self.carry_len += k;
            bytes = &bytes[k..];
            if self.carry_len < n {
                return;
            }
            let c = self.carry;
            self.carry_len = 0;
            self.push_whole(&c[..n]);
        }
        let used = self.push_whole(bytes);
        let rest = &bytes[used..];
        if !self.is_full() && !rest.is_empty() && rest.len() < n {
            self.carry[..rest.len()].copy_from_slice(rest);
            self.carry_len = rest.len();
        }
    }

    fn push_whole(&mut self, bytes: &[u8]) -> usize {
        if matches!(self.mode, SampleMode::Keep) {
            return self.push_kept(bytes);
        }
        let size = self.ty.size();
        let mut used = 0;
        while used + size <= bytes.len() && !self.is_full() {
            let take = (bytes.len() - used).min(PASS_CHUNK * size);
            used += self.push_kept(&bytes[used..used + take]);
            self.flush();
        }
        used
    }

    fn push_kept(&mut self, bytes: &[u8]) -> usize {
        let room = self.expected.saturating_sub(self.len());
        let e = self.endian;
        let expected = self.expected;
        match &mut self.samples {
            Samples::U8(v) => {
                let k = bytes.len().min(room);
                grow(v, k, expected);
                v.extend_from_slice(&bytes[..k]);
                k
            }
            Samples::I8(v) => {
                let k = bytes.len().min(room);
                grow(v, k, expected);
                v.extend(bytes[..k].iter().map(|&b| b as i8));
                k
            }
            Samples::U16(v) => push_typed!(v, u16, 2, bytes, e, room, expected),
            Samples::I16(v) => push_typed!(v, i16, 2, bytes, e, room, expected),
            Samples::U32(v) => push_typed!(v, u32, 4, bytes, e, room, expected),
            Samples::I32(v) => push_typed!(v, i32, 4, bytes, e, room, expected),
            Samples::F32(v) => push_typed!(v, f32, 4, bytes, e, room, expected),
            Samples::F64(v) => push_typed!(v, f64, 8, bytes, e, room, expected),
        }
    }

    /// What the builder's mode produced.
    pub(crate) fn finish_decoded(mut self) -> Decoded {
        self.flush();
        match self.mode {
            SampleMode::Keep => Decoded::Samples(self.samples),
            SampleMode::Range { .. } => Decoded::Range(self.range.finished()),
            SampleMode::Quantize { .. } => Decoded::Quantized(self.quantized),
            SampleMode::Widen => Decoded::Widened {
                patterns: self.quantized,
                range: self.range.finished(),
            },
        }
    }
}

/// Reads exactly `count` samples from `reader` in chunks (no intermediate full-size byte buffer).
/// `what` describes the data source for the "data ended early" error.
pub(crate) fn read_samples(
    reader: impl Read,
    ty: SampleType,
    endian: Endian,
    count: usize,
    path: &Path,
    what: &str,
) -> Result<Samples, VolumeError> {
    match read_samples_mode(reader, ty, endian, count, path, what, SampleMode::Keep)? {
        Decoded::Samples(samples) => Ok(samples),
        _ => unreachable!("SampleMode::Keep decodes samples"),
    }
}

/// [`read_samples`] with the samples handled as `mode` says.
pub(crate) fn read_samples_mode(
    reader: impl Read,
    ty: SampleType,
    endian: Endian,
    count: usize,
    path: &Path,
    what: &str,
    mode: SampleMode,
) -> Result<Decoded, VolumeError> {
    let expected_bytes = count as u64 * ty.size() as u64;
    let mut reader = reader.take(expected_bytes);
    let mut b = SampleBuilder::with_mode(ty, endian, count, mode);
    let mut buf = vec![0u8; 1 << 20];
    let mut got: u64 = 0;
    while !b.is_full() {
        let n = match reader.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => {
                return Err(VolumeError::io(
                    path,
                    format!("reading {what} (after {got} of {expected_bytes} bytes)"),
                    e,
                ));
            }
        };
        got += n as u64;
        b.push(&buf[..n]);
    }
    if !b.is_full() {
        return Err(VolumeError::format(
            path,
            format!(
                "{what} is truncated: expected {expected_bytes} bytes ({count} samples of {ty}), \
                 found only {got}"
            ),
        ));
    }
    Ok(b.finish_decoded())
}

/// Samples read in two streaming passes straight to 16 bits: the volume's data and the range
/// it was quantized against (`volume::assemble` makes the [`crate::Volume`]).
pub(crate) struct Streamed {
    pub data: Vec<u16>,
    pub range: ValueRange,
}

/// A loader's samples of type `ty`, read through `read` (rescaled by `affine` when given).
///
/// - With `streaming` (what `load` asks for), samples that are not 16-bit and rescaled ones go
///   straight to 16 bits ([`read_streamed`]); the returned samples are then empty (of the type
///   they would have had). 16-bit samples are not streamed: their quantization rewrites them in
///   their own allocation, so keeping them costs nothing.
/// - Otherwise they are kept in their type, or as `f32` after a rescale.
// `x as f64` is the identity in the macro's f64 arm.
#[allow(clippy::unnecessary_cast)]
pub(crate) fn read_samples_as(
    ty: SampleType,
    affine: Option<Affine>,
    streaming: bool,
    mut read: impl FnMut(SampleMode) -> Result<Decoded, VolumeError>,
) -> Result<(Samples, Option<Streamed>), VolumeError> {
    if streaming && (affine.is_some() || ty.size() != 2) {
        let kept_ty = if affine.is_some() {
            SampleType::F32
        } else {
            ty
        };
        return Ok((
            Samples::empty(kept_ty),
            Some(read_streamed(ty, affine, read)?),
        ));
    }
    let Decoded::Samples(samples) = read(SampleMode::Keep)? else {
        unreachable!("SampleMode::Keep decodes samples")
    };
    let samples = match affine {
        Some(a) => Samples::F32(
            each_samples!(&samples, v => v.iter().map(|&x| a.apply(x as f64)).collect()),
        ),
        None => samples,
    };
    Ok((samples, None))
}

/// Reads a volume's samples of type `ty` through `read` straight to 16 bits: 8-bit samples in
/// one pass (widened, then quantized in place by a table), wider or rescaled ones in two (their
/// range, then their quantization).
pub(crate) fn read_streamed(
    ty: SampleType,
    affine: Option<Affine>,
    mut read: impl FnMut(SampleMode) -> Result<Decoded, VolumeError>,
) -> Result<Streamed, VolumeError> {
    if ty.size() == 1 && affine.is_none() {
        let Decoded::Widened {
            patterns: mut data,
            range,
        } = read(SampleMode::Widen)?
        else {
            unreachable!("SampleMode::Widen decodes 16-bit patterns")
        };
        let quantizer = Quantizer::new(range.min, range.max);
        let signed = ty == SampleType::I8;
        let table: Vec<u16> = (0..256u16)
            .map(|p| {
                let x = if signed {
                    p as u8 as i8 as f64
                } else {
                    p as f64
                };
                quantizer.quantize(x)
            })
            .collect();
        data.iter_mut().for_each(|p| *p = table[*p as usize & 0xff]);
        return Ok(Streamed { data, range });
    }
    let Decoded::Range(range) = read(SampleMode::Range { affine })? else {
        unreachable!("SampleMode::Range decodes a range")
    };
    let quantizer = Quantizer::new(range.min, range.max);
    let Decoded::Quantized(data) = read(SampleMode::Quantize { affine, quantizer })? else {
        unreachable!("SampleMode::Quantize decodes 16-bit data")
    };
    Ok(Streamed { data, range })
}

/// Loads a headerless raw file with explicitly given layout. `header_bytes` are skipped first.
pub fn load_raw_file(
    path: &Path,
    dims: [u32; 3],
    sample: SampleType,
    endian: Endian,
    spacing: [f32; 3],
    header_bytes: u64,
) -> Result<RawVolume, VolumeError> {
    let dims = check_dims(path, "raw dims argument", dims.map(u64::from))?;
    let spacing = check_spacing(path, "raw spacing argument", spacing.map(f64::from))?;
    let nbytes = byte_count(dims, sample);
    let mut file =
        File::open(path).map_err(|e| VolumeError::io(path, "opening the raw file", e))?;
    let len = file
        .metadata()
        .map_err(|e| VolumeError::io(path, "reading the file size", e))?
        .len();
    let needed = header_bytes.saturating_add(nbytes);
    if len < needed {
        return Err(VolumeError::format(
            path,
            format!(
                "file is {len} bytes, but header ({header_bytes} bytes) + data ({}×{}×{} × {} bytes \
                 = {nbytes}) needs {needed}",
                dims[0],
                dims[1],
                dims[2],
                sample.size()
            ),
        ));
    }
    file.seek(SeekFrom::Start(header_bytes))
        .map_err(|e| VolumeError::io(path, "seeking past the header", e))?;
    let count = nbytes as usize / sample.size();
    let samples = read_samples(
        std::io::BufReader::new(file),
        sample,
        endian,
        count,
        path,
        "raw data",
    )?;
    let mut warnings = Vec::new();
    if len > needed {
        warnings.push(format!(
            "{}: {} trailing bytes after the expected data were ignored",
            path.display(),
            len - needed
        ));
    }
    Ok(RawVolume {
        dims,
        spacing,
        samples,
        units: String::new(),
        modality: String::new(),
        format: format!("raw ({sample}, {})", endian.name()),
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builder_handles_split_elements() {
        let vals: Vec<u16> = (0..1000u16).map(|i| i.wrapping_mul(977)).collect();
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
        let mut b = SampleBuilder::with_mode(SampleType::U16, Endian::Big, vals.len(), Keep);
        for c in bytes.chunks(7) {
            b.push(c);
        }
        assert_eq!(kept(b), Samples::U16(vals));
    }

    use SampleMode::Keep;

    fn kept(b: SampleBuilder) -> Samples {
        match b.finish_decoded() {
            Decoded::Samples(s) => s,
            _ => panic!("SampleMode::Keep decodes samples"),
        }
    }

    #[test]
    fn builder_ignores_excess() {
        let mut b = SampleBuilder::with_mode(SampleType::I32, Endian::Little, 2, Keep);
        b.push(&[1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]);
        assert_eq!(kept(b), Samples::I32(vec![1, 2]));
        for mode in [
            SampleMode::Range { affine: None },
            SampleMode::Quantize {
                affine: None,
                quantizer: Quantizer::new(1.0, 2.0),
            },
        ] {
            let mut b = SampleBuilder::with_mode(SampleType::I32, Endian::Little, 2, mode);
            b.push(&[1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]);
            assert!(b.is_full());
            match b.finish_decoded() {
                Decoded::Range(r) => assert_eq!((r.min, r.max), (1.0, 2.0)),
                Decoded::Quantized(q) => assert_eq!(q, vec![0, 65535]),
                Decoded::Samples(_) | Decoded::Widened { .. } => panic!("not this mode"),
            }
        }
    }

    #[test]
    fn dims_checks() {
        let p = Path::new("x");
        assert!(check_dims(p, "t", [0, 1, 1]).is_err());
        assert!(matches!(
            check_dims(p, "t", [100_000, 100_000, 100_000]),
            Err(VolumeError::TooLarge { .. })
        ));
        assert!(matches!(
            check_dims(p, "t", [u64::MAX, u64::MAX, 2]),
            Err(VolumeError::TooLarge {
                voxels: u64::MAX,
                ..
            })
        ));
        assert_eq!(check_dims(p, "t", [2, 3, 4]).ok(), Some([2, 3, 4]));
    }

    #[test]
    fn raw_stats() {
        let r = RawVolume {
            dims: [2, 2, 1],
            spacing: [1.0; 3],
            samples: Samples::F32(vec![1.0, f32::NAN, -2.0, 4.0]),
            units: String::new(),
            modality: String::new(),
            format: String::new(),
            warnings: vec![],
        };
        assert_eq!(r.min_max(), (-2.0, 4.0));
        assert_eq!(r.value(0, 1, 0), -2.0);
        assert!(r.value(2, 0, 0).is_nan());
        assert_eq!(r.sum_exact(), None);
    }
}
