//! The interstellar foreground as a field on the sky (effect `foreground_field`).
//!
//! A Gaussian random field by random Fourier features on the unit sphere: at the unit
//! vector n of a star (from its RA and Dec),
//! ```text
//! q(n) = q_mean + rms sqrt(2/M) sum_j cos(k_j . n + phi_j)      (j = 1..M)
//! ```
//! and u the same with its own M modes. Each k_j is a 3-D vector with independent
//! N(0, 1/l^2) components, l the coherence scale in radians, and phi_j is uniform in
//! [0, 2 pi). Over the draws of the modes, `E[q(n)] = q_mean` and
//! `cov(q(n1), q(n2)) = rms^2 exp(-|n1 - n2|^2 / (2 l^2))` (the characteristic function of
//! the Gaussian k), |n1 - n2| the chord, equal to the angle to 1 part in 10^8 at 1 deg.
//! For one draw, the mean of q over a region much larger than l is q_mean and its
//! variance is rms^2 exactly (each cosine of distinct frequency averages 1/2 in square);
//! its correlation at separation d is `(1/M) sum_j cos(k_j . d)`, exp(-d^2/(2 l^2))
//! within ~1/sqrt(2M). The modes are drawn once per scene from `seed` (the section's, else
//! the scene's), so a star's foreground depends only on where it is on the sky.
//!
//! Composition: the foreground's (q, u) is added to the star's own (first order, as for
//! `interstellar_polarization`); the neglected cross term of a dichroic screen in front of a
//! polarized star is of order p_foreground p_star (2e-3 for 3 % and 7 %).
use serde::Serialize;

use super::rng::stream;
use super::scene::{EffectKind, ForegroundFieldConfig, INNER_SCALE_RATIO};
use crate::stokes::model::Polarization;

/// Radians per arcsec.
const RAD_PER_ARCSEC: f64 = std::f64::consts::PI / (180.0 * 3600.0);

/// One realisation of the foreground field.
#[derive(Debug, Clone)]
pub struct ForegroundField {
    mean: Polarization,
    /// sqrt(2/M) rms.
    amp: f64,
    /// (k, phi) of q's modes; k in 1/radian.
    q_modes: Vec<([f64; 3], f64)>,
    /// (k, phi) of u's modes.
    u_modes: Vec<([f64; 3], f64)>,
}

impl ForegroundField {
    /// Draw the field's modes from `seed` (deterministic).
    pub fn new(c: &ForegroundFieldConfig, seed: u64) -> ForegroundField {
        let kscale = 1.0 / (c.coherence_arcsec * RAD_PER_ARCSEC);
        let draw = |which: u64| {
            let mut r = stream(seed, EffectKind::ForegroundField, which, 0, 0);
            (0..c.modes)
                .map(|_| {
                    let g = [super::normal(&mut r), super::normal(&mut r), super::normal(&mut r)];
                    let k = match c.structure_exponent {
                        None => g.map(|v| kscale * v),
                        Some(alpha) => {
                            // |k| from p(k) ~ k^-(alpha + 1) on [1/outer, 1/inner] by the
                            // inverse of its distribution function, the direction g/|g|.
                            let (lo, hi) = (kscale, kscale / INNER_SCALE_RATIO);
                            let (a, b) = (lo.powf(-alpha), hi.powf(-alpha));
                            let kk = (a - super::uniform(&mut r) * (a - b)).powf(-1.0 / alpha);
                            let norm = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt().max(1e-300);
                            g.map(|v| kk * v / norm)
                        }
                    };
                    (k, std::f64::consts::TAU * super::uniform(&mut r))
                })
                .collect::<Vec<_>>()
        };
        ForegroundField {
            mean: Polarization::from_p_gamma(c.p, c.angle_deg),
            amp: c.rms * (2.0 / c.modes.max(1) as f64).sqrt(),
            q_modes: draw(0),
            u_modes: draw(1),
        }
    }

    /// The field's mean (q, u).
    pub fn mean(&self) -> Polarization {
        self.mean
    }

    /// The foreground (q, u) at the unit vector `n`.
    pub fn at_unit(&self, n: [f64; 3]) -> Polarization {
        let sum = |modes: &[([f64; 3], f64)]| {
            modes
                .iter()
                .map(|(k, phi)| (k[0] * n[0] + k[1] * n[1] + k[2] * n[2] + phi).cos())
                .sum::<f64>()
        };
        Polarization {
            q: self.mean.q + self.amp * sum(&self.q_modes),
            u: self.mean.u + self.amp * sum(&self.u_modes),
        }
    }

    /// The foreground (q, u) at (RA, Dec), deg.
    pub fn at(&self, ra_deg: f64, dec_deg: f64) -> Polarization {
        self.at_unit(unit_vector(ra_deg, dec_deg))
    }
}

/// The unit vector of (RA, Dec), deg: (cos d cos a, cos d sin a, sin d).
pub fn unit_vector(ra_deg: f64, dec_deg: f64) -> [f64; 3] {
    let (a, d) = (ra_deg.to_radians(), dec_deg.to_radians());
    [d.cos() * a.cos(), d.cos() * a.sin(), d.sin()]
}

/// The position `sep_arcsec` from (RA, Dec) at position angle `pa_deg` (east of north)
/// along the great circle: (RA in [0, 360), Dec), deg.
pub fn offset_position(ra_deg: f64, dec_deg: f64, sep_arcsec: f64, pa_deg: f64) -> (f64, f64) {
    if sep_arcsec == 0.0 {
        return (ra_deg, dec_deg);
    }
    let (d0, th, pa) = (dec_deg.to_radians(), sep_arcsec * RAD_PER_ARCSEC, pa_deg.to_radians());
    let sin_d = d0.sin() * th.cos() + d0.cos() * th.sin() * pa.cos();
    let d = sin_d.clamp(-1.0, 1.0).asin();
    let da = (pa.sin() * th.sin() * d0.cos()).atan2(th.cos() - d0.sin() * sin_d);
    ((ra_deg + da.to_degrees()).rem_euclid(360.0), d.to_degrees())
}

/// The foreground at one star, as truth.json records it.
#[derive(Debug, Clone, Serialize)]
pub struct StarForeground {
    /// "A", "B", "field1"...
    pub name: String,
    /// Where the star is: RA, deg.
    pub ra_deg: f64,
    /// Dec, deg.
    pub dec_deg: f64,
    /// The field's q there (added to the star's own).
    pub q: f64,
    /// The field's u there.
    pub u: f64,
}

/// The field's parameters in truth.json.
#[derive(Debug, Clone, Serialize)]
pub struct ForegroundFieldTruth {
    /// Mean q.
    pub q_mean: f64,
    /// Mean u.
    pub u_mean: f64,
    /// Mean degree (fraction).
    pub p: f64,
    /// Mean angle, deg east of north.
    pub angle_deg: f64,
    /// rms of q and of u.
    pub rms: f64,
    /// Coherence scale, arcsec (the outer scale of a power-law field).
    pub coherence_arcsec: f64,
    /// The power-law field's structure-function exponent (absent: Gaussian correlation).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub structure_exponent: Option<f64>,
    /// Fourier modes per Stokes parameter.
    pub modes: usize,
    /// Seed the modes were drawn from.
    pub seed: u64,
}

impl ForegroundFieldTruth {
    /// The truth of a configuration drawn from `seed`.
    pub fn of(c: &ForegroundFieldConfig, seed: u64) -> ForegroundFieldTruth {
        let m = Polarization::from_p_gamma(c.p, c.angle_deg);
        ForegroundFieldTruth {
            q_mean: m.q,
            u_mean: m.u,
            p: c.p,
            angle_deg: c.angle_deg,
            rms: c.rms,
            coherence_arcsec: c.coherence_arcsec,
            structure_exponent: c.structure_exponent,
            modes: c.modes,
            seed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(rms: f64, coherence: f64, seed: u64) -> ForegroundField {
        ForegroundField::new(
            &ForegroundFieldConfig {
                p: 0.02,
                angle_deg: 30.0,
                rms,
                coherence_arcsec: coherence,
                structure_exponent: None,
                modes: 64,
                seed: None,
            },
            seed,
        )
    }

    /// Positions on a patch near (ra0, dec0) offset by (east, north) arcsec.
    fn at(f: &ForegroundField, east: f64, north: f64) -> Polarization {
        let (sep, pa) = (east.hypot(north), east.atan2(north).to_degrees());
        let (ra, dec) = offset_position(83.8, -5.4, sep, pa);
        f.at(ra, dec)
    }

    #[test]
    fn mean_and_rms_over_many_positions_match_the_configuration() {
        // 40 x 40 grid spaced 3 coherence scales (nearly independent samples), 4 seeds.
        let (rms, l) = (0.005, 20.0);
        let mean = Polarization::from_p_gamma(0.02, 30.0);
        let mut qs = Vec::new();
        let mut us = Vec::new();
        for seed in 0..4 {
            let f = field(rms, l, seed);
            for i in 0..40 {
                for j in 0..40 {
                    let p = at(&f, 3.0 * l * i as f64, 3.0 * l * j as f64);
                    qs.push(p.q - mean.q);
                    us.push(p.u - mean.u);
                }
            }
        }
        for v in [&qs, &us] {
            let n = v.len() as f64;
            let m = v.iter().sum::<f64>() / n;
            let s = (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / n).sqrt();
            // 6400 samples: the mean within 4 rms/sqrt(n) = 0.05 rms, the rms within 5 %.
            assert!(m.abs() < 0.05 * rms, "mean offset {m}");
            assert!((s / rms - 1.0).abs() < 0.05, "rms {s} vs {rms}");
        }
    }

    #[test]
    fn correlation_is_near_one_well_inside_and_near_zero_well_outside_the_coherence_scale() {
        let l = 30.0;
        let corr = |d: f64| {
            let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
            for seed in 0..8 {
                let f = field(0.004, l, seed);
                let m = f.mean();
                for i in 0..30 {
                    for j in 0..30 {
                        let (x, y) = (7.0 * l * i as f64, 7.0 * l * j as f64);
                        let a = at(&f, x, y);
                        let b = at(&f, x + d * 0.6, y + d * 0.8);
                        for (p, q) in [(a.q - m.q, b.q - m.q), (a.u - m.u, b.u - m.u)] {
                            sxy += p * q;
                            sxx += p * p;
                            syy += q * q;
                        }
                    }
                }
            }
            sxy / (sxx * syy).sqrt()
        };
        let near = corr(0.03 * l);
        assert!(near > 0.995, "correlation at 0.03 l: {near}");
        // The stated scale: exp(-1/2) = 0.607 at d = l (8 fields of 64 modes: +-0.05).
        let at_l = corr(l);
        assert!((at_l - (-0.5f64).exp()).abs() < 0.08, "correlation at l: {at_l}");
        let far = corr(20.0 * l);
        assert!(far.abs() < 0.08, "correlation at 20 l: {far}");
    }

    /// A power-law field's structure function against its expectation over the modes'
    /// draws, computed independently by quadrature: `D(d) = 2 rms^2 (1 - E[sinc(k d)])`, k
    /// of density ~ k^-(alpha + 1) between the outer and inner scales (an isotropic 3-D
    /// mode's cos(k . d) averages sinc(|k| |d|) over directions). And it grows as d^alpha
    /// inside the range (alpha = 1: about tenfold from d = l/100 to l/10).
    #[test]
    fn a_power_law_fields_structure_function_matches_its_quadrature() {
        let (rms, l, alpha) = (0.004, 300.0, 1.0);
        let expected = |d: f64| {
            let (lo, hi) = (
                1.0 / (l * RAD_PER_ARCSEC),
                1.0 / (l * INNER_SCALE_RATIO * RAD_PER_ARCSEC),
            );
            let n = 20_000;
            let (mut num, mut den) = (0.0, 0.0);
            for i in 0..n {
                // Midpoints in ln k: density in ln k is k^-alpha.
                let k = lo * (hi / lo).powf((i as f64 + 0.5) / n as f64);
                let w = k.powf(-alpha);
                let x = k * d * RAD_PER_ARCSEC;
                num += w * x.sin() / x;
                den += w;
            }
            2.0 * rms * rms * (1.0 - num / den)
        };
        let measured = |d: f64| {
            let mut s = 0.0;
            let mut n = 0usize;
            for seed in 0..200 {
                let f = ForegroundField::new(
                    &ForegroundFieldConfig {
                        p: 0.02,
                        angle_deg: 30.0,
                        rms,
                        coherence_arcsec: l,
                        structure_exponent: Some(alpha),
                        modes: 64,
                        seed: None,
                    },
                    seed,
                );
                for i in 0..10 {
                    let (x, y) = (3.0 * l * i as f64, 0.0);
                    let (a, b) = (at(&f, x, y), at(&f, x + d * 0.6, y + d * 0.8));
                    s += (a.q - b.q).powi(2) + (a.u - b.u).powi(2);
                    n += 2;
                }
            }
            s / n as f64
        };
        for d in [1.0, 10.0, 100.0, 1000.0] {
            let (m, e) = (measured(d), expected(d));
            // 4000 squared differences of a Gaussian field: about 2.2 % standard error; the
            // modes' sampling adds its own.
            assert!((m / e - 1.0).abs() < 0.12, "D({d}\") = {m:.3e}, expected {e:.3e}");
        }
        // Well inside the range (10 inner scales to 1/10 of the outer; quadrature 11.1).
        let ratio = expected(30.0) / expected(3.0);
        assert!((ratio - 10.0).abs() < 2.0, "d^alpha: {ratio}");
    }

    #[test]
    fn offset_position_is_the_great_circle_offset() {
        // Separation back from the unit vectors, and the direction east of north.
        for (ra, dec, sep, pa) in [
            (10.0, -30.0, 20.0, 0.0),
            (359.99, 60.0, 90.0, 90.0),
            (120.0, 0.0, 5.0, 225.0),
        ] {
            let (ra2, dec2) = offset_position(ra, dec, sep, pa);
            let (a, b) = (unit_vector(ra, dec), unit_vector(ra2, dec2));
            let chord = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            let ang = 2.0 * (chord / 2.0).asin() / RAD_PER_ARCSEC;
            assert!((ang - sep).abs() < 1e-6, "{ang} vs {sep}");
            let east = (ra2 - ra + 180.0).rem_euclid(360.0) - 180.0;
            let e = east * 3600.0 * dec.to_radians().cos();
            let n = (dec2 - dec) * 3600.0;
            assert!(
                (e - sep * pa.to_radians().sin()).abs() < 1e-3 * sep.max(1.0),
                "east {e}"
            );
            assert!(
                (n - sep * pa.to_radians().cos()).abs() < 1e-3 * sep.max(1.0),
                "north {n}"
            );
        }
    }
}
