//! Sky subtraction from the dithers themselves, and cosmic-ray flagging.
//!
//! The stars move between the dithers of one orientation (jitter ~87 px along x) while
//! the sky and the detector stay put, so the sky of dither i is the per-pixel median of
//! the *other* dithers ([`crate::stack`], one selection network per pixel for all of
//! them), each first brought to a common level:
//!
//! * [`SkyScaling::Multiplicative`] (default): sky_i = L_i x median_{j != i}(raw_j / L_j);
//! * [`SkyScaling::Additive`]: sky_i = L_i + median_{j != i}(raw_j - L_j);
//!
//! with L_j the frame's sky level ([`sky_level`]: median over the strip rows of the
//! unmasked, unsaturated pixels). The output frame is raw - sky with a variance map
//! (ADU^2) and the mask bits of the input plus SATURATED, NONLINEAR and OFF_STRIP:
//!
//! ```text
//! var = max(raw, 0) / (g NDIT) + (RON/g)^2 / NDIT                      (this frame)
//!     + c(m)/m x [ max(sky, 0) / (g NDIT) + (RON/g)^2 / NDIT ]         (the sky estimate)
//! ```
//!
//! m = N - 1 is the number of frames in each median and c(m) = m Var(median)/sigma^2
//! for Gaussian samples ([`median_variance_factor`]; docs/calibration.md). When the
//! input frame already carries a variance map, it replaces the first line.
//!
//! [`flag_cosmic_rays`] then marks sharp positive outliers of the sky-subtracted frame
//! (outliers in time, because the sky is the other dithers, *and* in space, because they
//! are much sharper than the PSF) with [`mask::COSMIC`].
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::frame::{mask, Frame};
use crate::profile::Profile;
use crate::stack::{self, Affine};

/// How the other dithers are brought to this frame's sky level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SkyScaling {
    /// sky_i = L_i x median(raw_j / L_j): the sky pattern (flat-field and illumination)
    /// scales with the level. The usual choice for near-infrared sky.
    #[default]
    Multiplicative,
    /// sky_i = L_i + median(raw_j - L_j): the pattern is a fixed additive structure
    /// (thermal background, bias residuals) on top of a varying level.
    Additive,
}

impl SkyScaling {
    fn name(self) -> &'static str {
        match self {
            SkyScaling::Multiplicative => "multiplicative",
            SkyScaling::Additive => "additive",
        }
    }
}

/// Cosmic-ray detection thresholds.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CosmicOptions {
    /// Flag cosmic rays at all (`false` turns the flagging off).
    pub enabled: bool,
    /// A seed pixel exceeds this many sigma (sqrt of the variance map) above the sky.
    pub sigma_clip: f64,
    /// ... and exceeds `sharpness_ratio` x the mean of its unmasked 4-neighbours by
    /// `sigma_clip` sigma: value - ratio x max(mean4, 0) > sigma_clip x sigma. A pixel-
    /// integrated Gaussian star of FWHM 1.7 px centred on a pixel has value / mean4 = 2.3,
    /// broader stars less; a single-pixel hit has a ratio of hundreds, the head of a
    /// 2-4 pixel track about 8.
    pub sharpness_ratio: f64,
    /// Neighbours (8-connected) of flagged pixels above this many sigma are flagged too
    /// (the tails of tracks).
    pub grow_sigma: f64,
    /// Growth passes (a 4-pixel track needs 3).
    pub grow_iterations: usize,
}

impl Default for CosmicOptions {
    fn default() -> Self {
        CosmicOptions {
            enabled: true,
            sigma_clip: 5.0,
            sharpness_ratio: 4.0,
            grow_sigma: 3.0,
            grow_iterations: 3,
        }
    }
}

/// Options of [`sky_subtract`]. `Default` is [`SkyOptions::recommended`]: multiplicative
/// scaling and cosmic-ray flagging, also for every key a `[sky]` table leaves out (a table
/// with only `scaling` used to drop the flagging silently). Turn flagging off with
/// `[sky.cosmic_rays] enabled = false`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SkyOptions {
    /// Level scaling.
    pub scaling: SkyScaling,
    /// Flag cosmic rays in each sky-subtracted frame ([`flag_cosmic_rays`]); `None`: don't.
    pub cosmic_rays: Option<CosmicOptions>,
}

impl Default for SkyOptions {
    fn default() -> Self {
        Self::recommended()
    }
}

impl SkyOptions {
    /// The cosmic-ray options in force (`None` when absent or `enabled = false`).
    pub fn cosmic(&self) -> Option<&CosmicOptions> {
        self.cosmic_rays.as_ref().filter(|c| c.enabled)
    }

    /// Multiplicative scaling and cosmic-ray flagging with default thresholds.
    pub fn recommended() -> Self {
        SkyOptions {
            scaling: SkyScaling::Multiplicative,
            cosmic_rays: Some(CosmicOptions::default()),
        }
    }
}

/// What [`flag_cosmic_rays`] found in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CosmicReport {
    /// Pixels passing both the sigma and the sharpness test.
    pub seeds: usize,
    /// Pixels added by growth around the seeds.
    pub grown: usize,
    /// seeds + grown (pixels newly flagged COSMIC).
    pub total: usize,
}

/// What [`sky_subtract_with_report`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct SkyReport {
    /// Sky level L_i of each input frame, ADU.
    pub levels_adu: Vec<f64>,
    /// Frames in each median (N - 1).
    pub median_of: usize,
    /// c(m) used in the variance of the sky estimate.
    pub median_variance_factor: f64,
    /// Cosmic-ray counts per frame (empty when not requested).
    pub cosmic: Vec<CosmicReport>,
}

/// c(m) = m Var(median of m iid N(0, sigma^2)) / sigma^2, for m = 1..=32 (index m - 1).
///
/// Computed by numerical integration of the exact order-statistic densities (odd m: the
/// density of X_(k+1); even m: the joint density of X_(k), X_(k+1), median their mean),
/// with scipy `quad`/`dblquad`, and checked against Monte Carlo (4e5 draws each for
/// m <= 12) and the classical Var(median of 3) = 0.4487 sigma^2. For m = 2 the median
/// is the mean (c = 1); c -> pi/2 as m grows (odd m from below, even m more slowly).
pub const MEDIAN_VARIANCE_FACTOR: [f64; 32] = [
    1.000000, 1.000000, 1.346013, 1.192798, 1.434168, 1.288456, 1.473128, 1.345447, 1.494912, 1.383264, 1.508787,
    1.410194, 1.518387, 1.430350, 1.525420, 1.446003, 1.530792, 1.458513, 1.535029, 1.468741, 1.538455, 1.477258,
    1.541283, 1.484463, 1.543656, 1.490635, 1.545677, 1.495984, 1.547418, 1.500663, 1.548933, 1.504790,
];

/// c(m): Var(median of m Gaussian values) = c(m) sigma^2 / m. Table
/// [`MEDIAN_VARIANCE_FACTOR`] for m <= 32, the asymptote pi/2 beyond (within 1.5 % for
/// odd and 4.5 % for even m = 33). m = 0 is treated as 1.
pub fn median_variance_factor(m: usize) -> f64 {
    match m {
        0 => 1.0,
        1..=32 => MEDIAN_VARIANCE_FACTOR[m - 1],
        _ => std::f64::consts::FRAC_PI_2,
    }
}

/// Reads averaged in the frame: the profile's NDIT keyword, 1 when absent (an error when
/// present but not a positive integer).
pub fn frame_ndit(frame: &Frame, profile: &Profile) -> Result<u32> {
    let key = &profile.keywords.ndit;
    if !frame.header.contains(key) {
        return Ok(1);
    }
    let v = frame.header.get_i64(key)?;
    if v < 1 || v > u32::MAX as i64 {
        return Err(Error::BadKeyword {
            path: frame.header.path.clone(),
            keyword: key.clone(),
            value: v.to_string(),
            reason: "NDIT must be a positive integer".into(),
        });
    }
    Ok(v as u32)
}

fn posang_text(frame: &Frame, profile: &Profile) -> String {
    match frame.header.opt_f64(&profile.keywords.posang) {
        Ok(Some(p)) => format!("{p}"),
        _ => "(unknown)".into(),
    }
}

fn frame_name(frame: &Frame, i: usize) -> String {
    let p = frame.path();
    if p.as_os_str().is_empty() {
        format!("frame {i}")
    } else {
        p.file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| p.display().to_string())
    }
}

/// Sky level of a frame, ADU: the median of the pixels in the strip rows that carry no
/// mask bit and lie below the saturation level, sampled one pixel in 8 along each row
/// (phase shifted row to row: ~125k pixels on SOFI, so the median's statistical error
/// is ~0.004 sigma_pixel, 2e-5 of the level, and it costs ~1 ms).
pub fn sky_level(frame: &Frame, profile: &Profile) -> Result<f64> {
    const STEP: usize = 8;
    let (ny, nx) = frame.shape();
    let g = &profile.geometry;
    let sat = profile.detector.saturation_adu as f32;
    let mut v: Vec<f32> = Vec::with_capacity(ny * nx / STEP + ny);
    for y in (0..ny).filter(|&y| g.row_in_strip(y)) {
        let (d, m) = (frame.data.row(y), frame.mask.row(y));
        for x in ((y * 3) % STEP..nx).step_by(STEP) {
            let val = d[x];
            if m[x] == 0 && val < sat && val.is_finite() {
                v.push(val);
            }
        }
    }
    if v.is_empty() {
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "{}: no unmasked, unsaturated pixel in the strip rows to measure the sky level",
                frame_name(frame, 0)
            ),
        });
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    Ok(*m as f64)
}

/// Sky-subtract the dithers of ONE orientation (see the module documentation). Output
/// frame i = input frame i minus its sky, with variance, mask bits and history. Needs at
/// least 2 frames of one shape, NaN-free. With `opts.cosmic_rays`, cosmic rays are
/// flagged too.
pub fn sky_subtract(frames: &[Frame], profile: &Profile, opts: &SkyOptions) -> Result<Vec<Frame>> {
    sky_subtract_with_report(frames, profile, opts).map(|(f, _)| f)
}

/// [`sky_subtract`] that also returns levels and cosmic-ray counts.
pub fn sky_subtract_with_report(
    frames: &[Frame],
    profile: &Profile,
    opts: &SkyOptions,
) -> Result<(Vec<Frame>, SkyReport)> {
    let n = frames.len();
    if n < 2 {
        let pa = frames
            .first()
            .map(|f| posang_text(f, profile))
            .unwrap_or_else(|| "(none)".into());
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "fewer than 2 dithers at POSANG {pa} ({n} given): cannot sky-subtract from the data itself"
            ),
        });
    }
    if n > stack::MAX_STACK {
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "{n} dithers at POSANG {}: at most {} per call",
                posang_text(&frames[0], profile),
                stack::MAX_STACK
            ),
        });
    }
    if let Some(co) = opts.cosmic() {
        check_cosmic_options(co)?;
    }
    let shape = frames[0].shape();
    let g = &profile.geometry;
    for (i, f) in frames.iter().enumerate() {
        if f.shape() != shape {
            return Err(Error::Stage {
                stage: "sky",
                reason: format!(
                    "{} is {}x{} (ny x nx) but {} is {}x{}",
                    frame_name(f, i),
                    f.shape().0,
                    f.shape().1,
                    frame_name(&frames[0], 0),
                    shape.0,
                    shape.1
                ),
            });
        }
        if f.mask.dim() != shape || f.variance.as_ref().is_some_and(|v| v.dim() != shape) {
            return Err(Error::Stage {
                stage: "sky",
                reason: format!("{}: mask or variance shape differs from the data's", frame_name(f, i)),
            });
        }
    }
    let strip_end = g.strips().iter().map(|(_, r)| r[1]).max().unwrap_or(0);
    if shape.0 < strip_end {
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "frames have {} rows but the profile's strips reach row {strip_end}",
                shape.0
            ),
        });
    }

    let levels: Vec<f64> = frames
        .par_iter()
        .map(|f| sky_level(f, profile))
        .collect::<Result<_>>()?;
    if opts.scaling == SkyScaling::Multiplicative {
        if let Some((i, l)) = levels.iter().enumerate().find(|(_, l)| l.is_nan() || **l <= 0.0) {
            return Err(Error::Stage {
                stage: "sky",
                reason: format!(
                    "{}: sky level {l} ADU <= 0: multiplicative scaling impossible (use additive)",
                    frame_name(&frames[i], i)
                ),
            });
        }
    }
    let ndits: Vec<u32> = frames.iter().map(|f| frame_ndit(f, profile)).collect::<Result<_>>()?;
    let maps: Vec<Affine> = levels
        .iter()
        .map(|&l| match opts.scaling {
            SkyScaling::Multiplicative => Affine {
                scale: (1.0 / l) as f32,
                offset: 0.0,
            },
            SkyScaling::Additive => Affine {
                scale: 1.0,
                offset: -l as f32,
            },
        })
        .collect();
    let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.data.view()).collect();
    let loo = stack::leave_one_out_medians_affine(&views, &maps)?;

    let m = n - 1;
    let c = median_variance_factor(m);
    let det = &profile.detector;
    let (sat, nonlin) = (det.saturation_adu as f32, det.nonlinear_warn_adu as f32);
    let off_rows: Vec<bool> = (0..shape.0).map(|y| !g.row_in_strip(y)).collect();
    let names: Vec<String> = frames.iter().enumerate().map(|(i, f)| frame_name(f, i)).collect();

    let mut out = Vec::with_capacity(n);
    let mut cosmic = Vec::new();
    let nx = shape.1;
    let c_over_m = (c / m as f64) as f32;
    for (i, (f, mut sky)) in frames.iter().zip(loo).enumerate() {
        let level = levels[i] as f32;
        let inv_g = (1.0 / det.effective_gain(ndits[i])) as f32;
        let rv = det.read_variance_adu2(ndits[i]) as f32;
        let scaling = opts.scaling;
        // One pass, row-parallel: sky <- level-scaled median, then data = raw - sky
        // (in the same buffer), variance and mask alongside. Counts non-finite inputs,
        // which the medians cannot handle (checked here rather than in a separate pass).
        let raw = f.data.as_standard_layout();
        let vin = f.variance.as_ref().map(|v| v.as_standard_layout());
        let mut var = Array2::<f32>::zeros(shape);
        let mut msk = f.mask.as_standard_layout().into_owned();
        let nonfinite: usize = sky
            .as_slice_mut()
            .expect("fresh array")
            .par_chunks_mut(nx)
            .zip(var.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
            .zip(msk.as_slice_mut().expect("standard layout").par_chunks_mut(nx))
            .zip(raw.as_slice().expect("standard layout").par_chunks(nx))
            .enumerate()
            .map(|(y, (((srow, vrow), mrow), rrow))| {
                match scaling {
                    SkyScaling::Multiplicative => srow.iter_mut().for_each(|s| *s *= level),
                    SkyScaling::Additive => srow.iter_mut().for_each(|s| *s += level),
                }
                match &vin {
                    None => {
                        for ((v, &s), &r) in vrow.iter_mut().zip(srow.iter()).zip(rrow) {
                            *v = r.max(0.0) * inv_g + rv + c_over_m * (s.max(0.0) * inv_g + rv);
                        }
                    }
                    Some(vin) => {
                        // The input's own variance replaces this frame's Poisson + read model.
                        let vi = &vin.as_slice().expect("standard layout")[y * nx..(y + 1) * nx];
                        for ((v, &s), &vi) in vrow.iter_mut().zip(srow.iter()).zip(vi) {
                            *v = vi + c_over_m * (s.max(0.0) * inv_g + rv);
                        }
                    }
                }
                for (s, &r) in srow.iter_mut().zip(rrow) {
                    *s = r - *s;
                }
                let off = if off_rows[y] { mask::OFF_STRIP } else { 0 };
                for (b, &r) in mrow.iter_mut().zip(rrow) {
                    *b |= off | (((r >= sat) as u8) * mask::SATURATED) | (((r >= nonlin) as u8) * mask::NONLINEAR);
                }
                rrow.iter().filter(|r| !r.is_finite()).count()
            })
            .sum();
        if nonfinite > 0 {
            return Err(Error::Stage {
                stage: "sky",
                reason: format!(
                    "{}: {nonfinite} non-finite pixel values (NaN/inf); sky medians need finite data",
                    names[i]
                ),
            });
        }
        let others: Vec<&str> = (0..n).filter(|&j| j != i).map(|j| names[j].as_str()).collect();
        let detail = format!(
            "{} scaling, level {:.2} ADU; sky = {} of the other {m} dithers [{}] (levels {}); \
             variance = Poisson (gain {} e-/ADU x NDIT {}) + read ({} e-)^2/gain^2/NDIT{} + c({m}) = {:.6} / {m} x sky variance; \
             mask: SATURATED >= {} ADU, NONLINEAR >= {} ADU, OFF_STRIP outside the strips",
            scaling.name(),
            levels[i],
            match scaling {
                SkyScaling::Multiplicative => "level x median of raw/level",
                SkyScaling::Additive => "level + median of raw-level",
            },
            others.join(", "),
            (0..n).filter(|&j| j != i).map(|j| format!("{:.2}", levels[j])).collect::<Vec<_>>().join(", "),
            det.gain_e_per_adu,
            ndits[i],
            det.read_noise_e,
            if f.variance.is_some() { " (input variance map used for this frame)" } else { "" },
            c,
            det.saturation_adu,
            det.nonlinear_warn_adu,
        );
        let mut history = f.history.clone();
        history.push(crate::frame::HistoryRecord::new("sky", detail));
        if let Some(co) = opts.cosmic() {
            let rep = cosmic_flags(&sky, &var.view(), &mut msk, co);
            history.push(cosmic_record(co, &rep));
            cosmic.push(rep);
        }
        // Marked as a product: written out (`--save-intermediate`) it must never be read
        // back as a raw frame (crate::classify::PRODUCT_KEYWORD).
        let mut header = f.header.clone();
        header.set_with_comment(
            crate::classify::PRODUCT_KEYWORD,
            "SKYSUB",
            "sofipol product (sky-subtracted), not a raw frame",
        );
        out.push(Frame {
            data: sky,
            variance: Some(var),
            mask: msk,
            header,
            history,
        });
    }
    Ok((
        out,
        SkyReport {
            levels_adu: levels,
            median_of: m,
            median_variance_factor: c,
            cosmic,
        },
    ))
}

/// Mask bits that exclude a pixel from cosmic-ray tests (as candidate and as neighbour).
const CR_SKIP: u8 = mask::BAD | mask::OFF_STRIP | mask::SATURATED;

fn check_cosmic_options(opts: &CosmicOptions) -> Result<()> {
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

fn cosmic_record(opts: &CosmicOptions, rep: &CosmicReport) -> crate::frame::HistoryRecord {
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
fn cosmic_flags(
    d: &Array2<f32>,
    var: &ndarray::ArrayView2<f32>,
    msk: &mut Array2<u8>,
    opts: &CosmicOptions,
) -> CosmicReport {
    let (ny, nx) = d.dim();
    let (k, r) = (opts.sigma_clip as f32, opts.sharpness_ratio as f32);
    let k2 = k * k;
    let mk: &Array2<u8> = msk;
    let (ds, vs, ms) = (
        d.as_slice().expect("standard layout"),
        var.as_slice().expect("standard layout"),
        mk.as_slice().expect("standard layout"),
    );
    // Seeds, row-parallel. The cheap test (value > k sigma, squared: no sqrt) rejects
    // almost every pixel before the neighbours are read.
    let seeds: Vec<(usize, usize)> = (0..ny)
        .into_par_iter()
        .flat_map_iter(|y| {
            let row = y * nx..(y + 1) * nx;
            let (drow, vrow) = (&ds[row.clone()], &vs[row]);
            let mut hits = Vec::new();
            // Candidate flags in a branch-free (vectorised) pass, then a scan of the rare
            // candidates: a per-pixel `v > 0 && ...` branch mispredicts half the time.
            let cand: Vec<bool> = drow
                .iter()
                .zip(vrow)
                .map(|(&v, &vv)| (v > 0.0) & (v * v > k2 * vv))
                .collect();
            for x in cand.iter().enumerate().filter_map(|(x, &c)| c.then_some(x)) {
                let (v, vv) = (drow[x], vrow[x]);
                let i = y * nx + x;
                if ms[i] & CR_SKIP != 0 {
                    continue;
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
                    continue;
                }
                let mean4 = (sum / cnt as f32).max(0.0);
                if v - r * mean4 > k * vv.max(0.0).sqrt() {
                    hits.push((y, x));
                }
            }
            hits.into_iter()
        })
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

#[cfg(test)]
mod tests;
