//! The telescope's own polarization in the joint fit of the standards.
//!
//! The tertiary mirror adds to every source the sky-frame polarization
//! `(q_tel, u_tel) = R(2 eta) (a, b)`, `(a, b) = p_tel (cos 2psi_tel, sin 2psi_tel)`, so an
//! orientation whose frames have parallactic angles eta sees in F the extra term
//!
//! ```text
//! T = a <cos 2(phi - eta)> + b <sin 2(phi - eta)>
//!   = a (C cos 2phi + S sin 2phi) + b (C sin 2phi - S cos 2phi),   (C, S) = <(cos 2eta, sin 2eta)>
//! ```
//!
//! (`<>`: the weighted mean over the orientation's frames, as F is). (a, b) join c and theta0
//! as instrument parameters of the joint fit. Unpolarized standards at different parallactic
//! angles separate them from c: at one parallactic angle, T is a constant per orientation
//! that c and the standards' own polarization absorb as well. The fit is kept only when every
//! instrument parameter is determined on its own: its multiple correlation with the others
//! at most [`MAX_CORRELATION`], more orientations than instrument parameters, and no second
//! solution as good.
use super::{
    inflation, separation_problem, usable, JointCalibration, JointOptions, Offset, Problem, Solution,
    StandardObservation, Std, CAL_C, CAL_TEL_A, CAL_TEL_B, CAL_THETA0, MAX_CORRELATION, PARITY_DCHI2,
};
use crate::stokes::calibration::AngleCalibration;
use crate::stokes::fresnel::TelescopePrior;
use crate::stokes::model::TelescopePolarization;

/// Why the standards cannot measure the telescope's polarization (its `Display` is
/// [`JointCalibration::telescope_problem`]). `what` describes the standards fitted ("N
/// orientation(s) of M standard(s) whose parallactic angles span X deg (mod 180)").
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub(super) enum TelescopeFitError {
    /// No unpolarized standard, and theta0 is not fitted.
    #[error("no unpolarized standard, and the polarized ones do not fix theta0")]
    NoUnpolarized,
    /// Standards whose frames carry no parallactic angle.
    #[error("{missing} standard(s) without a parallactic angle in their frames (TEL PARANG)")]
    NoParallacticAngle {
        /// How many.
        missing: usize,
    },
    /// No more orientations than instrument parameters.
    #[error("{what}: no more orientations than the {n_inst} instrument parameters")]
    TooFewOrientations {
        /// The standards fitted.
        what: String,
        /// Instrument parameters fitted.
        n_inst: usize,
    },
    /// The unpolarized standards alone do not determine the term and c: the polarized
    /// standards' share of it rests on their table values, whose errors (25 % in p, 2 deg in
    /// angle) are as large as the term, and such a fit's errors are far too small.
    #[error(
        "{what}: the {unpolarized} unpolarized standard(s) do not measure the term on their own (it takes \
         orientations of unpolarized standards at two or more parallactic angles; the polarized standards' \
         table values are not known well enough to stand in for them)"
    )]
    FewUnpolarized {
        /// The standards fitted.
        what: String,
        /// Unpolarized standards among them.
        unpolarized: usize,
    },
    /// The normal matrix cannot be inverted.
    #[error("{what}: the normal matrix is singular (the telescope's term is not separable from c)")]
    Singular {
        /// The standards fitted.
        what: String,
    },
    /// Another solution fits as well (the words of `separation_problem`).
    #[error("{0}")]
    NotSeparable(String),
    /// An instrument parameter is nearly a combination of the others.
    #[error(
        "{what}: {parameter} is not determined on its own (multiple correlation {correlation:.3} with the other \
         instrument parameters, beyond {max}); observe unpolarized standards at \
         parallactic angles further apart",
        max = MAX_CORRELATION
    )]
    Correlated {
        /// The standards fitted.
        what: String,
        /// The parameter (c, theta0, a or b).
        parameter: &'static str,
        /// Its multiple correlation with the others.
        correlation: f64,
    },
}

/// The joint fit with the telescope's term, from the fit without it (`base`: its parity, and
/// whether it fitted theta0). `Err` says why the standards cannot measure the telescope.
///
/// With a `prior`, the prior's two rows join the data: the term is then determined by the
/// prior where the standards do not determine it, and only c against theta0 must be
/// separated by the standards (the rule of the fit without the term); a parameter
/// correlated with the term is not refused, its error is the prior's.
pub(super) fn refit<'a>(
    stds: &'a [StandardObservation],
    opts: &JointOptions,
    base: &JointCalibration,
    prior: Option<TelescopePrior>,
) -> Result<JointCalibration, TelescopeFitError> {
    let angles = base.angles;
    let all = usable(stds);
    let chosen: Vec<Std<'_>> = if angles.is_some() {
        all
    } else {
        // c from the unpolarized standards only (as without the telescope's term), with the
        // profile's analyzer angles.
        all.into_iter().filter(|s| !s.obs.polarized()).collect()
    };
    if chosen.is_empty() {
        return Err(TelescopeFitError::NoUnpolarized);
    }
    let missing = chosen
        .iter()
        .filter(|s| s.rows.iter().any(|r| r.parallactic_2eta.is_none()))
        .count();
    if missing > 0 {
        return Err(TelescopeFitError::NoParallacticAngle { missing });
    }
    let problem = |parity: i32, stds: Vec<Std<'a>>| Problem {
        stds,
        parity: parity as f64,
        fit_theta0: angles.is_some(),
        theta0_fixed: opts.profile_theta0_deg,
        fit_telescope: true,
        prior,
    };
    // The parity chosen again with the telescope's term in the model (without it, a
    // telescope polarization large against the errors can make the wrong parity fit better).
    let n_pol = chosen.iter().filter(|s| s.obs.polarized()).count();
    let (parity, parity_measured) = if angles.is_some() && n_pol >= 2 {
        let chi2 = |p: i32| problem(p, usable(stds).into_iter().collect()).solve().map(|s| s.0.chi2);
        match (chi2(1), chi2(-1)) {
            (Some(a), Some(b)) if (a - b).abs() > PARITY_DCHI2 => (if a <= b { 1 } else { -1 }, true),
            _ => (opts.default_parity, false),
        }
    } else {
        (
            angles.map_or(opts.default_parity, |a| a.parity),
            angles.is_some_and(|a| a.parity_measured),
        )
    };
    let pb = problem(parity, chosen);
    let what = describe(&pb);
    if prior.is_none() && pb.fit_theta0 && !unpolarized_measure_the_term(&pb) {
        return Err(TelescopeFitError::FewUnpolarized {
            what,
            unpolarized: pb.stds.iter().filter(|s| !s.obs.polarized()).count(),
        });
    }
    let n_inst = pb.n_inst();
    if pb.n_data() + pb.n_prior() <= n_inst {
        return Err(TelescopeFitError::TooFewOrientations { what, n_inst });
    }
    let Some((best, others)) = pb.solve() else {
        return Err(TelescopeFitError::Singular { what });
    };
    if prior.is_none() || pb.fit_theta0 {
        if let Some(why) = separation_problem(&pb, &best, &others) {
            return Err(TelescopeFitError::NotSeparable(why));
        }
    }
    let names = if pb.fit_theta0 {
        vec!["c", "theta0", "a", "b"]
    } else {
        vec!["c", "a", "b"]
    };
    if let Some((k, r)) = worst_multiple_correlation(&best.cov, n_inst).filter(|_| prior.is_none()) {
        if r > MAX_CORRELATION {
            return Err(TelescopeFitError::Correlated {
                what,
                parameter: names[k],
                correlation: r,
            });
        }
    }
    let dof = pb.n_data() + pb.n_prior() - n_inst;
    let best = match (prior.is_some() && pb.fit_theta0).then(|| marginalise_theta0(&pb, &best)) {
        Some(Some(marginal)) => marginal,
        _ => best,
    };
    let k = inflation(best.chi2, dof);
    let it = pb.i_tel();
    let index = |i: usize| match (pb.fit_theta0, i) {
        (_, 0) => CAL_C,
        (true, 1) => CAL_THETA0,
        (_, i) if i == it => CAL_TEL_A,
        _ => CAL_TEL_B,
    };
    let mut covariance = [[0.0; 4]; 4];
    for i in 0..n_inst {
        for j in 0..n_inst {
            covariance[index(i)][index(j)] = best.cov[i][j] * k;
        }
    }
    let (a, b) = (best.x[it], best.x[it + 1]);
    let ids = |pol: bool| {
        pb.stds
            .iter()
            .filter(|s| !pol || s.obs.polarized())
            .map(|s| s.index)
            .collect::<Vec<usize>>()
    };
    Ok(JointCalibration {
        offset: Some(Offset {
            c: best.x[0],
            sigma_c: covariance[CAL_C][CAL_C].sqrt(),
        }),
        angles: angles.map(|a| AngleCalibration {
            theta0_deg: best.x[1],
            sigma_theta0_deg: covariance[CAL_THETA0][CAL_THETA0].sqrt(),
            parity,
            parity_measured,
            ..a
        }),
        cov_c_theta0_deg: angles.map(|_| covariance[CAL_C][CAL_THETA0]),
        chi2: best.chi2,
        dof,
        incomplete: base.incomplete.clone(),
        offset_from: ids(false),
        angles_from: if angles.is_some() { ids(true) } else { vec![] },
        telescope: Some(TelescopePolarization {
            p_tel: a.hypot(b),
            psi_tel_deg: crate::stokes::model::normalize_axial_deg(0.5 * b.atan2(a).to_degrees()),
        }),
        telescope_problem: None,
        telescope_from_prior: None,
        covariance,
    })
}

/// `pb` with theta0 held at `theta0_deg` instead of fitted (x without its theta0).
fn with_theta0_held<'a>(pb: &Problem<'a>, theta0_deg: f64) -> Problem<'a> {
    Problem {
        stds: pb.stds.clone(),
        parity: pb.parity,
        fit_theta0: false,
        theta0_fixed: theta0_deg,
        fit_telescope: pb.fit_telescope,
        prior: pb.prior,
    }
}

/// Steps of the quadrature over theta0 per linear 1-sigma error, and how far it goes: until
/// the profile of chi^2 is this far above its minimum (the weight there is e^-15 of the
/// peak's) or 90 deg from the minimum.
const STEPS_PER_SIGMA: f64 = 4.0;
const QUADRATURE_DCHI2: f64 = 30.0;

/// The fit with the telescope's prior, marginalised over theta0 instead of linearised in it:
/// the posterior mean and covariance of every parameter, in place of the minimum and the
/// inverse of the normal matrix there.
///
/// With polarized standards only, theta0 enters the model through the rotation of stars whose
/// own polarization is known to 25 %, together with the term's prior; over its error
/// (several degrees) the chi^2 is far from a parabola in theta0. The curvature at the minimum
/// then understates the spread: over simulated nights drawn from the fit's own model and
/// prior, the linear errors gave theta0 pulls of median |x| 0.75 (0.67 for honest errors) and
/// 2 % beyond 4 sigma. Given theta0, the model is close to linear in the other parameters.
/// So on a grid of theta0 (1/4 of its linear error apart, outwards until the profile of chi^2
/// rises 30 above its minimum) each conditional fit gives the conditional mean `x(theta0)`,
/// covariance `Sigma(theta0)` and the weight `exp(-chi2(theta0)/2) det(Sigma(theta0))^(1/2)`
/// (Laplace's approximation of the integral over the others). Then
///
/// ```text
/// mean = sum w x(theta0),   cov = sum w [Sigma(theta0) + (x(theta0) - mean)(x(theta0) - mean)^T]
/// ```
///
/// (Sigma(theta0) with a zero row and column for theta0). `None` when a conditional fit fails.
fn marginalise_theta0(pb: &Problem, best: &Solution) -> Option<Solution> {
    let theta_hat = best.x[1];
    let sigma_lin = best.cov[1][1].sqrt();
    let step = (sigma_lin / STEPS_PER_SIGMA).clamp(0.02, 2.0);
    let mut rest = best.x.clone();
    rest.remove(1);
    // (chi2, x with theta0, covariance with theta0's zero row and column, half its log det)
    let mut nodes = Vec::new();
    type Node = (f64, Vec<f64>, Vec<Vec<f64>>, f64);
    let conditional = |theta: f64, start: &[f64]| -> Option<(Node, Vec<f64>)> {
        let s = with_theta0_held(pb, theta).minimise(start.to_vec())?;
        let log_det = log_det_spd(&s.cov)?;
        let mut x = s.x.clone();
        x.insert(1, theta);
        let n = x.len();
        let cov: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| match (i, j) {
                        (1, _) | (_, 1) => 0.0,
                        _ => s.cov[i - usize::from(i > 1)][j - usize::from(j > 1)],
                    })
                    .collect()
            })
            .collect();
        Some(((s.chi2, x, cov, 0.5 * log_det), s.x))
    };
    nodes.push(conditional(theta_hat, &rest)?.0);
    let chi2_min = nodes[0].0.min(best.chi2);
    for dir in [-1.0, 1.0] {
        let mut start = rest.clone();
        let mut k = 1.0;
        while k * step <= 90.0 {
            let (node, x) = conditional(theta_hat + dir * k * step, &start)?;
            let far = node.0 - chi2_min > QUADRATURE_DCHI2;
            nodes.push(node);
            if far {
                break;
            }
            start = x;
            k += 1.0;
        }
    }
    let log_w: Vec<f64> = nodes
        .iter()
        .map(|(chi2, _, _, half_log_det)| -0.5 * chi2 + half_log_det)
        .collect();
    let top = log_w.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let w: Vec<f64> = log_w.iter().map(|l| (l - top).exp()).collect();
    let total: f64 = w.iter().sum();
    if !(total > 0.0 && total.is_finite()) {
        return None;
    }
    let n = best.x.len();
    let mean: Vec<f64> = (0..n)
        .map(|i| nodes.iter().zip(&w).map(|(node, w)| w * node.1[i]).sum::<f64>() / total)
        .collect();
    let cov: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            (0..n)
                .map(|j| {
                    nodes
                        .iter()
                        .zip(&w)
                        .map(|((_, x, c, _), w)| w * (c[i][j] + (x[i] - mean[i]) * (x[j] - mean[j])))
                        .sum::<f64>()
                        / total
                })
                .collect()
        })
        .collect();
    let mut x = mean;
    x[1] = crate::stokes::model::normalize_axial_deg(x[1]);
    Some(Solution {
        x,
        cov,
        chi2: best.chi2,
    })
}

/// log det of a symmetric positive-definite matrix (Cholesky); `None` when it is not.
fn log_det_spd(a: &[Vec<f64>]) -> Option<f64> {
    let n = a.len();
    let mut l = vec![vec![0.0; n]; n];
    let mut log_det = 0.0;
    for i in 0..n {
        for j in 0..=i {
            let s = a[i][j] - (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>();
            if i == j {
                if !(s > 0.0 && s.is_finite()) {
                    return None;
                }
                l[i][i] = s.sqrt();
                log_det += 2.0 * l[i][i].ln();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(log_det)
}

/// Whether the unpolarized standards of `pb` alone determine c and the term (theta0 held at
/// its value in `pb`: their model does not depend on it but through the term's angle):
/// more orientations than those three parameters, a normal matrix that inverts, and no
/// parameter's multiple correlation beyond [`MAX_CORRELATION`]. Without that, a fit of
/// the term from the standards alone leans on the polarized standards' table values: over
/// simulated nights with one unpolarized standard or none among polarized ones, the errors
/// of theta0 and of the term's angle came out 2-6 times too small.
fn unpolarized_measure_the_term(pb: &Problem) -> bool {
    let sub = Problem {
        stds: pb.stds.iter().filter(|s| !s.obs.polarized()).cloned().collect(),
        parity: pb.parity,
        fit_theta0: false,
        theta0_fixed: pb.theta0_fixed,
        fit_telescope: true,
        prior: None,
    };
    let n_inst = sub.n_inst();
    if sub.n_data() <= n_inst {
        return false;
    }
    sub.solve().is_some_and(|(best, _)| {
        worst_multiple_correlation(&best.cov, n_inst).is_none_or(|(_, r)| r <= MAX_CORRELATION)
    })
}

/// The largest multiple correlation of one of the first `n` parameters with the other
/// `n - 1`, `R_k^2 = 1 - 1/(Sigma_kk (Sigma^-1)_kk)` on the `n x n` block: (index, R).
fn worst_multiple_correlation(cov: &[Vec<f64>], n: usize) -> Option<(usize, f64)> {
    let block: Vec<Vec<f64>> = (0..n).map(|i| cov[i][..n].to_vec()).collect();
    let Some(inv) = super::invert_spd(&block) else {
        return Some((0, 1.0));
    };
    (0..n)
        .map(|k| (k, (1.0 - 1.0 / (block[k][k] * inv[k][k])).max(0.0).sqrt()))
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// "N orientation(s) of M standard(s) whose parallactic angles span X deg".
fn describe(pb: &Problem) -> String {
    let mut etas: Vec<f64> = pb
        .stds
        .iter()
        .flat_map(|s| s.rows.iter())
        .filter_map(|r| r.parallactic_2eta)
        .map(|[c, s]| (0.5 * s.atan2(c).to_degrees()).rem_euclid(180.0))
        .collect();
    etas.sort_by(f64::total_cmp);
    // The smallest arc of the 180-deg circle holding every angle: 180 minus the largest gap.
    let largest_gap = etas
        .windows(2)
        .map(|w| w[1] - w[0])
        .chain(etas.first().zip(etas.last()).map(|(f, l)| f + 180.0 - l))
        .fold(0.0, f64::max);
    format!(
        "{} orientation(s) of {} standard(s) whose parallactic angles span {:.1} deg (mod 180)",
        pb.n_data(),
        pb.stds.len(),
        (180.0 - largest_gap).max(0.0)
    )
}

#[cfg(test)]
mod tests;
