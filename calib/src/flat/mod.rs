//! Flat field: the detector's pixel response, measured from dome flats or from the night's
//! own sky (a superflat), and divided out of the frames in the sky stage's last pass
//! ([`FlatRows`], [`crate::sky::sky_subtract_flat`]).
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
//! * **Application** ([`apply_flat`], or inside the sky stage with [`FlatRows`], the same
//!   reduction for the default multiplicative sky): data / flat with a variance map (photon + read noise
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
//! Flats are written as FITS ([`write_flat`]: the response in the primary HDU, UNCERT
//! and MASK extensions, what they were made of in the header and HISTORY: they open in
//! DS9) and read back with [`read_flat`].
use std::path::PathBuf;

use ndarray::{s, Array2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::frame::{mask, Frame, HistoryRecord};
use crate::header::Header;
use crate::profile::Profile;

/// Header keyword telling lamp on (T) from lamp off (F) in a dome flat (a fixed name, not
/// yet a profile setting; unverified on real data; docs/frame-format.md).
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
    pub fn embed_rows(self, r0: usize, ny: usize) -> Flat {
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
        // The rest moves over (the cropped maps are not copied).
        Flat {
            data,
            variance,
            bad,
            detail: format!("{} (rows {r0}-{r1} of the detector; 1 elsewhere)", self.detail),
            ..self
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

    /// What the catalog's provenance records of it.
    pub fn provenance(&self) -> FlatRecord {
        FlatRecord {
            kind: self.kind.name().to_string(),
            posang_deg: self.posang_deg,
            filter: self.filter.clone(),
            frames: self.sources.clone(),
            file: self.path.as_ref().map(|p| p.display().to_string()),
            bad_pixels: self.bad.iter().filter(|&&b| b != 0).count(),
            detail: self.detail.clone(),
        }
    }
}

/// One flat as a catalog's provenance records it (`provenance.flat.flats[]`; keys in
/// alphabetical order, as written before it was typed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlatRecord {
    /// Pixels the flat marks unusable.
    #[serde(default)]
    pub bad_pixels: usize,
    /// What was done, with the parameters.
    #[serde(default)]
    pub detail: String,
    /// The file it was read from, when read.
    #[serde(default)]
    pub file: Option<String>,
    /// Filter, when known.
    #[serde(default)]
    pub filter: Option<String>,
    /// The frames it was built from.
    #[serde(default)]
    pub frames: Vec<String>,
    /// `dome`, `superflat` or `file`.
    pub kind: String,
    /// Rotator angle it applies to (none: every angle), deg.
    #[serde(default)]
    pub posang_deg: Option<f64>,
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
    if shape.0 < g.lit_rows_end() {
        return Err(Error::Stage {
            stage,
            reason: format!(
                "{}: {} rows, the profile's strips reach row {}",
                name_of(frames[0], 0),
                shape.0,
                g.lit_rows_end()
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
    // Selected on integer keys in the order of `f32::total_cmp` (the same element, bit for
    // bit; integer comparisons are cheaper).
    use lanes::{from_key, key};
    if v.len() <= 64 {
        let mut keys = [0i32; 64];
        let keys = &mut keys[..v.len()];
        keys.iter_mut().zip(v.iter()).for_each(|(k, &x)| *k = key(x));
        return Some(from_key(*keys.select_nth_unstable(k).1));
    }
    let mut keys: Vec<i32> = v.iter().map(|&x| key(x)).collect();
    Some(from_key(*keys.select_nth_unstable(k).1))
}

/// Median of the finite values of rows [a, b) whose `mask` is 0 and which `ok` accepts (one
/// pixel in 4).
fn strip_median(data: &Array2<f32>, mask: &Array2<u8>, a: usize, b: usize, ok: impl Fn(f32) -> bool) -> Option<f32> {
    strip_median_step(data, mask, a, b, 4, ok)
}

/// Median of the finite values of rows [a, b) whose `mask` is 0 and which `ok` accepts (one
/// pixel in `step`, the phase shifted row to row). Rows are read as slices.
fn strip_median_step(
    data: &Array2<f32>,
    mask: &Array2<u8>,
    a: usize,
    b: usize,
    step: usize,
    ok: impl Fn(f32) -> bool,
) -> Option<f32> {
    let mut v = Vec::with_capacity(b.saturating_sub(a) * data.ncols() / step.max(1) + 1);
    for y in a..b {
        let (row, mrow) = (data.row(y), mask.row(y));
        match (row.as_slice(), mrow.as_slice()) {
            (Some(r), Some(m)) => {
                let m = &m[..r.len()];
                for x in ((y % step)..r.len()).step_by(step) {
                    let val = r[x];
                    if val.is_finite() && m[x] == 0 && ok(val) {
                        v.push(val);
                    }
                }
            }
            _ => {
                for x in ((y % step)..row.len()).step_by(step) {
                    let val = row[x];
                    if val.is_finite() && mrow[x] == 0 && ok(val) {
                        v.push(val);
                    }
                }
            }
        }
    }
    median_f32(&mut v)
}

/// The median of the values whose [`lanes::key`]s are `keys` (the element [`median_f32`]
/// picks) and their `i`-th smallest (`i` at most half the count), in `f32::total_cmp` order,
/// by two selections on the keys (the second only on the lower part). None when empty.
fn median_and_lower(keys: &mut [i32], i: usize) -> Option<(f32, f32)> {
    if keys.is_empty() {
        return None;
    }
    let k = keys.len() / 2;
    assert!(i <= k, "order {i} above the median's {k}");
    let (lower, m, _) = keys.select_nth_unstable(k);
    let med = lanes::from_key(*m);
    let p = if i == k {
        med
    } else {
        lanes::from_key(*lower.select_nth_unstable(i).1)
    };
    Some((med, p))
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
        let med = strip_median(resp, bad, a, b, |v| v > 0.0).ok_or_else(|| Error::Stage {
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
    let ndit = crate::profile::frame_ndit(frame, profile)?;
    let det = &profile.detector;
    Ok((
        (1.0 / det.effective_gain(ndit)) as f32,
        det.read_variance_adu2(ndit) as f32,
    ))
}

/// Flats by rotator angle and filter, with the choice of the flat for a frame.
#[derive(Debug, Clone, Default)]
pub struct FlatSet {
    /// The flats.
    pub flats: Vec<Flat>,
    /// The per-pixel maps of [`FlatSet::rows`], made once per flat and row range.
    prepared: PreparedCache,
}

/// One cached entry: (flat index, row0, ny) and its maps.
type PreparedEntry = ((usize, usize, usize), std::sync::Arc<apply::Prepared>);

/// Cache of [`FlatSet::rows`]: (flat index, row0, ny) -> maps. A clone starts empty.
#[derive(Default)]
struct PreparedCache(std::sync::Mutex<Vec<PreparedEntry>>);

impl Clone for PreparedCache {
    fn clone(&self) -> Self {
        PreparedCache::default()
    }
}

impl std::fmt::Debug for PreparedCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PreparedCache")
    }
}

impl FlatSet {
    /// A set of flats.
    pub fn new(flats: Vec<Flat>) -> FlatSet {
        FlatSet {
            flats,
            prepared: PreparedCache::default(),
        }
    }

    /// [`FlatRows::new`] of one of this set's flats, its per-pixel maps made once per flat and
    /// row range and shared by every target of the night (the flats of a set are not changed
    /// after it is made: change one and make a new set). A flat not in the set gets maps of
    /// its own.
    pub fn rows<'a>(&self, flat: &'a Flat, row0: usize, ny: usize) -> FlatRows<'a> {
        let Some(i) = self.flats.iter().position(|f| std::ptr::eq(f, flat)) else {
            return FlatRows::new(flat, row0, ny);
        };
        let key = (i, row0, ny);
        let mut cache = self.prepared.0.lock().unwrap_or_else(|e| e.into_inner());
        let maps = match cache.iter().find(|(k, _)| *k == key) {
            Some((_, m)) => m.clone(),
            None => {
                let m = std::sync::Arc::new(apply::Prepared::new(flat, row0, ny));
                cache.push((key, m.clone()));
                m
            }
        };
        FlatRows::from_prepared(flat, row0, maps)
    }

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

mod apply;
mod dome;
mod io;
pub(crate) mod lanes;
mod superflat;

pub(crate) use apply::FlatRow;
pub use apply::{apply_flat, apply_flat_in_place, check_flat, FlatRows};
pub use dome::{build_flats, dome_flat, dome_flat_info, DomeFlatInfo};
pub use io::{flat_file_name, read_flat, write_flat};
pub use superflat::superflat;

#[cfg(test)]
pub(crate) mod tests;

#[cfg(test)]
mod median_tests {
    /// The integer-key median is the `total_cmp` median, bit for bit (signed zeros, NaN,
    /// infinities, ties, every length up to 70, and long slices).
    #[test]
    fn median_f32_is_the_total_cmp_median() {
        let pool = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            1.5,
            2.5e-38,
            -3.0e38,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            0.97,
            1.03,
            1.0,
        ];
        let mut state = 12345u64;
        for len in 1..=70 {
            for _ in 0..50 {
                let mut v: Vec<f32> = (0..len)
                    .map(|_| {
                        state = state
                            .wrapping_mul(6364136223846793005)
                            .wrapping_add(1442695040888963407);
                        let i = (state >> 33) as usize;
                        if i.is_multiple_of(3) {
                            pool[i % pool.len()]
                        } else {
                            1.0 + (i % 1000) as f32 * 1e-4
                        }
                    })
                    .collect();
                let mut want = v.clone();
                want.sort_by(|a, b| a.total_cmp(b));
                let got = super::median_f32(&mut v).unwrap();
                assert_eq!(got.to_bits(), want[len / 2].to_bits(), "len {len}: {want:?}");
            }
        }
        for len in [65, 1000, 4097] {
            let mut v: Vec<f32> = (0..len)
                .map(|i| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    if i % 7 == 0 {
                        pool[(state >> 33) as usize % pool.len()]
                    } else {
                        ((state >> 40) % 977) as f32 * 0.01
                    }
                })
                .collect();
            let mut want = v.clone();
            want.sort_by(|a, b| a.total_cmp(b));
            assert_eq!(super::median_f32(&mut v).unwrap().to_bits(), want[len / 2].to_bits());
        }
        assert!(super::median_f32(&mut []).is_none());
    }

    /// Median and the lower order statistic from one key vector: the elements a full
    /// `total_cmp` sort puts at len/2 and at i.
    #[test]
    fn median_and_lower_are_the_sorted_elements() {
        let mut state = 777u64;
        for len in 1..200usize {
            let v: Vec<f32> = (0..len)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    ((state >> 40) % 97) as f32 * 0.5 - 20.0
                })
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(|a, b| a.total_cmp(b));
            for i in [0, len / 7, (len as f64 * 0.1587) as usize, len / 2] {
                let mut keys: Vec<i32> = v.iter().map(|&x| super::lanes::key(x)).collect();
                let (m, p) = super::median_and_lower(&mut keys, i).unwrap();
                assert_eq!(m.to_bits(), sorted[len / 2].to_bits(), "len {len}");
                assert_eq!(p.to_bits(), sorted[i].to_bits(), "len {len} i {i}");
            }
        }
        assert!(super::median_and_lower(&mut [], 0).is_none());
    }
}
