//! Superflat from the sky of the night's dithered science frames.
use ndarray::Array2;
use rayon::prelude::*;

use super::lanes::{from_key, key, sort_lanes, sorting_network, LANES, NO_VALUE};
use super::*;

/// Marks, inside the superflat builder, pixels with too few star-free values.
const UNKNOWN: u8 = 2;

/// The strips of a frame: which strip each row is in, the strips, the level above which
/// a pixel is not used.
struct Layout<'a> {
    shape: (usize, usize),
    strips: Vec<(&'a str, [usize; 2])>,
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
        .par_iter()
        .map(|f| {
            let mut l = [0f32; 6];
            for (k, (_, [a, b])) in strips.iter().enumerate() {
                let m = strip_median(&f.data, &f.mask, *a, *b, |v| v < sat).unwrap_or(0.0);
                l[k] = if m > 0.0 { 1.0 / m } else { 0.0 };
            }
            l
        })
        .collect();
    // Per pixel the median of the frames' values, LANES pixels at a time (lanes.rs).
    let net = sorting_network(sub.len());
    let mid = sub.len() / 2;
    let mut d = Array2::<u8>::zeros(shape);
    d.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(nx)
        .enumerate()
        .for_each_init(
            || vec![[NO_VALUE; LANES]; sub.len()],
            |keys, (y, row)| {
                let Some(k) = strip_of[y] else { return };
                let rows: Vec<(&[f32], f32)> = sub.iter().zip(&inv).map(|(f, l)| (row_of(&f.data, y), l[k])).collect();
                for x0 in (0..nx).step_by(LANES) {
                    let w = LANES.min(nx - x0);
                    for (&(d, l), kk) in rows.iter().zip(keys.iter_mut()) {
                        let mut dv = [0f32; LANES];
                        dv[..w].copy_from_slice(&d[x0..x0 + w]);
                        for i in 0..LANES {
                            kk[i] = key(dv[i] * l);
                        }
                    }
                    sort_lanes(keys, &net);
                    for (i, o) in row[x0..x0 + w].iter_mut().enumerate() {
                        let m = from_key(keys[mid][i]);
                        if !(m >= opts.min_response && m <= opts.max_response) {
                            *o = 1;
                        }
                    }
                }
            },
        );
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
        if let Some(l) = strip_median(&f.data, &f.mask, *a, *b, |v| v < sat) {
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
    // Keys of one block's values (reused): median and 15.9th percentile selected on them.
    let mut keys: Vec<i32> = Vec::new();
    for (k, (_, [a, b])) in strips.iter().enumerate() {
        for bi in 0..nb {
            let (x0, x1) = (bi * BLOCK, ((bi + 1) * BLOCK).min(nx));
            keys.clear();
            for y in *a..*b {
                let (drow, mrow) = (row_of(&f.data, y), row_of(&f.mask, y));
                for x in (x0 + (y % 2)..x1).step_by(2) {
                    let d = drow[x];
                    if mrow[x] == 0 && d.is_finite() && d < sat {
                        keys.push(key(d));
                    }
                }
            }
            let i16 = (keys.len() as f64 * 0.1587) as usize;
            if let Some((med, p16)) = median_and_lower(&mut keys, i16) {
                local[bi][k] = med;
                scatter[bi][k] = (med - p16).max(0.0);
            }
        }
    }
    // Significance of each pixel above its local level, in sigma of that level.
    let mut excl = Array2::<u8>::zeros(shape);
    let mut seed = Array2::<u8>::zeros(shape);
    // Per block the sigma of its level (the larger of the scatter and the photon + read
    // noise) and whether the block can be judged at all.
    let sigs: Vec<[f32; 6]> = (0..nb)
        .map(|bi| std::array::from_fn(|k| scatter[bi][k].max((local[bi][k] * inv_g + rv).sqrt())))
        .collect();
    for (y, strip) in strip_of.iter().enumerate().take(ny) {
        let Some(k) = *strip else { continue };
        let (drow, mrow, defrow) = (row_of(&f.data, y), row_of(&f.mask, y), row_of(defect, y));
        let (erow, srow) = (row_of_mut(&mut excl, y), row_of_mut(&mut seed, y));
        for bi in 0..nb {
            let (x0, x1) = (bi * BLOCK, ((bi + 1) * BLOCK).min(nx));
            let (l, sig) = (local[bi][k], sigs[bi][k]);
            let unjudged = inv_level[k] <= 0.0 || l <= 0.0;
            // Branch-free over the block (it vectorises): unusable pixels are excluded and
            // seed nothing; stars are excluded and seed 2; pixels above 2 sigma seed 1.
            let cols = x0..x1;
            for ((((&d, &m), &def), e), sd) in drow[cols.clone()]
                .iter()
                .zip(&mrow[cols.clone()])
                .zip(&defrow[cols.clone()])
                .zip(&mut erow[cols.clone()])
                .zip(&mut srow[cols])
            {
                let unusable = unjudged | (def != 0) | (m != 0) | !d.is_finite() | (d >= sat);
                let z = (d - l) / sig;
                let star = !unusable & (z > opts.star_sigma);
                let above = !unusable & (z > 2.0);
                *e = u8::from(unusable | star);
                *sd = if star { 2 } else { u8::from(above) };
            }
        }
    }
    // Grow stars (a significant pixel with a neighbour above 2 sigma: not a lone
    // noise spike or cosmic-ray pixel) by star_grow_px: box dilation.
    let r = opts.star_grow_px;
    if r > 0 {
        let mut grow = Vec::new();
        for y in 1..ny.saturating_sub(1) {
            let (up, row, down) = (row_of(&seed, y - 1), row_of(&seed, y), row_of(&seed, y + 1));
            // Most rows hold no star: skip them in one scan.
            if !row.contains(&2) {
                continue;
            }
            for x in 1..nx.saturating_sub(1) {
                if row[x] == 2 && (row[x - 1] > 0 || row[x + 1] > 0 || up[x] > 0 || down[x] > 0) {
                    grow.push((y, x));
                }
            }
        }
        for (y, x) in grow {
            for yy in y.saturating_sub(r)..(y + r + 1).min(ny) {
                row_of_mut(&mut excl, yy)[x.saturating_sub(r)..(x + r + 1).min(nx)].fill(1);
            }
        }
    }
    Ok(Prep { inv_level, sigma, excl })
}

/// Per pixel the clipped inverse-variance weighted mean of the star-free normalized
/// values: response, variance and UNKNOWN where too few values. The pixels of a row are
/// taken [`LANES`] at a time: their values are sorted side by side by one sorting network
/// (the median: the element `median_f32` picks), then every frame's value is tested and
/// summed in frame order, lane by lane (the sums of the one-pixel-at-a-time loop, bit for
/// bit: test `lane_combine_is_the_scalar_combine`).
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
    let net = sorting_network(frames.len());
    resp.as_slice_mut()
        .expect("fresh array")
        .par_chunks_mut(nx)
        .zip(var.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
        .zip(bad.as_slice_mut().expect("fresh array").par_chunks_mut(nx))
        .enumerate()
        .for_each_init(
            || {
                let n = frames.len();
                (
                    vec![[0f32; LANES]; n],
                    vec![[NO_VALUE; LANES]; n],
                    vec![[false; LANES]; n],
                )
            },
            |(vals, keys, free), (y, ((rrow, vrow), brow))| {
                let Some(k) = strip_of[y] else { return };
                // Row slices of every frame (no 2-D indexing per value).
                let rows: Vec<(&[f32], &[u8], f32, f32)> = frames
                    .iter()
                    .zip(preps)
                    .map(|(f, p)| (row_of(&f.data, y), row_of(&p.excl, y), p.inv_level[k], p.sigma[k]))
                    .collect();
                for x0 in (0..nx).step_by(LANES) {
                    let w = LANES.min(nx - x0);
                    // Normalized values; the key of each star-free one, NO_VALUE elsewhere.
                    let mut count = [0usize; LANES];
                    for (((&(d, e, il, _), v), kk), fr) in rows
                        .iter()
                        .zip(vals.iter_mut())
                        .zip(keys.iter_mut())
                        .zip(free.iter_mut())
                    {
                        let (mut dv, mut ev) = ([0f32; LANES], [1u8; LANES]);
                        dv[..w].copy_from_slice(&d[x0..x0 + w]);
                        ev[..w].copy_from_slice(&e[x0..x0 + w]);
                        for l in 0..LANES {
                            v[l] = dv[l] * il;
                            fr[l] = ev[l] == 0;
                            kk[l] = if fr[l] { key(v[l]) } else { NO_VALUE };
                            count[l] += usize::from(fr[l]);
                        }
                    }
                    sort_lanes(keys, &net);
                    let mut med = [0f32; LANES];
                    for l in 0..LANES {
                        // count <= frames: the index is in range.
                        med[l] = from_key(keys[count[l] / 2][l]);
                    }
                    // Clipped weighted sums over the frames, in frame order.
                    let (mut sw, mut swv, mut n) = ([0f64; LANES], [0f64; LANES], [0usize; LANES]);
                    for ((&(_, _, _, sg), v), fr) in rows.iter().zip(vals.iter()).zip(free.iter()) {
                        let (lim, wt) = (clip * sg, 1.0 / (sg as f64 * sg as f64));
                        for l in 0..LANES {
                            let keep = fr[l] && (v[l] - med[l]).abs() <= lim;
                            sw[l] += if keep { wt } else { 0.0 };
                            swv[l] += if keep { wt * v[l] as f64 } else { 0.0 };
                            n[l] += usize::from(keep);
                        }
                    }
                    for l in 0..w {
                        let x = x0 + l;
                        // Too few star-free values (a star sat here in most frames): the
                        // response is unknown, so this pixel is left uncorrected (response
                        // 1, no flat noise) rather than masked: masking it would mask the
                        // stars of the science frames, which sit exactly there.
                        if count[l] < min_values || n[l] < min_values {
                            brow[x] = UNKNOWN;
                            continue;
                        }
                        rrow[x] = (swv[l] / sw[l]) as f32;
                        vrow[x] = (1.0 / sw[l]) as f32;
                    }
                }
            },
        );
    (resp, var, bad)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random numbers in [0, 1).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// `n` frames of `ny` x `nx` pixels around 1000 ADU (a few NaN, infinite and
    /// saturated), their preps with random exclusion maps (from none to all frames of a
    /// pixel excluded) and a layout of two strips with one off-strip row.
    fn scene(n: usize, ny: usize, nx: usize, seed: u64) -> (Vec<Frame>, Vec<Prep>, Layout<'static>) {
        let mut r = Lcg(seed);
        let frames: Vec<Frame> = (0..n)
            .map(|_| {
                let data = Array2::from_shape_fn((ny, nx), |_| {
                    let u = r.next();
                    match (u * 1000.0) as u32 {
                        0 => f32::NAN,
                        1 => f32::INFINITY,
                        2 => 1e6,
                        _ => 1000.0 + 60.0 * (r.next() - 0.5) + 5.0 * (u - 0.5),
                    }
                })
                .as_standard_layout()
                .into_owned();
                Frame::new(data, crate::header::Header::new(""))
            })
            .collect();
        // Exclusion: a pixel-dependent fraction of frames (0 to 100 %).
        let frac = Array2::from_shape_fn((ny, nx), |_| r.next());
        let preps: Vec<Prep> = (0..n)
            .map(|i| Prep {
                inv_level: [1e-3 * (1.0 + 0.01 * i as f32); 6],
                sigma: [0.01 + 0.002 * (i % 5) as f32; 6],
                excl: Array2::from_shape_fn((ny, nx), |(y, x)| {
                    let d = frames[i].data[[y, x]];
                    u8::from(r.next() < frac[[y, x]] || !d.is_finite())
                }),
            })
            .collect();
        const STRIPS: [(&str, [usize; 2]); 6] = [
            ("a", [0, 3]),
            ("b", [4, 7]),
            ("c", [0, 0]),
            ("d", [0, 0]),
            ("e", [0, 0]),
            ("f", [0, 0]),
        ];
        let strip_of = (0..ny)
            .map(|y| STRIPS.iter().position(|(_, s)| y >= s[0] && y < s[1]))
            .collect();
        let lay = Layout {
            shape: (ny, nx),
            strips: STRIPS.to_vec(),
            strip_of,
            sat: 5e5,
        };
        (frames, preps, lay)
    }

    /// The one-pixel-at-a-time combination (median by `median_f32`, then the clipped
    /// weighted sums in frame order): the slow, obviously correct version.
    fn combine_scalar(frames: &[&Frame], preps: &[Prep], lay: &Layout, opts: &FlatOptions) -> [Array2<f32>; 2] {
        let (ny, nx) = lay.shape;
        let mut resp = Array2::<f32>::ones((ny, nx));
        let mut var = Array2::<f32>::zeros((ny, nx));
        for y in 0..ny {
            let Some(k) = lay.strip_of[y] else { continue };
            for x in 0..nx {
                let vals: Vec<(f32, f32)> = frames
                    .iter()
                    .zip(preps)
                    .filter(|(_, p)| p.excl[[y, x]] == 0)
                    .map(|(f, p)| (f.data[[y, x]] * p.inv_level[k], p.sigma[k]))
                    .collect();
                if vals.len() < opts.min_values {
                    resp[[y, x]] = f32::NAN;
                    continue;
                }
                let med = median_f32(&mut vals.iter().map(|v| v.0).collect::<Vec<_>>()).unwrap();
                let (mut sw, mut swv, mut n) = (0f64, 0f64, 0);
                for &(v, sg) in &vals {
                    if (v - med).abs() <= opts.clip_sigma * sg {
                        let w = 1.0 / (sg as f64 * sg as f64);
                        sw += w;
                        swv += w * v as f64;
                        n += 1;
                    }
                }
                if n < opts.min_values {
                    resp[[y, x]] = f32::NAN;
                    continue;
                }
                resp[[y, x]] = (swv / sw) as f32;
                var[[y, x]] = (1.0 / sw) as f32;
            }
        }
        [resp, var]
    }

    /// The lane-wise combination gives the scalar one's response and variance bit for bit,
    /// and UNKNOWN exactly where it has too few values; for frame counts on both sides of
    /// the network's powers of two and row lengths that leave a partial block of lanes.
    #[test]
    fn lane_combine_is_the_scalar_combine() {
        for (n, nx, seed) in [
            (3, 37, 1),
            (5, 16, 2),
            (8, 50, 3),
            (9, 33, 4),
            (16, 40, 5),
            (17, 19, 6),
            (25, 70, 7),
        ] {
            let (frames, preps, lay) = scene(n, 7, nx, seed);
            let refs: Vec<&Frame> = frames.iter().collect();
            let opts = FlatOptions {
                clip_sigma: 1.5,
                min_values: 2,
                ..FlatOptions::default()
            };
            let (resp, var, bad) = combine(&refs, &preps, &lay, &opts);
            let [want_r, want_v] = combine_scalar(&refs, &preps, &lay, &opts);
            let mut unknown = 0;
            for ((y, x), &w) in want_r.indexed_iter() {
                if w.is_nan() {
                    assert_eq!(bad[[y, x]], UNKNOWN, "n {n} ({y}, {x})");
                    unknown += 1;
                } else {
                    assert_eq!(bad[[y, x]], 0, "n {n} ({y}, {x})");
                    assert_eq!(resp[[y, x]].to_bits(), w.to_bits(), "n {n} ({y}, {x})");
                    assert_eq!(var[[y, x]].to_bits(), want_v[[y, x]].to_bits(), "n {n} ({y}, {x})");
                }
            }
            // Both outcomes occur (the test sees the clip and the count rules).
            assert!(unknown > 0 && unknown < 6 * nx, "n {n}: {unknown} unknown");
        }
    }

    /// The lane-wise defect map is the one from `median_f32` per pixel (NaN and infinite
    /// values included: they sort like `total_cmp`).
    #[test]
    fn lane_defects_are_the_scalar_defects() {
        for (n, nx, seed) in [(3, 21, 11), (9, 40, 12), (20, 17, 13)] {
            let (mut frames, _, lay) = scene(n, 7, nx, seed);
            // Defects: a dead column and a hot pixel in every frame; elsewhere about half
            // the values low (so the flag depends on exactly which element is the median).
            let mut r = Lcg(seed + 100);
            for f in frames.iter_mut() {
                f.data.mapv_inplace(|v| if r.next() < 0.45 { 0.2 * v } else { v });
                f.data.column_mut(3).fill(0.0);
                f.data[[5, 7]] = 3000.0;
            }
            let refs: Vec<&Frame> = frames.iter().collect();
            let opts = FlatOptions::default();
            let got = fixed_defects(&refs, &lay, &opts);
            let step = n.div_ceil(9).max(1);
            let sub: Vec<&Frame> = refs.iter().step_by(step).copied().collect();
            let inv: Vec<[f32; 6]> = sub
                .iter()
                .map(|f| {
                    std::array::from_fn(|k| {
                        let [a, b] = lay.strips[k].1;
                        let m = strip_median(&f.data, &f.mask, a, b, |v| v < lay.sat).unwrap_or(0.0);
                        if m > 0.0 {
                            1.0 / m
                        } else {
                            0.0
                        }
                    })
                })
                .collect();
            let mut flagged = 0;
            for y in 0..7 {
                for x in 0..nx {
                    let want = match lay.strip_of[y] {
                        None => 0,
                        Some(k) => {
                            let mut v: Vec<f32> = sub.iter().zip(&inv).map(|(f, l)| f.data[[y, x]] * l[k]).collect();
                            let m = median_f32(&mut v).unwrap();
                            u8::from(!(m >= opts.min_response && m <= opts.max_response))
                        }
                    };
                    assert_eq!(got[[y, x]], want, "n {n} ({y}, {x})");
                    flagged += usize::from(want);
                }
            }
            assert!(flagged >= 6 + nx / 8 && flagged < 6 * nx - nx / 8, "n {n}: {flagged}");
        }
    }
}
