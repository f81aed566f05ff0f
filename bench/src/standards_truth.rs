//! The true polarization of a simulated night's standards, drawn from their table values
//! and errors.
//!
//! A standards table states what is known of each star: p +- sigma_p and gamma +-
//! sigma_gamma. The calibration trusts the table only as far as those errors (the joint fit
//! carries each standard's polarization as a nuisance parameter with the table as its prior,
//! docs/calibration.md), and its covariance of (c, theta0, a, b) includes that doubt. A
//! simulated standard exactly at its table values makes an error that covariance counts
//! and the night never makes: every calibrated sigma_q is then too large, most visibly
//! for bright stars, whose own errors are smallest. So a harness that scores pulls draws
//! each standard's truth from what its table says, as the fit's prior states it:
//!
//! ```text
//! polarized (p > 3 sigma_p):  p_true = p + sigma_p z1,  gamma_true = gamma + sigma_gamma z2
//! otherwise:                  (q, u)_true = p (cos 2gamma, sin 2gamma) + sigma_p / sqrt(2) (z1, z2)
//! ```
//!
//! (z standard normal; a negative p_true is |p_true| at gamma + 90 deg.)
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use sofipol_pipeline::standards::StandardStar;
use sofipol_pipeline::stokes::model::normalize_axial_deg;

/// A standard's true (p, gamma in deg) drawn from its table entry (see the module
/// documentation).
pub fn draw_truth(entry: &StandardStar, rng: &mut impl rand::Rng) -> (f64, f64) {
    let mut z = || -> f64 { StandardNormal.sample(rng) };
    let (p, gamma) = if entry.polarized() {
        (
            entry.p + entry.sigma_p * z(),
            entry.gamma_deg + entry.sigma_gamma_deg * z(),
        )
    } else {
        let t = 2.0 * entry.gamma_deg.to_radians();
        let k = entry.sigma_p / 2f64.sqrt();
        let q = entry.p * t.cos() + k * z();
        let u = entry.p * t.sin() + k * z();
        (q.hypot(u), 0.5 * u.atan2(q).to_degrees())
    };
    if p < 0.0 {
        (-p, normalize_axial_deg(gamma + 90.0))
    } else {
        (p, normalize_axial_deg(gamma))
    }
}

/// The true (p, gamma in deg) of each of a night's standards, `entries` in the night's
/// order, drawn with [`draw_truth`] from a stream of their own seeded by `seed` (the other
/// draws of the night do not depend on them).
pub fn draw_night(entries: &[&StandardStar], seed: u64) -> Vec<(f64, f64)> {
    let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x57A2_DA2D_0000);
    entries.iter().map(|e| draw_truth(e, &mut rng)).collect()
}
