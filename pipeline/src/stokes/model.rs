//! The forward model of a dual-beam rotating-instrument polarimeter.
//!
//! One model, used by the scene simulator to make frames and by the tests of the
//! inversion to check that the pipeline undoes exactly what the instrument does
//! (docs/conventions.md, "Angles"; docs/polarimetry.md).
//!
//! * Analyzer angle `phi = s * POSANG + theta0` (profile `angles`).
//! * Beam fluxes for sky-frame Stokes `I, Q, U` (Q, U referred to north, angles east of north):
//!   `f_o = (T_o/2) (I + Q cos 2phi + U sin 2phi)`, `f_e = (T_e/2) (I - Q cos 2phi - U sin 2phi)`.
//! * Normalised difference `F = (f_o - f_e)/(f_o + f_e) = q cos 2phi + u sin 2phi` when `T_o = T_e`.
//! * A companion at separation `rho` (arcsec) and PA `psi` from the primary lies at detector
//!   offset `dx = -rho sin(psi - theta)/scale`, `dy = rho cos(psi - theta)/scale` at POSANG theta.

/// Normalised Stokes parameters of a source (sky frame).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Polarization {
    /// q = Q/I.
    pub q: f64,
    /// u = U/I.
    pub u: f64,
}

impl Polarization {
    /// From degree `p` (fraction, not percent) and angle `gamma_deg` (east of north).
    pub fn from_p_gamma(p: f64, gamma_deg: f64) -> Self {
        let two_g = 2.0 * gamma_deg.to_radians();
        Polarization {
            q: p * two_g.cos(),
            u: p * two_g.sin(),
        }
    }
    /// Degree of linear polarization.
    pub fn p(&self) -> f64 {
        self.q.hypot(self.u)
    }
    /// Angle east of north, degrees in [0, 180). Uses atan2, never atan(u/q).
    pub fn gamma_deg(&self) -> f64 {
        normalize_axial_deg(0.5 * self.u.atan2(self.q).to_degrees())
    }
    /// Sum of two polarizations (valid for the small degrees of the NIR regime; exact
    /// for Stokes parameters of light passing through a weak polarizer to first order).
    #[allow(clippy::should_implement_trait)] // by name: a first-order sum, not an exact one
    pub fn add(self, other: Polarization) -> Polarization {
        Polarization {
            q: self.q + other.q,
            u: self.u + other.u,
        }
    }
}

/// The polarization the telescope itself adds (the NTT's tertiary mirror M3, in front of the
/// rotator): fixed relative to the mirror's plane of incidence, which on the sky is the local
/// vertical, so in the sky frame it turns with the parallactic angle eta:
/// `(q_tel, u_tel) = p_tel (cos 2(eta + psi_tel), sin 2(eta + psi_tel))`
/// (docs/frame-format.md, "Polarization of the telescope itself").
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct TelescopePolarization {
    /// p_tel, fraction.
    pub p_tel: f64,
    /// psi_tel, deg: the angle of the telescope's polarization from the vertical.
    pub psi_tel_deg: f64,
}

impl TelescopePolarization {
    /// Sky-frame (q_tel, u_tel) at parallactic angle `eta_deg`.
    pub fn at(&self, eta_deg: f64) -> Polarization {
        Polarization::from_p_gamma(self.p_tel, eta_deg + self.psi_tel_deg)
    }
    /// The vertical-frame components `(a, b) = p_tel (cos 2psi_tel, sin 2psi_tel)`, in which
    /// the model is linear: `q_tel = a cos 2eta - b sin 2eta`, `u_tel = a sin 2eta + b cos 2eta`.
    pub fn ab(&self) -> [f64; 2] {
        let t = 2.0 * self.psi_tel_deg.to_radians();
        [self.p_tel * t.cos(), self.p_tel * t.sin()]
    }
}

/// Map an axial angle (degrees) into [0, 180).
pub fn normalize_axial_deg(a: f64) -> f64 {
    let r = a.rem_euclid(180.0);
    if r >= 180.0 {
        0.0
    } else {
        r
    }
}

/// Normalised difference F(phi) = q cos 2phi + u sin 2phi.
pub fn normalized_difference(pol: Polarization, phi_deg: f64) -> f64 {
    let t = 2.0 * phi_deg.to_radians();
    pol.q * t.cos() + pol.u * t.sin()
}

/// The error of F = (o - e)/(o + e) from the fluxes' variances and covariance (first
/// order): dF/do = 2e/(o + e)^2, dF/de = -2o/(o + e)^2, so a positive covariance (a common
/// error of both beams, e.g. the PSF shape's in a joint fit) lowers it.
pub fn f_error(o: f64, e: f64, var_o: f64, var_e: f64, cov_oe: f64) -> f64 {
    let tot2 = (o + e).powi(2);
    let (dfo, dfe) = (2.0 * e / tot2, -2.0 * o / tot2);
    (dfo * dfo * var_o + dfe * dfe * var_e + 2.0 * dfo * dfe * cov_oe).sqrt()
}

/// Ordinary and extraordinary beam fluxes of a source of total intensity `i`
/// (any flux unit), at analyzer angle `phi_deg`, with beam transmissions `t_o`, `t_e`.
pub fn beam_fluxes(i: f64, pol: Polarization, phi_deg: f64, t_o: f64, t_e: f64) -> (f64, f64) {
    let f = normalized_difference(pol, phi_deg);
    (0.5 * t_o * i * (1.0 + f), 0.5 * t_e * i * (1.0 - f))
}

/// Detector offset (dx, dy) in pixels of a companion at separation `sep_arcsec` and
/// position angle `pa_deg` from the primary, at rotator position angle `posang_deg`.
pub fn companion_offset_px(sep_arcsec: f64, pa_deg: f64, posang_deg: f64, scale_arcsec_per_px: f64) -> (f64, f64) {
    let d = (pa_deg - posang_deg).to_radians();
    (
        -sep_arcsec * d.sin() / scale_arcsec_per_px,
        sep_arcsec * d.cos() / scale_arcsec_per_px,
    )
}

/// Inverse of [`companion_offset_px`]: separation (arcsec) and PA (degrees, [0, 360)).
pub fn offset_to_sep_pa(dx_px: f64, dy_px: f64, posang_deg: f64, scale_arcsec_per_px: f64) -> (f64, f64) {
    let sep = dx_px.hypot(dy_px) * scale_arcsec_per_px;
    let pa = ((-dx_px).atan2(dy_px).to_degrees() + posang_deg).rem_euclid(360.0);
    (sep, pa)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn o_plus_e_is_i_and_difference_is_f() {
        let pol = Polarization::from_p_gamma(0.07, 33.0);
        for phi in [0.0, 22.5, 45.0, 90.0, 135.0, 200.0] {
            let (o, e) = beam_fluxes(1234.5, pol, phi, 1.0, 1.0);
            assert!((o + e - 1234.5).abs() < 1e-9);
            let f = (o - e) / (o + e);
            let t = 2.0 * f64::to_radians(phi);
            assert!((f - (pol.q * t.cos() + pol.u * t.sin())).abs() < 1e-15);
        }
    }

    #[test]
    fn telescope_polarization_turns_with_the_parallactic_angle() {
        let t = TelescopePolarization {
            p_tel: 0.006,
            psi_tel_deg: 20.0,
        };
        // At eta = 0 its angle on the sky is psi_tel; it turns one for one with eta.
        assert!((t.at(0.0).gamma_deg() - 20.0).abs() < 1e-9);
        assert!((t.at(30.0).gamma_deg() - 50.0).abs() < 1e-9);
        assert!((t.at(-60.0).gamma_deg() - 140.0).abs() < 1e-9);
        // An axial quantity: eta and eta + 180 give the same polarization.
        let (a, b) = (t.at(-157.0), t.at(23.0));
        assert!((a.q - b.q).abs() < 1e-15 && (a.u - b.u).abs() < 1e-15);
        // The linear form in (a, b).
        let [ca, cb] = t.ab();
        for eta in [-170.0, -45.0, 0.0, 12.5, 99.0] {
            let e = 2.0 * f64::to_radians(eta);
            let p = t.at(eta);
            assert!((p.q - (ca * e.cos() - cb * e.sin())).abs() < 1e-15);
            assert!((p.u - (ca * e.sin() + cb * e.cos())).abs() < 1e-15);
            assert!((p.p() - 0.006).abs() < 1e-15);
        }
    }

    #[test]
    fn angle_conventions() {
        // gamma from (q, u) in all four quadrants, [0, 180).
        for g in [0.0, 10.0, 44.9, 45.0, 90.0, 135.0, 179.0] {
            let p = Polarization::from_p_gamma(0.1, g);
            assert!((p.gamma_deg() - g).abs() < 1e-9, "{g} -> {}", p.gamma_deg());
        }
        // At POSANG 0, north is +y and east is -x.
        let (dx, dy) = companion_offset_px(2.88, 0.0, 0.0, 0.288);
        assert!((dx - 0.0).abs() < 1e-12 && (dy - 10.0).abs() < 1e-12);
        let (dx, dy) = companion_offset_px(2.88, 90.0, 0.0, 0.288);
        assert!((dx + 10.0).abs() < 1e-12 && dy.abs() < 1e-12);
        // At POSANG theta, detector +y points to PA theta.
        let (dx, dy) = companion_offset_px(2.88, 45.0, 45.0, 0.288);
        assert!(dx.abs() < 1e-12 && (dy - 10.0).abs() < 1e-12);
        let (sep, pa) = offset_to_sep_pa(-3.0, 4.0, 45.0, 0.288);
        let (dx, dy) = companion_offset_px(sep, pa, 45.0, 0.288);
        assert!((dx + 3.0).abs() < 1e-12 && (dy - 4.0).abs() < 1e-12);
    }
}
