//! The sky estimate of every dither from the other dithers: the median (fast path,
//! [`crate::stack`]), a sigma-clipped mean, and a second pass with the sources of the
//! first pass masked (the trade-offs shown by `sofipol bench accuracy --report`).
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

use super::{median_variance_factor, SkyEstimator, SkyOptions, SkyScaling};
use crate::error::Result;
use crate::stack::{self, Affine};

/// What the estimators need: the raw frames, their level maps, levels, and noise (1/g and
/// read variance in ADU^2) of each frame.
pub(super) struct Ctx<'a> {
    pub frames: &'a [ArrayView2<'a, f32>],
    pub maps: &'a [Affine],
    pub levels: &'a [f64],
    pub noise: &'a [(f32, f32)],
    pub opts: &'a SkyOptions,
}

/// The level-normalized sky of every frame, and (source-masked pass only) the number of
/// other dithers used at each pixel.
pub(super) type Skies = (Vec<Array2<f32>>, Vec<Option<Array2<u8>>>);

/// Sky estimates of every frame (level-normalized: multiply by, or add, the frame's level).
pub(super) fn skies(ctx: &Ctx) -> Result<Skies> {
    let n = ctx.frames.len();
    let first = match ctx.opts.estimator {
        SkyEstimator::Median => stack::leave_one_out_medians_affine(ctx.frames, ctx.maps)?,
        SkyEstimator::ClippedMean => (0..n).map(|i| estimate_excluding(ctx, i, None).0).collect(),
    };
    if !ctx.opts.mask_sources {
        return Ok((first, vec![None; n]));
    }
    let sources: Vec<Array2<bool>> = (0..n).map(|j| source_mask(ctx, j, &first[j])).collect();
    let (skies, counts): (Vec<_>, Vec<_>) = (0..n)
        .map(|i| {
            let (s, c) = estimate_excluding(ctx, i, Some(&sources));
            (s, Some(c))
        })
        .unzip();
    Ok((skies, counts))
}

/// c(m) of the estimator for m values: Var(estimate) = c(m) sigma^2 / m.
pub(super) fn variance_factor(e: SkyEstimator, m: usize) -> f64 {
    match e {
        SkyEstimator::Median => median_variance_factor(m),
        SkyEstimator::ClippedMean => 1.0,
    }
}

/// c(k)/k for k = 0..=MAX_STACK values (0 for k = 0).
pub(super) fn c_over_count_table(e: SkyEstimator) -> [f32; stack::MAX_STACK + 1] {
    std::array::from_fn(|k| {
        if k == 0 {
            0.0
        } else {
            (variance_factor(e, k) / k as f64) as f32
        }
    })
}

/// How the sky was estimated, for the history record.
pub(super) fn describe(o: &SkyOptions) -> String {
    let est = match o.estimator {
        SkyEstimator::Median => "median".to_string(),
        SkyEstimator::ClippedMean => format!("{}-sigma clipped mean", o.clip_sigma),
    };
    let base = match o.scaling {
        SkyScaling::Multiplicative => format!("level x {est} of raw/level"),
        SkyScaling::Additive => format!("level + {est} of raw-level"),
    };
    if o.mask_sources {
        format!(
            "{base}, second pass with the sources of the first (> {} sigma, grown {} px) left out",
            o.source_sigma, o.source_grow_px
        )
    } else {
        base
    }
}

/// Median of a few values (sorted in place; even counts: mean of the middle two, as the
/// selection networks compute it).
fn median_of(v: &mut [f32]) -> f32 {
    v.sort_unstable_by(f32::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) * 0.5
    }
}

/// The estimator on values `v` with noise `sig` (same units).
fn estimate(o: &SkyOptions, v: &mut [f32], sig: &[f32], tmp: &mut Vec<f32>) -> f32 {
    tmp.clear();
    tmp.extend_from_slice(v);
    let med = median_of(tmp);
    match o.estimator {
        SkyEstimator::Median => med,
        SkyEstimator::ClippedMean => {
            let k = o.clip_sigma as f32;
            let (mut s, mut n) = (0f64, 0u32);
            for (&x, &sg) in v.iter().zip(sig) {
                if (x - med).abs() <= k * sg {
                    s += x as f64;
                    n += 1;
                }
            }
            if n == 0 {
                med
            } else {
                (s / n as f64) as f32
            }
        }
    }
}

/// Sky of frame `i` from the other frames with the estimator, per pixel; with `sources`,
/// leaving out the frames whose source mask is set at the pixel (all others when every
/// one is). Returns the estimate and the number of values used per pixel.
fn estimate_excluding(ctx: &Ctx, i: usize, sources: Option<&[Array2<bool>]>) -> (Array2<f32>, Array2<u8>) {
    let (ny, nx) = ctx.frames[0].dim();
    let n = ctx.frames.len();
    let mut out = Array2::<f32>::zeros((ny, nx));
    let mut cnt = Array2::<u8>::zeros((ny, nx));
    let others: Vec<usize> = (0..n).filter(|&j| j != i).collect();
    out.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(nx)
        .zip(cnt.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
        .enumerate()
        .for_each(|(y, (orow, crow))| {
            let (mut v, mut sig, mut tmp) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
            for x in 0..nx {
                v.clear();
                sig.clear();
                for &j in &others {
                    if sources.is_some_and(|s| s[j][[y, x]]) {
                        continue;
                    }
                    push_value(ctx, j, y, x, &mut v, &mut sig);
                }
                if v.is_empty() {
                    for &j in &others {
                        push_value(ctx, j, y, x, &mut v, &mut sig);
                    }
                }
                crow[x] = v.len() as u8;
                orow[x] = estimate(ctx.opts, &mut v, &sig, &mut tmp);
            }
        });
    (out, cnt)
}

/// Frame j's level-normalized value at (y, x) and its noise in the same units.
#[inline]
fn push_value(ctx: &Ctx, j: usize, y: usize, x: usize, v: &mut Vec<f32>, sig: &mut Vec<f32>) {
    let r = ctx.frames[j][[y, x]];
    let (inv_g, rv) = ctx.noise[j];
    v.push(ctx.maps[j].apply(r));
    sig.push((r.max(0.0) * inv_g + rv).sqrt() * ctx.maps[j].scale.abs());
}

/// Sources of frame `j` in its first-pass sky-subtracted image: pixels more than
/// `source_sigma` sigma (Poisson + read noise) above the sky, grown by `source_grow_px`.
fn source_mask(ctx: &Ctx, j: usize, sky: &Array2<f32>) -> Array2<bool> {
    let f = &ctx.frames[j];
    let (ny, nx) = f.dim();
    let (inv_g, rv) = ctx.noise[j];
    let level = ctx.levels[j] as f32;
    let k = ctx.opts.source_sigma as f32;
    let hit = Array2::from_shape_fn((ny, nx), |(y, x)| {
        let r = f[[y, x]];
        let s = match ctx.opts.scaling {
            SkyScaling::Multiplicative => sky[[y, x]] * level,
            SkyScaling::Additive => sky[[y, x]] + level,
        };
        let d = r - s;
        d > 0.0 && d * d > k * k * (r.max(0.0) * inv_g + rv)
    });
    let g = ctx.opts.source_grow_px;
    if g == 0 {
        return hit;
    }
    let mut out = Array2::from_elem((ny, nx), false);
    for ((y, x), &h) in hit.indexed_iter() {
        // A lone pixel above threshold is noise (0.1 % of pixels at 3 sigma): grow only
        // pixels with a neighbour above threshold too.
        let neighbour = (y > 0 && hit[[y - 1, x]])
            || (y + 1 < ny && hit[[y + 1, x]])
            || (x > 0 && hit[[y, x - 1]])
            || (x + 1 < nx && hit[[y, x + 1]]);
        if h && neighbour {
            for yy in y.saturating_sub(g)..(y + g + 1).min(ny) {
                for xx in x.saturating_sub(g)..(x + g + 1).min(nx) {
                    out[[yy, xx]] = true;
                }
            }
        }
    }
    out
}
