//! Scoring a world night: each reduced target against its truth (pulls of q, u, P and
//! gamma; components missing, refused, relabelled), the bins' statistics, the pooling of
//! nights and the table.

use sofipol_pipeline::catalog::flags::join;
use sofipol_pipeline::catalog::{FlagCode, Target};
use sofipol_pipeline::sim::TargetTruth;

use super::{Reduced, WorldBin, WorldTarget, GAMMA_PULL_MIN_SNR, P_PULL_MIN_SNR, RELABEL_RATIO};

/// A component the reduction refuses to vouch for: flagged `saturated`, or
/// `ab_identity_unverified` (which star was measured at some orientation is not known:
/// it fails the cut). Counted as refused, not scored.
fn refused_component(c: &sofipol_pipeline::catalog::Component) -> bool {
    c.flags
        .iter()
        .any(|f| matches!(f.code, FlagCode::Saturated | FlagCode::AbIdentityUnverified))
}

/// Match the catalog's components to the truth and compute the pulls. Refused components
/// ([`refused_component`]) are counted, not scored; the others are scored.
fn score(target: &Target, tt: &TargetTruth, ratio: f64) -> Score {
    let found_pa = target.pa_deg;
    let swapped = found_pa.is_some_and(|pa| {
        let d = (pa - tt.pa_deg).rem_euclid(360.0);
        d > 90.0 && d < 270.0
    });
    let mut truth = tt.components.clone();
    if swapped {
        truth.swap(0, 1);
    }
    let (mut pulls, mut sigmas, mut errors, mut missing, mut refused) = (Vec::new(), Vec::new(), Vec::new(), 0, 0);
    let (mut p_pulls, mut gamma_pulls) = (Vec::new(), Vec::new());
    for (i, tc) in truth.iter().enumerate() {
        match target.components.get(i) {
            Some(c) if refused_component(c) => refused += 1,
            Some(c) if c.q.is_finite() && c.sigma_q > 0.0 && c.sigma_u > 0.0 => {
                pulls.push((c.q - tc.q) / c.sigma_q);
                pulls.push((c.u - tc.u) / c.sigma_u);
                errors.extend([c.q - tc.q, c.u - tc.u]);
                sigmas.push(c.sigma_q);
                let snr_true = tc.p / c.sigma_p;
                if snr_true > P_PULL_MIN_SNR {
                    p_pulls.push((c.p_debiased - tc.p) / c.sigma_p);
                }
                if snr_true > GAMMA_PULL_MIN_SNR {
                    gamma_pulls.push(wrap_angle_deg(c.gamma_deg - tc.gamma_deg) / c.sigma_gamma_deg);
                }
            }
            _ => missing += 1,
        }
    }
    // A/B labels are judged where both components were measured unflagged by saturation.
    Score {
        pulls,
        sigmas,
        errors,
        p_pulls,
        gamma_pulls,
        missing,
        refused,
        relabelled: swapped && ratio < RELABEL_RATIO && refused == 0,
    }
}

/// An angle difference of polarization angles (period 180 deg) wrapped to [-90, 90) deg.
pub fn wrap_angle_deg(d: f64) -> f64 {
    (d + 90.0).rem_euclid(180.0) - 90.0
}

/// A target's components scored against the truth.
struct Score {
    pulls: Vec<f64>,
    sigmas: Vec<f64>,
    errors: Vec<f64>,
    p_pulls: Vec<f64>,
    gamma_pulls: Vec<f64>,
    missing: usize,
    refused: usize,
    relabelled: bool,
}

pub(super) fn scored(r: Reduced, saturated_design: bool) -> WorldTarget {
    let Score {
        pulls,
        sigmas,
        errors,
        p_pulls,
        gamma_pulls,
        missing,
        refused,
        relabelled,
    } = score(&r.target, &r.truth, r.ratio);
    let target = &r.target;
    let dither_chi2 = target
        .components
        .iter()
        .filter(|c| c.q.is_finite() && !refused_component(c))
        .filter_map(|c| c.orientations.as_ref())
        .flatten()
        .filter(|o| o.chi2.is_finite())
        .map(|o| (o.chi2, o.n_dithers))
        .collect();
    let orientation_f = target
        .components
        .iter()
        .filter(|c| c.q.is_finite() && !refused_component(c))
        .filter_map(|c| c.orientations.as_ref())
        .map(|os| {
            os.iter()
                .filter(|o| [o.analyzer_deg, o.f, o.sigma_f].iter().all(|v| v.is_finite()))
                .map(|o| (o.analyzer_deg, o.f, o.sigma_f))
                .collect()
        })
        .collect();
    WorldTarget {
        orientation_f,
        photometry: target.photometry.clone().unwrap_or_default(),
        dither_chi2,
        object: r.truth.object.clone(),
        separation_arcsec: r.truth.separation_arcsec,
        flux_ratio: r.ratio,
        flux_a_adu: r.truth.components[0].flux,
        conditions: r.cond,
        pulls,
        sigmas,
        errors,
        p_pulls,
        gamma_pulls,
        missing,
        refused,
        saturated: saturated_design,
        relabelled,
        note: format!(
            "{:?} {} flags {:?} err {:?}",
            target.status,
            target
                .components
                .iter()
                .map(|c| format!("{}[{}]", c.name, join(&c.flags, ",")))
                .collect::<Vec<_>>()
                .join(" "),
            target.flags,
            target.error
        ),
    }
}

/// A bin's statistics from its targets.
pub(super) fn bin_of(sep_arcsec: (f64, f64), targets: Vec<WorldTarget>) -> WorldBin {
    let pulls: Vec<f64> = targets.iter().flat_map(|t| t.pulls.iter().copied()).collect();
    let mut sig: Vec<f64> = targets.iter().flat_map(|t| t.sigmas.iter().copied()).collect();
    sig.sort_by(f64::total_cmp);
    let np = pulls.len().max(1) as f64;
    let errors: Vec<f64> = targets.iter().flat_map(|t| t.errors.iter().copied()).collect();
    let rms_error = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len().max(1) as f64).sqrt();
    let p_pulls: Vec<f64> = targets.iter().flat_map(|t| t.p_pulls.iter().copied()).collect();
    let gamma_pulls: Vec<f64> = targets.iter().flat_map(|t| t.gamma_pulls.iter().copied()).collect();
    let (rms_p_pull, mean_p_pull) = rms_and_mean(&p_pulls);
    let (rms_gamma_pull, mean_gamma_pull) = rms_and_mean(&gamma_pulls);
    WorldBin {
        sep_arcsec,
        n_pulls: pulls.len(),
        rms_pull: (pulls.iter().map(|p| p * p).sum::<f64>() / np).sqrt(),
        mean_pull: pulls.iter().sum::<f64>() / np,
        median_sigma: sig.get(sig.len() / 2).copied().unwrap_or(f64::NAN),
        n_p_pulls: p_pulls.len(),
        rms_p_pull,
        mean_p_pull,
        n_gamma_pulls: gamma_pulls.len(),
        rms_gamma_pull,
        mean_gamma_pull,
        rms_error,
        missing: targets.iter().map(|t| t.missing).sum(),
        refused: targets.iter().map(|t| t.refused).sum(),
        relabelled: targets.iter().filter(|t| t.relabelled).count(),
        targets,
    }
}

/// The rms and the mean of `x` (NaN for none).
pub fn rms_and_mean(x: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    (
        (x.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
        x.iter().sum::<f64>() / n,
    )
}

/// The bins of several nights (each from [`run`](super::run), the same bins), pooled: targets
/// concatenated, statistics recomputed.
pub fn pool_nights(nights: &[Vec<WorldBin>]) -> Vec<WorldBin> {
    (0..nights.first().map_or(0, Vec::len))
        .map(|i| {
            let targets = nights.iter().flat_map(|n| n[i].targets.iter().cloned()).collect();
            bin_of(nights[0][i].sep_arcsec, targets)
        })
        .collect()
}

/// A table of the bins; with `detail`, one line per target whose worst pull exceeds 4 or
/// that lost a component.
pub fn table(bins: &[WorldBin], detail: bool) -> String {
    let mut s = format!(
        "{:>11} {:>6} {:>9} {:>9} {:>10} {:>10} {:>8} {:>8} {:>10} {:>11} {:>12}\n",
        "sep [\"]",
        "pulls",
        "rms pull",
        "mean",
        "med sig_q",
        "rms error",
        "missing",
        "refused",
        "relabelled",
        "rms P pull",
        "rms gam pull"
    );
    for b in bins {
        s += &format!(
            "{:>5.2}-{:<5.2} {:>6} {:>9.3} {:>9.3} {:>10.5} {:>10.5} {:>8} {:>8} {:>10} {:>11.3} {:>12.3}\n",
            b.sep_arcsec.0,
            b.sep_arcsec.1,
            b.n_pulls,
            b.rms_pull,
            b.mean_pull,
            b.median_sigma,
            b.rms_error,
            b.missing,
            b.refused,
            b.relabelled,
            b.rms_p_pull,
            b.rms_gamma_pull
        );
        if detail {
            for t in &b.targets {
                let worst = t.pulls.iter().fold(0.0f64, |a, p| a.max(p.abs()));
                if worst > 4.0 || t.missing > 0 || t.relabelled || t.refused > 0 || t.saturated {
                    s += &format!(
                        "    {} sep {:.2}\" A {:.0} ADU B/A {:.2} {:?}: worst pull {:.1}, missing {} | {}\n",
                        t.object,
                        t.separation_arcsec,
                        t.flux_a_adu,
                        t.flux_ratio,
                        t.conditions,
                        worst,
                        t.missing,
                        t.note
                    );
                }
            }
        }
    }
    s
}
