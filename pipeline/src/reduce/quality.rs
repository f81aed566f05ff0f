//! Each measured frame's observing conditions (the catalog's `frame_quality`), from what the
//! reduction already has: the seeing from the PSF fits of stage 5 (`fluxes.rs`: the
//! photometry's fit, or a beta-free refit of the primary when the photometry holds beta at
//! the stack's value), the sky level from the sky stage, the airmass and time from the
//! header, the transparency from the primary star's o+e flux. Nothing here changes a
//! measured value.
use sofipol_calib::{Frame, Profile};

use super::{DitherValue, Measured, SkySubtractedOrientation};
use crate::catalog::frame_quality::median;
use crate::catalog::FrameQuality;

/// The conditions of every frame of `cal` (in its order: orientation by orientation, the
/// dithers in exposure order), `sky_levels_adu` the sky stage's level of each frame (per
/// orientation, as `cal`), `measured` the sequence's measurement.
///
/// The transparency of a frame is the primary star's (component A's) o+e flux in it over
/// the median of that flux over the sequence's frames: o+e does not depend on the
/// polarization, so it moves only with the light that reaches the detector. A frame whose
/// photometry of A was rejected (cosmic ray, saturation, bad pixel, truncated aperture, not
/// found) has none, and is not in the median.
pub fn frame_quality(
    cal: &[SkySubtractedOrientation],
    sky_levels_adu: &[Vec<f64>],
    measured: &Measured,
    profile: &Profile,
) -> Vec<FrameQuality> {
    let scale = profile.geometry.pixscale_arcsec;
    let primary = measured.dithers.first();
    let flux = |k: usize, i: usize| primary.and_then(|c| c.get(k)?.get(i)).and_then(total_flux);
    let all: Vec<f64> = cal
        .iter()
        .enumerate()
        .flat_map(|(k, o)| (0..o.frames.len()).filter_map(move |i| flux(k, i)))
        .collect();
    let reference = median(all.into_iter()).filter(|m| *m > 0.0);
    let kw = &profile.keywords;
    cal.iter()
        .enumerate()
        .flat_map(|(k, o)| {
            o.frames.iter().enumerate().map(move |(i, f)| {
                let fwhm_px = measured.frame_fwhm_px.get(k).and_then(|v| v.get(i)).copied();
                FrameQuality {
                    file: f.path().display().to_string(),
                    posang_deg: o.posang_deg,
                    dither: i + 1,
                    mjd: header_number(f, &kw.mjd_obs),
                    airmass: airmass(f, &kw.airmass, &kw.airmass_end),
                    fwhm_arcsec: fwhm_px.filter(|w| w.is_finite()).map(|w| w * scale),
                    sky_adu: sky_levels_adu
                        .get(k)
                        .and_then(|v| v.get(i))
                        .copied()
                        .filter(|s| s.is_finite()),
                    transparency: flux(k, i).zip(reference).map(|(f, r)| f / r),
                }
            })
        })
        .collect()
}

/// The o+e flux of a dither's star when its photometry was kept and is positive, ADU.
fn total_flux(d: &DitherValue) -> Option<f64> {
    let sum = d.o.flux + d.e.flux;
    (d.rejected.is_none() && sum.is_finite() && sum > 0.0).then_some(sum)
}

/// A finite number from the header, `None` when absent or unreadable.
fn header_number(f: &Frame, key: &str) -> Option<f64> {
    f.header.opt_f64(key).ok().flatten().filter(|v| v.is_finite())
}

/// The mean of the start and end airmass (the start alone without an end).
fn airmass(f: &Frame, start: &str, end: &str) -> Option<f64> {
    let a = header_number(f, start)?;
    Some(header_number(f, end).map_or(a, |b| 0.5 * (a + b)))
}
