//! Finding the binary: the primary's position in every frame (header jitter offsets
//! refined by centroids), the e-o beam offset (measured), and the companion's offset at
//! each orientation (from a two-star PSF fit on the registered stack of the dithers).
use ndarray::{s, Array2, ArrayView2};
use sofipol_calib::Frame;

use crate::photometry::{centroid, fit_psf, CentroidParams, PsfFitParams, PsfModel};
use crate::stokes::model::{companion_offset_px, offset_to_sep_pa};

/// Brightest point of a 3x3 box-smoothed image within `radius` of (x0, y0), restricted to
/// rows [y_lo, y_hi) and unmasked pixels. Returns (x, y, smoothed value).
pub fn brightest_peak(
    img: ArrayView2<f32>,
    mask: ArrayView2<u8>,
    x0: f64,
    y0: f64,
    radius: f64,
    rows: [usize; 2],
) -> Option<(f64, f64, f64)> {
    let (ny, nx) = img.dim();
    let r = radius.ceil() as i64;
    let mut best: Option<(f64, f64, f64)> = None;
    for y in (y0.round() as i64 - r).max(rows[0] as i64 + 1)
        ..=(y0.round() as i64 + r).min(rows[1] as i64 - 2).min(ny as i64 - 2)
    {
        for x in (x0.round() as i64 - r).max(1)..=(x0.round() as i64 + r).min(nx as i64 - 2) {
            if ((x as f64 - x0).powi(2) + (y as f64 - y0).powi(2)) > radius * radius {
                continue;
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
            if n < 5 {
                continue;
            }
            let v = sum / n as f64;
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

/// Shift-and-add of square cut-outs of half-size `h` centred on the rounded positions
/// `centres` (one per frame). Returns the stack (mean) and the mean fractional offset of
/// the true centres from the cut-out centre.
pub fn stack_cutouts(
    frames: &[(&Array2<f32>, &Array2<u8>)],
    centres: &[(f64, f64)],
    h: usize,
) -> (Array2<f32>, Array2<u8>, (f64, f64)) {
    let n = 2 * h + 1;
    let mut acc = Array2::<f64>::zeros((n, n));
    let mut cnt = Array2::<u32>::zeros((n, n));
    let (mut fx, mut fy) = (0.0, 0.0);
    for (&(img, mask), &(cx, cy)) in frames.iter().zip(centres) {
        let (ix, iy) = (cx.round() as i64, cy.round() as i64);
        fx += cx - ix as f64;
        fy += cy - iy as f64;
        let (ny, nx) = img.dim();
        for j in 0..n {
            for i in 0..n {
                let (y, x) = (iy - h as i64 + j as i64, ix - h as i64 + i as i64);
                if y < 0 || x < 0 || y >= ny as i64 || x >= nx as i64 {
                    continue;
                }
                let (y, x) = (y as usize, x as usize);
                if mask[[y, x]] == 0 && img[[y, x]].is_finite() {
                    acc[[j, i]] += img[[y, x]] as f64;
                    cnt[[j, i]] += 1;
                }
            }
        }
    }
    let k = frames.len().max(1) as f64;
    let stack = Array2::from_shape_fn((n, n), |(j, i)| {
        if cnt[[j, i]] > 0 {
            (acc[[j, i]] / cnt[[j, i]] as f64) as f32
        } else {
            0.0
        }
    });
    let smask = cnt.mapv(|c| u8::from(c == 0));
    (stack, smask, (fx / k, fy / k))
}

/// The pair found on a stack: positions relative to the stack's reference centre.
#[derive(Debug, Clone, Copy)]
pub struct PairOnStack {
    /// Primary (brighter) offset from the reference centroid, px.
    pub a: (f64, f64),
    /// Companion offset from the reference centroid, px.
    pub b: (f64, f64),
    /// Fitted fluxes (stack units) of A and B.
    pub flux: (f64, f64),
    /// Flux error of B.
    pub flux_b_err: f64,
    /// Fitted FWHM, px.
    pub fwhm_px: f64,
    /// Fitted Moffat beta (NaN for a Gaussian model).
    pub beta: f64,
    /// F statistic of the two-star fit against the one-star fit on the same pixels:
    /// ((S1 - S2)/3) / (S2/(n - 7)) with S the residual sums of squares. A single star
    /// gives ~1; a real companion gives hundreds or more.
    pub f_stat: f64,
}

impl PairOnStack {
    /// Whether the companion is real: F above `min_f` and separated by at least
    /// `min_sep_px` (the whole-pixel registration of the stack blurs a lone star so that a
    /// "pair" ~0.5 px apart fits it better).
    pub fn companion(&self, min_f: f64, min_sep_px: f64) -> bool {
        self.f_stat > min_f && self.flux.1 > 0.0 && (self.b.0 - self.a.0).hypot(self.b.1 - self.a.1) >= min_sep_px
    }
}

/// Residual sum of squares of `model_resid` over unmasked pixels within `r` of `(x, y)`.
fn rss(resid: &Array2<f32>, smask: &Array2<u8>, x: f64, y: f64, r: f64) -> (f64, usize) {
    let (mut s, mut n) = (0.0, 0);
    for ((j, i), &v) in resid.indexed_iter() {
        if smask[[j, i]] == 0 && ((i as f64 - x).powi(2) + (j as f64 - y).powi(2)) <= r * r {
            s += (v as f64).powi(2);
            n += 1;
        }
    }
    (s, n)
}

/// Find the companion on a stack centred (to within `frac`) on the blend centroid: fit one
/// star, look for the largest residual within `search_px`, then fit two stars. With
/// `predicted` (offset of B from A, px) the residual search is skipped. Both fits use `model`.
pub fn find_pair(
    stack: &Array2<f32>,
    smask: &Array2<u8>,
    frac: (f64, f64),
    fwhm_guess: f64,
    search_px: f64,
    predicted: Option<(f64, f64)>,
    model: PsfModel,
) -> Option<PairOnStack> {
    let n = stack.dim().0;
    let c = ((n / 2) as f64 + frac.0, (n / 2) as f64 + frac.1);
    let p1 = PsfFitParams {
        fwhm_px: fwhm_guess,
        fit_radius_px: (2.0 * fwhm_guess).max(4.0),
        background: Some(0.0),
        model,
        ..PsfFitParams::default()
    };
    let single = fit_psf(stack.view(), None, Some(smask.view()), &[c], &p1).ok()?;
    let s0 = single.stars[0];
    let fwhm = single.fwhm_x().clamp(0.5 * fwhm_guess, 3.0 * fwhm_guess);
    let b_guess = match predicted {
        Some((dx, dy)) => (s0.x + dx * 0.5, s0.y + dy * 0.5, s0.x - dx * 0.5, s0.y - dy * 0.5),
        None => {
            let resid = crate::photometry::subtract_star(stack.view(), &single, 0);
            let (bx, by, v) = brightest_peak(resid.view(), smask.view(), s0.x, s0.y, search_px, [0, n])?;
            if !(v > 0.0) {
                return None;
            }
            // The single fit sits between the two stars: put A opposite B about it,
            // weighted by the residual peak relative to the single fit's peak.
            let peak = s0.flux / (2.0 * std::f64::consts::PI * single.sigma_x * single.sigma_y);
            let w = (v / peak).clamp(0.05, 1.0);
            let (dx, dy) = (bx - s0.x, by - s0.y);
            (bx, by, s0.x - w * dx / (1.0 + w), s0.y - w * dy / (1.0 + w))
        }
    };
    let sep_guess = ((b_guess.0 - b_guess.2).powi(2) + (b_guess.1 - b_guess.3).powi(2)).sqrt();
    let p2 = PsfFitParams {
        fwhm_px: fwhm,
        fit_radius_px: (1.5 * fwhm).max(3.0).max(0.6 * sep_guess),
        background: Some(0.0),
        model,
        ..PsfFitParams::default()
    };
    let single_only = PairOnStack {
        a: (s0.x - c.0 + frac.0, s0.y - c.1 + frac.1),
        b: (f64::NAN, f64::NAN),
        flux: (s0.flux, 0.0),
        flux_b_err: f64::INFINITY,
        fwhm_px: single.fwhm_x(),
        beta: single.beta,
        f_stat: 0.0,
    };
    let Ok(two) = fit_psf(
        stack.view(),
        None,
        Some(smask.view()),
        &[(b_guess.2, b_guess.3), (b_guess.0, b_guess.1)],
        &p2,
    ) else {
        return Some(single_only);
    };
    let (sa, sb) = (two.stars[0], two.stars[1]);
    let (a, b) = if sa.flux >= sb.flux { (sa, sb) } else { (sb, sa) };
    // Model selection on one fixed set of pixels: is the second star needed?
    let sep = (a.x - b.x).hypot(a.y - b.y);
    let r = (2.0 * fwhm).max(sep + 1.5 * fwhm).min(n as f64 / 2.0);
    let r1 = crate::photometry::subtract_star(stack.view(), &single, 0);
    let r2 = crate::photometry::subtract_star(crate::photometry::subtract_star(stack.view(), &two, 0).view(), &two, 1);
    let (s1, npix) = rss(&r1, smask, s0.x, s0.y, r);
    let (s2, _) = rss(&r2, smask, s0.x, s0.y, r);
    let f_stat = if npix > 8 && s2 > 0.0 {
        ((s1 - s2) / 3.0) / (s2 / (npix - 7) as f64)
    } else {
        0.0
    };
    if std::env::var_os("SOFIPOL_DEBUG_PAIR").is_some() {
        eprintln!(
            "find_pair: sep {sep:.2} px, fluxes {:.0} {:.0}, S1 {s1:.3e} S2 {s2:.3e} n {npix} F {f_stat:.1}",
            a.flux, b.flux
        );
    }
    if !(b.flux > 0.0) {
        return Some(single_only);
    }
    Some(PairOnStack {
        a: (a.x - c.0 + frac.0, a.y - c.1 + frac.1),
        b: (b.x - c.0 + frac.0, b.y - c.1 + frac.1),
        flux: (a.flux, b.flux),
        flux_b_err: b.flux_err,
        fwhm_px: two.fwhm_x(),
        beta: two.beta,
        f_stat,
    })
}

/// Combine the companion offsets found at several orientations into one separation and
/// PA (flux-error weighted circular mean of the PA), returning also the largest position
/// disagreement in px.
pub fn combine_geometry(found: &[(f64, (f64, f64), f64)], scale: f64) -> Option<(f64, f64, f64)> {
    // found: (posang, offset of B from A, weight)
    if found.is_empty() {
        return None;
    }
    let (mut ws, mut wsep, mut cx, mut cy) = (0.0, 0.0, 0.0, 0.0);
    for &(posang, (dx, dy), w) in found {
        let (sep, pa) = offset_to_sep_pa(dx, dy, posang, scale);
        ws += w;
        wsep += w * sep;
        cx += w * pa.to_radians().cos();
        cy += w * pa.to_radians().sin();
    }
    let sep = wsep / ws;
    let pa = cy.atan2(cx).to_degrees().rem_euclid(360.0);
    let worst = found
        .iter()
        .map(|&(posang, (dx, dy), _)| {
            let (px, py) = companion_offset_px(sep, pa, posang, scale);
            (px - dx).hypot(py - dy)
        })
        .fold(0.0, f64::max);
    Some((sep, pa, worst))
}

/// Median e-o offset from per-frame (o, e) centroids.
pub fn median_offset(pairs: &[((f64, f64), (f64, f64))]) -> Option<(f64, f64)> {
    if pairs.is_empty() {
        return None;
    }
    let med = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        let n = v.len();
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    };
    Some((
        med(pairs.iter().map(|(o, e)| e.0 - o.0).collect()),
        med(pairs.iter().map(|(o, e)| e.1 - o.1).collect()),
    ))
}

/// A cut-out view helper: rows of a strip.
pub fn strip_rows(img: &Array2<f32>, rows: [usize; 2]) -> ArrayView2<'_, f32> {
    img.slice(s![rows[0]..rows[1], ..])
}

/// The e-o beam offset by cross-correlation of ordinary and extraordinary cut-outs of the
/// target (summed over frames): the two beams show the same pair with fluxes that differ
/// only by the polarization, so the correlation peaks at the true offset even when the
/// brighter star in one beam is the fainter in the other (a brightest-peak match would
/// then jump between the components). Integer search within `search` px of `start`, then
/// a parabola through the peak and its neighbours on each axis.
pub fn eo_offset_by_correlation(
    frames: &[(&Array2<f32>, &Array2<u8>)],
    centres: &[(f64, f64)],
    start: (f64, f64),
    h: usize,
    search: i64,
) -> Option<(f64, f64)> {
    let n = 2 * search as usize + 1;
    let mut score = vec![0.0f64; n * n];
    let mut used = 0;
    for (&(img, mask), &(cx, cy)) in frames.iter().zip(centres) {
        let (ny, nx) = img.dim();
        let (ox, oy) = (cx.round() as i64, cy.round() as i64);
        let (ex0, ey0) = ((cx + start.0).round() as i64, (cy + start.1).round() as i64);
        let hh = h as i64;
        if ox - hh < 0 || oy - hh < 0 || ox + hh >= nx as i64 || oy + hh >= ny as i64 {
            continue;
        }
        if ex0 - hh - search < 0
            || ey0 - hh - search < 0
            || ex0 + hh + search >= nx as i64
            || ey0 + hh + search >= ny as i64
        {
            continue;
        }
        used += 1;
        for sy in -search..=search {
            for sx in -search..=search {
                let mut acc = 0.0;
                for j in -hh..=hh {
                    for i in -hh..=hh {
                        let (oyy, oxx) = ((oy + j) as usize, (ox + i) as usize);
                        let (eyy, exx) = ((ey0 + sy + j) as usize, (ex0 + sx + i) as usize);
                        if mask[[oyy, oxx]] == 0 && mask[[eyy, exx]] == 0 {
                            acc += img[[oyy, oxx]] as f64 * img[[eyy, exx]] as f64;
                        }
                    }
                }
                score[((sy + search) as usize) * n + (sx + search) as usize] += acc;
            }
        }
    }
    if used == 0 {
        return None;
    }
    let (mut bi, mut bv) = (0, f64::NEG_INFINITY);
    for (k, &v) in score.iter().enumerate() {
        if v > bv {
            bv = v;
            bi = k;
        }
    }
    let (by, bx) = (bi / n, bi % n);
    let para = |m: f64, c: f64, p: f64| {
        let d = m - 2.0 * c + p;
        if d < 0.0 {
            0.5 * (m - p) / d
        } else {
            0.0
        }
    };
    let dx = if bx > 0 && bx + 1 < n {
        para(score[by * n + bx - 1], bv, score[by * n + bx + 1])
    } else {
        0.0
    };
    let dy = if by > 0 && by + 1 < n {
        para(score[(by - 1) * n + bx], bv, score[(by + 1) * n + bx])
    } else {
        0.0
    };
    let fx = (start.0).round() + (bx as f64 - search as f64) + dx.clamp(-0.5, 0.5) - start.0;
    let fy = (start.1).round() + (by as f64 - search as f64) + dy.clamp(-0.5, 0.5) - start.1;
    Some((start.0 + fx, start.1 + fy))
}
