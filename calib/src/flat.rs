//! Flat field: the detector's pixel response, measured from dome flats or from the night's
//! own sky (a superflat), and divided out of the raw frames before sky subtraction.
//!
//! * **Dome flat** ([`dome_flat`]): per rotator angle, mean(lamp on) - mean(lamp off)
//!   (`INS LAMP1 ST` = T / F, [`LAMP_KEYWORD`]). The lamp light is itself polarized by a
//!   few percent, so the o and e strips differ in level for reasons that are not
//!   throughput: **each strip is normalized separately** (by the median of its good
//!   pixels). A flat gives the pixel-to-pixel response, never the beam ratio.
//! * **Superflat** ([`superflat`]): the sky of many dithered science frames of the night.
//!   Each frame is divided by its own sky level, strip by strip; stars (pixels more than
//!   `star_sigma` sigma above the level, grown by `star_grow_px`) and masked pixels are left
//!   out; per pixel the values are combined by a clipped, inverse-variance weighted mean
//!   around their median; then each strip is normalized to median 1.
//! * **Application** ([`apply_flat`]): data / flat with a variance map (photon + read noise
//!   of the raw frame, divided by flat^2, plus the flat's own noise on the signal above the
//!   sky level, see below) and a history record; pixels whose response is unusable get the
//!   BAD mask bit.
//!
//! The flat's own noise: the sky of a frame is estimated from the other dithers at the
//! same pixel, divided by the same flat, so a flat error at a pixel scales the frame *and*
//! its sky alike and cancels in raw - sky, except on the signal above the sky. The flat
//! variance therefore enters as `max(data - L, 0)^2 var_flat / flat^2`, L the strip's sky
//! level. Off-strip rows (blocked by the focal mask) have flat 1 and variance 0.
//!
//! Flats are written as FITS ([`write_flat`]: the response in the primary HDU, VARIANCE
//! and MASK extensions, what they were made of in the header and HISTORY: they open in
//! DS9) and read back with [`read_flat`].
use std::path::{Path, PathBuf};

use ndarray::{s, Array2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::frame::{mask, Frame, HistoryRecord};
use crate::header::{Header, HeaderValue};
use crate::profile::Profile;

/// Header keyword telling lamp on (T) from lamp off (F) in a dome flat (keyword
/// *profile*, unverified on real data; ../shared/docs/frame-format.md).
pub const LAMP_KEYWORD: &str = "ESO INS LAMP1 ST";
/// TPL ID of a dome-flat template.
pub const DOME_FLAT_TEMPLATE: &str = "SOFI_img_cal_DomeFlat";
/// DPR TYPE of a flat frame.
pub const FLAT_TYPE: &str = "FLAT";
/// Header keyword of a written flat: "dome", "superflat".
pub const KIND_KEYWORD: &str = "SOFIPOL FLAT KIND";
/// Header keyword of a written flat: rotator angle of a dome flat, deg.
pub const POSANG_KEYWORD: &str = "SOFIPOL FLAT POSANG";
/// Header keyword of a written flat: filter.
pub const FILTER_KEYWORD: &str = "SOFIPOL FLAT FILTER";
/// Header keyword of a written flat: number of frames combined.
pub const NCOMBINE_KEYWORD: &str = "SOFIPOL FLAT NCOMBINE";

/// How a flat was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlatKind {
    /// Dome flat: lamp on minus lamp off.
    Dome,
    /// Superflat from the sky of the night's science frames.
    Superflat,
}

impl FlatKind {
    /// Name as written in headers and provenance.
    pub fn name(self) -> &'static str {
        match self {
            FlatKind::Dome => "dome",
            FlatKind::Superflat => "superflat",
        }
    }
}

/// A normalized pixel response map with its variance and unusable pixels.
#[derive(Debug, Clone)]
pub struct Flat {
    /// Relative response, median 1 in every strip; 1 off-strip and where unusable.
    pub data: Array2<f32>,
    /// Variance of `data`.
    pub variance: Array2<f32>,
    /// 1 where the response is unusable (dead, non-finite, outside the allowed range, too
    /// few frames): such pixels get the BAD mask bit when the flat is applied.
    pub bad: Array2<u8>,
    /// How it was made.
    pub kind: FlatKind,
    /// Rotator angle (dome flats), deg.
    pub posang_deg: Option<f64>,
    /// Filter, when known.
    pub filter: Option<String>,
    /// Files combined.
    pub sources: Vec<String>,
    /// What was done, with the parameters (history record and provenance).
    pub detail: String,
    /// The file it was read from, when read.
    pub path: Option<PathBuf>,
}

impl Flat {
    /// Image shape (ny, nx).
    pub fn shape(&self) -> (usize, usize) {
        self.data.dim()
    }

    /// Rows [r0, r1) (pair with [`Frame::crop_rows`] and [`Profile::cropped_rows`]).
    pub fn crop_rows(&self, r0: usize, r1: usize) -> Flat {
        let ny = self.shape().0;
        let (r0, r1) = (r0.min(ny), r1.min(ny).max(r0.min(ny)));
        Flat {
            data: self.data.slice(s![r0..r1, ..]).to_owned(),
            variance: self.variance.slice(s![r0..r1, ..]).to_owned(),
            bad: self.bad.slice(s![r0..r1, ..]).to_owned(),
            ..self.clone()
        }
    }

    /// This flat (made on rows [r0, r0 + its height) of a detector of `ny` rows) placed in
    /// a full-height flat: 1 with variance 0 elsewhere.
    pub fn embed_rows(&self, r0: usize, ny: usize) -> Flat {
        let (h, nx) = self.shape();
        let r1 = (r0 + h).min(ny);
        let mut data = Array2::<f32>::ones((ny, nx));
        let mut variance = Array2::<f32>::zeros((ny, nx));
        let mut bad = Array2::<u8>::zeros((ny, nx));
        data.slice_mut(s![r0..r1, ..])
            .assign(&self.data.slice(s![..r1 - r0, ..]));
        variance
            .slice_mut(s![r0..r1, ..])
            .assign(&self.variance.slice(s![..r1 - r0, ..]));
        bad.slice_mut(s![r0..r1, ..]).assign(&self.bad.slice(s![..r1 - r0, ..]));
        Flat {
            data,
            variance,
            bad,
            detail: format!("{} (rows {r0}-{r1} of the detector; 1 elsewhere)", self.detail),
            ..self.clone()
        }
    }

    /// One line for provenance: kind, angle, filter, frames, file.
    pub fn describe(&self) -> String {
        let mut s = self.kind.name().to_string();
        if let Some(p) = self.posang_deg {
            s += &format!(" POSANG {p}");
        }
        if let Some(f) = &self.filter {
            s += &format!(" filter {f}");
        }
        s += &format!(", {} frames", self.sources.len());
        if let Some(p) = &self.path {
            s += &format!(", file {}", p.display());
        }
        s
    }

    /// A provenance object (catalog `extra`, calibration.json).
    pub fn provenance(&self) -> serde_json::Value {
        serde_json::json!({
            "kind": self.kind.name(),
            "posang_deg": self.posang_deg,
            "filter": self.filter,
            "frames": self.sources,
            "file": self.path.as_ref().map(|p| p.display().to_string()),
            "bad_pixels": self.bad.iter().filter(|&&b| b != 0).count(),
            "detail": self.detail,
        })
    }
}

/// Settings of flat building.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlatOptions {
    /// A normalized response below this is unusable (dead or vignetted away).
    pub min_response: f32,
    /// A normalized response above this is unusable (hot in the lamp frames).
    pub max_response: f32,
    /// Superflat: a pixel this many sigma above its frame's strip level is a star.
    pub star_sigma: f32,
    /// Superflat: star pixels are grown by this many pixels (box) to catch the wings.
    pub star_grow_px: usize,
    /// Superflat: values farther than this many sigma from the pixel's median are dropped.
    pub clip_sigma: f32,
    /// Superflat: fewer usable values than this at a pixel make it unusable.
    pub min_values: usize,
    /// Superflat: at most this many frames are combined.
    pub max_frames: usize,
}

impl Default for FlatOptions {
    fn default() -> Self {
        FlatOptions {
            min_response: 0.5,
            max_response: 1.5,
            star_sigma: 4.0,
            star_grow_px: 3,
            clip_sigma: 4.0,
            min_values: 5,
            max_frames: 25,
        }
    }
}

/// What the header says about a dome-flat frame.
#[derive(Debug, Clone, PartialEq)]
pub struct DomeFlatInfo {
    /// Rotator angle, deg.
    pub posang_deg: f64,
    /// Lamp on (T) or off (F).
    pub lamp_on: bool,
    /// Filter, when present.
    pub filter: Option<String>,
}

/// Whether a header is a dome flat (DPR TYPE 'FLAT', or TPL ID the dome-flat template), and
/// its rotator angle and lamp state. `Ok(None)`: not a flat; `Err`: a flat whose lamp or
/// angle keyword is missing or malformed (the error names the file and the keyword).
pub fn dome_flat_info(header: &Header, profile: &Profile) -> Result<Option<DomeFlatInfo>> {
    let kw = &profile.keywords;
    let is = |k: &str, want: &str| header.opt_str(k).is_some_and(|v| v.trim().eq_ignore_ascii_case(want));
    // The dome-flat template, or a flat (DPR TYPE) that carries the lamp keyword: a flat of
    // another template without it (a sky flat) is not a dome flat.
    let template = is(&kw.tpl_id, DOME_FLAT_TEMPLATE);
    if !(template || (is(&kw.dpr_type, FLAT_TYPE) && header.contains(LAMP_KEYWORD))) {
        return Ok(None);
    }
    let lamp_on = match header.get(LAMP_KEYWORD) {
        Some(HeaderValue::Bool(b)) => *b,
        Some(HeaderValue::Str(s)) if matches!(s.trim(), "T" | "t" | "ON" | "on") => true,
        Some(HeaderValue::Str(s)) if matches!(s.trim(), "F" | "f" | "OFF" | "off") => false,
        Some(v) => {
            return Err(Error::BadKeyword {
                path: header.path.clone(),
                keyword: LAMP_KEYWORD.into(),
                value: v.to_string(),
                reason: "expected T (lamp on) or F (lamp off)".into(),
            })
        }
        None => {
            return Err(Error::MissingKeyword {
                path: header.path.clone(),
                keyword: LAMP_KEYWORD.into(),
            })
        }
    };
    let posang_deg = header.get_f64(&kw.posang)?;
    Ok(Some(DomeFlatInfo {
        posang_deg,
        lamp_on,
        filter: header.opt_str(&kw.filter).map(|s| s.trim().to_string()),
    }))
}

fn name_of(f: &Frame, i: usize) -> String {
    let p = f.path();
    if p.as_os_str().is_empty() {
        format!("frame {i}")
    } else {
        p.display().to_string()
    }
}

fn check_shapes(frames: &[&Frame], profile: &Profile, stage: &'static str) -> Result<(usize, usize)> {
    let shape = frames.first().map(|f| f.shape()).ok_or_else(|| Error::Stage {
        stage,
        reason: "no frame".into(),
    })?;
    for (i, f) in frames.iter().enumerate() {
        if f.shape() != shape {
            return Err(Error::Stage {
                stage,
                reason: format!(
                    "{}: shape {:?} differs from {}'s {:?}",
                    name_of(f, i),
                    f.shape(),
                    name_of(frames[0], 0),
                    shape
                ),
            });
        }
    }
    let g = &profile.geometry;
    if shape.0 < g.strips().iter().map(|(_, r)| r[1]).max().unwrap_or(0) {
        return Err(Error::Stage {
            stage,
            reason: format!(
                "{}: {} rows, the profile's strips reach row {}",
                name_of(frames[0], 0),
                shape.0,
                g.strips().iter().map(|(_, r)| r[1]).max().unwrap_or(0)
            ),
        });
    }
    Ok(shape)
}

fn median_f32(v: &mut [f32]) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    Some(*v.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1)
}

/// Median of the finite values of rows [a, b) where `ok` says so (one pixel in 4).
fn strip_median(data: &Array2<f32>, a: usize, b: usize, ok: impl Fn(usize, usize, f32) -> bool) -> Option<f32> {
    strip_median_step(data, a, b, 4, ok)
}

/// Median of the finite values of rows [a, b) where `ok` says so (one pixel in `step`).
fn strip_median_step(
    data: &Array2<f32>,
    a: usize,
    b: usize,
    step: usize,
    ok: impl Fn(usize, usize, f32) -> bool,
) -> Option<f32> {
    let mut v = Vec::new();
    for y in a..b {
        let row = data.row(y);
        for x in ((y % step)..row.len()).step_by(step) {
            let val = row[x];
            if val.is_finite() && ok(y, x, val) {
                v.push(val);
            }
        }
    }
    median_f32(&mut v)
}

/// Normalize every strip of a raw response (and its variance) to median 1 over its good
/// pixels; mark unusable pixels; off-strip rows become 1 with variance 0.
fn normalize_strips(
    resp: &mut Array2<f32>,
    var: &mut Array2<f32>,
    bad: &mut Array2<u8>,
    profile: &Profile,
    opts: &FlatOptions,
    stage: &'static str,
) -> Result<Vec<(String, f32)>> {
    let g = &profile.geometry;
    let mut levels = Vec::new();
    for (name, [a, b]) in g.strips() {
        if a >= b || b > resp.dim().0 {
            continue; // a strip outside the rows at hand (cropped frames)
        }
        let med = strip_median(resp, a, b, |y, x, v| bad[[y, x]] == 0 && v > 0.0).ok_or_else(|| Error::Stage {
            stage,
            reason: format!("strip {name} (rows {a}-{b}) has no usable pixel"),
        })?;
        if !(med > 0.0) {
            return Err(Error::Stage {
                stage,
                reason: format!("strip {name} (rows {a}-{b}): median response {med} is not positive"),
            });
        }
        let inv = 1.0 / med;
        resp.slice_mut(s![a..b, ..]).mapv_inplace(|v| v * inv);
        var.slice_mut(s![a..b, ..]).mapv_inplace(|v| v * inv * inv);
        levels.push((name.to_string(), med));
    }
    let (ny, _) = resp.dim();
    for y in 0..ny {
        let on = g.row_in_strip(y);
        for ((r, v), b) in resp
            .row_mut(y)
            .iter_mut()
            .zip(var.row_mut(y).iter_mut())
            .zip(bad.row_mut(y).iter_mut())
        {
            if !on {
                *r = 1.0;
                *v = 0.0;
                *b = 0;
            } else if *b != 0 || !r.is_finite() || !v.is_finite() || *r < opts.min_response || *r > opts.max_response {
                *r = 1.0;
                *v = 0.0;
                *b = 1;
            }
        }
    }
    Ok(levels)
}

/// Per-pixel variance of a raw frame from its own values: Poisson + read noise.
fn raw_variance(frame: &Frame, profile: &Profile) -> Result<(f32, f32)> {
    let ndit = crate::sky::frame_ndit(frame, profile)?;
    let det = &profile.detector;
    Ok((
        (1.0 / det.effective_gain(ndit)) as f32,
        det.read_variance_adu2(ndit) as f32,
    ))
}

/// Dome flat of one rotator angle: mean(on) - mean(off), each strip normalized separately
/// (see the module documentation). Needs at least one frame of each; all of one shape.
pub fn dome_flat(on: &[Frame], off: &[Frame], profile: &Profile, opts: &FlatOptions) -> Result<Flat> {
    const STAGE: &str = "flat";
    if on.is_empty() || off.is_empty() {
        return Err(Error::Stage {
            stage: STAGE,
            reason: format!(
                "dome flat needs lamp-on and lamp-off frames: {} on, {} off",
                on.len(),
                off.len()
            ),
        });
    }
    let all: Vec<&Frame> = on.iter().chain(off.iter()).collect();
    let shape = check_shapes(&all, profile, STAGE)?;
    let mut resp = Array2::<f32>::zeros(shape);
    let mut var = Array2::<f32>::zeros(shape);
    let mut bad = Array2::<u8>::zeros(shape);
    let sat = profile.detector.nonlinear_warn_adu as f32;
    for (set, sign) in [(on, 1.0f32), (off, -1.0f32)] {
        let n = set.len() as f32;
        for f in set {
            let (inv_g, rv) = raw_variance(f, profile)?;
            ndarray::Zip::from(&mut resp)
                .and(&mut var)
                .and(&mut bad)
                .and(&f.data)
                .and(&f.mask)
                .par_for_each(|r, v, b, &d, &m| {
                    *r += sign * d / n;
                    *v += (d.max(0.0) * inv_g + rv) / (n * n);
                    if m != 0 || !d.is_finite() || d >= sat {
                        *b = 1;
                    }
                });
        }
    }
    let levels = normalize_strips(&mut resp, &mut var, &mut bad, profile, opts, STAGE)?;
    let info = dome_flat_info(&on[0].header, profile).ok().flatten();
    let sources: Vec<String> = all.iter().enumerate().map(|(i, f)| name_of(f, i)).collect();
    let detail = format!(
        "dome flat = mean of {} lamp-on - mean of {} lamp-off frames; strips normalized separately by their median \
         (lamp-on - off levels {}); unusable outside [{}, {}]: {} pixels",
        on.len(),
        off.len(),
        levels
            .iter()
            .map(|(n, l)| format!("{n} {l:.1}"))
            .collect::<Vec<_>>()
            .join(", "),
        opts.min_response,
        opts.max_response,
        bad.iter().filter(|&&b| b != 0).count()
    );
    Ok(Flat {
        data: resp,
        variance: var,
        bad,
        kind: FlatKind::Dome,
        posang_deg: info.as_ref().map(|i| i.posang_deg),
        filter: info.and_then(|i| i.filter),
        sources,
        detail,
        path: None,
    })
}

/// Marks, inside the superflat builder, pixels with too few star-free values.
const UNKNOWN: u8 = 2;

/// Superflat from the sky of dithered science frames (raw, one shape; see the module
/// documentation). Needs at least `opts.min_values` frames. Pixels where fewer than
/// `opts.min_values` frames are free of stars are left uncorrected (response 1), not masked.
pub fn superflat(frames: &[Frame], profile: &Profile, opts: &FlatOptions) -> Result<Flat> {
    const STAGE: &str = "superflat";
    let frames: Vec<&Frame> = frames.iter().take(opts.max_frames.max(1)).collect();
    if frames.len() < opts.min_values.max(3) {
        return Err(Error::Stage {
            stage: STAGE,
            reason: format!(
                "{} frames: a superflat needs at least {}",
                frames.len(),
                opts.min_values.max(3)
            ),
        });
    }
    let shape = check_shapes(&frames, profile, STAGE)?;
    let (ny, nx) = shape;
    let g = &profile.geometry;
    let strips = g.strips();
    let strip_of: Vec<Option<usize>> = (0..ny)
        .map(|y| strips.iter().position(|(_, r)| y >= r[0] && y < r[1]))
        .collect();
    let sat = profile.detector.nonlinear_warn_adu as f32;

    // Fixed detector defects (hot pixels and columns, dead pixels) sit at the same pixel in
    // every frame: found first as pixels whose median over (up to 9) frames, each divided
    // by its strip level, is outside [min_response, max_response], so that they are not
    // taken for stars (whose surroundings are left out).
    let defect = {
        let step = frames.len().div_ceil(9).max(1);
        let sub: Vec<&Frame> = frames.iter().step_by(step).copied().collect();
        let inv: Vec<[f32; 6]> = sub
            .iter()
            .map(|f| {
                let mut l = [0f32; 6];
                for (k, (_, [a, b])) in strips.iter().enumerate() {
                    let m = strip_median(&f.data, *a, *b, |y, x, v| f.mask[[y, x]] == 0 && v < sat).unwrap_or(0.0);
                    l[k] = if m > 0.0 { 1.0 / m } else { 0.0 };
                }
                l
            })
            .collect();
        let mut d = Array2::<u8>::zeros(shape);
        d.as_slice_mut()
            .expect("fresh array")
            .par_chunks_mut(nx)
            .enumerate()
            .for_each(|(y, row)| {
                let Some(k) = strip_of[y] else { return };
                let mut v = Vec::with_capacity(sub.len());
                for (x, o) in row.iter_mut().enumerate() {
                    v.clear();
                    v.extend(sub.iter().zip(&inv).map(|(f, l)| f.data[[y, x]] * l[k]));
                    let m = median_f32(&mut v).unwrap_or(f32::NAN);
                    if !(m >= opts.min_response && m <= opts.max_response) {
                        *o = 1;
                    }
                }
            });
        d
    };

    // Per frame: strip levels and the per-pixel sigma of a normalized value, and the
    // exclusion map (defects, masked, saturated, stars grown by star_grow_px).
    struct Prep {
        inv_level: [f32; 6],
        sigma: [f32; 6],
        excl: Array2<u8>,
    }
    let preps: Vec<Prep> = frames
        .par_iter()
        .map(|f| -> Result<Prep> {
            let (inv_g, rv) = raw_variance(f, profile)?;
            let mut inv_level = [0f32; 6];
            let mut sigma = [f32::INFINITY; 6];
            for (k, (_, [a, b])) in strips.iter().enumerate() {
                if let Some(l) = strip_median(&f.data, *a, *b, |y, x, v| f.mask[[y, x]] == 0 && v < sat) {
                    if l > 0.0 {
                        inv_level[k] = 1.0 / l;
                        sigma[k] = (l * inv_g + rv).sqrt() / l;
                    }
                }
            }
            // Local level: median of blocks of BLOCK columns of each strip (the sky is
            // not flat: a gradient would push whole regions over a global threshold).
            const BLOCK: usize = 64;
            let nb = nx.div_ceil(BLOCK);
            // Level and robust scatter (median - 15.9th percentile: photon noise and the
            // pixel response itself, which looks like noise within one frame).
            let mut local = vec![[0f32; 6]; nb];
            let mut scatter = vec![[0f32; 6]; nb];
            for (k, (_, [a, b])) in strips.iter().enumerate() {
                for bi in 0..nb {
                    let lv = &mut local[bi];
                    let (x0, x1) = (bi * BLOCK, ((bi + 1) * BLOCK).min(nx));
                    let mut v: Vec<f32> = Vec::with_capacity((b - a) * (x1 - x0) / 2 + 1);
                    for y in *a..*b {
                        for x in (x0 + (y % 2)..x1).step_by(2) {
                            let d = f.data[[y, x]];
                            if f.mask[[y, x]] == 0 && d.is_finite() && d < sat {
                                v.push(d);
                            }
                        }
                    }
                    lv[k] = median_f32(&mut v).unwrap_or(0.0);
                    if !v.is_empty() {
                        let i16 = (v.len() as f64 * 0.1587) as usize;
                        let p16 = *v.select_nth_unstable_by(i16, |a, b| a.total_cmp(b)).1;
                        scatter[bi][k] = (lv[k] - p16).max(0.0);
                    }
                }
            }
            // Significance of each pixel above its local level, in sigma of that level.
            let mut excl = Array2::<u8>::zeros(shape);
            let mut seed = Array2::<u8>::zeros(shape);
            for y in 0..ny {
                let Some(k) = strip_of[y] else { continue };
                for x in 0..nx {
                    let d = f.data[[y, x]];
                    let l = local[x / BLOCK][k];
                    if inv_level[k] <= 0.0
                        || l <= 0.0
                        || defect[[y, x]] != 0
                        || f.mask[[y, x]] != 0
                        || !d.is_finite()
                        || d >= sat
                    {
                        excl[[y, x]] = 1;
                        continue;
                    }
                    let sig = scatter[x / BLOCK][k].max((l * inv_g + rv).sqrt());
                    let z = (d - l) / sig;
                    if z > opts.star_sigma {
                        excl[[y, x]] = 1;
                        seed[[y, x]] = 2;
                    } else if z > 2.0 {
                        seed[[y, x]] = 1;
                    }
                }
            }
            // Grow stars (a significant pixel with a neighbour above 2 sigma: not a lone
            // noise spike or cosmic-ray pixel) by star_grow_px: box dilation.
            let r = opts.star_grow_px;
            if r > 0 {
                let mut grow = Vec::new();
                for y in 1..ny.saturating_sub(1) {
                    for x in 1..nx.saturating_sub(1) {
                        if seed[[y, x]] == 2
                            && (seed[[y, x - 1]] > 0
                                || seed[[y, x + 1]] > 0
                                || seed[[y - 1, x]] > 0
                                || seed[[y + 1, x]] > 0)
                        {
                            grow.push((y, x));
                        }
                    }
                }
                for (y, x) in grow {
                    for yy in y.saturating_sub(r)..(y + r + 1).min(ny) {
                        for xx in x.saturating_sub(r)..(x + r + 1).min(nx) {
                            excl[[yy, xx]] = 1;
                        }
                    }
                }
            }
            Ok(Prep { inv_level, sigma, excl })
        })
        .collect::<Result<Vec<_>>>()?;

    let mut resp = Array2::<f32>::ones(shape);
    let mut var = Array2::<f32>::zeros(shape);
    let mut bad = Array2::<u8>::zeros(shape);
    let (clip, min_values) = (opts.clip_sigma, opts.min_values.max(1));
    resp.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(nx)
        .zip(var.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
        .zip(bad.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
        .enumerate()
        .for_each(|(y, ((rrow, vrow), brow))| {
            let Some(k) = strip_of[y] else { return };
            let mut vals: Vec<(f32, f32)> = Vec::with_capacity(frames.len());
            let mut tmp: Vec<f32> = Vec::with_capacity(frames.len());
            for x in 0..nx {
                vals.clear();
                for (f, p) in frames.iter().zip(&preps) {
                    if p.excl[[y, x]] == 0 {
                        vals.push((f.data[[y, x]] * p.inv_level[k], p.sigma[k]));
                    }
                }
                // Too few star-free values (a star sat here in most frames): the response
                // is unknown, so this pixel is left uncorrected (response 1, no flat noise)
                // rather than masked: masking it would mask the stars of the science frames,
                // which sit exactly there.
                if vals.len() < min_values {
                    brow[x] = UNKNOWN;
                    continue;
                }
                tmp.clear();
                tmp.extend(vals.iter().map(|v| v.0));
                let med = median_f32(&mut tmp).unwrap_or(1.0);
                let (mut sw, mut swv, mut n) = (0f64, 0f64, 0usize);
                for &(v, sg) in &vals {
                    if (v - med).abs() <= clip * sg {
                        let w = 1.0 / (sg as f64 * sg as f64);
                        sw += w;
                        swv += w * v as f64;
                        n += 1;
                    }
                }
                if n < min_values {
                    brow[x] = UNKNOWN;
                    continue;
                }
                rrow[x] = (swv / sw) as f32;
                vrow[x] = (1.0 / sw) as f32;
            }
        });
    let unknown = bad.mapv(|b| u8::from(b == UNKNOWN));
    let n_unknown = unknown.iter().filter(|&&u| u != 0).count();
    // The strip medians leave the unknown pixels out (they are in `bad` here); afterwards
    // they are uncorrected (response 1, no variance), not bad.
    let levels = normalize_strips(&mut resp, &mut var, &mut bad, profile, opts, STAGE)?;
    ndarray::Zip::from(&mut resp)
        .and(&mut var)
        .and(&mut bad)
        .and(&unknown)
        .for_each(|r, v, b, &u| {
            if u != 0 {
                *r = 1.0;
                *v = 0.0;
                *b = 0;
            }
        });
    let sources: Vec<String> = frames.iter().enumerate().map(|(i, f)| name_of(f, i)).collect();
    let detail = format!(
        "superflat from the sky of {} science frames: each divided by its strip sky level, stars (> {} sigma, grown {} px) \
         and masked pixels left out, per pixel the inverse-variance weighted mean of the values within {} sigma of their \
         median (at least {}); strips normalized separately (medians {}); {} pixels unusable; {} pixels left uncorrected \
         (too few star-free values)",
        frames.len(),
        opts.star_sigma,
        opts.star_grow_px,
        opts.clip_sigma,
        min_values,
        levels
            .iter()
            .map(|(n, l)| format!("{n} {l:.4}"))
            .collect::<Vec<_>>()
            .join(", "),
        bad.iter().filter(|&&b| b != 0).count(),
        n_unknown
    );
    let filter = frames[0]
        .header
        .opt_str(&profile.keywords.filter)
        .map(|s| s.trim().to_string());
    Ok(Flat {
        data: resp,
        variance: var,
        bad,
        kind: FlatKind::Superflat,
        posang_deg: None,
        filter,
        sources,
        detail,
        path: None,
    })
}

/// Divide a raw frame by a flat of the same shape (crop the flat with
/// [`Flat::crop_rows`] for a cropped frame; `profile` then the matching
/// [`Profile::cropped_rows`]). The output carries a variance map: the frame's own
/// (Poisson + read noise of the raw values when it has none) divided by flat^2, plus the
/// flat's noise on the signal above the strip's sky level (module documentation). Pixels
/// the flat marks unusable keep their raw value and get [`mask::BAD`].
pub fn apply_flat(frame: &Frame, flat: &Flat, profile: &Profile) -> Result<Frame> {
    if frame.shape() != flat.shape() {
        return Err(Error::Stage {
            stage: "flat",
            reason: format!(
                "{}: frame shape {:?} differs from the flat's {:?}{}",
                name_of(frame, 0),
                frame.shape(),
                flat.shape(),
                flat.path
                    .as_ref()
                    .map(|p| format!(" ({})", p.display()))
                    .unwrap_or_default()
            ),
        });
    }
    let (ny, nx) = frame.shape();
    let (inv_g, rv) = raw_variance(frame, profile)?;
    let g = &profile.geometry;
    let sat = profile.detector.saturation_adu as f32;
    // Sky level of each strip (rows outside strips: 0).
    let mut level_of_row = vec![0f32; ny];
    for (_, [a, b]) in g.strips() {
        let (a, b) = (a.min(ny), b.min(ny));
        if a >= b {
            continue;
        }
        let l = strip_median_step(&frame.data, a, b, 16, |y, x, v| frame.mask[[y, x]] == 0 && v < sat).unwrap_or(0.0);
        for lr in &mut level_of_row[a..b] {
            *lr = l;
        }
    }
    let mut data = frame.data.as_standard_layout().into_owned();
    let mut var = Array2::<f32>::zeros((ny, nx));
    let mut msk = frame.mask.as_standard_layout().into_owned();
    let vin = frame.variance.as_ref().map(|v| v.as_standard_layout().into_owned());
    let fd = flat.data.as_standard_layout();
    let fv = flat.variance.as_standard_layout();
    let fb = flat.bad.as_standard_layout();
    let (fd, fv, fb) = (
        fd.as_slice().expect("standard"),
        fv.as_slice().expect("standard"),
        fb.as_slice().expect("standard"),
    );
    let vin_s = vin.as_ref().map(|v| v.as_slice().expect("standard"));
    let n_bad: usize = data
        .as_slice_mut()
        .expect("standard")
        .par_chunks_mut(nx)
        .zip(var.as_slice_mut().expect("fresh").par_chunks_mut(nx))
        .zip(msk.as_slice_mut().expect("standard").par_chunks_mut(nx))
        .enumerate()
        .map(|(y, ((drow, vrow), mrow))| {
            let l = level_of_row[y];
            let mut n = 0;
            for x in 0..nx {
                let i = y * nx + x;
                let raw = drow[x];
                let v0 = match vin_s {
                    Some(v) => v[i],
                    None => raw.max(0.0) * inv_g + rv,
                };
                if fb[i] != 0 {
                    mrow[x] |= mask::BAD;
                    vrow[x] = v0;
                    n += 1;
                    continue;
                }
                let f = fd[i];
                let out = raw / f;
                let excess = (out - l).max(0.0);
                drow[x] = out;
                vrow[x] = (v0 + excess * excess * fv[i]) / (f * f);
            }
            n
        })
        .sum();
    let mut history = frame.history.clone();
    history.push(HistoryRecord::new(
        "flat",
        format!(
            "divided by the {}; variance = raw variance / flat^2 + (signal above strip sky)^2 var_flat / flat^2; \
             {n_bad} pixels unusable in the flat marked BAD",
            flat.describe()
        ),
    ));
    Ok(Frame {
        data,
        variance: Some(var),
        mask: msk,
        header: frame.header.clone(),
        history,
    })
}

/// Flats by rotator angle and filter, with the choice of the flat for a frame.
#[derive(Debug, Clone, Default)]
pub struct FlatSet {
    /// The flats.
    pub flats: Vec<Flat>,
}

impl FlatSet {
    /// The flat for a frame: same filter (when both are known) and same rotator angle
    /// (within 0.5 deg, modulo 360); else a flat of the same filter without angle
    /// (superflat, or the nearest angle); else None.
    pub fn for_frame(&self, posang_deg: f64, filter: &str) -> Option<&Flat> {
        let filt_ok = |f: &Flat| {
            f.filter
                .as_deref()
                .is_none_or(|ff| ff.trim().eq_ignore_ascii_case(filter.trim()))
        };
        let dang = |f: &Flat| {
            f.posang_deg.map(|p| {
                let d = (p - posang_deg).rem_euclid(360.0);
                d.min(360.0 - d)
            })
        };
        let cands: Vec<&Flat> = self.flats.iter().filter(|f| filt_ok(f)).collect();
        if let Some(f) = cands.iter().find(|f| dang(f).is_some_and(|d| d < 0.5)) {
            return Some(f);
        }
        if let Some(f) = cands.iter().find(|f| f.posang_deg.is_none()) {
            return Some(f);
        }
        cands
            .into_iter()
            .min_by(|a, b| dang(a).unwrap_or(f64::MAX).total_cmp(&dang(b).unwrap_or(f64::MAX)))
    }

    /// Whether there is no flat.
    pub fn is_empty(&self) -> bool {
        self.flats.is_empty()
    }
}

/// Dome flats of a night: read the headers of `paths`, keep the dome-flat frames, group
/// them by (filter, rotator angle), and build one flat per group that has lamp-on and
/// lamp-off frames. Returns the flats and the files that could not be used, with the
/// reason (unreadable, bad keyword, a group without on or off frames, a failed build).
pub fn build_flats(paths: &[PathBuf], profile: &Profile, opts: &FlatOptions) -> (FlatSet, Vec<(PathBuf, String)>) {
    let mut problems = Vec::new();
    type Key = (String, i64);
    let mut groups: std::collections::BTreeMap<Key, (Vec<PathBuf>, Vec<PathBuf>)> = Default::default();
    let infos: Vec<(PathBuf, Result<Option<DomeFlatInfo>>)> = paths
        .par_iter()
        .map(|p| {
            (
                p.clone(),
                crate::fits::read_header(p).and_then(|h| dome_flat_info(&h, profile)),
            )
        })
        .collect();
    for (p, r) in infos {
        match r {
            Ok(Some(i)) => {
                let key = (
                    i.filter.clone().unwrap_or_default(),
                    (i.posang_deg.rem_euclid(360.0) * 100.0).round() as i64,
                );
                let g = groups.entry(key).or_default();
                if i.lamp_on {
                    g.0.push(p);
                } else {
                    g.1.push(p);
                }
            }
            Ok(None) => {}
            Err(e) => problems.push((p, e.to_string())),
        }
    }
    let mut flats = Vec::new();
    for ((filter, pa), (on, off)) in groups {
        if on.is_empty() || off.is_empty() {
            for p in on.iter().chain(off.iter()) {
                problems.push((
                    p.clone(),
                    format!(
                        "dome flat filter '{filter}' POSANG {}: {} lamp-on and {} lamp-off frames, need both",
                        pa as f64 / 100.0,
                        on.len(),
                        off.len()
                    ),
                ));
            }
            continue;
        }
        let read = |ps: &[PathBuf], problems: &mut Vec<(PathBuf, String)>| -> Vec<Frame> {
            let r: Vec<(PathBuf, Result<Frame>)> =
                ps.par_iter().map(|p| (p.clone(), crate::fits::read_frame(p))).collect();
            r.into_iter()
                .filter_map(|(p, f)| match f {
                    Ok(f) => Some(f),
                    Err(e) => {
                        problems.push((p, e.to_string()));
                        None
                    }
                })
                .collect()
        };
        let on_f = read(&on, &mut problems);
        let off_f = read(&off, &mut problems);
        match dome_flat(&on_f, &off_f, profile, opts) {
            Ok(f) => flats.push(f),
            Err(e) => {
                for p in on.iter().chain(off.iter()) {
                    problems.push((p.clone(), e.to_string()));
                }
            }
        }
    }
    (FlatSet { flats }, problems)
}

/// Conventional file name of a flat: `flat_<kind>_<filter>[_pa<angle>].fits`.
pub fn flat_file_name(flat: &Flat) -> String {
    let filt: String = flat
        .filter
        .as_deref()
        .unwrap_or("any")
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    match flat.posang_deg {
        Some(p) => format!("flat_{}_{filt}_pa{:03}.fits", flat.kind.name(), p.round() as i64),
        None => format!("flat_{}_{filt}.fits", flat.kind.name()),
    }
}

/// Write a flat as FITS (atomically): the response in the primary HDU, VARIANCE and MASK
/// (1 = unusable) extensions, kind / angle / filter / frame count in the header, the
/// detail and the files combined as HISTORY.
pub fn write_flat(path: &Path, flat: &Flat) -> Result<()> {
    let mut h = Header::new(path);
    h.set(KIND_KEYWORD, flat.kind.name());
    if let Some(p) = flat.posang_deg {
        h.set(POSANG_KEYWORD, p);
    }
    if let Some(f) = &flat.filter {
        h.set(FILTER_KEYWORD, f.as_str());
    }
    h.set(NCOMBINE_KEYWORD, flat.sources.len() as i64);
    let mut frame = Frame {
        data: flat.data.clone(),
        variance: Some(flat.variance.clone()),
        mask: flat.bad.clone(),
        header: h,
        history: vec![HistoryRecord::new("flat", flat.detail.clone())],
    };
    for s in &flat.sources {
        frame.history.push(HistoryRecord::new("flat-input", s.clone()));
    }
    crate::fits::write_frame(
        path,
        &frame,
        &crate::fits::WriteOptions {
            with_variance_and_mask: true,
            ..Default::default()
        },
    )
}

/// Read a flat written by [`write_flat`], or any FITS image of the pixel response (then:
/// kind superflat unless the header says otherwise, variance 0 when there is no VARIANCE
/// extension, unusable where MASK is nonzero or the value is not finite or <= 0). The
/// data are used as they are (not renormalized).
pub fn read_flat(path: &Path) -> Result<Flat> {
    let f = crate::fits::read_frame(path)?;
    let kind = match f.header.opt_str(KIND_KEYWORD).as_deref().map(str::trim) {
        Some("dome") => FlatKind::Dome,
        Some("superflat") | None => FlatKind::Superflat,
        Some(other) => {
            return Err(Error::BadKeyword {
                path: path.to_path_buf(),
                keyword: KIND_KEYWORD.into(),
                value: other.into(),
                reason: "expected 'dome' or 'superflat'".into(),
            })
        }
    };
    let posang_deg = f.header.opt_f64(POSANG_KEYWORD)?;
    let filter = f.header.opt_str(FILTER_KEYWORD).map(|s| s.trim().to_string());
    let mut data = f.data;
    let mut bad = f.mask;
    let mut variance = f.variance.unwrap_or_else(|| Array2::zeros(data.raw_dim()));
    ndarray::Zip::from(&mut data)
        .and(&mut variance)
        .and(&mut bad)
        .for_each(|d, v, b| {
            if *b != 0 || !d.is_finite() || *d <= 0.0 || !v.is_finite() {
                *d = 1.0;
                *v = 0.0;
                *b = 1;
            }
        });
    let detail = f
        .history
        .iter()
        .find(|r| r.stage == "flat")
        .map(|r| r.detail.clone())
        .unwrap_or_else(|| "flat read from file".into());
    let sources = f
        .history
        .iter()
        .filter(|r| r.stage == "flat-input")
        .map(|r| r.detail.clone())
        .collect();
    Ok(Flat {
        data,
        variance,
        bad,
        kind,
        posang_deg,
        filter,
        sources,
        detail,
        path: Some(path.to_path_buf()),
    })
}

#[cfg(test)]
mod tests;
