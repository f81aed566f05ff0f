//! Joint fit of the instrumental offset `c` and the angle zero-point `theta0` over every
//! orientation of every standard, with the table values of the standards as nuisance
//! parameters (docs/polarimetry.md, "Calibration from standards").
//!
//! ```text
//! polarized standard j, orientation i:   F_ji = p_j cos 2(phi_ji - gamma_j) + c
//! unpolarized standard k, orientation i: F_ki = a_k cos 2s PA_ki + b_k sin 2s PA_ki + c
//! phi = s PA + theta0
//!
//! chi^2 = sum_ji (F_ji - model)^2 / sigma_F^2
//!       + sum_j (p_j - p_table)^2 / sigma_p^2 + (gamma_j - gamma_table)^2 / sigma_gamma^2
//!       + sum_k (a_k^2 + b_k^2) / (sigma_p,k^2 / 2)
//! ```
//!
//! minimised over x = (c, theta0, p_j, gamma_j, a_k, b_k) by Gauss-Newton. An unpolarized
//! standard's own polarization (table: 0 +- sigma_p) is the pair (a_k, b_k) of its q, u turned
//! into the analyzer frame (the prior is isotropic, so theta0 drops out); a polarized
//! standard's table error enters once, through its (p_j, gamma_j), and correlates its
//! orientations as it should. `cov(c, theta0)` is the (c, theta0) block of the inverse of
//! the normal matrix (the nuisances marginalised), multiplied by chi^2/dof when the scatter
//! exceeds the errors significantly (chi^2 beyond its 99th percentile; dof = orientations - 2;
//! `inflation` says why not whenever chi^2/dof > 1).
//!
//! The standards separate c from theta0 only when there are more orientations than the two
//! unknowns and the normal matrix is far from singular; otherwise the fit is reported
//! incomplete (see [`fit_joint`]).
use super::{AngleCalibration, Offset, StandardObservation};
use crate::stokes::fresnel::TelescopePrior;
use crate::stokes::model::{normalize_axial_deg, TelescopePolarization};
pub use crate::stokes::propagation::{CAL_C, CAL_TEL_A, CAL_TEL_B, CAL_THETA0};

/// |corr(c, theta0)| above which the standards are taken not to separate c from theta0.
pub const MAX_CORRELATION: f64 = 0.95;

/// |corr(c, theta0)| above which a fit with the telescope's prior is taken not to separate c
/// from theta0. The prior makes the solution unique where the standards alone leave a
/// direction free, and the covariance carries the correlation into every error; only a
/// near-degeneracy (a variance inflation beyond ~50) is refused.
pub const MAX_CORRELATION_WITH_PRIOR: f64 = 0.99;

/// chi^2 difference between two parities above which the parity counts as measured
/// (5 sigma; below it the profile's parity is kept).
const PARITY_DCHI2: f64 = 25.0;

/// Starting values of theta0, deg (the fit is not linear in theta0; F varies as
/// cos 2 theta0, so a start within 15 deg of every point of the 180 deg period).
const THETA0_STARTS: [f64; 6] = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0];

/// The calibration of one filter from its standards.
#[derive(Debug, Clone, PartialEq)]
pub struct JointCalibration {
    /// c and its error (inflated by sqrt(chi^2/dof) when the scatter exceeds the errors
    /// significantly, [`INFLATION_P`]);
    /// `None` without any usable standard, or when incomplete without an unpolarized one.
    pub offset: Option<Offset>,
    /// theta0 and parity; `None` without polarized standards or when incomplete.
    pub angles: Option<AngleCalibration>,
    /// cov(c, theta0), units of c x deg (with the same inflation), when both were fitted.
    pub cov_c_theta0_deg: Option<f64>,
    /// chi^2 (data and priors) at the solution and its degrees of freedom.
    pub chi2: f64,
    /// Orientations minus the fitted instrument parameters.
    pub dof: usize,
    /// Why c and theta0 could not be separated, when they could not.
    pub incomplete: Option<String>,
    /// Input indices of the standards the offset comes from.
    pub offset_from: Vec<usize>,
    /// Input indices of the standards the angles come from.
    pub angles_from: Vec<usize>,
    /// The telescope's own polarization, when fitted and separated from c and theta0.
    pub telescope: Option<TelescopePolarization>,
    /// Why the telescope's polarization was not measured, when it was asked for and not.
    pub telescope_problem: Option<String>,
    /// When the telescope's term comes from the fit with the profile's prior (the standards
    /// alone did not separate it): why the standards alone did not.
    pub telescope_from_prior: Option<String>,
    /// Covariance of (c, theta0 in deg, a, b) with the same inflation as the errors;
    /// zero rows and columns for what was not fitted ([`CAL_C`], [`CAL_THETA0`],
    /// [`CAL_TEL_A`], [`CAL_TEL_B`]).
    pub covariance: [[f64; 4]; 4],
}

/// What the joint fit needs besides the standards.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointOptions {
    /// The profile's parity, kept unless two or more polarized standards measure it.
    pub default_parity: i32,
    /// The profile's theta0, deg: the analyzer angles of the telescope's term when the
    /// standards do not fit theta0.
    pub profile_theta0_deg: f64,
    /// Also fit the telescope's polarization (kept only when the standards separate it).
    pub fit_telescope: bool,
    /// The profile's prior of the telescope's term in this filter: used in the fit when the
    /// standards alone do not separate the term.
    pub telescope_prior: Option<TelescopePrior>,
}

/// One orientation of a standard: PA, F, sigma_F and the weighted mean (cos 2eta, sin 2eta)
/// of its frames' parallactic angles (`None`: unknown).
#[derive(Debug, Clone, Copy)]
struct Row {
    pa: f64,
    f: f64,
    sigma_f: f64,
    parallactic_2eta: Option<[f64; 2]>,
}

/// One usable standard: its valid orientations and table values.
#[derive(Clone)]
struct Std<'a> {
    index: usize,
    obs: &'a StandardObservation,
    rows: Vec<Row>,
}

/// The least-squares problem of one parity: instrument parameters (c; theta0 when
/// `fit_theta0`, else `theta0_fixed`; the telescope's (a, b) when `fit_telescope`), then two
/// nuisances per standard.
struct Problem<'a> {
    stds: Vec<Std<'a>>,
    parity: f64,
    fit_theta0: bool,
    theta0_fixed: f64,
    fit_telescope: bool,
    /// The prior of the telescope's (a, b), when it is part of the fit (two rows more).
    prior: Option<TelescopePrior>,
}

/// A converged fit: parameters, the inverse of the normal matrix (not inflated), chi^2.
#[derive(Debug, Clone)]
struct Solution {
    x: Vec<f64>,
    cov: Vec<Vec<f64>>,
    chi2: f64,
}

fn floor(s: f64) -> f64 {
    s.max(1e-12)
}

impl Problem<'_> {
    fn n_inst(&self) -> usize {
        1 + usize::from(self.fit_theta0) + 2 * usize::from(self.fit_telescope)
    }

    /// Index of the telescope's `a` (then `b`) in x.
    fn i_tel(&self) -> usize {
        1 + usize::from(self.fit_theta0)
    }

    fn n_params(&self) -> usize {
        self.n_inst() + 2 * self.stds.len()
    }

    fn n_data(&self) -> usize {
        self.stds.iter().map(|s| s.rows.len()).sum()
    }

    /// Rows of the telescope's prior (2 when it is part of the fit): data in the count of
    /// the degrees of freedom.
    fn n_prior(&self) -> usize {
        if self.fit_telescope && self.prior.is_some() {
            2
        } else {
            0
        }
    }

    /// Normalised residuals (observed - model)/sigma and their derivatives d model/dx / sigma,
    /// data rows then prior rows.
    fn residuals(&self, x: &[f64]) -> (Vec<f64>, Vec<Vec<f64>>) {
        let n = self.n_params();
        let (mut r, mut jac) = (Vec::new(), Vec::new());
        let theta0 = if self.fit_theta0 { x[1] } else { self.theta0_fixed };
        let d2 = 2f64.to_radians(); // d(2 angle_rad)/d(angle_deg)
        for (j, s) in self.stds.iter().enumerate() {
            let b = self.n_inst() + 2 * j;
            let pol = s.obs.polarized();
            for r_ in &s.rows {
                let (pa, f, sf) = (r_.pa, r_.f, r_.sigma_f);
                let mut row = vec![0.0; n];
                row[0] = 1.0;
                let telescope = if self.fit_telescope {
                    // T = a r_a + b r_b, r_a = cos 2(phi - eta), r_b = sin 2(phi - eta)
                    // (each averaged over the orientation's frames).
                    let [cos_2eta, sin_2eta] = r_.parallactic_2eta.unwrap_or([0.0, 0.0]);
                    let t = 2.0 * (self.parity * pa + theta0).to_radians();
                    let r_a = cos_2eta * t.cos() + sin_2eta * t.sin();
                    let r_b = cos_2eta * t.sin() - sin_2eta * t.cos();
                    let (i, a, bt) = (self.i_tel(), x[self.i_tel()], x[self.i_tel() + 1]);
                    row[i] = r_a;
                    row[i + 1] = r_b;
                    if self.fit_theta0 {
                        row[1] += (bt * r_a - a * r_b) * d2;
                    }
                    a * r_a + bt * r_b
                } else {
                    0.0
                };
                let model = if pol {
                    let (p, gamma) = (x[b], x[b + 1]);
                    let t = 2.0 * (self.parity * pa + theta0 - gamma).to_radians();
                    if self.fit_theta0 {
                        // Added to the telescope's own d/dtheta0 (set above), not in place of it.
                        row[1] += -p * t.sin() * d2;
                    }
                    row[b] = t.cos();
                    row[b + 1] = p * t.sin() * d2;
                    x[0] + p * t.cos()
                } else {
                    let t = 2.0 * (self.parity * pa).to_radians();
                    row[b] = t.cos();
                    row[b + 1] = t.sin();
                    x[0] + x[b] * t.cos() + x[b + 1] * t.sin()
                } + telescope;
                r.push((f - model) / sf);
                jac.push(row.iter().map(|v| v / sf).collect());
            }
        }
        for (j, s) in self.stds.iter().enumerate() {
            let b = self.n_inst() + 2 * j;
            let o = s.obs;
            let priors = if o.polarized() {
                [(o.p, floor(o.sigma_p)), (o.gamma_deg, floor(o.sigma_gamma_deg))]
            } else {
                let s = floor(o.sigma_p / 2f64.sqrt());
                [(0.0, s), (0.0, s)]
            };
            for (k, (v, s)) in priors.into_iter().enumerate() {
                let mut row = vec![0.0; n];
                row[b + k] = 1.0 / s;
                let d = if o.polarized() && k == 1 {
                    // An axial angle: the residual folded into [-90, 90).
                    (v - x[b + k] + 90.0).rem_euclid(180.0) - 90.0
                } else {
                    v - x[b + k]
                };
                r.push(d / s);
                jac.push(row);
            }
        }
        if let (true, Some(prior)) = (self.fit_telescope, self.prior) {
            let it = self.i_tel();
            for (u, value) in prior.rows() {
                let mut row = vec![0.0; n];
                row[it] = u[0];
                row[it + 1] = u[1];
                r.push(value - u[0] * x[it] - u[1] * x[it + 1]);
                jac.push(row);
            }
        }
        (r, jac)
    }

    fn chi2(&self, x: &[f64]) -> f64 {
        self.residuals(x).0.iter().map(|v| v * v).sum()
    }

    /// Starting point: c = 0, theta0 given, the telescope's term at its prior's mean, the
    /// nuisances at their table values.
    fn start(&self, theta0: f64) -> Vec<f64> {
        let mut x = vec![0.0; self.n_params()];
        if self.fit_theta0 {
            x[1] = theta0;
        }
        if let (true, Some(prior)) = (self.fit_telescope, self.prior) {
            let [a, b] = prior.mean();
            x[self.i_tel()] = a;
            x[self.i_tel() + 1] = b;
        }
        for (j, s) in self.stds.iter().enumerate() {
            if s.obs.polarized() {
                let b = self.n_inst() + 2 * j;
                x[b] = s.obs.p;
                x[b + 1] = s.obs.gamma_deg;
            }
        }
        x
    }

    /// Gauss-Newton from `x` (step halved while chi^2 grows). `None` when the normal
    /// matrix is singular.
    fn gauss_newton(&self, mut x: Vec<f64>) -> Option<Solution> {
        let mut chi2 = self.chi2(&x);
        for _ in 0..200 {
            let (r, jac) = self.residuals(&x);
            let (normal, grad) = normal_equations(&r, &jac);
            let inv = invert_spd(&normal)?;
            let step: Vec<f64> = inv.iter().map(|row| dot(row, &grad)).collect();
            let mut t = 1.0;
            let (mut trial, mut chi2_trial);
            loop {
                trial = x.iter().zip(&step).map(|(a, d)| a + t * d).collect::<Vec<f64>>();
                chi2_trial = self.chi2(&trial);
                if chi2_trial <= chi2 || t < 1e-6 {
                    break;
                }
                t *= 0.5;
            }
            let small = step
                .iter()
                .zip(&trial)
                .all(|(d, v)| (t * d).abs() <= 1e-13 * (1.0 + v.abs()));
            let no_gain = chi2 - chi2_trial <= 1e-14 * (1.0 + chi2);
            if chi2_trial <= chi2 {
                x = trial;
                chi2 = chi2_trial;
            }
            if small || (no_gain && t < 1.0) {
                break;
            }
        }
        self.solution_at(x, chi2)
    }

    /// Levenberg-Marquardt from `x`: the Gauss-Newton step of `(J^T J + lambda diag(J^T J))`,
    /// lambda divided by 10 after a step that lowers chi^2 and multiplied by 10 until one
    /// does. For the fit with the telescope's prior, whose valley of (c, theta0, a, b) can
    /// be long and curved (polarized standards only): plain Gauss-Newton with step halving
    /// stopped in it short of the minimum (chi^2 2.6 where the minimum is 1.8, theta0 5 deg
    /// off, on a simulated night; measured while the polarized standards' rows still lacked
    /// the term's d/dtheta0). `None` when the normal matrix is singular at the end.
    fn levenberg_marquardt(&self, mut x: Vec<f64>) -> Option<Solution> {
        let mut chi2 = self.chi2(&x);
        let mut lambda = 1e-3;
        for _ in 0..2000 {
            let (r, jac) = self.residuals(&x);
            let (normal, grad) = normal_equations(&r, &jac);
            let mut accepted = None;
            while lambda < 1e16 {
                let mut damped = normal.clone();
                for (i, row) in damped.iter_mut().enumerate() {
                    row[i] += lambda * normal[i][i];
                }
                if let Some(inv) = invert_spd(&damped) {
                    let step: Vec<f64> = inv.iter().map(|row| dot(row, &grad)).collect();
                    let trial: Vec<f64> = x.iter().zip(&step).map(|(a, d)| a + d).collect();
                    let c = self.chi2(&trial);
                    if c < chi2 {
                        accepted = Some((trial, c));
                        lambda = (lambda * 0.1).max(1e-12);
                        break;
                    }
                }
                lambda *= 10.0;
            }
            let Some((trial, c)) = accepted else { break };
            let gain = chi2 - c;
            x = trial;
            chi2 = c;
            if gain <= 1e-13 * (1.0 + chi2) {
                break;
            }
        }
        self.solution_at(x, chi2)
    }

    /// The converged fit at `x`: the inverse of the normal matrix there, theta0 folded into
    /// [0, 180). `None` when the normal matrix is singular.
    fn solution_at(&self, mut x: Vec<f64>, chi2: f64) -> Option<Solution> {
        let (r, jac) = self.residuals(&x);
        let cov = invert_spd(&normal_equations(&r, &jac).0)?;
        if self.fit_theta0 {
            x[1] = normalize_axial_deg(x[1]);
        }
        Some(Solution { x, cov, chi2 })
    }

    /// The minimiser: Gauss-Newton, or with the telescope's prior Levenberg-Marquardt.
    fn minimise(&self, x: Vec<f64>) -> Option<Solution> {
        if self.n_prior() > 0 {
            self.levenberg_marquardt(x)
        } else {
            self.gauss_newton(x)
        }
    }

    /// The best of the fits from every theta0 start, and the other minima found.
    fn solve(&self) -> Option<(Solution, Vec<Solution>)> {
        let starts: &[f64] = if self.fit_theta0 { &THETA0_STARTS } else { &[0.0] };
        let mut all: Vec<Solution> = starts.iter().filter_map(|&t| self.minimise(self.start(t))).collect();
        all.sort_by(|a, b| a.chi2.total_cmp(&b.chi2));
        let best = all.first()?.clone();
        Some((best, all))
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// J^T J and J^T r.
fn normal_equations(r: &[f64], jac: &[Vec<f64>]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let n = jac.first().map_or(0, Vec::len);
    let mut a = vec![vec![0.0; n]; n];
    let mut g = vec![0.0; n];
    for (ri, row) in r.iter().zip(jac) {
        for i in 0..n {
            if row[i] == 0.0 {
                continue;
            }
            g[i] += row[i] * ri;
            for j in 0..n {
                a[i][j] += row[i] * row[j];
            }
        }
    }
    (a, g)
}

/// Inverse of a symmetric positive (semi-)definite matrix by Gauss-Jordan elimination on
/// its unit-diagonal (correlation) form; `None` when a pivot falls below 1e-10 (singular or
/// nearly so).
fn invert_spd(a: &[Vec<f64>]) -> Option<Vec<Vec<f64>>> {
    let n = a.len();
    let d: Vec<f64> = (0..n).map(|i| a[i][i]).collect();
    if d.iter().any(|v| !(*v > 0.0 && v.is_finite())) {
        return None;
    }
    let s: Vec<f64> = d.iter().map(|v| v.sqrt().recip()).collect();
    let mut m: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            let mut row: Vec<f64> = (0..n).map(|j| a[i][j] * s[i] * s[j]).collect();
            row.extend((0..n).map(|j| f64::from(u8::from(i == j))));
            row
        })
        .collect();
    for col in 0..n {
        let piv = (col..n).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if !(m[piv][col].abs() > 1e-10) {
            return None;
        }
        m.swap(col, piv);
        let p = m[col][col];
        m[col].iter_mut().for_each(|v| *v /= p);
        let pivot_row = m[col].clone();
        for (i, row) in m.iter_mut().enumerate() {
            if i != col && row[col] != 0.0 {
                let f = row[col];
                row.iter_mut().zip(&pivot_row).for_each(|(v, pv)| *v -= f * pv);
            }
        }
    }
    Some(
        (0..n)
            .map(|i| (0..n).map(|j| m[i][n + j] * s[i] * s[j]).collect())
            .collect(),
    )
}

/// The usable standards: those with at least one orientation with finite PA, F and a
/// positive sigma_F.
fn usable(stds: &[StandardObservation]) -> Vec<Std<'_>> {
    stds.iter()
        .enumerate()
        .filter_map(|(index, obs)| {
            let rows: Vec<Row> = obs
                .f
                .iter()
                .zip(&obs.posang_deg)
                .enumerate()
                .filter(|(_, (o, pa))| o.f.is_finite() && pa.is_finite() && o.sigma_f.is_finite() && o.sigma_f > 0.0)
                .map(|(i, (o, &pa))| Row {
                    pa,
                    f: o.f,
                    sigma_f: o.sigma_f,
                    parallactic_2eta: obs
                        .parallactic_2eta
                        .get(i)
                        .copied()
                        .flatten()
                        .filter(|v| v.iter().all(|x| x.is_finite())),
                })
                .collect();
            (!rows.is_empty()).then_some(Std { index, obs, rows })
        })
        .collect()
}

/// Upper-tail probability of the standards' chi^2 below which their scatter is taken to
/// exceed their errors and the covariance is multiplied by chi^2/dof (the threshold of a
/// combined F's excess dither scatter, `reduce::entry`).
pub const INFLATION_P: f64 = 0.01;

/// The factor the fit's covariance is multiplied by: chi^2/dof when the chi^2 is improbably
/// large for its dof (upper-tail probability below [`INFLATION_P`]), else 1 (also for
/// dof = 0).
///
/// Why not `max(1, chi^2/dof)` (the Birge ratio whenever it exceeds 1): with honest errors
/// chi^2 ~ chi^2_nu, independent of the (linearised) estimates, so a reported variance
/// k(chi^2) V gives pulls with E[z^2] = E[1/k]. For k = max(1, chi^2/nu),
/// E[1/k] = F_nu(nu) + nu/(nu - 2) (1 - F_{nu-2}(nu)) (F: the chi^2 CDF; from
/// E[1/X; X > a] = (1 - F_{nu-2}(a))/(nu - 2)): 0.876 at nu = 6, the dof of 5 standards at
/// 0/45 with the telescope's term (rms pull 0.936), 0.891 at nu = 10: every error 6-7 %
/// too large on nights whose errors are right. Inflating only beyond the 99th percentile a
/// of chi^2_nu gives E[1/k] = F_nu(a) + nu/(nu - 2) (1 - F_{nu-2}(a)) = 0.993 at nu = 6,
/// and still scales the errors of a night whose standards scatter beyond them.
///
/// The one rule of sofipol for scaling errors by a fit's chi^2: also the half-wave-plate
/// least squares ([`crate::stokes::hwp`]) and the photometric zero point
/// ([`crate::calibration::photometric::combine`]).
pub fn inflation(chi2: f64, dof: usize) -> f64 {
    if dof == 0 || !chi2.is_finite() {
        return 1.0;
    }
    let dist = statrs::distribution::ChiSquared::new(dof as f64).expect("dof > 0");
    let p = 1.0 - statrs::distribution::ContinuousCDF::cdf(&dist, chi2);
    if p < INFLATION_P {
        chi2 / dof as f64
    } else {
        1.0
    }
}

/// The offset alone from the unpolarized standards (theta0 does not enter their model).
fn offset_only(stds: Vec<Std<'_>>) -> Option<(Offset, f64, usize, Vec<usize>)> {
    let pb = Problem {
        stds: stds.into_iter().filter(|s| !s.obs.polarized()).collect(),
        parity: 1.0,
        fit_theta0: false,
        theta0_fixed: 0.0,
        fit_telescope: false,
        prior: None,
    };
    if pb.stds.is_empty() {
        return None;
    }
    let (sol, _) = pb.solve()?;
    let dof = pb.n_data() - 1;
    let k = inflation(sol.chi2, dof);
    let off = Offset {
        c: sol.x[0],
        sigma_c: (sol.cov[0][0] * k).sqrt(),
    };
    Some((off, sol.chi2, dof, pb.stds.iter().map(|s| s.index).collect()))
}

/// Why the fit cannot separate c from theta0, if it cannot: no degree of freedom (as many
/// orientations as unknowns: a polarized standard at two orientations fits any c with a
/// matching theta0), a correlation beyond [`MAX_CORRELATION`], or another solution as good
/// as the best (chi^2 within 1) more than 3 sigma away.
fn separation_problem(pb: &Problem, best: &Solution, others: &[Solution]) -> Option<String> {
    let dof = (pb.n_data() + pb.n_prior()) as i64 - pb.n_inst() as i64;
    let n_pol = pb.stds.iter().filter(|s| s.obs.polarized()).count();
    let what = format!(
        "{} orientation(s) of {} standard(s), {} of them polarized",
        pb.n_data(),
        pb.stds.len(),
        n_pol
    );
    if dof <= 0 {
        return Some(format!(
            "{what}: as many data as the unknowns c and theta0, which they cannot separate \
             (observe an unpolarized standard, a second polarized one at another angle, or 4 orientations)"
        ));
    }
    let corr = best.cov[0][1] / (best.cov[0][0] * best.cov[1][1]).sqrt();
    let max = if pb.n_prior() > 0 {
        MAX_CORRELATION_WITH_PRIOR
    } else {
        MAX_CORRELATION
    };
    if !(corr.abs() <= max) {
        return Some(format!(
            "{what}: corr(c, theta0) = {corr:.3}, beyond +-{max}: the standards do not separate c from theta0"
        ));
    }
    let (sc, st) = (best.cov[0][0].sqrt(), best.cov[1][1].sqrt());
    let other = others.iter().find(|o| {
        let dt = (o.x[1] - best.x[1] + 90.0).rem_euclid(180.0) - 90.0;
        o.chi2 - best.chi2 < 1.0 && (dt.abs() > 3.0 * st || (o.x[0] - best.x[0]).abs() > 3.0 * sc)
    });
    other.map(|o| {
        format!(
            "{what}: two solutions fit equally well (c = {:.5}, theta0 = {:.2} deg and c = {:.5}, theta0 = {:.2} deg)",
            best.x[0], best.x[1], o.x[0], o.x[1]
        )
    })
}

/// The joint fit of c and theta0 from a filter's standards. Parity: with two or more
/// polarized standards, the one whose fit has the smaller chi^2 when the two differ by more
/// than 25 (measured), else `default_parity`. Without polarized standards only c is fitted.
/// When the standards cannot separate c from theta0 ([`JointCalibration::incomplete`]), the
/// angles are left to the profile and c comes from the unpolarized standards alone (none
/// without them). `None` without any usable standard.
pub fn fit_joint(stds: &[StandardObservation], default_parity: i32) -> Option<JointCalibration> {
    fit_joint_with(
        stds,
        &JointOptions {
            default_parity,
            profile_theta0_deg: 0.0,
            fit_telescope: false,
            telescope_prior: None,
        },
    )
}

/// [`fit_joint`], and with `fit_telescope` the telescope's polarization (a, b) fitted
/// together with c and theta0 (`telescope::refit`). When the standards alone cannot separate
/// it, the fit again with the profile's prior of the term
/// ([`JointCalibration::telescope_from_prior`] says why the standards alone did not: c and
/// theta0 are then marginalised over the term instead of absorbing it); without a prior, or
/// when even that fit fails, the fit without the term and
/// [`JointCalibration::telescope_problem`] saying why.
pub fn fit_joint_with(stds: &[StandardObservation], opts: &JointOptions) -> Option<JointCalibration> {
    let base = fit_instrument(stds, opts.default_parity)?;
    if !opts.fit_telescope {
        return Some(base);
    }
    let alone = match telescope::refit(stds, opts, &base, None) {
        Ok(j) => return Some(j),
        Err(why) => why,
    };
    let with_prior = opts
        .telescope_prior
        .map(|prior| telescope::refit(stds, opts, &base, Some(prior)));
    Some(match with_prior {
        Some(Ok(j)) => JointCalibration {
            telescope_from_prior: Some(alone.to_string()),
            ..j
        },
        // With the term marginalised the polarized standards do not separate c from theta0:
        // the fit without it would take the term into c and theta0 (and may measure the
        // wrong parity), so theta0 is left to the profile and c to the unpolarized standards.
        Some(Err(also @ telescope::TelescopeFitError::NotSeparable(_))) if base.angles.is_some() => JointCalibration {
            telescope_problem: Some(format!("{alone}; with the mirror's prior: {also}")),
            ..from_unpolarized(
                stds,
                Some(format!(
                    "with the telescope's term marginalised over the mirror's prior, {also}"
                )),
            )
        },
        Some(Err(also)) => JointCalibration {
            telescope_problem: Some(format!("{alone}; with the mirror's prior: {also}")),
            ..base
        },
        None => JointCalibration {
            telescope_problem: Some(alone.to_string()),
            ..base
        },
    })
}

/// The calibration when the polarized standards do not fix theta0 (`why`; `None`: there
/// are none): c from the unpolarized standards alone (none without them), the angles left
/// to the profile.
fn from_unpolarized(stds: &[StandardObservation], why: Option<String>) -> JointCalibration {
    let (offset, chi2, dof, from) = match offset_only(usable(stds)) {
        Some((o, chi2, dof, from)) => (Some(o), chi2, dof, from),
        None => (None, 0.0, 0, vec![]),
    };
    let mut covariance = [[0.0; 4]; 4];
    covariance[CAL_C][CAL_C] = offset.map_or(0.0, |o| o.sigma_c * o.sigma_c);
    JointCalibration {
        offset,
        angles: None,
        cov_c_theta0_deg: None,
        chi2,
        dof,
        incomplete: why,
        offset_from: from,
        angles_from: vec![],
        telescope: None,
        telescope_problem: None,
        telescope_from_prior: None,
        covariance,
    }
}

/// c and theta0 (and parity) without the telescope's term.
fn fit_instrument(stds: &[StandardObservation], default_parity: i32) -> Option<JointCalibration> {
    let all = usable(stds);
    if all.is_empty() {
        return None;
    }
    let n_pol = all.iter().filter(|s| s.obs.polarized()).count();
    let from_unpolarized = |why: Option<String>| Some(from_unpolarized(stds, why));
    if n_pol == 0 {
        return from_unpolarized(None);
    }
    let problem = |parity: i32| Problem {
        stds: usable(stds),
        parity: parity as f64,
        fit_theta0: true,
        theta0_fixed: 0.0,
        fit_telescope: false,
        prior: None,
    };
    let fit = |parity: i32| {
        let pb = problem(parity);
        pb.solve().map(|(best, others)| (pb, best, others))
    };
    let trials: Vec<(i32, _)> = if n_pol >= 2 {
        vec![(1, fit(1)), (-1, fit(-1))]
    } else {
        vec![(default_parity, fit(default_parity))]
    };
    let chi2_of = |p: i32| {
        trials
            .iter()
            .find(|t| t.0 == p)
            .and_then(|t| t.1.as_ref().map(|f| f.1.chi2))
    };
    let measured = match (chi2_of(1), chi2_of(-1)) {
        (Some(a), Some(b)) => (a - b).abs() > PARITY_DCHI2,
        _ => false,
    };
    let parity = if measured {
        if chi2_of(1) <= chi2_of(-1) {
            1
        } else {
            -1
        }
    } else {
        default_parity
    };
    let Some((pb, best, others)) = trials.into_iter().find(|t| t.0 == parity).and_then(|t| t.1) else {
        return from_unpolarized(Some(format!(
            "{} polarized standard(s): the normal matrix of (c, theta0) is singular",
            n_pol
        )));
    };
    if let Some(why) = separation_problem(&pb, &best, &others) {
        return from_unpolarized(Some(why));
    }
    let dof = pb.n_data() - 2;
    let k = inflation(best.chi2, dof);
    let idx: Vec<usize> = pb.stds.iter().map(|s| s.index).collect();
    let mut covariance = [[0.0; 4]; 4];
    for (i, ci) in [(0, CAL_C), (1, CAL_THETA0)] {
        for (j, cj) in [(0, CAL_C), (1, CAL_THETA0)] {
            covariance[ci][cj] = best.cov[i][j] * k;
        }
    }
    Some(JointCalibration {
        offset: Some(Offset {
            c: best.x[0],
            sigma_c: (best.cov[0][0] * k).sqrt(),
        }),
        angles: Some(AngleCalibration {
            theta0_deg: best.x[1],
            sigma_theta0_deg: (best.cov[1][1] * k).sqrt(),
            parity,
            parity_measured: measured,
            n_standards: n_pol,
        }),
        cov_c_theta0_deg: Some(best.cov[0][1] * k),
        chi2: best.chi2,
        dof,
        incomplete: None,
        angles_from: pb.stds.iter().filter(|s| s.obs.polarized()).map(|s| s.index).collect(),
        offset_from: idx,
        telescope: None,
        telescope_problem: None,
        telescope_from_prior: None,
        covariance,
    })
}

mod telescope;

#[cfg(test)]
mod tests;
