//! The catalog entry of a measured sequence: per component, the dither values of each
//! orientation combined (rejections, clipping, weighted mean, honest error), then q and u by
//! least squares over the orientations, P, gamma and their errors, debiasing and the cut.
use super::{DitherValue, MeasureParams, Measured, SkySubtractedOrientation};
use crate::catalog::flags::has;
use crate::catalog::{CombinedF, Component, DroppedDither, FieldStar, Flag, FlagCode, Status, Target};
use crate::stokes::inversion::{clip_dithers, combine_dithers, Polarization};
use sofipol_calib::profile::Keywords;
use sofipol_calib::Profile;

/// The component flag of `k` of its `n` dithers dropped for masked pixels (a detector
/// defect, a pixel the flat cannot correct, off the strip) within the aperture (radius +
/// 0.71 px): the flag's name, then what it cost.
pub fn bad_pixels_flag(k: usize, n: usize) -> Flag {
    Flag::with_detail(
        FlagCode::BadPixels,
        format!("{k} of {n} dithers dropped (a masked pixel within the aperture)"),
    )
}

/// Turn the per-dither values of one component into its catalog entry. `parallactic_deg`
/// holds each dither's parallactic angle and `files` its frame (per orientation, in dither
/// order; `None` when the frame has no angle).
pub fn component_from_dithers(
    name: &str,
    per_orient: &[Vec<DitherValue>],
    analyzer_deg: &[f64],
    parallactic_deg: &[Vec<Option<f64>>],
    files: &[Vec<String>],
    params: &MeasureParams,
    profile: &Profile,
) -> Component {
    let mut acc = Combination {
        parallactic_deg,
        files,
        any_eta: parallactic_deg.iter().flatten().any(Option::is_some),
        ..Combination::default()
    };
    for (k, dv) in per_orient.iter().enumerate() {
        acc.orientation(k, dv, analyzer_deg[k], params);
    }
    let mut c = acc.component(name, per_orient);
    solve_provisionally(&mut c, profile, params);
    c
}

/// The provisional q, u of a freshly measured component: the one Stokes solve
/// ([`crate::solve::resolve_component`]) by least squares, without a calibration. It
/// decides the target's status; the catalog keeps what the night's calibration re-solves.
/// What the calibration has not yet said (`uncalibrated`, the telescope's term not
/// removed) is left to it; orientations that do not constrain q and u are flagged
/// `undefined_polarization`.
fn solve_provisionally(c: &mut Component, profile: &Profile, params: &MeasureParams) {
    use crate::stokes::calibration::StokesMethod;
    crate::solve::resolve_component(
        c,
        &crate::solve::SolveSettings {
            profile,
            cal: None,
            method: StokesMethod::LeastSquares,
            debias: params.debias,
            cut_snr: params.cut_snr,
            telescope_prior: None,
            telescope_polarizes: profile.telescope.polarizes,
        },
    );
    c.flags.retain(|f| {
        !f.is(FlagCode::Uncalibrated) && !f.is(FlagCode::TelescopeUncorrected) && !f.is(FlagCode::TelescopeUnaccounted)
    });
    c.calibration = None;
    if !c.q.is_finite() {
        c.flags.retain(|f| !f.is(FlagCode::StokesMethodFailed));
        c.flags.push(Flag::with_detail(
            FlagCode::UndefinedPolarization,
            "orientations do not constrain q and u",
        ));
        c.passes_cut = false;
    }
}

/// A component's dithers combined orientation by orientation: the flags, the dithers left
/// out with why, F per orientation, the flux.
#[derive(Default)]
struct Combination<'a> {
    parallactic_deg: &'a [Vec<Option<f64>>],
    files: &'a [Vec<String>],
    /// Some frame has a parallactic angle: a dither whose frame has none is left out.
    any_eta: bool,
    flags: Vec<Flag>,
    dropped: Vec<DroppedDither>,
    per_orientation: Vec<CombinedF>,
    sum_flux: f64,
    n_flux: usize,
    /// The kept dithers' o+e fluxes, and the sum of their variances (ADU^2).
    fluxes: Vec<f64>,
    sum_flux_var: f64,
}

impl Combination<'_> {
    /// Flag `code` once.
    fn flag(&mut self, code: FlagCode) {
        if !has(&self.flags, code) {
            self.flags.push(Flag::new(code));
        }
    }

    /// Dither `i` of orientation `k` has no parallactic angle while other frames have one:
    /// the telescope's polarization cannot be removed from it, so it is left out by name
    /// (the others keep the correction). With no angle anywhere, nothing is left out (the
    /// calibration flags the component uncorrected).
    fn no_eta(&self, k: usize, i: usize) -> bool {
        self.any_eta
            && self
                .parallactic_deg
                .get(k)
                .and_then(|v| v.get(i))
                .copied()
                .flatten()
                .is_none()
    }

    /// Combine orientation `k` (analyzer angle `phi`): flag, choose the usable dithers,
    /// clip, record what was left out, and combine what is kept.
    fn orientation(&mut self, k: usize, dv: &[DitherValue], phi: f64, params: &MeasureParams) {
        let usable = self.usable(k, dv);
        let vals: Vec<f64> = usable.iter().map(|&i| dv[i].f).collect();
        let sig: Vec<f64> = usable.iter().map(|&i| dv[i].sigma_f).collect();
        let keep = clip_dithers(&vals, &sig, params.clip_sigma, 2);
        self.left_out(k, dv, &usable, &keep);
        let kept: Vec<usize> = keep.iter().map(|&j| usable[j]).collect();
        for &i in &kept {
            self.sum_flux += dv[i].o.flux + dv[i].e.flux;
            self.n_flux += 1;
            self.fluxes.push(dv[i].o.flux + dv[i].e.flux);
            self.sum_flux_var += dv[i].o.var + dv[i].e.var;
        }
        let kv: Vec<f64> = keep.iter().map(|&j| vals[j]).collect();
        let ks: Vec<f64> = keep.iter().map(|&j| sig[j]).collect();
        if let Some(f) = self.combined(k, dv.len(), phi, &kept, &kv, &ks) {
            self.per_orientation.push(f);
        }
    }

    /// The dithers of orientation `k` that enter its F, flagging what the others say: not
    /// rejected and with an angle when others have one; all finite values (flagged
    /// `used_flagged_dithers`) when that leaves none. Photometry flags of the usable ones
    /// are carried.
    fn usable(&mut self, k: usize, dv: &[DitherValue]) -> Vec<usize> {
        let mut usable: Vec<usize> = (0..dv.len())
            .filter(|&i| dv[i].rejected.is_none() && !self.no_eta(k, i))
            .collect();
        if (0..dv.len()).any(|i| dv[i].rejected.is_none() && self.no_eta(k, i)) {
            self.flag(FlagCode::NoParallacticAngle);
        }
        for d in dv.iter().filter(|d| d.rejected.is_some()) {
            // A dither's reasons are flag names (`cosmic_ray,bad_pixels`).
            for r in d.rejected.as_deref().unwrap_or("").split(',').filter(|r| !r.is_empty()) {
                let r = Flag::parse(r);
                if !self.flags.contains(&r) {
                    self.flags.push(r);
                }
            }
        }
        if usable.is_empty() {
            // Everything is flagged: fall back to all finite values rather than nothing.
            usable = (0..dv.len())
                .filter(|&i| dv[i].f.is_finite() && dv[i].sigma_f > 0.0)
                .collect();
            if !usable.is_empty() {
                self.flag(FlagCode::UsedFlaggedDithers);
            }
        }
        for &i in &usable {
            let pf = crate::photometry::Flags(dv[i].o.phot_flags | dv[i].e.phot_flags);
            for (bit, code) in [
                (crate::photometry::Flags::COMPANION_OVERLAP, FlagCode::CompanionOverlap),
                (
                    crate::photometry::Flags::ANNULUS_CONTAMINATED,
                    FlagCode::AnnulusContaminated,
                ),
            ] {
                if pf.contains(bit) {
                    self.flag(code);
                }
            }
        }
        usable
    }

    /// Every dither of orientation `k` not kept (`keep`: indices into `usable`), by frame,
    /// with why.
    fn left_out(&mut self, k: usize, dv: &[DitherValue], usable: &[usize], keep: &[usize]) {
        for (i, d) in dv.iter().enumerate() {
            if keep.iter().any(|&j| usable[j] == i) {
                continue;
            }
            let reason = match d.rejected.as_deref() {
                Some(r) if !usable.contains(&i) => r.split(',').collect::<Vec<_>>().join(", "),
                None if !usable.contains(&i) && self.no_eta(k, i) => FlagCode::NoParallacticAngle.name().to_string(),
                // Usable but left out by the clipping: an outlier, or a value or error that
                // is not a number (never combined).
                _ if d.f.is_finite() && d.sigma_f > 0.0 => "clipped".to_string(),
                _ => "no value".to_string(),
            };
            // Only an outlier clipped is `dither_clipped`; a value that is not a number
            // was never a candidate.
            if reason == "clipped" {
                self.flag(FlagCode::DitherClipped);
            }
            let file = self
                .files
                .get(k)
                .and_then(|f| f.get(i))
                .cloned()
                .unwrap_or_else(|| format!("orientation {} dither {}", k + 1, i + 1));
            self.dropped.push(DroppedDither { file, reason });
        }
    }

    /// F of orientation `k` from its kept dithers (`kept`: their indices, `kv`, `ks`: their
    /// F and errors), the honest error: the propagated one, inflated by sqrt(chi2/dof)
    /// when the dither scatter is significantly larger (p < 0.01).
    fn combined(
        &mut self,
        k: usize,
        n_total: usize,
        phi: f64,
        kept: &[usize],
        kv: &[f64],
        ks: &[f64],
    ) -> Option<CombinedF> {
        let c = combine_dithers(kv, ks)?;
        let dof = (c.n.saturating_sub(1)) as f64;
        let mut sigma = c.sigma;
        if dof >= 1.0 {
            let p = 1.0
                - statrs::distribution::ContinuousCDF::cdf(
                    &statrs::distribution::ChiSquared::new(dof).expect("dof > 0"),
                    c.chi2,
                );
            if p < 0.01 {
                sigma *= (c.chi2 / dof).sqrt();
                self.flag(FlagCode::ExcessDitherScatter);
            }
        }
        let etas: Option<Vec<f64>> = kept
            .iter()
            .map(|&i| self.parallactic_deg.get(k).and_then(|v| v.get(i).copied().flatten()))
            .collect();
        let parallactic = etas.and_then(|e| ParallacticMean::of(&e, ks));
        Some(CombinedF {
            analyzer_deg: phi,
            chi2: c.chi2,
            f: c.value,
            n_dithers: c.n,
            n_dithers_total: n_total,
            parallactic_2eta: parallactic.map(|p| p.cos_sin_2eta),
            parallactic_deg: parallactic.map(|p| p.eta_deg),
            posang_deg: None,
            sigma_f: sigma,
            sigma_f_propagated: c.sigma,
            sigma_f_scatter: c.sigma_scatter,
        })
    }

    /// The component, its q and u still to solve. The `bad_pixels` flag says how many
    /// dithers it dropped.
    fn component(mut self, name: &str, per_orient: &[Vec<DitherValue>]) -> Component {
        let n_dithers: usize = per_orient.iter().map(Vec::len).sum();
        let n_bad_pixels = per_orient
            .iter()
            .flatten()
            .filter(|d| {
                d.rejected
                    .as_deref()
                    .is_some_and(|r| r.split(',').any(|x| x == FlagCode::BadPixels.name()))
            })
            .count();
        if let Some(f) = self.flags.iter_mut().find(|f| **f == Flag::new(FlagCode::BadPixels)) {
            *f = bad_pixels_flag(n_bad_pixels, n_dithers);
        }
        let flux = if self.n_flux > 0 {
            self.sum_flux / self.n_flux as f64
        } else {
            f64::NAN
        };
        let sigma_flux = mean_flux_error(&self.fluxes, self.sum_flux_var);
        Component {
            orientations: Some(self.per_orientation),
            dropped_dithers: (!self.dropped.is_empty()).then_some(self.dropped),
            flux_adu: Some(flux),
            sigma_flux_adu: Some(sigma_flux),
            flags: self.flags,
            ..Component::new(name, Polarization::UNDEFINED)
        }
    }
}

/// The 1-sigma error of the mean of `fluxes` (ADU), whose variances sum to `sum_var`: the
/// propagated `sqrt(sum_var)/n`, or the standard error of their scatter `s/sqrt(n)` when that
/// is larger (seeing and transparency move a star's flux from dither to dither beyond its
/// photon noise). NaN without a flux.
pub fn mean_flux_error(fluxes: &[f64], sum_var: f64) -> f64 {
    let n = fluxes.len() as f64;
    if fluxes.is_empty() {
        return f64::NAN;
    }
    let propagated = sum_var.max(0.0).sqrt() / n;
    if fluxes.len() < 2 {
        return propagated;
    }
    let mean = fluxes.iter().sum::<f64>() / n;
    let var = fluxes.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / (n - 1.0);
    propagated.max((var / n).sqrt())
}

/// The parallactic angle of an orientation's dithers, weighted as F is.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ParallacticMean {
    /// Weighted mean of (cos 2eta, sin 2eta): the telescope's polarization is linear in
    /// these, so its weighted mean over the dithers is exact with them.
    cos_sin_2eta: [f64; 2],
    /// Weighted circular mean of eta, deg in (-180, 180] (for reading).
    eta_deg: f64,
}

impl ParallacticMean {
    /// With the weights 1/sigma^2 of the weighted mean of F. `None` without a finite angle
    /// and weight for every dither.
    fn of(eta_deg: &[f64], sigma: &[f64]) -> Option<ParallacticMean> {
        let (mut sw, mut c2, mut s2, mut c1, mut s1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (&eta, &s) in eta_deg.iter().zip(sigma) {
            let w = s.powi(-2);
            if !(eta.is_finite() && w.is_finite() && w > 0.0) {
                return None;
            }
            let e = eta.to_radians();
            sw += w;
            c2 += w * (2.0 * e).cos();
            s2 += w * (2.0 * e).sin();
            c1 += w * e.cos();
            s1 += w * e.sin();
        }
        (sw > 0.0).then(|| ParallacticMean {
            cos_sin_2eta: [c2 / sw, s2 / sw],
            eta_deg: s1.atan2(c1).to_degrees(),
        })
    }
}

/// Each dither's parallactic angle from its frame's header (`None` when absent or unreadable).
/// An unreadable value is named in `flags`, and so is an absent one when other frames
/// have an angle (those dithers are then left out: [`component_from_dithers`]).
fn parallactic_angles(
    orients: &[SkySubtractedOrientation],
    kw: &Keywords,
    flags: &mut Vec<Flag>,
) -> Vec<Vec<Option<f64>>> {
    let read: Vec<Vec<(String, sofipol_calib::Result<Option<f64>>)>> = orients
        .iter()
        .map(|o| {
            o.frames
                .iter()
                .map(|f| (f.path().display().to_string(), kw.parallactic_angle_deg(&f.header)))
                .collect()
        })
        .collect();
    let any = read.iter().flatten().any(|(_, r)| matches!(r, Ok(Some(_))));
    read.into_iter()
        .map(|o| {
            o.into_iter()
                .map(|(path, r)| match r {
                    Ok(eta) => {
                        if eta.is_none() && any {
                            flags.push(Flag::with_detail(
                                FlagCode::ParallacticAngleNotUsed,
                                format!("{path}: no {}", kw.parang),
                            ));
                        }
                        eta
                    }
                    Err(e) => {
                        flags.push(Flag::with_detail(FlagCode::ParallacticAngleNotUsed, e.to_string()));
                        None
                    }
                })
                .collect()
        })
        .collect()
}

/// Build the catalog entry of a measured sequence (`profile`: the header keywords of the
/// frames' parallactic angles, the angles of the provisional Stokes solve).
pub fn target_entry(
    object: &str,
    orients: &[SkySubtractedOrientation],
    m: &Measured,
    params: &MeasureParams,
    profile: &Profile,
) -> Target {
    let phis: Vec<f64> = orients.iter().map(|o| o.analyzer_deg).collect();
    let mut target_flags = m.flags.clone();
    let etas = parallactic_angles(orients, &profile.keywords, &mut target_flags);
    let files: Vec<Vec<String>> = orients
        .iter()
        .map(|o| o.frames.iter().map(|f| f.path().display().to_string()).collect())
        .collect();
    let names = ["A", "B"];
    // Which star was measured at some orientation is not known: every component may mix
    // the two stars' q and u. Reported, flagged, never a detection.
    let unverified = has(&m.flags, FlagCode::AbIdentityUnverified);
    let components: Vec<Component> = m
        .dithers
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let mut c = component_from_dithers(names[i], d, &phis, &etas, &files, params, profile);
            if unverified {
                c.flags.push(Flag::new(FlagCode::AbIdentityUnverified));
                c.passes_cut = false;
            }
            c
        })
        .collect();
    let field_stars = params
        .field_stars
        .then(|| field_star_entries(&m.field, &phis, &etas, &files, params, profile));
    // No component with a value (all null) is a failure, not a partial result.
    let status = if components.len() == 2 && components.iter().all(|c| c.q.is_finite()) {
        Status::Ok
    } else if components.iter().any(|c| c.q.is_finite()) {
        Status::Partial
    } else {
        Status::Failed
    };
    let mut t = Target {
        error: match status {
            Status::Ok => None,
            Status::Partial => m.flags.first().map(Flag::to_string).or(Some(
                if components.first().is_some_and(|c| c.q.is_finite()) {
                    "companion not measured"
                } else {
                    "primary not measured"
                }
                .into(),
            )),
            Status::Failed => Some(format!(
                "no component could be measured{}",
                m.flags.first().map(|f| format!(": {f}")).unwrap_or_default()
            )),
        },
        components,
        eo_offset_px: Some([m.eo_offset_px.0, m.eo_offset_px.1]),
        fwhm_px: Some(m.fwhm_px),
        photometry: Some(m.photometry.clone()),
        aperture_radius_px: Some(m.aperture_px),
        separation_arcsec: m.geometry.map(|g| g.0),
        pa_deg: m.geometry.map(|g| g.1),
        orientations_deg: Some(orients.iter().map(|o| o.posang_deg).collect()),
        flags: Some(target_flags),
        field_stars,
        ..Target::new(object, status)
    };
    t.update_delta_gamma(None);
    t
}

/// The catalog entries of the field stars: each one's dithers combined and solved by
/// [`component_from_dithers`] as a component's, then its own flags (dithers beyond the
/// field or at a strip edge counted, `blended` with what, `faint`) and whether usable.
/// Positions are in the reduced rows (the caller adds the crop's first row and the sky
/// position).
fn field_star_entries(
    field: &[super::field::FieldMeasured],
    phis: &[f64],
    etas: &[Vec<Option<f64>>],
    files: &[Vec<String>],
    params: &MeasureParams,
    profile: &Profile,
) -> Vec<FieldStar> {
    field
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let id = format!("F{}", i + 1);
            let mut c = component_from_dithers(&id, &s.dithers, phis, etas, files, params, profile);
            let n: usize = s.dithers.iter().map(Vec::len).sum();
            c.flags
                .retain(|f| !f.is(FlagCode::OutsideField) && !f.is(FlagCode::StripEdge));
            if s.n_outside > 0 {
                c.flags.push(Flag::with_detail(
                    FlagCode::OutsideField,
                    format!("{} of {n} dithers", s.n_outside),
                ));
            }
            if s.n_edge > 0 {
                c.flags.push(Flag::with_detail(
                    FlagCode::StripEdge,
                    format!("{} of {n} dithers", s.n_edge),
                ));
            }
            if !s.blended_with.is_empty() {
                c.flags
                    .push(Flag::with_detail(FlagCode::Blended, s.blended_with.join(", ")));
            }
            let flux_snr = c.flux_adu.zip(c.sigma_flux_adu).map_or(f64::NAN, |(f, e)| f / e);
            if !(flux_snr >= crate::catalog::field_stars::MIN_FLUX_SNR) {
                c.flags
                    .push(Flag::with_detail(FlagCode::Faint, format!("flux S/N {flux_snr:.1}")));
            }
            let mut star = FieldStar {
                id,
                usable: false,
                x_px: s.xy_px.0,
                y_px: s.xy_px.1,
                separation_arcsec: s.sep_arcsec,
                pa_deg: s.pa_deg,
                ra_deg: None,
                dec_deg: None,
                n_detected: s.n_detected,
                detection_snr: s.detection_snr,
                star: c,
            };
            star.settle();
            star
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reduce::{BeamFlux, DitherValue};
    use crate::stokes::inversion::LinearPolarization;
    use crate::stokes::propagation::QuCovariance;

    /// The mean flux's error by hand: fluxes 98, 100, 102 (standard deviation 2, standard
    /// error 2/sqrt 3 = 1.1547) with summed variances 3 (propagated sqrt 3 / 3 = 0.5774):
    /// the scatter's; with 300 (5.7735): the propagated; one flux: its own error.
    #[test]
    fn the_mean_fluxs_error_is_the_larger_of_propagated_and_scatter_by_hand() {
        let f = [98.0, 100.0, 102.0];
        assert!((mean_flux_error(&f, 3.0) - 2.0 / 3f64.sqrt()).abs() < 1e-12);
        assert!((mean_flux_error(&f, 300.0) - 300f64.sqrt() / 3.0).abs() < 1e-12);
        assert_eq!(mean_flux_error(&[50.0], 16.0), 4.0);
        assert!(mean_flux_error(&[], 1.0).is_nan());
    }

    /// Two components, both with a 10-sigma polarization at 0/45/90/135 (q = 0.03, u = 0.02,
    /// sigma_F = 0.001 per dither, 3 dithers).
    fn measured(flags: Vec<Flag>) -> Measured {
        let phis = [0.0f64, 45.0, 90.0, 135.0];
        let comp = |q: f64, u: f64| -> Vec<Vec<DitherValue>> {
            phis.iter()
                .map(|phi| {
                    let t = (2.0 * phi).to_radians();
                    let f = q * t.cos() + u * t.sin();
                    dithers(&[(f - 0.0005, 0.001), (f, 0.001), (f + 0.0005, 0.001)])
                })
                .collect()
        };
        Measured {
            eo_offset_px: (0.0, 167.0),
            fwhm_px: 3.0,
            frame_fwhm_px: Vec::new(),
            geometry: Some((5.0, 340.0)),
            photometry: "aperture".into(),
            aperture_px: 3.0,
            dithers: vec![comp(0.03, 0.02), comp(-0.02, 0.04)],
            flags,
            field: Vec::new(),
        }
    }

    fn orients() -> Vec<SkySubtractedOrientation> {
        [0.0, 45.0, 90.0, 135.0]
            .iter()
            .map(|&p| SkySubtractedOrientation {
                posang_deg: p,
                analyzer_deg: p,
                frames: Vec::new(),
                offsets: Vec::new(),
            })
            .collect()
    }

    #[test]
    fn flagged_dithers_are_flagged_once_and_a_target_without_any_value_fails() {
        let params = MeasureParams::default();
        // Every dither of every orientation flagged (finite values): used, flagged once.
        let mut m = measured(Vec::new());
        for d in m.dithers.iter_mut().flatten().flatten() {
            d.rejected = Some("saturated".into());
        }
        let t = target_entry("X", &orients(), &m, &params, &sofipol_calib::Profile::sofi());
        for c in &t.components {
            let n = c.flags.iter().filter(|f| f.is(FlagCode::UsedFlaggedDithers)).count();
            assert_eq!(n, 1, "{:?}", c.flags);
            assert!(!c.passes_cut && c.q.is_finite());
        }
        // One component (no companion), no dither measured: nothing to report, failed.
        let mut m = measured(Vec::new());
        m.dithers.truncate(1);
        for d in m.dithers.iter_mut().flatten().flatten() {
            *d = DitherValue::missing("primary_not_found");
        }
        let t = target_entry("X", &orients(), &m, &params, &sofipol_calib::Profile::sofi());
        assert!(t.components.iter().all(|c| c.q.is_nan()), "{t:?}");
        assert_eq!(t.status, Status::Failed, "{t:?}");
        assert!(
            t.error.as_deref().unwrap().contains("no component could be measured"),
            "{t:?}"
        );
        // A measured primary without its companion stays partial.
        let mut m = measured(Vec::new());
        m.dithers.truncate(1);
        assert_eq!(
            target_entry("X", &orients(), &m, &params, &sofipol_calib::Profile::sofi()).status,
            Status::Partial
        );
    }

    /// The `bad_pixels` flag counts the dithers it dropped, of every dither of the
    /// component (12 here); a dither dropped for two reasons counts once for each.
    #[test]
    fn the_bad_pixels_flag_says_how_many_dithers_it_dropped() {
        let params = MeasureParams::default();
        let mut m = measured(Vec::new());
        let a = &mut m.dithers[0];
        a[0][1].rejected = Some("bad_pixels".into());
        a[1][0].rejected = Some("bad_pixels".into());
        a[2][0].rejected = Some("cosmic_ray,bad_pixels".into());
        a[3][2].rejected = Some("cosmic_ray".into());
        let t = target_entry("X", &orients(), &m, &params, &sofipol_calib::Profile::sofi());
        let flags = &t.components[0].flags;
        let want = "bad_pixels: 3 of 12 dithers dropped (a masked pixel within the aperture)";
        assert_eq!(
            flags.iter().filter(|f| f.is(FlagCode::BadPixels)).collect::<Vec<_>>(),
            [&Flag::parse(want)],
            "{flags:?}"
        );
        assert!(flags.iter().any(|f| f.is(FlagCode::CosmicRay)), "{flags:?}");
        assert!(t.components[1].flags.is_empty(), "{:?}", t.components[1].flags);
        // Each dither left out is named with its reason (the frames are not known here:
        // orientation and dither); the other component used all of its dithers.
        let dropped: Vec<(String, String)> = t.components[0]
            .dropped_dithers
            .iter()
            .flatten()
            .map(|d| (d.file.clone(), d.reason.clone()))
            .collect();
        let want = [
            ("orientation 1 dither 2", "bad_pixels"),
            ("orientation 2 dither 1", "bad_pixels"),
            ("orientation 3 dither 1", "cosmic_ray, bad_pixels"),
            ("orientation 4 dither 3", "cosmic_ray"),
        ]
        .map(|(a, b)| (a.to_string(), b.to_string()));
        assert_eq!(dropped, want);
        assert_eq!(t.components[1].dropped_dithers, None);
    }

    /// An outlier among an orientation's dithers is clipped and listed as such.
    #[test]
    fn a_clipped_dither_is_listed_as_clipped() {
        let mut m = measured(Vec::new());
        m.dithers[1][1][0].f += 0.05;
        m.dithers[1][2][0].f += 0.05;
        m.dithers[1][2][0].rejected = Some("saturated".into());
        let params = MeasureParams::default();
        let t = target_entry("X", &orients(), &m, &params, &sofipol_calib::Profile::sofi());
        let d = t.components[1].dropped_dithers.clone().unwrap();
        let got: Vec<(&str, &str)> = d.iter().map(|d| (d.file.as_str(), d.reason.as_str())).collect();
        assert_eq!(
            got,
            [
                ("orientation 2 dither 1", "clipped"),
                ("orientation 3 dither 1", "saturated")
            ]
        );
        let clipped = |t: &Target, i: usize| {
            t.components[i]
                .flags
                .iter()
                .filter(|f| f.is(FlagCode::DitherClipped))
                .count()
        };
        assert_eq!((clipped(&t, 0), clipped(&t, 1)), (0, 1), "{t:?}");
    }

    /// Every dither of an orientation flagged: the finite values with a positive error
    /// are used (flagged `used_flagged_dithers`); a NaN value or a zero error is left out
    /// with its own flag as the reason.
    #[test]
    fn all_flagged_dithers_fall_back_to_the_finite_ones() {
        let mut first = dithers(&[(0.01, 0.001), (0.011, 0.001), (f64::NAN, 0.001), (0.5, 0.0)]);
        for d in first.iter_mut() {
            d.rejected = Some("saturated".into());
        }
        let c = component_with_first(first);
        let o = &c.orientations.as_ref().unwrap()[0];
        assert_eq!((o.n_dithers, o.n_dithers_total), (2, 4), "{o:?}");
        assert!((o.f - 0.0105).abs() < 1e-15, "{o:?}");
        let dropped: Vec<(&str, &str)> = c
            .dropped_dithers
            .iter()
            .flatten()
            .map(|d| (d.file.as_str(), d.reason.as_str()))
            .collect();
        assert_eq!(
            dropped,
            [
                ("orientation 1 dither 3", "saturated"),
                ("orientation 1 dither 4", "saturated")
            ]
        );
        assert!(
            c.flags.iter().any(|f| f.is(FlagCode::UsedFlaggedDithers)),
            "{:?}",
            c.flags
        );
        assert!(!c.flags.iter().any(|f| f.is(FlagCode::DitherClipped)), "{:?}", c.flags);
        // An outlier among flagged values in use is clipped, and said so.
        let mut first = dithers(&[(0.01, 0.001), (0.0101, 0.001), (0.0099, 0.001), (0.05, 0.001)]);
        for d in first.iter_mut() {
            d.rejected = Some("saturated".into());
        }
        let c = component_with_first(first);
        let dropped: Vec<(&str, &str)> = c
            .dropped_dithers
            .iter()
            .flatten()
            .map(|d| (d.file.as_str(), d.reason.as_str()))
            .collect();
        assert_eq!(dropped, [("orientation 1 dither 4", "clipped")]);
        // Flagged once, after the flags the fallback set (`saturated`, `used_flagged_dithers`).
        let n = c.flags.iter().filter(|f| f.is(FlagCode::DitherClipped)).count();
        assert_eq!(n, 1, "{:?}", c.flags);
    }

    #[test]
    fn unverified_ab_identity_fails_the_cut_whatever_the_snr() {
        let params = MeasureParams::default();
        let t = target_entry(
            "X",
            &orients(),
            &measured(Vec::new()),
            &params,
            &sofipol_calib::Profile::sofi(),
        );
        assert!(t.components.iter().all(|c| c.passes_cut), "{t:?}");
        assert!(t.delta_gamma_deg.is_some());
        let flag =
            "ab_identity_unverified: companion not found at POSANG 90.0 and the components are near equal in flux";
        let t = target_entry(
            "X",
            &orients(),
            &measured(vec![Flag::parse(flag)]),
            &params,
            &sofipol_calib::Profile::sofi(),
        );
        for c in &t.components {
            assert!(!c.passes_cut, "{c:?}");
            assert!(c.flags.iter().any(|f| f.is(FlagCode::AbIdentityUnverified)), "{c:?}");
            // Still reported (the value is there, not a detection).
            assert!(c.q.is_finite() && c.snr.unwrap() > 10.0, "{c:?}");
        }
        assert!(t.delta_gamma_deg.is_none());
        assert!(crate::solve::refused_by_flags(&[Flag::new(
            FlagCode::AbIdentityUnverified
        )]));
        assert!(crate::solve::refused_by_flags(&[Flag::new(
            FlagCode::UsedFlaggedDithers
        )]));
        assert!(!crate::solve::refused_by_flags(&[
            Flag::new(FlagCode::LowSnr),
            Flag::new(FlagCode::BadPixels)
        ]));
    }

    /// One orientation's dithers as values (F, sigma_F) with unit beam fluxes.
    fn dithers(values: &[(f64, f64)]) -> Vec<DitherValue> {
        values
            .iter()
            .map(|&(f, sigma_f)| DitherValue {
                f,
                sigma_f,
                o: BeamFlux {
                    flux: 1e4,
                    ..BeamFlux::missing()
                },
                e: BeamFlux {
                    flux: 1e4,
                    ..BeamFlux::missing()
                },
                rejected: None,
            })
            .collect()
    }

    /// Three dithers that agree (sigma 0.001) at orientation `k` of 0/45/90/135, of q = 0.01,
    /// u = 0.
    fn agreeing(k: usize) -> Vec<DitherValue> {
        dithers(&[([0.01, 0.0, -0.01, 0.0][k], 0.001); 3])
    }

    /// A component at 0/45/90/135 whose first orientation is `first` and the others
    /// [`agreeing`].
    fn component_with_first(first: Vec<DitherValue>) -> Component {
        let per = vec![first, agreeing(1), agreeing(2), agreeing(3)];
        let none = vec![vec![None; 3]; 4];
        component_from_dithers(
            "A",
            &per,
            &[0.0, 45.0, 90.0, 135.0],
            &none,
            &[],
            &MeasureParams::default(),
            &sofipol_calib::Profile::sofi(),
        )
    }

    /// Two dithers at F = 0.01 -+ d (sigma 0.001): chi2 = 2 (d/0.001)^2 on one degree of
    /// freedom. The error is inflated by sqrt(chi2/dof) exactly when the chi2 probability
    /// is below 0.01 (chi2 > 6.635), and flagged; else it is the propagated 0.001/sqrt 2.
    #[test]
    fn excess_dither_scatter_inflates_the_error_by_sqrt_chi2_per_dof() {
        let prop = 0.001 / 2f64.sqrt();
        for (chi2, inflated) in [(0.5, false), (6.4, false), (6.9, true), (18.0, true)] {
            let d: f64 = 0.001 * (chi2 / 2.0f64).sqrt();
            let c = component_with_first(dithers(&[(0.01 - d, 0.001), (0.01 + d, 0.001)]));
            let o = &c.orientations.as_ref().unwrap()[0];
            assert_eq!(o.n_dithers, 2);
            assert!((o.chi2 - chi2).abs() < 1e-9, "{o:?}");
            assert!((o.sigma_f_propagated - prop).abs() < 1e-15, "{o:?}");
            let want = if inflated { prop * chi2.sqrt() } else { prop };
            assert!((o.sigma_f - want).abs() < 1e-12 * want, "chi2 {chi2}: {o:?}");
            assert_eq!(
                c.flags.iter().any(|f| f.is(FlagCode::ExcessDitherScatter)),
                inflated,
                "{:?}",
                c.flags
            );
            // The other orientations agree: not inflated.
            let o = &c.orientations.as_ref().unwrap()[1];
            assert!((o.sigma_f - 0.001 / 3f64.sqrt()).abs() < 1e-15, "{o:?}");
        }
        // Three dithers at 0.01 - 3s, 0.01, 0.01 + 3s (none clipped at 4 sigma): chi2 = 18 on
        // two degrees of freedom, the error inflated by sqrt(18/2) = 3.
        let c = component_with_first(dithers(&[(0.007, 0.001), (0.01, 0.001), (0.013, 0.001)]));
        let o = &c.orientations.as_ref().unwrap()[0];
        assert_eq!(o.n_dithers, 3);
        assert!((o.sigma_f - 3.0 * 0.001 / 3f64.sqrt()).abs() < 1e-12, "{o:?}");
        // A single dither has no scatter to judge: its own error.
        let c = component_with_first(dithers(&[(0.5, 0.001)]));
        let o = &c.orientations.as_ref().unwrap()[0];
        assert_eq!((o.n_dithers, o.sigma_f), (1, 0.001));
    }

    /// The weighted parallactic mean, against values worked by hand: weights 1/sigma^2,
    /// (cos 2eta, sin 2eta) averaged as they are, eta as a circular mean.
    #[test]
    fn the_parallactic_mean_is_weighted_as_f_is() {
        // eta = 0 and 90 deg with weights 1 and 3: cos 2eta = (1 - 3)/4, sin 2eta = 0, and
        // the circular mean atan2(3, 1).
        let m = ParallacticMean::of(&[0.0, 90.0], &[1.0, 1.0 / 3f64.sqrt()]).unwrap();
        assert!(
            (m.cos_sin_2eta[0] + 0.5).abs() < 1e-12 && m.cos_sin_2eta[1].abs() < 1e-12,
            "{m:?}"
        );
        assert!((m.eta_deg - 3f64.atan().to_degrees()).abs() < 1e-9, "{m:?}");
        // +-20 deg, equal weights: (cos 40, 0), mean 0.
        let m = ParallacticMean::of(&[20.0, -20.0], &[0.5, 0.5]).unwrap();
        assert!((m.cos_sin_2eta[0] - 40f64.to_radians().cos()).abs() < 1e-12, "{m:?}");
        assert!(m.cos_sin_2eta[1].abs() < 1e-12 && m.eta_deg.abs() < 1e-9, "{m:?}");
        // Across +-180: 170 and -174 average to 178, not to -2.
        let m = ParallacticMean::of(&[170.0, -174.0], &[1.0, 1.0]).unwrap();
        assert!((m.eta_deg - 178.0).abs() < 1e-9, "{m:?}");
        let (c, s) = ((340f64.to_radians()).cos(), (-348f64.to_radians()).sin());
        let want = [
            (c + (-348f64.to_radians()).cos()) / 2.0,
            ((340f64.to_radians()).sin() + s) / 2.0,
        ];
        assert!((m.cos_sin_2eta[0] - want[0]).abs() < 1e-12 && (m.cos_sin_2eta[1] - want[1]).abs() < 1e-12);
        // Without a finite angle and weight for every dither: no mean.
        assert_eq!(ParallacticMean::of(&[], &[]), None);
        assert_eq!(ParallacticMean::of(&[10.0, f64::NAN], &[1.0, 1.0]), None);
        assert_eq!(ParallacticMean::of(&[10.0, 20.0], &[1.0, 0.0]), None);
        assert_eq!(ParallacticMean::of(&[10.0, 20.0], &[1.0, f64::INFINITY]), None);
    }

    /// The component's parallactic angle and flux come from the dithers kept, matched by
    /// index after the rejected ones are left out; photometry flags of a used dither reach
    /// the component; a value that is not a number is "no value", not "clipped", and does
    /// not flag the component `dither_clipped`.
    #[test]
    fn kept_dithers_carry_their_angle_flux_and_photometry_flags() {
        let mut first = dithers(&[
            (0.01, 0.001),
            (0.01, 0.002),
            (0.01, 0.001),
            (f64::NAN, 0.001),
            (0.01, 0.0),
        ]);
        first[0].rejected = Some("cosmic_ray".into());
        first[0].o.flux = 9e9;
        first[1].o.flux = 3e4;
        first[1].e.phot_flags = crate::photometry::Flags::ANNULUS_CONTAMINATED.0;
        // The same flag on both beams of a dither, and on a second dither: flagged once.
        let overlap = crate::photometry::Flags::COMPANION_OVERLAP.0;
        (first[2].o.phot_flags, first[2].e.phot_flags) = (overlap, overlap);
        let mut second = agreeing(1);
        (second[0].o.phot_flags, second[0].e.phot_flags) = (overlap, overlap);
        let per = vec![first, second, agreeing(2), agreeing(3)];
        let mut eta = vec![vec![Some(0.0); 3]; 4];
        // Dither 0 (rejected) at 50 deg must not count; kept dithers 1 and 2 at 0 and 90 deg
        // with weights 1/4 and 1: cos 2eta = (1/4 - 1)/(5/4) = -0.6.
        eta[0] = vec![Some(50.0), Some(0.0), Some(90.0), Some(0.0), Some(0.0)];
        let files = vec![vec![
            "a.fits".to_string(),
            "b.fits".into(),
            "c.fits".into(),
            "d.fits".into(),
            "e.fits".into(),
        ]];
        let c = component_from_dithers(
            "A",
            &per,
            &[0.0, 45.0, 90.0, 135.0],
            &eta,
            &files,
            &MeasureParams::default(),
            &sofipol_calib::Profile::sofi(),
        );
        let o = &c.orientations.as_ref().unwrap()[0];
        assert_eq!((o.n_dithers, o.n_dithers_total), (2, 5));
        let p = o.parallactic_2eta.unwrap();
        assert!((p[0] + 0.6).abs() < 1e-12 && p[1].abs() < 1e-12, "{o:?}");
        assert!(
            (o.parallactic_deg.unwrap() - 4f64.atan().to_degrees()).abs() < 1e-9,
            "{o:?}"
        );
        // Orientations without an angle for every kept dither get none.
        assert!(c.orientations.as_ref().unwrap()[1].parallactic_deg.is_some());
        // Flux: o + e averaged over the 11 dithers kept (the 3e4 one once), the rejected
        // 9e9 and the NaN left out.
        let want = (3e4 + 1e4 + 10.0 * 2e4) / 11.0;
        assert!((c.flux_adu.unwrap() - want).abs() < 1e-6, "{:?}", c.flux_adu);
        for f in [
            FlagCode::CompanionOverlap,
            FlagCode::AnnulusContaminated,
            FlagCode::CosmicRay,
        ] {
            assert_eq!(c.flags.iter().filter(|x| x.is(f)).count(), 1, "{f:?}: {:?}", c.flags);
        }
        let dropped: Vec<(&str, &str)> = c
            .dropped_dithers
            .iter()
            .flatten()
            .map(|d| (d.file.as_str(), d.reason.as_str()))
            .collect();
        assert_eq!(
            dropped,
            [("a.fits", "cosmic_ray"), ("d.fits", "no value"), ("e.fits", "no value")]
        );
        // Values that are not numbers were never clipped: no `dither_clipped`.
        assert!(!c.flags.iter().any(|f| f.is(FlagCode::DitherClipped)), "{:?}", c.flags);
        assert!(c.passes_cut && c.snr.unwrap() > 3.0, "{c:?}");
        assert!(!c.flags.iter().any(|f| f.is(FlagCode::LowSnr)), "{:?}", c.flags);
    }

    /// The cut and its flag: a component below S/N 3 is flagged `low_snr` and fails; the
    /// catalog values are those of the inversion (the fit's covariance kept).
    #[test]
    fn a_faint_polarization_is_flagged_low_snr_and_its_covariance_kept() {
        let per: Vec<Vec<DitherValue>> = [0.001, 0.0, -0.001, 0.0]
            .iter()
            .map(|&f| dithers(&[(f, 0.001); 3]))
            .collect();
        let none = vec![vec![None; 3]; 4];
        let c = component_from_dithers(
            "B",
            &per,
            &[0.0, 45.0, 90.0, 135.0],
            &none,
            &[],
            &MeasureParams::default(),
            &sofipol_calib::Profile::sofi(),
        );
        // q = 0.001, sigma_q = sigma_u = (0.001/sqrt 3)/sqrt 2: S/N = sqrt 6 < 3.
        let s = 0.001 / 6f64.sqrt();
        assert!((c.q - 0.001).abs() < 1e-15 && c.u.abs() < 1e-15, "{c:?}");
        assert!((c.sigma_q_stat.unwrap() - s).abs() < 1e-15, "{c:?}");
        assert!((c.snr.unwrap() - 6f64.sqrt()).abs() < 1e-9, "{c:?}");
        assert!(c.cov_qu.unwrap().abs() < 1e-20 && c.cov_qu == c.cov_qu_stat, "{c:?}");
        // The statistical errors are the inversion's, of this q, u and covariance.
        let cov = QuCovariance {
            var_q: s * s,
            var_u: s * s,
            cov_qu: c.cov_qu.unwrap(),
        };
        let lp = LinearPolarization::from_qu_cov(c.q, c.u, &cov, MeasureParams::default().debias);
        assert!((c.sigma_u_stat.unwrap() - s).abs() < 1e-15, "{c:?}");
        assert!(
            (c.sigma_gamma_stat_deg.unwrap() - lp.sigma_gamma_deg).abs() < 1e-9,
            "{c:?}"
        );
        assert!(
            (c.sigma_gamma_nkc_deg.unwrap() - lp.sigma_gamma_nkc_deg).abs() < 1e-9,
            "{c:?}"
        );
        assert!(lp.sigma_gamma_deg > 5.0 && lp.sigma_gamma_nkc_deg > 5.0, "{lp:?}");
        assert!(!c.passes_cut);
        assert!(c.flags.iter().any(|f| f.is(FlagCode::LowSnr)), "{:?}", c.flags);
        // Angles that do not separate q from u: no value, said so.
        let c = component_from_dithers(
            "B",
            &per[..1],
            &[0.0],
            &none,
            &[],
            &MeasureParams::default(),
            &sofipol_calib::Profile::sofi(),
        );
        assert!(c.q.is_nan() && !c.passes_cut);
        assert!(
            c.flags.iter().any(|f| f.is(FlagCode::UndefinedPolarization)),
            "{:?}",
            c.flags
        );
    }

    /// Status and error of the target: both components measured is OK (no error); one is
    /// partial, with the measurement's first flag as its reason (or which star was not
    /// measured); none is failed, with that flag after the reason.
    #[test]
    fn the_status_and_error_say_what_was_measured() {
        let params = MeasureParams::default();
        let kw = &sofipol_calib::Profile::sofi();
        let t = target_entry("X", &orients(), &measured(Vec::new()), &params, kw);
        assert_eq!((t.status, t.error.clone()), (Status::Ok, None));
        assert_eq!(t.eo_offset_px, Some([0.0, 167.0]));
        assert_eq!((t.separation_arcsec, t.pa_deg), (Some(5.0), Some(340.0)));
        assert_eq!(t.orientations_deg, Some(vec![0.0, 45.0, 90.0, 135.0]));
        assert_eq!((t.fwhm_px, t.aperture_radius_px), (Some(3.0), Some(3.0)));
        assert_eq!(t.photometry.as_deref(), Some("aperture"));
        assert_eq!(t.flags.as_deref(), Some(&[][..]));
        let mut m = measured(Vec::new());
        m.dithers.truncate(1);
        let t = target_entry("X", &orients(), &m, &params, kw);
        assert_eq!(t.error.as_deref(), Some("companion not measured"));
        m.flags = vec![Flag::new(FlagCode::CompanionNotFound)];
        let t = target_entry("X", &orients(), &m, &params, kw);
        assert_eq!(
            (t.status, t.error.as_deref()),
            (Status::Partial, Some("companion_not_found"))
        );
        // One star measured, the other not (every dither missing): partial, and said which.
        let without = |star: usize, reason: &str| {
            let mut m = measured(Vec::new());
            for d in m.dithers[star].iter_mut().flatten() {
                *d = DitherValue::missing(reason);
            }
            m
        };
        let mut m = without(0, "primary_not_found");
        for (m, want) in [
            (&m, "primary not measured"),
            (&without(1, "companion_not_found"), "companion not measured"),
        ] {
            let t = target_entry("X", &orients(), m, &params, kw);
            assert_eq!((t.status, t.error.as_deref()), (Status::Partial, Some(want)));
        }
        for d in m.dithers[1].iter_mut().flatten() {
            *d = DitherValue::missing("primary_not_found");
        }
        m.flags = vec![Flag::parse("sky too bright")];
        let t = target_entry("X", &orients(), &m, &params, kw);
        assert_eq!(t.status, Status::Failed);
        assert_eq!(
            t.error.as_deref(),
            Some("no component could be measured: sky too bright")
        );
    }

    /// The frames' parallactic angles reach the catalog: each dither's from its header (the
    /// mean of start and end), averaged per orientation; a frame whose angle cannot be
    /// read leaves its orientation without one and is named in the target's flags; the
    /// frames name the dithers left out.
    #[test]
    fn the_frames_parallactic_angles_reach_each_orientation() {
        let kw = sofipol_calib::Profile::sofi();
        let mut orients = orients();
        for (k, o) in orients.iter_mut().enumerate() {
            for i in 0..3 {
                let mut h = sofipol_calib::header::Header::new(format!("o{k}d{i}.fits"));
                let start = 10.0 * k as f64 + i as f64;
                if (k, i) == (3, 1) {
                    h.set(&kw.keywords.parang, "east");
                } else {
                    h.set(&kw.keywords.parang, start);
                    h.set(&kw.keywords.parang_end, start + 2.0);
                }
                o.frames
                    .push(sofipol_calib::frame::Frame::new(ndarray::Array2::zeros((1, 1)), h));
            }
        }
        let mut m = measured(Vec::new());
        m.dithers[0][2][1].rejected = Some("cosmic_ray".into());
        let t = target_entry("X", &orients, &m, &MeasureParams::default(), &kw);
        let flags = t.flags.clone().unwrap();
        assert_eq!(flags.len(), 1, "{flags:?}");
        assert!(flags[0].is(FlagCode::ParallacticAngleNotUsed), "{flags:?}");
        for (ci, c) in t.components.iter().enumerate() {
            let per = c.orientations.as_ref().unwrap();
            for (k, o) in per.iter().enumerate() {
                // Dithers at 10k + 1, + 2, + 3 deg (equal weights); A's dither 2 of the third
                // orientation dropped: 21 and 23, mean 22 all the same.
                let want = 10.0 * k as f64 + 2.0;
                if k == 3 {
                    // The dither whose frame has no readable angle is left out: 31 and 33
                    // remain, the orientation keeps their mean.
                    assert_eq!(o.n_dithers, 2, "{o:?}");
                    assert!((o.parallactic_deg.unwrap() - 32.0).abs() < 1e-9, "{o:?}");
                } else {
                    let got = o.parallactic_deg.unwrap();
                    assert!((got - want).abs() < 1e-9, "component {ci} orientation {k}: {got}");
                    let c2 = o.parallactic_2eta.unwrap()[0];
                    let mean_cos: f64 = if ci == 0 && k == 2 {
                        [21.0f64, 23.0]
                            .iter()
                            .map(|e| (2.0 * e.to_radians()).cos())
                            .sum::<f64>()
                            / 2.0
                    } else {
                        (1..=3)
                            .map(|i| (2.0 * (want - 2.0 + i as f64).to_radians()).cos())
                            .sum::<f64>()
                            / 3.0
                    };
                    assert!((c2 - mean_cos).abs() < 1e-12, "component {ci} orientation {k}");
                }
            }
        }
        let dropped = t.components[0].dropped_dithers.clone().unwrap();
        let pairs: Vec<(&str, &str)> = dropped.iter().map(|d| (d.file.as_str(), d.reason.as_str())).collect();
        assert_eq!(
            pairs,
            [("o2d1.fits", "cosmic_ray"), ("o3d1.fits", "no_parallactic_angle")]
        );
        for c in &t.components {
            assert!(
                c.flags.iter().any(|f| f.is(FlagCode::NoParallacticAngle)),
                "{:?}",
                c.flags
            );
        }
    }

    /// A frame without the keyword among frames with it: named, its dither left out; with
    /// no angle anywhere, nothing is left out and nothing is flagged.
    #[test]
    fn a_frame_without_a_parallactic_angle_is_left_out_only_when_others_have_one() {
        let kw = sofipol_calib::Profile::sofi();
        let build = |with_angles: bool| {
            let mut orients = orients();
            for (k, o) in orients.iter_mut().enumerate() {
                for i in 0..3 {
                    let mut h = sofipol_calib::header::Header::new(format!("o{k}d{i}.fits"));
                    if with_angles && (k, i) != (1, 0) {
                        h.set(&kw.keywords.parang, 20.0);
                    }
                    o.frames
                        .push(sofipol_calib::frame::Frame::new(ndarray::Array2::zeros((1, 1)), h));
                }
            }
            target_entry("X", &orients, &measured(Vec::new()), &MeasureParams::default(), &kw)
        };
        let t = build(true);
        let flags = t.flags.clone().unwrap();
        assert_eq!(
            flags,
            [Flag::parse(
                "parallactic angle not used: o1d0.fits: no ESO TEL PARANG START"
            )]
        );
        assert!(flags[0].is(FlagCode::ParallacticAngleNotUsed));
        let per = t.components[0].orientations.as_ref().unwrap();
        assert_eq!(per[1].n_dithers, 2);
        assert!(
            per.iter().all(|o| (o.parallactic_deg.unwrap() - 20.0).abs() < 1e-9),
            "{per:?}"
        );
        let t = build(false);
        assert!(t.flags.clone().unwrap().is_empty());
        let c = &t.components[0];
        assert!(c.dropped_dithers.is_none() && !c.flags.iter().any(|f| f.is(FlagCode::NoParallacticAngle)));
        assert!(c
            .orientations
            .as_ref()
            .unwrap()
            .iter()
            .all(|o| o.parallactic_deg.is_none() && o.n_dithers == 3));
    }
}
