//! The normal equations of the PSF fit: the parameter layout, the fitted pixels, and the
//! chi-square with `(J^T W J, J^T W r)` from the analytic Jacobians of the pixel-integrated
//! models (Gaussian: erf differences per axis; Moffat: the batched Moffat kernel).
//!
//! A fit may span several images ("panels", e.g. the o and e beams of one exposure): every
//! panel holds the same stars with the same shape; panel 0 has each star's flux and
//! position, every other panel its own flux per star and one shift of all positions.

use crate::photometry::model::gauss_pixel_1d_derivs;
use crate::photometry::moffat::{moffat_pixels, moffat_pixels_derivs_any, moffat_pixels_elliptical};
use crate::photometry::psf::PsfModel;

/// One star as seen in one panel: where its flux and position sit in the parameter vector.
/// Its position is `(p[x], p[y])`, plus `(p[shift.0], p[shift.1])` outside panel 0.
#[derive(Debug, Clone, Copy)]
pub(super) struct Src {
    pub(super) flux: usize,
    pub(super) x: usize,
    pub(super) y: usize,
    pub(super) shift: Option<(usize, usize)>,
    pub(super) panel: u8,
}

/// Where each parameter sits in the parameter vector (see [`crate::photometry::PsfFit::param_names`]):
/// panel 0's stars `(flux, x, y)`, the shape, beta, the background; then, per further panel,
/// a flux per star and the shift (x, y).
pub(super) struct Layout {
    /// Stars per panel.
    pub(super) n_src: usize,
    /// Every star in every panel, panel by panel.
    pub(super) srcs: Vec<Src>,
    /// Panels (1 for a single image).
    /// sigma_x (Gaussian) or alpha (Moffat).
    pub(super) i_sx: usize,
    /// sigma_y (= i_sx unless elliptical; = i_sx for a Moffat).
    pub(super) i_sy: usize,
    /// Moffat beta, when fitted.
    pub(super) i_beta: Option<usize>,
    /// An elliptical Moffat's (e1, e2), at `i_e` and `i_e + 1`.
    pub(super) i_e: Option<usize>,
    pub(super) i_b: Option<usize>,
    pub(super) n: usize,
    /// Some(fixed beta or NaN when fitted) for a Moffat.
    pub(super) moffat: Option<f64>,
    pub(super) n_panels: usize,
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
                    srcs: single_panel(n_src),
                    i_sx,
                    i_sy,
                    i_beta: None,
                    i_e: None,
                    i_b,
                    n: i_sy + 1 + fit_b as usize,
                    moffat: None,
                    n_panels: 1,
                }
            }
            PsfModel::Moffat { beta } => {
                let i_beta = beta.is_none().then_some(i_sx + 1);
                let i_e = elliptical.then_some(i_beta.unwrap_or(i_sx) + 1);
                let last = i_e.map_or(i_beta.unwrap_or(i_sx), |i| i + 1);
                let i_b = fit_b.then_some(last + 1);
                Layout {
                    n_src,
                    srcs: single_panel(n_src),
                    i_sx,
                    i_sy: i_sx,
                    i_beta,
                    i_e,
                    i_b,
                    n: last + 1 + fit_b as usize,
                    moffat: Some(beta.unwrap_or(f64::NAN)),
                    n_panels: 1,
                }
            }
        }
    }

    /// The layout of `n_panels` panels: [`Layout::new`]'s parameters, then per further
    /// panel a flux per star and a shift (x, y) of the positions.
    pub(super) fn panels(n_src: usize, elliptical: bool, fit_b: bool, model: PsfModel, n_panels: usize) -> Layout {
        let mut lay = Layout::new(n_src, elliptical, fit_b, model);
        for panel in 1..n_panels {
            let shift = (lay.n + n_src, lay.n + n_src + 1);
            for k in 0..n_src {
                lay.srcs.push(Src {
                    flux: lay.n + k,
                    x: 3 * k + 1,
                    y: 3 * k + 2,
                    shift: Some(shift),
                    panel: panel as u8,
                });
            }
            lay.n += n_src + 2;
        }
        lay.n_panels = n_panels;
        lay
    }

    /// The position of `src` at parameters `p`.
    pub(super) fn position(&self, src: &Src, p: &[f64]) -> (f64, f64) {
        match src.shift {
            Some((sx, sy)) => (p[src.x] + p[sx], p[src.y] + p[sy]),
            None => (p[src.x], p[src.y]),
        }
    }

    /// An elliptical Moffat's (e1, e2) at parameters `p` (None: circular).
    pub(super) fn ellipticity(&self, p: &[f64]) -> Option<[f64; 2]> {
        self.i_e.map(|i| [p[i], p[i + 1]])
    }

    /// Moffat beta at parameters `p`.
    pub(super) fn beta(&self, p: &[f64]) -> f64 {
        match self.i_beta {
            Some(i) => p[i],
            None => self.moffat.unwrap_or(f64::NAN),
        }
    }
}

/// Panel 0's stars, `(flux, x, y)` at `3k..3k + 3`.
fn single_panel(n_src: usize) -> Vec<Src> {
    (0..n_src)
        .map(|k| Src {
            flux: 3 * k,
            x: 3 * k + 1,
            y: 3 * k + 2,
            shift: None,
            panel: 0,
        })
        .collect()
}

/// A fitted pixel: its panel, its indices there, value (ADU) and weight. The pixels of a
/// fit are ordered by panel.
pub(super) struct Pixel {
    pub(super) ix: usize,
    pub(super) iy: usize,
    pub(super) v: f64,
    pub(super) w: f64, // 1 / sigma
    pub(super) panel: u8,
}

/// The model's 1-D factors for every column/row of the fitted box, per star.
struct Factors {
    x0: usize,
    y0: usize,
    // [star in a panel (Layout::srcs)][col] -> (P, dP/dmu, dP/dsigma)
    fx: Vec<Vec<(f64, f64, f64)>>,
    fy: Vec<Vec<(f64, f64, f64)>>,
}

impl Factors {
    fn new(p: &[f64], lay: &Layout, bx: (usize, usize, usize, usize)) -> Factors {
        let (x0, x1, y0, y1) = bx;
        let (sx, sy) = (p[lay.i_sx], p[lay.i_sy]);
        let pos: Vec<(f64, f64)> = lay.srcs.iter().map(|s| lay.position(s, p)).collect();
        let fx = pos
            .iter()
            .map(|&(x, _)| (x0..=x1).map(|ix| gauss_pixel_1d_derivs(ix as i64, x, sx)).collect())
            .collect();
        let fy = pos
            .iter()
            .map(|&(_, y)| (y0..=y1).map(|iy| gauss_pixel_1d_derivs(iy as i64, y, sy)).collect())
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
    let (alpha, beta, ell) = (p[lay.i_sx], lay.beta(p), lay.ellipticity(p));
    let b = background_of(p, lay, fixed_b);
    let n = lay.n;
    let mut jrow = vec![0.0; n];
    if let Some((a, g)) = normal.as_mut() {
        a.iter_mut().for_each(|v| *v = 0.0);
        g.iter_mut().for_each(|v| *v = 0.0);
    }
    // The pixels of each panel (they come ordered by panel), and each panel's stars.
    let np = pixels.len();
    let panel_pixels: Vec<std::ops::Range<usize>> = (0..lay.n_panels)
        .map(|q| {
            let lo = pixels.partition_point(|px| (px.panel as usize) < q);
            let hi = pixels.partition_point(|px| (px.panel as usize) <= q);
            lo..hi
        })
        .collect();
    let panel_srcs: Vec<Vec<usize>> = (0..lay.n_panels)
        .map(|q| {
            (0..lay.srcs.len())
                .filter(|&j| lay.srcs[j].panel as usize == q)
                .collect()
        })
        .collect();
    // A Moffat's pixel values (and derivatives) of every star at every pixel of its panel,
    // from the batched kernel: star j's at [j * np + ip].
    let (mut values, mut derivs) = (Vec::new(), Vec::new());
    if lay.moffat.is_some() {
        let mut offsets = Vec::with_capacity(np);
        if normal.is_some() {
            derivs = vec![[0.0; 7]; np * lay.srcs.len()];
        } else {
            values = vec![0.0; np * lay.srcs.len()];
        }
        for (j, src) in lay.srcs.iter().enumerate() {
            let range = panel_pixels[src.panel as usize].clone();
            let (x, y) = lay.position(src, p);
            offsets.clear();
            offsets.extend(
                pixels[range.clone()]
                    .iter()
                    .map(|px| (px.ix as f64 - x, px.iy as f64 - y)),
            );
            let at = j * np + range.start..j * np + range.end;
            match (normal.is_some(), ell) {
                (true, _) => moffat_pixels_derivs_any(&offsets, alpha, beta, ell, &mut derivs[at]),
                (false, None) => moffat_pixels(&offsets, alpha, beta, &mut values[at]),
                (false, Some(e)) => moffat_pixels_elliptical(&offsets, alpha, beta, e, &mut values[at]),
            }
        }
    }
    let mut chi2 = 0.0;
    for (ip, px) in pixels.iter().enumerate() {
        let mut m = b;
        if normal.is_some() {
            jrow.iter_mut().for_each(|v| *v = 0.0);
        }
        for &j in &panel_srcs[px.panel as usize] {
            let src = &lay.srcs[j];
            let flux = p[src.flux];
            // The model's value at the pixel per unit flux and its derivatives in x, y and
            // the shape (width; beta for a fitted Moffat beta).
            // (and the ellipticity's for an elliptical Moffat).
            let (v, dx, dy, dsx, dsy, dbeta, de) = match &f {
                Some(f) => {
                    let (cx, cy) = (px.ix - f.x0, px.iy - f.y0);
                    let (gx, dgx, sgx) = f.fx[j][cx];
                    let (gy, dgy, sgy) = f.fy[j][cy];
                    (gx * gy, dgx * gy, gx * dgy, sgx * gy, gx * sgy, 0.0, [0.0; 2])
                }
                None if normal.is_some() => {
                    let d = derivs[j * np + ip];
                    (d[0], d[1], d[2], d[3], 0.0, d[4], [d[5], d[6]])
                }
                None => (values[j * np + ip], 0.0, 0.0, 0.0, 0.0, 0.0, [0.0; 2]),
            };
            m += flux * v;
            if normal.is_some() {
                jrow[src.flux] = v;
                jrow[src.x] += flux * dx;
                jrow[src.y] += flux * dy;
                if let Some((sx, sy)) = src.shift {
                    jrow[sx] += flux * dx;
                    jrow[sy] += flux * dy;
                }
                jrow[lay.i_sx] += flux * dsx;
                if f.is_some() {
                    jrow[lay.i_sy] += flux * dsy; // same slot as sx when circular
                } else if let Some(ib) = lay.i_beta {
                    jrow[ib] += flux * dbeta;
                }
                if let Some(ie) = lay.i_e {
                    jrow[ie] += flux * de[0];
                    jrow[ie + 1] += flux * de[1];
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
