//! The primary: its position in every frame (the brightest peak near the header jitter
//! offset, refined by a windowed centroid), and the unusable-pixel masks the later stages use.
//! The target is the source at the pointing, not the brightest of the strip: a brighter
//! field star elsewhere in the strip is named in the flag `brighter_source_in_strip`.
use ndarray::{Array2, ArrayView2};
use sofipol_calib::profile::Beam;
use sofipol_calib::{Frame, Profile};

use super::{MeasureError, MeasureParams, SkySubtractedOrientation};
use crate::catalog::{Flag, FlagCode};
use crate::photometry::{centroid, CentroidParams};
use crate::stokes::model::offset_to_sep_pa;

/// Brightest point of a 3x3 box-smoothed image within `radius` of (x0, y0), restricted to
/// rows [y_lo, y_hi) and unmasked pixels (boxes need >= 5 of their 9 pixels unmasked).
/// Returns (x, y, smoothed value): the largest mean, the first in row-major order among
/// equal ones.
///
/// Rows are visited in decreasing order of the largest unmasked pixel of their three image
/// rows (an upper bound of every box mean in the row: a mean of values <= M computed in
/// floating point is <= M) and the search stops at the first row whose bound is below the
/// best mean found: the same answer as [`brightest_peak_scan`] (the plain scan), bit for bit,
/// without smoothing most of a whole-strip search. Regions holding non-finite values are
/// scanned plainly.
pub fn brightest_peak(
    img: ArrayView2<f32>,
    mask: ArrayView2<u8>,
    x0: f64,
    y0: f64,
    radius: f64,
    rows: [usize; 2],
) -> Option<(f64, f64, f64)> {
    let w = Window::new(img.dim(), x0, y0, radius, rows)?;
    // Largest unmasked value of each image row the boxes read (rows y_lo-1 ..= y_hi+1).
    let mut row_max = Vec::with_capacity((w.y_hi - w.y_lo + 3) as usize);
    for y in w.y_lo - 1..=w.y_hi + 1 {
        let (vals, ms) = (img.row(y as usize), mask.row(y as usize));
        let (Some(vals), Some(ms)) = (vals.as_slice(), ms.as_slice()) else {
            return brightest_peak_scan(img, mask, x0, y0, radius, rows);
        };
        let cols = (w.x_lo - 1) as usize..=(w.x_hi + 1) as usize;
        let Some(m) = unmasked_max(&vals[cols.clone()], &ms[cols]) else {
            return brightest_peak_scan(img, mask, x0, y0, radius, rows);
        };
        row_max.push(m);
    }
    let mut order: Vec<(f32, i64)> = (w.y_lo..=w.y_hi)
        .map(|y| {
            let k = (y - w.y_lo) as usize;
            (row_max[k].max(row_max[k + 1]).max(row_max[k + 2]), y)
        })
        .collect();
    order.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut best: Option<(f64, f64, f64)> = None;
    for (bound, y) in order {
        if best.is_some_and(|b| (bound as f64) < b.2) {
            break;
        }
        for x in w.x_lo..=w.x_hi {
            let Some(v) = w.box_mean(img, mask, x, y) else {
                continue;
            };
            let better = match best {
                None => true,
                Some(b) => v > b.2 || (v == b.2 && (y as f64, x as f64) < (b.1, b.0)),
            };
            if better {
                best = Some((x as f64, y as f64, v));
            }
        }
    }
    best
}

/// The largest of `vals` where `mask` is 0 (-inf when there is none), or None when any
/// value is not finite. Branch-free, in 16 independent lanes: one running maximum would
/// chain every compare-and-select on the previous one (a float reduction the compiler may
/// not reorder), at a few cycles a pixel over whole strips. The maximum of finite values
/// does not depend on the order they are compared in.
#[inline]
fn unmasked_max(vals: &[f32], mask: &[u8]) -> Option<f32> {
    const L: usize = 16;
    let mut lanes = [f32::NEG_INFINITY; L];
    let mut exp_all_ones = [0u32; L];
    let mut fold = |lane: usize, v: f32, k: u8| {
        exp_all_ones[lane] |= u32::from(v.to_bits() & 0x7f80_0000 == 0x7f80_0000);
        let c = if k == 0 { v } else { f32::NEG_INFINITY };
        lanes[lane] = if c > lanes[lane] { c } else { lanes[lane] };
    };
    let (vc, mc) = (vals.chunks_exact(L), mask.chunks_exact(L));
    let (vr, mr) = (vc.remainder(), mc.remainder());
    for (v, k) in vc.zip(mc) {
        for j in 0..L {
            fold(j, v[j], k[j]);
        }
    }
    for (j, (&v, &k)) in vr.iter().zip(mr).enumerate() {
        fold(j, v, k);
    }
    if exp_all_ones.iter().any(|&e| e != 0) {
        return None;
    }
    Some(lanes.iter().fold(f32::NEG_INFINITY, |m, &c| if c > m { c } else { m }))
}

/// The candidate box centres of [`brightest_peak`].
struct Window {
    x0: f64,
    y0: f64,
    radius: f64,
    x_lo: i64,
    x_hi: i64,
    y_lo: i64,
    y_hi: i64,
}

impl Window {
    fn new((ny, nx): (usize, usize), x0: f64, y0: f64, radius: f64, rows: [usize; 2]) -> Option<Window> {
        let r = radius.ceil() as i64;
        let w = Window {
            x0,
            y0,
            radius,
            x_lo: (x0.round() as i64 - r).max(1),
            x_hi: (x0.round() as i64 + r).min(nx as i64 - 2),
            y_lo: (y0.round() as i64 - r).max(rows[0] as i64 + 1),
            y_hi: (y0.round() as i64 + r).min(rows[1] as i64 - 2).min(ny as i64 - 2),
        };
        (w.x_lo <= w.x_hi && w.y_lo <= w.y_hi).then_some(w)
    }

    /// Mean of the unmasked pixels of the 3x3 box at (x, y), None when the centre is beyond
    /// `radius` or fewer than 5 pixels are unmasked.
    #[inline]
    fn box_mean(&self, img: ArrayView2<f32>, mask: ArrayView2<u8>, x: i64, y: i64) -> Option<f64> {
        if ((x as f64 - self.x0).powi(2) + (y as f64 - self.y0).powi(2)) > self.radius * self.radius {
            return None;
        }
        let (yu, xu) = (y as usize, x as usize);
        let mut sum = 0.0;
        let mut n = 0;
        for j in yu - 1..=yu + 1 {
            for i in xu - 1..=xu + 1 {
                if mask[[j, i]] == 0 {
                    sum += img[[j, i]] as f64;
                    n += 1;
                }
            }
        }
        (n >= 5).then(|| sum / n as f64)
    }
}

/// [`brightest_peak`] by the plain row-major scan of every candidate (the reference; used
/// where the image holds non-finite values).
pub fn brightest_peak_scan(
    img: ArrayView2<f32>,
    mask: ArrayView2<u8>,
    x0: f64,
    y0: f64,
    radius: f64,
    rows: [usize; 2],
) -> Option<(f64, f64, f64)> {
    let w = Window::new(img.dim(), x0, y0, radius, rows)?;
    let mut best: Option<(f64, f64, f64)> = None;
    for y in w.y_lo..=w.y_hi {
        for x in w.x_lo..=w.x_hi {
            let Some(v) = w.box_mean(img, mask, x, y) else {
                continue;
            };
            if best.is_none_or(|b| v > b.2) {
                best = Some((x as f64, y as f64, v));
            }
        }
    }
    best
}

/// Mask bits that make a pixel unusable for centroids and fits.
pub const UNUSABLE: u8 = sofipol_calib::frame::mask::BAD
    | sofipol_calib::frame::mask::COSMIC
    | sofipol_calib::frame::mask::SATURATED
    | sofipol_calib::frame::mask::OFF_STRIP;

/// A 0/1 view of the unusable pixels.
pub fn unusable(frame: &Frame) -> Array2<u8> {
    frame.mask.mapv(|m| u8::from(m & UNUSABLE != 0))
}

/// Refine a position by a windowed centroid; None when it fails.
pub fn refine(
    img: ArrayView2<f32>,
    mask: ArrayView2<u8>,
    x: f64,
    y: f64,
    fwhm_px: f64,
    max_shift_px: f64,
) -> Option<(f64, f64)> {
    let p = CentroidParams {
        fwhm_px,
        max_shift_px,
        background: Some(0.0),
        ..CentroidParams::default()
    };
    centroid(img, Some(mask), x, y, &p).map(|c| (c.x, c.y))
}

/// Where the primary (the blend centroid of the pair) is in every frame.
#[derive(Debug, Clone)]
pub struct Primary {
    /// Per orientation, per frame: the centre, px (None: not found in that frame).
    pub centres: Vec<Vec<Option<(f64, f64)>>>,
    /// FWHM assumed before any fit (0.8" seeing), px.
    pub fwhm_guess: f64,
    /// Target-level flags of the identification (`brighter_source_in_strip`).
    pub flags: Vec<Flag>,
}

impl Primary {
    /// The frames of orientation `k` where the primary was found, with their unusable-pixel
    /// masks, and the centres.
    pub fn found_in<'a>(
        &self,
        k: usize,
        orient: &'a SkySubtractedOrientation,
        masks: &'a [Array2<u8>],
    ) -> FramesWithCentres<'a> {
        let (mut fr, mut cc) = (Vec::new(), Vec::new());
        for ((f, m), c) in orient.frames.iter().zip(masks).zip(&self.centres[k]) {
            if let Some(c) = c {
                fr.push((&f.data, m));
                cc.push(*c);
            }
        }
        (fr, cc)
    }
}

/// Frames (data, unusable mask) and the primary's centre in each.
pub type FramesWithCentres<'a> = (Vec<(&'a Array2<f32>, &'a Array2<u8>)>, Vec<(f64, f64)>);

/// Unusable-pixel masks, once per frame (centring, e-o correlation and stacks use them).
pub fn unusable_masks(orients: &[SkySubtractedOrientation]) -> Vec<Vec<Array2<u8>>> {
    orients
        .iter()
        .map(|o| o.frames.iter().map(unusable).collect())
        .collect()
}

/// Stage 1: the primary in every frame.
///
/// The target is identified by its position: at `measure.nominal_xy_px` when given, else
/// at the pointing (the detector centre in x, the middle of the o-target strip in y) moved
/// by each frame's header jitter offset, brightness deciding only among the sources
/// compatible with it ([`Primary::flags`] name a brighter source of the strip taken for a
/// field star).
///
/// Within an orientation every frame is registered on the same star: the first frame's
/// centre (brightest peak near the header position) carried by the header offsets and
/// refined by a centroid. Picking the brightest peak in every frame would jump between the
/// components of a near-equal pair.
///
/// Without a focal mask both images of every source lie on the detector, the target's e
/// image within the search radius of its o image and as bright: the search then runs on
/// the pair images ([`pair_images`]), where only the o image of a source holds both of its
/// images, and the centres are refined on the frames themselves.
pub fn locate_primary(
    orients: &[SkySubtractedOrientation],
    masks: &[Vec<Array2<u8>>],
    profile: &Profile,
    params: &MeasureParams,
) -> Result<Primary, MeasureError> {
    let g = &profile.geometry;
    if g.has_mask() {
        return locate_primary_in(orients, masks, profile, params);
    }
    let (pairs, pair_masks) = pair_images(orients, masks, (g.eo_offset_px[0], g.eo_offset_px[1]));
    let mut primary = locate_primary_in(&pairs, &pair_masks, profile, params)?;
    for ((cs, o), ms) in primary.centres.iter_mut().zip(orients).zip(masks) {
        for ((c, f), m) in cs.iter_mut().zip(&o.frames).zip(ms) {
            if let Some(xy) = c {
                let fwhm = primary.fwhm_guess;
                *xy = refine(f.data.view(), m.view(), xy.0, xy.1, fwhm, 2.0).unwrap_or(*xy);
            }
        }
    }
    Ok(primary)
}

/// The pair images of the frames for a beam offset `eo` (e image minus o image, px): at
/// every pixel p the sum of the frame at p and at p + eo (rounded to whole pixels), the
/// variance summed alike, unusable where either pixel is (or p + eo is off the frame).
/// A source's o image then holds both of its images, its e image one only and the point
/// `eo` before its o image the o image alone: the brightest point of a source in the pair
/// image is its o image, whatever the source's polarization, while in the frame the e
/// image of a star (as bright as its o image, `eo` away) could be taken for it.
pub fn pair_images(
    orients: &[SkySubtractedOrientation],
    masks: &[Vec<Array2<u8>>],
    eo: (f64, f64),
) -> (Vec<SkySubtractedOrientation>, Vec<Vec<Array2<u8>>>) {
    let (dx, dy) = (eo.0.round() as i64, eo.1.round() as i64);
    let mut out_masks = Vec::with_capacity(masks.len());
    let pairs = orients
        .iter()
        .zip(masks)
        .map(|(o, ms)| {
            let mut frames = Vec::with_capacity(o.frames.len());
            let mut pms = Vec::with_capacity(ms.len());
            for (f, m) in o.frames.iter().zip(ms) {
                let (ny, nx) = f.shape();
                let mut data = f.data.clone();
                let mut var = f.variance.clone();
                let mut pm = m.clone();
                for y in 0..ny {
                    let ye = y as i64 + dy;
                    for x in 0..nx {
                        let xe = x as i64 + dx;
                        if ye < 0 || xe < 0 || ye >= ny as i64 || xe >= nx as i64 {
                            pm[[y, x]] = 1;
                            continue;
                        }
                        let (ye, xe) = (ye as usize, xe as usize);
                        data[[y, x]] += f.data[[ye, xe]];
                        if let (Some(v), Some(v0)) = (var.as_mut(), f.variance.as_ref()) {
                            v[[y, x]] += v0[[ye, xe]];
                        }
                        pm[[y, x]] |= m[[ye, xe]];
                    }
                }
                let mut pf = Frame::new(data, f.header.clone());
                pf.variance = var;
                pf.mask = f.mask.clone();
                frames.push(pf);
                pms.push(pm);
            }
            out_masks.push(pms);
            SkySubtractedOrientation {
                posang_deg: o.posang_deg,
                analyzer_deg: o.analyzer_deg,
                frames,
                offsets: o.offsets.clone(),
            }
        })
        .collect();
    (pairs, out_masks)
}

/// [`locate_primary`] on frames where the target's brightest point is its o image.
fn locate_primary_in(
    orients: &[SkySubtractedOrientation],
    masks: &[Vec<Array2<u8>>],
    profile: &Profile,
    params: &MeasureParams,
) -> Result<Primary, MeasureError> {
    let g = &profile.geometry;
    let orow = g.target_rows(Beam::Ordinary);
    let first = orients
        .first()
        .and_then(|o| o.frames.first())
        .ok_or_else(|| MeasureError::new("no frames"))?;
    let (_, nx) = first.shape();
    let o0 = &orients[0];
    // Frames agree on the target when their brightest sources are within a pair's
    // separation (plus the pointing tolerance) of each other.
    let reach = params.companion_search_arcsec / g.pixscale_arcsec + POINTING_TOL_PX;
    let mut flags = Vec::new();
    // The anchor is searched within `primary_search_px` of the nominal position, or less
    // when a brighter source set aside lies closer: half way to it.
    let mut search_px = params.primary_search_px;
    let nominal = match params.nominal_xy_px {
        Some(xy) => xy,
        None => {
            // The pointing: where the telescope puts the target at zero jitter offset.
            let pointing = if g.has_mask() {
                (nx as f64 / 2.0, (orow[0] + orow[1]) as f64 / 2.0 - 0.5)
            } else {
                g.pointing_px()
            };
            let found = target_at_zero_offset(o0, &masks[0], orow, pointing, reach, params.primary_search_px);
            if let Some(b) = found.brighter {
                search_px = search_px.min(0.5 * (b.xy.0 - found.xy.0).hypot(b.xy.1 - found.xy.1));
                let (sep, pa) = offset_to_sep_pa(
                    b.xy.0 - found.xy.0,
                    b.xy.1 - found.xy.1,
                    o0.posang_deg,
                    g.pixscale_arcsec,
                );
                flags.push(Flag::with_detail(
                    FlagCode::BrighterSourceInStrip,
                    format!(
                        "{sep:.1}\" at PA {pa:.1} deg from the target ({:.0} px at POSANG {}), its peak {:.1} times \
                         the target's",
                        (b.xy.0 - found.xy.0).hypot(b.xy.1 - found.xy.1),
                        o0.posang_deg,
                        b.peak / found.peak
                    ),
                ));
            }
            found.xy
        }
    };
    let fwhm_guess = 0.8 / g.pixscale_arcsec;
    // The star at the nominal position in every frame of the first orientation, carried
    // back by the header offsets; the anchor is the position most frames agree on (within
    // 3 px; the earliest frame wins ties). One frame alone can pick the fainter component
    // when a cosmic ray or a masked pixel sits on the brighter one's core.
    let mut at_zero: Vec<(f64, f64)> = Vec::new();
    for ((f, off), m) in o0.frames.iter().zip(&o0.offsets).zip(&masks[0]) {
        let peak = brightest_peak(
            f.data.view(),
            m.view(),
            nominal.0 + off[0],
            nominal.1 + off[1],
            search_px,
            orow,
        );
        if let Some((px, py, _)) = peak {
            let c = refine(f.data.view(), m.view(), px, py, fwhm_guess, 4.0).unwrap_or((px, py));
            at_zero.push((c.0 - off[0], c.1 - off[1]));
        }
    }
    let votes = |p: &(f64, f64)| {
        at_zero
            .iter()
            .filter(|q| (q.0 - p.0).hypot(q.1 - p.1) <= POINTING_TOL_PX)
            .count()
    };
    let anchor = at_zero
        .iter()
        .enumerate()
        .max_by_key(|(i, p)| (votes(p), std::cmp::Reverse(*i)))
        .map(|(_, p)| *p)
        .ok_or_else(|| {
            MeasureError::new(format!(
                "no source found within {search_px} px of the nominal target position"
            ))
        })?;
    // The star found at the anchor may be either component; the other rotates about the
    // pointing centre, so at another rotator angle the anchored star can have moved by up
    // to twice the companion search radius (the labels are made consistent later, from
    // the stacks).
    let wide = 8.0 + 2.0 * params.companion_search_arcsec / g.pixscale_arcsec;
    let centres = orients
        .iter()
        .zip(masks)
        .map(|(o, ms)| centres_in_orientation(o, ms, anchor, fwhm_guess, orow, wide))
        .collect();
    Ok(Primary {
        centres,
        fwhm_guess,
        flags,
    })
}

/// A source found in most frames of an orientation at one position at zero jitter offset.
#[derive(Debug, Clone, Copy)]
struct Agreed {
    /// Position at zero offset, px (the median of the frames that agree, on each axis).
    xy: (f64, f64),
    /// Median peak (3x3 box mean of unmasked pixels) of those frames, ADU.
    peak: f64,
}

/// The target's position at zero offset when no position is given ([`target_at_zero_offset`]).
#[derive(Debug, Clone, Copy)]
struct TargetAtZero {
    /// The centre of the primary search at zero offset, px.
    xy: (f64, f64),
    /// Peak of the target found there, ADU (NaN: the pointing itself, nothing found).
    peak: f64,
    /// A brighter source of the strip that is not the target.
    brighter: Option<Agreed>,
}

/// Smallest signal-to-noise ratio of the 3x3 box at a peak near the pointing for it to be
/// taken as a star (noise, a cosmic-ray remnant, a star's wing: none agree across frames
/// and reach this together).
const POINTING_MIN_SNR: f64 = 5.0;

/// Where the target sits at zero jitter offset when no position is given. The target is
/// the binary at the pointing, not the brightest star of the strip: a brighter field star
/// elsewhere in the target's strip must not take its place.
///
/// 1. The brightest source of the strip that most frames agree on ([`brightest_in_strip`]):
///    when it lies within `search_px` (`measure.primary_search_px`) of the pointing, it is
///    the target (brightness decides among sources compatible with the pointing).
/// 2. Else the brightest source within `search_px` of the pointing in each frame (the
///    pointing carried by the frame's header offset), a peak of its own (inside the search
///    disc, at S/N >= [`POINTING_MIN_SNR`]) that at least half of the frames agree on: the
///    target, and the brighter one is reported, unless the two are within `reach` (the
///    two stars of one pair).
/// 3. Else the brightest source of the strip (a target placed away from the pointing),
///    else the pointing itself.
fn target_at_zero_offset(
    o: &SkySubtractedOrientation,
    ms: &[Array2<u8>],
    orow: [usize; 2],
    pointing: (f64, f64),
    reach: f64,
    search_px: f64,
) -> TargetAtZero {
    let at_pointing = |xy: (f64, f64)| (xy.0 - pointing.0).hypot(xy.1 - pointing.1) <= search_px;
    let Some(bright) = brightest_in_strip(o, ms, orow, reach) else {
        return TargetAtZero {
            xy: pointing,
            peak: f64::NAN,
            brighter: None,
        };
    };
    let as_target = |a: Agreed| TargetAtZero {
        xy: a.xy,
        peak: a.peak,
        brighter: None,
    };
    // Without a header offset for every frame the pointing cannot be followed from frame
    // to frame: the brightest source, as before the pointing was used.
    if at_pointing(bright.xy) || o.offsets.len() != o.frames.len() {
        return as_target(bright);
    }
    match source_at_pointing(o, ms, orow, pointing, reach, search_px) {
        Some(t) if (t.xy.0 - bright.xy.0).hypot(t.xy.1 - bright.xy.1) > reach => TargetAtZero {
            xy: t.xy,
            peak: t.peak,
            brighter: Some(bright),
        },
        _ => as_target(bright),
    }
}

/// The brightest source of the o-target strip in each frame of the first orientation,
/// carried back by the header offset. The brightest source is either star of a near-equal
/// pair (a different one from frame to frame) and the header offsets miss the true pointing
/// by a pixel or two, so frames agree on the target when their positions are within `reach`
/// (the largest pair separation searched plus the pointing tolerance): the position most
/// frames agree with (the earliest wins ties), accepted when at least half of them do (a
/// cosmic ray or a defect that escaped the masks wins in one frame, not in most); the
/// position is the median of the agreeing positions on each axis. None: no agreement.
fn brightest_in_strip(o: &SkySubtractedOrientation, ms: &[Array2<u8>], orow: [usize; 2], reach: f64) -> Option<Agreed> {
    let mut at_zero = Vec::new();
    for ((f, off), m) in o.frames.iter().zip(&o.offsets).zip(ms) {
        let (_, nx) = f.shape();
        let centre = (nx as f64 / 2.0, (orow[0] + orow[1]) as f64 / 2.0);
        if let Some((x, y, v)) = brightest_peak(f.data.view(), m.view(), centre.0, centre.1, nx as f64, orow) {
            at_zero.push((x - off[0], y - off[1], v));
        }
    }
    agreed(&at_zero, reach, at_zero.len())
}

/// The brightest star within `search_px` of the pointing in each frame of the first
/// orientation (the pointing moved by the frame's header offset), carried back to zero
/// offset; only peaks of their own count (inside the disc by 1.5 px: a brighter star's wing
/// beyond it peaks on the rim; S/N of the 3x3 box >= [`POINTING_MIN_SNR`] when the frame
/// has a variance). Accepted when at least half of all the frames agree within `reach`.
fn source_at_pointing(
    o: &SkySubtractedOrientation,
    ms: &[Array2<u8>],
    orow: [usize; 2],
    pointing: (f64, f64),
    reach: f64,
    search_px: f64,
) -> Option<Agreed> {
    let mut at_zero = Vec::new();
    for ((f, off), m) in o.frames.iter().zip(&o.offsets).zip(ms) {
        let guess = (pointing.0 + off[0], pointing.1 + off[1]);
        let Some((x, y, v)) = brightest_peak(f.data.view(), m.view(), guess.0, guess.1, search_px, orow) else {
            continue;
        };
        let inside = (x - guess.0).hypot(y - guess.1) <= search_px - 1.5;
        let significant = f
            .variance
            .as_ref()
            .is_none_or(|var| box_snr(f.data.view(), var.view(), m.view(), x, y) >= POINTING_MIN_SNR);
        if inside && significant {
            at_zero.push((x - off[0], y - off[1], v));
        }
    }
    agreed(&at_zero, reach, o.frames.len())
}

/// Signal-to-noise ratio of the unmasked pixels of the 3x3 box at (x, y) (integers inside
/// the image, as [`brightest_peak`] returns them): their sum over the square root of their
/// summed variance (0 when nothing is unmasked or the variance is not positive).
fn box_snr(img: ArrayView2<f32>, var: ArrayView2<f32>, mask: ArrayView2<u8>, x: f64, y: f64) -> f64 {
    let (ny, nx) = img.dim();
    let (xc, yc) = (x as usize, y as usize);
    let (mut s, mut v) = (0.0, 0.0);
    for j in yc.saturating_sub(1)..=(yc + 1).min(ny - 1) {
        for i in xc.saturating_sub(1)..=(xc + 1).min(nx - 1) {
            if mask[[j, i]] == 0 {
                s += img[[j, i]] as f64;
                v += var[[j, i]] as f64;
            }
        }
    }
    if v > 0.0 {
        s / v.sqrt()
    } else {
        0.0
    }
}

/// The position most of `at_zero` (x, y, peak) agree with within `reach` (the earliest
/// wins ties), accepted when the agreeing ones are at least half of `n_frames`; position
/// and peak the medians of the agreeing ones.
fn agreed(at_zero: &[(f64, f64, f64)], reach: f64, n_frames: usize) -> Option<Agreed> {
    let agreeing = |p: &(f64, f64, f64)| -> Vec<(f64, f64, f64)> {
        at_zero
            .iter()
            .filter(|q| (q.0 - p.0).hypot(q.1 - p.1) <= reach)
            .copied()
            .collect()
    };
    let group = at_zero
        .iter()
        .enumerate()
        .map(|(i, p)| (agreeing(p), i))
        .max_by_key(|(g, i)| (g.len(), std::cmp::Reverse(*i)))?
        .0;
    if 2 * group.len() < n_frames {
        return None;
    }
    let med = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    Some(Agreed {
        xy: (
            med(group.iter().map(|p| p.0).collect()),
            med(group.iter().map(|p| p.1).collect()),
        ),
        peak: med(group.iter().map(|p| p.2).collect()),
    })
}

/// How far the true pointing may be from the header offsets, px (the agreement radius of
/// positions carried back to zero offset).
const POINTING_TOL_PX: f64 = 3.0;
/// Search radius about the anchor for the first frame of an orientation, px.
const NEAR_ANCHOR_PX: f64 = 8.0;
/// A peak near the anchor fainter than this fraction of the brightest peak within reach of
/// the rotation is noise or a wing, not the anchored star (the components of the pairs
/// measured are within a factor 4 in flux).
const NEAR_ANCHOR_MIN_PEAK: f64 = 0.1;

/// The primary in the frames of one orientation, starting from `anchor` (its position at
/// zero jitter offset).
fn centres_in_orientation(
    o: &SkySubtractedOrientation,
    ms: &[Array2<u8>],
    anchor: (f64, f64),
    fwhm_guess: f64,
    orow: [usize; 2],
    wide: f64,
) -> Vec<Option<(f64, f64)>> {
    let mut cs: Vec<Option<(f64, f64)>> = Vec::new();
    let mut first: Option<((f64, f64), [f64; 2])> = None;
    for ((f, off), m) in o.frames.iter().zip(&o.offsets).zip(ms) {
        let c = match first {
            Some((c1, off1)) => {
                let guess = (c1.0 + off[0] - off1[0], c1.1 + off[1] - off1[1]);
                refine(f.data.view(), m.view(), guess.0, guess.1, fwhm_guess, 3.0).or_else(|| {
                    // A defect or cosmic ray near the guess: restart from the brightest
                    // peak within the pointing tolerance.
                    brightest_peak(f.data.view(), m.view(), guess.0, guess.1, 3.0, orow)
                        .and_then(|(x, y, _)| refine(f.data.view(), m.view(), x, y, fwhm_guess, 3.0))
                })
            }
            None => {
                let guess = (anchor.0 + off[0], anchor.1 + off[1]);
                let peak = |r: f64| brightest_peak(f.data.view(), m.view(), guess.0, guess.1, r, orow);
                let star = |(x, y, _): (f64, f64, f64)| refine(f.data.view(), m.view(), x, y, fwhm_guess, 4.0);
                // Near the anchor first; when no star is there (the anchored component
                // rotated away), the brightest star within reach of the rotation. The
                // brightest point near the anchor is a star only when it is a peak of its
                // own: inside the search disc (the wing of a star beyond it peaks on the
                // rim) and not much fainter than the brightest star within reach (noise).
                let far = peak(wide);
                let near = peak(NEAR_ANCHOR_PX).filter(|&(x, y, v)| {
                    (x - guess.0).hypot(y - guess.1) <= NEAR_ANCHOR_PX - 1.5
                        && far.is_none_or(|(_, _, vf)| v >= NEAR_ANCHOR_MIN_PEAK * vf)
                });
                let c = near.and_then(star).or_else(|| far.and_then(star));
                if let Some(c) = c {
                    first = Some((c, *off));
                }
                c
            }
        };
        cs.push(c);
    }
    cs
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A star whose o image (at (40, 30)) is fainter than its e image (at (40, 30) + (17,
    /// -9): 40 % polarized) and an unrelated star brighter than the o image: on the frame
    /// the brightest point near the o image is not the o image, on the pair image it is
    /// (o + e there, e alone at the e image, the other star alone at its place). Each pixel
    /// sums its partner's value and variance and is unusable where its partner is, or where
    /// the partner is off the frame.
    #[test]
    fn the_pair_image_peaks_at_the_o_image() {
        let (ny, nx) = (64, 96);
        let eo = (17.0, -9.0);
        let star = |x0: f64, y0: f64, f: f32| {
            Array2::from_shape_fn((ny, nx), |(y, x)| {
                let r2 = (x as f64 - x0).powi(2) + (y as f64 - y0).powi(2);
                f * (-r2 / (2.0 * 1.5f64.powi(2))).exp() as f32
            })
        };
        let data = star(40.0, 30.0, 30.0) + star(57.0, 21.0, 70.0) + star(50.0, 40.0, 60.0);
        let mut f = Frame::new(data, sofipol_calib::header::Header::new("t.fits"));
        f.variance = Some(Array2::from_elem((ny, nx), 1.0));
        let mut m = Array2::<u8>::zeros((ny, nx));
        m[[21, 57]] = 1; // a bad pixel at the e image's centre
        let o = SkySubtractedOrientation {
            posang_deg: 0.0,
            analyzer_deg: 0.0,
            frames: vec![f],
            offsets: vec![[0.0, 0.0]],
        };
        let on_frame = brightest_peak(o.frames[0].data.view(), m.view(), 45.0, 30.0, 20.0, [0, ny]).unwrap();
        assert_ne!((on_frame.0, on_frame.1), (40.0, 30.0));
        let (pairs, pms) = pair_images(std::slice::from_ref(&o), &[vec![m.clone()]], eo);
        let p = &pairs[0].frames[0];
        let pm = &pms[0][0];
        let best = brightest_peak(p.data.view(), pm.view(), 45.0, 30.0, 20.0, [0, ny]).unwrap();
        assert_eq!((best.0, best.1), (40.0, 30.0), "{best:?}");
        // Sum, variance and mask of each pixel and its partner.
        assert_eq!(
            p.data[[30, 40]],
            o.frames[0].data[[30, 40]] + o.frames[0].data[[21, 57]]
        );
        assert_eq!(p.variance.as_ref().unwrap()[[30, 40]], 2.0);
        assert_eq!(pm[[30, 40]], 1, "the partner's bad pixel");
        assert_eq!(pm[[30, 41]], 0);
        // Partners off the frame: columns x + 17 >= nx, rows y - 9 < 0.
        assert!((0..ny).all(|y| pm[[y, nx - 17]] == 1));
        assert!((0..nx).all(|x| pm[[8, x]] == 1));
        assert_eq!(pm[[9, nx - 18]], 0);
    }
}
