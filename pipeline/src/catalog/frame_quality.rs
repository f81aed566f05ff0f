//! Per-frame observing conditions, as ORAC-DR's and ESO's quality control give them: the
//! seeing, sky level, airmass and transparency of every frame a target or standard was
//! reduced from (a TARGET's and a STANDARD's `frame_quality`, docs/catalog-schema.md),
//! and the night's medians and outliers that the night log and the report show.
use serde::{Deserialize, Serialize};

/// One frame's conditions. Numbers the frame does not give (no `MJD-OBS`, no fit of the
/// primary star) are absent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameQuality {
    /// The frame, as in `input_files`.
    pub file: String,
    /// Rotator position angle of the frame's orientation, deg.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub posang_deg: f64,
    /// Index of the frame among its orientation's dithers, 1-based, in exposure order.
    pub dither: usize,
    /// `MJD-OBS` of the frame, d.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub mjd: Option<f64>,
    /// Airmass: the mean of the header's `TEL AIRM START` and `END` (START alone when END
    /// is absent).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub airmass: Option<f64>,
    /// Seeing: the FWHM of the PSF (Moffat, beta free) fitted to the primary star in this
    /// frame, arcsec (docs/products.md, "Frame quality").
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub fwhm_arcsec: Option<f64>,
    /// Sky level the sky stage measured in the frame (median of its strip rows), ADU.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sky_adu: Option<f64>,
    /// The primary star's o+e flux in this frame over the median of that flux over the
    /// sequence's frames (1: as usual; a passing cloud lowers it). Absent when the
    /// primary's photometry in this frame was rejected (cosmic ray, saturation...).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub transparency: Option<f64>,
}

/// A frame is an outlier of the night when its seeing is worse (larger) than the night's
/// median by more than this many robust standard deviations, or its transparency lower.
pub const OUTLIER_SIGMA: f64 = 3.0;
/// The smallest robust standard deviation of the seeing taken, as a fraction of the
/// median: on a night of steady seeing a frame 5 % worse is not an outlier.
pub const MIN_SEEING_SIGMA_FRAC: f64 = 0.05;
/// The smallest robust standard deviation of the transparency taken (a fraction).
pub const MIN_TRANSPARENCY_SIGMA: f64 = 0.02;

/// The night's medians over every frame that has the value.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct NightMedians {
    /// Median airmass.
    pub airmass: Option<f64>,
    /// Median seeing, arcsec.
    pub fwhm_arcsec: Option<f64>,
    /// Median sky level, ADU.
    pub sky_adu: Option<f64>,
    /// Median transparency.
    pub transparency: Option<f64>,
    /// Seeing above this is an outlier, arcsec.
    pub fwhm_limit_arcsec: Option<f64>,
    /// Transparency below this is an outlier.
    pub transparency_limit: Option<f64>,
}

/// Why a frame is an outlier of the night (empty when it is not).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Outlier {
    /// Seeing worse than [`NightMedians::fwhm_limit_arcsec`].
    pub seeing: bool,
    /// Transparency below [`NightMedians::transparency_limit`].
    pub transparency: bool,
}

impl Outlier {
    /// Whether either is set.
    pub fn any(self) -> bool {
        self.seeing || self.transparency
    }

    /// "seeing", "transparency", "seeing, transparency" or "".
    pub fn words(self) -> String {
        [(self.seeing, "seeing"), (self.transparency, "transparency")]
            .iter()
            .filter(|(on, _)| *on)
            .map(|(_, w)| *w)
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// The median of the finite values, `None` when there is none.
pub fn median(values: impl Iterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// 1.4826 x the median absolute deviation of the finite values from `centre`.
fn robust_sigma(values: impl Iterator<Item = f64>, centre: f64) -> Option<f64> {
    median(values.map(|x| (x - centre).abs())).map(|m| 1.4826 * m)
}

impl NightMedians {
    /// The medians and outlier limits of `frames` (every frame of the night).
    pub fn of<'a>(frames: impl Iterator<Item = &'a FrameQuality> + Clone) -> NightMedians {
        let get = |f: fn(&FrameQuality) -> Option<f64>| frames.clone().filter_map(f);
        let fwhm = median(get(|q| q.fwhm_arcsec));
        let transparency = median(get(|q| q.transparency));
        let fwhm_limit = fwhm.map(|m| {
            let s = robust_sigma(get(|q| q.fwhm_arcsec), m).unwrap_or(0.0);
            m + OUTLIER_SIGMA * s.max(MIN_SEEING_SIGMA_FRAC * m)
        });
        let transparency_limit = transparency.map(|m| {
            let s = robust_sigma(get(|q| q.transparency), m).unwrap_or(0.0);
            m - OUTLIER_SIGMA * s.max(MIN_TRANSPARENCY_SIGMA)
        });
        NightMedians {
            airmass: median(get(|q| q.airmass)),
            fwhm_arcsec: fwhm,
            sky_adu: median(get(|q| q.sky_adu)),
            transparency,
            fwhm_limit_arcsec: fwhm_limit,
            transparency_limit,
        }
    }

    /// Whether `q` is an outlier of the night.
    pub fn outlier(&self, q: &FrameQuality) -> Outlier {
        Outlier {
            seeing: matches!((q.fwhm_arcsec, self.fwhm_limit_arcsec), (Some(v), Some(l)) if v > l),
            transparency: matches!((q.transparency, self.transparency_limit), (Some(v), Some(l)) if v < l),
        }
    }
}

/// One row of the night's quality table: the frame, whose it is and its conditions.
#[derive(Debug, Clone, Copy)]
pub struct NightFrame<'a> {
    /// The target's object or the standard's name.
    pub source: &'a str,
    /// Whether it is a standard star's frame.
    pub standard: bool,
    /// Its conditions.
    pub quality: &'a FrameQuality,
}

/// Every frame of the night with a quality entry, targets' and standards', in time order
/// (`MJD-OBS`; frames without one last, by file name).
pub fn night_frames(cat: &super::Catalog) -> Vec<NightFrame<'_>> {
    let mut rows: Vec<NightFrame> = cat
        .targets
        .iter()
        .flat_map(|t| {
            t.frame_quality.iter().flatten().map(|q| NightFrame {
                source: t.object.as_str(),
                standard: false,
                quality: q,
            })
        })
        .chain(cat.standards.iter().flat_map(|s| {
            s.frame_quality.iter().flatten().map(|q| NightFrame {
                source: s.name.as_str(),
                standard: true,
                quality: q,
            })
        }))
        .collect();
    rows.sort_by(|a, b| {
        let key = |r: &NightFrame| r.quality.mjd.filter(|m| m.is_finite()).unwrap_or(f64::INFINITY);
        key(a)
            .total_cmp(&key(b))
            .then_with(|| a.quality.file.cmp(&b.quality.file))
    });
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(fwhm: f64, t: f64) -> FrameQuality {
        FrameQuality {
            file: "f.fits".into(),
            posang_deg: 0.0,
            dither: 1,
            mjd: None,
            airmass: Some(1.2),
            fwhm_arcsec: Some(fwhm),
            sky_adu: Some(1000.0),
            transparency: Some(t),
        }
    }

    #[test]
    fn a_frame_far_worse_than_the_night_is_an_outlier_and_small_changes_are_not() {
        let mut frames: Vec<FrameQuality> = (0..20)
            .map(|i| frame(0.8 + 0.002 * i as f64, 1.0 - 0.001 * i as f64))
            .collect();
        frames.push(frame(1.3, 0.99));
        frames.push(frame(0.82, 0.7));
        let m = NightMedians::of(frames.iter());
        // The robust sigma of the seeing is below 5 % of the median: the floor holds.
        assert!((m.fwhm_limit_arcsec.unwrap() - (0.82 + 3.0 * 0.05 * 0.82)).abs() < 0.01);
        let marks: Vec<Outlier> = frames.iter().map(|q| m.outlier(q)).collect();
        assert_eq!(marks.iter().filter(|o| o.any()).count(), 2, "{marks:?}");
        assert!(marks[20].seeing && !marks[20].transparency);
        assert!(marks[21].transparency && !marks[21].seeing);
        assert_eq!(marks[21].words(), "transparency");
    }

    #[test]
    fn an_entry_without_the_optional_numbers_reads_and_writes_them_absent() {
        let q: FrameQuality =
            serde_json::from_str(r#"{"file": "a.fits", "posang_deg": 45.0, "dither": 2, "fwhm_arcsec": null}"#)
                .unwrap();
        assert!(q.fwhm_arcsec.unwrap().is_nan() && q.mjd.is_none());
        let back = serde_json::to_string(&q).unwrap();
        assert_eq!(
            back,
            r#"{"file":"a.fits","posang_deg":45.0,"dither":2,"fwhm_arcsec":null}"#
        );
    }
}
