//! Frame classification from the header alone. STUB: being implemented.
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::header::Header;
use crate::profile::Profile;

/// What the header says about one polarimetric science frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScienceInfo {
    /// File.
    pub path: PathBuf,
    /// Target name (OBJECT, or OBS TARG NAME when OBJECT is the standard alias).
    pub object: String,
    /// Template start (identifies the sequence together with the object).
    pub tpl_start: String,
    /// Sequence identifier: `"{object}@{tpl_start}"`.
    pub sequence: String,
    /// Rotator position angle, degrees (ADA POSANG).
    pub posang_deg: f64,
    /// Cumulative jitter offset (dx, dy), pixels (SEQ CUMOFFSETX/Y).
    pub offset_px: [f64; 2],
    /// Filter name.
    pub filter: String,
    /// Optical element that identified the Wollaston.
    pub wollaston: String,
    /// DIT, seconds.
    pub dit_s: f64,
    /// NDIT (reads averaged).
    pub ndit: u32,
    /// 1-based exposure number in the template, when present.
    pub expno: Option<u32>,
    /// Number of exposures in the template, when present.
    pub nexp: Option<u32>,
    /// MJD-OBS when present.
    pub mjd: Option<f64>,
    /// Pixel scale, arcsec/px (INS PIXSCALE, else the profile's).
    pub pixscale_arcsec: f64,
}

/// The verdict on one header.
#[derive(Debug, Clone, PartialEq)]
pub enum Classification {
    /// A polarimetric science frame.
    Science(Box<ScienceInfo>),
    /// Anything else, with the reason in words naming the keyword and value.
    Rejected {
        /// Why the frame is not polarimetric science.
        reason: String,
    },
}

/// Classify one header.
pub fn classify(header: &Header, profile: &Profile) -> Classification {
    let _ = (header, profile);
    unimplemented!()
}
