//! The half-wave-plate night as sofipol's catalog ([`crate::catalog::Catalog`]): one target
//! per star and filter, its one component the result on the sky that the summary gives
//! first (the complete cycles combined, else the least squares over the frames), the rest
//! of the reduction in the target's typed `half_wave_plate` section, the files not used as
//! the catalog's `failures` (docs/instruments.md, "The catalog").
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use sofipol_calib::Profile;

use super::{InputFile, SinglePointingCatalog, TargetResult};
use crate::catalog::half_wave_plate::{HalfWavePlateResult, Pol, FROM_CYCLES, FROM_LEAST_SQUARES};
use crate::catalog::{CalibrationState, Catalog, Component, Failure, Flag, FlagCode, Status, Target, TermSource};
use crate::error::{Error, Result};
use crate::stokes::inversion::{Debias, LinearPolarization};

/// The detection cut on P / sigma_P, as for SOFI.
const SNR_CUT: f64 = 3.0;

/// The largest angle error, deg: that of an angle uniform on [-90, 90).
const MAX_SIGMA_GAMMA_DEG: f64 = 51.961_524_227_066_32;

/// `sp` as a [`Catalog`]; `files` are the inputs it was reduced from (their paths, which
/// `sp` names by file name), `profile` the profile it was reduced with.
pub fn to_catalog(sp: &SinglePointingCatalog, files: &[InputFile], profile: &Profile) -> Result<Catalog> {
    let paths = Paths::new(files);
    let mut provenance = sp.provenance.clone();
    provenance.profile = Some(serde_json::json!(profile));
    let mut targets = Vec::with_capacity(sp.targets.len());
    for t in &sp.targets {
        targets.push(target(sp, t, &paths, profile)?);
    }
    let failures = sp
        .not_used
        .iter()
        .map(|n| {
            Ok(Failure {
                file: paths.of(&n.file)?,
                error: n.reason.clone(),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Catalog {
        schema_version: crate::catalog::SCHEMA_VERSION.into(),
        targets,
        failures,
        provenance,
        ..Catalog::default()
    })
}

/// File name -> path of the inputs.
struct Paths(HashMap<String, Vec<PathBuf>>);

impl Paths {
    fn new(files: &[InputFile]) -> Paths {
        let mut m: HashMap<String, Vec<PathBuf>> = HashMap::new();
        for f in files {
            m.entry(super::name(&f.path)).or_default().push(f.path.clone());
        }
        Paths(m)
    }

    /// The path of the input named `name`; an error when two inputs share the name (the
    /// reduction names frames by file name).
    fn of(&self, name: &str) -> Result<String> {
        match self.0.get(name).map(Vec::as_slice) {
            Some([p]) => Ok(p.display().to_string()),
            Some(many) => Err(Error::SinglePointing {
                file: name.to_string(),
                reason: format!(
                    "{} inputs have this file name ({}): the catalog could not tell which was used; give each frame once",
                    many.len(),
                    many.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
                ),
            }),
            // Not an input given (cannot happen for a reduced file): kept as named.
            None => Ok(name.to_string()),
        }
    }

    fn all(&self, names: &[String]) -> Result<Vec<String>> {
        names.iter().map(|n| self.of(n)).collect()
    }
}

fn target(sp: &SinglePointingCatalog, t: &TargetResult, paths: &Paths, profile: &Profile) -> Result<Target> {
    let input_files = paths.all(&t.frames.iter().map(|f| f.file.clone()).collect::<Vec<_>>())?;
    let mut out = Target::new(t.name.clone(), Status::Ok);
    let first_mjd = t.frames.iter().map(|f| f.mjd).fold(f64::INFINITY, f64::min);
    out.sequence = Some(format!("{}@{}@MJD {first_mjd:.5}", t.name, t.filter));
    out.filter = (!t.filter.is_empty()).then(|| t.filter.clone());
    out.mjd_mean = t.mjd.is_finite().then_some(t.mjd);
    out.bad_pixels_masked = Some(sp.bad_pixels);
    out.photometry = Some("aperture".into());
    let n = t.frames.len() as f64;
    if n > 0.0 {
        let mean = |k: usize| t.frames.iter().map(|f| f.eo_offset[k]).sum::<f64>() / n;
        out.eo_offset_px = Some([mean(0), mean(1)]);
    }
    let headers: Vec<sofipol_calib::header::Header> = input_files
        .iter()
        .filter_map(|f| sofipol_calib::fits::read_header(Path::new(f)).ok())
        .collect();
    let kw = &profile.keywords;
    if let Some((ra, dec)) = mean_ra_dec_deg(&headers, &kw.ra, &kw.dec) {
        (out.ra_deg, out.dec_deg) = (Some(ra), Some(dec));
    }
    let dits: Vec<f64> = headers.iter().filter_map(|h| h.get_f64(&kw.dit).ok()).collect();
    if let Some(&d) = dits.first() {
        if dits.len() == headers.len() && dits.iter().all(|&x| x == d) && d.is_finite() && d > 0.0 {
            out.dit_s = Some(d);
        }
    }
    out.input_files = Some(input_files);
    let zp = &sp.zero_point;
    let (main, from) = match (&t.sky, &t.least_squares_sky) {
        (Some(p), _) => (Some(*p), FROM_CYCLES),
        (None, Some(ls)) => (Some(ls.pol), FROM_LEAST_SQUARES),
        (None, None) => (None, FROM_CYCLES),
    };
    match main {
        Some(p) => {
            let offset = if from == FROM_CYCLES {
                TermSource::Cancelled
            } else {
                // Without a complete cycle nothing cancels c: fitted, or missing (q and u
                // then carry it, and the cut refuses them).
                match t.least_squares_sky.as_ref().and_then(|l| l.c) {
                    Some(_) => TermSource::Fitted,
                    None => TermSource::Missing,
                }
            };
            out.components
                .push(component(&p, zp.sigma_deg, &zp.source, offset, from));
            if from == FROM_LEAST_SQUARES {
                out.status = Status::Partial;
                let c_note = t
                    .least_squares_sky
                    .as_ref()
                    .and_then(|l| l.c_not_fitted.as_ref())
                    .map(|why| format!("; the offset c was not fitted ({why}): q and u carry it"))
                    .unwrap_or_default();
                out.error = Some(format!(
                    "no complete plate cycle (0, 22.5, 45, 67.5 deg) in {} frame(s): q and u from the least squares over the frames{c_note}",
                    t.frames.len()
                ));
            } else if !t.left_out.is_empty() {
                out.status = Status::Partial;
                out.error = Some(format!(
                    "{} frame(s) in no complete plate cycle, left out of the cycles' combination: {}",
                    t.left_out.len(),
                    t.left_out.join(", ")
                ));
            }
        }
        None => {
            out.status = Status::Failed;
            out.error = Some(format!(
                "no complete plate cycle and no least squares from {} frame(s): q and u are not constrained",
                t.frames.len()
            ));
        }
    }
    out.half_wave_plate = Some(HalfWavePlateResult {
        component_from: from.into(),
        zero_point: zp.clone(),
        profile: sp.profile.clone(),
        modulation: sp.modulation.clone(),
        field_rotation: sp.field_rotation.clone(),
        darks: paths.all(&sp.darks)?,
        skies: paths.all(&sp.skies)?,
        flat_from: paths.all(&sp.flat_from)?,
        bad_pixels: sp.bad_pixels,
        sky_cosmic_ray_pixels: sp.sky_cosmic_ray_pixels,
        instrument: t.instrument,
        sky: t.sky,
        cycles: t.cycles.clone(),
        cycle_agreement: t.cycle_agreement.clone(),
        least_squares_instrument: t.least_squares_instrument.clone(),
        least_squares_sky: t.least_squares_sky.clone(),
        left_out: t.left_out.clone(),
        frames: t.frames.clone(),
    });
    Ok(out)
}

/// The star's component from the result on the sky `p`: q, u, their errors, P, sigma_P,
/// the angle and its statistical error as `p` has them (as the night's summary gives
/// them); sigma_gamma_deg that angle error and the zero point's `sigma_zero_point_deg` in
/// quadrature (each also alone), P debiased by Wardle & Kronberg.
fn component(p: &Pol, sigma_zero_point_deg: f64, zero_point_source: &str, offset: TermSource, from: &str) -> Component {
    let lp = LinearPolarization::from_qu(p.q, p.u, p.sigma_q, p.sigma_u, Debias::WardleKronberg);
    let mut pol = lp.pol;
    (pol.p, pol.sigma_p, pol.gamma_deg) = (p.p, p.sigma_p, p.angle_deg);
    let stat = p.sigma_angle_deg;
    pol.sigma_gamma_deg = stat.hypot(sigma_zero_point_deg).min(MAX_SIGMA_GAMMA_DEG);
    let calibration = CalibrationState {
        offset,
        // Nothing removes the polarization the telescope and the optics before the plate add.
        telescope: TermSource::Missing,
        zero_point: TermSource::Prior,
    };
    let mut c = Component::new("A", pol);
    c.passes_cut = lp.passes_cut(SNR_CUT) && calibration.complete_for_the_cut();
    c.calibration = Some(calibration);
    c.snr = Some(lp.snr);
    c.sigma_gamma_nkc_deg = Some(lp.sigma_gamma_nkc_deg);
    c.sigma_gamma_stat_deg = Some(stat);
    c.sigma_gamma_zero_point_deg = Some(sigma_zero_point_deg);
    c.sigma_q_stat = Some(p.sigma_q);
    c.sigma_u_stat = Some(p.sigma_u);
    c.zero_point_gradient = Some(crate::stokes::propagation::rotation_gradient_per_deg(p.q, p.u));
    c.stokes_method = Some(
        if from == FROM_CYCLES {
            "double_difference"
        } else {
            "least_squares"
        }
        .into(),
    );
    c.flags
        .push(Flag::with_detail(FlagCode::ZeroPointFromProfile, zero_point_source));
    c.flags.push(Flag::with_detail(
        FlagCode::TelescopeUncorrected,
        "the half-wave-plate reduction removes no polarization of the telescope or of the optics before the plate",
    ));
    if !lp.passes_cut(SNR_CUT) {
        c.flags.push(Flag::new(FlagCode::LowSnr));
    }
    c
}

/// An angle keyword's value in degrees: a number, or sexagesimal `d:m:s` (`hours` for a
/// right ascension in `h:m:s`, then times 15).
pub fn header_angle_deg(h: &sofipol_calib::header::Header, key: &str, hours: bool) -> Option<f64> {
    if let Ok(v) = h.get_f64(key) {
        return v.is_finite().then_some(v);
    }
    let s = h.opt_str(key)?;
    let v = sexagesimal(&s)?;
    Some(if hours { 15.0 * v } else { v })
}

/// `[+-]a:b:c` (or `a b c`) as a + b/60 + c/3600 with the sign of the whole.
fn sexagesimal(s: &str) -> Option<f64> {
    let s = s.trim();
    let (neg, rest) = match s.strip_prefix('-') {
        Some(r) => (true, r),
        None => (false, s.strip_prefix('+').unwrap_or(s)),
    };
    let parts: Vec<f64> = rest
        .split([':', ' '])
        .filter(|p| !p.is_empty())
        .map(|p| p.parse::<f64>().ok().filter(|v| v.is_finite() && *v >= 0.0))
        .collect::<Option<_>>()?;
    if parts.is_empty() || parts.len() > 3 || parts[1..].iter().any(|&v| v >= 60.0) {
        return None;
    }
    let v = parts.iter().zip([1.0, 60.0, 3600.0]).map(|(p, d)| p / d).sum::<f64>();
    Some(if neg { -v } else { v })
}

/// Mean (RA, Dec) of the frames that have both, deg: Dec the arithmetic mean, RA the
/// circular mean in [0, 360) (as a SOFI sequence's).
fn mean_ra_dec_deg(headers: &[sofipol_calib::header::Header], ra: &str, dec: &str) -> Option<(f64, f64)> {
    let pts: Vec<(f64, f64)> = headers
        .iter()
        .filter_map(|h| header_angle_deg(h, ra, true).zip(header_angle_deg(h, dec, false)))
        .filter(|(r, d)| (0.0..=360.0).contains(r) && (-90.0..=90.0).contains(d))
        .collect();
    if pts.is_empty() {
        return None;
    }
    let dec = pts.iter().map(|p| p.1).sum::<f64>() / pts.len() as f64;
    let (s, c) = pts.iter().fold((0.0, 0.0), |(s, c), p| {
        let a = p.0.to_radians();
        (s + a.sin(), c + a.cos())
    });
    Some((s.atan2(c).to_degrees().rem_euclid(360.0), dec))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sexagesimal_angles_read_as_degrees() {
        // AB Aur's header: RA '04:55:45.91', DEC '+30:33:08.1'.
        let ra = 15.0 * sexagesimal("04:55:45.91").unwrap();
        assert!((ra - (4.0 + 55.0 / 60.0 + 45.91 / 3600.0) * 15.0).abs() < 1e-12);
        assert!((ra - 73.941_291_666_666_67).abs() < 1e-9, "{ra}");
        let dec = sexagesimal("+30:33:08.1").unwrap();
        assert!((dec - 30.552_25).abs() < 1e-12, "{dec}");
        assert!((sexagesimal("-00:30:00").unwrap() + 0.5).abs() < 1e-15);
        for bad in ["", "ab:cd", "10:61:00", "1:2:3:4", "--1:00"] {
            assert_eq!(sexagesimal(bad), None, "{bad}");
        }
    }

    #[test]
    fn the_component_is_the_result_given_and_the_zero_point_adds_to_the_angle_error_only() {
        let p = Pol::new(0.03, -0.04, 0.002, 0.003, 0.0015, 0.0025);
        let c = component(&p, 12.0, "somewhere", TermSource::Cancelled, FROM_CYCLES);
        assert_eq!((c.q, c.u, c.sigma_q, c.sigma_u), (p.q, p.u, p.sigma_q, p.sigma_u));
        // P = 5 %, sigma_P = sqrt((q sq)^2 + (u su)^2) / P, angle 0.5 atan2(u, q), by hand.
        assert!((c.p - 0.05).abs() < 1e-15);
        let sp = ((0.03f64 * 0.002).powi(2) + (0.04f64 * 0.003).powi(2)).sqrt() / 0.05;
        assert!((c.sigma_p - sp).abs() < 1e-15, "{} {sp}", c.sigma_p);
        assert!((c.gamma_deg - (180.0 + 0.5 * (-0.04f64).atan2(0.03).to_degrees())).abs() < 1e-12);
        // Debiased by Wardle & Kronberg: sqrt(P^2 - sigma_P^2).
        assert!((c.p_debiased - (0.05f64 * 0.05 - sp * sp).sqrt()).abs() < 1e-15);
        // The angle's statistical error 0.5 sigma_P / P rad, the zero point's in quadrature.
        let stat = (0.5 * sp / 0.05).to_degrees();
        assert!((c.sigma_gamma_stat_deg.unwrap() - stat).abs() < 1e-12);
        assert!((c.sigma_gamma_deg - stat.hypot(12.0)).abs() < 1e-12);
        // P/sigma ~ 19 but the telescope's polarization is not removed: below the cut.
        assert!(!c.passes_cut);
        assert!(c.flags.iter().any(|f| f.code == FlagCode::TelescopeUncorrected));
        assert!(!c.flags.iter().any(|f| f.code == FlagCode::LowSnr));
    }
}
