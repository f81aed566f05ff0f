//! Grouping classified science frames into target sequences: one sequence per
//! (object, TPL START), and within it one group of dithers per rotator orientation.
use std::collections::BTreeMap;

use serde::Serialize;
use sofipol_calib::classify::ScienceInfo;
use sofipol_calib::Profile;

use crate::catalog::{Flag, FlagCode};

/// Dithers whose header offsets all lie within this distance (pixels) of the first are
/// "at one position" ([`Sequence::stationary_orientations`]); real jitter steps are tens
/// of pixels (SOFI: 86.8).
pub const STATIONARY_PX: f64 = 2.0;

/// The dithers taken at one rotator position angle.
#[derive(Debug, Clone, Serialize)]
pub struct Orientation {
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle phi = s POSANG + theta0, deg.
    pub analyzer_deg: f64,
    /// Exposures in exposure order (EXPNO, then MJD, then file name).
    pub exposures: Vec<ScienceInfo>,
}

/// One target sequence.
#[derive(Debug, Clone, Serialize)]
pub struct Sequence {
    /// `object@tpl_start`.
    pub id: String,
    /// Object name.
    pub object: String,
    /// TPL START.
    pub tpl_start: String,
    /// Filter (of the first exposure; a mixture is reported by [`Sequence::problems`]).
    pub filter: String,
    /// Orientations in increasing POSANG.
    pub orientations: Vec<Orientation>,
}

impl Sequence {
    /// All files of the sequence.
    pub fn files(&self) -> Vec<String> {
        self.orientations
            .iter()
            .flat_map(|o| o.exposures.iter().map(|e| e.path.display().to_string()))
            .collect()
    }

    /// Every exposure of the sequence.
    fn exposures(&self) -> impl Iterator<Item = &ScienceInfo> {
        self.orientations.iter().flat_map(|o| o.exposures.iter())
    }

    /// The integration time every frame shares (`DET DIT`, else `EXPTIME`), s; `None` when
    /// the frames' times differ (beyond 1e-9 relative) or there is no frame.
    pub fn common_dit_s(&self) -> Option<f64> {
        let mut dits = self.exposures().map(|e| e.dit_s);
        let first = dits.next()?;
        dits.all(|d| (d - first).abs() <= 1e-9 * first.abs())
            .then_some(first)
            .filter(|d| d.is_finite() && *d > 0.0)
    }

    /// Mean MJD-OBS of the frames that have one (`None` when none has).
    pub fn mean_mjd(&self) -> Option<f64> {
        mean(self.exposures().filter_map(|e| e.mjd))
    }

    /// Mean pointing (RA, Dec) in degrees over the frames that have both: Dec the
    /// arithmetic mean, RA the circular mean (frames at 359.99 and 0.01 deg give 0, not
    /// 180) in [0, 360). `None` when no frame has both.
    pub fn mean_ra_dec_deg(&self) -> Option<(f64, f64)> {
        let pts: Vec<(f64, f64)> = self.exposures().filter_map(|e| e.ra_deg.zip(e.dec_deg)).collect();
        let dec = mean(pts.iter().map(|p| p.1))?;
        let (s, c) = pts.iter().fold((0.0, 0.0), |(s, c), p| {
            let a = p.0.to_radians();
            (s + a.sin(), c + a.cos())
        });
        Some((s.atan2(c).to_degrees().rem_euclid(360.0), dec))
    }

    /// POSANG of the orientations whose dithers all sit at one position (header offsets
    /// within [`STATIONARY_PX`] of each other): the sky median of such dithers contains
    /// the star itself, and the star stays put on the detector like a defect.
    pub fn stationary_orientations(&self) -> Vec<f64> {
        self.orientations
            .iter()
            .filter(|o| {
                o.exposures.len() >= 2
                    && o.exposures.iter().all(|e| {
                        let d = &o.exposures[0].offset_px;
                        (e.offset_px[0] - d[0]).hypot(e.offset_px[1] - d[1]) < STATIONARY_PX
                    })
            })
            .map(|o| o.posang_deg)
            .collect()
    }

    /// Things that degrade the sequence, in words (empty when complete): an orientation
    /// with fewer than 2 dithers, unequal dither counts, fewer exposures than TPL NEXP,
    /// mixed filters, dithers all at one position.
    pub fn problems(&self) -> Vec<Flag> {
        let mut out = Vec::new();
        for pa in self.stationary_orientations() {
            out.push(Flag::with_detail(
                FlagCode::StationaryDithers,
                format!("{pa} deg at one position (SEQ CUMOFFSET equal): the sky median contains the star"),
            ));
        }
        let counts: Vec<usize> = self.orientations.iter().map(|o| o.exposures.len()).collect();
        for o in &self.orientations {
            if o.exposures.len() < 2 {
                out.push(Flag::with_detail(
                    FlagCode::OneDither,
                    format!(
                        "{} dither at POSANG {} deg: cannot sky-subtract from the data itself",
                        o.exposures.len(),
                        o.posang_deg
                    ),
                ));
            }
        }
        if counts.iter().any(|&c| c != counts[0]) {
            out.push(Flag::with_detail(FlagCode::UnequalDithers, format!("{counts:?}")));
        }
        let total: usize = counts.iter().sum();
        if let Some(nexp) = self.orientations.iter().flat_map(|o| &o.exposures).find_map(|e| e.nexp) {
            if (total as u32) < nexp {
                out.push(Flag::with_detail(
                    FlagCode::MissingExposures,
                    format!("{total} of {nexp}"),
                ));
            }
        }
        let mjds: Vec<f64> = self.exposures().filter_map(|e| e.mjd).collect();
        let lo = mjds.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = mjds.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if hi - lo > MAX_TEMPLATE_DAYS {
            out.push(Flag::with_detail(
                FlagCode::MjdSpread,
                format!(
                    "{:.1} days ({} to {}): one template is observed within hours, \
                     so some frames' dates are wrong",
                    hi - lo,
                    sofipol_calib::text::short_number(lo),
                    sofipol_calib::text::short_number(hi)
                ),
            ));
        }
        let filters: std::collections::BTreeSet<&str> = self
            .orientations
            .iter()
            .flat_map(|o| o.exposures.iter().map(|e| e.filter.as_str()))
            .collect();
        if filters.len() > 1 {
            out.push(Flag::with_detail(FlagCode::MixedFilters, format!("{filters:?}")));
        }
        out
    }
}

/// The longest a template's frames may span in MJD-OBS, days: a polarimetric template
/// takes well under an hour; frames further apart carry wrong dates.
pub const MAX_TEMPLATE_DAYS: f64 = 1.0;

/// Arithmetic mean (`None` of nothing).
fn mean(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (n, sum) = v.fold((0usize, 0.0), |(n, s), x| (n + 1, s + x));
    (n > 0).then(|| sum / n as f64)
}

/// Group science frames into sequences, sorted by (TPL START, object) so that the order,
/// and everything computed from it, does not depend on the order files were found in.
/// Orientations are equal when their POSANG agree to 0.01 deg.
pub fn group(infos: Vec<ScienceInfo>, profile: &Profile) -> Vec<Sequence> {
    let mut by_seq: BTreeMap<(String, String), Vec<ScienceInfo>> = BTreeMap::new();
    for i in infos {
        by_seq
            .entry((i.tpl_start.clone(), i.object.clone()))
            .or_default()
            .push(i);
    }
    by_seq
        .into_iter()
        .map(|((tpl_start, object), frames)| {
            let mut by_pa: BTreeMap<i64, Vec<ScienceInfo>> = BTreeMap::new();
            for f in frames {
                by_pa.entry((f.posang_deg * 100.0).round() as i64).or_default().push(f);
            }
            let orientations: Vec<Orientation> = by_pa
                .into_values()
                .map(|mut ex| {
                    ex.sort_by(|a, b| {
                        a.expno
                            .cmp(&b.expno)
                            .then(a.mjd.unwrap_or(0.0).total_cmp(&b.mjd.unwrap_or(0.0)))
                            .then(a.path.cmp(&b.path))
                    });
                    let posang = ex[0].posang_deg;
                    Orientation {
                        posang_deg: posang,
                        analyzer_deg: profile.angles.analyzer_angle_deg(posang),
                        exposures: ex,
                    }
                })
                .collect();
            let filter = orientations[0].exposures[0].filter.clone();
            Sequence {
                id: format!("{object}@{tpl_start}"),
                object,
                tpl_start,
                filter,
                orientations,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(obj: &str, tpl: &str, pa: f64, expno: u32) -> ScienceInfo {
        ScienceInfo {
            path: format!("{obj}_{pa}_{expno}.fits").into(),
            object: obj.into(),
            tpl_start: tpl.into(),
            sequence: format!("{obj}@{tpl}"),
            posang_deg: pa,
            offset_px: [86.8 * expno as f64, 0.0],
            filter: "Ks".into(),
            wollaston: "WOLLASTON".into(),
            dit_s: 10.0,
            ndit: 6,
            expno: Some(expno),
            nexp: Some(10),
            mjd: None,
            ra_deg: None,
            dec_deg: None,
            pixscale_arcsec: 0.288,
        }
    }

    #[test]
    fn frames_dated_far_apart_are_a_problem_naming_the_span() {
        let mk = |mjds: &[f64]| {
            let v: Vec<ScienceInfo> = mjds
                .iter()
                .enumerate()
                .map(|(k, &m)| {
                    let mut i = info(
                        "Dated",
                        "1999-03-03T03:00:00",
                        if k % 2 == 0 { 0.0 } else { 45.0 },
                        k as u32 + 1,
                    );
                    i.nexp = Some(mjds.len() as u32);
                    i.mjd = Some(m);
                    i
                })
                .collect();
            group(v, &sofipol_calib::Profile::sofi()).remove(0).problems()
        };
        // Within a template's hour: no problem.
        assert!(mk(&[51240.04, 51240.05, 51240.06, 51240.07]).is_empty());
        // 1970, 1999 and 2100 in one template.
        let p = crate::catalog::flags::join(&mk(&[40587.0, 51240.04, 51240.05, 88069.0]), "; ");
        assert!(
            p.contains("MJD-OBS") && p.contains("47482.0 days") && p.contains("40587"),
            "{p}"
        );
    }

    #[test]
    fn all_dithers_at_one_position_are_detected_from_the_headers() {
        // Regression: a sequence without offsets was reduced with the star in its own sky
        // median and no diagnosis.
        let mut v = Vec::new();
        for k in 1..=6 {
            let mut i = info("Still", "1999-03-03T03:00:00", if k <= 3 { 0.0 } else { 45.0 }, k);
            i.nexp = Some(6);
            i.offset_px = if k <= 3 {
                [0.3 * k as f64, 0.0]
            } else {
                [86.8 * k as f64, 0.0]
            };
            v.push(i);
        }
        let seqs = group(v, &Profile::sofi());
        assert_eq!(seqs[0].stationary_orientations(), vec![0.0]);
        let p = seqs[0].problems();
        assert!(
            p.len() == 1 && p[0].to_string().contains("one position") && p[0].to_string().contains("POSANG 0"),
            "{p:?}"
        );
    }

    #[test]
    fn groups_by_template_and_orientation_in_a_stable_order() {
        let mut v = Vec::new();
        for k in (1..=10).rev() {
            v.push(info(
                "HK Tau",
                "1999-03-03T02:10:41",
                if k <= 5 { 0.0 } else { 45.0 },
                k,
            ));
        }
        for k in 1..=9 {
            v.push(info(
                "GG Tau",
                "1999-03-03T01:00:00",
                if k <= 5 { 0.0 } else { 45.0 },
                k,
            ));
        }
        let seqs = group(v, &Profile::sofi());
        assert_eq!(seqs.len(), 2);
        assert_eq!(seqs[0].object, "GG Tau");
        assert_eq!(seqs[1].orientations.len(), 2);
        assert_eq!(seqs[1].orientations[1].posang_deg, 45.0);
        let e: Vec<u32> = seqs[1].orientations[0]
            .exposures
            .iter()
            .map(|e| e.expno.unwrap())
            .collect();
        assert_eq!(e, vec![1, 2, 3, 4, 5]);
        assert!(seqs[1].problems().is_empty());
        let p = crate::catalog::flags::join(&seqs[0].problems(), "; ");
        assert!(p.contains("unequal") && p.contains("9 of 10"), "{p}");
    }
}
