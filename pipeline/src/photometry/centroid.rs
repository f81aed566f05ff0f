//! Centroid refinement: iterative Gaussian-windowed first moment (SExtractor's XWIN idea).

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use super::aperture::mirror_stencil;
use super::background::{annulus_background, Annulus, BkgStat};
use super::model::FWHM_PER_SIGMA;

/// Settings of [`centroid`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CentroidParams {
    /// Expected FWHM of the star, px; the window is a Gaussian of this FWHM, cut at 4 sigma.
    pub fwhm_px: f64,
    /// Maximum iterations.
    pub max_iter: u32,
    /// Stop when a step is shorter than this, px.
    pub tol_px: f64,
    /// Give up (None) if the centroid wanders farther than this from the guess, px.
    pub max_shift_px: f64,
    /// Background level to subtract, ADU; None: sigma-clipped median of a ring of pixels
    /// between 4 and 4 + max(3, 2) sigma_window around the guess.
    pub background: Option<f64>,
}

impl Default for CentroidParams {
    fn default() -> Self {
        CentroidParams {
            fwhm_px: 3.0,
            max_iter: 100,
            tol_px: 1e-6,
            max_shift_px: 5.0,
            background: None,
        }
    }
}

/// A refined position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Centroid {
    /// x, px.
    pub x: f64,
    /// y, px.
    pub y: f64,
    /// Iterations done.
    pub iterations: u32,
    /// True if the last step was below `tol_px`.
    pub converged: bool,
    /// Background level that was subtracted, ADU.
    pub background: f64,
}

/// Refines the position of the star near `(x0, y0)` (px).
///
/// Iterates `c <- c + g * sum(w I d) / sum(w I)` with `I` = background-subtracted pixel values,
/// `d` = pixel centre - `c`, `w = exp(-|d|^2 / 2 s^2)` (s = FWHM/2.3548, window cut at 4 s),
/// and gain `g = 1.5` (the exact gain for a Gaussian star matching the window is 2; 1.5 still
/// converges fast and cannot oscillate when the star is narrower than the window). The fixed
/// point is where the windowed first moment vanishes, i.e. the centre of a symmetric star.
/// A masked (nonzero) or non-finite pixel takes the value bilinearly interpolated at its mirror
/// image through the current centre (skipped if that is not possible).
///
/// Returns None when the windowed flux is not positive or the centroid leaves
/// `max_shift_px` of the guess.
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::{centroid, model::add_gaussian, CentroidParams};
/// let mut img = Array2::<f32>::from_elem((32, 32), 10.0);
/// add_gaussian(&mut img.view_mut(), 1e4, 15.3, 16.7, 1.3, 1.3);
/// let c = centroid(img.view(), None, 16.0, 16.0, &CentroidParams::default()).unwrap();
/// assert!((c.x - 15.3).abs() < 1e-3 && (c.y - 16.7).abs() < 1e-3);
/// ```
pub fn centroid(
    img: ArrayView2<f32>,
    mask: Option<ArrayView2<u8>>,
    x0: f64,
    y0: f64,
    params: &CentroidParams,
) -> Option<Centroid> {
    let (ny, nx) = img.dim();
    if params.fwhm_px.is_nan() || params.fwhm_px <= 0.0 || !x0.is_finite() || !y0.is_finite() || nx == 0 || ny == 0 {
        return None;
    }
    let sw = params.fwhm_px / FWHM_PER_SIGMA;
    let rwin = (4.0 * sw).max(2.0);
    let background = match params.background {
        Some(b) => b,
        None => {
            let ann = Annulus {
                x: x0,
                y: y0,
                r_in: rwin,
                r_out: rwin + (2.0 * sw).max(3.0),
            };
            annulus_background(img, mask, &ann, &[], BkgStat::ClippedMedian, 3.0, 5).map_or(0.0, |b| b.level)
        }
    };
    let inv2s2 = 0.5 / (sw * sw);
    let good = |ix: usize, iy: usize| img[[iy, ix]].is_finite() && mask.as_ref().is_none_or(|m| m[[iy, ix]] == 0);
    let (mut x, mut y) = (x0, y0);
    let mut converged = false;
    let mut iterations = 0;
    while iterations < params.max_iter {
        iterations += 1;
        let y_lo = (y - rwin).floor().max(0.0) as usize;
        let y_hi = ((y + rwin).ceil().min(ny as f64 - 1.0)).max(0.0) as usize;
        let x_lo = (x - rwin).floor().max(0.0) as usize;
        let x_hi = ((x + rwin).ceil().min(nx as f64 - 1.0)).max(0.0) as usize;
        let (mut s0, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
        for iy in y_lo..=y_hi {
            let dy = iy as f64 - y;
            for ix in x_lo..=x_hi {
                let dx = ix as f64 - x;
                let d2 = dx * dx + dy * dy;
                if d2 >= rwin * rwin {
                    continue;
                }
                let v = if good(ix, iy) {
                    img[[iy, ix]] as f64
                } else {
                    // A bad pixel takes the value at its mirror image through the current
                    // centre, so that a hole does not pull the moment off-centre.
                    match mirror_stencil((ny, nx), good, x, y, ix, iy) {
                        Some(st) => st
                            .iter()
                            .filter(|s| s.2 != 0.0)
                            .map(|&(a, b, w)| w * img[[b, a]] as f64)
                            .sum(),
                        None => continue,
                    }
                };
                let wi = (-d2 * inv2s2).exp() * (v - background);
                s0 += wi;
                sx += wi * dx;
                sy += wi * dy;
            }
        }
        if s0.is_nan() || s0 <= 0.0 {
            return None;
        }
        let (stx, sty) = (1.5 * sx / s0, 1.5 * sy / s0);
        x += stx;
        y += sty;
        if (x - x0).hypot(y - y0) > params.max_shift_px {
            return None;
        }
        if stx.hypot(sty) < params.tol_px {
            converged = true;
            break;
        }
    }
    Some(Centroid {
        x,
        y,
        iterations,
        converged,
        background,
    })
}
