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
    /// At or above the profile's `nonlinear_warn_adu` (usable with care).
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

mod summary;

pub use summary::PixelSummary;
pub(crate) use summary::SummaryLanes;
