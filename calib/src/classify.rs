//! Frame classification from the header alone.
//!
//! A frame is polarimetric science when, in this order (the first failing test gives the
//! rejection reason, naming the keyword and its value):
//! 0. the frame is not a sofipol product (no [`PRODUCT_KEYWORD`] card);
//! 1. `INSTRUME` equals the profile's instrument;
//! 2. the template is the polarimetry template (`TPL ID`) **or** `DPR TECH` contains the
//!    polarimetry technique;
//! 3. `DPR TYPE`, when present, is one of the profile's science types (OBJECT, STD: a
//!    polarimetric standard is science for sofipol even though ESO files it under
//!    `DPR CATG = 'CALIB'`); when `DPR TYPE` is absent, `DPR CATG` must be `SCIENCE` or
//!    absent (simulated and older headers may lack both);
//! 4. some `INS OPTIi ID` (i = 1..=opti_max) contains the Wollaston marker;
//! 5. every keyword a reduction needs is present and valid: position angle, cumulative
//!    offsets x and y, template start, object name (OBJECT, or OBS TARG NAME when OBJECT
//!    is the standard alias or absent), filter, DIT (`DET DIT`, else EXPTIME) and NDIT.
//!    NDIT is required (no default of 1): the noise model depends on it, so a missing
//!    NDIT is reported rather than guessed.
//!
//! Optional: TPL EXPNO / NEXP, MJD-OBS, RA and DEC (deg), INS PIXSCALE (else the profile's
//! pixel scale);
//! present but malformed optional keywords are also rejected, never silently ignored.
//! String comparisons ignore case and surrounding blanks. Every keyword name comes from
//! the [`Profile`].
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::header::{Header, HeaderValue};
use crate::profile::Profile;

/// Header keyword sofipol writes into every image product it derives from a raw frame
/// (value: the product kind, e.g. `'SKYSUB'` for `--save-intermediate`). A frame carrying
/// it is never classified as a raw science frame, so products saved inside a night folder
/// are skipped (and reported) by the next run instead of being reduced as raw data.
pub const PRODUCT_KEYWORD: &str = "SOFIPROD";

/// `DPR CATG` value of science frames (an ESO data-product convention, not instrument
/// specific).
pub const SCIENCE_CATEGORY: &str = "SCIENCE";

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
    /// Right ascension of the pointing (profile keyword `ra`), deg in [0, 360), when present.
    #[serde(default)]
    pub ra_deg: Option<f64>,
    /// Declination of the pointing (profile keyword `dec`), deg in [-90, 90], when present.
    #[serde(default)]
    pub dec_deg: Option<f64>,
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

impl Classification {
    /// The science information, if this is a science frame.
    pub fn science(&self) -> Option<&ScienceInfo> {
        match self {
            Classification::Science(s) => Some(s),
            Classification::Rejected { .. } => None,
        }
    }

    /// The rejection reason, if this is not a science frame.
    pub fn reason(&self) -> Option<&str> {
        match self {
            Classification::Science(_) => None,
            Classification::Rejected { reason } => Some(reason),
        }
    }

    /// Whether this is a polarimetric science frame.
    pub fn is_science(&self) -> bool {
        matches!(self, Classification::Science(_))
    }
}

/// Read the header of a file ([`crate::fits::read_header`]) and classify it.
/// Unreadable files are errors, not rejections.
pub fn classify_file(path: &Path, profile: &Profile) -> Result<Classification> {
    let header = crate::fits::read_header(path)?;
    Ok(classify(&header, profile))
}

/// Classify one header (see the module documentation for the rules).
///
/// ```
/// use sofipol_calib::{classify::classify, Header, Profile};
/// let mut h = Header::new("x.fits");
/// h.set("INSTRUME", "ISAAC");
/// let c = classify(&h, &Profile::sofi());
/// assert_eq!(c.reason(), Some("not SOFI: INSTRUME = 'ISAAC'"));
/// ```
pub fn classify(header: &Header, profile: &Profile) -> Classification {
    match science_info(header, profile) {
        Ok(info) => Classification::Science(Box::new(info)),
        Err(e) => {
            let mut reason = e.to_string();
            // Keywords of a primary header without image are not the image's: say where
            // they were looked for.
            if header.image_hdu > 0 && reason.contains("missing keyword") {
                reason.push_str(&format!(
                    " in the header of HDU {}, the image extension (the primary HDU holds no image; \
                     its keywords are not read)",
                    header.image_hdu
                ));
            }
            Classification::Rejected { reason }
        }
    }
}

/// The template a header says it belongs to, `object@tpl_start` as
/// [`ScienceInfo::sequence`], read leniently: only the object (or the target name behind
/// the standard alias) and the template start are needed, so a frame refused for another
/// keyword (a bad MJD-OBS, an instrument setting) can still be told to belong to its
/// template. `None` when either is missing.
pub fn template_id(h: &Header, p: &Profile) -> Option<String> {
    let k = &p.keywords;
    let tpl_start = text(h, &k.tpl_start)?;
    let object = match text(h, &k.object) {
        Some(o) if !same(&o, &p.matching.object_std_alias) => o,
        _ => text(h, &k.targ_name)?,
    };
    Some(format!("{object}@{tpl_start}"))
}

fn same(a: &str, b: &str) -> bool {
    a.trim().eq_ignore_ascii_case(b.trim())
}

fn contains_ci(haystack: &str, needle: &str) -> bool {
    haystack
        .to_ascii_uppercase()
        .contains(&needle.trim().to_ascii_uppercase())
}

/// A string keyword's value (trimmed), `None` when absent or blank.
fn text(h: &Header, key: &str) -> Option<String> {
    match h.get(key)? {
        HeaderValue::Str(s) => Some(s.trim().to_string()).filter(|s| !s.is_empty()),
        v => Some(v.to_string()),
    }
}

/// `KEY = 'value'` or `KEY absent`, for messages.
fn shown(h: &Header, key: &str) -> String {
    match h.get(key) {
        Some(v) => format!("{key} = {v}"),
        None => format!("{key} absent"),
    }
}

/// A rejection with this reason.
fn reject(reason: String) -> Error {
    Error::Rejected { reason }
}

/// Turn a header error into a rejection (its reason without the file name: the caller knows it).
fn reason_of(e: Error) -> Error {
    reject(match e {
        Error::MissingKeyword { keyword, .. } => format!("missing keyword {keyword}"),
        Error::BadKeyword {
            keyword, value, reason, ..
        } => format!("bad keyword {keyword} = {value}: {reason}"),
        other => other.to_string(),
    })
}

fn required_text(h: &Header, key: &str) -> Result<String> {
    text(h, key).ok_or_else(|| {
        reject(match h.get(key) {
            Some(v) => format!("empty keyword {key} = {v}"),
            None => format!("missing keyword {key}"),
        })
    })
}

fn finite(h: &Header, key: &str) -> Result<f64> {
    h.get_f64(key).map_err(reason_of)
}

/// Optional positive integer that fits in u32.
fn opt_count(h: &Header, key: &str) -> Result<Option<u32>> {
    if !h.contains(key) {
        return Ok(None);
    }
    let v = h.get_i64(key).map_err(reason_of)?;
    u32::try_from(v)
        .ok()
        .filter(|&n| n >= 1)
        .map(Some)
        .ok_or_else(|| reject(format!("bad keyword {key} = {v}: expected an integer >= 1")))
}

/// Step 4 of [`classify`]: the Wollaston's OPTIi.ID value, first match of OPTI1..OPTImax.
fn wollaston_in_beam(h: &Header, p: &Profile) -> Result<String> {
    let (k, m) = (&p.keywords, &p.matching);
    let mut seen = Vec::new();
    let mut wollaston = None;
    for i in 1..=k.opti_max {
        let key = p.opti_key(i);
        if let Some(v) = text(h, &key) {
            if contains_ci(&v, &m.wollaston_contains) {
                wollaston = Some(v);
                break;
            }
            seen.push(shown(h, &key));
        }
    }
    wollaston.ok_or_else(|| {
        let found = if seen.is_empty() {
            "none present".to_string()
        } else {
            seen.join(", ")
        };
        reject(format!(
            "no Wollaston in {}1..{} ID (looking for '{}'; {found})",
            k.opti_prefix, k.opti_max, m.wollaston_contains
        ))
    })
}

fn science_info(h: &Header, p: &Profile) -> Result<ScienceInfo> {
    let k = &p.keywords;
    let m = &p.matching;

    // 0. Not one of sofipol's own products.
    if h.contains(PRODUCT_KEYWORD) {
        return Err(reject(format!(
            "a sofipol product ({}), not a raw frame: skipped",
            shown(h, PRODUCT_KEYWORD)
        )));
    }

    // 1. Instrument.
    match text(h, &k.instrument) {
        Some(i) if same(&i, &m.instrument) => {}
        Some(_) => return Err(reject(format!("not {}: {}", m.instrument, shown(h, &k.instrument)))),
        None => {
            return Err(reject(format!(
                "not {}: missing keyword {}",
                m.instrument, k.instrument
            )))
        }
    }

    // 2. Polarimetric template or technique.
    let by_template = text(h, &k.tpl_id).is_some_and(|t| same(&t, &m.polarimetry_template));
    let by_tech = text(h, &k.dpr_tech).is_some_and(|t| contains_ci(&t, &m.polarimetry_tech));
    if !(by_template || by_tech) {
        let mut reason = format!("not polarimetric: {}, {}", shown(h, &k.tpl_id), shown(h, &k.dpr_tech));
        if h.contains(&k.dpr_type) {
            reason.push_str(&format!(" ({})", shown(h, &k.dpr_type)));
        }
        return Err(reject(reason));
    }

    // 3. Science, not calibration.
    match text(h, &k.dpr_type) {
        Some(t) => {
            if !m.science_types.iter().any(|s| same(s, &t)) {
                return Err(reject(format!(
                    "calibration frame: {} (science types: {})",
                    shown(h, &k.dpr_type),
                    m.science_types.join(", ")
                )));
            }
        }
        None => {
            if let Some(c) = text(h, &k.dpr_catg) {
                if !same(&c, SCIENCE_CATEGORY) {
                    return Err(reject(format!(
                        "calibration frame: {} ({} absent)",
                        shown(h, &k.dpr_catg),
                        k.dpr_type
                    )));
                }
            }
        }
    }

    // 4. Wollaston in the beam.
    let wollaston = wollaston_in_beam(h, p)?;

    // 5. Everything a reduction needs.
    let posang_deg = finite(h, &k.posang)?;
    let offset_px = [finite(h, &k.offset_x)?, finite(h, &k.offset_y)?];
    let tpl_start = required_text(h, &k.tpl_start)?;
    let object = match text(h, &k.object) {
        Some(o) if !same(&o, &m.object_std_alias) => o,
        Some(o) => text(h, &k.targ_name).ok_or_else(|| {
            reject(format!(
                "{} = '{o}' (standard alias) but missing keyword {}",
                k.object, k.targ_name
            ))
        })?,
        None => text(h, &k.targ_name)
            .ok_or_else(|| reject(format!("missing keyword {} (and {})", k.object, k.targ_name)))?,
    };
    let filter = required_text(h, &k.filter)?;
    let (dit_key, dit_s) = if h.contains(&k.dit) {
        (&k.dit, finite(h, &k.dit)?)
    } else if h.contains(&k.exptime) {
        (&k.exptime, finite(h, &k.exptime)?)
    } else {
        return Err(reject(format!("missing keyword {} (and {})", k.dit, k.exptime)));
    };
    if dit_s <= 0.0 {
        return Err(reject(format!(
            "bad keyword {dit_key} = {dit_s}: integration time must be > 0 s"
        )));
    }
    let ndit = match h.get_i64(&k.ndit).map_err(reason_of)? {
        n if n >= 1 && n <= u32::MAX as i64 => n as u32,
        n => {
            return Err(reject(format!(
                "bad keyword {} = {n}: expected an integer >= 1",
                k.ndit
            )))
        }
    };
    let expno = opt_count(h, &k.tpl_expno)?;
    let nexp = opt_count(h, &k.tpl_nexp)?;
    let mjd = h.opt_f64(&k.mjd_obs).map_err(reason_of)?;
    let ra_deg = opt_in_range(h, &k.ra, 0.0..=360.0, "right ascension must be in [0, 360] deg")?.map(|a| a % 360.0);
    let dec_deg = opt_in_range(h, &k.dec, -90.0..=90.0, "declination must be in [-90, 90] deg")?;
    let pixscale_arcsec = match h.opt_f64(&k.pixscale).map_err(reason_of)? {
        Some(s) if s > 0.0 => s,
        Some(s) => {
            return Err(reject(format!(
                "bad keyword {} = {s}: pixel scale must be > 0",
                k.pixscale
            )))
        }
        None => p.geometry.pixscale_arcsec,
    };

    Ok(ScienceInfo {
        path: h.path.clone(),
        sequence: format!("{object}@{tpl_start}"),
        object,
        tpl_start,
        posang_deg,
        offset_px,
        filter,
        wollaston,
        dit_s,
        ndit,
        expno,
        nexp,
        mjd,
        ra_deg,
        dec_deg,
        pixscale_arcsec,
    })
}

/// An optional number that, when present, must lie in `range` (else the frame is rejected
/// naming the keyword and its value).
fn opt_in_range(h: &Header, key: &str, range: std::ops::RangeInclusive<f64>, why: &str) -> Result<Option<f64>> {
    match h.opt_f64(key).map_err(reason_of)? {
        Some(v) if !range.contains(&v) => Err(reject(format!("bad keyword {key} = {v}: {why}"))),
        v => Ok(v),
    }
}
