//! The night's plan: when each target sequence starts and where the telescope points
//! (docs/simulator.md, "Pointing").
//!
//! Sequences with a `start_ut` start then; the others are placed one after another in
//! scene order (binaries, then standards) from the observation's `start_ut`, each after
//! the previous one and clear of every fixed sequence. Coordinates a scene does not give
//! are drawn from the target's name so that the target is well above the horizon.
use super::pointing::{self, Pointing, LA_SILLA_NTT};
use super::scene::{Binary, Scene, StandardSource};
use super::{effects, rng};
use crate::error::{Error, Result};

/// Where and when a target sequence is observed: the optional keys shared by `[[binary]]`
/// and `[[standard]]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetPointing<'a> {
    /// `ra_deg`.
    pub ra_deg: Option<f64>,
    /// `dec_deg`.
    pub dec_deg: Option<f64>,
    /// `hour_angle_h`.
    pub hour_angle_h: Option<f64>,
    /// `start_ut`.
    pub start_ut: Option<&'a str>,
}

impl Binary {
    /// Its pointing keys.
    pub fn pointing(&self) -> TargetPointing<'_> {
        TargetPointing {
            ra_deg: self.ra_deg,
            dec_deg: self.dec_deg,
            hour_angle_h: self.hour_angle_h,
            start_ut: self.start_ut.as_deref(),
        }
    }
}

impl StandardSource {
    /// Its pointing keys.
    pub fn pointing(&self) -> TargetPointing<'_> {
        TargetPointing {
            ra_deg: self.ra_deg,
            dec_deg: self.dec_deg,
            hour_angle_h: self.hour_angle_h,
            start_ut: self.start_ut.as_deref(),
        }
    }
}

/// Seconds from a sequence's start (TPL START) to its first exposure.
pub const FIRST_EXPOSURE_S: f64 = 20.0;
/// Seconds a sequence occupies besides its exposures: 20 s before the first, 100 s after
/// the last (the preset of the next target).
const SEQUENCE_OVERHEAD_S: f64 = 120.0;

/// One target sequence's place in the night.
#[derive(Debug, Clone, PartialEq)]
pub struct SequencePlan {
    /// MJD of TPL START.
    pub mjd: f64,
    /// TPL START, ISO to the second.
    pub tpl_start: String,
    /// Right ascension, deg.
    pub ra_deg: f64,
    /// Declination, deg.
    pub dec_deg: f64,
}

impl Scene {
    /// Seconds of one exposure, DIT x NDIT.
    pub fn exposure_s(&self) -> f64 {
        self.observation.dit_s * self.observation.ndit as f64
    }

    /// Seconds a sequence occupies: 20 s, its exposures with their overheads, 100 s.
    pub fn sequence_s(&self) -> f64 {
        let o = &self.observation;
        let nframes = o.orientations_deg.len() * o.dithers;
        nframes as f64 * (self.exposure_s() + o.overhead_s) + SEQUENCE_OVERHEAD_S
    }

    /// The plan of every sequence: binaries, then standards ([`plan_sequences`]).
    pub fn plan(&self) -> Result<Vec<SequencePlan>> {
        let keys: Vec<(&str, TargetPointing)> = self
            .binary
            .iter()
            .map(|b| (b.name.as_str(), b.pointing()))
            .chain(self.standard.iter().map(|s| (s.name.as_str(), s.pointing())))
            .collect();
        plan_sequences(self, &keys)
    }

    /// MJD of the observation's start (`date`, `start_ut`).
    pub fn start_mjd(&self) -> Result<f64> {
        let o = &self.observation;
        effects::mjd_from_date_time(&o.date, &o.start_ut).ok_or_else(|| {
            invalid(format!(
                "observation.date/start_ut '{} {}' not understood",
                o.date, o.start_ut
            ))
        })
    }
}

/// MJD of exposure `k` (0-based) of a sequence starting at `tpl_mjd`: 20 s after the
/// start, then one exposure every DIT x NDIT + overhead.
pub fn exposure_mjd(scene: &Scene, tpl_mjd: f64, k: usize) -> f64 {
    let o = &scene.observation;
    tpl_mjd + (k as f64 * (scene.exposure_s() + o.overhead_s) + FIRST_EXPOSURE_S) / 86400.0
}

/// The pointing at the start and at the end of exposure `k` of sequence `plan`.
pub fn exposure_pointing(scene: &Scene, plan: &SequencePlan, k: usize) -> (Pointing, Pointing) {
    let mjd = exposure_mjd(scene, plan.mjd, k);
    let at = |m: f64| pointing::pointing(&LA_SILLA_NTT, m, plan.ra_deg, plan.dec_deg);
    (at(mjd), at(mjd + scene.exposure_s() / 86400.0))
}

/// A deterministic number in [0, 1) from a target's name and a draw index.
fn name_uniform(name: &str, draw: u64) -> f64 {
    let h = rng::splitmix64(
        name.bytes()
            .fold(7u64, |a, c| a.wrapping_mul(31).wrapping_add(c as u64)),
    );
    (rng::splitmix64(h ^ draw) >> 11) as f64 / (1u64 << 53) as f64
}

/// Plan every sequence of `targets` (name and pointing keys, in scene order). Errors name
/// the target and the key: a `start_ut` not understood, two fixed sequences that overlap,
/// a target below the horizon during one of its exposures.
pub fn plan_sequences(scene: &Scene, targets: &[(&str, TargetPointing)]) -> Result<Vec<SequencePlan>> {
    let mjd0 = scene.start_mjd()?;
    let dur = scene.sequence_s() / 86400.0;
    // Fixed starts first.
    let mut fixed: Vec<(f64, usize)> = Vec::new();
    for (i, (name, p)) in targets.iter().enumerate() {
        if let Some(ut) = p.start_ut {
            let mut m = effects::mjd_from_date_time(&scene.observation.date, ut)
                .ok_or_else(|| invalid(format!("'{name}': start_ut = '{ut}' not understood (HH:MM:SS)")))?;
            if m < mjd0 {
                m += 1.0;
            }
            fixed.push((m, i));
        }
    }
    fixed.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in fixed.windows(2) {
        if w[1].0 < w[0].0 + dur {
            return Err(invalid(format!(
                "'{}' (start_ut {}) starts before '{}' (start_ut {}) has ended: a sequence takes {:.0} s",
                targets[w[1].1].0,
                effects::iso_from_mjd(w[1].0, false),
                targets[w[0].1].0,
                effects::iso_from_mjd(w[0].0, false),
                dur * 86400.0
            )));
        }
    }
    // The others one after another, around the fixed ones.
    let mut starts = vec![f64::NAN; targets.len()];
    for &(m, i) in &fixed {
        starts[i] = m;
    }
    let (mut anchor, mut j) = (mjd0, 0usize);
    for (i, (_, p)) in targets.iter().enumerate() {
        if p.start_ut.is_some() {
            continue;
        }
        let mut m = anchor + j as f64 * scene.sequence_s() / 86400.0;
        while let Some(&(f, _)) = fixed.iter().find(|&&(f, _)| f < m + dur && m < f + dur) {
            (anchor, j) = (f + dur, 0);
            m = f + dur;
        }
        starts[i] = m;
        j += 1;
    }
    let mut plans = Vec::with_capacity(targets.len());
    for ((name, p), mjd) in targets.iter().zip(starts) {
        let dec = p.dec_deg.unwrap_or_else(|| -75.0 + 80.0 * name_uniform(name, 1));
        let ra = p.ra_deg.unwrap_or_else(|| {
            let h = p.hour_angle_h.unwrap_or_else(|| -3.0 + 6.0 * name_uniform(name, 2));
            pointing::wrap_360(pointing::lst_deg(mjd, &LA_SILLA_NTT) - 15.0 * h)
        });
        let plan = SequencePlan {
            mjd,
            tpl_start: effects::iso_from_mjd(mjd, false),
            ra_deg: ra,
            dec_deg: dec,
        };
        let nframes = scene.observation.orientations_deg.len() * scene.observation.dithers;
        for k in 0..nframes {
            let (s, e) = exposure_pointing(scene, &plan, k);
            if let Some(low) = [s, e].into_iter().find(|q| q.alt_deg <= 0.0) {
                return Err(invalid(format!(
                    "'{name}' (RA {ra:.3}, Dec {dec:.3}) is below the horizon at {} (altitude {:.1} deg): change its ra_deg, dec_deg, hour_angle_h or start_ut",
                    effects::iso_from_mjd(low.mjd, false),
                    low.alt_deg
                )));
            }
        }
        plans.push(plan);
    }
    Ok(plans)
}

fn invalid(reason: String) -> Error {
    Error::Scene {
        origin: "scene".into(),
        reason,
    }
}
