//! Pixel-integrated Gaussian star model (exact integrals over each pixel via erf differences).
//!
//! A star of total flux `F` (ADU) at `(x, y)` with axis-aligned widths `sigma_x`, `sigma_y` (px)
//! puts `F * Px(ix) * Py(iy)` in pixel `(ix, iy)`, where
//! `Px(ix) = Phi((ix + 1/2 - x)/sigma_x) - Phi((ix - 1/2 - x)/sigma_x)` is the fraction of a
//! 1-D normal distribution falling in `[ix-1/2, ix+1/2]`. Used by the PSF fit and by tests and
//! simulators that need stars with a known exact pixel content.

use ndarray::ArrayViewMut2;
use statrs::function::erf::{erf, erfc};

/// `FWHM / sigma` of a Gaussian, `2 sqrt(2 ln 2)`.
pub const FWHM_PER_SIGMA: f64 = 2.354_820_045_030_949;

const INV_SQRT2: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// `1 / sqrt(2 pi)`.
const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// `Phi(zb) - Phi(za)` for the standard normal CDF, accurate in both tails (uses erfc when
/// both arguments are on the same side of 0).
pub fn normal_cdf_diff(za: f64, zb: f64) -> f64 {
    if za >= 0.0 {
        0.5 * (erfc(za * INV_SQRT2) - erfc(zb * INV_SQRT2))
    } else if zb <= 0.0 {
        0.5 * (erfc(-zb * INV_SQRT2) - erfc(-za * INV_SQRT2))
    } else {
        0.5 * (erf(zb * INV_SQRT2) - erf(za * INV_SQRT2))
    }
}

/// Standard normal density.
#[inline]
fn phi(z: f64) -> f64 {
    INV_SQRT_2PI * (-0.5 * z * z).exp()
}

/// Fraction of a 1-D Gaussian `(mu, sigma)` falling in pixel `i`, `[i - 1/2, i + 1/2]`.
pub fn gauss_pixel_1d(i: i64, mu: f64, sigma: f64) -> f64 {
    let za = (i as f64 - 0.5 - mu) / sigma;
    let zb = (i as f64 + 0.5 - mu) / sigma;
    normal_cdf_diff(za, zb)
}

/// [`gauss_pixel_1d`] and its derivatives with respect to `mu` and `sigma`.
pub(crate) fn gauss_pixel_1d_derivs(i: i64, mu: f64, sigma: f64) -> (f64, f64, f64) {
    let za = (i as f64 - 0.5 - mu) / sigma;
    let zb = (i as f64 + 0.5 - mu) / sigma;
    let (pa, pb) = (phi(za), phi(zb));
    (
        normal_cdf_diff(za, zb),
        -(pb - pa) / sigma,
        -(zb * pb - za * pa) / sigma,
    )
}

/// Adds a pixel-integrated Gaussian star (flux `flux` ADU, centre `(x, y)` px, widths
/// `sigma_x`, `sigma_y` px) to `img` (indexed `[y, x]`), over the pixels within 10 sigma of
/// the centre (the rest is below 1e-22 of the flux). A negative flux subtracts the star.
pub fn add_gaussian(img: &mut ArrayViewMut2<f32>, flux: f64, x: f64, y: f64, sigma_x: f64, sigma_y: f64) {
    let (ny, nx) = img.dim();
    if nx == 0 || ny == 0 || !(sigma_x > 0.0 && sigma_y > 0.0) || !x.is_finite() || !y.is_finite() {
        return;
    }
    let span = |c: f64, s: f64, n: usize| -> (usize, usize) {
        let lo = (c - 10.0 * s - 1.0).floor().max(0.0).min(n as f64 - 1.0) as usize;
        let hi = (c + 10.0 * s + 1.0).ceil().max(0.0).min(n as f64 - 1.0) as usize;
        (lo, hi)
    };
    let (x_lo, x_hi) = span(x, sigma_x, nx);
    let (y_lo, y_hi) = span(y, sigma_y, ny);
    let px: Vec<f64> = (x_lo..=x_hi).map(|ix| gauss_pixel_1d(ix as i64, x, sigma_x)).collect();
    for iy in y_lo..=y_hi {
        let fy = flux * gauss_pixel_1d(iy as i64, y, sigma_y);
        for (k, ix) in (x_lo..=x_hi).enumerate() {
            let v = &mut img[[iy, ix]];
            *v = (*v as f64 + fy * px[k]) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn photometry_model_pixel_fractions() {
        // Sum over all pixels is 1, for any centre.
        for &(mu, s) in &[(0.0, 0.3), (0.37, 1.0), (-2.5, 2.7)] {
            let t: f64 = (-40..=40).map(|i| gauss_pixel_1d(i, mu, s)).sum();
            assert!((t - 1.0).abs() < 1e-14, "{t}");
        }
        // Central pixel of a centred unit Gaussian: erf(0.5/sqrt 2) = 0.382924922548026.
        assert!((gauss_pixel_1d(0, 0.0, 1.0) - 0.382_924_922_548_026).abs() < 1e-14);
        // Far tail keeps relative accuracy (no erf cancellation): Phi(-19.5) - Phi(-20.5).
        let t = gauss_pixel_1d(20, 0.0, 1.0);
        let expect = 0.5 * (erfc(19.5 * INV_SQRT2) - erfc(20.5 * INV_SQRT2));
        assert!(t > 1e-90 && t < 1e-80 && (t / expect - 1.0).abs() < 1e-12, "{t}");
        // Derivatives against central differences.
        let (p, dmu, ds) = gauss_pixel_1d_derivs(2, 1.3, 0.9);
        let h = 1e-6;
        let nmu = (gauss_pixel_1d(2, 1.3 + h, 0.9) - gauss_pixel_1d(2, 1.3 - h, 0.9)) / (2.0 * h);
        let ns = (gauss_pixel_1d(2, 1.3, 0.9 + h) - gauss_pixel_1d(2, 1.3, 0.9 - h)) / (2.0 * h);
        assert_eq!(p, gauss_pixel_1d(2, 1.3, 0.9));
        assert!((dmu - nmu).abs() < 1e-8 && (ds - ns).abs() < 1e-8);
        // add_gaussian puts the whole flux on a large enough image.
        let mut img = Array2::<f32>::zeros((40, 50));
        add_gaussian(&mut img.view_mut(), 1000.0, 20.3, 18.9, 1.5, 2.0);
        let tot: f64 = img.iter().map(|&v| v as f64).sum();
        assert!((tot - 1000.0).abs() < 1e-3, "{tot}");
    }
}
