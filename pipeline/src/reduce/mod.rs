//! Reduction of one target sequence, from calibrated (sky-subtracted) frames to a catalog
//! entry.
//!
//! ```text
//! per orientation: sky-subtracted frames (data, variance, mask) + header jitter offsets
//!   -> primary: header offset + centroid in every frame (blend centroid C_i)
//!   -> e-o offset: median over frames of (e centroid - o centroid)
//!   -> companion: two-star PSF fit on the registered stack of the dithers; the offsets
//!      found at all orientations give one separation and PA (rotation convention)
//!   -> per frame and beam: two-star PSF fit (deblending), then
//!        separation >= deblend limit: aperture photometry of each star on the frame with
//!                                     the companion's model subtracted (exact overlap)
//!        closer:                      PSF-fit fluxes
//!   -> F = (o - e)/(o + e) per dither, dithers with bad pixels / cosmics / saturation in
//!      an aperture dropped, clipped at `clip_sigma`, weighted mean per orientation
//!   -> q, u (least squares over orientations), P, gamma, errors, debiasing, cut
//! ```
pub mod locate;
pub mod target;

use ndarray::{s, Array2};
use serde::{Deserialize, Serialize};
use sofipol_calib::frame::mask as mbits;
use sofipol_calib::{Frame, Profile};

use crate::catalog::{self, Component, Status, Target};
use crate::photometry::{fit_psf, measure, subtract_star, Method, PhotParams, PsfFitParams, PsfModel};
use crate::stokes::inversion::{clip_dithers, combine_dithers, fit_qu, Debias, LinearPolarization};
use crate::stokes::model::companion_offset_px;
use locate::*;

/// Settings of the measurement (defaults are the documented choices, docs/configuration.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeasureParams {
    /// Aperture radius in units of the frame's FWHM.
    pub aperture_fwhm: f64,
    /// Residual-background annulus (inner, outer) in units of the median FWHM.
    pub annulus_fwhm: (f64, f64),
    /// Aperture pixel-weighting method.
    pub method: Method,
    /// Pairs closer than this many FWHM are measured by PSF fitting instead of apertures.
    pub psf_photometry_below_fwhm: f64,
    /// Search radius for the primary around its nominal position, px.
    pub primary_search_px: f64,
    /// Nominal position of the primary's ordinary image at zero jitter offset (x, y) px;
    /// None: detector centre in x, middle of the o-target strip in y.
    pub nominal_xy_px: Option<(f64, f64)>,
    /// Largest companion separation searched, arcsec.
    pub companion_search_arcsec: f64,
    /// Companion accepted when its stacked flux S/N exceeds this.
    pub min_companion_snr: f64,
    /// ... and the two-star fit of the stack beats the one-star fit with an F statistic
    /// above this (3 and n-7 degrees of freedom; a lone star gives ~1).
    pub min_companion_f: f64,
    /// ... and lies at least this far from the primary, arcsec (the study's closest pair
    /// is 0.5").
    pub min_companion_sep_arcsec: f64,
    /// Dither values further than this many sigma from the others are rejected.
    pub clip_sigma: f64,
    /// P / sigma_P threshold of the cut.
    pub cut_snr: f64,
    /// Debiasing estimator.
    pub debias: Debias,
    /// Known separation (arcsec) and PA (deg) of the companion, when a target list gives it.
    pub companion_hint: Option<(f64, f64)>,
    /// PSF model of the stack and per-frame fits (deblending and PSF-fit fluxes). Default: a
    /// circular Moffat with beta fitted, `{ kind = "moffat" }`, since seeing-limited PSFs have
    /// Moffat wings that a Gaussian misfits; `{ kind = "moffat", beta = 3.0 }` fixes beta,
    /// `{ kind = "gaussian" }` restores the Gaussian fit.
    pub psf_model: PsfModel,
    /// With a Moffat model of free beta: measure beta on the registered stacks and hold it
    /// fixed in the per-frame fits.
    pub beta_from_stack: bool,
}

impl Default for MeasureParams {
    fn default() -> Self {
        MeasureParams {
            aperture_fwhm: 1.0,
            annulus_fwhm: (4.0, 6.0),
            method: Method::Exact,
            psf_photometry_below_fwhm: 2.0,
            primary_search_px: 60.0,
            nominal_xy_px: None,
            companion_search_arcsec: 6.0,
            min_companion_snr: 5.0,
            min_companion_f: 50.0,
            min_companion_sep_arcsec: 0.3,
            clip_sigma: 4.0,
            cut_snr: 3.0,
            debias: Debias::WardleKronberg,
            companion_hint: None,
            psf_model: PsfModel::Moffat { beta: None },
            beta_from_stack: true,
        }
    }
}

/// The dithers of one orientation after calibration.
#[derive(Debug, Clone)]
pub struct CalibratedOrientation {
    /// Rotator position angle, deg.
    pub posang_deg: f64,
    /// Analyzer angle, deg.
    pub analyzer_deg: f64,
    /// Sky-subtracted frames with variance and mask.
    pub frames: Vec<Frame>,
    /// Header jitter offsets (dx, dy), px.
    pub offsets: Vec<[f64; 2]>,
}

/// One star in one beam of one frame.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BeamFlux {
    /// Flux, ADU.
    pub flux: f64,
    /// Variance, ADU^2.
    pub var: f64,
    /// Position (x, y), px.
    pub xy: (f64, f64),
    /// Aperture-photometry flags of this measurement ([`crate::photometry::Flags`] bits;
    /// 0 for PSF-fit fluxes).
    pub phot_flags: u32,
}

/// Per-dither measurement of one component.
#[derive(Debug, Clone, Serialize)]
pub struct DitherValue {
    /// F = (o - e)/(o + e).
    pub f: f64,
    /// sigma_F.
    pub sigma_f: f64,
    /// o beam.
    pub o: BeamFlux,
    /// e beam.
    pub e: BeamFlux,
    /// Why this dither is not used (None: used unless clipped).
    pub rejected: Option<String>,
}

/// The intermediate results of a measured sequence (for diagnostics and plots).
#[derive(Debug, Clone, Serialize)]
pub struct Measured {
    /// e-o offset found, px.
    pub eo_offset_px: (f64, f64),
    /// Median FWHM, px.
    pub fwhm_px: f64,
    /// Separation (arcsec) and PA (deg) of B from A, when B was found.
    pub geometry: Option<(f64, f64)>,
    /// Photometry method: "aperture" or "psf_fit".
    pub photometry: String,
    /// Aperture radius used (median over frames), px.
    pub aperture_px: f64,
    /// Per component, per orientation, per dither.
    pub dithers: Vec<Vec<Vec<DitherValue>>>,
    /// Target flags.
    pub flags: Vec<String>,
}

/// An error that stops the measurement of a sequence.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct MeasureError(pub String);

fn cutout(frame: &Frame, cx: f64, cy: f64, h: usize) -> (Array2<f32>, Array2<f32>, Array2<u8>, Array2<u8>, (f64, f64)) {
    let (ny, nx) = frame.shape();
    let x0 = (cx.round() as i64 - h as i64).clamp(0, nx as i64 - 1) as usize;
    let y0 = (cy.round() as i64 - h as i64).clamp(0, ny as i64 - 1) as usize;
    let x1 = (cx.round() as usize + h + 1).min(nx);
    let y1 = (cy.round() as usize + h + 1).min(ny);
    let sl = s![y0..y1, x0..x1];
    let img = frame.data.slice(sl).to_owned();
    let var = match &frame.variance {
        Some(v) => v.slice(sl).to_owned(),
        None => Array2::from_elem(img.raw_dim(), 1.0),
    };
    let bits = frame.mask.slice(sl).to_owned();
    let bad = bits.mapv(|m| u8::from(m & UNUSABLE != 0));
    (img, var, bad, bits, (x0 as f64, y0 as f64))
}

/// Mask bits inside radius r of (x, y) in a cut-out.
fn bits_inside(bits: &Array2<u8>, x: f64, y: f64, r: f64) -> u8 {
    let (ny, nx) = bits.dim();
    let mut acc = 0u8;
    let rr = r.ceil() as i64 + 1;
    for j in (y.round() as i64 - rr).max(0)..=(y.round() as i64 + rr).min(ny as i64 - 1) {
        for i in (x.round() as i64 - rr).max(0)..=(x.round() as i64 + rr).min(nx as i64 - 1) {
            if ((i as f64 - x).powi(2) + (j as f64 - y).powi(2)).sqrt() <= r + 0.71 {
                acc |= bits[[j as usize, i as usize]];
            }
        }
    }
    acc
}

fn bit_names(b: u8) -> Vec<String> {
    let mut v = Vec::new();
    if b & (mbits::BAD | mbits::OFF_STRIP) != 0 {
        v.push("bad_pixels".to_string());
    }
    if b & mbits::COSMIC != 0 {
        v.push("cosmic_ray".to_string());
    }
    if b & mbits::SATURATED != 0 {
        v.push("saturated".to_string());
    }
    if b & mbits::NONLINEAR != 0 {
        v.push("nonlinear".to_string());
    }
    v
}

/// Measure both components of a calibrated sequence.
pub fn measure_sequence(
    orients: &[CalibratedOrientation],
    profile: &Profile,
    params: &MeasureParams,
) -> Result<Measured, MeasureError> {
    let g = &profile.geometry;
    let scale = g.pixscale_arcsec;
    let orow = g.o_target;
    let err = |m: String| MeasureError(m);
    let first = orients
        .first()
        .and_then(|o| o.frames.first())
        .ok_or_else(|| err("no frames".into()))?;
    let (_, nx) = first.shape();
    let mut flags: Vec<String> = Vec::new();

    // 1. The primary (blend centroid) in every frame.
    let nominal = params
        .nominal_xy_px
        .unwrap_or((nx as f64 / 2.0, (orow[0] + orow[1]) as f64 / 2.0 - 0.5));
    // Unusable-pixel masks, once per frame (centring, e-o correlation and stacks use them).
    let masks_all: Vec<Vec<Array2<u8>>> = orients
        .iter()
        .map(|o| o.frames.iter().map(unusable).collect())
        .collect();
    let o0 = &orients[0];
    let m0 = &masks_all[0][0];
    let (px, py, _) = brightest_peak(
        o0.frames[0].data.view(),
        m0.view(),
        nominal.0 + o0.offsets[0][0],
        nominal.1 + o0.offsets[0][1],
        params.primary_search_px,
        orow,
    )
    .ok_or_else(|| {
        err(format!(
            "no source found within {} px of the nominal target position",
            params.primary_search_px
        ))
    })?;
    let fwhm_guess = 0.8 / scale;
    let c0 = refine(o0.frames[0].data.view(), m0.view(), px, py, fwhm_guess, 4.0).unwrap_or((px, py));
    let anchor = (c0.0 - o0.offsets[0][0], c0.1 - o0.offsets[0][1]);
    // Within an orientation every frame is registered on the same star: the first frame's
    // centre (brightest peak near the header position) carried by the header offsets and
    // refined by a centroid. Picking the brightest peak in every frame would jump between
    // the components of a near-equal pair.
    let mut centres: Vec<Vec<Option<(f64, f64)>>> = Vec::new();
    for (o, ms) in orients.iter().zip(&masks_all) {
        let mut cs: Vec<Option<(f64, f64)>> = Vec::new();
        let mut first: Option<((f64, f64), [f64; 2])> = None;
        for ((f, off), m) in o.frames.iter().zip(&o.offsets).zip(ms) {
            let c = match first {
                Some((c1, off1)) => {
                    let guess = (c1.0 + off[0] - off1[0], c1.1 + off[1] - off1[1]);
                    refine(f.data.view(), m.view(), guess.0, guess.1, fwhm_guess, 3.0).or_else(|| {
                        // A defect or cosmic ray near the guess: restart from the brightest
                        // peak within the pointing tolerance.
                        brightest_peak(f.data.view(), m.view(), guess.0, guess.1, 3.0, orow)
                            .and_then(|(x, y, _)| refine(f.data.view(), m.view(), x, y, fwhm_guess, 3.0))
                    })
                }
                None => {
                    let guess = (anchor.0 + off[0], anchor.1 + off[1]);
                    let peak = brightest_peak(f.data.view(), m.view(), guess.0, guess.1, 8.0, orow);
                    let c = peak.and_then(|(x, y, _)| refine(f.data.view(), m.view(), x, y, fwhm_guess, 4.0));
                    if let Some(c) = c {
                        first = Some((c, *off));
                    }
                    c
                }
            };
            cs.push(c);
        }
        centres.push(cs);
    }
    // The e-o offset, by cross-correlating the o and e images of the target.
    let (mut fr, mut cc) = (Vec::new(), Vec::new());
    for ((o, cs), ms) in orients.iter().zip(&centres).zip(&masks_all) {
        for ((f, c), m) in o.frames.iter().zip(cs).zip(ms) {
            if let Some(c) = c {
                fr.push((&f.data, m));
                cc.push(*c);
            }
        }
    }
    let h_corr = (2.5 * fwhm_guess).ceil() as usize + 4;
    let eo = eo_offset_by_correlation(&fr, &cc, (g.eo_offset_px[0], g.eo_offset_px[1]), h_corr, 5)
        .ok_or_else(|| err("could not measure the e-o beam offset (target too close to the strip edges)".into()))?;
    if (eo.0 - g.eo_offset_px[0]).hypot(eo.1 - g.eo_offset_px[1]) > 3.0 {
        flags.push(format!("eo_offset_differs_from_profile: ({:.2}, {:.2}) px", eo.0, eo.1));
    }

    // 2. The companion, orientation by orientation, on registered stacks.
    let search_px = params.companion_search_arcsec / scale;
    let h = (search_px + 3.0 * fwhm_guess).ceil() as usize;
    let mut found: Vec<Option<PairOnStack>> = Vec::new();
    let mut fwhms = Vec::new();
    for ((o, cs), masks) in orients.iter().zip(&centres).zip(&masks_all) {
        let (mut fr, mut cc) = (Vec::new(), Vec::new());
        for ((f, m), c) in o.frames.iter().zip(masks).zip(cs) {
            if let Some(c) = c {
                fr.push((&f.data, m));
                cc.push(*c);
            }
        }
        if fr.is_empty() {
            found.push(None);
            continue;
        }
        let (stack, smask, frac) = stack_cutouts(&fr, &cc, h);
        let predicted = params
            .companion_hint
            .map(|(sep, pa)| companion_offset_px(sep, pa, o.posang_deg, scale));
        let p = find_pair(&stack, &smask, frac, fwhm_guess, search_px, predicted, params.psf_model);
        if let Some(p) = p {
            fwhms.push(p.fwhm_px);
        }
        found.push(p);
    }
    // Make A/B consistent across orientations: the companion of the best orientation
    // predicts where B is at the others; swap where the fit labelled them the other way.
    // A companion must both be significant in flux and improve the fit significantly
    // over a single star (F test on the stack): a lone star is otherwise split in two.
    let min_f = params.min_companion_f;
    let min_sep_px = params.min_companion_sep_arcsec / scale;
    let snr = |p: &PairOnStack| {
        if p.companion(min_f, min_sep_px) {
            p.flux.1 / p.flux_b_err.max(1e-30)
        } else {
            0.0
        }
    };
    let best = found
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.map(|p| (i, snr(&p))))
        .max_by(|a, b| a.1.total_cmp(&b.1));
    let mut geometry = None;
    if let Some((ib, best_snr)) = best {
        if best_snr >= params.min_companion_snr {
            let pb = found[ib].expect("best exists");
            let d = (pb.b.0 - pb.a.0, pb.b.1 - pb.a.1);
            let (sep0, pa0) = crate::stokes::model::offset_to_sep_pa(d.0, d.1, orients[ib].posang_deg, scale);
            let mut obs = Vec::new();
            for (i, p) in found.iter_mut().enumerate() {
                let Some(p) = p else { continue };
                let pred = companion_offset_px(sep0, pa0, orients[i].posang_deg, scale);
                let (dab, dba) = ((p.b.0 - p.a.0, p.b.1 - p.a.1), (p.a.0 - p.b.0, p.a.1 - p.b.1));
                if (dba.0 - pred.0).hypot(dba.1 - pred.1) < (dab.0 - pred.0).hypot(dab.1 - pred.1) {
                    std::mem::swap(&mut p.a, &mut p.b);
                    p.flux = (p.flux.1, p.flux.0);
                }
                if snr(p) >= params.min_companion_snr {
                    obs.push((orients[i].posang_deg, (p.b.0 - p.a.0, p.b.1 - p.a.1), snr(p).powi(2)));
                }
            }
            // A is the brighter over all orientations.
            let (fa, fb): (f64, f64) = found
                .iter()
                .flatten()
                .fold((0.0, 0.0), |acc, p| (acc.0 + p.flux.0, acc.1 + p.flux.1));
            if fb > fa {
                for p in found.iter_mut().flatten() {
                    std::mem::swap(&mut p.a, &mut p.b);
                    p.flux = (p.flux.1, p.flux.0);
                }
                for o in obs.iter_mut() {
                    o.1 = (-o.1 .0, -o.1 .1);
                }
            }
            // A real companion is seen at every orientation where the rotation puts it; a
            // fit artefact (blur, a cosmic ray in a stack) is not.
            let need = orients.len().min(2);
            match combine_geometry(&obs, scale) {
                Some(_) if obs.len() < need => {
                    flags.push(format!(
                        "companion_rejected: significant at {} of {} orientations",
                        obs.len(),
                        orients.len()
                    ));
                }
                Some((_, _, worst)) if worst > 1.5 => {
                    flags.push(format!(
                        "companion_rejected: positions disagree by {worst:.2} px between orientations"
                    ));
                }
                Some((sep, pa, worst)) => {
                    if worst > 0.5 {
                        flags.push(format!(
                            "companion_position_scatter: {worst:.2} px between orientations"
                        ));
                    }
                    geometry = Some((sep, pa));
                }
                None => {}
            }
        }
    }
    if geometry.is_none() {
        flags.push("companion_not_found".into());
    }
    // Moffat beta measured once on the stacks (the wings, which the whole-pixel
    // registration of the stack does not blur) and held fixed in the per-frame fits,
    // where only the seeing (alpha) changes: fewer free parameters, smaller flux errors
    // for close pairs, and faster fits.
    let mut betas: Vec<f64> = found
        .iter()
        .flatten()
        .map(|p| p.beta)
        .filter(|b| b.is_finite())
        .collect();
    betas.sort_by(|a, b| a.total_cmp(b));
    let frame_model = match (params.psf_model, params.beta_from_stack, betas.get(betas.len() / 2)) {
        (PsfModel::Moffat { beta: None }, true, Some(&b)) => PsfModel::Moffat { beta: Some(b) },
        (m, _, _) => m,
    };
    fwhms.sort_by(|a, b| a.total_cmp(b));
    let fwhm_med = if fwhms.is_empty() {
        fwhm_guess
    } else {
        fwhms[fwhms.len() / 2]
    };
    let sep_px = geometry.map(|(s, _)| s / scale).unwrap_or(f64::INFINITY);
    let use_psf = sep_px < params.psf_photometry_below_fwhm * fwhm_med;
    let ncomp = if geometry.is_some() { 2 } else { 1 };

    // 3. Per-frame photometry of both components in both beams.
    let mut dithers: Vec<Vec<Vec<DitherValue>>> = vec![Vec::new(); ncomp];
    let mut apertures = Vec::new();
    let mut refined_eo = Vec::new();
    let mut per_frame_offsets = Vec::new();
    for (k, (o, cs)) in orients.iter().zip(&centres).enumerate() {
        let rel_a = found[k].map(|p| p.a).unwrap_or((0.0, 0.0));
        let off_b = geometry.map(|(sep, pa)| companion_offset_px(sep, pa, o.posang_deg, scale));
        for c in dithers.iter_mut() {
            c.push(Vec::new());
        }
        for (f, c) in o.frames.iter().zip(cs) {
            let Some(c) = c else {
                flags.push(format!("primary not found in {}", f.path().display()));
                for comp in dithers.iter_mut() {
                    comp[k].push(DitherValue {
                        f: f64::NAN,
                        sigma_f: f64::NAN,
                        o: BeamFlux {
                            flux: f64::NAN,
                            var: f64::NAN,
                            xy: (f64::NAN, f64::NAN),
                            phot_flags: 0,
                        },
                        e: BeamFlux {
                            flux: f64::NAN,
                            var: f64::NAN,
                            xy: (f64::NAN, f64::NAN),
                            phot_flags: 0,
                        },
                        rejected: Some("primary_not_found".into()),
                    });
                }
                continue;
            };
            let a_o = (c.0 + rel_a.0, c.1 + rel_a.1);
            let mut stars = vec![a_o];
            if let Some(ob) = off_b {
                stars.push((a_o.0 + ob.0, a_o.1 + ob.1));
            }
            let mut beams: Vec<Vec<(BeamFlux, u8)>> = Vec::new();
            let mut fitted_a: [Option<(f64, f64)>; 2] = [None, None];
            let mut frame_fwhm = fwhm_med;
            for (bi, shift) in [(0.0, 0.0), eo].into_iter().enumerate() {
                let pos: Vec<(f64, f64)> = stars.iter().map(|&(x, y)| (x + shift.0, y + shift.1)).collect();
                let (cx, cy) = pos.iter().fold((0.0, 0.0), |a, p| {
                    (a.0 + p.0 / pos.len() as f64, a.1 + p.1 / pos.len() as f64)
                });
                let half = (params.annulus_fwhm.1 * fwhm_med + sep_px.min(40.0) + 4.0).ceil() as usize;
                let (img, var, bad, bits, (x0, y0)) = cutout(f, cx, cy, half);
                let local: Vec<(f64, f64)> = pos.iter().map(|&(x, y)| (x - x0, y - y0)).collect();
                let fitp = PsfFitParams {
                    fwhm_px: fwhm_med,
                    fit_radius_px: (1.5 * fwhm_med).max(3.0),
                    background: Some(0.0),
                    model: frame_model,
                    ..PsfFitParams::default()
                };
                let fit = fit_psf(img.view(), Some(var.view()), Some(bad.view()), &local, &fitp).ok();
                if bi == 0 {
                    if let Some(ft) = &fit {
                        frame_fwhm = ft.fwhm_x().clamp(0.5 * fwhm_med, 2.0 * fwhm_med);
                    }
                }
                let r_ap = (params.aperture_fwhm * frame_fwhm).max(1.0);
                // Centre apertures on the fitted positions (both beams are fitted freely,
                // so the e-o offset found above only needs to be good to a pixel).
                let local: Vec<(f64, f64)> = match &fit {
                    Some(ft) if ft.converged => ft.stars.iter().map(|st| (st.x, st.y)).collect(),
                    _ => local,
                };
                if let Some(&(ax, ay)) = local.first() {
                    fitted_a[bi] = Some((ax + x0, ay + y0));
                }
                if let (Some(ft), 2) = (&fit, local.len()) {
                    if ft.converged {
                        per_frame_offsets.push((o.posang_deg, (local[1].0 - local[0].0, local[1].1 - local[0].1), 1.0));
                    }
                }
                let mut out = Vec::new();
                for (si, &(lx, ly)) in local.iter().enumerate() {
                    let bits_in = bits_inside(&bits, lx, ly, r_ap);
                    if use_psf {
                        match &fit {
                            Some(ft) => {
                                let st = ft.stars[si];
                                out.push((
                                    BeamFlux {
                                        flux: st.flux,
                                        var: st.flux_err.powi(2),
                                        xy: (st.x + x0, st.y + y0),
                                        phot_flags: 0,
                                    },
                                    bits_in,
                                ));
                            }
                            None => out.push((
                                BeamFlux {
                                    flux: f64::NAN,
                                    var: f64::NAN,
                                    xy: (lx + x0, ly + y0),
                                    phot_flags: 0,
                                },
                                bits_in,
                            )),
                        }
                    } else {
                        // Deblend: subtract the other stars' models, then measure.
                        let mut work = img.clone();
                        if let Some(ft) = &fit {
                            for other in 0..local.len() {
                                if other != si {
                                    work = subtract_star(work.view(), ft, other);
                                }
                            }
                        }
                        let others: Vec<(f64, f64)> = local
                            .iter()
                            .enumerate()
                            .filter(|(j, _)| *j != si)
                            .map(|(_, p)| *p)
                            .collect();
                        let pp = PhotParams {
                            r_ap_px: r_ap,
                            annulus_px: Some((params.annulus_fwhm.0 * fwhm_med, params.annulus_fwhm.1 * fwhm_med)),
                            method: params.method,
                            companion_radius_px: r_ap,
                            annulus_exclude_radius_px: 2.0 * fwhm_med,
                            ..PhotParams::default()
                        };
                        let ph = measure(work.view(), Some(var.view()), Some(bad.view()), &pp, lx, ly, &others);
                        out.push((
                            BeamFlux {
                                flux: ph.flux,
                                var: ph.variance,
                                xy: (lx + x0, ly + y0),
                                phot_flags: ph.flags.0,
                            },
                            bits_in,
                        ));
                    }
                }
                if bi == 0 {
                    apertures.push(r_ap);
                }
                beams.push(out);
            }
            if let [Some(a), Some(b)] = fitted_a {
                refined_eo.push((a, b));
            }
            for (si, comp) in dithers.iter_mut().enumerate() {
                let (o_b, ob) = beams[0][si];
                let (e_b, eb) = beams[1][si];
                let tot = o_b.flux + e_b.flux;
                let fval = (o_b.flux - e_b.flux) / tot;
                let sigma_f = 2.0 * ((e_b.flux.powi(2) * o_b.var) + (o_b.flux.powi(2) * e_b.var)).sqrt() / tot.powi(2);
                let blocking = (ob | eb) & (mbits::BAD | mbits::COSMIC | mbits::SATURATED | mbits::OFF_STRIP);
                let pf = crate::photometry::Flags(o_b.phot_flags | e_b.phot_flags);
                let rejected = if !(fval.is_finite() && sigma_f.is_finite() && sigma_f > 0.0 && tot > 0.0) {
                    Some("photometry failed".to_string())
                } else if pf.contains(crate::photometry::Flags::TRUNCATED) {
                    Some("truncated".to_string())
                } else if blocking != 0 {
                    Some(bit_names(blocking).join(","))
                } else {
                    None
                };
                comp[k].push(DitherValue {
                    f: fval,
                    sigma_f,
                    o: o_b,
                    e: e_b,
                    rejected,
                });
            }
        }
    }
    apertures.sort_by(|a, b| a.total_cmp(b));
    let eo = median_offset(&refined_eo).unwrap_or(eo);
    // Report the geometry from the per-frame fits (the stack is registered to whole pixels).
    let geometry = match combine_geometry(&per_frame_offsets, scale) {
        Some((sep, pa, _)) if geometry.is_some() => Some((sep, pa)),
        _ => geometry,
    };
    Ok(Measured {
        eo_offset_px: eo,
        fwhm_px: fwhm_med,
        geometry,
        photometry: if use_psf { "psf_fit".into() } else { "aperture".into() },
        aperture_px: apertures.get(apertures.len() / 2).copied().unwrap_or(f64::NAN),
        dithers,
        flags,
    })
}

/// Turn the per-dither values of one component into its catalog entry.
pub fn component_from_dithers(
    name: &str,
    per_orient: &[Vec<DitherValue>],
    analyzer_deg: &[f64],
    params: &MeasureParams,
) -> Component {
    let mut flags: Vec<String> = Vec::new();
    let (mut phis, mut fs, mut ss) = (Vec::new(), Vec::new(), Vec::new());
    let mut extra = serde_json::Map::new();
    let mut per_orientation = Vec::new();
    let mut sum_flux = 0.0;
    let mut n_flux = 0;
    for (k, dv) in per_orient.iter().enumerate() {
        let mut usable: Vec<usize> = (0..dv.len()).filter(|&i| dv[i].rejected.is_none()).collect();
        for d in dv.iter().filter(|d| d.rejected.is_some()) {
            for r in d.rejected.as_deref().unwrap_or("").split(',') {
                let r = r.to_string();
                if !r.is_empty() && !flags.contains(&r) {
                    flags.push(r);
                }
            }
        }
        if usable.is_empty() {
            // Everything is flagged: fall back to all finite values rather than nothing.
            usable = (0..dv.len())
                .filter(|&i| dv[i].f.is_finite() && dv[i].sigma_f > 0.0)
                .collect();
            if !usable.is_empty() {
                flags.push("used_flagged_dithers".into());
            }
        }
        for &i in &usable {
            let pf = crate::photometry::Flags(dv[i].o.phot_flags | dv[i].e.phot_flags);
            for (bit, name) in [
                (crate::photometry::Flags::COMPANION_OVERLAP, "companion_overlap"),
                (crate::photometry::Flags::ANNULUS_CONTAMINATED, "annulus_contaminated"),
            ] {
                if pf.contains(bit) && !flags.iter().any(|f| f == name) {
                    flags.push(name.to_string());
                }
            }
        }
        let vals: Vec<f64> = usable.iter().map(|&i| dv[i].f).collect();
        let sig: Vec<f64> = usable.iter().map(|&i| dv[i].sigma_f).collect();
        let keep = clip_dithers(&vals, &sig, params.clip_sigma, 2);
        if keep.len() < vals.len() && !flags.contains(&"dither_clipped".to_string()) {
            flags.push("dither_clipped".into());
        }
        let kv: Vec<f64> = keep.iter().map(|&i| vals[i]).collect();
        let ks: Vec<f64> = keep.iter().map(|&i| sig[i]).collect();
        for &i in &keep {
            let d = &dv[usable[i]];
            sum_flux += d.o.flux + d.e.flux;
            n_flux += 1;
        }
        if let Some(c) = combine_dithers(&kv, &ks) {
            // Honest error: the propagated one, inflated by sqrt(chi2/dof) when the dither
            // scatter is significantly larger (p < 0.01).
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
                    if !flags.contains(&"excess_dither_scatter".to_string()) {
                        flags.push("excess_dither_scatter".into());
                    }
                }
            }
            phis.push(analyzer_deg[k]);
            fs.push(c.value);
            ss.push(sigma);
            per_orientation.push(serde_json::json!({
                "analyzer_deg": analyzer_deg[k], "f": c.value, "sigma_f": sigma, "sigma_f_propagated": c.sigma,
                "sigma_f_scatter": c.sigma_scatter, "chi2": c.chi2, "n_dithers": c.n, "n_dithers_total": dv.len(),
            }));
        }
    }
    extra.insert("orientations".into(), serde_json::Value::Array(per_orientation));
    extra.insert(
        "flux_adu".into(),
        serde_json::json!(if n_flux > 0 { sum_flux / n_flux as f64 } else { f64::NAN }),
    );
    let fit = fit_qu(&phis, &fs, &ss);
    match fit {
        Some(r) => {
            let lp = LinearPolarization::from_qu(r.q, r.u, r.var_q.sqrt(), r.var_u.sqrt(), params.debias);
            extra.insert("snr".into(), serde_json::json!(lp.snr));
            extra.insert("sigma_gamma_nkc_deg".into(), serde_json::json!(lp.sigma_gamma_nkc_deg));
            extra.insert("cov_qu".into(), serde_json::json!(r.cov_qu));
            if lp.snr <= params.cut_snr {
                flags.push("low_snr".into());
            }
            Component {
                name: name.into(),
                q: lp.q,
                u: lp.u,
                sigma_q: lp.sigma_q,
                sigma_u: lp.sigma_u,
                p: lp.p,
                sigma_p: lp.sigma_p,
                p_debiased: lp.p_debiased,
                gamma_deg: lp.gamma_deg,
                sigma_gamma_deg: lp.sigma_gamma_deg,
                passes_cut: lp.passes_cut(params.cut_snr),
                flags,
                extra,
            }
        }
        None => {
            flags.push("undefined_polarization: orientations do not constrain q and u".into());
            Component {
                name: name.into(),
                q: f64::NAN,
                u: f64::NAN,
                sigma_q: f64::NAN,
                sigma_u: f64::NAN,
                p: f64::NAN,
                sigma_p: f64::NAN,
                p_debiased: f64::NAN,
                gamma_deg: f64::NAN,
                sigma_gamma_deg: f64::NAN,
                passes_cut: false,
                flags,
                extra,
            }
        }
    }
}

/// Build the catalog entry of a measured sequence.
pub fn target_entry(object: &str, orients: &[CalibratedOrientation], m: &Measured, params: &MeasureParams) -> Target {
    let phis: Vec<f64> = orients.iter().map(|o| o.analyzer_deg).collect();
    let names = ["A", "B"];
    let components: Vec<Component> = m
        .dithers
        .iter()
        .enumerate()
        .map(|(i, d)| component_from_dithers(names[i], d, &phis, params))
        .collect();
    let delta = if components.len() == 2 && components.iter().all(|c| c.passes_cut) {
        Some(catalog::fold_delta_gamma(
            components[0].gamma_deg,
            components[1].gamma_deg,
        ))
    } else {
        None
    };
    let status = if components.len() == 2 && components.iter().all(|c| c.q.is_finite()) {
        Status::Ok
    } else {
        Status::Partial
    };
    let mut extra = serde_json::Map::new();
    extra.insert(
        "eo_offset_px".into(),
        serde_json::json!([m.eo_offset_px.0, m.eo_offset_px.1]),
    );
    extra.insert("fwhm_px".into(), serde_json::json!(m.fwhm_px));
    extra.insert("photometry".into(), serde_json::json!(m.photometry));
    extra.insert("aperture_radius_px".into(), serde_json::json!(m.aperture_px));
    if let Some((sep, pa)) = m.geometry {
        extra.insert("separation_arcsec".into(), serde_json::json!(sep));
        extra.insert("pa_deg".into(), serde_json::json!(pa));
    }
    extra.insert(
        "orientations_deg".into(),
        serde_json::json!(orients.iter().map(|o| o.posang_deg).collect::<Vec<_>>()),
    );
    extra.insert("flags".into(), serde_json::json!(m.flags));
    Target {
        object: object.into(),
        status,
        error: if status == Status::Partial {
            m.flags.first().cloned().or(Some("companion not measured".into()))
        } else {
            None
        },
        components,
        delta_gamma_deg: delta,
        extra,
    }
}
