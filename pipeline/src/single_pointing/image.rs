//! Pixel operations of the single-pointing reduction: whole images in `f64`, row-major,
//! pixel `(x, y)` centred on integer coordinates (0-based), as the rest of sofipol and
//! photutils count them.
use crate::photometry::overlap_circle_pixel;

/// An image, `v[y * nx + x]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Img {
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// Values.
    pub v: Vec<f64>,
}

impl Img {
    /// An image of `value`.
    pub fn filled(nx: usize, ny: usize, value: f64) -> Img {
        Img {
            nx,
            ny,
            v: vec![value; nx * ny],
        }
    }
    /// The value at `(x, y)`.
    pub fn at(&self, x: usize, y: usize) -> f64 {
        self.v[y * self.nx + x]
    }
}

/// The median of a slice (NaN when empty; the mean of the two middle values when even).
pub fn median(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    let (_, m, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *m;
    if n % 2 == 1 {
        hi
    } else {
        let lo = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lo + hi)
    }
}

/// Per-pixel median of images of one shape.
pub fn median_stack(imgs: &[&Img]) -> Img {
    let (nx, ny) = (imgs[0].nx, imgs[0].ny);
    let mut out = Img::filled(nx, ny, 0.0);
    let mut buf = vec![0.0; imgs.len()];
    for (i, o) in out.v.iter_mut().enumerate() {
        for (b, im) in buf.iter_mut().zip(imgs) {
            *b = im.v[i];
        }
        *o = median(&mut buf);
    }
    out
}

/// Median over the `(2h+1) x (2h+1)` box around each pixel, the box clipped at the edges.
pub fn median_filter(img: &Img, h: usize) -> Img {
    let mut out = Img::filled(img.nx, img.ny, 0.0);
    let mut buf = Vec::with_capacity((2 * h + 1).pow(2));
    for y in 0..img.ny {
        for x in 0..img.nx {
            buf.clear();
            for yy in y.saturating_sub(h)..(y + h + 1).min(img.ny) {
                buf.extend_from_slice(&img.v[yy * img.nx + x.saturating_sub(h)..yy * img.nx + (x + h + 1).min(img.nx)]);
            }
            out.v[y * img.nx + x] = median(&mut buf);
        }
    }
    out
}

/// Mean over the `w x w` box (w odd) around each pixel of rows `[r0, r1)`, with `bad`
/// pixels counted as 0; NaN within `w` of the region's edges.
pub fn boxcar_in_rows(img: &Img, bad: &[bool], rows: [usize; 2], w: usize) -> Img {
    let nx = img.nx;
    let h = w / 2;
    // Integral image of the rows.
    let nr = rows[1] - rows[0];
    let mut s = vec![0.0; (nr + 1) * (nx + 1)];
    for y in 0..nr {
        let mut acc = 0.0;
        for x in 0..nx {
            let i = (rows[0] + y) * nx + x;
            acc += if bad[i] || !img.v[i].is_finite() { 0.0 } else { img.v[i] };
            s[(y + 1) * (nx + 1) + x + 1] = s[y * (nx + 1) + x + 1] + acc;
        }
    }
    let mut out = Img::filled(nx, img.ny, f64::NAN);
    for y in w..nr.saturating_sub(w) {
        for x in w..nx.saturating_sub(w) {
            let (y0, y1, x0, x1) = (y - h, y + h + 1, x - h, x + h + 1);
            let sum = s[y1 * (nx + 1) + x1] - s[y0 * (nx + 1) + x1] - s[y1 * (nx + 1) + x0] + s[y0 * (nx + 1) + x0];
            out.v[(rows[0] + y) * nx + x] = sum / (w * w) as f64;
        }
    }
    out
}

/// Catmull-Rom (Keys, a = -0.5) cubic-convolution weights of the 4 taps around a fraction.
fn keys_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

/// Bicubic (cubic convolution) value at `(x, y)`; NaN within 2 px of the edge.
pub fn interp(img: &Img, x: f64, y: f64) -> f64 {
    let (fx, fy) = (x.floor(), y.floor());
    if fx < 1.0 || fy < 1.0 || fx + 2.0 >= img.nx as f64 || fy + 2.0 >= img.ny as f64 {
        return f64::NAN;
    }
    let (ix, iy) = (fx as usize, fy as usize);
    let (wx, wy) = (keys_weights(x - fx), keys_weights(y - fy));
    let mut acc = 0.0;
    for (j, wyj) in wy.iter().enumerate() {
        let row = (iy + j - 1) * img.nx + ix - 1;
        let r = &img.v[row..row + 4];
        acc += wyj * (wx[0] * r[0] + wx[1] * r[1] + wx[2] * r[2] + wx[3] * r[3]);
    }
    acc
}

/// Bicubic value at `(x, y)` when none of its 16 taps is masked (`mask[i]`: bad or not
/// finite) and it lies 2 px inside the edge.
pub(crate) fn interp_unmasked(img: &Img, mask: &[bool], x: f64, y: f64) -> Option<f64> {
    let (fx, fy) = (x.floor(), y.floor());
    if fx < 1.0 || fy < 1.0 || fx + 2.0 >= img.nx as f64 || fy + 2.0 >= img.ny as f64 {
        return None;
    }
    let (ix, iy) = (fx as usize, fy as usize);
    for j in 0..4 {
        let row = (iy + j - 1) * img.nx + ix - 1;
        if mask[row..row + 4].iter().any(|&m| m) {
            return None;
        }
    }
    Some(interp(img, x, y))
}

/// `img` with each masked pixel that has a good neighbour on both sides along x or along y
/// set to the mean of those pairs' means, and the mask of the pixels left bad.
fn fill_bad(img: &Img, mask: &[bool]) -> (Img, Vec<bool>) {
    let (nx, ny) = (img.nx, img.ny);
    let mut out = img.clone();
    let mut left = mask.to_vec();
    for y in 0..ny {
        for x in 0..nx {
            let i = y * nx + x;
            if !mask[i] {
                continue;
            }
            let (mut s, mut n) = (0.0, 0);
            if x > 0 && x + 1 < nx && !mask[i - 1] && !mask[i + 1] {
                s += 0.5 * (img.v[i - 1] + img.v[i + 1]);
                n += 1;
            }
            if y > 0 && y + 1 < ny && !mask[i - nx] && !mask[i + nx] {
                s += 0.5 * (img.v[i - nx] + img.v[i + nx]);
                n += 1;
            }
            if n > 0 {
                out.v[i] = s / n as f64;
                left[i] = false;
            }
        }
    }
    (out, left)
}

/// The centre `(x, y)` of 180-degree symmetry of `img` between radii `r_in` and `r_out`
/// about a first guess: the point minimizing the mean of `(I(c + d) - I(c - d))^2` over the
/// integer offsets `d` of the annulus, first on a 1-px grid within `search` px of the guess
/// (a saturated ring fools a local start), then by a pattern search down to 0.001 px.
/// A saturated core has no usable peak or centroid; its symmetry remains.
///
/// Bad pixels (`bad`) and pixels that are not finite (NaN) are first filled where they can
/// be interpolated, for the centring only: the mean of the means of the two good neighbours
/// along x and along y (either pair when only one is good; a pixel without a good pair, e.g.
/// beyond the beam's rows, stays bad). A bad pixel that stays bad is left out by pairs: a
/// pair `(c + d, c - d)` either of whose bicubic values would read it is not used. The pairs
/// left out then depend on `c`, so the search runs twice: with the pairs left out at each
/// trial centre (the mean over the pairs used), then again from that centre with the pairs
/// fixed: every pair that reads a bad pixel anywhere within 1.5 px of it is left out
/// throughout, and the cost is smooth. Filling rather than leaving out every pair near a
/// bad pixel keeps the weighting of the star's (not quite symmetric) light: on a real NIRC2
/// frame of AB Aur (a disk about the star) leaving out the pairs near 12 NaN pixels moved
/// the centre by up to 0.19 px, filling them by 0.01 px. Without a bad pixel near the star
/// this is the single search on every pair. `None` when fewer than a quarter of the pairs
/// are left.
pub fn symmetry_centre(
    img: &Img,
    bad: &[bool],
    guess: (f64, f64),
    r_in: f64,
    r_out: f64,
    search: f64,
) -> Option<(f64, f64)> {
    let h = r_out.ceil() as i64 + 1;
    let mut d = Vec::new();
    for dy in -h..=h {
        for dx in -h..=h {
            let r = ((dx * dx + dy * dy) as f64).sqrt();
            // Half of the annulus: the other half is its mirror.
            if r > r_in && r < r_out && (dy > 0 || (dy == 0 && dx > 0)) {
                d.push((dx as f64, dy as f64));
            }
        }
    }
    let mut mask: Vec<bool> = img.v.iter().zip(bad).map(|(v, &b)| b || !v.is_finite()).collect();
    let filled;
    let img = if mask.iter().any(|&m| m) {
        let (f, m) = fill_bad(img, &mask);
        filled = f;
        mask = m;
        &filled
    } else {
        img
    };
    let min_pairs = (d.len() / 4).max(1);
    // `fixed`: the pairs left out throughout (pass 2); `None`: left out where they read a
    // bad pixel (pass 1).
    let cost = |cx: f64, cy: f64, fixed: Option<&[bool]>| -> f64 {
        let (mut s, mut n) = (0.0, 0usize);
        for (k, &(dx, dy)) in d.iter().enumerate() {
            if fixed.is_some_and(|f| f[k]) {
                continue;
            }
            match (
                interp_unmasked(img, &mask, cx + dx, cy + dy),
                interp_unmasked(img, &mask, cx - dx, cy - dy),
            ) {
                (Some(a), Some(b)) => {
                    s += (a - b) * (a - b);
                    n += 1;
                }
                _ if fixed.is_some() => return f64::INFINITY,
                _ => {}
            }
        }
        let m = s / n as f64;
        if n >= min_pairs && m.is_finite() {
            m
        } else {
            f64::INFINITY
        }
    };
    let pattern = |mut best: (f64, f64, f64), fixed: Option<&[bool]>| -> (f64, f64, f64) {
        let mut step = 0.5;
        while step >= 0.001 {
            for _ in 0..50 {
                let mut moved = false;
                let (bx, by) = (best.1, best.2);
                for (sx, sy) in [
                    (-1.0, 0.0),
                    (1.0, 0.0),
                    (0.0, -1.0),
                    (0.0, 1.0),
                    (-1.0, -1.0),
                    (1.0, 1.0),
                    (-1.0, 1.0),
                    (1.0, -1.0),
                ] {
                    let (x, y) = (bx + sx * step, by + sy * step);
                    let c = cost(x, y, fixed);
                    if c < best.0 {
                        best = (c, x, y);
                        moved = true;
                    }
                }
                if !moved {
                    break;
                }
            }
            step *= 0.5;
        }
        best
    };
    let n = search.floor() as i64;
    let mut best = (f64::INFINITY, guess.0, guess.1);
    for gy in -n..=n {
        for gx in -n..=n {
            let (x, y) = (guess.0.round() + gx as f64, guess.1.round() + gy as f64);
            let c = cost(x, y, None);
            if c < best.0 {
                best = (c, x, y);
            }
        }
    }
    if !best.0.is_finite() {
        return None;
    }
    let first = pattern(best, None);
    // Pass 2: the pairs that read a bad pixel within 1.5 px of the first centre.
    let (cx, cy) = (first.1, first.2);
    let mut fixed = vec![false; d.len()];
    let mut any = false;
    for (k, &(dx, dy)) in d.iter().enumerate() {
        'probe: for oy in [-1.5, 0.0, 1.5] {
            for ox in [-1.5, 0.0, 1.5] {
                let (x, y) = (cx + ox, cy + oy);
                // The union of the taps over the 3 x 3 probes covers every centre within 1.5 px.
                if interp_unmasked(img, &mask, x + dx, y + dy).is_none()
                    || interp_unmasked(img, &mask, x - dx, y - dy).is_none()
                {
                    fixed[k] = true;
                    any = true;
                    break 'probe;
                }
            }
        }
    }
    if !any {
        return Some((cx, cy));
    }
    if d.len() - fixed.iter().filter(|&&f| f).count() < min_pairs {
        return None;
    }
    let start = (cost(cx, cy, Some(&fixed)), cx, cy);
    if !start.0.is_finite() {
        return None;
    }
    let second = pattern(start, Some(&fixed));
    Some((second.1, second.2))
}

/// Sum of `img` and of `var` over the annulus `r_in..r_out` about `(cx, cy)` with exact
/// pixel weights (`w` = the pixel's area inside the outer circle less that inside the inner
/// one), `bad` pixels left out (as photutils' `mask`): `(sum w I, sqrt(sum w var))`, the
/// error weighted as photutils' `aperture_photometry` weights it.
pub fn annulus_sum(img: &Img, var: &Img, bad: &[bool], (cx, cy): (f64, f64), r_in: f64, r_out: f64) -> (f64, f64) {
    let h = r_out.ceil() as i64 + 1;
    let (mut s, mut v) = (0.0, 0.0);
    for iy in (cy.round() as i64 - h)..=(cy.round() as i64 + h) {
        for ix in (cx.round() as i64 - h)..=(cx.round() as i64 + h) {
            if ix < 0 || iy < 0 || ix >= img.nx as i64 || iy >= img.ny as i64 {
                continue;
            }
            let i = iy as usize * img.nx + ix as usize;
            if bad[i] {
                continue;
            }
            let w = overlap_circle_pixel(cx, cy, r_out, ix, iy)
                - if r_in > 0.0 {
                    overlap_circle_pixel(cx, cy, r_in, ix, iy)
                } else {
                    0.0
                };
            if w > 0.0 {
                s += w * img.v[i];
                v += w * var.v[i];
            }
        }
    }
    (s, v.sqrt())
}

/// Whether an annulus (or circle) about `(cx, cy)` of outer radius `r` lies inside the
/// image.
pub fn inside(img: &Img, (cx, cy): (f64, f64), r: f64) -> bool {
    cx - r >= 0.0 && cy - r >= 0.0 && cx + r <= (img.nx - 1) as f64 && cy + r <= (img.ny - 1) as f64
}

/// The sky frame's scale and offset `S ~ a K + b` by least squares on the pixels of rows
/// `[r0, r1)` farther than `r_min` from `centre` and not `bad`, iterated with 4-sigma
/// clipping (sigma = 1.4826 x the median absolute residual) until the set of pixels used
/// stops changing (at most 6 passes): `(a, b, sigma, pixels used)`.
pub fn fit_sky(
    s: &Img,
    k: &Img,
    bad: &[bool],
    rows: [usize; 2],
    centre: (f64, f64),
    r_min: f64,
) -> Option<(f64, f64, f64, usize)> {
    let nx = s.nx;
    let mut idx = Vec::new();
    for y in rows[0]..rows[1] {
        for x in 0..nx {
            let i = y * nx + x;
            let (dx, dy) = (x as f64 - centre.0, y as f64 - centre.1);
            if !bad[i] && dx.hypot(dy) > r_min && s.v[i].is_finite() && k.v[i].is_finite() {
                idx.push(i);
            }
        }
    }
    let mut good = vec![true; idx.len()];
    let (mut a, mut b, mut sig) = (1.0, 0.0, f64::NAN);
    for _ in 0..6 {
        let (mut n, mut sk, mut ss, mut skk, mut sks) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (&i, &g) in idx.iter().zip(&good) {
            if g {
                let (kv, sv) = (k.v[i], s.v[i]);
                n += 1.0;
                sk += kv;
                ss += sv;
                skk += kv * kv;
                sks += kv * sv;
            }
        }
        let det = n * skk - sk * sk;
        if n < 3.0 || det.abs() <= 0.0 {
            return None;
        }
        a = (n * sks - sk * ss) / det;
        b = (ss - a * sk) / n;
        let mut res: Vec<f64> = idx
            .iter()
            .zip(&good)
            .filter(|(_, &g)| g)
            .map(|(&i, _)| (s.v[i] - a * k.v[i] - b).abs())
            .collect();
        sig = 1.4826 * median(&mut res);
        if !(sig > 0.0) {
            // An exact fit (noise-free frames): nothing to clip.
            break;
        }
        let new: Vec<bool> = idx
            .iter()
            .map(|&i| (s.v[i] - a * k.v[i] - b).abs() < 4.0 * sig)
            .collect();
        if new == good {
            break;
        }
        good = new;
    }
    Some((a, b, sig, good.iter().filter(|&&g| g).count()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth star-like image (Gaussian core + ring) centred at a known sub-pixel point,
    /// with its core hollowed out (a saturated core reading low): the symmetry centre finds
    /// the centre from 5 px away, to 0.01 px.
    #[test]
    fn symmetry_centre_finds_a_hollow_core() {
        let (nx, ny) = (120, 110);
        let (x0, y0) = (61.37, 52.81);
        let mut img = Img::filled(nx, ny, 0.0);
        for y in 0..ny {
            for x in 0..nx {
                let r = (x as f64 - x0).hypot(y as f64 - y0);
                let v = 1e4 * (-0.5 * (r / 6.0).powi(2)).exp() + 800.0 * (-0.5 * ((r - 14.0) / 2.5).powi(2)).exp();
                img.v[y * nx + x] = if r < 5.0 { 50.0 } else { v };
            }
        }
        let bad = vec![false; nx * ny];
        let (cx, cy) = symmetry_centre(&img, &bad, (x0 + 4.0, y0 - 3.0), 9.0, 30.0, 8.0).unwrap();
        assert!((cx - x0).abs() < 0.01 && (cy - y0).abs() < 0.01, "{cx} {cy}");
    }

    /// NaN and bad pixels near the core (inside the centring annulus, within a few px of
    /// the star) are left out: the same centre to 0.01 px. A bad pixel with a huge value
    /// would pull a centre that used it.
    #[test]
    fn symmetry_centre_leaves_out_nan_and_bad_pixels() {
        let (nx, ny) = (120, 110);
        let (x0, y0) = (61.37, 52.81);
        let mut img = Img::filled(nx, ny, 0.0);
        for y in 0..ny {
            for x in 0..nx {
                let r = (x as f64 - x0).hypot(y as f64 - y0);
                img.v[y * nx + x] =
                    1e4 * (-0.5 * (r / 6.0).powi(2)).exp() + 800.0 * (-0.5 * ((r - 14.0) / 2.5).powi(2)).exp();
            }
        }
        let mut bad = vec![false; nx * ny];
        let clean = symmetry_centre(&img, &bad, (x0 + 2.0, y0 - 1.0), 3.0, 30.0, 4.0).unwrap();
        assert!((clean.0 - x0).abs() < 0.01 && (clean.1 - y0).abs() < 0.01, "{clean:?}");
        for (x, y) in [(65, 52), (66, 52), (58, 57), (61, 47)] {
            img.v[y * nx + x] = f64::NAN;
        }
        for (x, y) in [(55, 50), (70, 60)] {
            img.v[y * nx + x] = 1e9;
            bad[y * nx + x] = true;
        }
        let (cx, cy) = symmetry_centre(&img, &bad, (x0 + 2.0, y0 - 1.0), 3.0, 30.0, 4.0).expect("a centre");
        assert!(
            (cx - clean.0).abs() < 0.01 && (cy - clean.1).abs() < 0.01,
            "{cx} {cy} vs {clean:?}"
        );
    }

    /// The annulus weights sum to the exact area pi (r_out^2 - r_in^2); a constant image sums
    /// to that area; a bad pixel removes exactly its weight.
    #[test]
    fn annulus_sum_is_exact_area() {
        let img = Img::filled(100, 100, 2.0);
        let var = Img::filled(100, 100, 9.0);
        let mut bad = vec![false; 100 * 100];
        let (s, e) = annulus_sum(&img, &var, &bad, (50.3, 49.6), 18.0, 40.0);
        let area = std::f64::consts::PI * (40.0f64.powi(2) - 18.0f64.powi(2));
        assert!((s / 2.0 - area).abs() < 1e-9 * area, "{s}");
        assert!((e * e / 9.0 - area).abs() < 1e-9 * area);
        // A pixel wholly inside the annulus (30 px right of the centre).
        bad[50 * 100 + 80] = true;
        let (s2, _) = annulus_sum(&img, &var, &bad, (50.3, 49.6), 18.0, 40.0);
        assert!((s - s2 - 2.0).abs() < 1e-9);
    }

    /// The sky fit recovers a scale and offset exactly, with an outlier clipped.
    #[test]
    fn sky_fit_recovers_scale_and_offset() {
        let (nx, ny) = (60, 40);
        let mut k = Img::filled(nx, ny, 0.0);
        for (i, v) in k.v.iter_mut().enumerate() {
            *v = 1000.0 + (i % 37) as f64 * 13.0 + (i % 11) as f64;
        }
        let mut s = k.clone();
        for (sv, kv) in s.v.iter_mut().zip(&k.v) {
            *sv = 1.02 * kv - 35.0 + if (*kv as i64) % 2 == 0 { 0.5 } else { -0.5 };
        }
        s.v[5] = 1e6;
        let bad = vec![false; nx * ny];
        let (a, b, _, n) = fit_sky(&s, &k, &bad, [0, ny], (0.0, 0.0), -1.0).unwrap();
        assert!((a - 1.02).abs() < 1e-3 && (b + 35.0).abs() < 1.5, "{a} {b}");
        assert_eq!(n, nx * ny - 1);
    }
}
