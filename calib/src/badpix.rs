//! Bad pixels: detected from the science frames themselves, loaded from a calibration
//! mask, combined, and applied as [`mask::BAD`].
//!
//! Detection ([`detect_bad_pixels`]) uses what the dithers give for free: the stars
//! move on the detector between dithers (and rotate between orientations) while hot and
//! dead pixels, dead clusters and bad column segments stay put. So:
//!
//! 1. the per-pixel median of all frames of a sequence, each scaled to the mean sky level,
//!    keeps the defects and loses the stars;
//! 2. each pixel of that median image is compared with a running median along x (window
//!    `window_px`, default 15): the strip edges are horizontal, so a 1-D median along the
//!    rows is not confused by them, while bad columns are vertical and stand out;
//! 3. a pixel is bad when the residual deviates from the strip's median residual by more
//!    than `sigma` robust standard deviations (1.4826 x MAD of the residuals of that
//!    strip), positive = hot, negative = dead/low.
//!
//! Only rows inside the six strips are tested: elsewhere the focal mask blocks the sky and
//! a defect cannot be told from the dark background (nor does it matter).
use std::path::Path;

use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::frame::{mask, Frame};
use crate::profile::Profile;
use crate::stack::{self, Affine};

/// Options of [`detect_bad_pixels`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BadPixelOptions {
    /// Threshold in robust standard deviations of the residual (median stack minus
    /// running median), per strip.
    pub sigma: f64,
    /// Running-median window along x, px (odd; even values are rounded up; at most 31).
    /// Must exceed twice the widest defect along a row (dead clusters: ~5 px).
    pub window_px: usize,
    /// Also require |residual| >= this, ADU (guards noiseless or very low-noise data).
    pub min_deviation_adu: f64,
}

impl Default for BadPixelOptions {
    fn default() -> Self {
        BadPixelOptions {
            sigma: 6.0,
            window_px: 15,
            min_deviation_adu: 0.0,
        }
    }
}

/// What [`detect_bad_pixels`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct BadPixelReport {
    /// Frames in the median stack.
    pub frames: usize,
    /// Pixels above the threshold (hot, warm columns...).
    pub hot: usize,
    /// Pixels below it (dead, low-response, dead clusters).
    pub low: usize,
    /// hot + low.
    pub total: usize,
    /// Robust standard deviation of the residual per strip, (strip name, ADU).
    pub strip_sigma_adu: Vec<(String, f64)>,
    /// Threshold used, sigma.
    pub sigma: f64,
    /// Running-median window used, px.
    pub window_px: usize,
}

/// One strip's result: name, robust sigma (ADU), and (y, x, hot) of its bad pixels.
type StripHits = (&'static str, f64, Vec<(usize, usize, bool)>);

fn stage_err(reason: String) -> Error {
    Error::Stage {
        stage: "badpix",
        reason,
    }
}

/// Median of a vector (reordered in place); upper middle for even counts.
fn select_median(v: &mut [f32]) -> f32 {
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
}

/// Detect pixels that stay deviant on the detector while the sky and stars move (see
/// the module documentation). `frames`: all frames of a sequence (at least 3, one
/// shape, NaN-free; the more dithers and orientations the cleaner). Returns a mask
/// (`mask::BAD` where bad, 0 elsewhere) and counts.
pub fn detect_bad_pixels(
    frames: &[&Frame],
    profile: &Profile,
    opts: &BadPixelOptions,
) -> Result<(Array2<u8>, BadPixelReport)> {
    detect_bad_pixels_at(frames, None, profile, opts)
}

/// Frames within this distance (px, header offsets) are at one dither position for
/// [`dither_groups`]: a star keeps most of its flux within a few FWHM (~4 px on SOFI).
pub const SAME_POSITION_PX: f64 = 10.0;

/// Group frames by dither position (header offsets (dx, dy), px): frames within
/// [`SAME_POSITION_PX`] of a group's first frame join it. Returns the group of each frame
/// (0, 1, ... in order of first appearance).
pub fn dither_groups(offsets: &[[f64; 2]]) -> Vec<usize> {
    let mut reps: Vec<[f64; 2]> = Vec::new();
    offsets
        .iter()
        .map(|o| {
            match reps
                .iter()
                .position(|r| (r[0] - o[0]).hypot(r[1] - o[1]) < SAME_POSITION_PX)
            {
                Some(g) => g,
                None => {
                    reps.push(*o);
                    reps.len() - 1
                }
            }
        })
        .collect()
}

/// Check the frame count, options, frame shapes and profile strips; returns the common shape.
fn check_inputs(
    frames: &[&Frame],
    offsets: Option<&[[f64; 2]]>,
    profile: &Profile,
    opts: &BadPixelOptions,
) -> Result<(usize, usize)> {
    let n = frames.len();
    if let Some(o) = offsets {
        if o.len() != n {
            return Err(stage_err(format!("{} offsets for {n} frames", o.len())));
        }
    }
    if n < 3 {
        return Err(stage_err(format!(
            "{n} frames given: need at least 3 dithered frames so that stars drop out of the median"
        )));
    }
    if n > stack::MAX_STACK {
        return Err(stage_err(format!(
            "{n} frames given: at most {} per median stack",
            stack::MAX_STACK
        )));
    }
    if opts.sigma.is_nan() || opts.sigma <= 0.0 || opts.window_px < 3 || 2 * (opts.window_px / 2) + 1 > stack::MAX_STACK
    {
        return Err(stage_err(format!(
            "sigma = {} must be > 0 and window_px = {} must be in 3..={}",
            opts.sigma,
            opts.window_px,
            stack::MAX_STACK - 1
        )));
    }
    let shape = frames[0].shape();
    if let Some((i, f)) = frames.iter().enumerate().find(|(_, f)| f.shape() != shape) {
        return Err(stage_err(format!(
            "{} (frame {i}) is {}x{} but the first frame is {}x{}",
            f.path().display(),
            f.shape().0,
            f.shape().1,
            shape.0,
            shape.1
        )));
    }
    let g = &profile.geometry;
    let strip_end = g.lit_rows_end();
    if shape.0 < strip_end {
        return Err(stage_err(format!(
            "frames have {} rows but the profile's strips reach row {strip_end}",
            shape.0
        )));
    }
    Ok(shape)
}

/// Median stack of the frames scaled (or offset) to their mean sky level; with too few
/// dither positions, a median per position and then the minimum / median of those.
fn common_level_median(frames: &[&Frame], offsets: Option<&[[f64; 2]]>, profile: &Profile) -> Result<Array2<f32>> {
    let levels: Vec<f64> = frames
        .par_iter()
        .map(|f| crate::sky::sky_level(f, profile))
        .collect::<Result<_>>()?;
    let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.data.view()).collect();
    median_at_levels(&views, &levels, offsets)
}

/// The stack of [`common_level_median`] of `views` at the frames' sky `levels`.
fn median_at_levels(views: &[ArrayView2<f32>], levels: &[f64], offsets: Option<&[[f64; 2]]>) -> Result<Array2<f32>> {
    let n = views.len();
    let mean_level = levels.iter().sum::<f64>() / n as f64;
    let maps: Vec<Affine> = if levels.iter().all(|&l| l > 0.0) {
        levels
            .iter()
            .map(|&l| Affine {
                scale: (mean_level / l) as f32,
                offset: 0.0,
            })
            .collect()
    } else {
        levels
            .iter()
            .map(|&l| Affine {
                scale: 1.0,
                offset: (mean_level - l) as f32,
            })
            .collect()
    };
    let groups = offsets.map(dither_groups).unwrap_or_else(|| (0..n).collect());
    let n_groups = groups.iter().max().map_or(0, |g| g + 1);
    let largest = (0..n_groups)
        .map(|g| groups.iter().filter(|&&k| k == g).count())
        .max()
        .unwrap_or(0);
    let med = if 2 * largest < n {
        stack::median_stack_affine(views, &maps)?
    } else {
        if n_groups < 2 {
            return Err(stage_err(format!(
                "all {n} frames at one dither position (header offsets within {SAME_POSITION_PX} px): \
                 stars cannot be told from defects"
            )));
        }
        let per_group: Vec<Array2<f32>> = (0..n_groups)
            .map(|g| {
                let idx: Vec<usize> = (0..n).filter(|&j| groups[j] == g).collect();
                let v: Vec<ArrayView2<f32>> = idx.iter().map(|&j| views[j].view()).collect();
                let m: Vec<Affine> = idx.iter().map(|&j| maps[j]).collect();
                stack::median_stack_affine(&v, &m)
            })
            .collect::<Result<_>>()?;
        if n_groups == 2 {
            let mut lo = per_group[0].clone();
            Zip::from(&mut lo).and(&per_group[1]).for_each(|a, &b| *a = a.min(b));
            lo
        } else {
            let v: Vec<ArrayView2<f32>> = per_group.iter().map(|a| a.view()).collect();
            stack::median_stack(&v)?
        }
    };

    Ok(med)
}

/// Robust sigma (1.4826 MAD, from every 3rd pixel: +-0.7 % at 57k samples) and
/// threshold per strip, strips in parallel.
fn strip_hits(resid: &Array2<f32>, profile: &Profile, opts: &BadPixelOptions) -> Vec<StripHits> {
    profile
        .geometry
        .strips()
        .par_iter()
        .filter(|(_, [y0, y1])| y1 > y0) // a cropped profile has empty strips
        .map(|&(name, [y0, y1])| {
            let block = resid.slice(ndarray::s![y0..y1, ..]);
            let mut v: Vec<f32> = block.iter().step_by(3).copied().collect();
            let centre = select_median(&mut v);
            for x in v.iter_mut() {
                *x = (*x - centre).abs();
            }
            let sigma = 1.4826 * select_median(&mut v) as f64;
            let thr = (opts.sigma * sigma) as f32;
            let min_dev = opts.min_deviation_adu as f32;
            let mut hits = Vec::new();
            for y in y0..y1 {
                for (x, &r) in resid.row(y).iter().enumerate() {
                    let r = r - centre;
                    // Strictly beyond the threshold: a noiseless strip (sigma 0) flags
                    // only real deviations.
                    if r.abs() > thr && r.abs() >= min_dev {
                        hits.push((y, x, r > 0.0));
                    }
                }
            }
            (name, sigma, hits)
        })
        .collect()
}

/// [`detect_bad_pixels`] knowing where the stars are: `offsets`, the header offset of each
/// frame (None: unknown, every frame taken as its own position). The target of every
/// sequence sits at the same detector position for a given dither offset, whatever the
/// rotator angle, so the frames of one position all hold a star on the same pixels. When
/// one position holds at least half of the frames (2 dithers per orientation: exactly
/// half) the plain median keeps that star (the star core was masked as a defect and the
/// target's flux lost). Then the stack is built per position instead: the median of each
/// position's frames, and across positions the median (3 or more positions) or the
/// per-pixel minimum (2 positions: the star is in one of them, a defect in both). One
/// position only is an error (a star cannot be told from a defect).
pub fn detect_bad_pixels_at(
    frames: &[&Frame],
    offsets: Option<&[[f64; 2]]>,
    profile: &Profile,
    opts: &BadPixelOptions,
) -> Result<(Array2<u8>, BadPixelReport)> {
    let shape = check_inputs(frames, offsets, profile, opts)?;
    // 1. Median stack at a common level.
    let med = common_level_median(frames, offsets, profile)?;
    defects_of_stack(med, shape, frames.len(), profile, opts)
}

/// [`detect_bad_pixels_at`] on the rows `[r0, r1)` only, for a reduction that uses only
/// those rows: every frame's sky level is measured on the whole frame as there, the stack,
/// its running median and the strips' thresholds are computed on those rows alone (a third
/// of the work on SOFI). The rows must hold whole strips of the profile (the target strips:
/// each strip's threshold comes from its own pixels), so the mask of those rows is the
/// one [`detect_bad_pixels_at`] finds there, bit for bit. Returns the mask of the rows
/// `[r0, r1)` (`r1 - r0` rows; its row 0 is row r0 of the frames).
pub fn detect_bad_pixels_in_rows(
    frames: &[&Frame],
    offsets: Option<&[[f64; 2]]>,
    profile: &Profile,
    opts: &BadPixelOptions,
    (r0, r1): (usize, usize),
) -> Result<(Array2<u8>, BadPixelReport)> {
    let (ny, nx) = check_inputs(frames, offsets, profile, opts)?;
    let g = &profile.geometry;
    let whole = g
        .strips()
        .iter()
        .all(|(_, [a, b])| b <= &r0 || a >= &r1 || (a >= &r0 && b <= &r1));
    if r0 >= r1 || r1 > ny || !whole {
        return Err(stage_err(format!(
            "rows [{r0}, {r1}) of {ny}: not whole strips of the profile, or outside the frames"
        )));
    }
    let med = stack_in_rows(frames, offsets, profile, (r0, r1))?;
    defects_of_stack(med, (r1 - r0, nx), frames.len(), &profile.cropped_rows(r0, r1), opts)
}

/// [`detect_bad_pixels_in_rows`] from the rows `[r0, r1)` of the frames alone (`parts[i]`:
/// frame i cropped to them, [`Frame::crop_rows`]) and the sky levels of the whole frames
/// (`levels[i]`: [`crate::sky::sky_level`] of frame i before cropping), so that a caller
/// reading many frames keeps only their rows: the same mask, bit for bit.
pub fn detect_bad_pixels_from_rows(
    parts: &[&Frame],
    levels: &[f64],
    offsets: Option<&[[f64; 2]]>,
    profile: &Profile,
    opts: &BadPixelOptions,
    (r0, r1): (usize, usize),
) -> Result<(Array2<u8>, BadPixelReport)> {
    let cropped = profile.cropped_rows(r0, r1);
    let (ny, nx) = check_inputs(parts, offsets, &cropped, opts)?;
    let g = &profile.geometry;
    let whole = g
        .strips()
        .iter()
        .all(|(_, [a, b])| b <= &r0 || a >= &r1 || (a >= &r0 && b <= &r1));
    if r0 >= r1 || r1 > g.ny || !whole || ny != r1 - r0 || levels.len() != parts.len() {
        return Err(stage_err(format!(
            "rows [{r0}, {r1}) of {}: not whole strips of the profile, or {} frames of {ny} rows with {} levels",
            g.ny,
            parts.len(),
            levels.len()
        )));
    }
    let views: Vec<ArrayView2<f32>> = parts.iter().map(|f| f.data.view()).collect();
    let med = median_at_levels(&views, levels, offsets)?;
    defects_of_stack(med, (ny, nx), parts.len(), &cropped, opts)
}

/// The rows `[r0, r1)` of [`common_level_median`]: the levels from the whole frames.
fn stack_in_rows(
    frames: &[&Frame],
    offsets: Option<&[[f64; 2]]>,
    profile: &Profile,
    (r0, r1): (usize, usize),
) -> Result<Array2<f32>> {
    let levels: Vec<f64> = frames
        .par_iter()
        .map(|f| crate::sky::sky_level(f, profile))
        .collect::<Result<_>>()?;
    let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.data.slice(ndarray::s![r0..r1, ..])).collect();
    median_at_levels(&views, &levels, offsets)
}

/// Steps 2 and 3 of [`detect_bad_pixels_at`] on the median stack `med` of `n` frames.
fn defects_of_stack(
    med: Array2<f32>,
    (ny, nx): (usize, usize),
    n: usize,
    profile: &Profile,
    opts: &BadPixelOptions,
) -> Result<(Array2<u8>, BadPixelReport)> {
    // 2. Residual from a running median along x (all rows: the few blocked rows cost
    //    less than skipping them).
    let h = opts.window_px / 2;
    let run = stack::running_median_x(med.view(), h)?;
    let resid = &med - &run;

    // 3. Robust sigma and threshold per strip, strips in parallel.
    let per_strip = strip_hits(&resid, profile, opts);
    let mut out = Array2::<u8>::zeros((ny, nx));
    let mut report = BadPixelReport {
        frames: n,
        hot: 0,
        low: 0,
        total: 0,
        strip_sigma_adu: Vec::new(),
        sigma: opts.sigma,
        window_px: 2 * h + 1,
    };
    for (name, sigma, hits) in per_strip {
        report.strip_sigma_adu.push((name.to_string(), sigma));
        for (y, x, hot) in hits {
            out[[y, x]] = mask::BAD;
            if hot {
                report.hot += 1;
            } else {
                report.low += 1;
            }
        }
    }
    report.total = report.hot + report.low;
    Ok((out, report))
}

/// Read a calibration bad-pixel mask from a FITS image: nonzero (or NaN) = bad. Returns
/// `mask::BAD` where bad, 0 elsewhere.
pub fn load_mask(path: &Path) -> Result<Array2<u8>> {
    let f = crate::fits::read_frame(path)?;
    Ok(f.data.mapv(|v| if v != 0.0 || v.is_nan() { mask::BAD } else { 0 }))
}

/// Union of two bad-pixel masks (nonzero = bad), as `mask::BAD`/0. Shapes must agree.
pub fn combine_masks(a: &Array2<u8>, b: &Array2<u8>) -> Result<Array2<u8>> {
    if a.dim() != b.dim() {
        return Err(stage_err(format!(
            "cannot combine bad-pixel masks of {}x{} and {}x{} (ny x nx)",
            a.dim().0,
            a.dim().1,
            b.dim().0,
            b.dim().1
        )));
    }
    Ok(Zip::from(a)
        .and(b)
        .map_collect(|&p, &q| if p != 0 || q != 0 { mask::BAD } else { 0 }))
}

/// A copy of `frame` with [`mask::BAD`] set wherever `bad` is nonzero; data, variance and
/// the other mask bits are unchanged. Appends a `badpix` history record.
pub fn apply_mask(frame: &Frame, bad: &Array2<u8>) -> Result<Frame> {
    let mut out = frame.clone();
    apply_mask_in_place(&mut out, bad)?;
    Ok(out)
}

/// [`apply_mask`] in place (no copy of the frame); on error the frame is unchanged.
pub fn apply_mask_in_place(frame: &mut Frame, bad: &Array2<u8>) -> Result<()> {
    if bad.dim() != frame.mask.dim() {
        return Err(stage_err(format!(
            "{}: bad-pixel mask is {}x{} but the frame is {}x{} (ny x nx)",
            frame.path().display(),
            bad.dim().0,
            bad.dim().1,
            frame.shape().0,
            frame.shape().1
        )));
    }
    let (total, newly) = match (frame.mask.as_slice_mut(), bad.as_slice()) {
        (Some(m), Some(b)) => set_bad_sparse(m, b),
        _ => {
            let (mut total, mut newly) = (0usize, 0usize);
            Zip::from(&mut frame.mask).and(bad).for_each(|m, &b| {
                let hit = u8::from(b != 0);
                total += hit as usize;
                newly += (hit & u8::from(*m & mask::BAD == 0)) as usize;
                *m |= hit * mask::BAD;
            });
            (total, newly)
        }
    };
    frame.history.push(crate::frame::HistoryRecord::new(
        "badpix",
        format!("bad-pixel mask applied: {total} pixels BAD ({newly} newly); data unchanged"),
    ));
    Ok(())
}

/// Bytes of the bad-pixel mask tested together by [`set_bad_sparse`].
const SPARSE_CHUNK: usize = 64;

/// Sets [`mask::BAD`] in `m` wherever `bad` is nonzero; returns (pixels set in `bad`, of
/// those the ones not BAD before). This runs on every frame of the night, and a detector
/// mask is sparse (~0.1 % of the pixels): the mask is scanned in chunks with a
/// branch-free OR (vectorised), and only the rare chunks holding a bad pixel touch the
/// frame's mask, which is otherwise neither read nor written.
fn set_bad_sparse(m: &mut [u8], bad: &[u8]) -> (usize, usize) {
    debug_assert_eq!(m.len(), bad.len());
    let (mut total, mut newly) = (0usize, 0usize);
    let mut one = |m: &mut u8, b: u8| {
        if b != 0 {
            total += 1;
            newly += usize::from(*m & mask::BAD == 0);
            *m |= mask::BAD;
        }
    };
    let mut mc = m.chunks_exact_mut(SPARSE_CHUNK);
    let mut bc = bad.chunks_exact(SPARSE_CHUNK);
    for (mch, bch) in (&mut mc).zip(&mut bc) {
        if bch.iter().fold(0u8, |a, &b| a | b) != 0 {
            mch.iter_mut().zip(bch).for_each(|(m, &b)| one(m, b));
        }
    }
    mc.into_remainder()
        .iter_mut()
        .zip(bc.remainder())
        .for_each(|(m, &b)| one(m, b));
    (total, newly)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::header::Header;

    fn synthetic(j: usize) -> Frame {
        let p = Profile::sofi();
        let mut d = Array2::from_shape_fn((1024, 1024), |(y, x)| {
            if p.geometry.row_in_strip(y) {
                // Hash noise (sum of 4 uniforms, sd ~7 ADU) plus a gradient.
                let mut z = ((y * 1024 + x) as u64) << 8 | j as u64;
                let mut n = 0f32;
                for _ in 0..4 {
                    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
                    let mut q = z;
                    q = (q ^ (q >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                    q = (q ^ (q >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                    q ^= q >> 31;
                    n += ((q >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 12.0;
                }
                1500.0 + 0.05 * x as f32 + n
            } else {
                0.0
            }
        });
        for dy in -2i64..=2 {
            for dx in -2i64..=2 {
                d[[(400 + dy) as usize, (100 + 87 * j as i64 + dx) as usize]] += 3000.0;
            }
        }
        d[[300, 300]] = 20000.0;
        d[[700, 10]] = 0.0;
        for y in 100..160 {
            d[[y, 512]] = 5000.0;
        }
        Frame::new(d, Header::new(format!("f{j}.fits")))
    }

    #[test]
    fn finds_hot_dead_and_column_but_not_moving_star() {
        let frames: Vec<Frame> = (0..5).map(synthetic).collect();
        let refs: Vec<&Frame> = frames.iter().collect();
        let (m, rep) = detect_bad_pixels(&refs, &Profile::sofi(), &BadPixelOptions::default()).unwrap();
        assert_eq!(m[[300, 300]], mask::BAD);
        assert_eq!(m[[700, 10]], mask::BAD);
        assert!((100..160).all(|y| m[[y, 512]] == mask::BAD));
        assert_eq!(rep.total, 62, "{rep:?}");
        assert_eq!((rep.hot, rep.low), (61, 1));
        assert_eq!(m[[400, 100]], 0);
        // apply_mask sets BAD only and keeps data.
        let a = apply_mask(&frames[0], &m).unwrap();
        assert_eq!(a.data, frames[0].data);
        assert_eq!(a.mask[[300, 300]], mask::BAD);
        assert!(a.history.last().unwrap().detail.contains("62 pixels BAD"));
        let c = combine_masks(&m, &Array2::from_elem((1024, 1024), 0u8)).unwrap();
        assert_eq!(c, m);
        let e = combine_masks(&m, &Array2::zeros((3, 3))).unwrap_err().to_string();
        assert!(e.contains("3x3"), "{e}");
        let e = detect_bad_pixels(&refs[..2], &Profile::sofi(), &BadPixelOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 frames") && e.contains("at least 3"), "{e}");
    }

    /// Detection on the target strips' rows finds, there, the mask detection on whole
    /// frames finds, bit for bit: defects inside and outside those rows, frames at
    /// different sky levels (the levels come from the whole frames), the plain median and
    /// the per-position stacks (header offsets with 2 positions); rows that cut a strip
    /// are refused.
    #[test]
    fn detection_on_the_target_rows_is_detection_on_whole_frames_there() {
        let p = Profile::sofi();
        let frames: Vec<Frame> = (0..5)
            .map(|j| {
                let mut f = synthetic(j);
                f.data.mapv_inplace(|v| v * (1.0 + 0.07 * j as f32));
                f.data[[500, 200]] = 20000.0;
                f.data[[600, 700]] = 0.0;
                for y in 520..560 {
                    f.data[[y, 800]] += 900.0;
                }
                f
            })
            .collect();
        let refs: Vec<&Frame> = frames.iter().collect();
        let opts = BadPixelOptions::default();
        let rows = (345, 679);
        let two = [[0.0, 0.0], [87.0, 0.0], [0.0, 0.0], [87.0, 0.0], [0.0, 0.0]];
        for offsets in [None, Some(&two[..])] {
            // The stack itself (levels from the whole frames), bit for bit.
            let bits = |a: ndarray::ArrayView2<f32>| a.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let full = common_level_median(&refs, offsets, &p).unwrap();
            let cut = stack_in_rows(&refs, offsets, &p, rows).unwrap();
            assert_eq!(
                bits(cut.view()),
                bits(full.slice(ndarray::s![345..679, ..])),
                "offsets {offsets:?}"
            );
            let (whole, _) = detect_bad_pixels_at(&refs, offsets, &p, &opts).unwrap();
            let (part, rep) = detect_bad_pixels_in_rows(&refs, offsets, &p, &opts, rows).unwrap();
            assert_eq!(part, whole.slice(ndarray::s![345..679, ..]), "offsets {offsets:?}");
            // From the rows alone and the whole frames' levels: the same.
            let levels: Vec<f64> = refs.iter().map(|f| crate::sky::sky_level(f, &p).unwrap()).collect();
            let cut: Vec<Frame> = refs.iter().map(|f| (*f).clone().crop_rows(345, 679)).collect();
            let cut_refs: Vec<&Frame> = cut.iter().collect();
            let (from_rows, rep2) = detect_bad_pixels_from_rows(&cut_refs, &levels, offsets, &p, &opts, rows).unwrap();
            assert_eq!(from_rows, part, "offsets {offsets:?}");
            assert_eq!(rep2.total, rep.total);
            // Levels of the rows alone would be another stack (the test above would fail).
            let row_levels: Vec<f64> = cut_refs
                .iter()
                .map(|f| crate::sky::sky_level(f, &p.cropped_rows(345, 679)).unwrap())
                .collect();
            assert_ne!(row_levels, levels);
            assert_eq!(part[[500 - 345, 200]], mask::BAD);
            assert_eq!(part[[600 - 345, 700]], mask::BAD);
            assert!((520..560).all(|y| part[[y - 345, 800]] == mask::BAD));
            assert_eq!(rep.strip_sigma_adu.len(), 2, "{rep:?}");
        }
        let e = detect_bad_pixels_in_rows(&refs, None, &p, &opts, (300, 679))
            .unwrap_err()
            .to_string();
        assert!(e.contains("[300, 679)") && e.contains("whole strips"), "{e}");
    }

    /// The dense, obviously correct definition of [`set_bad_sparse`].
    fn set_bad_dense(m: &mut [u8], bad: &[u8]) -> (usize, usize) {
        let (mut total, mut newly) = (0, 0);
        for (m, &b) in m.iter_mut().zip(bad) {
            if b != 0 {
                total += 1;
                if *m & mask::BAD == 0 {
                    newly += 1;
                }
                *m |= mask::BAD;
            }
        }
        (total, newly)
    }

    #[test]
    fn sparse_mask_application_matches_the_dense_one() {
        let mut z = 0x1234_5678_9abc_def0u64;
        let mut next = move || {
            z ^= z << 13;
            z ^= z >> 7;
            z ^= z << 17;
            z
        };
        // Lengths around the chunk size and its multiples; densities from empty to full.
        for len in [0, 1, 63, 64, 65, 127, 128, 200, 1000, 4099] {
            for density in [0u64, 1, 8, 128, 256] {
                let bad: Vec<u8> = (0..len)
                    .map(|_| {
                        if next() % 256 < density {
                            (next() % 255 + 1) as u8
                        } else {
                            0
                        }
                    })
                    .collect();
                // Frame masks with other bits and some BAD bits already set.
                let m0: Vec<u8> = (0..len).map(|_| (next() % 64) as u8).collect();
                let (mut a, mut b) = (m0.clone(), m0.clone());
                let got = set_bad_sparse(&mut a, &bad);
                let want = set_bad_dense(&mut b, &bad);
                assert_eq!(got, want, "len {len} density {density}");
                assert_eq!(a, b, "len {len} density {density}");
            }
        }
        // The in-place application on a non-standard-layout mask (the Zip path) agrees.
        let bad = Array2::from_shape_fn((37, 70), |(y, x)| u8::from((y * 70 + x) % 97 == 3));
        let mut f = Frame::new(Array2::zeros((37, 70)), Header::new("t.fits"));
        f.mask = Array2::from_shape_fn((37, 70), |(y, x)| ((y + x) % 3) as u8);
        let mut g = f.clone();
        g.mask = Array2::from_shape_fn(ndarray::ShapeBuilder::f((37, 70)), |(y, x)| f.mask[[y, x]]);
        assert!(!g.mask.is_standard_layout());
        apply_mask_in_place(&mut f, &bad).unwrap();
        apply_mask_in_place(&mut g, &bad).unwrap();
        assert_eq!(f.mask, g.mask);
        assert_eq!(f.history, g.history);
    }

    #[test]
    fn load_mask_reads_nonzero_as_bad() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bpm.fits");
        let mut d = Array2::<f32>::zeros((8, 6));
        d[[2, 3]] = 1.0;
        d[[7, 0]] = -4.0;
        let f = Frame::new(d, Header::new(&path));
        crate::fits::write_frame(&path, &f, &crate::fits::WriteOptions::default()).unwrap();
        let m = load_mask(&path).unwrap();
        assert_eq!(m.dim(), (8, 6));
        assert_eq!(m.iter().filter(|&&b| b == mask::BAD).count(), 2);
        assert_eq!(m[[2, 3]], mask::BAD);
        assert_eq!(m[[7, 0]], mask::BAD);
        let e = load_mask(&dir.path().join("missing.fits")).unwrap_err().to_string();
        assert!(e.contains("missing.fits"), "{e}");
    }
}
