//! Superflat from the sky of the night's dithered science frames.
use ndarray::Array2;
use rayon::prelude::*;

use super::*;

/// Marks, inside the superflat builder, pixels with too few star-free values.
const UNKNOWN: u8 = 2;

/// The strips of a frame: which strip each row is in, the strips, the level above which
/// a pixel is not used.
struct Layout<'a> {
    shape: (usize, usize),
    strips: [(&'a str, [usize; 2]); 6],
    strip_of: Vec<Option<usize>>,
    sat: f32,
}

/// Per frame: strip levels and the per-pixel sigma of a normalized value, and the
/// exclusion map (defects, masked, saturated, stars grown by star_grow_px).
struct Prep {
    inv_level: [f32; 6],
    sigma: [f32; 6],
    excl: Array2<u8>,
}

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
    // Row slices below: frames not in standard layout (never from FITS) are copied once.
    let standard: Vec<std::borrow::Cow<Frame>> = frames
        .iter()
        .map(|&f| {
            if f.data.is_standard_layout() && f.mask.is_standard_layout() {
                std::borrow::Cow::Borrowed(f)
            } else {
                let mut g = f.clone();
                g.data = g.data.as_standard_layout().into_owned();
                g.mask = g.mask.as_standard_layout().into_owned();
                std::borrow::Cow::Owned(g)
            }
        })
        .collect();
    let frames: Vec<&Frame> = standard.iter().map(|c| c.as_ref()).collect();
    let shape = check_shapes(&frames, profile, STAGE)?;
    let ny = shape.0;
    let g = &profile.geometry;
    let strips = g.strips();
    let strip_of: Vec<Option<usize>> = (0..ny)
        .map(|y| strips.iter().position(|(_, r)| y >= r[0] && y < r[1]))
        .collect();
    let sat = profile.detector.nonlinear_warn_adu as f32;
    let lay = Layout {
        shape,
        strips,
        strip_of,
        sat,
    };
    let defect = fixed_defects(&frames, &lay, opts);
    let preps: Vec<Prep> = frames
        .par_iter()
        .map(|f| prep_frame(f, profile, &lay, &defect, opts))
        .collect::<Result<Vec<_>>>()?;
    let (mut resp, mut var, mut bad) = combine(&frames, &preps, &lay, opts);
    let min_values = opts.min_values.max(1);
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

/// Fixed detector defects (hot pixels and columns, dead pixels) sit at the same pixel in
/// every frame: found first as pixels whose median over (up to 9) frames, each divided
/// by its strip level, is outside [min_response, max_response], so that they are not
/// taken for stars (whose surroundings are left out).
fn fixed_defects(frames: &[&Frame], lay: &Layout, opts: &FlatOptions) -> Array2<u8> {
    let (shape, strips, strip_of, sat) = (lay.shape, &lay.strips, &lay.strip_of, lay.sat);
    let nx = shape.1;
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
            let rows: Vec<(&[f32], f32)> = sub.iter().zip(&inv).map(|(f, l)| (row_of(&f.data, y), l[k])).collect();
            for (x, o) in row.iter_mut().enumerate() {
                v.clear();
                v.extend(rows.iter().map(|(d, l)| d[x] * l));
                let m = median_f32(&mut v).unwrap_or(f32::NAN);
                if !(m >= opts.min_response && m <= opts.max_response) {
                    *o = 1;
                }
            }
        });
    d
}

/// Row `y` of an array as a slice (standard layout or not: a row of a 2-D array is
/// contiguous when its column stride is 1, which every array here has; checked).
fn row_of<T>(a: &Array2<T>, y: usize) -> &[T] {
    a.row(y).to_slice().expect("rows with unit column stride")
}

/// [`row_of`], mutable.
fn row_of_mut<T>(a: &mut Array2<T>, y: usize) -> &mut [T] {
    a.row_mut(y).into_slice().expect("rows with unit column stride")
}

/// Levels, sigmas and the exclusion map of one frame (stars found against a local level
/// and grown).
fn prep_frame(f: &Frame, profile: &Profile, lay: &Layout, defect: &Array2<u8>, opts: &FlatOptions) -> Result<Prep> {
    let (shape, strips, strip_of, sat) = (lay.shape, &lay.strips, &lay.strip_of, lay.sat);
    let (ny, nx) = shape;
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
        let (drow, mrow, defrow) = (row_of(&f.data, y), row_of(&f.mask, y), row_of(defect, y));
        let (erow, srow) = (row_of_mut(&mut excl, y), row_of_mut(&mut seed, y));
        for x in 0..nx {
            let d = drow[x];
            let l = local[x / BLOCK][k];
            if inv_level[k] <= 0.0 || l <= 0.0 || defrow[x] != 0 || mrow[x] != 0 || !d.is_finite() || d >= sat {
                erow[x] = 1;
                continue;
            }
            let sig = scatter[x / BLOCK][k].max((l * inv_g + rv).sqrt());
            let z = (d - l) / sig;
            if z > opts.star_sigma {
                erow[x] = 1;
                srow[x] = 2;
            } else if z > 2.0 {
                srow[x] = 1;
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
                    && (seed[[y, x - 1]] > 0 || seed[[y, x + 1]] > 0 || seed[[y - 1, x]] > 0 || seed[[y + 1, x]] > 0)
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
}

/// Per pixel the clipped inverse-variance weighted mean of the star-free normalized
/// values: response, variance and UNKNOWN where too few values.
fn combine(
    frames: &[&Frame],
    preps: &[Prep],
    lay: &Layout,
    opts: &FlatOptions,
) -> (Array2<f32>, Array2<f32>, Array2<u8>) {
    let (shape, strip_of) = (lay.shape, &lay.strip_of);
    let nx = shape.1;
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
            // Row slices of every frame (no 2-D indexing per value).
            let rows: Vec<(&[f32], &[u8], f32, f32)> = frames
                .iter()
                .zip(preps)
                .map(|(f, p)| (row_of(&f.data, y), row_of(&p.excl, y), p.inv_level[k], p.sigma[k]))
                .collect();
            for x in 0..nx {
                vals.clear();
                for &(d, e, il, sg) in &rows {
                    if e[x] == 0 {
                        vals.push((d[x] * il, sg));
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
    (resp, var, bad)
}
