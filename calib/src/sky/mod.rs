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
//! [`sky_subtract_flat`] also divides by a flat in the same last pass (all dithers of an
//! orientation row block by row block, the flat's rows read once for all of them):
//! data = (raw - sky) / flat, variance / flat^2 plus the flat's noise on the signal
//! ([`crate::flat::FlatRows`]; the same reduction as dividing the raw frames first, for
//! the default multiplicative scaling). With the default estimator (the plain median of
//! the other dithers) that pass computes the leave-one-out medians itself, a row block at a
//! time while the raw rows are in cache, instead of writing whole sky frames out and
//! reading them back (the same numbers; test `the_fused_sky_pass_matches_the_two_pass_stage`),
//! and it collects the cosmic-ray candidates of each row it has just written.
//!
//! [`flag_cosmic_rays`] then marks sharp positive outliers of the sky-subtracted frame
//! (outliers in time, because the sky is the other dithers, *and* in space, because they
//! are much sharper than the PSF) with [`crate::frame::mask::COSMIC`].
//!
//! Files: this one (options, levels, the stage `sky_subtract_by` step by step, history);
//! `fused.rs` (the last pass over the frames' buffers, block by block); `lanes.rs` (its
//! arithmetic on a block, portable and vector builds); `estimate.rs` (the clipped mean and
//! the source-masked pass); `cosmic.rs` (cosmic-ray flagging).
use ndarray::ArrayView2;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::flat::FlatRows;
use crate::frame::Frame;
use crate::profile::{frame_ndit, Profile};
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

/// How the sky of a dither is estimated from the other dithers (after level scaling).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SkyEstimator {
    /// Per-pixel median of the other dithers (default; robust to a star in one of them,
    /// one selection network per pixel for all dithers, [`crate::stack`]).
    #[default]
    Median,
    /// Per-pixel mean of the other dithers after dropping values farther than
    /// `clip_sigma` x their expected noise (Poisson + read) from the median: less noisy
    /// than the median (variance factor 1 instead of c(m)), slower.
    ClippedMean,
}

impl SkyEstimator {
    /// Name as in the settings.
    pub fn name(self) -> &'static str {
        match self {
            SkyEstimator::Median => "median",
            SkyEstimator::ClippedMean => "clipped_mean",
        }
    }
}

fn is_default<T: Default + PartialEq>(v: &T) -> bool {
    *v == T::default()
}

fn default_clip_sigma() -> f64 {
    3.0
}

fn is_default_clip_sigma(v: &f64) -> bool {
    *v == default_clip_sigma()
}

fn default_source_sigma() -> f64 {
    3.0
}

fn is_default_source_sigma(v: &f64) -> bool {
    *v == default_source_sigma()
}

fn default_source_grow_px() -> usize {
    2
}

fn is_default_source_grow_px(v: &usize) -> bool {
    *v == default_source_grow_px()
}

/// Options of [`sky_subtract`]. `Default` is [`SkyOptions::recommended`]: multiplicative
/// scaling, the median of the other dithers, no source masking, and cosmic-ray flagging,
/// also for every key a `[sky]` table leaves out (a table with only `scaling` used to
/// drop the flagging silently). Turn flagging off with `[sky.cosmic_rays] enabled = false`.
/// Keys at their defaults are not written out (provenance stays as it was).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SkyOptions {
    /// Level scaling.
    pub scaling: SkyScaling,
    /// Flag cosmic rays in each sky-subtracted frame ([`flag_cosmic_rays`]); `None`: don't.
    pub cosmic_rays: Option<CosmicOptions>,
    /// Estimator of the sky from the other dithers.
    #[serde(skip_serializing_if = "is_default")]
    pub estimator: SkyEstimator,
    /// `clipped_mean`: values farther than this many sigma from the median are dropped.
    #[serde(skip_serializing_if = "is_default_clip_sigma")]
    pub clip_sigma: f64,
    /// Second pass: sources found in the first-pass sky-subtracted dithers (pixels above
    /// `source_sigma` sigma, grown by `source_grow_px`) are left out of the other dithers'
    /// skies, which are estimated again.
    #[serde(skip_serializing_if = "is_default")]
    pub mask_sources: bool,
    /// Source threshold of the second pass, sigma of the pixel noise.
    #[serde(skip_serializing_if = "is_default_source_sigma")]
    pub source_sigma: f64,
    /// Source pixels are grown by this many pixels (box) before masking.
    #[serde(skip_serializing_if = "is_default_source_grow_px")]
    pub source_grow_px: usize,
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

    /// Multiplicative scaling, median of the other dithers, no source masking, cosmic-ray
    /// flagging with default thresholds.
    pub fn recommended() -> Self {
        SkyOptions {
            scaling: SkyScaling::Multiplicative,
            cosmic_rays: Some(CosmicOptions::default()),
            estimator: SkyEstimator::Median,
            clip_sigma: default_clip_sigma(),
            mask_sources: false,
            source_sigma: default_source_sigma(),
            source_grow_px: default_source_grow_px(),
        }
    }

    /// The allowed ranges of the estimator settings: `clip_sigma` and `source_sigma`
    /// finite and > 0, `source_grow_px` <= 10. The error names the key and value.
    pub fn check(&self) -> Result<()> {
        let bad = |key: &str, v: String, want: &str| Error::Stage {
            stage: "sky",
            reason: format!("sky.{key} = {v}: must be {want}"),
        };
        if !(self.clip_sigma.is_finite() && self.clip_sigma > 0.0) {
            return Err(bad("clip_sigma", self.clip_sigma.to_string(), "finite and > 0"));
        }
        if !(self.source_sigma.is_finite() && self.source_sigma > 0.0) {
            return Err(bad("source_sigma", self.source_sigma.to_string(), "finite and > 0"));
        }
        if self.source_grow_px > 10 {
            return Err(bad("source_grow_px", self.source_grow_px.to_string(), "in 0..=10"));
        }
        Ok(())
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
    let mut v = strip_sample(frame, profile)?;
    Ok(median_of_keys(&mut v))
}

/// The pixels [`sky_level`] takes its median of, as `total_cmp`-ordered integer keys; an
/// error naming the frame when there is none.
fn strip_sample(frame: &Frame, profile: &Profile) -> Result<Vec<i32>> {
    const STEP: usize = 8;
    let (ny, nx) = frame.shape();
    let g = &profile.geometry;
    let sat = profile.detector.saturation_adu as f32;
    // Integer keys in `total_cmp` order: the same element is selected, with integer
    // comparisons.
    let mut v: Vec<i32> = Vec::with_capacity(ny * nx / STEP + ny);
    for y in (0..ny).filter(|&y| g.row_in_strip(y)) {
        let (d, m) = (frame.data.row(y), frame.mask.row(y));
        for x in ((y * 3) % STEP..nx).step_by(STEP) {
            let val = d[x];
            if m[x] == 0 && val < sat && val.is_finite() {
                v.push(crate::flat::lanes::key(val));
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
    Ok(v)
}

/// The median (upper middle element) of a non-empty sample of keys, ADU.
fn median_of_keys(v: &mut [i32]) -> f64 {
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable(k);
    crate::flat::lanes::from_key(*m) as f64
}

/// The sky level L of a frame ([`sky_level`]) when the sky stage can use it with
/// `scaling`, else an error naming the frame and saying why. Additive scaling needs a
/// measurable level. Multiplicative scaling divides each frame by its level, so the level
/// must stand out of the pixel noise: L > sigma, with sigma = 1.4826 x the median absolute
/// deviation of the same pixels (a real sky of L ADU has sigma ~ sqrt(L / gain) and more,
/// L / sigma ~ 40 at 1500 ADU; a frame whose data were negated, byte-swapped or already
/// sky-subtracted has L <= 0 or L of the order of sigma, and would put its own noise
/// divided by ~0 into the other dithers' skies).
pub fn usable_sky_level(frame: &Frame, profile: &Profile, scaling: SkyScaling) -> Result<f64> {
    let mut v = strip_sample(frame, profile)?;
    let level = median_of_keys(&mut v);
    if scaling == SkyScaling::Additive {
        return Ok(level);
    }
    let mut dev: Vec<i32> = v
        .iter()
        .map(|&k| crate::flat::lanes::key((crate::flat::lanes::from_key(k) as f64 - level).abs() as f32))
        .collect();
    let sigma = 1.4826 * median_of_keys(&mut dev);
    if level > sigma {
        return Ok(level);
    }
    Err(Error::Stage {
        stage: "sky",
        reason: format!(
            "{}: sky level {} ADU is not above the pixel scatter {} ADU (1.4826 x MAD of the {} unmasked, \
             unsaturated pixels sampled in the strip rows): no sky to scale the dithers by (saturated, negated, \
             byte-swapped or already sky-subtracted data?)",
            frame_name(frame, 0),
            adu(level),
            adu(sigma),
            v.len()
        ),
    })
}

/// A level in ADU for a message: 2 decimals, or 3 significant digits when tiny.
fn adu(x: f64) -> String {
    if x != 0.0 && x.abs() < 0.01 {
        format!("{x:.2e}")
    } else {
        format!("{x:.2}")
    }
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
    check_inputs(frames, profile, opts)?;
    sky_subtract_owned(frames.to_vec(), profile, opts)
}

/// [`sky_subtract_with_report`] on frames the caller gives away: their buffers become
/// the outputs' (the data, mask and variance maps are not copied), with the same numbers
/// bit for bit.
pub fn sky_subtract_owned(frames: Vec<Frame>, profile: &Profile, opts: &SkyOptions) -> Result<(Vec<Frame>, SkyReport)> {
    sky_subtract_flat(frames, profile, opts, None)
}

/// [`sky_subtract_owned`] of raw frames that also divides them by a flat (the flat's rows
/// matching the frames): data = (raw - sky) / flat, the variance as
/// [`crate::flat::apply_flat`] gives it followed by this stage, in the same last pass
/// ([`crate::flat::FlatRows`]). With multiplicative scaling (the default) the per-pixel
/// sky of the other dithers is estimated on the raw values, which divides by the shared
/// flat like the frames; with additive scaling, where it would not, the frames are divided
/// by the flat first ([`crate::flat::apply_flat_in_place`]). Errors name the flat when its
/// rows do not cover the frames.
pub fn sky_subtract_flat(
    frames: Vec<Frame>,
    profile: &Profile,
    opts: &SkyOptions,
    flat: Option<&FlatRows>,
) -> Result<(Vec<Frame>, SkyReport)> {
    sky_subtract_by(frames, profile, opts, flat, Route::FAST)
}

/// How [`sky_subtract_by`] computes: the fast way ([`Route::FAST`], what the reduction
/// uses), or a reference way the tests compare it with bit for bit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Route {
    /// The plain leave-one-out medians (the default estimator) inside the last pass, a
    /// row block at a time while the raw rows are in cache (`true`), or over whole frames
    /// before it, as the other estimators are (`false`).
    pub(crate) fuse_medians: bool,
    /// The build of the last pass's row kernel.
    pub(crate) kernel: Kernel,
}

impl Route {
    /// Medians in the last pass, the fastest kernel build.
    pub(crate) const FAST: Route = Route {
        fuse_medians: true,
        kernel: Kernel::Fastest,
    };
}

/// [`sky_subtract_flat`] the `route` way (the same numbers every way).
pub(crate) fn sky_subtract_by(
    mut frames: Vec<Frame>,
    profile: &Profile,
    opts: &SkyOptions,
    flat: Option<&FlatRows>,
    route: Route,
) -> Result<(Vec<Frame>, SkyReport)> {
    check_inputs(&frames, profile, opts)?;
    let flat = flat_in_the_pass(&mut frames, profile, opts, flat)?;
    let n = frames.len();
    let levels = sky_levels(&frames, profile, opts.scaling)?;
    let ndits: Vec<u32> = frames.iter().map(|f| frame_ndit(f, profile)).collect::<Result<_>>()?;
    // Each frame brought to a common level before the medians.
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
    let det = &profile.detector;
    // Per frame: 1 / effective gain and the read variance, ADU.
    let noise: Vec<(f32, f32)> = ndits
        .iter()
        .map(|&nd| ((1.0 / det.effective_gain(nd)) as f32, det.read_variance_adu2(nd) as f32))
        .collect();
    // The plain leave-one-out median (the default) is computed inside the last pass, a
    // row block at a time, while the raw rows are in cache (the same numbers as computing
    // it first); the other estimators first, over whole frames.
    let fused = route.fuse_medians && opts.estimator == SkyEstimator::Median && !opts.mask_sources;
    let (skies, counts) = if fused {
        (SkySource::Loo(stack::LooRows::new(&maps)), vec![None; n])
    } else {
        let views: Vec<ArrayView2<f32>> = frames.iter().map(|f| f.data.view()).collect();
        let ctx = estimate::Ctx {
            frames: &views,
            maps: &maps,
            levels: &levels,
            noise: &noise,
            opts,
        };
        let (skies, counts) = estimate::skies(&ctx)?;
        (SkySource::Given(skies), counts)
    };
    let m = n - 1;
    let c = estimate::variance_factor(opts.estimator, m);
    let names: Vec<String> = frames.iter().enumerate().map(|(i, f)| frame_name(f, i)).collect();
    let g = &profile.geometry;
    let fin = Finish {
        scaling: opts.scaling,
        off_rows: (0..frames[0].shape().0).map(|y| !g.row_in_strip(y)).collect(),
        sat: det.saturation_adu as f32,
        nonlin: det.nonlinear_warn_adu as f32,
        c_over_m: (c / m as f64) as f32,
        c_over_count: estimate::c_over_count_table(opts.estimator),
        cosmic_k2: opts.cosmic().map(cosmic::candidate_threshold),
    };
    let has_vin: Vec<bool> = frames.iter().map(|f| f.variance.is_some()).collect();
    let inp = FinishInputs {
        counts: &counts,
        levels: levels.iter().map(|&l| l as f32).collect(),
        noise: &noise,
        names: &names,
        flat,
    };
    let (done, candidates) = fused::subtract_skies(&fin, frames, skies, &inp, route.kernel)?;
    let mut out = Vec::with_capacity(n);
    let mut cosmic = Vec::new();
    let record = RecordInputs {
        opts,
        profile,
        levels_adu: &levels,
        names: &names,
        c,
    };
    for (i, (mut frame, candidates)) in done.into_iter().zip(candidates).enumerate() {
        let others: Vec<usize> = (0..n).filter(|&j| j != i).collect();
        let detail = sky_record(&record, i, &others, ndits[i], has_vin[i]);
        frame.history.push(crate::frame::HistoryRecord::new("sky", detail));
        if let Some(co) = opts.cosmic() {
            let var = frame.variance.as_ref().expect("set by the sky stage");
            let rep = cosmic_flags_from(&frame.data, &var.view(), &mut frame.mask, co, &candidates);
            frame.history.push(cosmic_record(co, &rep));
            cosmic.push(rep);
        }
        // Marked as a product: written out (`--save-intermediate`) it must never be read
        // back as a raw frame (crate::classify::PRODUCT_KEYWORD).
        frame.header.set_with_comment(
            crate::classify::PRODUCT_KEYWORD,
            "SKYSUB",
            "sofipol product (sky-subtracted), not a raw frame",
        );
        out.push(frame);
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

/// The flat to divide out in the last pass: `flat` when its rows cover the frames (else
/// an error naming it), with multiplicative scaling; with additive scaling the frames are
/// divided by it here, first, and the pass gets none.
fn flat_in_the_pass<'f>(
    frames: &mut [Frame],
    profile: &Profile,
    opts: &SkyOptions,
    flat: Option<&'f FlatRows<'f>>,
) -> Result<Option<&'f FlatRows<'f>>> {
    let Some(fr) = flat else {
        return Ok(None);
    };
    let (ny, nx) = frames[0].shape();
    let (fny, fnx) = fr.flat.shape();
    if fnx != nx || fr.row0 + ny > fny || fr.ny() != ny {
        return Err(Error::Stage {
            stage: "flat",
            reason: format!(
                "{}: frame shape {:?} at flat row {} does not fit the {} of shape {:?}{}",
                frame_name(&frames[0], 0),
                (ny, nx),
                fr.row0,
                fr.flat.describe(),
                fr.flat.shape(),
                fr.flat
                    .path
                    .as_ref()
                    .map(|p| format!(" ({})", p.display()))
                    .unwrap_or_default()
            ),
        });
    }
    if opts.scaling == SkyScaling::Additive {
        for f in frames.iter_mut() {
            crate::flat::apply_flat_in_place(f, fr.flat, fr.row0, profile)?;
        }
        return Ok(None);
    }
    Ok(Some(fr))
}

/// The sky level L_i of every frame ([`sky_level`]), in parallel; with multiplicative
/// scaling an error names the first frame whose level is not positive.
fn sky_levels(frames: &[Frame], profile: &Profile, scaling: SkyScaling) -> Result<Vec<f64>> {
    let levels: Vec<f64> = frames
        .par_iter()
        .map(|f| sky_level(f, profile))
        .collect::<Result<_>>()?;
    if scaling == SkyScaling::Multiplicative {
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
    Ok(levels)
}

/// What the sky records of an orientation's frames share ([`sky_record`]).
struct RecordInputs<'a> {
    /// The sky stage's settings.
    opts: &'a SkyOptions,
    /// The instrument (detector numbers for the variance model and the mask).
    profile: &'a Profile,
    /// Sky level L_i of every frame, ADU.
    levels_adu: &'a [f64],
    /// Every frame's name.
    names: &'a [String],
    /// The variance factor c(m) of the estimator, m = the frames in a sky (dimensionless).
    c: f64,
}

/// The sky stage's history record of frame `i` (its sky from the frames `others`, `ndit`
/// DITs, `has_vin` with an input variance map): the scaling and levels, the estimator, the
/// variance model with its numbers (c = c(m)), the mask bits set.
fn sky_record(inputs: &RecordInputs, i: usize, others: &[usize], ndit: u32, has_vin: bool) -> String {
    let RecordInputs {
        opts,
        profile,
        levels_adu: levels,
        names,
        c,
    } = *inputs;
    let det = &profile.detector;
    let m = others.len();
    format!(
        "{} scaling, level {:.2} ADU; sky = {} of the other {m} dithers [{}] (levels {}); \
         variance = Poisson (gain {} e-/ADU x NDIT {}) + read ({} e-)^2/gain^2/NDIT{} + c({m}) = {:.6} / {m} x sky variance; \
         mask: SATURATED >= {} ADU, NONLINEAR >= {} ADU, OFF_STRIP outside the strips",
        opts.scaling.name(),
        levels[i],
        estimate::describe(opts),
        others.iter().map(|&j| names[j].as_str()).collect::<Vec<_>>().join(", "),
        others.iter().map(|&j| format!("{:.2}", levels[j])).collect::<Vec<_>>().join(", "),
        det.gain_e_per_adu,
        ndit,
        det.read_noise_e,
        if has_vin { " (input variance map used for this frame)" } else { "" },
        c,
        det.saturation_adu,
        det.nonlinear_warn_adu,
    )
}

/// The checks of [`sky_subtract`]: 2..=MAX_STACK frames of one shape, masks and variance
/// maps of that shape, the strips inside the frames, valid cosmic-ray and sky options.
fn check_inputs(frames: &[Frame], profile: &Profile, opts: &SkyOptions) -> Result<()> {
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
    opts.check()?;
    let shape = frames[0].shape();
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
    let strip_end = profile.geometry.lit_rows_end();
    if shape.0 < strip_end {
        return Err(Error::Stage {
            stage: "sky",
            reason: format!(
                "frames have {} rows but the profile's strips reach row {strip_end}",
                shape.0
            ),
        });
    }
    Ok(())
}

mod cosmic;
mod estimate;
mod fused;
mod lanes;

use fused::SkySource;
pub(crate) use lanes::Kernel;
use lanes::{Finish, FinishInputs};

#[cfg(test)]
use cosmic::cosmic_flags;
pub use cosmic::flag_cosmic_rays;
use cosmic::{check_cosmic_options, cosmic_flags_from, cosmic_record};

#[cfg(test)]
mod tests;
