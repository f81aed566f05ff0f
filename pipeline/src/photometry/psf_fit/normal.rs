//! The normal equations of the PSF fit: the parameter layout, the fitted pixels, and the
//! chi-square with `(J^T W J, J^T W r)` from the analytic Jacobians of the pixel-integrated
//! models (Gaussian: erf differences per axis; Moffat: the batched Moffat kernel).

use crate::photometry::model::gauss_pixel_1d_derivs;
use crate::photometry::moffat::{moffat_pixels, moffat_pixels_derivs};
use crate::photometry::psf::PsfModel;

/// Where each parameter sits in the parameter vector (see [`crate::photometry::PsfFit::param_names`]).
pub(super) struct Layout {
    pub(super) n_src: usize,
    /// sigma_x (Gaussian) or alpha (Moffat).
    pub(super) i_sx: usize,
    /// sigma_y (= i_sx unless elliptical; = i_sx for a Moffat).
    pub(super) i_sy: usize,
    /// Moffat beta, when fitted.
    pub(super) i_beta: Option<usize>,
    pub(super) i_b: Option<usize>,
    pub(super) n: usize,
    /// Some(fixed beta or NaN when fitted) for a Moffat.
    pub(super) moffat: Option<f64>,
}

impl Layout {
    pub(super) fn new(n_src: usize, elliptical: bool, fit_b: bool, model: PsfModel) -> Layout {
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
    pub(super) fn beta(&self, p: &[f64]) -> f64 {
        match self.i_beta {
            Some(i) => p[i],
            None => self.moffat.unwrap_or(f64::NAN),
        }
    }
}

/// A fitted pixel: its indices, value (ADU) and weight.
pub(super) struct Pixel {
    pub(super) ix: usize,
    pub(super) iy: usize,
    pub(super) v: f64,
    pub(super) w: f64, // 1 / sigma
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

/// The background at parameters `p`: fitted, or held fixed at `fixed` (else 0).
pub(super) fn background_of(p: &[f64], lay: &Layout, fixed: Option<f64>) -> f64 {
    match lay.i_b {
        Some(i) => p[i],
        None => fixed.unwrap_or(0.0),
    }
}

/// chi2, and when `normal` is given, fills it with (J^T W J, J^T W r).
pub(super) fn evaluate(
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
    // A Moffat's pixel values (and derivatives) of every star at every pixel, from the
    // batched kernel: star k's at [k * pixels.len()..].
    let np = pixels.len();
    let (mut values, mut derivs) = (Vec::new(), Vec::new());
    if lay.moffat.is_some() {
        let mut offsets = Vec::with_capacity(np);
        if normal.is_some() {
            derivs = vec![[0.0; 5]; np * lay.n_src];
        } else {
            values = vec![0.0; np * lay.n_src];
        }
        for k in 0..lay.n_src {
            offsets.clear();
            offsets.extend(
                pixels
                    .iter()
                    .map(|px| (px.ix as f64 - p[3 * k + 1], px.iy as f64 - p[3 * k + 2])),
            );
            if normal.is_some() {
                moffat_pixels_derivs(&offsets, alpha, beta, &mut derivs[k * np..(k + 1) * np]);
            } else {
                moffat_pixels(&offsets, alpha, beta, &mut values[k * np..(k + 1) * np]);
            }
        }
    }
    let mut chi2 = 0.0;
    for (ip, px) in pixels.iter().enumerate() {
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
                    if normal.is_some() {
                        let d = derivs[k * np + ip];
                        m += flux * d[0];
                        jrow[3 * k] = d[0];
                        jrow[3 * k + 1] = flux * d[1];
                        jrow[3 * k + 2] = flux * d[2];
                        jrow[lay.i_sx] += flux * d[3];
                        if let Some(ib) = lay.i_beta {
                            jrow[ib] += flux * d[4];
                        }
                    } else {
                        m += flux * values[k * np + ip];
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
