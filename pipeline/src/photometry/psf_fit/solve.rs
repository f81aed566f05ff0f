//! The damped Levenberg-Marquardt iteration of the PSF fit and its linear algebra (Cholesky
//! factorisation and solve of the small normal matrix).

use super::normal::{evaluate, Layout, Pixel};
use crate::photometry::psf::{MOFFAT_ALPHA_RANGE, MOFFAT_BETA_RANGE, MOFFAT_ELLIPTICITY_MAX};

/// In-place Cholesky factorisation of the symmetric n x n matrix `a` (lower triangle).
pub(super) fn cholesky(a: &mut [f64], n: usize) -> bool {
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

/// The chi-square decrease `g . d` of the undamped Gauss-Newton step `A d = g`, by the
/// quadratic model; `None` when `A` is not positive definite.
fn predicted_gain(a: &[f64], g: &[f64], n: usize) -> Option<f64> {
    let mut l = a.to_vec();
    cholesky(&mut l, n).then(|| cholesky_solve(&l, n, g).iter().zip(g).map(|(d, g)| d * g).sum())
}

/// Solves `L L^T x = b` with the factor from [`cholesky`].
pub(super) fn cholesky_solve(l: &[f64], n: usize, b: &[f64]) -> Vec<f64> {
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

/// What one fit works on.
pub(super) struct Problem<'a> {
    pub(super) lay: &'a Layout,
    /// The background when it is held fixed.
    pub(super) fixed_b: Option<f64>,
    pub(super) pixels: &'a [Pixel],
    /// Bounding box of the pixels (x0, x1, y0, y1).
    pub(super) bx: (usize, usize, usize, usize),
    pub(super) guesses: &'a [(f64, f64)],
    /// Per panel after the first, the shift of its stars from panel 0's it starts from.
    pub(super) shift_guesses: &'a [(f64, f64)],
    /// Fit radius: no star (and no panel's shift) may move farther from its guess.
    pub(super) rf: f64,
    /// No early stops (see [`super::fit_psf_until`]).
    pub(super) to_the_end: bool,
}

/// Where the iteration stopped.
pub(super) struct Solution {
    pub(super) p: Vec<f64>,
    pub(super) chi2: f64,
    /// The undamped normal matrix at `p`.
    pub(super) a: Vec<f64>,
    pub(super) iterations: u32,
    pub(super) converged: bool,
}

impl Problem<'_> {
    /// Whether a trial point is inside the accepted ranges.
    fn acceptable(&self, q: &[f64]) -> bool {
        let lay = self.lay;
        let widths_ok = match lay.moffat {
            None => [q[lay.i_sx], q[lay.i_sy]].iter().all(|&s| (0.05..=50.0).contains(&s)),
            Some(_) => {
                (MOFFAT_ALPHA_RANGE.0..=MOFFAT_ALPHA_RANGE.1).contains(&q[lay.i_sx])
                    && lay
                        .i_beta
                        .is_none_or(|i| (MOFFAT_BETA_RANGE.0..=MOFFAT_BETA_RANGE.1).contains(&q[i]))
                    && lay
                        .ellipticity(q)
                        .is_none_or(|e| e[0].hypot(e[1]) <= MOFFAT_ELLIPTICITY_MAX)
            }
        };
        let pos_ok = self
            .guesses
            .iter()
            .enumerate()
            .all(|(k, &(gx, gy))| (q[3 * k + 1] - gx).hypot(q[3 * k + 2] - gy) <= self.rf);
        let shifts_ok = lay
            .srcs
            .iter()
            .filter_map(|s| s.shift.map(|sh| (s.panel, sh)))
            .all(|(panel, (sx, sy))| {
                let (gx, gy) = self.shift_guesses[panel as usize - 1];
                (q[sx] - gx).hypot(q[sy] - gy) <= self.rf
            });
        widths_ok && pos_ok && shifts_ok && q.iter().all(|v| v.is_finite())
    }

    /// chi2 at `p`, and the normal equations there into `normal`.
    fn evaluate(&self, p: &[f64], normal: Option<(&mut [f64], &mut [f64])>) -> f64 {
        evaluate(p, self.lay, self.fixed_b, self.pixels, self.bx, normal)
    }

    /// The damped Levenberg-Marquardt iteration from `p`.
    pub(super) fn solve(&self, mut p: Vec<f64>, max_iter: u32) -> Solution {
        /// Absolute chi-square gain of an accepted Gauss-Newton step below which the fit
        /// has converged.
        const CHI2_GAIN_DONE: f64 = 1e-6;
        let n = self.lay.n;
        let mut a = vec![0.0; n * n];
        let mut g = vec![0.0; n];
        // The trial point's normal equations are built with its chi-square (same operations,
        // bit-identical chi-square): an accepted step then needs no second evaluation.
        let mut a_trial = vec![0.0; n * n];
        let mut g_trial = vec![0.0; n];
        let mut chi2 = self.evaluate(&p, Some((&mut a, &mut g)));
        let mut lambda = 1e-3;
        let mut converged = false;
        let mut iterations = 0;
        while iterations < max_iter {
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
                Some(q) if self.acceptable(q) => {
                    let c = self.evaluate(q, Some((&mut a_trial, &mut g_trial)));
                    (c <= chi2).then_some(c)
                }
                _ => None,
            };
            match (improved, trial) {
                (Some(c), Some(q)) => {
                    let small_step = p.iter().zip(&q).all(|(x, y)| (x - y).abs() <= 1e-10 * (x.abs() + 1e-6));
                    // Converged when the step gained less than 1e-13 of chi-square, or less
                    // than 1e-6 in absolute terms at Gauss-Newton damping: from there the
                    // minimum is within ~1e-3 sigma of every parameter (chi-square rises by 1
                    // at 1 sigma), far below the noise (q, u of the bench night move by
                    // <= 1e-5 sigma), and the last iterations cost 12 % of the fits.
                    let small_gain = chi2 - c <= 1e-13 * chi2 || (chi2 - c <= CHI2_GAIN_DONE && lambda <= 1e-2);
                    let gauss_newton = lambda <= 1e-2;
                    p = q;
                    chi2 = c;
                    std::mem::swap(&mut a, &mut a_trial);
                    std::mem::swap(&mut g, &mut g_trial);
                    lambda = (lambda * 0.1).max(1e-12);
                    if self.to_the_end {
                        continue;
                    }
                    if small_step || small_gain || chi2 == 0.0 {
                        converged = true;
                        break;
                    }
                    // The same rule one step ahead: when the next Gauss-Newton step would
                    // gain less than CHI2_GAIN_DONE by the quadratic model (g.d with
                    // A d = g, which the last steps follow closely), stop here rather
                    // than evaluate it (the fits' last evaluation; the parameters stay
                    // within ~1e-3 sigma of the minimum, as with the rule above).
                    if gauss_newton && predicted_gain(&a, &g, n).is_some_and(|d| d <= CHI2_GAIN_DONE) {
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
        Solution {
            p,
            chi2,
            a,
            iterations,
            converged,
        }
    }
}
