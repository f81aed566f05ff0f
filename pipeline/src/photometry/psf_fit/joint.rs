//! The joint fit of the same stars in several images of one exposure (the o and e beams):
//! one shape for all, the stars' positions fitted in the first image and moved by one
//! shift into each other, a flux per star and image.
//!
//! The o and e images of an exposure are the same photons through the same optics, split by
//! the Wollaston prism: the PSF and the pair's geometry are the same in both, only the
//! fluxes (the polarization) and the e-o offset differ. Fitting the two beams separately
//! measures the shape (and the pair's geometry) twice from half the photons each, and the
//! flux partition of a close pair follows that noise independently in o and e, straight
//! into F = (o - e)/(o + e). Fitted jointly, the shape's error is common to the two beams
//! and cancels in F to first order; the flux covariance between the beams
//! ([`JointFit::flux_covariance`]) says by how much.

use ndarray::ArrayView2;

use super::normal::{Layout, Pixel};
use super::solve::Problem;
use super::{assemble, check_params, covariance_of, fit_pixels, start_values, Fitted};
use crate::photometry::psf::{PsfFit, PsfFitError, PsfFitParams};

/// One image of a joint fit: pixels, variance (ADU^2; all images or none), mask (nonzero =
/// bad) and the stars' initial positions there, in the same order in every image.
#[derive(Debug, Clone, Copy)]
pub struct FitImage<'a> {
    /// The image, ADU.
    pub img: ArrayView2<'a, f32>,
    /// Its variance, ADU^2.
    pub var: Option<ArrayView2<'a, f32>>,
    /// Unusable pixels (nonzero).
    pub mask: Option<ArrayView2<'a, u8>>,
    /// Initial positions of the stars, px.
    pub guesses: &'a [(f64, f64)],
}

/// The result of [`fit_psf_joint`].
#[derive(Debug, Clone)]
pub struct JointFit {
    /// Per image: its stars (fluxes, positions in its pixel coordinates) and the shared
    /// shape, with the covariance of its own parameters (as from [`super::fit_psf`]). The
    /// chi-square, degrees of freedom and iterations are the joint fit's.
    pub fits: Vec<PsfFit>,
    /// Covariance of the joint fit's parameters.
    covariance: Vec<Vec<f64>>,
    /// Where each image's fluxes sit in the joint parameters: `[image][star]`.
    flux_index: Vec<Vec<usize>>,
}

impl JointFit {
    /// Covariance of star `a.1`'s flux in image `a.0` with star `b.1`'s in image `b.0`, ADU^2.
    pub fn flux_covariance(&self, a: (usize, usize), b: (usize, usize)) -> f64 {
        self.covariance[self.flux_index[a.0][a.1]][self.flux_index[b.0][b.1]]
    }
}

/// Fits the stars of `images` jointly: one PSF shape ([`PsfFitParams::model`], fitted or
/// fixed beta as there), each star's position in the first image, one shift of all the
/// positions into each further image (started at the mean difference of the guesses), and a
/// flux per star per image; pixels within `fit_radius_px` of a guess in its image. The
/// background must be held fixed (`params.background = Some(b)`, the same in every image).
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::moffat::add_moffat;
/// use sofipol_pipeline::photometry::{fit_psf_joint, FitImage, PsfFitParams, PsfModel};
/// // A 1.2-FWHM pair seen in two beams 40 % (o) and 60 % (e) of the flux, at offset (0.3, 1.6).
/// let (mut o, mut e) = (Array2::<f32>::zeros((30, 30)), Array2::<f32>::zeros((30, 30)));
/// for (img, frac, (dx, dy)) in [(&mut o, 0.4, (0.0, 0.0)), (&mut e, 0.6, (0.3, 1.6))] {
///     add_moffat(&mut img.view_mut(), frac * 2e4, 14.0 + dx, 15.0 + dy, 2.0, 3.0);
///     add_moffat(&mut img.view_mut(), frac * 1e4, 17.4 + dx, 15.5 + dy, 2.0, 3.0);
/// }
/// let params = PsfFitParams {
///     fwhm_px: 2.6,
///     fit_radius_px: 5.0,
///     background: Some(0.0),
///     model: PsfModel::Moffat { beta: None },
///     ..PsfFitParams::default()
/// };
/// let (go, ge) = ([(14.2, 15.1), (17.0, 15.3)], [(14.0, 16.4), (17.9, 17.0)]);
/// let images = [(&o, &go), (&e, &ge)].map(|(a, g)| FitImage { img: a.view(), var: None, mask: None, guesses: g });
/// let fit = fit_psf_joint(&images, &params).unwrap();
/// assert!((fit.fits[1].stars[1].flux / 6e3 - 1.0).abs() < 1e-4);
/// assert!((fit.fits[1].stars[0].x - 14.3).abs() < 1e-4 && (fit.fits[0].beta - 3.0).abs() < 1e-3);
/// ```
pub fn fit_psf_joint(images: &[FitImage], params: &PsfFitParams) -> Result<JointFit, PsfFitError> {
    let Some(first) = images.first() else {
        return Err(PsfFitError::NoSources);
    };
    check_params(first.guesses, params)?;
    let n_src = first.guesses.len();
    if images.iter().any(|im| im.guesses.len() != n_src) {
        return Err(PsfFitError::InvalidParams {
            name: "guesses (a different number of stars per image)",
            value: images.len() as f64,
        });
    }
    let Some(b) = params.background else {
        return Err(PsfFitError::InvalidParams {
            name: "background (a joint fit holds it fixed)",
            value: f64::NAN,
        });
    };
    let weighted = first.var.is_some();
    if images.iter().any(|im| im.var.is_some() != weighted) {
        return Err(PsfFitError::InvalidParams {
            name: "var (given for some images only)",
            value: images.len() as f64,
        });
    }
    let lay = Layout::panels(n_src, params.elliptical, false, params.model, images.len());
    // Every image's pixels, panel by panel; the bounding box of them all.
    let mut pixels: Vec<Pixel> = Vec::new();
    let mut bx = (usize::MAX, 0, usize::MAX, 0);
    let mut per_image = Vec::with_capacity(images.len());
    for (q, im) in images.iter().enumerate() {
        let (px, b) = fit_pixels(im.img, im.var, im.mask, im.guesses, params.fit_radius_px);
        per_image.push(px.len());
        if !px.is_empty() {
            bx = (bx.0.min(b.0), bx.1.max(b.1), bx.2.min(b.2), bx.3.max(b.3));
        }
        pixels.extend(px.into_iter().map(|p| Pixel { panel: q as u8, ..p }));
    }
    if pixels.len() <= lay.n || per_image.contains(&0) {
        return Err(PsfFitError::TooFewPixels {
            n_pixels: pixels.len(),
            n_params: lay.n,
        });
    }
    // Start: the first image's stars and shape; each further image's fluxes from its own
    // pixels, its shift from the guesses.
    let single = Layout::new(n_src, params.elliptical, false, params.model);
    let panel = |q: usize| {
        let lo = pixels.partition_point(|px| (px.panel as usize) < q);
        let hi = pixels.partition_point(|px| (px.panel as usize) <= q);
        &pixels[lo..hi]
    };
    let mut p = start_values(params, &single, panel(0), first.guesses);
    p.resize(lay.n, 0.0);
    let mut shift_guesses = Vec::new();
    for (q, im) in images.iter().enumerate().skip(1) {
        let own = start_values(params, &single, panel(q), im.guesses);
        let shift = im.guesses.iter().zip(first.guesses).fold((0.0, 0.0), |s, (g, g0)| {
            (s.0 + (g.0 - g0.0) / n_src as f64, s.1 + (g.1 - g0.1) / n_src as f64)
        });
        shift_guesses.push(shift);
        let src = lay.srcs.iter().filter(|s| s.panel as usize == q).collect::<Vec<_>>();
        for (k, s) in src.iter().enumerate() {
            p[s.flux] = own[3 * k];
        }
        let (sx, sy) = src[0].shift.expect("a further panel's star is shifted");
        p[sx] = shift.0;
        p[sy] = shift.1;
    }
    let problem = Problem {
        lay: &lay,
        fixed_b: Some(b),
        pixels: &pixels,
        bx,
        guesses: first.guesses,
        shift_guesses: &shift_guesses,
        rf: params.fit_radius_px,
        to_the_end: false,
    };
    let sol = problem.solve(p, params.max_iter);
    let cov = covariance_of(&problem, &sol, weighted)?;
    let dof = pixels.len() - lay.n;
    // Each image's parameters as a linear map of the joint ones: rows of (coefficient,
    // index) pairs in the single-image layout.
    let mut fits = Vec::with_capacity(images.len());
    let mut flux_index = Vec::with_capacity(images.len());
    for (q, &n_pixels) in per_image.iter().enumerate() {
        let src: Vec<_> = lay.srcs.iter().filter(|s| s.panel as usize == q).collect();
        let mut rows: Vec<Vec<usize>> = vec![Vec::new(); single.n];
        for (k, s) in src.iter().enumerate() {
            rows[3 * k] = vec![s.flux];
            rows[3 * k + 1] = std::iter::once(s.x).chain(s.shift.map(|sh| sh.0)).collect();
            rows[3 * k + 2] = std::iter::once(s.y).chain(s.shift.map(|sh| sh.1)).collect();
        }
        for (i, row) in rows.iter_mut().enumerate().skip(3 * n_src) {
            *row = vec![i];
        }
        let value = |r: &Vec<usize>| r.iter().map(|&i| sol.p[i]).sum::<f64>();
        let pq: Vec<f64> = rows.iter().map(value).collect();
        let covq: Vec<Vec<f64>> = rows
            .iter()
            .map(|ri| {
                rows.iter()
                    .map(|rj| {
                        ri.iter()
                            .flat_map(|&a| rj.iter().map(move |&b| (a, b)))
                            .map(|(a, b)| cov[a][b])
                            .sum()
                    })
                    .collect()
            })
            .collect();
        flux_index.push(src.iter().map(|s| s.flux).collect());
        fits.push(assemble(
            &single,
            &pq,
            covq,
            params,
            Fitted {
                chi2: sol.chi2,
                dof,
                n_pixels,
                iterations: sol.iterations,
                converged: sol.converged,
            },
        ));
    }
    Ok(JointFit {
        fits,
        covariance: cov,
        flux_index,
    })
}

#[cfg(test)]
mod tests;
