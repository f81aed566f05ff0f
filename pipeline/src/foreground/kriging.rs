//! The foreground at the binary by Bayesian ordinary kriging of the field stars (one
//! coordinate, q or u, at a time).
//!
//! # Why
//!
//! Dust varies smoothly on the sky: two field stars close together see more nearly the same
//! foreground than two far apart. Treating the binary as "one more random place" of the
//! field (the random-effects mean) is honest only when the places are independent; for a
//! field correlated over the strip it overstates the error at a binary in the middle of
//! its stars (pulls 0.7 at a coherence scale of 90", 0.4 at 600"), and it gives a star
//! next to the binary no more weight than one at the strip's far end.
//!
//! # The model
//!
//! The foreground (one coordinate) at place x is `f(x) = m + e(x)`, m unknown, with the
//! semivariogram
//!
//! ```text
//! gamma(h) = 1/2 E[(e(x) - e(x + h))^2] = t^2 [h > 0] + s^2 (h / H)^alpha,   H = 300"
//! ```
//!
//! a nugget t (variation between places closer than the stars are to each other: patchy
//! dust, independent from one object to the next, even at the same place) plus a power law
//! (a field that varies more the farther apart two places are; s^2 is its semivariance at
//! 5 arcmin, one SOFI field). A power law assumes no scale and needs no coherence length,
//! which 5-30 stars cannot measure; its exponent says how smooth the field is below the
//! stars' spacing: 1 is Brownian motion on the plane, 5/3 Kolmogorov turbulence, near 2 a
//! field as smooth as a gradient across the strip, below 1 a rough one. The dispersion of
//! polarization angles in molecular clouds grows with separation as such a power law over
//! the scales of a field (a turbulent part plus a smooth large-scale one), and the exponent
//! differs from cloud to cloud, so it is a parameter: alpha on [`ALPHAS`] with a flat prior.
//! With alpha fixed at 1, fields smooth below the stars' spacing got errors 1.3-1.4 times
//! too large (pulls 0.77 at a Gaussian coherence of 90"). Field
//! star j measures `y_j = f(x_j) + n_j`, n_j its measurement error (variance S_j).
//!
//! # Estimation
//!
//! For given (t, s, alpha), the covariance of the stars is `Sigma = diag(S_j) + t^2 I + s^2
//! (C - D)`, D the matrix of their (separation / H)^alpha and C a constant large enough for Sigma to
//! be positive definite: the restricted (REML) likelihood of (t, s) and the ordinary-kriging
//! predictor do not depend on C (both use only contrasts of the stars and weights that sum
//! to one). The ordinary-kriging weights lambda (sum 1) minimise the variance of the error
//! at the binary,
//!
//! ```text
//! V = lambda^T Sigma lambda - 2 lambda^T k_b + K_bb,
//! k_b,j = s^2 (C - d_jb),   K_bb = s^2 C + t^2
//! ```
//!
//! (d_jb the binary's (separation / H)^alpha; the binary's own nugget draw is in K_bb: it
//! is not measured by any star). t and s each get a flat prior on [0, tau_max] (as the
//! random-effects dispersion), alpha a flat one over [`ALPHAS`]; the REML likelihood is
//! evaluated on a [`GRID`] x [`GRID`] x 4 grid (a 24 x 24 grid gave the same pulls to
//! 0.001) and the prediction and its variance are the posterior mixture: `f_hat = sum_i
//! p_i lambda_i^T y`, `V = sum_i p_i (V_i + (f_i - f_hat)^2)`. The uncertainty of t, s and
//! alpha is thereby in the variance, as with the random-effects dispersion.
//!
//! When the stars show no spatial structure (s near 0), the prediction is the random-
//! effects weighted mean and V its error of the mean plus t^2: the model contains the
//! previous one.
use super::separation_arcmin;

/// Points per parameter of the posterior grid (t and s each, quadratic spacing from 0 to
/// the prior's bound: finer near 0 where a precise field's likelihood peaks).
pub const GRID: usize = 16;

/// The separation at which the power-law part's semivariance is s^2, arcsec (5 arcmin: one
/// SOFI field).
pub const H_ARCSEC: f64 = 300.0;

/// The exponents alpha of the power-law part `s^2 (h/H)^alpha` on the posterior grid
/// (a flat prior over them): from a rough field (0.5; 1 is Brownian motion on the plane) to
/// one nearly as smooth as a gradient (1.9; 2 is not a valid semivariogram with a nugget
/// alone and would be a plane).
pub const ALPHAS: [f64; 4] = [0.5, 1.0, 1.5, 1.9];

/// The most stars a prediction uses: the nearest to the binary (the cost grows as the cube
/// of the number; a star beyond the 60th nearest adds nothing the nearer ones do not say).
pub const MAX_STARS: usize = 60;

/// One star for the kriging.
#[derive(Debug, Clone, Copy)]
pub struct Site {
    /// The measured value (q or u).
    pub y: f64,
    /// Its measurement variance.
    pub var: f64,
    /// Right ascension, deg.
    pub ra_deg: f64,
    /// Declination, deg.
    pub dec_deg: f64,
}

/// The prediction at the binary.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// The foreground at the binary.
    pub value: f64,
    /// The variance of its error (the posterior mixture).
    pub var: f64,
    /// The posterior mean of the predictor's weights (sum 1), one per site.
    pub weights: Vec<f64>,
    /// E[t^2]: the nugget.
    pub nugget2: f64,
    /// E[s^2]: the power-law part's semivariance at [`H_ARCSEC`].
    pub slope2: f64,
    /// E\[alpha\]: the power-law part's exponent.
    pub alpha: f64,
}

/// Cholesky factor (lower, row-major) of the symmetric n x n `a`; None when not positive
/// definite.
fn cholesky(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if !(s > 0.0) {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    Some(l)
}

/// Solve `L L^T x = b` in place.
fn solve(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i * n + k] * b[k];
        }
        b[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= l[k * n + i] * b[k];
        }
        b[i] = s / l[i * n + i];
    }
}

/// Solve the small dense p x p system `a x = b` (Gaussian elimination with partial
/// pivoting); None when singular.
fn solve_dense(mut a: Vec<f64>, p: usize, mut b: Vec<f64>) -> Option<Vec<f64>> {
    for c in 0..p {
        let piv = (c..p).max_by(|&i, &j| a[i * p + c].abs().total_cmp(&a[j * p + c].abs()))?;
        if !(a[piv * p + c].abs() > 0.0) {
            return None;
        }
        for k in 0..p {
            a.swap(c * p + k, piv * p + k);
        }
        b.swap(c, piv);
        for i in c + 1..p {
            let f = a[i * p + c] / a[c * p + c];
            for k in c..p {
                a[i * p + k] -= f * a[c * p + k];
            }
            b[i] -= f * b[c];
        }
    }
    for c in (0..p).rev() {
        let s: f64 = (c + 1..p).map(|k| a[c * p + k] * b[k]).sum();
        b[c] = (b[c] - s) / a[c * p + c];
    }
    Some(b)
}

/// The REML log-likelihood, the kriging weights, prediction and error variance for one
/// (t^2, b = s^2), the separations `d` (stars, n x n) and `d_b` (stars to the binary) given
/// as `(h/H)^alpha`, with the drift columns `x` (n x p, row-major; the first all ones) and
/// the binary's `x_b`; None when the covariance is not positive definite at any C tried.
#[allow(clippy::too_many_arguments)]
fn at(
    sites: &[Site],
    d: &[f64],
    d_b: &[f64],
    x: &[f64],
    x_b: &[f64],
    c0: f64,
    t2: f64,
    b: f64,
) -> Option<(f64, Vec<f64>, f64, f64)> {
    let n = sites.len();
    let p = x_b.len();
    let mut c = c0;
    for _ in 0..8 {
        let mut sigma = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                sigma[i * n + j] = b * (c - d[i * n + j]);
            }
            sigma[i * n + i] += sites[i].var + t2;
        }
        let Some(l) = cholesky(&sigma, n) else {
            c *= 4.0;
            continue;
        };
        let ln_det: f64 = (0..n).map(|i| 2.0 * l[i * n + i].ln()).sum();
        // Sigma^-1 X, column by column.
        let mut six = vec![0.0; n * p];
        for a in 0..p {
            let mut col: Vec<f64> = (0..n).map(|i| x[i * p + a]).collect();
            solve(&l, n, &mut col);
            for i in 0..n {
                six[i * p + a] = col[i];
            }
        }
        let mut xsx = vec![0.0; p * p];
        for a in 0..p {
            for bb in 0..p {
                xsx[a * p + bb] = (0..n).map(|i| x[i * p + a] * six[i * p + bb]).sum();
            }
        }
        let ln_det_xsx = {
            // Determinant by the elimination of a copy (p <= 3).
            let mut m = xsx.clone();
            let mut det = 1.0;
            for cc in 0..p {
                let piv = (cc..p).max_by(|&i, &j| m[i * p + cc].abs().total_cmp(&m[j * p + cc].abs()))?;
                if piv != cc {
                    for k in 0..p {
                        m.swap(cc * p + k, piv * p + k);
                    }
                }
                let v = m[cc * p + cc];
                if v == 0.0 || v.is_nan() {
                    return None;
                }
                det *= v;
                for i in cc + 1..p {
                    let f = m[i * p + cc] / v;
                    for k in cc..p {
                        m[i * p + k] -= f * m[cc * p + k];
                    }
                }
            }
            det.abs().ln()
        };
        let mut siy: Vec<f64> = sites.iter().map(|s| s.y).collect();
        solve(&l, n, &mut siy);
        let y_siy: f64 = sites.iter().zip(&siy).map(|(s, v)| s.y * v).sum();
        let xsy: Vec<f64> = (0..p).map(|a| (0..n).map(|i| x[i * p + a] * siy[i]).sum()).collect();
        let beta = solve_dense(xsx.clone(), p, xsy.clone())?;
        let fit: f64 = beta.iter().zip(&xsy).map(|(b, v)| b * v).sum();
        let logl = -0.5 * (ln_det + ln_det_xsx + y_siy - fit);
        let k: Vec<f64> = d_b.iter().map(|db| b * (c - db)).collect();
        let mut sik = k.clone();
        solve(&l, n, &mut sik);
        // lambda = Sigma^-1 (k + X mu), X^T lambda = x_b.
        let rhs: Vec<f64> = (0..p)
            .map(|a| x_b[a] - (0..n).map(|i| x[i * p + a] * sik[i]).sum::<f64>())
            .collect();
        let mu = solve_dense(xsx, p, rhs)?;
        let lambda: Vec<f64> = (0..n)
            .map(|i| sik[i] + (0..p).map(|a| six[i * p + a] * mu[a]).sum::<f64>())
            .collect();
        let value: f64 = lambda.iter().zip(sites).map(|(w, s)| w * s.y).sum();
        // V = lambda^T Sigma lambda - 2 lambda^T k + K_bb.
        let mut quad = 0.0;
        for i in 0..n {
            let row: f64 = (0..n).map(|j| sigma[i * n + j] * lambda[j]).sum();
            quad += lambda[i] * row;
        }
        let lk: f64 = lambda.iter().zip(&k).map(|(a, b)| a * b).sum();
        let var = quad - 2.0 * lk + b * c + t2;
        if !(value.is_finite() && logl.is_finite() && var.is_finite()) {
            return None;
        }
        return Some((logl, lambda, value, var.max(0.0)));
    }
    None
}

/// The grid of one parameter (quadratic spacing on [0, tau_max]) and its trapezoid weights
/// for a flat prior.
fn grid(tau_max: f64) -> (Vec<f64>, Vec<f64>) {
    let gn = GRID;
    let g: Vec<f64> = (0..gn)
        .map(|i| tau_max * (i as f64 / (gn - 1) as f64).powi(2))
        .collect();
    let w: Vec<f64> = (0..gn)
        .map(|i| {
            let lo = if i == 0 { g[0] } else { g[i - 1] };
            let hi = if i + 1 == gn { g[gn - 1] } else { g[i + 1] };
            0.5 * (hi - lo)
        })
        .collect();
    (g, w)
}

/// Separations of the sites from each other (n x n) and from the binary, arcsec.
pub fn separations(sites: &[Site], ra_deg: f64, dec_deg: f64) -> (Vec<f64>, Vec<f64>) {
    let n = sites.len();
    let mut d = vec![0.0; n * n];
    for i in 0..n {
        for j in i + 1..n {
            let s = 60.0 * separation_arcmin(sites[i].ra_deg, sites[i].dec_deg, sites[j].ra_deg, sites[j].dec_deg);
            d[i * n + j] = s;
            d[j * n + i] = s;
        }
    }
    let d_b = sites
        .iter()
        .map(|s| 60.0 * separation_arcmin(ra_deg, dec_deg, s.ra_deg, s.dec_deg))
        .collect();
    (d, d_b)
}

/// One point of the posterior grid: the parameters, the REML log-likelihood, and the
/// kriging prediction, its error variance and weights at those parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct GridPoint {
    /// t^2.
    pub t2: f64,
    /// s^2.
    pub s2: f64,
    /// The power-law part's exponent ([`ALPHAS`]).
    pub alpha: f64,
    /// ln of the flat prior's trapezoid weight.
    pub ln_prior: f64,
    /// The REML log-likelihood.
    pub logl: f64,
    /// The prediction at the binary.
    pub value: f64,
    /// Its error variance.
    pub var: f64,
    /// The kriging weights (sum 1).
    pub lambda: Vec<f64>,
}

/// The posterior grid of the kriging at (`ra_deg`, `dec_deg`) from `sites` (module doc),
/// t and s on [0, `tau_max`] ([`GRID`] x [`GRID`] points, the same list for every field),
/// with a plane across the field as drift when `drift`. Empty when there are too few
/// sites.
pub fn grid_points(sites: &[Site], ra_deg: f64, dec_deg: f64, tau_max: f64, drift: bool) -> Vec<GridPoint> {
    let n = sites.len();
    let p = if drift { 3 } else { 1 };
    if n < p + 1 {
        return Vec::new();
    }
    let (d, d_b) = separations(sites, ra_deg, dec_deg);
    let cosd = dec_deg.to_radians().cos();
    let x: Vec<f64> = sites
        .iter()
        .flat_map(|s| {
            let de = ((s.ra_deg - ra_deg + 540.0).rem_euclid(360.0) - 180.0) * cosd * 3600.0 / H_ARCSEC;
            let dn = (s.dec_deg - dec_deg) * 3600.0 / H_ARCSEC;
            [1.0, de, dn].into_iter().take(p)
        })
        .collect();
    let x_b: Vec<f64> = [1.0, 0.0, 0.0].into_iter().take(p).collect();
    let (g, w) = grid(tau_max);
    let mut points = Vec::with_capacity(g.len() * g.len() * ALPHAS.len());
    for &alpha in &ALPHAS {
        let pow = |h: &f64| (h / H_ARCSEC).powf(alpha);
        let (d, d_b): (Vec<f64>, Vec<f64>) = (d.iter().map(pow).collect(), d_b.iter().map(pow).collect());
        let dmax = d.iter().chain(&d_b).copied().fold(0.0, f64::max);
        let c0 = 2.0 * dmax + 1.0;
        for (i, &t) in g.iter().enumerate() {
            for (j, &s) in g.iter().enumerate() {
                let prior = w[i] * w[j] / ALPHAS.len() as f64;
                // A grid point whose covariance is not positive definite (not seen: the nugget
                // and measurement variances are on the diagonal) keeps its place with zero
                // likelihood, so every field's grid stays the same list.
                let (logl, lambda, value, var) = at(sites, &d, &d_b, &x, &x_b, c0, t * t, s * s).unwrap_or((
                    f64::NEG_INFINITY,
                    vec![0.0; n],
                    0.0,
                    0.0,
                ));
                points.push(GridPoint {
                    t2: t * t,
                    s2: s * s,
                    alpha,
                    ln_prior: prior.ln(),
                    logl,
                    value,
                    var,
                    lambda,
                });
            }
        }
    }
    points
}

/// The posterior mixture of the grid's predictions, each point weighted by its likelihood,
/// its prior and `ln_extra(i)` (e.g. what the night's other fields say about t and s).
pub fn combine(points: &[GridPoint], ln_extra: impl Fn(usize) -> f64) -> Option<Prediction> {
    if points.is_empty() {
        return None;
    }
    let lp: Vec<f64> = points
        .iter()
        .enumerate()
        .map(|(i, p)| p.logl + p.ln_prior + ln_extra(i))
        .collect();
    let top = lp.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !top.is_finite() {
        return None;
    }
    let n = points[0].lambda.len();
    let mut z = 0.0;
    let (mut value, mut weights, mut nugget2, mut slope2, mut alpha) = (0.0, vec![0.0; n], 0.0, 0.0, 0.0);
    for (p, l) in points.iter().zip(&lp) {
        let w = (l - top).exp();
        z += w;
        value += w * p.value;
        nugget2 += w * p.t2;
        slope2 += w * p.s2;
        alpha += w * p.alpha;
        for (a, b) in weights.iter_mut().zip(&p.lambda) {
            *a += w * b;
        }
    }
    value /= z;
    nugget2 /= z;
    slope2 /= z;
    alpha /= z;
    weights.iter_mut().for_each(|w| *w /= z);
    let var = points
        .iter()
        .zip(&lp)
        .map(|(p, l)| (l - top).exp() * (p.var + (p.value - value).powi(2)))
        .sum::<f64>()
        / z;
    Some(Prediction {
        value,
        var,
        weights,
        nugget2,
        slope2,
        alpha,
    })
}

/// The night's prior of (t, s, alpha) over the common grid for one field, from the
/// night's other fields ([`night_prior`]).
#[derive(Debug, Clone, PartialEq)]
pub struct NightPrior {
    /// ln-weights relative to the flat prior, one per grid point (to add to each point's
    /// ln-likelihood + ln-prior).
    pub ln_weights: Vec<f64>,
    /// The flat prior's share of the mixture ([`FLAT_SHARES`]).
    pub flat_share: f64,
}

/// The flat prior's shares [`night_prior`] chooses from: from leaning almost wholly on the
/// other fields (1 %) to ignoring them (1).
pub const FLAT_SHARES: [f64; 8] = [0.01, 0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 1.0];

/// The prior of one field from the night's other fields `fields` (each the likelihood
/// grids of one field, q and u: `Vec`s of ln-likelihoods on the common grid of flat prior
/// weights `ln_prior`): the nonparametric maximum-likelihood distribution of (t, s, alpha)
/// over the grid (EM, [`EM_ROUNDS`] rounds from the flat prior), mixed with the flat prior.
///
/// The flat prior's share is chosen from [`FLAT_SHARES`] by how well the other fields
/// predict each other: each other field g's marginal likelihood (q and u) under the mixture
/// made without g and without the fields `related` to it (sharing its stars), in ln, one
/// score per share (at most [`LOO_FIELDS`] such g), combined by [`share_from_scores`]. A
/// night whose fields look alike leans on their distribution; one whose fields differ (dust
/// of different clouds) keeps the flat prior. With fewer than 3 other fields (no field left
/// to predict from two), the share is 1/(n + 1), the flat prior weighing as one of the n
/// fields.
///
/// Measured against the simulator's fields (nights of 6): pulls of 1.06, 0.97 and 0.86 at
/// coherence scales of 20", 90" and 600", and end to end 0.93 over 16 nights; with the
/// plain sum's best share 1.04, 0.95, 0.85 and 0.89; with a fixed share of 1/(n + 1) 1.02,
/// 0.86, 0.73 and 0.83 (too wide: the flat prior's mass at large variations, which a field
/// of 6-24 stars cannot exclude, entered every field's error).
pub fn night_prior(fields: &[&[Vec<f64>]], related: impl Fn(usize, usize) -> bool, ln_prior: &[f64]) -> NightPrior {
    let k = ln_prior.len();
    let flat_prior = |share: f64| NightPrior {
        ln_weights: vec![0.0; k],
        flat_share: share,
    };
    let top = ln_prior.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut flat: Vec<f64> = ln_prior.iter().map(|l| (l - top).exp()).collect();
    let z: f64 = flat.iter().sum();
    flat.iter_mut().for_each(|v| *v /= z);
    // Each field's likelihood grids, each scaled to its maximum.
    let lik: Vec<Vec<Vec<f64>>> = fields
        .iter()
        .map(|grids| {
            grids
                .iter()
                .filter(|g| g.len() == k && g.iter().any(|l| l.is_finite()))
                .map(|g| {
                    let m = g.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    g.iter().map(|l| (l - m).exp()).collect()
                })
                .collect()
        })
        .collect();
    let used: Vec<usize> = (0..lik.len()).filter(|&i| !lik[i].is_empty()).collect();
    if used.is_empty() {
        return flat_prior(1.0);
    }
    let npmle = |members: &[usize]| -> Vec<f64> {
        let grids: Vec<&Vec<f64>> = members.iter().flat_map(|&i| &lik[i]).collect();
        let mut pi = flat.clone();
        for _ in 0..EM_ROUNDS {
            let mut next = vec![0.0; k];
            for l in &grids {
                let norm: f64 = pi.iter().zip(*l).map(|(p, l)| p * l).sum();
                if norm > 0.0 {
                    for ((nx, p), l) in next.iter_mut().zip(&pi).zip(*l) {
                        *nx += p * l / norm;
                    }
                }
            }
            let total: f64 = next.iter().sum();
            if total > 0.0 {
                pi = next.into_iter().map(|v| v / total).collect();
            }
        }
        pi
    };
    let mix = |pi: &[f64], share: f64| -> Vec<f64> {
        pi.iter()
            .zip(&flat)
            .map(|(p, q)| (1.0 - share) * p + share * q)
            .collect()
    };
    // The share: each other field predicted by the rest (leave-one-out marginal likelihood).
    let mut rows: Vec<[f64; FLAT_SHARES.len()]> = Vec::new();
    // At most LOO_FIELDS of them (evenly spread over the night's list): each costs an EM.
    let step = used.len().div_ceil(LOO_FIELDS).max(1);
    for &g in used.iter().step_by(step) {
        let rest: Vec<usize> = used.iter().copied().filter(|&h| h != g && !related(g, h)).collect();
        if rest.len() < 2 {
            continue;
        }
        let pi = npmle(&rest);
        let mut row = [0.0; FLAT_SHARES.len()];
        for (sc, &share) in row.iter_mut().zip(&FLAT_SHARES) {
            let prior = mix(&pi, share);
            *sc = lik[g]
                .iter()
                .map(|l| {
                    prior
                        .iter()
                        .zip(l)
                        .map(|(p, l)| p * l)
                        .sum::<f64>()
                        .max(f64::MIN_POSITIVE)
                        .ln()
                })
                .sum::<f64>();
        }
        rows.push(row);
    }
    let share = if rows.is_empty() {
        1.0 / (used.len() as f64 + 1.0)
    } else {
        FLAT_SHARES[share_from_scores(rows)]
    };
    let prior = mix(&npmle(&used), share);
    NightPrior {
        ln_weights: prior.iter().zip(&flat).map(|(p, q)| (p / q).ln()).collect(),
        flat_share: share,
    }
}

/// The flat prior's share (an index into [`FLAT_SHARES`]) from the leave-one-out scores of
/// [`night_prior`], one row per predicted field (its ln marginal likelihood under each share):
///
/// - with at least [`TRIM_FROM`] rows, the row that most prefers the flat prior (largest
///   score at share 1 minus its score at the smallest share) is not counted: one field
///   unlike the rest (a young star's polarization left among its stars, another cloud's
///   dust) keeps the flat prior in its own estimate through its own likelihood, but it does
///   not decide every other field's share (in end-to-end nights one such field made the
///   other five keep the flat prior, their pulls 0.6);
/// - of the shares whose summed score is within [`SHARE_TOLERANCE`] of the best, the
///   smallest: fields of 6-24 stars barely tell a small variation from a large one, so
///   their scores differ by tenths under any share, and the flat prior is kept only when
///   the fields speak against their own distribution.
pub fn share_from_scores(mut rows: Vec<[f64; FLAT_SHARES.len()]>) -> usize {
    let last = FLAT_SHARES.len() - 1;
    if rows.len() >= TRIM_FROM {
        let flat_preference = |r: &[f64; FLAT_SHARES.len()]| r[last] - r[0];
        if let Some(odd) =
            (0..rows.len()).max_by(|&a, &b| flat_preference(&rows[a]).total_cmp(&flat_preference(&rows[b])))
        {
            rows.swap_remove(odd);
        }
    }
    let mut score = [0.0; FLAT_SHARES.len()];
    for r in &rows {
        for (s, v) in score.iter_mut().zip(r) {
            *s += v;
        }
    }
    let top = score.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    (0..FLAT_SHARES.len())
        .find(|&j| score[j] >= top - SHARE_TOLERANCE)
        .unwrap_or(last)
}

/// Fewest predicted fields for [`share_from_scores`] to leave the oddest one out (3 would
/// leave 2 to decide).
pub const TRIM_FROM: usize = 4;

/// How much lower (ln marginal likelihood, summed over the predicted fields) a smaller flat
/// share's score may be than the best and still be preferred ([`share_from_scores`]).
/// Against 0: end to end 0.93 instead of 0.91 (16 nights, with the oddest field left out),
/// the simulator's fields alike within 0.01.
pub const SHARE_TOLERANCE: f64 = 0.5;

/// The most other fields [`night_prior`] predicts from the rest to choose the flat prior's
/// share (each one an EM; a night of 49 binaries would otherwise cost 48 EMs per field).
pub const LOO_FIELDS: usize = 12;

/// Rounds of the EM of [`night_prior`].
pub const EM_ROUNDS: usize = 100;

/// The Bayesian kriging prediction at (`ra_deg`, `dec_deg`) from `sites` with flat priors
/// ([`grid_points`], [`combine`]).
pub fn predict(sites: &[Site], ra_deg: f64, dec_deg: f64, tau_max: f64, drift: bool) -> Option<Prediction> {
    combine(&grid_points(sites, ra_deg, dec_deg, tau_max, drift), |_| 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flat prior's share of a night's prior follows how alike the other fields are:
    /// fields whose likelihoods all peak at one grid point predict each other, and the
    /// share is the smallest; fields each peaked at a different point do not, and the flat
    /// prior keeps the largest share. Too few fields to predict one from two: 1/(n + 1).
    #[test]
    fn the_flat_share_follows_how_alike_the_other_fields_are() {
        let k = 12;
        let ln_prior = vec![-(k as f64).ln(); k];
        // A field whose q and u likelihoods peak sharply at grid point `at`.
        let peaked = |at: usize| -> Vec<Vec<f64>> {
            let g: Vec<f64> = (0..k).map(|i| -2.0 * (i as f64 - at as f64).powi(2)).collect();
            vec![g.clone(), g]
        };
        let alike: Vec<Vec<Vec<f64>>> = (0..5).map(|_| peaked(4)).collect();
        let refs: Vec<&[Vec<f64>]> = alike.iter().map(Vec::as_slice).collect();
        let p = night_prior(&refs, |_, _| false, &ln_prior);
        assert_eq!(p.flat_share, FLAT_SHARES[0], "alike fields");
        // The prior then favours the common point.
        let best = (0..k)
            .max_by(|&a, &b| p.ln_weights[a].total_cmp(&p.ln_weights[b]))
            .unwrap();
        assert_eq!(best, 4);
        let differ: Vec<Vec<Vec<f64>>> = (0..5).map(|i| peaked(2 * i + 1)).collect();
        let refs: Vec<&[Vec<f64>]> = differ.iter().map(Vec::as_slice).collect();
        let q = night_prior(&refs, |_, _| false, &ln_prior);
        assert!(q.flat_share >= 0.35, "differing fields: share {}", q.flat_share);
        // Fields related to every other (sharing stars) leave nothing to predict from.
        let r = night_prior(&refs, |_, _| true, &ln_prior);
        assert!((r.flat_share - 1.0 / 6.0).abs() < 1e-12, "{}", r.flat_share);
    }

    /// The Cholesky solve against a hand-computed 2 x 2 system.
    /// One field unlike the rest does not decide the others' share, and near-ties go to the
    /// smaller share. Rows as `night_prior` makes them (ln marginal likelihood of each
    /// predicted field under each share): four fields of few stars, nearly indifferent but
    /// a little better predicted by the night's distribution, and one field unlike the
    /// others, far better predicted by the flat prior. The plain sum's best share is the
    /// flat prior (1); without the odd field, the fields' distribution (the smallest).
    #[test]
    fn one_odd_field_does_not_make_the_others_keep_the_flat_prior() {
        let n = FLAT_SHARES.len();
        let ramp = |from: f64, to: f64| -> [f64; FLAT_SHARES.len()] {
            std::array::from_fn(|j| from + (to - from) * FLAT_SHARES[j].sqrt())
        };
        let mut rows = vec![ramp(-0.30, -0.45); 4];
        rows.insert(2, ramp(-4.8, -1.2));
        // The plain sum prefers the flat prior.
        let sum: Vec<f64> = (0..n).map(|j| rows.iter().map(|r| r[j]).sum()).collect();
        let plain = (0..n).max_by(|&a, &b| sum[a].total_cmp(&sum[b])).unwrap();
        assert_eq!(plain, n - 1, "the plain sum: {sum:?}");
        assert_eq!(share_from_scores(rows.clone()), 0);
        // Every field unlike the others: the flat prior stays.
        let differ = vec![ramp(-4.8, -1.2); 5];
        assert_eq!(share_from_scores(differ), n - 1);
        // A near tie (the flat prior better by less than the tolerance) goes to the smaller
        // share; a clear preference does not.
        let tie = vec![ramp(-0.5, -0.5 + 0.8 * SHARE_TOLERANCE / 3.0); 3];
        assert_eq!(share_from_scores(tie), 0);
        let clear = vec![ramp(-0.5, -0.5 + 2.0 * SHARE_TOLERANCE / 3.0); 3];
        assert!(share_from_scores(clear) > 0);
        // Through night_prior: four fields of weak likelihoods alike and one sharply
        // peaked elsewhere; the four keep their distribution.
        let k = 12;
        let ln_prior = vec![-(k as f64).ln(); k];
        let field = |at: usize, curvature: f64| -> Vec<Vec<f64>> {
            let g: Vec<f64> = (0..k).map(|i| -curvature * (i as f64 - at as f64).powi(2)).collect();
            vec![g.clone(), g]
        };
        let mut fields: Vec<Vec<Vec<f64>>> = (0..4).map(|_| field(3, 0.3)).collect();
        fields.push(field(10, 3.0));
        let refs: Vec<&[Vec<f64>]> = fields.iter().map(Vec::as_slice).collect();
        let p = night_prior(&refs, |_, _| false, &ln_prior);
        assert!(p.flat_share <= 0.05, "share {}", p.flat_share);
    }

    #[test]
    fn cholesky_solves_a_small_system() {
        let a = [4.0, 2.0, 2.0, 3.0];
        let l = cholesky(&a, 2).unwrap();
        let mut b = [2.0, 1.0];
        solve(&l, 2, &mut b);
        // [4 2; 2 3]^-1 [2 1] = [0.5, 0].
        assert!((b[0] - 0.5).abs() < 1e-14 && b[1].abs() < 1e-14, "{b:?}");
        assert!(cholesky(&[1.0, 2.0, 2.0, 1.0], 2).is_none());
    }

    /// Stars at one place (no separations: the power-law part is one common offset) weigh
    /// by their errors: the least precise least, the weights summing to 1.
    #[test]
    fn stars_at_one_place_weigh_by_their_errors() {
        let sites: Vec<Site> = [(0.01, 1e-6), (0.02, 4e-6), (0.015, 1e-6)]
            .iter()
            .map(|&(y, var)| Site {
                y,
                var,
                ra_deg: 10.0,
                dec_deg: -5.0,
            })
            .collect();
        let p = predict(&sites, 10.0, -5.0 + 1.0 / 3600.0, 0.005, false).unwrap();
        assert!((p.weights.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        assert!((p.weights[0] - p.weights[2]).abs() < 1e-12, "{:?}", p.weights);
        assert!(p.weights[1] < p.weights[0], "{:?}", p.weights);
    }

    /// With a plane as drift, stars on an exact plane (tiny noise) predict the plane's value
    /// at the binary, off their centroid; without it, their weighted mean is pulled toward
    /// the place's neighbours only.
    #[test]
    fn a_plane_as_drift_is_recovered() {
        let plane = |ra: f64, dec: f64| 0.01 + 0.02 * (ra - 10.0) - 0.03 * (dec + 5.0);
        let sites: Vec<Site> = (0..9)
            .map(|i| {
                let (ra, dec) = (10.0 + 0.01 * (i % 3) as f64, -5.0 + 0.01 * (i / 3) as f64);
                Site {
                    y: plane(ra, dec),
                    var: 1e-12,
                    ra_deg: ra,
                    dec_deg: dec,
                }
            })
            .collect();
        let (ra, dec) = (10.004, -4.997);
        let p = predict(&sites, ra, dec, 0.005, true).unwrap();
        assert!(
            (p.value - plane(ra, dec)).abs() < 1e-6,
            "{} vs {}",
            p.value,
            plane(ra, dec)
        );
        assert!((p.weights.iter().sum::<f64>() - 1.0).abs() < 1e-9);
    }

    /// The kriging variance for given parameters against a slow Monte Carlo of the model
    /// itself: draw the field (a Brownian sheet is awkward; use the same covariance with C)
    /// at the stars and the binary, the measurements, predict with the weights, and compare
    /// the scatter of the error with V.
    #[test]
    fn the_kriging_variance_matches_a_monte_carlo_of_its_model() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(3);
        let n = 8;
        let sites: Vec<Site> = (0..n)
            .map(|_| Site {
                y: 0.0,
                var: (0.001 + 0.003 * rng.random::<f64>()).powi(2),
                ra_deg: 10.0 + (rng.random::<f64>() - 0.5) * 0.08,
                dec_deg: -5.0 + (rng.random::<f64>() - 0.5) * 0.02,
            })
            .collect();
        let (d, d_b) = separations(&sites, 10.0, -5.0);
        let dmax = d.iter().chain(&d_b).copied().fold(0.0, f64::max);
        let c = 2.0 * dmax + H_ARCSEC;
        // alpha = 1: the separations in units of H, b = s^2 / H per arcsec.
        let (t2, b) = (0.002f64.powi(2), 0.003f64.powi(2) / H_ARCSEC);
        let ones = vec![1.0; n];
        let (_, lambda, _, var) = at(&sites, &d, &d_b, &ones, &[1.0], c, t2, b).unwrap();
        // The joint covariance of (e at the stars, e at the binary) with the constant C:
        // a valid covariance for this configuration (checked by its Cholesky below).
        let m = n + 1;
        let mut k = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                let dij = match (i < n, j < n) {
                    (true, true) => d[i * n + j],
                    (true, false) => d_b[i],
                    (false, true) => d_b[j],
                    (false, false) => 0.0,
                };
                k[i * m + j] = b * (c - dij) + if i == j { t2 } else { 0.0 };
            }
        }
        let l = cholesky(&k, m).expect("joint covariance positive definite");
        let normal = |rng: &mut rand::rngs::Xoshiro256PlusPlus| {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let draws = 40_000;
        let mut ss = 0.0;
        for _ in 0..draws {
            let z: Vec<f64> = (0..m).map(|_| normal(&mut rng)).collect();
            let e: Vec<f64> = (0..m).map(|i| (0..=i).map(|j| l[i * m + j] * z[j]).sum()).collect();
            let pred: f64 = (0..n)
                .map(|i| lambda[i] * (e[i] + sites[i].var.sqrt() * normal(&mut rng)))
                .sum();
            ss += (pred - e[n]).powi(2);
        }
        let mc = ss / draws as f64;
        assert!((mc / var - 1.0).abs() < 0.03, "Monte Carlo {mc:.4e} vs V {var:.4e}");
    }
}
