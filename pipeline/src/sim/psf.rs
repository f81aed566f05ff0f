//! Point-spread functions rendered as pixel integrals, and the no-PSF point source.
use ndarray::Array2;

use super::scene::PsfKind;

/// A PSF shape for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Psf {
    /// Unresolved point (no `psf` effect): flux shared among the four nearest pixel
    /// centres with bilinear (cloud-in-cell) weights, so flux and centroid are exact.
    Point,
    /// Circular Gaussian of standard deviation `sigma_px`.
    Gaussian {
        /// sigma, px.
        sigma_px: f64,
    },
    /// Circular Moffat, I ~ (1 + r^2/alpha^2)^-beta, truncated at the radius enclosing
    /// 1 - 1e-5 of the flux (at most 60 px) and renormalised to unit sum.
    Moffat {
        /// alpha, px.
        alpha_px: f64,
        /// beta.
        beta: f64,
    },
    /// Elliptical Moffat: I ~ (1 + (ratio u^2 + v^2/ratio)/alpha^2)^-beta, u along the
    /// major axis (position angle `pa_deg` from +x towards +y), v across; the axes are
    /// alpha/sqrt(ratio) and alpha sqrt(ratio) (same area, same FWHM as geometric mean).
    /// Truncated on the ellipse enclosing 1 - 1e-5 of the flux and renormalised.
    EllipticalMoffat {
        /// alpha (geometric mean of the two axes), px.
        alpha_px: f64,
        /// beta.
        beta: f64,
        /// Minor/major axis ratio, (0, 1].
        ratio: f64,
        /// Major-axis angle from +x towards +y, deg.
        pa_deg: f64,
    },
}

impl Psf {
    /// Build from a family and a FWHM in pixels.
    pub fn from_fwhm(kind: PsfKind, fwhm_px: f64, beta: f64) -> Psf {
        match kind {
            PsfKind::Gaussian => Psf::Gaussian {
                sigma_px: fwhm_px / (2.0 * (2.0 * std::f64::consts::LN_2).sqrt()),
            },
            PsfKind::Moffat => Psf::Moffat {
                alpha_px: fwhm_px / (2.0 * (2f64.powf(1.0 / beta) - 1.0).sqrt()),
                beta,
            },
        }
    }

    /// The same PSF stretched along `pa_deg` to the minor/major axis ratio `ratio` (only
    /// a Moffat; a ratio of 1 leaves it circular and unchanged).
    pub fn with_ellipticity(self, ratio: f64, pa_deg: f64) -> Psf {
        match self {
            Psf::Moffat { alpha_px, beta } if ratio != 1.0 => Psf::EllipticalMoffat {
                alpha_px,
                beta,
                ratio,
                pa_deg,
            },
            p => p,
        }
    }

    /// Moffat beta (0 for other profiles).
    pub fn beta(&self) -> f64 {
        match *self {
            Psf::Moffat { beta, .. } | Psf::EllipticalMoffat { beta, .. } => beta,
            _ => 0.0,
        }
    }

    /// FWHM in pixels (0 for a point; geometric mean of the axes for an ellipse).
    pub fn fwhm_px(&self) -> f64 {
        match *self {
            Psf::Point => 0.0,
            Psf::Gaussian { sigma_px } => sigma_px * 2.0 * (2.0 * std::f64::consts::LN_2).sqrt(),
            Psf::Moffat { alpha_px, beta } | Psf::EllipticalMoffat { alpha_px, beta, .. } => {
                2.0 * alpha_px * (2f64.powf(1.0 / beta) - 1.0).sqrt()
            }
        }
    }

    /// Half-size of the rendered stamp, px: a Moffat is truncated at the radius beyond
    /// which the fraction `tail` of its flux lies ([`MOFFAT_TAIL`] but for faint field
    /// stars, [`render_with_tail`]).
    fn half_size(&self, tail: f64) -> usize {
        match *self {
            Psf::Point => 1,
            Psf::Gaussian { sigma_px } => (8.0 * sigma_px).ceil() as usize + 1,
            Psf::Moffat { alpha_px, beta } => {
                // 1 - (1 + R^2/a^2)^(1-beta) = 1 - tail
                let x = tail.powf(1.0 / (1.0 - beta)) - 1.0;
                ((alpha_px * x.max(0.0).sqrt()).ceil() as usize + 1).min(60)
            }
            Psf::EllipticalMoffat {
                alpha_px, beta, ratio, ..
            } => {
                let x = tail.powf(1.0 / (1.0 - beta)) - 1.0;
                ((alpha_px * x.max(0.0).sqrt() / ratio.sqrt()).ceil() as usize + 1).min(60)
            }
        }
    }
}

/// Standard normal CDF via statrs' erf.
fn phi(x: f64) -> f64 {
    0.5 * (1.0 + statrs::function::erf::erf(x / std::f64::consts::SQRT_2))
}

use crate::numeric::{GL2_W, GL2_X, GL4_W, GL4_X};

/// A unit-sum stamp: `values[[j, i]]` is the fraction of the flux falling in pixel
/// `(x0 + i, y0 + j)`.
#[derive(Debug, Clone)]
pub struct Stamp {
    /// Column of values[[_, 0]].
    pub x0: i64,
    /// Row of values[[0, _]].
    pub y0: i64,
    /// Flux fractions, unit sum.
    pub values: Array2<f64>,
}

/// Fraction of a Moffat's flux beyond its truncation radius (before renormalising).
pub const MOFFAT_TAIL: f64 = 1e-5;

/// Render a unit-flux PSF centred at (cx, cy) (pixel centres at integers).
pub fn render(psf: Psf, cx: f64, cy: f64) -> Stamp {
    render_with_tail(psf, cx, cy, MOFFAT_TAIL)
}

/// [`render`] with a Moffat truncated where the fraction `tail` of the flux lies beyond
/// (at least [`MOFFAT_TAIL`]): the field stars of a `field_population` are rendered with
/// `tail = 0.5 ADU / flux`, so a faint star's stamp stops where its wing holds half an
/// ADU in all (renormalised: its flux is unchanged), far below the sky noise of a pixel.
pub fn render_with_tail(psf: Psf, cx: f64, cy: f64, tail: f64) -> Stamp {
    let tail = tail.max(MOFFAT_TAIL);
    match psf {
        Psf::Point => {
            let ix = cx.floor();
            let iy = cy.floor();
            let fx = cx - ix;
            let fy = cy - iy;
            let mut v = Array2::zeros((2, 2));
            v[[0, 0]] = (1.0 - fx) * (1.0 - fy);
            v[[0, 1]] = fx * (1.0 - fy);
            v[[1, 0]] = (1.0 - fx) * fy;
            v[[1, 1]] = fx * fy;
            Stamp {
                x0: ix as i64,
                y0: iy as i64,
                values: v,
            }
        }
        Psf::Gaussian { sigma_px } => {
            let h = psf.half_size(tail) as i64;
            let x0 = cx.round() as i64 - h;
            let y0 = cy.round() as i64 - h;
            let n = (2 * h + 1) as usize;
            let prof = |c: f64, start: i64| -> Vec<f64> {
                (0..n)
                    .map(|i| {
                        let p = (start + i as i64) as f64;
                        phi((p + 0.5 - c) / sigma_px) - phi((p - 0.5 - c) / sigma_px)
                    })
                    .collect()
            };
            let px = prof(cx, x0);
            let py = prof(cy, y0);
            let sx: f64 = px.iter().sum();
            let sy: f64 = py.iter().sum();
            let v = Array2::from_shape_fn((n, n), |(j, i)| py[j] / sy * px[i] / sx);
            Stamp { x0, y0, values: v }
        }
        Psf::Moffat { alpha_px, beta } => {
            let h = psf.half_size(tail) as i64;
            let x0 = cx.round() as i64 - h;
            let y0 = cy.round() as i64 - h;
            let n = (2 * h + 1) as usize;
            let ia2 = 1.0 / (alpha_px * alpha_px);
            let r2max = ((h as f64) - 0.5).powi(2);
            let wing2 = (4.0 * alpha_px).powi(2);
            let mut v = Array2::from_shape_fn((n, n), |(j, i)| {
                let px = (x0 + i as i64) as f64 - cx;
                let py = (y0 + j as i64) as f64 - cy;
                let mut s = 0.0;
                // The wings are smooth: 2x2 Gauss-Legendre beyond 4 alpha, 4x4 inside.
                let (xs, ws): (&[f64], &[f64]) = if px * px + py * py > wing2 {
                    (&GL2_X, &GL2_W)
                } else {
                    (&GL4_X, &GL4_W)
                };
                for (a, wa) in xs.iter().zip(ws) {
                    for (b, wb) in xs.iter().zip(ws) {
                        let dx = px + a;
                        let dy = py + b;
                        let r2 = dx * dx + dy * dy;
                        if r2 <= r2max {
                            s += wa * wb * (-beta * (r2 * ia2).ln_1p()).exp();
                        }
                    }
                }
                s
            });
            let total: f64 = v.sum();
            v.mapv_inplace(|x| x / total);
            Stamp { x0, y0, values: v }
        }
        Psf::EllipticalMoffat {
            alpha_px,
            beta,
            ratio,
            pa_deg,
        } => {
            let h = psf.half_size(tail) as i64;
            let x0 = cx.round() as i64 - h;
            let y0 = cy.round() as i64 - h;
            let n = (2 * h + 1) as usize;
            let ia2 = 1.0 / (alpha_px * alpha_px);
            // The truncation ellipse: the circular profile's radius in the scaled metric,
            // which fits inside the stamp along the major axis.
            let r2max = (((h as f64) - 0.5) * ratio.sqrt()).powi(2);
            let wing2 = (4.0 * alpha_px).powi(2);
            let (sn, cs) = pa_deg.to_radians().sin_cos();
            let metric = |dx: f64, dy: f64| {
                let u = dx * cs + dy * sn;
                let w = -dx * sn + dy * cs;
                ratio * u * u + w * w / ratio
            };
            let mut v = Array2::from_shape_fn((n, n), |(j, i)| {
                let px = (x0 + i as i64) as f64 - cx;
                let py = (y0 + j as i64) as f64 - cy;
                let mut s = 0.0;
                let (xs, ws): (&[f64], &[f64]) = if metric(px, py) > wing2 {
                    (&GL2_X, &GL2_W)
                } else {
                    (&GL4_X, &GL4_W)
                };
                for (a, wa) in xs.iter().zip(ws) {
                    for (b, wb) in xs.iter().zip(ws) {
                        let r2 = metric(px + a, py + b);
                        if r2 <= r2max {
                            s += wa * wb * (-beta * (r2 * ia2).ln_1p()).exp();
                        }
                    }
                }
                s
            });
            let total: f64 = v.sum();
            v.mapv_inplace(|x| x / total);
            Stamp { x0, y0, values: v }
        }
    }
}

impl Stamp {
    /// The same stamp moved by a whole number of pixels.
    pub fn shifted(&self, dx: i64, dy: i64) -> Stamp {
        Stamp {
            x0: self.x0 + dx,
            y0: self.y0 + dy,
            values: self.values.clone(),
        }
    }
}

/// Add `flux * stamp` into `img` (pixels outside the image are dropped and returned as
/// the lost flux).
pub fn add_stamp(img: &mut Array2<f32>, stamp: &Stamp, flux: f64) -> f64 {
    add_stamp_rows(img, stamp, flux, |_| true)
}

/// [`add_stamp`] on the rows `open` admits only: the light on the other rows is lost (a
/// focal mask's bar). Returns the flux lost off the detector or on closed rows.
pub fn add_stamp_rows(img: &mut Array2<f32>, stamp: &Stamp, flux: f64, open: impl Fn(usize) -> bool) -> f64 {
    let (ny, nx) = img.dim();
    let mut lost = 0.0;
    for ((j, i), &v) in stamp.values.indexed_iter() {
        let x = stamp.x0 + i as i64;
        let y = stamp.y0 + j as i64;
        if x < 0 || y < 0 || x >= nx as i64 || y >= ny as i64 || !open(y as usize) {
            lost += flux * v;
            continue;
        }
        img[[y as usize, x as usize]] += (flux * v) as f32;
    }
    lost
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_larger_tail_gives_a_smaller_stamp_of_the_same_flux_and_profile() {
        let psf = Psf::from_fwhm(super::super::scene::PsfKind::Moffat, 2.8, 3.0);
        let full = render(psf, 100.3, 200.7);
        let cut = render_with_tail(psf, 100.3, 200.7, 1e-3);
        assert!(
            cut.values.len() * 3 < full.values.len(),
            "{} vs {}",
            cut.values.len(),
            full.values.len()
        );
        assert!((cut.values.sum() - 1.0).abs() < 1e-12);
        // Inside the smaller stamp the profile is the same up to the renormalisation.
        let (dx, dy) = ((cut.x0 - full.x0) as usize, (cut.y0 - full.y0) as usize);
        let c = cut.values[[cut.values.nrows() / 2, cut.values.ncols() / 2]]
            / full.values[[dy + cut.values.nrows() / 2, dx + cut.values.ncols() / 2]];
        assert!((c - 1.0).abs() < 2e-3 && c >= 1.0, "{c}");
        // A tail below the default changes nothing.
        assert_eq!(render_with_tail(psf, 100.3, 200.7, 1e-9).values, full.values);
    }

    fn moments(s: &Stamp) -> (f64, f64, f64) {
        let mut t = 0.0;
        let mut mx = 0.0;
        let mut my = 0.0;
        for ((j, i), &v) in s.values.indexed_iter() {
            t += v;
            mx += v * (s.x0 + i as i64) as f64;
            my += v * (s.y0 + j as i64) as f64;
        }
        (t, mx / t, my / t)
    }

    #[test]
    fn every_psf_has_unit_flux_and_the_right_centroid() {
        for psf in [
            Psf::Point,
            Psf::from_fwhm(PsfKind::Gaussian, 2.8, 0.0),
            Psf::from_fwhm(PsfKind::Moffat, 2.8, 3.0),
            Psf::from_fwhm(PsfKind::Moffat, 4.0, 2.5),
        ] {
            for (cx, cy) in [(100.0, 100.0), (100.3, 99.71), (50.5, 20.5)] {
                let s = render(psf, cx, cy);
                let (t, mx, my) = moments(&s);
                assert!((t - 1.0).abs() < 1e-12, "{psf:?} sum {t}");
                // The Moffat truncation circle is sampled at quadrature nodes: a few 1e-6 px.
                assert!(
                    (mx - cx).abs() < 2e-5 && (my - cy).abs() < 2e-5,
                    "{psf:?} centroid {mx} {my}"
                );
            }
        }
    }

    /// Second moments of a stamp about its centroid: (Ixx, Iyy, Ixy).
    fn second_moments(s: &Stamp) -> (f64, f64, f64) {
        let (t, mx, my) = moments(s);
        let (mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0);
        for ((j, i), &v) in s.values.indexed_iter() {
            let dx = (s.x0 + i as i64) as f64 - mx;
            let dy = (s.y0 + j as i64) as f64 - my;
            xx += v * dx * dx;
            yy += v * dy * dy;
            xy += v * dx * dy;
        }
        (xx / t, yy / t, xy / t)
    }

    #[test]
    fn an_elliptical_moffat_has_unit_flux_its_centroid_and_its_axes() {
        let base = Psf::from_fwhm(PsfKind::Moffat, 3.0, 3.5);
        // A ratio of 1 is the circular Moffat itself.
        assert_eq!(base.with_ellipticity(1.0, 30.0), base);
        for (ratio, pa) in [(0.9, 0.0), (0.8, 90.0), (0.7, 30.0), (0.95, 137.0)] {
            let p = base.with_ellipticity(ratio, pa);
            assert!((p.fwhm_px() - 3.0).abs() < 1e-12);
            let s = render(p, 100.3, 99.6);
            let (t, mx, my) = moments(&s);
            assert!((t - 1.0).abs() < 1e-12);
            assert!((mx - 100.3).abs() < 1e-4 && (my - 99.6).abs() < 1e-4, "{mx} {my}");
            // The second-moment tensor's eigenvectors point along pa and across, and the
            // eigenvalue ratio is ratio^2 (the axes scale as 1/sqrt(ratio), sqrt(ratio)):
            // the profile is a linear stretch of the circular one, up to pixel integration
            // (+1/12 px^2 on each axis) and the truncation.
            let (xx, yy, xy) = second_moments(&s);
            let angle = 0.5 * (2.0 * xy).atan2(xx - yy).to_degrees();
            let d = (angle - pa).rem_euclid(180.0);
            assert!(d.min(180.0 - d) < 0.5, "ratio {ratio} pa {pa}: moments angle {angle}");
            let tr = 0.5 * (xx + yy);
            let disc = (0.25 * (xx - yy).powi(2) + xy * xy).sqrt();
            let (l1, l2) = (tr + disc - 1.0 / 12.0, tr - disc - 1.0 / 12.0);
            assert!((l2 / l1 - ratio * ratio).abs() < 0.02, "ratio {ratio}: {}", l2 / l1);
        }
    }

    #[test]
    fn fwhm_round_trips() {
        for kind in [PsfKind::Gaussian, PsfKind::Moffat] {
            let p = Psf::from_fwhm(kind, 3.3, 2.7);
            assert!((p.fwhm_px() - 3.3).abs() < 1e-12);
        }
        // The Gaussian pixel integral: central pixel of a centred sigma=1 Gaussian.
        let s = render(Psf::Gaussian { sigma_px: 1.0 }, 10.0, 10.0);
        let c = s.values[[(10 - s.y0) as usize, (10 - s.x0) as usize]];
        let one_d = statrs::function::erf::erf(0.5 / std::f64::consts::SQRT_2);
        assert!((c - one_d * one_d).abs() < 1e-12);
    }
}
