//! The polarization a bare metal mirror gives unpolarized light on reflection (Fresnel):
//! the physical size of the telescope's own polarization (the NTT's tertiary mirror reflects
//! at 45 deg).
//!
//! For a mirror of complex refractive index `N = n + i k` and incidence angle `theta`, with
//! `w = sqrt(N^2 - sin^2 theta)`:
//!
//! ```text
//! r_s = (cos theta - w) / (cos theta + w)            R_s = |r_s|^2
//! r_p = (N^2 cos theta - w) / (N^2 cos theta + w)    R_p = |r_p|^2
//! p   = (R_s - R_p) / (R_s + R_p)
//! ```
//!
//! `p > 0`: the reflected light is polarized perpendicular to the plane of incidence (the
//! s direction). At 45 deg `R_p = R_s^2` for any `N` (Abeles), so `p = (1 - R_s)/(1 + R_s)`:
//! the better the mirror reflects, the less it polarizes. For aluminium (Rakic 1995) this
//! gives 4.1 % at 0.90 um (Z), 1.2 % in J, 0.86 % in H and 0.77 % in Ks.

/// A complex number, as far as the Fresnel equations need one.
#[derive(Debug, Clone, Copy, PartialEq)]
struct C {
    re: f64,
    im: f64,
}

impl C {
    fn new(re: f64, im: f64) -> C {
        C { re, im }
    }
    fn add(self, o: C) -> C {
        C::new(self.re + o.re, self.im + o.im)
    }
    fn sub(self, o: C) -> C {
        C::new(self.re - o.re, self.im - o.im)
    }
    fn mul(self, o: C) -> C {
        C::new(self.re * o.re - self.im * o.im, self.re * o.im + self.im * o.re)
    }
    fn scale(self, s: f64) -> C {
        C::new(self.re * s, self.im * s)
    }
    fn norm2(self) -> f64 {
        self.re * self.re + self.im * self.im
    }
    /// The principal square root (real part >= 0), without cancellation: the larger of
    /// the two parts from `(|z| + |re|)/2`, the other from `im / 2` divided by it.
    fn sqrt(self) -> C {
        let m = self.norm2().sqrt();
        if m == 0.0 {
            return C::new(0.0, 0.0);
        }
        let t = ((m + self.re.abs()) / 2.0).sqrt();
        if self.re >= 0.0 {
            C::new(t, self.im / (2.0 * t))
        } else {
            C::new(self.im.abs() / (2.0 * t), t.copysign(self.im))
        }
    }
}

/// `|a / b|^2`.
fn ratio_norm2(a: C, b: C) -> f64 {
    a.norm2() / b.norm2()
}

/// The reflectances (R_s, R_p) of a mirror of refractive index `n + i k` at incidence
/// `incidence_deg` (from the normal).
pub fn reflectances(n: f64, k: f64, incidence_deg: f64) -> (f64, f64) {
    let th = incidence_deg.to_radians();
    let (s, c) = th.sin_cos();
    let big_n = C::new(n, k);
    let n2 = big_n.mul(big_n);
    let w = n2.sub(C::new(s * s, 0.0)).sqrt();
    let cos = C::new(c, 0.0);
    let rs = ratio_norm2(cos.sub(w), cos.add(w));
    let n2c = n2.scale(c);
    let rp = ratio_norm2(n2c.sub(w), n2c.add(w));
    (rs, rp)
}

/// The degree of linear polarization `(R_s - R_p)/(R_s + R_p)` that one reflection gives
/// unpolarized light, perpendicular to the plane of incidence when positive.
pub fn mirror_polarization(n: f64, k: f64, incidence_deg: f64) -> f64 {
    let (rs, rp) = reflectances(n, k, incidence_deg);
    (rs - rp) / (rs + rp)
}

/// What the profile's mirror says the telescope's term `(a, b) = p_tel (cos 2psi_tel,
/// sin 2psi_tel)` is in one filter, before any standard is looked at: a Gaussian of mean
/// `p (cos 2psi, sin 2psi)` with `p` the Fresnel value, a relative width along that
/// direction and the angle's width across it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TelescopePrior {
    /// p_tel from the Fresnel equations, fraction.
    pub p_tel: f64,
    /// Its 1-sigma uncertainty, fraction.
    pub sigma_p_tel: f64,
    /// psi_tel, deg (the mirror's plane of incidence).
    pub psi_tel_deg: f64,
    /// Its 1-sigma uncertainty, deg.
    pub sigma_psi_tel_deg: f64,
}

impl TelescopePrior {
    /// The prior of `filter` from the profile's mirror; `None` when the profile gives no
    /// refractive index for that filter.
    pub fn of(telescope: &sofipol_calib::profile::Telescope, filter: &str) -> Option<TelescopePrior> {
        let i = telescope.index(filter)?;
        let p = mirror_polarization(i.n, i.k, telescope.incidence_deg);
        Some(TelescopePrior {
            p_tel: p,
            sigma_p_tel: telescope.relative_width * p,
            psi_tel_deg: telescope.psi_deg,
            sigma_psi_tel_deg: telescope.sigma_psi_deg,
        })
    }

    /// The unit vectors along and across the mean direction in the (a, b) plane.
    fn axes(&self) -> ([f64; 2], [f64; 2]) {
        let t = 2.0 * self.psi_tel_deg.to_radians();
        ([t.cos(), t.sin()], [-t.sin(), t.cos()])
    }

    /// The 1-sigma widths along and across the mean direction: `sigma_p` and `p 2 sigma_psi`
    /// (the angle of (a, b) is 2 psi).
    fn widths(&self) -> [f64; 2] {
        [
            self.sigma_p_tel.max(1e-12),
            (self.p_tel * 2.0 * self.sigma_psi_tel_deg.to_radians()).max(1e-12),
        ]
    }

    /// The mean `(a, b)`.
    pub fn mean(&self) -> [f64; 2] {
        let (along, _) = self.axes();
        [self.p_tel * along[0], self.p_tel * along[1]]
    }

    /// The prior's two independent rows: for `v = (a, b)`, `(value - u . v) / sigma` with
    /// `(u / sigma, value / sigma)` returned (the residual is `value/sigma - (u/sigma) . v`).
    pub fn rows(&self) -> [([f64; 2], f64); 2] {
        let (along, across) = self.axes();
        let [s_along, s_across] = self.widths();
        [
            ([along[0] / s_along, along[1] / s_along], self.p_tel / s_along),
            ([across[0] / s_across, across[1] / s_across], 0.0),
        ]
    }

    /// The covariance of `(a, b)`.
    pub fn covariance(&self) -> [[f64; 2]; 2] {
        let (along, across) = self.axes();
        let [s1, s2] = self.widths();
        std::array::from_fn(|i| {
            std::array::from_fn(|j| s1 * s1 * along[i] * along[j] + s2 * s2 * across[i] * across[j])
        })
    }

    /// The mean square of `(a, b)` about zero, `m m^T + covariance`: the error of a q, u
    /// from which the term was not removed.
    pub fn second_moment(&self) -> [[f64; 2]; 2] {
        let m = self.mean();
        let c = self.covariance();
        std::array::from_fn(|i| std::array::from_fn(|j| m[i] * m[j] + c[i][j]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_prior_of_ks_is_the_fresnel_value_along_the_profiles_angle_with_its_widths() {
        let prof = sofipol_calib::Profile::sofi();
        let p = TelescopePrior::of(&prof.telescope, " ks ").unwrap();
        assert!((p.p_tel - mirror_polarization(2.661, 21.878, 45.0)).abs() < 1e-15);
        assert!((p.p_tel - 0.0077).abs() < 0.0002, "{}", p.p_tel);
        assert!((p.sigma_p_tel - 0.2 * p.p_tel).abs() < 1e-15);
        assert!(TelescopePrior::of(&prof.telescope, "NB_2.17").is_none());
        // At psi = 30 deg: (a, b) along 60 deg; the variance along it is sigma_p^2, across
        // it (p 2 sigma_psi)^2; the rows reproduce the inverse covariance.
        let q = TelescopePrior { psi_tel_deg: 30.0, ..p };
        let m = q.mean();
        assert!((m[1].atan2(m[0]).to_degrees() - 60.0).abs() < 1e-9);
        let c = q.covariance();
        let along = [60f64.to_radians().cos(), 60f64.to_radians().sin()];
        let var_along: f64 = (0..2)
            .map(|i| (0..2).map(|j| along[i] * c[i][j] * along[j]).sum::<f64>())
            .sum();
        assert!((var_along - q.sigma_p_tel.powi(2)).abs() < 1e-18);
        let across = [-along[1], along[0]];
        let var_across: f64 = (0..2)
            .map(|i| (0..2).map(|j| across[i] * c[i][j] * across[j]).sum::<f64>())
            .sum();
        assert!((var_across - (q.p_tel * 2.0 * 5f64.to_radians()).powi(2)).abs() < 1e-18);
        // sum of row row^T = the inverse covariance.
        let rows = q.rows();
        let info: [[f64; 2]; 2] =
            std::array::from_fn(|i| std::array::from_fn(|j| rows.iter().map(|(u, _)| u[i] * u[j]).sum()));
        let prod: [[f64; 2]; 2] =
            std::array::from_fn(|i| std::array::from_fn(|j| (0..2).map(|k| info[i][k] * c[k][j]).sum()));
        for (i, row) in prod.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                assert!((v - f64::from(u8::from(i == j))).abs() < 1e-9, "{prod:?}");
            }
        }
        // The residuals vanish at the mean.
        for (u, v) in rows {
            assert!((v - (u[0] * m[0] + u[1] * m[1])).abs() < 1e-9);
        }
        let s = q.second_moment();
        assert!((s[0][0] + s[1][1] - (q.p_tel.powi(2) + c[0][0] + c[1][1])).abs() < 1e-18);
    }

    #[test]
    fn a_dielectric_follows_the_textbook_values() {
        // Glass n = 1.5 at 45 deg: r_s = (cos - w)/(cos + w) with w = sqrt(2.25 - 0.5).
        let w = 1.75f64.sqrt();
        let c = 0.5f64.sqrt();
        let rs = ((c - w) / (c + w)).powi(2);
        let rp = ((2.25 * c - w) / (2.25 * c + w)).powi(2);
        let (s, p) = reflectances(1.5, 0.0, 45.0);
        assert!((s - rs).abs() < 1e-15 && (p - rp).abs() < 1e-15, "{s} {p}");
        // At Brewster's angle p-light is not reflected: fully polarized.
        let brewster = 1.5f64.atan().to_degrees();
        assert!(reflectances(1.5, 0.0, brewster).1 < 1e-30);
        assert!((mirror_polarization(1.5, 0.0, brewster) - 1.0).abs() < 1e-12);
        // At normal incidence s and p are the same: no polarization, R = ((n-1)/(n+1))^2.
        let (s, p) = reflectances(1.5, 0.0, 0.0);
        assert!((s - 0.04).abs() < 1e-15 && (p - 0.04).abs() < 1e-15);
    }

    #[test]
    fn at_45_degrees_r_p_is_r_s_squared_for_any_metal() {
        for (n, k) in [
            (2.113, 8.218),
            (1.325, 12.314),
            (2.661, 21.878),
            (0.05, 3.0),
            (0.2, 0.01),
        ] {
            let (rs, rp) = reflectances(n, k, 45.0);
            assert!((rp - rs * rs).abs() < 1e-13, "n {n} k {k}: {rp} vs {}", rs * rs);
            let p = mirror_polarization(n, k, 45.0);
            assert!((p - (1.0 - rs) / (1.0 + rs)).abs() < 1e-13);
            assert!(p > 0.0 && p < 1.0);
        }
    }

    #[test]
    fn a_perfect_conductor_does_not_polarize_and_the_square_root_is_principal() {
        assert!(mirror_polarization(0.0, 1e8, 45.0).abs() < 1e-7);
        for (re, im) in [
            (4.0, 0.0),
            (-4.0, 0.0),
            (-4.0, 1e-300),
            (3.0, 4.0),
            (-3.0, -4.0),
            (-1e-20, 1.0),
        ] {
            let r = C::new(re, im).sqrt();
            let back = r.mul(r);
            assert!(r.re >= 0.0, "{re} {im}: {r:?}");
            assert!(
                (back.re - re).abs() < 1e-12 && (back.im - im).abs() < 1e-12,
                "{re} {im}: {back:?}"
            );
        }
    }
}
