//! Cosmic-ray flagging of sky-subtracted frames.
use ndarray::Array2;
use rayon::prelude::*;

use super::{frame_name, CosmicOptions, CosmicReport};
use crate::error::{Error, Result};
use crate::frame::{mask, Frame};

/// Pixels of a row whose seed candidate flags are computed together.
const SEED_CHUNK: usize = 64;

/// Mask bits that exclude a pixel from cosmic-ray tests (as candidate and as neighbour).
const CR_SKIP: u8 = mask::BAD | mask::OFF_STRIP | mask::SATURATED;

pub(super) fn check_cosmic_options(opts: &CosmicOptions) -> Result<()> {
    if !(opts.sigma_clip > 0.0 && opts.sharpness_ratio >= 0.0 && opts.grow_sigma > 0.0) {
        return Err(Error::Stage {
            stage: "cosmic",
            reason: format!(
                "thresholds sigma_clip = {}, sharpness_ratio = {}, grow_sigma = {} must be > 0, >= 0, > 0",
                opts.sigma_clip, opts.sharpness_ratio, opts.grow_sigma
            ),
        });
    }
    Ok(())
}

pub(super) fn cosmic_record(opts: &CosmicOptions, rep: &CosmicReport) -> crate::frame::HistoryRecord {
    crate::frame::HistoryRecord::new(
        "cosmic",
        format!(
            "sigma_clip {} sigma, sharpness ratio {} (value - ratio x mean4 > sigma_clip sigma), grow {} sigma x {}: \
             {} seeds + {} grown = {} pixels flagged COSMIC",
            opts.sigma_clip,
            opts.sharpness_ratio,
            opts.grow_sigma,
            opts.grow_iterations,
            rep.seeds,
            rep.grown,
            rep.total
        ),
    )
}

/// Flag cosmic rays in a sky-subtracted frame (one with a variance map): seeds are pixels
/// with value > `sigma_clip` sigma and value - `sharpness_ratio` x max(mean of unmasked
/// 4-neighbours, 0) > `sigma_clip` sigma; then 8-connected neighbours of flagged pixels
/// above `grow_sigma` sigma are added, `grow_iterations` times. Pixels marked BAD,
/// OFF_STRIP or SATURATED are never tested nor used as neighbours. Data are not changed.
pub fn flag_cosmic_rays(frame: &Frame, opts: &CosmicOptions) -> Result<(Frame, CosmicReport)> {
    let var = frame.variance.as_ref().ok_or_else(|| Error::Stage {
        stage: "cosmic",
        reason: format!("{}: no variance map (run the sky stage first)", frame_name(frame, 0)),
    })?;
    check_cosmic_options(opts)?;
    if var.dim() != frame.data.dim() || frame.mask.dim() != frame.data.dim() {
        return Err(Error::Stage {
            stage: "cosmic",
            reason: format!(
                "{}: variance or mask shape differs from the data's",
                frame_name(frame, 0)
            ),
        });
    }
    let mut out = frame.clone();
    if !out.data.is_standard_layout() {
        out.data = out.data.as_standard_layout().into_owned();
    }
    if !out.mask.is_standard_layout() {
        out.mask = out.mask.as_standard_layout().into_owned();
    }
    let var = var.as_standard_layout();
    let rep = cosmic_flags(&out.data, &var.view(), &mut out.mask, opts);
    out.history.push(cosmic_record(opts, &rep));
    Ok((out, rep))
}

/// Core of [`flag_cosmic_rays`]: sets COSMIC bits in `msk` (same shapes, standard layout).
pub(super) fn cosmic_flags(
    d: &Array2<f32>,
    var: &ndarray::ArrayView2<f32>,
    msk: &mut Array2<u8>,
    opts: &CosmicOptions,
) -> CosmicReport {
    let (ny, nx) = d.dim();
    let k2 = candidate_threshold(opts);
    let (ds, vs) = (
        d.as_slice().expect("standard layout"),
        var.as_slice().expect("standard layout"),
    );
    // Candidates row-parallel, in row-major order.
    let candidates: Vec<u32> = (0..ny)
        .into_par_iter()
        .flat_map_iter(|y| {
            let row = y * nx..(y + 1) * nx;
            let mut c = Vec::new();
            push_candidates(&ds[row.clone()], &vs[row], k2, (y * nx) as u32, &mut c);
            c.into_iter()
        })
        .collect();
    cosmic_flags_from(d, var, msk, opts, &candidates)
}

/// The squared threshold of [`push_candidates`] for `opts`.
pub(super) fn candidate_threshold(opts: &CosmicOptions) -> f32 {
    let k = opts.sigma_clip as f32;
    k * k
}

/// The candidate seeds of one row (data `drow`, variance `vrow`; `first` = the flat index
/// of its first pixel), appended to `out` in order: value > k sigma (squared, `k2` =
/// [`candidate_threshold`]: no sqrt), the cheap test that rejects almost every pixel
/// before the neighbours are read. Branch-free (vectorised) over chunks of the row, then a
/// scan of the rare candidates only in the chunks that hold one: a per-pixel
/// `v > 0 && ...` branch mispredicts half the time. The sky stage runs it on each row it
/// has just written, while the row is in cache.
#[inline]
pub(super) fn push_candidates(drow: &[f32], vrow: &[f32], k2: f32, first: u32, out: &mut Vec<u32>) {
    let mut cand = [0u8; SEED_CHUNK];
    for (c, (dch, vch)) in drow.chunks(SEED_CHUNK).zip(vrow.chunks(SEED_CHUNK)).enumerate() {
        for ((o, &v), &vv) in cand.iter_mut().zip(dch).zip(vch) {
            *o = u8::from(v > 0.0) & u8::from(v * v > k2 * vv);
        }
        let cand = &cand[..dch.len()];
        if cand.iter().fold(0u8, |a, &b| a | b) == 0 {
            continue;
        }
        for (j, _) in cand.iter().enumerate().filter(|(_, &f)| f != 0) {
            out.push(first + (c * SEED_CHUNK + j) as u32);
        }
    }
}

/// [`cosmic_flags`] from its candidates ([`push_candidates`] over every row, in row-major
/// order; flat indices): the seed test on each, then the growth.
pub(super) fn cosmic_flags_from(
    d: &Array2<f32>,
    var: &ndarray::ArrayView2<f32>,
    msk: &mut Array2<u8>,
    opts: &CosmicOptions,
    candidates: &[u32],
) -> CosmicReport {
    let (ny, nx) = d.dim();
    let (k, r) = (opts.sigma_clip as f32, opts.sharpness_ratio as f32);
    let mk: &Array2<u8> = msk;
    let (ds, vs, ms) = (
        d.as_slice().expect("standard layout"),
        var.as_slice().expect("standard layout"),
        mk.as_slice().expect("standard layout"),
    );
    // The seed test of one candidate pixel: unmasked, and above k sigma over `r` times
    // the mean of its usable 4-neighbours.
    let seed = |i: usize| {
        let (y, x) = (i / nx, i % nx);
        let (v, vv) = (ds[i], vs[i]);
        if ms[i] & CR_SKIP != 0 {
            return false;
        }
        let (mut sum, mut cnt) = (0f32, 0u32);
        let mut add = |j: usize| {
            if ms[j] & CR_SKIP == 0 {
                sum += ds[j];
                cnt += 1;
            }
        };
        if y > 0 {
            add(i - nx);
        }
        if y + 1 < ny {
            add(i + nx);
        }
        if x > 0 {
            add(i - 1);
        }
        if x + 1 < nx {
            add(i + 1);
        }
        if cnt == 0 {
            return false;
        }
        let mean4 = (sum / cnt as f32).max(0.0);
        v - r * mean4 > k * vv.max(0.0).sqrt()
    };
    let seeds: Vec<(usize, usize)> = candidates
        .iter()
        .map(|&i| i as usize)
        .filter(|&i| seed(i))
        .map(|i| (i / nx, i % nx))
        .collect();
    for &(y, x) in &seeds {
        msk[[y, x]] |= mask::COSMIC;
    }
    let mut frontier = seeds.clone();
    let mut grown = 0;
    let gk = opts.grow_sigma as f32;
    for _ in 0..opts.grow_iterations {
        let mut next = Vec::new();
        for &(y, x) in &frontier {
            for yy in y.saturating_sub(1)..(y + 2).min(ny) {
                for xx in x.saturating_sub(1)..(x + 2).min(nx) {
                    if msk[[yy, xx]] & (CR_SKIP | mask::COSMIC) != 0 {
                        continue;
                    }
                    if d[[yy, xx]] > gk * var[[yy, xx]].max(0.0).sqrt() {
                        msk[[yy, xx]] |= mask::COSMIC;
                        next.push((yy, xx));
                        grown += 1;
                    }
                }
            }
        }
        if next.is_empty() {
            break;
        }
        frontier = next;
    }
    CosmicReport {
        seeds: seeds.len(),
        grown,
        total: seeds.len() + grown,
    }
}
