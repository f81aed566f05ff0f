//! Per-frame photometry of both components in both beams: the PSF model and method chosen
//! from the stacks, then for every frame a two-star PSF fit per beam (deblending) and either
//! aperture photometry on the frame with the other star's model subtracted (exact overlap) or
//! PSF-fit fluxes (close pairs); F = (o - e)/(o + e) per dither with its rejection reason.
use ndarray::{s, Array2};
use sofipol_calib::frame::mask as mbits;
use sofipol_calib::Frame;

use super::companion::Companion;
use super::sources::{Primary, UNUSABLE};
use super::{BeamFlux, DitherValue, MeasureParams, SkySubtractedOrientation};
use crate::catalog::{Flag, FlagCode};
use crate::photometry::model::add_gaussian;
use crate::photometry::moffat::{add_moffat, add_moffat_elliptical};
use crate::photometry::{
    aperture_sum, fit_psf, fit_psf_from, fit_psf_joint, measure, subtract_star_near_where, Aperture, FitImage, Flags,
    MaskFill, Method, PhotParams, PsfFit, PsfFitParams, PsfModel, PsfStart,
};
use crate::stokes::model::companion_offset_px;

/// How the fluxes are measured, chosen once per sequence from the stacks.
#[derive(Debug, Clone, Copy)]
pub struct PsfChoice {
    /// Median FWHM of the stack fits, px (the initial guess when no stack was fitted).
    pub fwhm_px: f64,
    /// PSF model of the per-frame fits.
    pub frame_model: PsfModel,
    /// PSF-fit fluxes (pair closer than `psf_photometry_below_fwhm`) instead of apertures.
    pub use_psf: bool,
    /// An elliptical Moffat in the per-frame fits (`psf_elliptical`, for PSF-fit fluxes).
    pub elliptical: bool,
    /// Separation of the pair, px (infinite without a companion).
    pub sep_px: f64,
}

/// Stage 4: the PSF model and photometry method.
///
/// Moffat beta is measured once on the stacks (the wings, which the whole-pixel registration
/// of the stack does not blur) and held fixed in the per-frame fits, where only the seeing
/// (alpha) changes: fewer free parameters, smaller flux errors for close pairs, faster fits.
pub fn choose_psf(companion: &Companion, fwhm_guess: f64, scale: f64, params: &MeasureParams) -> PsfChoice {
    let mut betas: Vec<f64> = companion
        .found
        .iter()
        .flatten()
        .map(|p| p.beta)
        .filter(|b| b.is_finite())
        .collect();
    betas.sort_by(|a, b| a.total_cmp(b));
    let mut fwhms = companion.fwhms.clone();
    fwhms.sort_by(|a, b| a.total_cmp(b));
    let fwhm_px = if fwhms.is_empty() {
        fwhm_guess
    } else {
        fwhms[fwhms.len() / 2]
    };
    let sep_px = companion.geometry.map(|(s, _)| s / scale).unwrap_or(f64::INFINITY);
    let use_psf = sep_px < params.psf_photometry_below_fwhm * fwhm_px;
    // A pair measured by PSF-fit fluxes keeps beta free in every frame: its flux partition
    // depends on the profile's shape, and a beta held at the stack's value (biased by the
    // stack's whole-pixel registration, blind to the frame-to-frame changes of the seeing)
    // moves the same fraction of each star's flux to the other in both beams, which mixes
    // the components' polarizations by an amount no error term contains (world harness:
    // pulls of 4 for bright 0.5-0.8" pairs; docs/accuracy.md). The beta-free fit's larger
    // errors are the honest ones there.
    let frame_model = match (
        params.psf_model,
        params.beta_from_stack && !use_psf,
        betas.get(betas.len() / 2),
    ) {
        (PsfModel::Moffat { beta: None }, true, Some(&b)) => PsfModel::Moffat { beta: Some(b) },
        (m, _, _) => m,
    };
    let elliptical = params.psf_elliptical && use_psf && matches!(frame_model, PsfModel::Moffat { .. });
    PsfChoice {
        fwhm_px,
        frame_model,
        use_psf,
        elliptical,
        sep_px,
    }
}

/// The per-frame measurements of a sequence.
#[derive(Debug, Clone, Default)]
pub struct Fluxes {
    /// Per component, per orientation, per dither.
    pub dithers: Vec<Vec<Vec<DitherValue>>>,
    /// Aperture radius of every measured frame, px.
    pub apertures: Vec<f64>,
    /// Fitted position of A in the o and e beams of every frame (refines the e-o offset).
    pub fitted_a_oe: Vec<((f64, f64), (f64, f64))>,
    /// Offset of B from A fitted in every frame: (POSANG, offset, weight).
    pub pair_offsets: Vec<(f64, (f64, f64), f64)>,
    /// Per orientation, per frame: the frame's seeing FWHM, px: the beta-free refit of the
    /// o beam when beta was held fixed (`seeing_fwhm_px`), else the mean of the converged PSF
    /// fits of the o and e beams; NaN when none converged.
    pub frame_fwhm_px: Vec<Vec<f64>>,
}

/// What every frame of a sequence is measured with, the same for all: the PSF model and
/// method ([`choose_psf`]), the beams' offset, the pixel scale and the settings.
#[derive(Debug, Clone, Copy)]
pub struct FluxSetup<'a> {
    /// The PSF model and photometry method chosen from the stacks.
    pub choice: &'a PsfChoice,
    /// Offset of the e beam from the o beam (x, y), px.
    pub eo_px: (f64, f64),
    /// Pixel scale, arcsec per px.
    pub scale_arcsec_per_px: f64,
    /// The measurement settings.
    pub params: &'a MeasureParams,
    /// Measure each frame's seeing ([`Fluxes::frame_fwhm_px`]: a beta-free refit of the o
    /// beam when beta is held fixed); off for the field stars, whose fits decide nothing
    /// about the frame.
    pub seeing: bool,
}

/// Stage 5: photometry of both components in both beams of every frame, where the
/// primary (`primary`) and the companion (`companion`) were found, with `setup`.
pub fn measure_fluxes(
    orients: &[SkySubtractedOrientation],
    primary: &Primary,
    companion: &Companion,
    setup: &FluxSetup,
    flags: &mut Vec<Flag>,
) -> Fluxes {
    let scale = setup.scale_arcsec_per_px;
    let ncomp = if companion.geometry.is_some() { 2 } else { 1 };
    let mut out = Fluxes {
        dithers: vec![Vec::new(); ncomp],
        ..Fluxes::default()
    };
    for (k, (o, cs)) in orients.iter().zip(&primary.centres).enumerate() {
        let rel_a = companion.found[k].map(|p| p.a).unwrap_or((0.0, 0.0));
        let off_b = companion
            .geometry
            .map(|(sep, pa)| companion_offset_px(sep, pa, o.posang_deg, scale));
        for c in out.dithers.iter_mut() {
            c.push(Vec::new());
        }
        out.frame_fwhm_px.push(Vec::with_capacity(o.frames.len()));
        for (f, c) in o.frames.iter().zip(cs) {
            let Some(c) = c else {
                out.frame_fwhm_px[k].push(f64::NAN);
                flags.push(Flag::with_detail(
                    FlagCode::PrimaryNotFoundIn,
                    f.path().display().to_string(),
                ));
                for comp in out.dithers.iter_mut() {
                    comp[k].push(DitherValue::missing(FlagCode::PrimaryNotFound.name()));
                }
                continue;
            };
            let a_o = (c.0 + rel_a.0, c.1 + rel_a.1);
            let mut stars = vec![a_o];
            if let Some(ob) = off_b {
                stars.push((a_o.0 + ob.0, a_o.1 + ob.1));
            }
            let (results, cov_oe) = measure_frame(f, &stars, setup);
            let fitted: Vec<f64> = results
                .iter()
                .map(|b| b.fit_fwhm_px)
                .filter(|w| w.is_finite())
                .collect();
            out.frame_fwhm_px[k].push(if fitted.is_empty() {
                f64::NAN
            } else {
                fitted.iter().sum::<f64>() / fitted.len() as f64
            });
            let mut beams: Vec<Vec<(BeamFlux, u8)>> = Vec::new();
            let mut fitted_a: [Option<(f64, f64)>; 2] = [None, None];
            for (bi, b) in results.into_iter().enumerate() {
                fitted_a[bi] = b.fitted_a;
                if let Some(d) = b.pair_offset {
                    out.pair_offsets.push((o.posang_deg, d, 1.0));
                }
                if bi == 0 {
                    out.apertures.push(b.r_ap);
                }
                beams.push(b.stars);
            }
            if let [Some(a), Some(b)] = fitted_a {
                out.fitted_a_oe.push((a, b));
            }
            for (si, comp) in out.dithers.iter_mut().enumerate() {
                comp[k].push(dither_value(beams[0][si], beams[1][si], cov_oe[si]));
            }
        }
    }
    out
}

/// Both beams of the stars at `stars` (o-beam positions, px) in frame `f`: fitted jointly
/// when `measure.joint_beams` is on and the joint fit can be made, else beam by beam; with
/// the o-e covariance of each star's fluxes. The one per-frame photometry of the
/// components and of the field stars ([`super::field`]).
pub(crate) fn measure_frame(f: &Frame, stars: &[(f64, f64)], setup: &FluxSetup) -> (Vec<BeamResult>, Vec<f64>) {
    let joint = setup
        .params
        .joint_beams
        .then(|| measure_beams_jointly(f, stars, setup))
        .flatten();
    match joint {
        Some(j) => j,
        None => (measure_beams_separately(f, stars, setup), vec![0.0; stars.len()]),
    }
}

/// Both beams of frame `f` fitted on their own, the o beam first (its fit starts the e
/// beam's and sets the frame's FWHM and PSF shape for both).
fn measure_beams_separately(f: &Frame, stars: &[(f64, f64)], setup: &FluxSetup) -> Vec<BeamResult> {
    let eo = setup.eo_px;
    let mut frame = FramePsf {
        fwhm_px: setup.choice.fwhm_px,
        shape: None,
    };
    // The e beam's fit starts from the o beam's (the same stars and seeing, moved by the
    // e-o offset): the same minimum in fewer steps.
    let mut e_start: Option<PsfStart> = None;
    let mut out = Vec::with_capacity(2);
    for (bi, shift) in [(0.0, 0.0), eo].into_iter().enumerate() {
        let b = measure_beam(f, stars, shift, bi == 0, &mut frame, e_start.as_ref(), setup);
        if bi == 0 {
            e_start = b.fit_start.clone().map(|mut st| {
                st.stars.iter_mut().for_each(|s| {
                    s.1 += eo.0;
                    s.2 += eo.1;
                });
                st
            });
        }
        out.push(b);
    }
    out
}

/// Both beams of frame `f` fitted jointly ([`fit_psf_joint`]: one shape, one pair geometry,
/// a flux per star and beam), then measured as [`measure_beam`] measures one; with the
/// covariance of each star's o and e PSF-fit fluxes (0 for aperture fluxes). None when the
/// joint fit cannot be made (too few pixels, a singular fit): the beams are then fitted on
/// their own.
fn measure_beams_jointly(f: &Frame, stars: &[(f64, f64)], setup: &FluxSetup) -> Option<(Vec<BeamResult>, Vec<f64>)> {
    let (choice, params) = (setup.choice, setup.params);
    let fwhm_med = choice.fwhm_px;
    let cuts: Vec<(Cutout, Vec<(f64, f64)>)> = [(0.0, 0.0), setup.eo_px]
        .into_iter()
        .map(|shift| beam_cutout(f, stars, shift, setup))
        .collect();
    let images: Vec<FitImage> = cuts
        .iter()
        .map(|(cut, local)| FitImage {
            img: cut.img.view(),
            var: Some(cut.var.view()),
            mask: Some(cut.bad.view()),
            guesses: local,
        })
        .collect();
    let joint = fit_psf_joint(&images, &fit_params(choice)).ok()?;
    let shape_fit = &joint.fits[0];
    let frame_fwhm = shape_fit.fwhm_x().clamp(0.5 * fwhm_med, 2.0 * fwhm_med);
    let frame_shape = shape_fit.converged.then(|| FrameShape::of(shape_fit));
    let r_ap = params.aperture_radius_px(frame_fwhm);
    let seeing = setup
        .seeing
        .then(|| seeing_fwhm_px(&cuts[0], shape_fit, choice))
        .flatten();
    let results = cuts
        .iter()
        .zip(&joint.fits)
        .map(|((cut, guesses), fit)| {
            let with = BeamFit {
                fit: Some(fit),
                shape: frame_shape,
                r_ap_px: r_ap,
            };
            let mut b = measured_beam(cut, guesses, &with, setup);
            if let Some(w) = seeing {
                b.fit_fwhm_px = w;
            }
            b
        })
        .collect();
    let cov_oe = (0..stars.len())
        .map(|k| {
            if choice.use_psf {
                joint.flux_covariance((0, k), (1, k))
            } else {
                0.0
            }
        })
        .collect();
    Some((results, cov_oe))
}

/// The frame's seeing FWHM, px, when the photometry's fit held Moffat beta at the stack's
/// value: the o beam's stars fitted again with beta free, from the converged joint fit
/// `fit` (a few iterations). A beta held at the stack's, which mixes the sequence's
/// seeing, biases a frame's FWHM by a few per cent when the seeing changes much between
/// frames; the photometry keeps its own fit (this one measures, it decides nothing).
/// `None` when beta is already free (the photometry's FWHM is the seeing) or the fit does
/// not converge.
fn seeing_fwhm_px(cut: &(Cutout, Vec<(f64, f64)>), fit: &PsfFit, choice: &PsfChoice) -> Option<f64> {
    if !(matches!(choice.frame_model, PsfModel::Moffat { beta: Some(_) }) && fit.converged) {
        return None;
    }
    let (cut, guesses) = cut;
    let params = PsfFitParams {
        model: PsfModel::Moffat { beta: None },
        ..fit_params(choice)
    };
    let start = PsfStart {
        stars: fit.stars.iter().map(|s| (s.flux, s.x, s.y)).collect(),
        shape: fit.alpha,
        beta: fit.beta,
        ellipticity: fit.ellipticity,
    };
    let free = fit_psf_from(
        cut.img.view(),
        Some(cut.var.view()),
        Some(cut.bad.view()),
        guesses,
        &params,
        &start,
    )
    .ok()?;
    let w = free.fwhm();
    (free.converged && w.is_finite() && w > 0.0).then_some(w)
}

/// The cut-out of one beam about the stars at `stars` + `shift`, and their positions in it.
fn beam_cutout(f: &Frame, stars: &[(f64, f64)], shift: (f64, f64), setup: &FluxSetup) -> (Cutout, Vec<(f64, f64)>) {
    let (choice, params) = (setup.choice, setup.params);
    let pos: Vec<(f64, f64)> = stars.iter().map(|&(x, y)| (x + shift.0, y + shift.1)).collect();
    let (cx, cy) = pos.iter().fold((0.0, 0.0), |a, p| {
        (a.0 + p.0 / pos.len() as f64, a.1 + p.1 / pos.len() as f64)
    });
    let half = (params.annulus_px(choice.fwhm_px).1 + choice.sep_px.min(40.0) + 4.0).ceil() as usize;
    let cut = Cutout::new(f, cx, cy, half);
    let (x0, y0) = cut.origin;
    let local = pos.iter().map(|&(x, y)| (x - x0, y - y0)).collect();
    (cut, local)
}

/// The per-frame PSF fit's settings.
fn fit_params(choice: &PsfChoice) -> PsfFitParams {
    PsfFitParams {
        fwhm_px: choice.fwhm_px,
        fit_radius_px: (1.5 * choice.fwhm_px).max(3.0),
        background: Some(0.0),
        model: choice.frame_model,
        elliptical: choice.elliptical,
        ..PsfFitParams::default()
    }
}

/// One beam of one frame.
pub(crate) struct BeamResult {
    /// Per star: the flux and the mask bits inside its aperture.
    pub(crate) stars: Vec<(BeamFlux, u8)>,
    /// Fitted (or assumed) position of A, frame px.
    fitted_a: Option<(f64, f64)>,
    /// Offset of B from A when the two-star fit converged, px.
    pair_offset: Option<(f64, f64)>,
    /// Aperture radius, px.
    pub(crate) r_ap: f64,
    /// The o beam's converged fit as a start for the e beam's (frame coordinates).
    fit_start: Option<PsfStart>,
    /// FWHM of this beam's PSF fit when it converged (the geometric mean of the axes'), px;
    /// NaN otherwise.
    fit_fwhm_px: f64,
}

/// The frame's PSF as the o beam's fit sets it for both beams ([`measure_beam`]).
struct FramePsf {
    /// FWHM, px (the sequence's median until the o beam is fitted).
    fwhm_px: f64,
    /// The shape, when the o beam's fit converged.
    shape: Option<FrameShape>,
}

/// Fit and measure the stars at `stars` + `shift` in one beam of frame `f`. The o beam
/// (`first`) sets `frame`'s FWHM and PSF shape (alpha, beta, sigma_x, sigma_y) from its
/// fit; both beams size their apertures with the one and correct them with the other (two
/// independently fitted widths would put their noise into F).
fn measure_beam(
    f: &Frame,
    stars: &[(f64, f64)],
    shift: (f64, f64),
    first: bool,
    frame: &mut FramePsf,
    start: Option<&PsfStart>,
    setup: &FluxSetup,
) -> BeamResult {
    let (choice, params) = (setup.choice, setup.params);
    let FramePsf {
        fwhm_px: frame_fwhm,
        shape: frame_shape,
    } = frame;
    let fwhm_med = choice.fwhm_px;
    let (cut, local) = beam_cutout(f, stars, shift, setup);
    let (x0, y0) = cut.origin;
    let fitp = fit_params(choice);
    let fit = match start {
        Some(st) => {
            let mut st = st.clone();
            st.stars.iter_mut().for_each(|s| {
                s.1 -= x0;
                s.2 -= y0;
            });
            fit_psf_from(
                cut.img.view(),
                Some(cut.var.view()),
                Some(cut.bad.view()),
                &local,
                &fitp,
                &st,
            )
        }
        None => fit_psf(
            cut.img.view(),
            Some(cut.var.view()),
            Some(cut.bad.view()),
            &local,
            &fitp,
        ),
    }
    .ok();
    if first {
        if let Some(ft) = &fit {
            *frame_fwhm = ft.fwhm_x().clamp(0.5 * fwhm_med, 2.0 * fwhm_med);
            if ft.converged {
                *frame_shape = Some(FrameShape::of(ft));
            }
        }
    }
    let r_ap = params.aperture_radius_px(*frame_fwhm);
    let with = BeamFit {
        fit: fit.as_ref(),
        shape: *frame_shape,
        r_ap_px: r_ap,
    };
    let mut out = measured_beam(&cut, &local, &with, setup);
    // Only the o beam's fit starts another (the e beam's).
    out.fit_start = fit.as_ref().filter(|ft| first && ft.converged).map(|ft| PsfStart {
        stars: ft.stars.iter().map(|s| (s.flux, s.x + x0, s.y + y0)).collect(),
        shape: match ft.model {
            PsfModel::Gaussian => ft.sigma_x,
            PsfModel::Moffat { .. } => ft.alpha,
        },
        beta: ft.beta,
        ellipticity: ft.ellipticity,
    });
    out
}

/// The frame's PSF shape (from the o beam's fit, or the joint fit's), for the aperture
/// correction of both beams.
#[derive(Debug, Clone, Copy)]
struct FrameShape {
    alpha: f64,
    beta: f64,
    sigma_x: f64,
    sigma_y: f64,
    ellipticity: [f64; 2],
}

impl FrameShape {
    fn of(ft: &PsfFit) -> FrameShape {
        FrameShape {
            alpha: ft.alpha,
            beta: ft.beta,
            sigma_x: ft.sigma_x,
            sigma_y: ft.sigma_y,
            ellipticity: ft.ellipticity,
        }
    }
}

/// What one beam's stars are measured with: its PSF fit, the frame's PSF shape (for the
/// aperture correction) and the aperture radius.
#[derive(Clone, Copy)]
struct BeamFit<'a> {
    /// The beam's PSF fit, if it was made.
    fit: Option<&'a PsfFit>,
    /// The frame's PSF shape, when a fit converged ([`FramePsf`]).
    shape: Option<FrameShape>,
    /// Aperture radius, px.
    r_ap_px: f64,
}

/// The stars of one beam's cut-out `cut` measured `with` its PSF fit (positions from the
/// fit when it converged, else `guesses`) and aperture.
fn measured_beam(cut: &Cutout, guesses: &[(f64, f64)], with: &BeamFit, setup: &FluxSetup) -> BeamResult {
    let (fit, r_ap) = (with.fit, with.r_ap_px);
    let (x0, y0) = cut.origin;
    // Centre apertures on the fitted positions (both beams are fitted freely, so the e-o
    // offset found before only needs to be good to a pixel).
    let local: Vec<(f64, f64)> = match fit {
        Some(ft) if ft.converged => ft.stars.iter().map(|st| (st.x, st.y)).collect(),
        _ => guesses.to_vec(),
    };
    let fitted_a = local.first().map(|&(ax, ay)| (ax + x0, ay + y0));
    let pair_offset = match (fit, local.len()) {
        (Some(ft), 2) if ft.converged => Some((local[1].0 - local[0].0, local[1].1 - local[0].1)),
        _ => None,
    };
    let stars = (0..local.len())
        .map(|si| measure_star(cut, &local, si, with, setup))
        .collect();
    BeamResult {
        stars,
        fitted_a,
        pair_offset,
        r_ap,
        fit_start: None,
        fit_fwhm_px: fit.filter(|ft| ft.converged).map_or(f64::NAN, PsfFit::fwhm),
    }
}

/// Flux of star `si` (at `local[si]` in the cut-out): PSF-fit flux, or aperture photometry
/// with the other stars' fitted models subtracted.
fn measure_star(cut: &Cutout, local: &[(f64, f64)], si: usize, with: &BeamFit, setup: &FluxSetup) -> (BeamFlux, u8) {
    let (choice, params) = (setup.choice, setup.params);
    let BeamFit {
        fit,
        shape,
        r_ap_px: r_ap,
    } = *with;
    let fwhm_med = choice.fwhm_px;
    let (x0, y0) = cut.origin;
    let (lx, ly) = local[si];
    let bits_in = bits_inside(&cut.bits, lx, ly, r_ap);
    if choice.use_psf {
        let flux = match fit {
            Some(ft) => {
                let st = ft.stars[si];
                BeamFlux {
                    flux: st.flux,
                    var: st.flux_err.powi(2),
                    xy: (st.x + x0, st.y + y0),
                    phot_flags: 0,
                    aperture_fraction: None,
                }
            }
            None => BeamFlux {
                xy: (lx + x0, ly + y0),
                ..BeamFlux::missing()
            },
        };
        return (flux, bits_in);
    }
    // Deblend: subtract the other stars' models, then measure.
    let others: Vec<(f64, f64)> = local
        .iter()
        .enumerate()
        .filter(|(j, _)| *j != si)
        .map(|(_, p)| *p)
        .collect();
    let pp = PhotParams {
        r_ap_px: r_ap,
        annulus_px: Some(params.annulus_px(fwhm_med)),
        method: params.method,
        companion_radius_px: r_ap,
        annulus_exclude_radius_px: 2.0 * fwhm_med,
        ..PhotParams::default()
    };
    // The photometry below reads the aperture and the annulus only: the other stars are
    // subtracted there (the same pixel values as a whole-cutout subtraction), and not on
    // the annulus pixels it leaves out near them (their cores, the costly part).
    let mut work = cut.img.clone();
    let reach = r_ap.max(params.annulus_px(fwhm_med).1) + 2.0;
    if let Some(ft) = fit {
        let read = pixels_read(&pp, (lx, ly), &others);
        for other in 0..local.len() {
            if other != si {
                subtract_star_near_where(&mut work, ft, other, (lx, ly), reach, &read);
            }
        }
    }
    let ph = measure(
        work.view(),
        Some(cut.var.view()),
        Some(cut.bad.view()),
        &pp,
        lx,
        ly,
        &others,
    );
    let flux = BeamFlux {
        flux: ph.flux,
        var: ph.variance,
        xy: (lx + x0, ly + y0),
        phot_flags: ph.flags.0,
        aperture_fraction: fit.zip(shape).and_then(|(ft, sh)| {
            let ap = Aperture { x: lx, y: ly, r: r_ap };
            model_fraction_in_aperture(ft, sh, si, cut.img.dim(), &ap, params.method)
        }),
    };
    (flux, bits_in)
}

/// A superset (by a pixel's margin) of the pixels [`measure`] with `pp` reads at `(x, y)`
/// with the other sources `others`: the aperture's bounding square, and the annulus without
/// the discs of `annulus_exclude_radius_px` about the others.
fn pixels_read<'a>(
    pp: &PhotParams,
    (x, y): (f64, f64),
    others: &'a [(f64, f64)],
) -> impl Fn(usize, usize) -> bool + 'a {
    let half = pp.r_ap_px + 1.0;
    let (r_in, r_out) = pp.annulus_px.unwrap_or((f64::INFINITY, f64::INFINITY));
    let inner = (r_in - 1.0).max(0.0);
    let outer = r_out + 1.0;
    let excl = pp.annulus_exclude_radius_px - 1.0;
    let annulus = pp.annulus_px.is_some();
    move |ix: usize, iy: usize| {
        let (dx, dy) = (ix as f64 - x, iy as f64 - y);
        if dx.abs() <= half && dy.abs() <= half {
            return true;
        }
        let d2 = dx * dx + dy * dy;
        if !annulus || d2 < inner * inner || d2 > outer * outer {
            return false;
        }
        excl <= 0.0
            || !others
                .iter()
                .any(|&(ox, oy)| (ix as f64 - ox).hypot(iy as f64 - oy) < excl)
    }
}

/// The fraction of star `si`'s fitted PSF model (pixel-integrated) that falls in the
/// aperture `ap` of the cut-out of size `dim` (ny, nx), measured with the same pixel weights
/// (`method`) as the data. A small aperture
/// on an undersampled star (FWHM ~2 px) catches a fraction that depends on the star's
/// sub-pixel position, which differs between the o and e images: dividing both beams by
/// their own fraction removes that difference from F (docs/photometry.md).
fn model_fraction_in_aperture(
    fit: &PsfFit,
    shape: FrameShape,
    si: usize,
    dim: (usize, usize),
    ap: &Aperture,
    method: Method,
) -> Option<f64> {
    let (x, y, r_ap) = (ap.x, ap.y, ap.r);
    let st = fit.stars.get(si)?;
    if !(fit.converged && st.flux.is_finite() && st.flux > 0.0) {
        return None;
    }
    // This beam's position, the frame's PSF shape (the o beam's fit). The model is rendered
    // on the pixels the aperture reads only (its bounding square, clipped to the cut-out):
    // in that sub-image, with the coordinates shifted by whole pixels (exact differences),
    // every value and the aperture sum are those of a whole cut-out render, bit for bit.
    let (ny, nx) = dim;
    if nx == 0 || ny == 0 || !(x.is_finite() && y.is_finite() && r_ap.is_finite()) {
        return None;
    }
    let clampi = |v: f64, n: usize| v.max(0.0).min(n as f64 - 1.0) as usize;
    let (wx0, wx1) = (
        clampi((x - r_ap - 1.0).floor(), nx),
        clampi((x + r_ap + 1.0).ceil(), nx),
    );
    let (wy0, wy1) = (
        clampi((y - r_ap - 1.0).floor(), ny),
        clampi((y + r_ap + 1.0).ceil(), ny),
    );
    let mut model = Array2::<f32>::zeros((wy1 - wy0 + 1, wx1 - wx0 + 1));
    let (sx, sy) = (st.x - wx0 as f64, st.y - wy0 as f64);
    let flux = 1.0 / st.flux * st.flux; // as `render_star` scales it
    let FrameShape {
        alpha,
        beta,
        sigma_x,
        sigma_y,
        ellipticity,
    } = shape;
    match fit.model {
        PsfModel::Gaussian => add_gaussian(&mut model.view_mut(), flux, sx, sy, sigma_x, sigma_y),
        PsfModel::Moffat { .. } if ellipticity != [0.0; 2] => {
            add_moffat_elliptical(&mut model.view_mut(), flux, sx, sy, alpha, beta, ellipticity)
        }
        PsfModel::Moffat { .. } => add_moffat(&mut model.view_mut(), flux, sx, sy, alpha, beta),
    }
    let ap = Aperture {
        x: x - wx0 as f64,
        y: y - wy0 as f64,
        r: r_ap,
    };
    let frac = aperture_sum(model.view(), None, None, &ap, method, MaskFill::Exclude).sum;
    (frac.is_finite() && frac > 0.2 && frac <= 1.0 + 1e-6).then_some(frac)
}

/// F = (o - e)/(o + e) of one dither from the o and e beam fluxes (with the mask bits in
/// their apertures), and why it is not used, if so.
pub(crate) fn dither_value(
    (mut o_b, ob): (BeamFlux, u8),
    (mut e_b, eb): (BeamFlux, u8),
    mut cov_oe: f64,
) -> DitherValue {
    // Aperture correction, only when both beams have one (else F would mix corrected and
    // uncorrected fluxes).
    if let (Some(fo), Some(fe)) = (o_b.aperture_fraction, e_b.aperture_fraction) {
        for (b, f) in [(&mut o_b, fo), (&mut e_b, fe)] {
            b.flux /= f;
            b.var /= f * f;
        }
        cov_oe /= fo * fe;
    }
    let tot = o_b.flux + e_b.flux;
    let fval = (o_b.flux - e_b.flux) / tot;
    let sigma_f = crate::stokes::model::f_error(o_b.flux, e_b.flux, o_b.var, e_b.var, cov_oe);
    let blocking = (ob | eb) & (mbits::BAD | mbits::COSMIC | mbits::SATURATED | mbits::OFF_STRIP);
    let pf = Flags(o_b.phot_flags | e_b.phot_flags);
    let rejected = if !(fval.is_finite() && sigma_f.is_finite() && sigma_f > 0.0 && tot > 0.0) {
        Some(FlagCode::PhotometryFailed.name().to_string())
    } else if pf.contains(Flags::TRUNCATED) {
        Some(FlagCode::Truncated.name().to_string())
    } else if blocking != 0 {
        Some(bit_names(blocking).join(","))
    } else {
        None
    };
    DitherValue {
        f: fval,
        sigma_f,
        o: o_b,
        e: e_b,
        rejected,
    }
}

/// A square cut-out of a frame around the target.
struct Cutout {
    img: Array2<f32>,
    /// Variance (1 where the frame has none).
    var: Array2<f32>,
    /// 0/1 unusable pixels.
    bad: Array2<u8>,
    /// The frame's mask bits.
    bits: Array2<u8>,
    /// Frame coordinates (x, y) of the cut-out's pixel (0, 0).
    origin: (f64, f64),
}

impl Cutout {
    fn new(frame: &Frame, cx: f64, cy: f64, h: usize) -> Cutout {
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
        Cutout {
            img,
            var,
            bad,
            bits,
            origin: (x0 as f64, y0 as f64),
        }
    }
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

/// Catalog flag names of blocking mask bits.
fn bit_names(b: u8) -> Vec<String> {
    [
        (mbits::BAD | mbits::OFF_STRIP, FlagCode::BadPixels),
        (mbits::COSMIC, FlagCode::CosmicRay),
        (mbits::SATURATED, FlagCode::Saturated),
        (mbits::NONLINEAR, FlagCode::Nonlinear),
    ]
    .into_iter()
    .filter(|(bits, _)| b & bits != 0)
    .map(|(_, code)| code.name().to_string())
    .collect()
}
