//! A frame: image data with its variance, bad-pixel mask, header and provenance.
use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::header::Header;

/// Bits of the per-pixel mask.
pub mod mask {
    /// Known bad pixel (calibration mask or detected hot/dead/cluster/column).
    pub const BAD: u8 = 1;
    /// At or above the profile's saturation level.
    pub const SATURATED: u8 = 2;
    /// Above the profile's linearity limit (usable with care).
    pub const NONLINEAR: u8 = 4;
    /// Hit by a cosmic ray (detected outlier in time).
    pub const COSMIC: u8 = 8;
    /// Blocked by the focal mask (outside every strip).
    pub const OFF_STRIP: u8 = 16;
    /// Pixel value was repaired (interpolated); see the stage's history record.
    pub const REPAIRED: u8 = 32;
}

/// One provenance record: what a stage did, with its parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryRecord {
    /// Stage name, e.g. `sky`.
    pub stage: String,
    /// Human-readable description with the parameter values used.
    pub detail: String,
}

impl HistoryRecord {
    /// New record.
    pub fn new(stage: impl Into<String>, detail: impl Into<String>) -> Self {
        HistoryRecord {
            stage: stage.into(),
            detail: detail.into(),
        }
    }
    /// One line as written to a FITS HISTORY card (`sofipol <stage>: <detail>`).
    pub fn line(&self) -> String {
        format!("sofipol {}: {}", self.stage, self.detail)
    }
}

/// Image data (ADU, averaged over NDIT reads) with variance (ADU^2), mask, header and
/// provenance. Arrays are indexed `[y, x]` with row 0 at the bottom of the image, as in FITS.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Pixel values, ADU.
    pub data: Array2<f32>,
    /// Per-pixel variance, ADU^2, when known.
    pub variance: Option<Array2<f32>>,
    /// Per-pixel mask bits (see [`mask`]).
    pub mask: Array2<u8>,
    /// Header as read (or as will be written).
    pub header: Header,
    /// Provenance: every stage that produced this frame, oldest first.
    pub history: Vec<HistoryRecord>,
}

impl Frame {
    /// A frame with the given data, no variance, an empty mask and no history.
    pub fn new(data: Array2<f32>, header: Header) -> Self {
        let mask = Array2::zeros(data.raw_dim());
        Frame {
            data,
            variance: None,
            mask,
            header,
            history: Vec::new(),
        }
    }

    /// Image shape as (ny, nx).
    pub fn shape(&self) -> (usize, usize) {
        let s = self.data.shape();
        (s[0], s[1])
    }

    /// Append a provenance record (builder style).
    pub fn with_history(mut self, stage: &str, detail: impl Into<String>) -> Self {
        self.history.push(HistoryRecord::new(stage, detail));
        self
    }

    /// Rows `[r0, r1)` of this frame as a new frame (row r0 becomes row 0), with a history
    /// record. Pair with [`crate::Profile::cropped_rows`] so that geometry follows.
    pub fn crop_rows(&self, r0: usize, r1: usize) -> Frame {
        let (ny, _) = self.shape();
        let (r0, r1) = (r0.min(ny), r1.min(ny).max(r0.min(ny)));
        let sl = ndarray::s![r0..r1, ..];
        Frame {
            data: self.data.slice(sl).to_owned(),
            variance: self.variance.as_ref().map(|v| v.slice(sl).to_owned()),
            mask: self.mask.slice(sl).to_owned(),
            header: self.header.clone(),
            history: self.history.clone(),
        }
        .with_history(
            "crop",
            format!("rows [{r0}, {r1}) of the detector; row {r0} is row 0 here"),
        )
    }

    /// The file this frame came from (may be empty).
    pub fn path(&self) -> &std::path::Path {
        &self.header.path
    }
}

/// How many pixel values are not finite (NaN, +-inf), and the smallest and largest finite
/// value (`+inf` and `-inf` when there is none): what the reduction checks of every frame
/// it reads. The night's frames get it from their conversion pass
/// ([`crate::fits::read_frame_rows_with_summary`]), other arrays from [`PixelSummary::of`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSummary {
    /// Values that are NaN or infinite.
    pub non_finite: usize,
    /// Smallest finite value.
    pub min: f32,
    /// Largest finite value.
    pub max: f32,
}

impl PixelSummary {
    /// The summary of `values` (compiled for AVX2 when the CPU has it; the same numbers
    /// either way).
    pub fn of(values: &[f32]) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2 (checked just above).
                #[allow(unsafe_code)]
                return unsafe { summary_avx2(values) };
            }
        }
        let mut l = SummaryLanes::new();
        l.add(values);
        l.finish()
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn summary_avx2(values: &[f32]) -> PixelSummary {
    let mut l = SummaryLanes::new();
    l.add(values);
    l.finish()
}

/// The running [`PixelSummary`] of values added slice by slice, in lanes of 16 (vector
/// code; a value's lane is its index mod 16 within its slice, which changes nothing:
/// counts, minima and maxima do not depend on the order).
pub(crate) struct SummaryLanes {
    bad: [u32; SummaryLanes::L],
    lo: [f32; SummaryLanes::L],
    hi: [f32; SummaryLanes::L],
    /// Values of slices' remainders (not a multiple of 16).
    rest: PixelSummary,
}

impl SummaryLanes {
    const L: usize = 16;

    pub(crate) fn new() -> Self {
        SummaryLanes {
            bad: [0; Self::L],
            lo: [f32::INFINITY; Self::L],
            hi: [f32::NEG_INFINITY; Self::L],
            rest: PixelSummary {
                non_finite: 0,
                min: f32::INFINITY,
                max: f32::NEG_INFINITY,
            },
        }
    }

    #[inline(always)]
    pub(crate) fn add(&mut self, values: &[f32]) {
        const L: usize = SummaryLanes::L;
        let mut c = values.chunks_exact(L);
        for ch in &mut c {
            for i in 0..L {
                let v = ch[i];
                // |v| < inf is false for NaN and +-inf.
                let fin = v.abs() < f32::INFINITY;
                self.bad[i] += u32::from(!fin);
                let w = if fin { v } else { self.lo[i] };
                self.lo[i] = if w < self.lo[i] { w } else { self.lo[i] };
                let w = if fin { v } else { self.hi[i] };
                self.hi[i] = if w > self.hi[i] { w } else { self.hi[i] };
            }
        }
        for &v in c.remainder() {
            if v.is_finite() {
                self.rest.min = self.rest.min.min(v);
                self.rest.max = self.rest.max.max(v);
            } else {
                self.rest.non_finite += 1;
            }
        }
    }

    pub(crate) fn finish(self) -> PixelSummary {
        PixelSummary {
            non_finite: self.rest.non_finite + self.bad.iter().map(|&b| b as usize).sum::<usize>(),
            min: self.lo.iter().copied().fold(self.rest.min, f32::min),
            max: self.hi.iter().copied().fold(self.rest.max, f32::max),
        }
    }
}
