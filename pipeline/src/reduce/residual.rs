//! The o-e residual of a field star without a focal mask: a second detection pass for the
//! sources too faint (or too close to the star) for the stack's peaks.
//!
//! A star's o and e images are one image of the sky through the two beams: the same PSF,
//! the same registration of the stacked dithers, fluxes in the ratio its polarization
//! sets. The o image minus the e image scaled and moved onto it (a fit of the flux ratio,
//! a residual shift and a background difference over the core) removes the star and
//! leaves the light that falls on one image only: another source's image of either beam
//! (positive where it adds to the o image, negative where it adds to the e image). That
//! light biases `(o - e)/(o + e)` and no sky distance shows it. It is found by a
//! matched filter (the PSF's Gaussian of the median FWHM) weighted by the residual's
//! noise: the stack's variance in both images and [`SHAPE_FLOOR`] of the star's image for
//! the two beams' shapes differing.
use ndarray::ArrayView2;
use sofipol_calib::profile::Beam;

/// The S/N of the matched filter on the o-e residual from which it is a source: 4
/// standard deviations (about one false source in a hundred stars at two rotator angles).
pub const RESIDUAL_SNR: f64 = 4.0;
/// The fraction of the star's image, per pixel, added (in quadrature) to the residual's
/// noise: the o and e images' shapes differ by this much (the interpolation of the e image
/// onto the o image's pixels, the beams' optics).
pub const SHAPE_FLOOR: f64 = 0.02;

/// One orientation's stack of dithers: mean, variance of the mean (ADU^2), and pixels
/// that no frame gave (1).
#[derive(Debug, Clone, Copy)]
pub struct StackImage<'a> {
    /// Mean of the frames, ADU.
    pub mean: ArrayView2<'a, f32>,
    /// Variance of the mean, ADU^2.
    pub var: ArrayView2<'a, f32>,
    /// 1 where no frame gave a usable pixel.
    pub bad: ArrayView2<'a, u8>,
}

/// A source found on the o-e residual of a star.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualSource {
    /// Where it is on the stack, px, in the beam whose image it falls on.
    pub xy: (f64, f64),
    /// The star's image it falls on.
    pub beam: Beam,
    /// Its distance from that image's centre, px.
    pub r_px: f64,
    /// The matched filter's S/N (its absolute value).
    pub snr: f64,
}

/// Keys' cubic convolution kernel (a = -0.5).
fn keys(t: f64) -> f64 {
    let t = t.abs();
    if t < 1.0 {
        (1.5 * t - 2.5) * t * t + 1.0
    } else if t < 2.0 {
        ((-0.5 * t + 2.5) * t - 4.0) * t + 2.0
    } else {
        0.0
    }
}

/// Solve the symmetric positive system `a x = b` (n <= 4) by Gaussian elimination with
/// partial pivoting; None when singular.
fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if !(a[p][c].abs() > 1e-300) {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        for r in c + 1..N {
            let f = a[r][c] / a[c][c];
            let pivot = a[c];
            for (v, pv) in a[r].iter_mut().zip(pivot).skip(c) {
                *v -= f * pv;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = [0.0; N];
    for c in (0..N).rev() {
        let s: f64 = (c + 1..N).map(|k| a[c][k] * x[k]).sum();
        x[c] = (b[c] - s) / a[c][c];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The sources on the o-e residual of the star whose o image is at `o` (px on the stack)
/// and e image at `o + eo`, within `radius` px of either image's centre, at S/N `snr_min`
/// or more (see the module documentation); `fwhm` the median FWHM, px. Each is a local
/// extremum of the filtered residual; the strongest first.
pub fn residual_sources(
    st: &StackImage,
    o: (f64, f64),
    eo: (f64, f64),
    fwhm: f64,
    radius: f64,
    snr_min: f64,
) -> Vec<ResidualSource> {
    let (ny, nx) = st.mean.dim();
    let sigma = fwhm / 2.3548;
    let kh = (1.5 * fwhm).ceil() as i64;
    let h = radius.ceil() as i64 + kh + 2;
    let n = (2 * h + 1) as usize;
    let (cx, cy) = (o.0.round() as i64, o.1.round() as i64);
    // The e image on the o image's stamp: whole pixels, then the fraction by cubic
    // convolution (its variance by the squared weights).
    let (ix, iy) = (eo.0.round() as i64, eo.1.round() as i64);
    let (fx, fy) = (eo.0 - ix as f64, eo.1 - iy as f64);
    let wx: Vec<f64> = (-1..=2).map(|k| keys(k as f64 - fx)).collect();
    let wy: Vec<f64> = (-1..=2).map(|k| keys(k as f64 - fy)).collect();
    let pix = |x: i64, y: i64| -> Option<(f64, f64)> {
        if x < 0 || y < 0 || x >= nx as i64 || y >= ny as i64 {
            return None;
        }
        let (xu, yu) = (x as usize, y as usize);
        let (v, var) = (st.mean[[yu, xu]] as f64, st.var[[yu, xu]] as f64);
        (st.bad[[yu, xu]] == 0 && v.is_finite() && var.is_finite() && var > 0.0).then_some((v, var))
    };
    // Per stamp pixel: o value and variance, e value and variance (moved onto it).
    let mut ov = vec![None; n * n];
    let mut ev = vec![None; n * n];
    for j in 0..n {
        for i in 0..n {
            let (x, y) = (cx - h + i as i64, cy - h + j as i64);
            ov[j * n + i] = pix(x, y);
            let mut acc = (0.0, 0.0);
            let mut ok = true;
            'taps: for (b, wyb) in wy.iter().enumerate() {
                for (a, wxa) in wx.iter().enumerate() {
                    match pix(x + ix - 1 + a as i64, y + iy - 1 + b as i64) {
                        Some((v, var)) => {
                            let w = wxa * wyb;
                            acc.0 += w * v;
                            acc.1 += w * w * var;
                        }
                        None => {
                            ok = false;
                            break 'taps;
                        }
                    }
                }
            }
            ev[j * n + i] = ok.then_some(acc);
        }
    }
    // The fit over the core: o = r e + sx de/dx + sy de/dy + c.
    let (ox, oy) = (o.0 - (cx - h) as f64, o.1 - (cy - h) as f64);
    let r_fit = 1.5 * fwhm;
    let grad = |i: usize, j: usize| -> Option<(f64, f64)> {
        if i == 0 || j == 0 || i + 1 >= n || j + 1 >= n {
            return None;
        }
        let g = |ii: usize, jj: usize| ev[jj * n + ii].map(|e| e.0);
        Some(((g(i + 1, j)? - g(i - 1, j)?) / 2.0, (g(i, j + 1)? - g(i, j - 1)?) / 2.0))
    };
    // A first flux ratio, for the weights' shape floor.
    let (mut so, mut se) = (0.0, 0.0);
    for j in 0..n {
        for i in 0..n {
            if (i as f64 - ox).hypot(j as f64 - oy) <= r_fit {
                if let (Some(o_p), Some(e_p)) = (ov[j * n + i], ev[j * n + i]) {
                    so += o_p.0;
                    se += e_p.0;
                }
            }
        }
    }
    let r0 = if se > 0.0 && so > 0.0 { so / se } else { 1.0 };
    let mut a = [[0.0; 4]; 4];
    let mut bv = [0.0; 4];
    for j in 0..n {
        for i in 0..n {
            if (i as f64 - ox).hypot(j as f64 - oy) > r_fit {
                continue;
            }
            let (Some((o_v, o_var)), Some((e_v, e_var)), Some((gx, gy))) = (ov[j * n + i], ev[j * n + i], grad(i, j))
            else {
                continue;
            };
            let w = 1.0 / (o_var + r0 * r0 * e_var + (SHAPE_FLOOR * r0 * e_v).powi(2));
            let basis = [e_v, gx, gy, 1.0];
            for p in 0..4 {
                bv[p] += w * basis[p] * o_v;
                for q in 0..4 {
                    a[p][q] += w * basis[p] * basis[q];
                }
            }
        }
    }
    let Some([ratio, sx, sy, c]) = solve(a, bv) else {
        return Vec::new();
    };
    // The residual and its variance.
    let mut d = vec![f64::NAN; n * n];
    let mut dv = vec![f64::NAN; n * n];
    for j in 0..n {
        for i in 0..n {
            let (Some((o_v, o_var)), Some((e_v, e_var)), Some((gx, gy))) = (ov[j * n + i], ev[j * n + i], grad(i, j))
            else {
                continue;
            };
            let model = ratio * e_v + sx * gx + sy * gy + c;
            d[j * n + i] = o_v - model;
            dv[j * n + i] = o_var + ratio * ratio * e_var + (SHAPE_FLOOR * model).powi(2);
        }
    }
    // The matched filter about every pixel within `radius` (and one beyond, for the
    // extremum test).
    let w: Vec<(i64, i64, f64)> = (-kh..=kh)
        .flat_map(|dy| (-kh..=kh).map(move |dx| (dx, dy)))
        .map(|(dx, dy)| (dx, dy, (-((dx * dx + dy * dy) as f64) / (2.0 * sigma * sigma)).exp()))
        .filter(|t| t.2 > 0.01)
        .collect();
    let mut snr = vec![f64::NAN; n * n];
    let lim = radius + 1.5;
    for j in kh..n as i64 - kh {
        for i in kh..n as i64 - kh {
            if (i as f64 - ox).hypot(j as f64 - oy) > lim {
                continue;
            }
            let (mut s, mut nn, mut wt) = (0.0, 0.0, 0.0);
            for &(dx, dy, wk) in &w {
                let k = ((j + dy) * n as i64 + i + dx) as usize;
                if d[k].is_finite() {
                    s += wk * d[k] / dv[k];
                    nn += wk * wk / dv[k];
                    wt += wk * wk;
                }
            }
            let full: f64 = w.iter().map(|t| t.2 * t.2).sum();
            if nn > 0.0 && wt >= 0.7 * full {
                snr[(j * n as i64 + i) as usize] = s / nn.sqrt();
            }
        }
    }
    let mut out = Vec::new();
    for j in 1..n - 1 {
        for i in 1..n - 1 {
            let v = snr[j * n + i];
            let r = (i as f64 - ox).hypot(j as f64 - oy);
            if !(v.abs() >= snr_min) || r > radius {
                continue;
            }
            let extreme = (j - 1..=j + 1)
                .flat_map(|jj| (i - 1..=i + 1).map(move |ii| (ii, jj)))
                .filter(|&p| p != (i, j))
                .all(|(ii, jj)| !(snr[jj * n + ii] * v.signum() > v.abs()));
            if !extreme {
                continue;
            }
            let (x, y) = ((cx - h) as f64 + i as f64, (cy - h) as f64 + j as f64);
            let (xy, beam) = if v > 0.0 {
                ((x, y), Beam::Ordinary)
            } else {
                ((x + eo.0, y + eo.1), Beam::Extraordinary)
            };
            out.push(ResidualSource {
                xy,
                beam,
                r_px: r,
                snr: v.abs(),
            });
        }
    }
    out.sort_by(|p, q| q.snr.total_cmp(&p.snr));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    /// A Moffat (beta 3) of total flux `f` at (x0, y0), FWHM `fwhm`, integrated over each
    /// pixel by 5x5 sub-samples.
    fn add_star(img: &mut Array2<f32>, (x0, y0): (f64, f64), f: f64, fwhm: f64) {
        let beta = 3.0;
        let alpha = fwhm / (2.0 * (2f64.powf(1.0 / beta) - 1.0).sqrt());
        let norm = (beta - 1.0) / (std::f64::consts::PI * alpha * alpha);
        let (ny, nx) = img.dim();
        for y in 0..ny {
            for x in 0..nx {
                let mut s = 0.0;
                for sy in 0..5 {
                    for sx in 0..5 {
                        let dx = x as f64 - 0.4 + 0.2 * sx as f64 - x0;
                        let dy = y as f64 - 0.4 + 0.2 * sy as f64 - y0;
                        s += norm * (1.0 + (dx * dx + dy * dy) / (alpha * alpha)).powf(-beta) / 25.0;
                    }
                }
                img[[y, x]] += (f * s) as f32;
            }
        }
    }

    /// Gaussian noise of `sd` from a fixed linear congruential sequence (Box-Muller).
    fn noise(img: &mut Array2<f32>, sd: f64, seed: u64) {
        let mut s = seed;
        let mut u = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        for v in img.iter_mut() {
            let g = (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos();
            *v += (sd * g) as f32;
        }
    }

    /// A polarized star (o and e fluxes differ by 10 %) at a fractional e-o offset: alone it
    /// leaves no source on its residual; a source of 1/40 of its flux 4 px from its e image
    /// (the other beam's image of another star) is found there, on the e image, and one
    /// 4 px from its o image on the o image.
    #[test]
    fn a_faint_image_on_one_beam_is_found_and_the_star_alone_is_clean() {
        let fwhm = 2.8;
        let eo = (24.3, -18.6);
        let o = (30.2, 40.7);
        let e = (o.0 + eo.0, o.1 + eo.1);
        let sd = 3.0;
        let make = |extra: Option<((f64, f64), f64)>, seed: u64| {
            let mut img = Array2::<f32>::zeros((80, 80));
            add_star(&mut img, o, 2.2e4, fwhm);
            add_star(&mut img, e, 1.8e4, fwhm);
            if let Some((xy, f)) = extra {
                add_star(&mut img, xy, f, fwhm);
            }
            // The stack's variance: the sky's and the sources' photon noise.
            let var = img.mapv(|v| (sd * sd) as f32 + v.max(0.0) / 50.0);
            let mut noisy = img.clone();
            noise(&mut noisy, sd, seed);
            // Photon noise of the sources on top of the sky's.
            let mut extra_noise = Array2::<f32>::zeros((80, 80));
            noise(&mut extra_noise, 1.0, seed + 7);
            for ((n, x), s) in noisy.iter_mut().zip(extra_noise.iter()).zip(img.iter()) {
                *n += *x * (s.max(0.0) / 50.0).sqrt();
            }
            (noisy, var)
        };
        let bad = Array2::<u8>::zeros((80, 80));
        let mut false_sources = 0;
        for seed in 1..=20 {
            let (img, var) = make(None, seed);
            let st = StackImage {
                mean: img.view(),
                var: var.view(),
                bad: bad.view(),
            };
            false_sources += residual_sources(&st, o, eo, fwhm, 5.6, RESIDUAL_SNR).len();
        }
        assert!(false_sources <= 1, "{false_sources} sources on 20 clean residuals");
        for (at, beam) in [
            ((e.0 + 4.0, e.1 - 0.5), Beam::Extraordinary),
            ((o.0 - 3.0, o.1 + 2.6), Beam::Ordinary),
        ] {
            let (img, var) = make(Some((at, 500.0)), 3);
            let st = StackImage {
                mean: img.view(),
                var: var.view(),
                bad: bad.view(),
            };
            let found = residual_sources(&st, o, eo, fwhm, 5.6, RESIDUAL_SNR);
            let best = found.first().unwrap_or_else(|| panic!("nothing found near {at:?}"));
            assert_eq!(best.beam, beam, "{found:?}");
            assert!(
                (best.xy.0 - at.0).hypot(best.xy.1 - at.1) < 1.5,
                "{best:?} for a source at {at:?}"
            );
        }
    }
}
