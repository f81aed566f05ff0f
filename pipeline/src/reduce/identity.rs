//! The A/B identity of a measured pair, checked on the per-dither photometry (stage 7):
//! every orientation must place B at the same sky position angle from A, and A must be the
//! brighter star in o+e flux over every orientation and dither. The labels of the
//! companion search ([`super::companion`]) come from two-star fits on registered stacks;
//! this check reads the fluxes and positions every dither measured.
//!
//! - **Geometry**: per orientation, the median over its dithers of B's offset from A (o
//!   beam), turned into a sky position angle with the orientation's rotator angle. Every
//!   orientation must be within 90 deg of their circular mean (a swap at one orientation
//!   turns its angle by 180 deg). An orientation whose offset is not measured is not used;
//!   when no orientation measured it, or the angles disagree, the identity is unverified.
//! - **Flux**: per dither where both stars were measured and kept, l = ln(f_B / f_A) with
//!   f = o + e (transparency and exposure cancel); the weighted mean over every dither of
//!   every orientation, with the larger of its propagated error and its scatter error.
//!   `|mean l| > 3 sigma`: the ratio is significant, and when B is the brighter the labels
//!   are exchanged (dithers, and the position angle turned by 180 deg). Otherwise the two
//!   stars cannot be told apart by flux: the geometry has already made the labels the same
//!   star at every orientation, so q and u are each one star's and Delta-gamma is unchanged
//!   by the naming; which of two equal stars is called A is then a convention, said by the
//!   target flag `ab_near_equal_flux: ...` (reported, not refused).
//!
//! An unverified identity (the geometry fails) is the target flag
//! `ab_identity_unverified: ...`; every component is then flagged and fails the cut
//! ([`super::entry::target_entry`]).
use super::{DitherValue, Measured, SkySubtractedOrientation};
use crate::catalog::{Flag, FlagCode};
use crate::stokes::model::offset_to_sep_pa;

/// The flux ratio must differ from 1 by this many sigma for A (the brighter) to be told
/// from B.
pub const FLUX_RATIO_SIGMA: f64 = 3.0;

/// The flux ratio B/A of a pair over its dithers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FluxRatio {
    /// Weighted mean of ln(f_B / f_A), f = o + e.
    pub ln_ratio: f64,
    /// Its error: the larger of the propagated one and the scatter's.
    pub sigma: f64,
    /// Dithers used.
    pub n: usize,
}

impl FluxRatio {
    /// B/A.
    pub fn ratio(&self) -> f64 {
        self.ln_ratio.exp()
    }

    /// Whether the ratio differs from 1 by more than [`FLUX_RATIO_SIGMA`] sigma.
    pub fn significant(&self) -> bool {
        self.ln_ratio.abs() > FLUX_RATIO_SIGMA * self.sigma
    }
}

/// o + e flux of a dither and its variance (None when not measured or rejected).
fn total(d: &DitherValue) -> Option<(f64, f64)> {
    let f = d.o.flux + d.e.flux;
    let v = d.o.var + d.e.var;
    (d.rejected.is_none() && f > 0.0 && f.is_finite() && v > 0.0 && v.is_finite()).then_some((f, v))
}

/// The flux ratio B/A over the dithers of every orientation where both stars were
/// measured and kept (None with fewer than 2 such dithers).
pub fn flux_ratio(a: &[Vec<DitherValue>], b: &[Vec<DitherValue>]) -> Option<FluxRatio> {
    let mut ls: Vec<(f64, f64)> = Vec::new();
    for (oa, ob) in a.iter().zip(b) {
        for (da, db) in oa.iter().zip(ob) {
            if let (Some((fa, va)), Some((fb, vb))) = (total(da), total(db)) {
                let var = va / (fa * fa) + vb / (fb * fb);
                ls.push(((fb / fa).ln(), 1.0 / var));
            }
        }
    }
    let n = ls.len();
    if n < 2 {
        return None;
    }
    let sw: f64 = ls.iter().map(|l| l.1).sum();
    let mean = ls.iter().map(|l| l.0 * l.1).sum::<f64>() / sw;
    let chi2: f64 = ls.iter().map(|l| (l.0 - mean).powi(2) * l.1).sum();
    // Propagated: 1/sqrt(sum w); from the scatter: that times sqrt(chi2/(n-1)).
    let sigma = (1.0 / sw).sqrt() * (chi2 / (n - 1) as f64).sqrt().max(1.0);
    Some(FluxRatio {
        ln_ratio: mean,
        sigma,
        n,
    })
}

/// Sky position angle of B from A at each orientation: the median over the dithers of B's
/// offset from A in the o beam (None where no dither measured both).
pub fn position_angles(
    a: &[Vec<DitherValue>],
    b: &[Vec<DitherValue>],
    orients: &[SkySubtractedOrientation],
    scale: f64,
) -> Vec<Option<f64>> {
    a.iter()
        .zip(b)
        .zip(orients)
        .map(|((oa, ob), o)| {
            let (dx, dy): (Vec<f64>, Vec<f64>) = oa
                .iter()
                .zip(ob)
                .map(|(da, db)| (db.o.xy.0 - da.o.xy.0, db.o.xy.1 - da.o.xy.1))
                .filter(|d| d.0.is_finite() && d.1.is_finite())
                .unzip();
            let (mx, my) = (crate::numeric::median_finite(&dx)?, crate::numeric::median_finite(&dy)?);
            Some(offset_to_sep_pa(mx, my, o.posang_deg, scale).1)
        })
        .collect()
}

/// The largest angle between an orientation's position angle and the circular mean of all
/// of them, deg, with the rotator angle where it occurs (None when no angle was measured).
fn worst_disagreement(pas: &[Option<f64>], orients: &[SkySubtractedOrientation]) -> Option<(f64, f64)> {
    let (cx, cy) = pas.iter().flatten().fold((0.0, 0.0), |a, p| {
        (a.0 + p.to_radians().cos(), a.1 + p.to_radians().sin())
    });
    let mean = cy.atan2(cx).to_degrees();
    pas.iter()
        .zip(orients)
        .filter_map(|(p, o)| p.map(|p| (((p - mean + 180.0).rem_euclid(360.0) - 180.0).abs(), o.posang_deg)))
        .max_by(|a, b| a.0.total_cmp(&b.0))
}

/// Check (and where the flux says so, correct) the A/B labels of a measured pair: see the
/// module documentation. Adds the target flags that say what was found. A single star
/// (one component) is left alone.
pub fn verify_pair(m: &mut Measured, orients: &[SkySubtractedOrientation], scale: f64) {
    if m.dithers.len() != 2 || m.geometry.is_none() {
        return;
    }
    let pas = position_angles(&m.dithers[0], &m.dithers[1], orients, scale);
    match worst_disagreement(&pas, orients) {
        None => {
            m.flags.push(Flag::with_detail(
                FlagCode::AbIdentityUnverified,
                "B's position from A not measured at any orientation",
            ));
            return;
        }
        Some((d, posang)) if d > 90.0 => {
            m.flags.push(Flag::with_detail(
                FlagCode::AbIdentityUnverified,
                format!(
                    "B's position angle from A at POSANG {posang:.1} is {d:.0} deg off the other orientations' (the labels disagree)"
                ),
            ));
            return;
        }
        Some(_) => {}
    }
    let Some(r) = flux_ratio(&m.dithers[0], &m.dithers[1]) else {
        m.flags.push(Flag::with_detail(
            FlagCode::AbNearEqualFlux,
            "fewer than 2 dithers measure both stars' flux; the labels follow the geometry",
        ));
        return;
    };
    let text = format!(
        "B/A = {:.3} +- {:.3} in o+e flux over {} dithers",
        r.ratio(),
        r.ratio() * r.sigma,
        r.n
    );
    if !r.significant() {
        m.flags.push(Flag::with_detail(
            FlagCode::AbNearEqualFlux,
            format!(
                "{text}, within {FLUX_RATIO_SIGMA} sigma of 1: the labels follow the geometry (the same star is A at every orientation)"
            ),
        ));
    } else if r.ln_ratio > 0.0 {
        m.dithers.swap(0, 1);
        if let Some((_, pa)) = m.geometry.as_mut() {
            *pa = (*pa + 180.0).rem_euclid(360.0);
        }
        m.flags.push(Flag::with_detail(
            FlagCode::AbRelabelledByFlux,
            format!("{text}: A is the brighter"),
        ));
    }
}
