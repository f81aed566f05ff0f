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

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};

use super::model::{add_gaussian, gauss_pixel_1d, gauss_pixel_1d_derivs, FWHM_PER_SIGMA};
use super::moffat::{add_moffat, add_moffat_where, moffat_alpha, moffat_fwhm, moffat_pixel, moffat_pixel_derivs};

/// Range of the Moffat `alpha` accepted by the fit, px.
pub const MOFFAT_ALPHA_RANGE: (f64, f64) = (0.3, 30.0);
/// Range of the Moffat `beta` accepted by the fit (when fitted).
pub const MOFFAT_BETA_RANGE: (f64, f64) = (1.2, 10.0);
/// Starting `beta` of a Moffat fit with a free `beta` (typical of seeing-limited PSFs).
pub const MOFFAT_BETA_START: f64 = 3.0;

/// The PSF model of [`fit_psf`]. In TOML: `{ kind = "gaussian" }`, `{ kind = "moffat" }`
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

/// Errors of [`fit_psf`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PsfFitError {
    /// No initial position was given.
    #[error("PSF fit: no source position given")]
    NoSources,
    /// Too few usable pixels.
    #[error("PSF fit: {n_pixels} usable pixels for {n_params} parameters")]
    TooFewPixels {
        /// Usable pixels found.
        n_pixels: usize,
        /// Parameters to fit.
        n_params: usize,
    },
    /// A setting is out of range.
    #[error("PSF fit: invalid setting {name} = {value}")]
    InvalidParams {
        /// Setting name.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// The normal matrix could not be inverted at the solution (degenerate model).
    #[error("PSF fit: singular normal matrix at the solution (degenerate sources?)")]
    Singular,
}

/// Settings of [`fit_psf`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PsfFitParams {
    /// Initial FWHM, px.
    pub fwhm_px: f64,
    /// Pixels whose centre is within this distance of any initial position are fitted, px.
    pub fit_radius_px: f64,
    /// Fit separate widths along x and y (axis-aligned ellipse) instead of one.
    pub elliptical: bool,
    /// None: fit a constant background; Some(b): hold it fixed at b ADU (e.g. 0 on
    /// sky-subtracted frames).
    pub background: Option<f64>,
    /// Maximum Levenberg-Marquardt iterations.
    pub max_iter: u32,
    /// PSF model (default Gaussian). `elliptical` is for the Gaussian only.
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

/// Result of [`fit_psf`].
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
    /// Background level, ADU (fitted or fixed).
    pub background: f64,
    /// Covariance matrix of the parameters, in the order of `param_names`. With a variance
    /// map it is `(J^T W J)^-1`; without, it is scaled by the reduced chi-square.
    /// `covariance[i][j]`, row-major.
    pub covariance: Vec<Vec<f64>>,
    /// Parameter names: `flux_0, x_0, y_0, ..., sigma_x, [sigma_y], [background]` (Gaussian)
    /// or `flux_0, x_0, y_0, ..., alpha, [beta], [background]` (Moffat).
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
    /// FWHM along x, px (the circular FWHM for a Moffat).
    pub fn fwhm_x(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * self.sigma_x,
            PsfModel::Moffat { .. } => self.fwhm(),
        }
    }
    /// FWHM along y, px (the circular FWHM for a Moffat).
    pub fn fwhm_y(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * self.sigma_y,
            PsfModel::Moffat { .. } => self.fwhm(),
        }
    }
    /// FWHM, px: `2 alpha sqrt(2^(1/beta) - 1)` for a Moffat, the geometric mean of the x and y
    /// FWHMs for a Gaussian.
    pub fn fwhm(&self) -> f64 {
        match self.model {
            PsfModel::Gaussian => FWHM_PER_SIGMA * (self.sigma_x * self.sigma_y).sqrt(),
            PsfModel::Moffat { .. } => moffat_fwhm(self.alpha, self.beta),
        }
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
            PsfModel::Moffat { .. } => s.flux * moffat_pixel(px - s.x, py - s.y, self.alpha, self.beta),
        }
    }
    /// Adds `scale` times the model of star `k` (not the background) to `img`; `scale = -1`
    /// subtracts it. Panics if `k` is out of range.
    pub fn render_star(&self, k: usize, img: &mut ArrayViewMut2<f32>, scale: f64) {
        let s = &self.stars[k];
        match self.model {
            PsfModel::Gaussian => add_gaussian(img, scale * s.flux, s.x, s.y, self.sigma_x, self.sigma_y),
            PsfModel::Moffat { .. } => add_moffat(img, scale * s.flux, s.x, s.y, self.alpha, self.beta),
        }
    }
}

struct Layout {
    n_src: usize,
    /// sigma_x (Gaussian) or alpha (Moffat).
    i_sx: usize,
    /// sigma_y (= i_sx unless elliptical; = i_sx for a Moffat).
    i_sy: usize,
    /// Moffat beta, when fitted.
    i_beta: Option<usize>,
    i_b: Option<usize>,
    n: usize,
    /// Some(fixed beta or NaN when fitted) for a Moffat.
    moffat: Option<f64>,
}

impl Layout {
    fn new(n_src: usize, elliptical: bool, fit_b: bool, model: PsfModel) -> Layout {
        let i_sx = 3 * n_src;
        match model {
            PsfModel::Gaussian => {
                let i_sy = if elliptical { i_sx + 1 } else { i_sx };
                let i_b = fit_b.then_some(i_sy + 1);
                Layout {
                    n_src,
                    i_sx,
                    i_sy,
                    i_beta: None,
                    i_b,
                    n: i_sy + 1 + fit_b as usize,
                    moffat: None,
                }
            }
            PsfModel::Moffat { beta } => {
                let i_beta = beta.is_none().then_some(i_sx + 1);
                let last = i_beta.unwrap_or(i_sx);
                let i_b = fit_b.then_some(last + 1);
                Layout {
                    n_src,
                    i_sx,
                    i_sy: i_sx,
                    i_beta,
                    i_b,
                    n: last + 1 + fit_b as usize,
                    moffat: Some(beta.unwrap_or(f64::NAN)),
                }
            }
        }
    }

    /// Moffat beta at parameters `p`.
    fn beta(&self, p: &[f64]) -> f64 {
        match self.i_beta {
            Some(i) => p[i],
            None => self.moffat.unwrap_or(f64::NAN),
        }
    }
}

struct Pixel {
    ix: usize,
    iy: usize,
    v: f64,
    w: f64, // 1 / sigma
}

/// The model's 1-D factors for every column/row of the fitted box, per star.
struct Factors {
    x0: usize,
    y0: usize,
    // [star][col] -> (P, dP/dmu, dP/dsigma)
    fx: Vec<Vec<(f64, f64, f64)>>,
    fy: Vec<Vec<(f64, f64, f64)>>,
}

impl Factors {
    fn new(p: &[f64], lay: &Layout, bx: (usize, usize, usize, usize)) -> Factors {
        let (x0, x1, y0, y1) = bx;
        let (sx, sy) = (p[lay.i_sx], p[lay.i_sy]);
        let fx = (0..lay.n_src)
            .map(|k| {
                (x0..=x1)
                    .map(|ix| gauss_pixel_1d_derivs(ix as i64, p[3 * k + 1], sx))
                    .collect()
            })
            .collect();
        let fy = (0..lay.n_src)
            .map(|k| {
                (y0..=y1)
                    .map(|iy| gauss_pixel_1d_derivs(iy as i64, p[3 * k + 2], sy))
                    .collect()
            })
            .collect();
        Factors { x0, y0, fx, fy }
    }
}

fn background_of(p: &[f64], lay: &Layout, fixed: Option<f64>) -> f64 {
    match lay.i_b {
        Some(i) => p[i],
        None => fixed.unwrap_or(0.0),
    }
}

/// chi2, and when `normal` is given, fills it with (J^T W J, J^T W r).
fn evaluate(
    p: &[f64],
    lay: &Layout,
    fixed_b: Option<f64>,
    pixels: &[Pixel],
    bx: (usize, usize, usize, usize),
    mut normal: Option<(&mut [f64], &mut [f64])>,
) -> f64 {
    let f = match lay.moffat {
        None => Some(Factors::new(p, lay, bx)),
        Some(_) => None,
    };
    let (alpha, beta) = (p[lay.i_sx], lay.beta(p));
    let b = background_of(p, lay, fixed_b);
    let n = lay.n;
    let mut jrow = vec![0.0; n];
    if let Some((a, g)) = normal.as_mut() {
        a.iter_mut().for_each(|v| *v = 0.0);
        g.iter_mut().for_each(|v| *v = 0.0);
    }
    let mut chi2 = 0.0;
    for px in pixels {
        let mut m = b;
        if normal.is_some() {
            jrow.iter_mut().for_each(|v| *v = 0.0);
        }
        match &f {
            Some(f) => {
                let (cx, cy) = (px.ix - f.x0, px.iy - f.y0);
                for k in 0..lay.n_src {
                    let flux = p[3 * k];
                    let (gx, dgx, sgx) = f.fx[k][cx];
                    let (gy, dgy, sgy) = f.fy[k][cy];
                    m += flux * gx * gy;
                    if normal.is_some() {
                        jrow[3 * k] = gx * gy;
                        jrow[3 * k + 1] = flux * dgx * gy;
                        jrow[3 * k + 2] = flux * gx * dgy;
                        jrow[lay.i_sx] += flux * sgx * gy;
                        jrow[lay.i_sy] += flux * gx * sgy; // same slot as sx when circular
                    }
                }
            }
            None => {
                for k in 0..lay.n_src {
                    let flux = p[3 * k];
                    let (dx, dy) = (px.ix as f64 - p[3 * k + 1], px.iy as f64 - p[3 * k + 2]);
                    if normal.is_some() {
                        let d = moffat_pixel_derivs(dx, dy, alpha, beta);
                        m += flux * d[0];
                        jrow[3 * k] = d[0];
                        jrow[3 * k + 1] = flux * d[1];
                        jrow[3 * k + 2] = flux * d[2];
                        jrow[lay.i_sx] += flux * d[3];
                        if let Some(ib) = lay.i_beta {
                            jrow[ib] += flux * d[4];
                        }
                    } else {
                        m += flux * moffat_pixel(dx, dy, alpha, beta);
                    }
                }
            }
        }
        let r = (px.v - m) * px.w;
        chi2 += r * r;
        if let Some((a, g)) = normal.as_mut() {
            if let Some(ib) = lay.i_b {
                jrow[ib] = 1.0;
            }
            for i in 0..n {
                let ji = jrow[i] * px.w;
                g[i] += ji * r;
                for j in 0..=i {
                    a[i * n + j] += ji * jrow[j] * px.w;
                }
            }
        }
    }
    if let Some((a, _)) = normal.as_mut() {
        for i in 0..n {
            for j in 0..i {
                a[j * n + i] = a[i * n + j];
            }
        }
    }
    chi2
}

/// In-place Cholesky factorisation of the symmetric n x n matrix `a` (lower triangle).
fn cholesky(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d.is_nan() || d <= 0.0 {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    true
}

/// Solves `L L^T x = b` with the factor from [`cholesky`].
fn cholesky_solve(l: &[f64], n: usize, b: &[f64]) -> Vec<f64> {
    let mut y = b.to_vec();
    for i in 0..n {
        for k in 0..i {
            y[i] -= l[i * n + k] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            y[i] -= l[k * n + i] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    y
}

/// Fits `guesses.len()` pixel-integrated Gaussians or Moffats ([`PsfFitParams::model`]) with a
/// shared shape to the image near the initial positions `guesses` (px). `var` (ADU^2) weights
/// the pixels; `mask` (nonzero = bad) and non-finite pixels are skipped.
///
/// Robustness: a step that would make a Gaussian width leave `[0.05, 50]` px, a Moffat alpha
/// leave [`MOFFAT_ALPHA_RANGE`], a fitted beta leave [`MOFFAT_BETA_RANGE`], or move a star
/// farther than `fit_radius_px` from its initial position is rejected (the damping grows
/// instead).
pub fn fit_psf(
    img: ArrayView2<f32>,
    var: Option<ArrayView2<f32>>,
    mask: Option<ArrayView2<u8>>,
    guesses: &[(f64, f64)],
    params: &PsfFitParams,
) -> Result<PsfFit, PsfFitError> {
    if guesses.is_empty() {
        return Err(PsfFitError::NoSources);
    }
    if !(params.fwhm_px > 0.0 && params.fwhm_px.is_finite()) {
        return Err(PsfFitError::InvalidParams {
            name: "fwhm_px",
            value: params.fwhm_px,
        });
    }
    if !(params.fit_radius_px > 0.0 && params.fit_radius_px.is_finite()) {
        return Err(PsfFitError::InvalidParams {
            name: "fit_radius_px",
            value: params.fit_radius_px,
        });
    }
    if let PsfModel::Moffat { beta } = params.model {
        if params.elliptical {
            return Err(PsfFitError::InvalidParams {
                name: "elliptical (Moffat is circular)",
                value: 1.0,
            });
        }
        if let Some(b) = beta {
            if !(b > 1.0 && b.is_finite()) {
                return Err(PsfFitError::InvalidParams { name: "beta", value: b });
            }
        }
    }
    let (ny, nx) = img.dim();
    let lay = Layout::new(
        guesses.len(),
        params.elliptical,
        params.background.is_none(),
        params.model,
    );
    let rf = params.fit_radius_px;

    // Pixels to fit.
    let mut pixels = Vec::new();
    let (mut bx0, mut bx1, mut by0, mut by1) = (usize::MAX, 0usize, usize::MAX, 0usize);
    if nx > 0 && ny > 0 {
        let gx0 = guesses.iter().map(|g| g.0).fold(f64::INFINITY, f64::min) - rf;
        let gx1 = guesses.iter().map(|g| g.0).fold(f64::NEG_INFINITY, f64::max) + rf;
        let gy0 = guesses.iter().map(|g| g.1).fold(f64::INFINITY, f64::min) - rf;
        let gy1 = guesses.iter().map(|g| g.1).fold(f64::NEG_INFINITY, f64::max) + rf;
        let clampi = |v: f64, n: usize| v.max(0.0).min(n as f64 - 1.0) as usize;
        for iy in clampi(gy0.floor(), ny)..=clampi(gy1.ceil(), ny) {
            for ix in clampi(gx0.floor(), nx)..=clampi(gx1.ceil(), nx) {
                let near = guesses
                    .iter()
                    .any(|&(gx, gy)| (ix as f64 - gx).powi(2) + (iy as f64 - gy).powi(2) <= rf * rf);
                let v = img[[iy, ix]];
                if !near || !v.is_finite() || mask.as_ref().is_some_and(|m| m[[iy, ix]] != 0) {
                    continue;
                }
                let w = match &var {
                    Some(vm) => {
                        let q = vm[[iy, ix]];
                        if !(q > 0.0 && q.is_finite()) {
                            continue;
                        }
                        1.0 / (q as f64).sqrt()
                    }
                    None => 1.0,
                };
                pixels.push(Pixel { ix, iy, v: v as f64, w });
                bx0 = bx0.min(ix);
                bx1 = bx1.max(ix);
                by0 = by0.min(iy);
                by1 = by1.max(iy);
            }
        }
    }
    if pixels.len() <= lay.n {
        return Err(PsfFitError::TooFewPixels {
            n_pixels: pixels.len(),
            n_params: lay.n,
        });
    }
    let bx = (bx0, bx1, by0, by1);

    // Initial values: background = 20th percentile of the fitted pixels; each flux from the
    // pixel nearest its guess, as the peak of a pixel-integrated model of the initial width.
    let s0 = params.fwhm_px / FWHM_PER_SIGMA;
    let beta0 = match params.model {
        PsfModel::Gaussian => f64::NAN,
        PsfModel::Moffat { beta } => beta.unwrap_or(MOFFAT_BETA_START),
    };
    let (shape0, peak_frac) = match params.model {
        PsfModel::Gaussian => (s0, gauss_pixel_1d(0, 0.0, s0).powi(2)),
        PsfModel::Moffat { .. } => {
            let a0 = moffat_alpha(params.fwhm_px, beta0).clamp(MOFFAT_ALPHA_RANGE.0, MOFFAT_ALPHA_RANGE.1);
            (a0, moffat_pixel(0.0, 0.0, a0, beta0))
        }
    };
    let mut p = vec![0.0; lay.n];
    let b0 = match params.background {
        Some(b) => b,
        None => {
            let mut vals: Vec<f64> = pixels.iter().map(|q| q.v).collect();
            let k = vals.len() / 5;
            *vals.select_nth_unstable_by(k, f64::total_cmp).1
        }
    };
    for (k, &(gx, gy)) in guesses.iter().enumerate() {
        let nearest = pixels
            .iter()
            .min_by(|a, b| {
                let da = (a.ix as f64 - gx).powi(2) + (a.iy as f64 - gy).powi(2);
                let db = (b.ix as f64 - gx).powi(2) + (b.iy as f64 - gy).powi(2);
                da.total_cmp(&db)
            })
            .map_or(0.0, |q| q.v);
        p[3 * k] = ((nearest - b0) / peak_frac).max(1e-3);
        p[3 * k + 1] = gx;
        p[3 * k + 2] = gy;
    }
    p[lay.i_sx] = shape0;
    p[lay.i_sy] = shape0;
    if let Some(ib) = lay.i_beta {
        p[ib] = beta0;
    }
    if let Some(ib) = lay.i_b {
        p[ib] = b0;
    }

    let n = lay.n;
    let acceptable = |q: &[f64]| -> bool {
        let widths_ok = match lay.moffat {
            None => [q[lay.i_sx], q[lay.i_sy]].iter().all(|&s| (0.05..=50.0).contains(&s)),
            Some(_) => {
                (MOFFAT_ALPHA_RANGE.0..=MOFFAT_ALPHA_RANGE.1).contains(&q[lay.i_sx])
                    && lay
                        .i_beta
                        .is_none_or(|i| (MOFFAT_BETA_RANGE.0..=MOFFAT_BETA_RANGE.1).contains(&q[i]))
            }
        };
        let pos_ok = guesses
            .iter()
            .enumerate()
            .all(|(k, &(gx, gy))| (q[3 * k + 1] - gx).hypot(q[3 * k + 2] - gy) <= rf);
        widths_ok && pos_ok && q.iter().all(|v| v.is_finite())
    };
    let mut a = vec![0.0; n * n];
    let mut g = vec![0.0; n];
    // The trial point's normal equations are built with its chi-square (same operations,
    // bit-identical chi-square): an accepted step then needs no second evaluation.
    let mut a_trial = vec![0.0; n * n];
    let mut g_trial = vec![0.0; n];
    let mut chi2 = evaluate(&p, &lay, params.background, &pixels, bx, Some((&mut a, &mut g)));
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut iterations = 0;
    while iterations < params.max_iter {
        iterations += 1;
        let mut damped = a.clone();
        for i in 0..n {
            let d = a[i * n + i];
            damped[i * n + i] = d + lambda * d.max(1e-300);
        }
        let step = if cholesky(&mut damped, n) {
            Some(cholesky_solve(&damped, n, &g))
        } else {
            None
        };
        let trial: Option<Vec<f64>> = step.map(|d| p.iter().zip(&d).map(|(x, dx)| x + dx).collect());
        let improved = match &trial {
            Some(q) if acceptable(q) => {
                let c = evaluate(
                    q,
                    &lay,
                    params.background,
                    &pixels,
                    bx,
                    Some((&mut a_trial, &mut g_trial)),
                );
                (c <= chi2).then_some(c)
            }
            _ => None,
        };
        match (improved, trial) {
            (Some(c), Some(q)) => {
                let small_step = p.iter().zip(&q).all(|(x, y)| (x - y).abs() <= 1e-10 * (x.abs() + 1e-6));
                let small_gain = chi2 - c <= 1e-13 * chi2;
                p = q;
                chi2 = c;
                std::mem::swap(&mut a, &mut a_trial);
                std::mem::swap(&mut g, &mut g_trial);
                lambda = (lambda * 0.1).max(1e-12);
                if small_step || small_gain || chi2 == 0.0 {
                    converged = true;
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e12 {
                    // No downhill step exists at working precision: we are at the minimum.
                    converged = true;
                    break;
                }
            }
        }
    }

    // Covariance from the undamped normal matrix.
    let mut l = a.clone();
    if !cholesky(&mut l, n) {
        return Err(PsfFitError::Singular);
    }
    let dof = pixels.len() - n;
    let scale = if var.is_some() { 1.0 } else { chi2 / dof as f64 };
    let mut cov = vec![vec![0.0; n]; n];
    for j in 0..n {
        let mut e = vec![0.0; n];
        e[j] = 1.0;
        let col = cholesky_solve(&l, n, &e);
        for i in 0..n {
            cov[i][j] = col[i] * scale;
        }
    }
    let err = |i: usize| cov[i][i].max(0.0).sqrt();
    let stars = (0..lay.n_src)
        .map(|k| PsfStar {
            flux: p[3 * k],
            x: p[3 * k + 1],
            y: p[3 * k + 2],
            flux_err: err(3 * k),
            x_err: err(3 * k + 1),
            y_err: err(3 * k + 2),
        })
        .collect();
    let mut names: Vec<String> = (0..lay.n_src)
        .flat_map(|k| [format!("flux_{k}"), format!("x_{k}"), format!("y_{k}")])
        .collect();
    let (sigma_x, sigma_y, alpha, beta) = match lay.moffat {
        None => {
            names.push("sigma_x".into());
            if params.elliptical {
                names.push("sigma_y".into());
            }
            (p[lay.i_sx], p[lay.i_sy], f64::NAN, f64::NAN)
        }
        Some(_) => {
            names.push("alpha".into());
            if lay.i_beta.is_some() {
                names.push("beta".into());
            }
            let (a, b) = (p[lay.i_sx], lay.beta(&p));
            let s = moffat_fwhm(a, b) / FWHM_PER_SIGMA;
            (s, s, a, b)
        }
    };
    if lay.i_b.is_some() {
        names.push("background".into());
    }
    Ok(PsfFit {
        stars,
        model: params.model,
        sigma_x,
        sigma_y,
        alpha,
        beta,
        background: background_of(&p, &lay, params.background),
        covariance: cov,
        param_names: names,
        chi2,
        dof,
        n_pixels: pixels.len(),
        iterations,
        converged,
    })
}

/// [`fit_psf`] for a pair: `a` and `b` are the initial positions of the two components.
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::{fit_two_psf, model::add_gaussian, subtract_star, PsfFitParams};
/// // Two stars 4 px apart (1.4 FWHM), on a sky of 5 ADU.
/// let mut img = Array2::<f32>::from_elem((40, 40), 5.0);
/// add_gaussian(&mut img.view_mut(), 2e4, 18.0, 20.0, 1.2, 1.2);
/// add_gaussian(&mut img.view_mut(), 5e3, 22.0, 20.5, 1.2, 1.2);
/// let fit = fit_two_psf(img.view(), None, None, (18.3, 19.8), (21.6, 20.9), &PsfFitParams::default()).unwrap();
/// assert!((fit.stars[1].flux / 5e3 - 1.0).abs() < 1e-4);
/// // Deblend: the primary alone (plus sky).
/// let primary = subtract_star(img.view(), &fit, 1);
/// assert!((primary[[20, 22]] - 5.0) < 0.1 * (img[[20, 22]] - 5.0));
/// ```
pub fn fit_two_psf(
    img: ArrayView2<f32>,
    var: Option<ArrayView2<f32>>,
    mask: Option<ArrayView2<u8>>,
    a: (f64, f64),
    b: (f64, f64),
    params: &PsfFitParams,
) -> Result<PsfFit, PsfFitError> {
    fit_psf(img, var, mask, &[a, b], params)
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
        PsfModel::Moffat { .. } => add_moffat_where(&mut view, -s.flux, x, y, fit.alpha, fit.beta, |ix, iy| {
            keep(ix + x0, iy + y0)
        }),
    }
}
