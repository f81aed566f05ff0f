//! PSF fitting of one or a few close stars: pixel-integrated Gaussians or circular Moffats
//! with a shared shape, separate fluxes and positions, fitted by a small hand-written
//! Levenberg-Marquardt.
//!
//! Gaussian model of pixel `(ix, iy)`: `b + sum_k F_k Px(ix; x_k, sx) Py(iy; y_k, sy)` (see
//! [`super::model`]); Moffat model: `b + sum_k F_k M(ix - x_k, iy - y_k; alpha, beta)` with `M`
//! the pixel integral of the unit-flux Moffat (see [`super::moffat`]). Fluxes are total fluxes.
//! Parameters, in this order (also [`PsfFit::param_names`]):
//! `F_0, x_0, y_0, F_1, x_1, y_1, ..., sx, [sy if elliptical], [b if fitted]` (Gaussian) or
//! `F_0, x_0, y_0, ..., alpha, [beta if fitted], [b if fitted]` (Moffat).
//! Deblending a close pair: fit both, then [`subtract_star`] the companion's model from the
//! image and do aperture photometry of the target on the result.
//!
//! This file holds the model, settings and result types and the star subtraction; the fit
//! itself ([`fit_psf`](super::fit_psf), [`fit_two_psf`](super::fit_two_psf)) is in
//! `psf_fit/`.

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};

use super::model::{add_gaussian, FWHM_PER_SIGMA};
use super::moffat::{
    add_moffat, add_moffat_elliptical, add_moffat_elliptical_where, add_moffat_where, moffat_fwhm, moffat_pixel,
    moffat_pixel_elliptical, MoffatStar,
};

/// Range of the Moffat `alpha` accepted by the fit, px.
pub const MOFFAT_ALPHA_RANGE: (f64, f64) = (0.3, 30.0);
/// Range of the Moffat `beta` accepted by the fit (when fitted).
pub const MOFFAT_BETA_RANGE: (f64, f64) = (1.2, 10.0);
/// Largest ellipticity `|e|` an elliptical Moffat fit accepts (axis ratio 0.58).
pub const MOFFAT_ELLIPTICITY_MAX: f64 = 0.5;
/// Starting `beta` of a Moffat fit with a free `beta` (typical of seeing-limited PSFs).
pub const MOFFAT_BETA_START: f64 = 3.0;

/// The PSF model of [`fit_psf`](super::fit_psf). In TOML: `{ kind = "gaussian" }`, `{ kind = "moffat" }`
/// (free beta) or `{ kind = "moffat", beta = 3.0 }` (fixed beta).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum PsfModel {
    /// Pixel-integrated (axis-aligned) Gaussian, exact erf differences.
    #[default]
    Gaussian,
    /// Circular Moffat `(beta-1)/(pi alpha^2) (1 + r^2/alpha^2)^-beta`, integrated over each
    /// pixel by Gauss-Legendre quadrature.
    Moffat {
        /// None: `beta` is fitted (shared by all stars, started at [`MOFFAT_BETA_START`],
        /// kept in [`MOFFAT_BETA_RANGE`]); Some(b): held fixed at b (> 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        beta: Option<f64>,
    },
}

/// Errors of [`fit_psf`](super::fit_psf) (defined with the crate's other errors).
pub use crate::error::PsfFitError;

/// Settings of [`fit_psf`](super::fit_psf).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PsfFitParams {
    /// Initial FWHM, px.
    pub fwhm_px: f64,
    /// Pixels whose centre is within this distance of any initial position are fitted, px.
    pub fit_radius_px: f64,
    /// An elliptical shape: a Gaussian gets separate widths along x and y (axis-aligned); a
    /// Moffat gets an ellipticity `(e1, e2)` at any angle ([`super::moffat`]), started
    /// circular, `|e|` at most [`MOFFAT_ELLIPTICITY_MAX`].
    pub elliptical: bool,
    /// None: fit a constant background; Some(b): hold it fixed at b ADU (e.g. 0 on
    /// sky-subtracted frames).
    pub background: Option<f64>,
    /// Maximum Levenberg-Marquardt iterations.
    pub max_iter: u32,
    /// PSF model (default Gaussian).
    #[serde(default)]
    pub model: PsfModel,
}

impl Default for PsfFitParams {
    fn default() -> Self {
        PsfFitParams {
            fwhm_px: 3.0,
            fit_radius_px: 8.0,
            elliptical: false,
            background: None,
            max_iter: 200,
            model: PsfModel::Gaussian,
        }
    }
}

/// One fitted star. Errors are 1-sigma from the covariance matrix.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PsfStar {
    /// Total flux of the star (the integral of the model over the plane), ADU.
    pub flux: f64,
    /// Centre x, px.
    pub x: f64,
    /// Centre y, px.
    pub y: f64,
    /// Error of `flux`, ADU.
    pub flux_err: f64,
    /// Error of `x`, px.
    pub x_err: f64,
    /// Error of `y`, px.
    pub y_err: f64,
}

/// Result of [`fit_psf`](super::fit_psf).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PsfFit {
    /// The stars, in the order of the initial positions.
    pub stars: Vec<PsfStar>,
    /// The model fitted (as in [`PsfFitParams::model`]: `Moffat { beta: None }` when beta was
    /// fitted; its value is [`PsfFit::beta`]).
    pub model: PsfModel,
    /// Gaussian sigma along x, px. For a Moffat: the sigma of the Gaussian of the same FWHM,
    /// `fwhm() / 2.3548` (informational).
    pub sigma_x: f64,
    /// Gaussian sigma along y, px (= sigma_x unless elliptical).
    pub sigma_y: f64,
    /// Moffat alpha, px (NaN for a Gaussian).
    pub alpha: f64,
    /// Moffat beta, fitted or fixed (NaN for a Gaussian).
    pub beta: f64,
    /// An elliptical Moffat's ellipticity `(e1, e2)` ([`super::moffat`]; `[0, 0]`: circular,
    /// and for a Gaussian).
    #[serde(default)]
    pub ellipticity: [f64; 2],
    /// Background level, ADU (fitted or fixed).
    pub background: f64,
    /// Covariance matrix of the parameters, in the order of `param_names`. With a variance
    /// map it is `(J^T W J)^-1`; without, it is scaled by the reduced chi-square.
    /// `covariance[i][j]`, row-major.
    pub covariance: Vec<Vec<f64>>,
    /// Parameter names: `flux_0, x_0, y_0, ..., sigma_x, [sigma_y], [background]` (Gaussian)
    /// or `flux_0, x_0, y_0, ..., alpha, [beta], [e1, e2], [background]` (Moffat).
    pub param_names: Vec<String>,
    /// Final chi-square (weighted by 1/variance when a variance map was given).
    pub chi2: f64,
    /// Degrees of freedom (pixels - parameters).
    pub dof: usize,
    /// Pixels used.
    pub n_pixels: usize,
    /// Iterations done.
    pub iterations: u32,
    /// False if the iteration limit was reached before convergence.
    pub converged: bool,
}

impl PsfFit {
    /// FWHM along x, px (for a Moffat [`PsfFit::fwhm`]).
    pub fn fwhm_x(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * self.sigma_x,
            PsfModel::Moffat { .. } => self.fwhm(),
        }
    }
    /// FWHM along y, px (for a Moffat [`PsfFit::fwhm`]).
    pub fn fwhm_y(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * self.sigma_y,
            PsfModel::Moffat { .. } => self.fwhm(),
        }
    }
    /// FWHM, px: `2 alpha sqrt(2^(1/beta) - 1)` for a circular Moffat, the geometric mean of
    /// the two axes' FWHMs for an elliptical one (`/ (1 - |e|^2)^(1/4)`) and for a Gaussian.
    pub fn fwhm(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * (self.sigma_x * self.sigma_y).sqrt(),
            PsfModel::Moffat { .. } if self.is_elliptical() => {
                let [e1, e2] = self.ellipticity;
                moffat_fwhm(self.alpha, self.beta) / (1.0 - e1 * e1 - e2 * e2).powf(0.25)
            }
            PsfModel::Moffat { .. } => moffat_fwhm(self.alpha, self.beta),
        }
    }
    /// Whether the fitted shape is an elliptical Moffat (a nonzero ellipticity).
    pub fn is_elliptical(&self) -> bool {
        self.ellipticity != [0.0; 2]
    }
    /// Model flux (ADU, background excluded) of star `k` in the pixel centred at `(px, py)`
    /// (pixel centres are integers; any position is accepted). Panics if `k` is out of range.
    pub fn model_value(&self, k: usize, px: f64, py: f64) -> f64 {
        let s = &self.stars[k];
        match self.model {
            PsfModel::Gaussian => {
                let fx =
                    super::model::normal_cdf_diff((px - 0.5 - s.x) / self.sigma_x, (px + 0.5 - s.x) / self.sigma_x);
                let fy =
                    super::model::normal_cdf_diff((py - 0.5 - s.y) / self.sigma_y, (py + 0.5 - s.y) / self.sigma_y);
                s.flux * fx * fy
            }
            PsfModel::Moffat { .. } if self.is_elliptical() => {
                s.flux * moffat_pixel_elliptical(px - s.x, py - s.y, self.alpha, self.beta, self.ellipticity)
            }
            PsfModel::Moffat { .. } => s.flux * moffat_pixel(px - s.x, py - s.y, self.alpha, self.beta),
        }
    }
    /// Adds `scale` times the model of star `k` (not the background) to `img`; `scale = -1`
    /// subtracts it. Panics if `k` is out of range.
    pub fn render_star(&self, k: usize, img: &mut ArrayViewMut2<f32>, scale: f64) {
        let s = &self.stars[k];
        match self.model {
            PsfModel::Gaussian => add_gaussian(img, scale * s.flux, s.x, s.y, self.sigma_x, self.sigma_y),
            PsfModel::Moffat { .. } if self.is_elliptical() => {
                add_moffat_elliptical(img, scale * s.flux, s.x, s.y, self.alpha, self.beta, self.ellipticity)
            }
            PsfModel::Moffat { .. } => add_moffat(img, scale * s.flux, s.x, s.y, self.alpha, self.beta),
        }
    }
}

/// A copy of `img` with the fitted model of star `k` (not the background) subtracted: the
/// deblended image on which to measure the other star(s). Panics if `k` is out of range.
pub fn subtract_star(img: ArrayView2<f32>, fit: &PsfFit, k: usize) -> Array2<f32> {
    let mut out = img.to_owned();
    fit.render_star(k, &mut out.view_mut(), -1.0);
    out
}

/// [`subtract_star`] on the pixels of the square `[floor(c - radius), ceil(c + radius)]` about
/// `centre` (clipped to the image; it holds every pixel within `radius`) only: there the
/// values are those of [`subtract_star`] bit for bit (the star is rendered into a sub-view
/// with shifted coordinates; differences of pixel indices and positions are exact), the
/// input's elsewhere. For deblending before aperture photometry, which reads only the
/// aperture and the annulus: the Moffat's 1e-9 wings otherwise cover the whole image.
/// Panics if `k` is out of range.
pub fn subtract_star_near(
    img: ArrayView2<f32>,
    fit: &PsfFit,
    k: usize,
    centre: (f64, f64),
    radius: f64,
) -> Array2<f32> {
    let mut out = img.to_owned();
    subtract_star_near_in_place(&mut out, fit, k, centre, radius);
    out
}

/// [`subtract_star_near`] in place.
pub fn subtract_star_near_in_place(img: &mut Array2<f32>, fit: &PsfFit, k: usize, centre: (f64, f64), radius: f64) {
    subtract_star_near_where(img, fit, k, centre, radius, |_, _| true);
}

/// [`subtract_star_near_in_place`] that may leave the pixels `(ix, iy)` (image indices) with
/// `keep(ix, iy)` false as they are (a Moffat skips them: its pixel integrals are the
/// costly part); every other pixel gets the value [`subtract_star_near`] gives it, bit for
/// bit. For photometry that reads only some of the square (the aperture and the unexcluded
/// part of the annulus).
pub fn subtract_star_near_where(
    img: &mut Array2<f32>,
    fit: &PsfFit,
    k: usize,
    (cx, cy): (f64, f64),
    radius: f64,
    keep: impl Fn(usize, usize) -> bool,
) {
    let (ny, nx) = img.dim();
    let s = fit.stars[k];
    if nx == 0 || ny == 0 || !(cx.is_finite() && cy.is_finite() && radius >= 0.0) {
        return;
    }
    let clampi = |v: f64, n: usize| v.max(0.0).min(n as f64 - 1.0) as usize;
    let (x0, x1) = (clampi((cx - radius).floor(), nx), clampi((cx + radius).ceil(), nx));
    let (y0, y1) = (clampi((cy - radius).floor(), ny), clampi((cy + radius).ceil(), ny));
    let mut view = img.slice_mut(ndarray::s![y0..=y1, x0..=x1]);
    let (x, y) = (s.x - x0 as f64, s.y - y0 as f64);
    match fit.model {
        PsfModel::Gaussian => add_gaussian(&mut view, -s.flux, x, y, fit.sigma_x, fit.sigma_y),
        PsfModel::Moffat { .. } if fit.is_elliptical() => add_moffat_elliptical_where(
            &mut view,
            MoffatStar {
                flux: -s.flux,
                x_px: x,
                y_px: y,
                alpha_px: fit.alpha,
                beta: fit.beta,
                e: fit.ellipticity,
            },
            |ix, iy| keep(ix + x0, iy + y0),
        ),
        PsfModel::Moffat { .. } => add_moffat_where(&mut view, -s.flux, x, y, fit.alpha, fit.beta, |ix, iy| {
            keep(ix + x0, iy + y0)
        }),
    }
}
