//! Magnitudes from the night's photometric standards: a standard whose table entry gives a
//! magnitude in its filter (`mag`, `sigma_mag`: `--standards FILE`; no built-in entry has
//! one) gives a zero-point, the standards of a filter are combined into the filter's
//! zero-point, and every science component of that filter gets a magnitude.
//!
//! ```text
//! rate r = flux_adu / dit_s               ADU per second: the frames are NDIT-averaged
//! standard i:  ZP_i = m_i + 2.5 log10(r_i) + k X_i
//!              sigma_ZP_i^2 = sigma_m_i^2 + (2.5/ln 10 sigma_r_i / r_i)^2
//! filter:      ZP = sum w_i ZP_i / sum w_i,  w_i = 1/sigma_ZP_i^2
//!              sigma_ZP = sqrt(1 / sum w_i) x sqrt(k),  k = chi2 / (n - 1) when chi2 is
//!                         beyond its 99th percentile for n - 1 dof, else 1   (n >= 2)
//! component:   m = ZP - 2.5 log10(r) - k X,  sigma_m^2 = (2.5/ln 10 sigma_r / r)^2 + sigma_ZP^2
//! ```
//!
//! `flux_adu` is the mean o+e flux per dither (aperture-corrected: the total flux), X the
//! mean airmass of the sequence's frames (`frame_quality`), k the profile's
//! `photometry` extinction of the filter (default 0). The zero-point, its error, the
//! scatter of the standards and the standards used are recorded in the catalog's
//! `calibration.photometry`; a filter without a photometric standard gets no magnitudes and
//! a note that says why.
use sofipol_calib::profile::Photometry;

use crate::catalog::{Catalog, Status};

/// The catalog's record of the photometric calibration (typed in the catalog, filled here).
pub use crate::catalog::photometry::{lines, PhotometricCalibration, PhotometricStandard, ZeroPoint};

/// 2.5 / ln 10: d(mag) per relative flux error.
pub const MAG_PER_RELATIVE_FLUX: f64 = 2.5 / std::f64::consts::LN_10;

/// One standard's zero-point and error: `m + 2.5 log10(r) + k X` (X = 0 when `airmass` is
/// `None`), `sqrt(sigma_m^2 + (1.0857 sigma_r / r)^2)`.
pub fn standard_zero_point(
    mag: f64,
    sigma_mag: f64,
    rate: f64,
    sigma_rate: f64,
    k: f64,
    airmass: Option<f64>,
) -> (f64, f64) {
    let zp = mag + 2.5 * rate.log10() + k * airmass.unwrap_or(0.0);
    (zp, sigma_mag.hypot(MAG_PER_RELATIVE_FLUX * sigma_rate / rate))
}

/// The weighted mean of zero-points `(zp, sigma)`, its error (scaled by the Birge ratio
/// `sqrt(chi2/(n-1))` only when chi2 exceeds its 99th percentile for n - 1 degrees of
/// freedom: [`crate::stokes::calibration::joint::inflation`], sofipol's one rule; scaling
/// whenever the ratio is above 1 makes honest errors too large on average) and the standard
/// deviation of the zero-points (n >= 2). `None` without a point.
pub fn combine(points: &[(f64, f64)]) -> Option<(f64, f64, Option<f64>)> {
    if points.is_empty() {
        return None;
    }
    let w: Vec<f64> = points.iter().map(|p| 1.0 / (p.1 * p.1)).collect();
    let sw: f64 = w.iter().sum();
    let zp = points.iter().zip(&w).map(|(p, w)| w * p.0).sum::<f64>() / sw;
    let mut sigma = (1.0 / sw).sqrt();
    let n = points.len();
    let mut scatter = None;
    if n >= 2 {
        let chi2: f64 = points.iter().zip(&w).map(|(p, w)| w * (p.0 - zp).powi(2)).sum();
        sigma *= crate::stokes::calibration::joint::inflation(chi2, n - 1).sqrt();
        let mean = points.iter().map(|p| p.0).sum::<f64>() / n as f64;
        let var = points.iter().map(|p| (p.0 - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        scatter = Some(var.sqrt());
    }
    Some((zp, sigma, scatter))
}

/// A source's magnitude and error from its count rate `r` +- `sigma_r` (ADU/s) at airmass
/// `airmass` with zero-point `zp` +- `sigma_zp` and extinction `k`. `None` when the rate is
/// not a positive finite number.
pub fn magnitude(
    zp: f64,
    sigma_zp: f64,
    k: f64,
    rate: f64,
    sigma_rate: f64,
    airmass: Option<f64>,
) -> Option<(f64, f64)> {
    if !(rate.is_finite() && rate > 0.0) {
        return None;
    }
    let m = zp - 2.5 * rate.log10() - k * airmass.unwrap_or(0.0);
    let rel = if sigma_rate.is_finite() {
        sigma_rate / rate
    } else {
        f64::NAN
    };
    Some((m, (MAG_PER_RELATIVE_FLUX * rel).hypot(sigma_zp)))
}

/// Mean airmass of the frames that give one.
fn mean_airmass(q: Option<&Vec<crate::catalog::FrameQuality>>) -> Option<f64> {
    let v: Vec<f64> = q?.iter().filter_map(|f| f.airmass).filter(|a| a.is_finite()).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// The rate and its error from a flux, its error and the integration time.
fn rate(flux: Option<f64>, sigma: Option<f64>, dit: Option<f64>) -> Result<(f64, f64), &'static str> {
    let dit = dit
        .filter(|d| d.is_finite() && *d > 0.0)
        .ok_or("no single integration time (DIT) of its frames")?;
    let f = flux
        .filter(|f| f.is_finite() && *f > 0.0)
        .ok_or("no positive flux measured")?;
    let s = sigma.filter(|s| s.is_finite() && *s >= 0.0).ok_or("no flux error")?;
    Ok((f / dit, s / dit))
}

/// The zero-points of the night from `cat.standards` (table entries with a magnitude in the
/// standard's filter), and magnitudes for every science component of those filters; the
/// result is stored in `cat.calibration.photometry` (when the catalog has a calibration
/// section) and returned, with the lines that say what was done or why not.
pub fn apply(cat: &mut Catalog, photometry: &Photometry) -> PhotometricCalibration {
    let mut out = PhotometricCalibration::default();
    let mut by_filter: std::collections::BTreeMap<String, Vec<PhotometricStandard>> = Default::default();
    for s in &cat.standards {
        let Some((t, mag, sigma_mag)) = s.table.as_ref().and_then(|t| Some((t, t.mag?, t.sigma_mag?))) else {
            continue;
        };
        let m = s.measured.as_ref();
        let measured = if s.status == Status::Failed {
            Err("not measured")
        } else {
            rate(m.and_then(|c| c.flux_adu), m.and_then(|c| c.sigma_flux_adu), s.dit_s)
        };
        let k = photometry.extinction(&s.filter);
        let airmass = mean_airmass(s.frame_quality.as_ref());
        let (r, sr) = match (measured, airmass) {
            (Err(why), _) => {
                out.notes.push(format!(
                    "photometric standard {} ({}) not used: {why}",
                    s.name, s.sequence
                ));
                continue;
            }
            (Ok(_), None) if k != 0.0 => {
                out.notes.push(format!(
                    "photometric standard {} ({}) not used: its frames give no airmass for the extinction term (k = {k} mag/airmass)",
                    s.name, s.sequence
                ));
                continue;
            }
            (Ok(rs), _) => rs,
        };
        let (zp, szp) = standard_zero_point(mag, sigma_mag, r, sr, k, airmass);
        by_filter
            .entry(s.filter.trim().to_string())
            .or_default()
            .push(PhotometricStandard {
                name: s.name.clone(),
                sequence: s.sequence.clone(),
                mag,
                sigma_mag,
                mag_band: t.mag_band.clone(),
                rate_adu_per_s: r,
                sigma_rate_adu_per_s: sr,
                airmass,
                zero_point_mag: zp,
                sigma_zero_point_mag: szp,
            });
    }
    for (filter, standards) in by_filter {
        let points: Vec<(f64, f64)> = standards
            .iter()
            .map(|s| (s.zero_point_mag, s.sigma_zero_point_mag))
            .collect();
        let Some((zp, sigma, scatter)) = combine(&points) else {
            continue;
        };
        out.filters.push(ZeroPoint {
            extinction_mag_per_airmass: photometry.extinction(&filter),
            filter,
            zero_point_mag: zp,
            sigma_zero_point_mag: sigma,
            scatter_mag: scatter,
            standards,
        });
    }
    let mut without: std::collections::BTreeSet<String> = Default::default();
    let mut no_dit = 0usize;
    for t in cat.targets.iter_mut() {
        let filter = t.filter.clone().unwrap_or_default();
        let zp = out
            .filters
            .iter()
            .find(|z| z.filter.eq_ignore_ascii_case(filter.trim()));
        let airmass = mean_airmass(t.frame_quality.as_ref());
        // The binary's components and its field stars, measured alike, get magnitudes alike.
        let field = t.field_stars.iter_mut().flatten().map(|f| &mut f.star);
        for c in t.components.iter_mut().chain(field) {
            (c.mag, c.sigma_mag) = (None, None);
            let Some(z) = zp else {
                without.insert(filter.clone());
                continue;
            };
            let k = z.extinction_mag_per_airmass;
            if t.dit_s.is_none() {
                no_dit += 1;
                continue;
            }
            if k != 0.0 && airmass.is_none() {
                continue;
            }
            let Ok((r, sr)) = rate(c.flux_adu, c.sigma_flux_adu, t.dit_s) else {
                continue;
            };
            if let Some((m, s)) = magnitude(z.zero_point_mag, z.sigma_zero_point_mag, k, r, sr, airmass) {
                (c.mag, c.sigma_mag) = (Some(m), Some(s));
            }
        }
    }
    if out.filters.is_empty() {
        out.notes.push(
            "no magnitudes: the night has no standard with a magnitude in its filter (fluxes in ADU only; \
             give mag and sigma_mag of a standard in --standards FILE)"
                .into(),
        );
    } else {
        for f in without
            .into_iter()
            .filter(|f| !out.filters.iter().any(|z| z.filter.eq_ignore_ascii_case(f)))
        {
            out.notes.push(format!(
                "no magnitudes in filter '{f}': no photometric standard in that filter (fluxes in ADU only)"
            ));
        }
    }
    if no_dit > 0 {
        out.notes.push(format!(
            "{no_dit} component(s) without a magnitude: their frames differ in integration time (DIT)"
        ));
    }
    if let Some(cal) = cat.calibration.as_mut() {
        cal.photometry = Some(out.clone());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Hand-computed: m = 7.0, r = 1e4 ADU/s, k = 0.1, X = 1.5: ZP = 7 + 10 + 0.15 = 17.15;
    /// sigma_r / r = 1 %: 0.010857 mag with sigma_m = 0.02 -> sqrt(0.02^2 + 0.010857^2) = 0.022757.
    #[test]
    fn one_standards_zero_point_by_hand() {
        let (zp, s) = standard_zero_point(7.0, 0.02, 1e4, 100.0, 0.1, Some(1.5));
        assert!((zp - 17.15).abs() < 1e-12, "{zp}");
        assert!((s - 0.022757).abs() < 1e-6, "{s}");
        // Without an airmass the extinction term is not applied.
        assert!((standard_zero_point(7.0, 0.02, 1e4, 100.0, 0.1, None).0 - 17.0).abs() < 1e-12);
    }

    /// Two standards 17.0 +- 0.03 and 17.1 +- 0.04: w = 1111.1, 625; ZP = (18888.9 + 10687.5)
    /// / 1736.1 = 17.036; 1/sqrt(sum w) = 0.024; chi2 = 1111.1 x 0.036^2 + 625 x 0.064^2 =
    /// 4.0 for 1 dof, below its 99th percentile 6.635: not inflated (the former rule,
    /// max(1, Birge ratio), gave 0.048); scatter |0.1| / sqrt 2 = 0.0707. 17.0 and 17.15:
    /// chi2 = 0.15^2 / (0.03^2 + 0.04^2) = 9.0, beyond it: sigma x sqrt(9) = 0.072.
    #[test]
    fn zero_points_are_combined_with_the_birge_ratio_by_hand() {
        let (zp, s, sc) = combine(&[(17.0, 0.03), (17.1, 0.04)]).unwrap();
        let w = [1.0 / 0.03f64.powi(2), 1.0 / 0.04f64.powi(2)];
        let want = (w[0] * 17.0 + w[1] * 17.1) / (w[0] + w[1]);
        assert!((zp - want).abs() < 1e-12 && (zp - 17.036).abs() < 1e-3, "{zp}");
        let chi2 = w[0] * (17.0 - want).powi(2) + w[1] * (17.1 - want).powi(2);
        assert!((chi2 - 4.0).abs() < 1e-9, "{chi2}");
        assert!((s - 0.024).abs() < 1e-9, "{s}");
        assert!((sc.unwrap() - 0.1 / 2f64.sqrt()).abs() < 1e-12);
        let (_, s, _) = combine(&[(17.0, 0.03), (17.15, 0.04)]).unwrap();
        assert!((s - 0.072).abs() < 1e-9, "{s}");
        // Agreeing standards: the error is the weighted mean's, not shrunk by the Birge ratio.
        let (_, s, _) = combine(&[(17.0, 0.03), (17.0, 0.04)]).unwrap();
        assert!((s - 0.024).abs() < 1e-9, "{s}");
        let (zp, s, sc) = combine(&[(17.0, 0.03)]).unwrap();
        assert_eq!((zp, s, sc), (17.0, 0.03, None));
        assert!(combine(&[]).is_none());
    }

    /// ZP 17.15, k 0.1, X 1.2, r 100 ADU/s +- 2 %: m = 17.15 - 5 - 0.12 = 12.03; sigma =
    /// hypot(0.021715, 0.02) = 0.029522.
    #[test]
    fn a_magnitude_by_hand_and_none_without_a_flux() {
        let (m, s) = magnitude(17.15, 0.02, 0.1, 100.0, 2.0, Some(1.2)).unwrap();
        assert!((m - 12.03).abs() < 1e-12, "{m}");
        assert!((s - 0.029522).abs() < 1e-6, "{s}");
        assert!(magnitude(17.0, 0.02, 0.0, 0.0, 1.0, None).is_none());
        assert!(magnitude(17.0, 0.02, 0.0, f64::NAN, 1.0, None).is_none());
        // The magnitude of the standard itself at its own zero-point is its table value.
        let (zp, szp) = standard_zero_point(8.5, 0.0, 2500.0, 0.0, 0.08, Some(1.3));
        let (m, _) = magnitude(zp, szp, 0.08, 2500.0, 0.0, Some(1.3)).unwrap();
        assert!((m - 8.5).abs() < 1e-12);
    }
}
