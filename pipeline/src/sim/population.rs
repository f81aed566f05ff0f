//! Field stars drawn from a K-band luminosity function (scene section `field_population`).
//!
//! Per binary, the number of stars between `k_min_mag` and `k_max_mag` is Poisson with mean
//! `density_per_arcmin2 x area x (10^(s (k_max - k_ref)) - 10^(s (k_min - k_ref)))`, s the
//! slope of log10 N(<K), over the area the three o strips see (detector width x the
//! strips' heights, at the first rotator angle and zero dither offset). Each star's K is
//! drawn from the truncated cumulative law by inversion,
//! `K = k_min + log10(1 + x (10^(s (k_max - k_min)) - 1)) / s`, x uniform; its position is
//! uniform over that area (a star within `exclude_arcsec` of A or B is dropped, so the
//! density stays uniform elsewhere); its flux is `dit_s 10^(-0.4 (K - zero_point_mag))`
//! ADU; a fraction `polarized_fraction` is intrinsically polarized, P uniform in
//! `p_polarized`, angle uniform in [0, 180), the others have P = 0. Draws come from their
//! own stream of the scene seed and the binary's index.
use rand::RngExt;
use rand_distr::{Distribution, Poisson};
use sofipol_calib::profile::Geometry;

use super::scene::{flux_of_magnitude, FieldPopulationConfig, FieldStar};
use crate::numeric::splitmix64;
use crate::stokes::model::offset_to_sep_pa;

/// The cumulative distribution of K between `k_min_mag` and `k_max_mag`:
/// `(10^(s (K - k_min)) - 1) / (10^(s (k_max - k_min)) - 1)`.
pub fn k_cdf(c: &FieldPopulationConfig, k: f64) -> f64 {
    let s = c.slope_dex_per_mag;
    let k = k.clamp(c.k_min_mag, c.k_max_mag);
    (10f64.powf(s * (k - c.k_min_mag)) - 1.0) / (10f64.powf(s * (c.k_max_mag - c.k_min_mag)) - 1.0)
}

/// The area the o strips see, arcmin^2.
pub fn area_arcmin2(g: &Geometry) -> f64 {
    let rows: usize = o_strips(g).iter().map(|r| r[1].saturating_sub(r[0])).sum();
    g.nx as f64 * rows as f64 * g.pixscale_arcsec.powi(2) / 3600.0
}

/// Expected stars per binary (before the exclusion around A and B).
pub fn expected_count(c: &FieldPopulationConfig, g: &Geometry) -> f64 {
    let s = c.slope_dex_per_mag;
    c.density_per_arcmin2
        * area_arcmin2(g)
        * (10f64.powf(s * (c.k_max_mag - c.k_ref_mag)) - 10f64.powf(s * (c.k_min_mag - c.k_ref_mag)))
}

/// The rows whose sky the o images see: the o strips, or every row without a focal mask.
fn o_strips(g: &Geometry) -> Vec<[usize; 2]> {
    if !g.has_mask() {
        return vec![[0, g.ny]];
    }
    g.strips()
        .into_iter()
        .filter(|(n, r)| n.starts_with("o_") && r[1] > r[0])
        .map(|(_, r)| r)
        .collect()
}

/// A drawn field star: the scene's field star and its K magnitude.
#[derive(Debug, Clone)]
pub struct DrawnStar {
    /// Position, flux and polarization as a scene field star.
    pub star: FieldStar,
    /// K magnitude.
    pub k_mag: f64,
}

/// Where the binary is: A's o image (x, y) at zero offset, B's offset from A at the first
/// rotator angle (px), the rotator angle, the pixel scale.
pub struct Frame0 {
    /// A's o image, px.
    pub a_xy: [f64; 2],
    /// B's offset from A, px.
    pub b_off: [f64; 2],
    /// First rotator angle, deg.
    pub posang_deg: f64,
}

/// Draw binary `t`'s field stars (deterministic from `seed` and `t`).
pub fn draw(
    c: &FieldPopulationConfig,
    zero_point_mag: f64,
    dit_s: f64,
    g: &Geometry,
    at: &Frame0,
    seed: u64,
    t: u64,
) -> Vec<DrawnStar> {
    let mut r = {
        use rand::SeedableRng;
        let h = splitmix64(splitmix64(seed ^ 0x4649_454C_4453) ^ t); // "FIELDS"
        rand::rngs::Xoshiro256PlusPlus::seed_from_u64(h)
    };
    let lambda = expected_count(c, g);
    let n = if lambda > 0.0 {
        Poisson::new(lambda).map(|p| p.sample(&mut r) as usize).unwrap_or(0)
    } else {
        0
    };
    let strips = o_strips(g);
    let heights: Vec<f64> = strips.iter().map(|s| (s[1] - s[0]) as f64).collect();
    let total: f64 = heights.iter().sum();
    let s = c.slope_dex_per_mag;
    let span = 10f64.powf(s * (c.k_max_mag - c.k_min_mag)) - 1.0;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        // Every draw is made for every star (dropped ones too): the stream stays aligned.
        let x = g.nx as f64 * r.random::<f64>();
        let mut h = total * r.random::<f64>();
        let mut y = 0.0;
        for (st, hh) in strips.iter().zip(&heights) {
            if h < *hh {
                y = st[0] as f64 + h;
                break;
            }
            h -= hh;
        }
        // Pixel centres at integers: row y0 spans [y0 - 0.5, y0 + 0.5).
        y -= 0.5;
        let k = c.k_min_mag + (1.0 + r.random::<f64>() * span).log10() / s;
        let polarized = r.random::<f64>() < c.polarized_fraction;
        let p = c.p_polarized[0] + (c.p_polarized[1] - c.p_polarized[0]) * r.random::<f64>();
        let gamma = 180.0 * r.random::<f64>();
        let (dx, dy) = (x - 0.5 - at.a_xy[0], y - at.a_xy[1]);
        let scale = g.pixscale_arcsec;
        let near = |ox: f64, oy: f64| (dx - ox).hypot(dy - oy) * scale < c.exclude_arcsec;
        if near(0.0, 0.0) || near(at.b_off[0], at.b_off[1]) {
            continue;
        }
        // Without a focal mask a star's e image can land on A's or B's o image and its o
        // image on their e images (offset d = the e-o offset). The sky turns about A with
        // the rotator while d stays fixed on the detector, so at some rotator angle it does
        // when the star's distance from A or from B is within `exclude_arcsec` of |d|: no
        // star there.
        let d = g.eo_offset_px[0].hypot(g.eo_offset_px[1]);
        let ring = |ox: f64, oy: f64| ((dx - ox).hypot(dy - oy) - d).abs() * scale < c.exclude_arcsec;
        if !g.has_mask() && (ring(0.0, 0.0) || ring(at.b_off[0], at.b_off[1])) {
            continue;
        }
        let (sep, pa) = offset_to_sep_pa(dx, dy, at.posang_deg, scale);
        out.push(DrawnStar {
            star: FieldStar {
                separation_arcsec: sep,
                pa_deg: pa,
                flux: flux_of_magnitude(k, zero_point_mag, dit_s),
                p: if polarized { p } else { 0.0 },
                gamma_deg: if polarized { gamma } else { 0.0 },
            },
            k_mag: k,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdf_is_zero_at_the_bright_end_one_at_the_faint_end_and_follows_the_slope() {
        let c = FieldPopulationConfig::default();
        assert_eq!(k_cdf(&c, c.k_min_mag), 0.0);
        assert!((k_cdf(&c, c.k_max_mag) - 1.0).abs() < 1e-15);
        // N(<K) grows by 10^slope per magnitude.
        let n = |k: f64| k_cdf(&c, k) + 1.0 / (10f64.powf(c.slope_dex_per_mag * (c.k_max_mag - c.k_min_mag)) - 1.0);
        assert!((n(15.0) / n(14.0) - 10f64.powf(c.slope_dex_per_mag)).abs() < 1e-12);
    }
}
