//! Local background from a circular annulus, with hand-written sigma clipping (f64).

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

/// A circular annulus centred on `(x, y)` (px) between radii `r_in` and `r_out` (px).
/// A pixel belongs to it when its centre satisfies `r_in <= d < r_out`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Annulus {
    /// Centre, x, px.
    pub x: f64,
    /// Centre, y, px.
    pub y: f64,
    /// Inner radius, px.
    pub r_in: f64,
    /// Outer radius, px.
    pub r_out: f64,
}

/// The statistic reported as the background level after clipping.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum BkgStat {
    /// Mean of the clipped sample; `var(level) = sigma^2 / n`.
    ClippedMean,
    /// Median of the clipped sample; `var(level) = (pi/2) sigma^2 / n` (Gaussian efficiency).
    ClippedMedian,
}

/// Statistics of a sigma-clipped sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Clipped {
    /// Mean of the kept values.
    pub mean: f64,
    /// Median of the kept values.
    pub median: f64,
    /// Sample standard deviation (n-1) of the kept values (0 when n = 1).
    pub std: f64,
    /// Number of kept values.
    pub n: usize,
    /// Number of values rejected.
    pub n_rejected: usize,
    /// Clipping iterations performed.
    pub iterations: u32,
}

/// Local background estimate. Level and sigma in ADU, `level_variance` in ADU^2.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Background {
    /// Background level per pixel, ADU.
    pub level: f64,
    /// Per-pixel scatter (sample standard deviation of the clipped annulus pixels), ADU.
    pub sigma: f64,
    /// Variance of `level` itself, ADU^2 (see [`BkgStat`]).
    pub level_variance: f64,
    /// Annulus pixels used (after clipping).
    pub n: usize,
    /// Annulus pixels rejected by the clipping.
    pub n_rejected: usize,
    /// Annulus pixels that were masked or non-finite (pixels off the image are not counted).
    pub n_masked: usize,
    /// Annulus pixels left out because they lie near another listed source.
    pub n_excluded: usize,
    /// The statistic used.
    pub stat: BkgStat,
}

use crate::numeric::median_in_place;

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (mean, 0.0);
    }
    let ss: f64 = v.iter().map(|x| (x - mean) * (x - mean)).sum();
    (mean, (ss / (n - 1.0)).sqrt())
}

/// Iterative sigma clipping about the median: at each iteration keep the values with
/// `|x - median| <= k * std` (std of the current sample, n-1), until nothing changes or
/// `max_iter` iterations. Non-finite values are dropped first. `values` is reordered and
/// truncated to the kept sample. Returns None for an empty sample.
///
/// ```
/// use sofipol_pipeline::photometry::sigma_clip;
/// let mut v: Vec<f64> = (0..100).map(|i| (i % 10) as f64).collect();
/// v.push(1000.0);
/// let c = sigma_clip(&mut v, 3.0, 10).unwrap();
/// assert_eq!(c.n_rejected, 1);
/// assert_eq!(c.mean, 4.5);
/// ```
pub fn sigma_clip(values: &mut Vec<f64>, k: f64, max_iter: u32) -> Option<Clipped> {
    let n0 = values.len();
    values.retain(|x| x.is_finite());
    if values.is_empty() {
        return None;
    }
    let mut iterations = 0;
    while iterations < max_iter {
        let med = median_in_place(values);
        let (_, std) = mean_std(values);
        if std.is_nan() || std <= 0.0 {
            break;
        }
        let before = values.len();
        values.retain(|x| (x - med).abs() <= k * std);
        iterations += 1;
        if values.len() == before || values.is_empty() {
            break;
        }
    }
    if values.is_empty() {
        return None;
    }
    let (mean, std) = mean_std(values);
    let median = median_in_place(values);
    Some(Clipped {
        mean,
        median,
        std,
        n: values.len(),
        n_rejected: n0 - values.len(),
        iterations,
    })
}

/// Background in an annulus: pixels whose centre lies in `[r_in, r_out)` from the annulus
/// centre, that are in the image, unmasked (`mask == 0`) and finite, and farther than `rad`
/// from every `(x, y, rad)` of `exclude` (other sources), are sigma-clipped
/// (`clip_sigma`, `iters`, see [`sigma_clip`]) and summarised by `stat`.
///
/// Returns None when fewer than 2 pixels survive (no scatter can be measured); the caller
/// decides whether `n` is enough (see `PhotParams::min_sky_pixels`).
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::{annulus_background, Annulus, BkgStat};
/// let mut img = Array2::<f32>::from_elem((40, 40), 3.0);
/// img[[20, 28]] = 1e4; // a hot pixel in the annulus, clipped
/// let ann = Annulus { x: 20.0, y: 20.0, r_in: 6.0, r_out: 10.0 };
/// let b = annulus_background(img.view(), None, &ann, &[], BkgStat::ClippedMean, 3.0, 5).unwrap();
/// assert_eq!((b.level, b.n_rejected), (3.0, 1));
/// ```
pub fn annulus_background(
    img: ArrayView2<f32>,
    mask: Option<ArrayView2<u8>>,
    ann: &Annulus,
    exclude: &[(f64, f64, f64)],
    stat: BkgStat,
    clip_sigma: f64,
    iters: u32,
) -> Option<Background> {
    let (ny, nx) = img.dim();
    if ann.r_out.is_nan()
        || ann.r_out <= ann.r_in.max(0.0)
        || !ann.x.is_finite()
        || !ann.y.is_finite()
        || ny == 0
        || nx == 0
    {
        return None;
    }
    let (ri2, ro2) = (ann.r_in.max(0.0).powi(2), ann.r_out * ann.r_out);
    let y_lo = (ann.y - ann.r_out).floor().max(0.0) as usize;
    let y_hi = ((ann.y + ann.r_out).ceil().max(-1.0) as i64).min(ny as i64 - 1);
    let x_lo = (ann.x - ann.r_out).floor().max(0.0) as usize;
    let x_hi = ((ann.x + ann.r_out).ceil().max(-1.0) as i64).min(nx as i64 - 1);
    let mut values = Vec::with_capacity((4.0 * ro2) as usize + 8);
    let (mut n_masked, mut n_excluded) = (0usize, 0usize);
    if y_hi >= 0 && x_hi >= 0 {
        for iy in y_lo..=y_hi as usize {
            let dy = iy as f64 - ann.y;
            for ix in x_lo..=x_hi as usize {
                let dx = ix as f64 - ann.x;
                let d2 = dx * dx + dy * dy;
                if d2 < ri2 || d2 >= ro2 {
                    continue;
                }
                let v = img[[iy, ix]];
                if !v.is_finite() || mask.as_ref().is_some_and(|m| m[[iy, ix]] != 0) {
                    n_masked += 1;
                    continue;
                }
                let near = exclude.iter().any(|&(ox, oy, orad)| {
                    let (ex, ey) = (ix as f64 - ox, iy as f64 - oy);
                    ex * ex + ey * ey < orad * orad
                });
                if near {
                    n_excluded += 1;
                    continue;
                }
                values.push(v as f64);
            }
        }
    }
    let c = sigma_clip(&mut values, clip_sigma, iters)?;
    if c.n < 2 {
        return None;
    }
    let (level, factor) = match stat {
        BkgStat::ClippedMean => (c.mean, 1.0),
        BkgStat::ClippedMedian => (c.median, std::f64::consts::FRAC_PI_2),
    };
    Some(Background {
        level,
        sigma: c.std,
        level_variance: factor * c.std * c.std / c.n as f64,
        n: c.n,
        n_rejected: c.n_rejected,
        n_masked,
        n_excluded,
        stat,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn photometry_sigma_clip_basics() {
        let mut v = vec![1.0, 2.0, 3.0, 4.0];
        let c = sigma_clip(&mut v, 3.0, 5).unwrap();
        assert_eq!((c.mean, c.median, c.n, c.n_rejected), (2.5, 2.5, 4, 0));
        assert!((c.std - (5.0f64 / 3.0).sqrt()).abs() < 1e-15);
        let mut e: Vec<f64> = vec![f64::NAN];
        assert!(sigma_clip(&mut e, 3.0, 5).is_none());
        let mut flat = vec![7.0; 10];
        let c = sigma_clip(&mut flat, 3.0, 5).unwrap();
        assert_eq!((c.mean, c.std, c.n), (7.0, 0.0, 10));
        // Outliers on one side are removed over several iterations.
        let mut w: Vec<f64> = (0..200).map(|i| ((i * 37) % 101) as f64 / 100.0).collect();
        w.extend([50.0, 20.0, 10.0, 6.0]);
        let c = sigma_clip(&mut w, 3.0, 20).unwrap();
        assert_eq!(c.n, 200);
        assert!(c.iterations >= 2);
    }

    #[test]
    fn photometry_annulus_background_excludes_star_mask_and_companion() {
        let mut img = Array2::<f32>::from_elem((40, 40), 10.0);
        // +-1 pattern: mean 10, known scatter.
        for ((iy, ix), v) in img.indexed_iter_mut() {
            *v += if (ix + iy) % 2 == 0 { 1.0 } else { -1.0 };
        }
        img[[20, 28]] = 500.0; // a cosmic ray in the annulus: clipped
        let mut mask = Array2::<u8>::zeros((40, 40));
        mask[[12, 20]] = 1;
        img[[12, 20]] = -1e9; // masked junk
                              // A companion at (20, 30): exclude 3 px around it.
        for iy in 27..34 {
            for ix in 17..24 {
                img[[iy, ix]] += 1000.0;
            }
        }
        let ann = Annulus {
            x: 20.0,
            y: 20.0,
            r_in: 6.0,
            r_out: 11.0,
        };
        let b = annulus_background(
            img.view(),
            Some(mask.view()),
            &ann,
            &[(20.0, 30.0, 4.5)],
            BkgStat::ClippedMean,
            3.0,
            10,
        )
        .unwrap();
        assert_eq!(b.n_masked, 1);
        assert!(b.n_excluded > 0);
        assert_eq!(b.n_rejected, 1);
        assert!((b.level - 10.0).abs() < 0.1, "{}", b.level);
        assert!((b.sigma - 1.0).abs() < 0.02, "{}", b.sigma);
        assert!((b.level_variance - b.sigma * b.sigma / b.n as f64).abs() < 1e-15);
        let m = annulus_background(
            img.view(),
            Some(mask.view()),
            &ann,
            &[(20.0, 30.0, 4.5)],
            BkgStat::ClippedMedian,
            3.0,
            10,
        )
        .unwrap();
        assert!((m.level - 10.0).abs() <= 1.0);
        // Off the image: None.
        let off = Annulus {
            x: -100.0,
            y: 5.0,
            r_in: 2.0,
            r_out: 5.0,
        };
        assert!(annulus_background(img.view(), None, &off, &[], BkgStat::ClippedMean, 3.0, 5).is_none());
    }
}
