//! Circular aperture sums over an image, with optional variance map and bad-pixel mask.

use ndarray::{s, ArrayView2};
use serde::{Deserialize, Serialize};

use super::overlap::{for_each_run, overlap_circle_rect, Method};

/// A circular aperture: centre `(x, y)` in 0-based pixel coordinates (pixel centres at
/// integers), radius `r` in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aperture {
    /// Centre, x (column) coordinate, px.
    pub x: f64,
    /// Centre, y (row) coordinate, px.
    pub y: f64,
    /// Radius, px.
    pub r: f64,
}

impl Aperture {
    /// Geometric area `pi r^2`, px^2.
    pub fn area(&self) -> f64 {
        std::f64::consts::PI * self.r * self.r
    }
}

/// What to do with masked (or non-finite) pixels inside the aperture.
///
/// Replacing a masked pixel by the local background level is *not* offered separately: after
/// background subtraction it contributes exactly zero, i.e. it is the same as [`MaskFill::Exclude`]
/// (the net flux of the excluded pixel is lost in both cases).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum MaskFill {
    /// Masked pixels are left out of the sum and of the area; their weight is reported in
    /// [`ApertureSum::masked_area`].
    Exclude,
    /// A masked pixel takes the value bilinearly interpolated at its mirror image through the
    /// aperture centre, `(2x - ix, 2y - iy)`, when the four pixels around it are in the image,
    /// unmasked and finite (after SExtractor's `MASK_TYPE CORRECT`); otherwise it is excluded.
    /// Good for an isolated bad pixel on a star's profile. The variance is propagated through
    /// the interpolation weights but counted as independent of the pixels' own contributions
    /// (they enter twice), a slight underestimate.
    Mirror,
}

/// Bilinear interpolation at the mirror image of pixel `(ix, iy)` through `(cx, cy)`:
/// the four pixels around `(2 cx - ix, 2 cy - iy)` and their weights, if all are in the image,
/// `good`, and none is `(ix, iy)` itself.
pub(crate) fn mirror_stencil(
    dim: (usize, usize),
    good: impl Fn(usize, usize) -> bool,
    cx: f64,
    cy: f64,
    ix: usize,
    iy: usize,
) -> Option<[(usize, usize, f64); 4]> {
    let (ny, nx) = dim;
    let (mx, my) = (2.0 * cx - ix as f64, 2.0 * cy - iy as f64);
    let (fx, fy) = (mx.floor(), my.floor());
    if !(fx >= 0.0 && fy >= 0.0 && fx + 1.0 < nx as f64 + 1.0 && fy + 1.0 < ny as f64 + 1.0) {
        return None;
    }
    let (tx, ty) = (mx - fx, my - fy);
    let (x0, y0) = (fx as usize, fy as usize);
    let st = [
        (x0, y0, (1.0 - tx) * (1.0 - ty)),
        (x0 + 1, y0, tx * (1.0 - ty)),
        (x0, y0 + 1, (1.0 - tx) * ty),
        (x0 + 1, y0 + 1, tx * ty),
    ];
    for &(x, y, w) in &st {
        // Points with zero weight may lie just off the image (mirror on the last column/row).
        if w == 0.0 {
            continue;
        }
        if x >= nx || y >= ny || (x, y) == (ix, iy) || !good(x, y) {
            return None;
        }
    }
    Some(st)
}

/// Result of [`aperture_sum`]. Units: the image's (ADU), variances in ADU^2, areas in px^2.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ApertureSum {
    /// `sum w_i v_i` over the pixels used (valid pixels, plus mirror-filled ones), ADU.
    pub sum: f64,
    /// `sum w_i^2 var_i` over the same pixels when a variance map was given, ADU^2.
    /// (photutils uses `sum w_i var_i`; `w^2` is the exact propagation for independent pixels.)
    pub variance: Option<f64>,
    /// `sum w_i` over the pixels used: the area to multiply the background level by, px^2.
    pub area: f64,
    /// `sum w_i^2` over the pixels used (for a per-pixel noise known only as a constant).
    pub area_w2: f64,
    /// Aperture area falling on masked or non-finite pixels of the image, filled or not, px^2.
    pub masked_area: f64,
    /// The part of `masked_area` that was filled by [`MaskFill::Mirror`], px^2.
    pub filled_area: f64,
    /// Exact geometric area of the disc outside the image, px^2 (method independent).
    pub outside_area: f64,
    /// Number of valid pixels with non-zero weight.
    pub n_pixels: usize,
    /// Largest value among the valid pixels with non-zero weight (None if there are none), ADU.
    pub max_value: Option<f64>,
}

impl ApertureSum {
    /// True when part of the disc lies off the image (beyond rounding).
    pub fn truncated(&self) -> bool {
        self.outside_area > 1e-12
    }
}

/// Sum of `img` in the circular aperture `ap`.
///
/// * `img`: image in ADU, indexed `[y, x]`.
/// * `var`: optional per-pixel variance map (ADU^2), same shape. Pixels with a non-finite or
///   negative variance are treated as bad.
/// * `mask`: optional, same shape, nonzero = bad pixel. Non-finite image values are bad too.
/// * `method`: pixel weights (exact overlap, centre, sub-pixel).
/// * `fill`: what to do with bad pixels ([`MaskFill`]).
///
/// Pixels outside the image contribute nothing; their geometric area is reported in
/// `outside_area` (flag the source as truncated). Sums accumulate in f64.
///
/// ```
/// use ndarray::Array2;
/// use sofipol_pipeline::photometry::{aperture_sum, Aperture, MaskFill, Method};
/// let img = Array2::<f32>::ones((32, 32));
/// let ap = Aperture { x: 15.3, y: 16.8, r: 5.0 };
/// let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
/// assert!((s.sum - ap.area()).abs() < 1e-11);
/// assert_eq!(s.outside_area, 0.0);
/// ```
pub fn aperture_sum(
    img: ArrayView2<f32>,
    var: Option<ArrayView2<f32>>,
    mask: Option<ArrayView2<u8>>,
    ap: &Aperture,
    method: Method,
    fill: MaskFill,
) -> ApertureSum {
    let (ny, nx) = img.dim();
    if let Some(v) = &var {
        assert_eq!(v.dim(), img.dim(), "variance map and image shapes differ");
    }
    if let Some(m) = &mask {
        assert_eq!(m.dim(), img.dim(), "mask and image shapes differ");
    }
    let mut out = ApertureSum {
        sum: 0.0,
        variance: var.as_ref().map(|_| 0.0),
        area: 0.0,
        area_w2: 0.0,
        masked_area: 0.0,
        filled_area: 0.0,
        outside_area: 0.0,
        n_pixels: 0,
        max_value: None,
    };
    if ap.r.is_nan() || ap.r <= 0.0 || !ap.x.is_finite() || !ap.y.is_finite() || !ap.r.is_finite() {
        return out;
    }
    let inside = if nx == 0 || ny == 0 {
        0.0
    } else {
        overlap_circle_rect(ap.x, ap.y, ap.r, -0.5, -0.5, nx as f64 - 0.5, ny as f64 - 0.5)
    };
    out.outside_area = (ap.area() - inside).max(0.0);
    if out.outside_area <= 1e-12 * ap.area().max(1.0) {
        out.outside_area = 0.0;
    }
    if nx == 0 || ny == 0 {
        return out;
    }
    let mut acc = Acc {
        max_value: f64::NEG_INFINITY,
        ..Acc::default()
    };
    let ctx = Ctx {
        img,
        var,
        mask,
        fill,
        cx: ap.x,
        cy: ap.y,
    };
    let cols = (0, nx as i64 - 1);
    let rows = (0, ny as i64 - 1);
    for_each_run(ap.x, ap.y, ap.r, method, cols, rows, |iy, ix0, ix1, w| {
        let iy = iy as usize;
        if ix0 == ix1 {
            ctx.pixel(&mut acc, ix0 as usize, iy, w);
            return;
        }
        // An interior run (w = 1): straight loops over the row, bad pixels handled one by one.
        let (a, b) = (ix0 as usize, ix1 as usize);
        let row = ctx.img.row(iy);
        if ctx.mask.is_none() {
            let vals = row.slice(s![a..=b]);
            let vrow = ctx.var.as_ref().map(|v| v.row(iy));
            let vars = vrow.as_ref().map(|v| v.slice(s![a..=b]));
            if let Some(vals) = vals.as_slice() {
                let vars = vars.as_ref().map(|v| v.as_slice());
                if let Some(done) = run_sum(vals, vars) {
                    acc.add_run(done, b - a + 1);
                    return;
                }
            }
        }
        match (&ctx.var, &ctx.mask) {
            (None, None) => {
                for (ix, &v) in (a..=b).zip(row.slice(s![a..=b]).iter()) {
                    if v.is_finite() {
                        acc.add(v as f64, 1.0, 0.0);
                    } else {
                        ctx.pixel(&mut acc, ix, iy, 1.0);
                    }
                }
            }
            (Some(vm), None) => {
                let vrow = vm.row(iy);
                for ((ix, &v), &q) in (a..=b)
                    .zip(row.slice(s![a..=b]).iter())
                    .zip(vrow.slice(s![a..=b]).iter())
                {
                    if v.is_finite() && q.is_finite() && q >= 0.0 {
                        acc.add(v as f64, 1.0, q as f64);
                    } else {
                        ctx.pixel(&mut acc, ix, iy, 1.0);
                    }
                }
            }
            _ => {
                for ix in a..=b {
                    ctx.pixel(&mut acc, ix, iy, 1.0);
                }
            }
        }
    });
    out.sum = acc.sum;
    out.area = acc.area;
    out.area_w2 = acc.area_w2;
    out.masked_area = acc.masked_area;
    out.filled_area = acc.filled_area;
    out.n_pixels = acc.n_pixels;
    if let Some(v) = out.variance.as_mut() {
        *v = acc.var_sum;
    }
    if out.n_pixels > 0 {
        out.max_value = Some(acc.max_value);
    }
    out
}

/// Sum, variance sum and maximum of a contiguous run of weight-1 pixels, or None if the run
/// holds a bad value (or the variance row is not contiguous): then it is done pixel by pixel.
#[inline]
fn run_sum(vals: &[f32], vars: Option<Option<&[f32]>>) -> Option<(f64, f64, f64)> {
    let mut sum = 0.0f64;
    let mut max = f32::NEG_INFINITY;
    let mut ok = true;
    for &v in vals {
        sum += v as f64;
        max = max.max(v);
        ok &= v.is_finite();
    }
    let mut var_sum = 0.0f64;
    if let Some(vars) = vars {
        let vars = vars?;
        for &q in vars {
            var_sum += q as f64;
            ok &= q.is_finite() && q >= 0.0;
        }
    }
    ok.then_some((sum, var_sum, max as f64))
}

#[derive(Default)]
struct Acc {
    sum: f64,
    area: f64,
    area_w2: f64,
    var_sum: f64,
    masked_area: f64,
    filled_area: f64,
    n_pixels: usize,
    max_value: f64,
}

impl Acc {
    /// A run of `n` valid weight-1 pixels summarised by [`run_sum`].
    #[inline]
    fn add_run(&mut self, (sum, var_sum, max): (f64, f64, f64), n: usize) {
        self.sum += sum;
        self.var_sum += var_sum;
        self.area += n as f64;
        self.area_w2 += n as f64;
        self.n_pixels += n;
        if max > self.max_value {
            self.max_value = max;
        }
    }

    /// A valid pixel of value `v`, weight `w`, variance `q` (0 without a map).
    #[inline]
    fn add(&mut self, v: f64, w: f64, q: f64) {
        self.sum += w * v;
        self.area += w;
        self.area_w2 += w * w;
        self.var_sum += w * w * q;
        self.n_pixels += 1;
        if v > self.max_value {
            self.max_value = v;
        }
    }
}

struct Ctx<'a> {
    img: ArrayView2<'a, f32>,
    var: Option<ArrayView2<'a, f32>>,
    mask: Option<ArrayView2<'a, u8>>,
    fill: MaskFill,
    cx: f64,
    cy: f64,
}

impl Ctx<'_> {
    #[inline]
    fn valid(&self, ix: usize, iy: usize) -> bool {
        self.img[[iy, ix]].is_finite()
            && self.mask.as_ref().is_none_or(|m| m[[iy, ix]] == 0)
            && self.var.as_ref().is_none_or(|v| {
                let q = v[[iy, ix]];
                q.is_finite() && q >= 0.0
            })
    }

    /// One pixel of weight `w`: summed if valid, else counted as masked and maybe filled.
    #[inline]
    fn pixel(&self, acc: &mut Acc, ix: usize, iy: usize, w: f64) {
        if self.valid(ix, iy) {
            let q = self.var.as_ref().map_or(0.0, |v| v[[iy, ix]] as f64);
            acc.add(self.img[[iy, ix]] as f64, w, q);
            return;
        }
        acc.masked_area += w;
        if self.fill == MaskFill::Mirror {
            let good = |x: usize, y: usize| self.valid(x, y);
            if let Some(st) = mirror_stencil(self.img.dim(), good, self.cx, self.cy, ix, iy) {
                let (mut value, mut value_var) = (0.0, 0.0);
                for &(x, y, b) in st.iter().filter(|s| s.2 != 0.0) {
                    value += b * self.img[[y, x]] as f64;
                    if let Some(vm) = &self.var {
                        value_var += b * b * vm[[y, x]] as f64;
                    }
                }
                acc.sum += w * value;
                acc.area += w;
                acc.area_w2 += w * w;
                acc.var_sum += w * w * value_var;
                acc.filled_area += w;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;
    use std::f64::consts::PI;

    #[test]
    fn photometry_all_ones_sum_is_pi_r2_over_grid() {
        let img = Array2::<f32>::ones((80, 80));
        let mut worst = 0.0f64;
        for &r in &[
            0.05,
            0.3,
            0.5,
            std::f64::consts::FRAC_1_SQRT_2,
            1.0,
            1.7,
            2.5,
            5.0,
            10.3,
            17.0,
            30.0,
        ] {
            for i in 0..9 {
                for j in 0..9 {
                    let (x, y) = (39.0 + i as f64 / 8.0, 40.0 + j as f64 / 8.0 + 0.01 * i as f64);
                    let ap = Aperture { x, y, r };
                    let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
                    let rel = (s.sum - PI * r * r).abs() / (PI * r * r);
                    worst = worst.max(rel);
                    assert!(rel < 1e-10, "x {x} y {y} r {r}: {} vs {}", s.sum, PI * r * r);
                    assert_eq!(s.area, s.sum);
                    assert_eq!(s.outside_area, 0.0);
                    assert_eq!(s.masked_area, 0.0);
                }
            }
        }
        assert!(worst < 1e-10);
    }

    proptest::proptest! {
        /// The run-based fast path equals a naive loop over every pixel with `pixel_weight`,
        /// with variance map, mask, NaNs and truncation.
        #[test]
        fn photometry_prop_sum_matches_naive_loop(
            cx in -4.0f64..24.0, cy in -4.0f64..20.0, r in 0.01f64..12.0, seed in 0u64..1000,
            m in 0usize..3, use_var in proptest::bool::ANY, use_mask in proptest::bool::ANY,
        ) {
            let method = [Method::Exact, Method::Center, Method::Subpixel(4)][m];
            let (ny, nx) = (17, 21);
            let h = |i: usize, k: u64| (((i as u64 + 1) * 2_654_435_761) ^ ((seed + k) * 40_503)) % 1000;
            let img = Array2::from_shape_fn((ny, nx), |(y, x)| {
                let i = y * nx + x;
                if h(i, 3) == 7 { f32::NAN } else { h(i, 0) as f32 * 0.37 - 50.0 }
            });
            let var = Array2::from_shape_fn((ny, nx), |(y, x)| h(y * nx + x, 1) as f32 * 0.01);
            let mask = Array2::from_shape_fn((ny, nx), |(y, x)| u8::from(h(y * nx + x, 2) < 60));
            let ap = Aperture { x: cx, y: cy, r };
            let vv = use_var.then(|| var.view());
            let mm = use_mask.then(|| mask.view());
            let s = aperture_sum(img.view(), vv, mm, &ap, method, MaskFill::Exclude);
            let (mut sum, mut vs, mut area, mut masked, mut n) = (0.0, 0.0, 0.0, 0.0, 0);
            for y in 0..ny {
                for x in 0..nx {
                    let w = crate::photometry::pixel_weight(method, cx, cy, r, x as i64, y as i64);
                    if w == 0.0 {
                        continue;
                    }
                    let bad = !img[[y, x]].is_finite() || (use_mask && mask[[y, x]] != 0);
                    if bad {
                        masked += w;
                    } else {
                        sum += w * img[[y, x]] as f64;
                        vs += w * w * var[[y, x]] as f64;
                        area += w;
                        n += 1;
                    }
                }
            }
            let tol = 1e-12 * (1.0 + sum.abs() + area);
            proptest::prop_assert!((s.sum - sum).abs() <= tol, "{} vs {}", s.sum, sum);
            proptest::prop_assert!((s.area - area).abs() <= 1e-12 * (1.0 + area));
            proptest::prop_assert!((s.masked_area - masked).abs() <= 1e-12 * (1.0 + masked));
            proptest::prop_assert_eq!(s.n_pixels, n);
            if use_var {
                proptest::prop_assert!((s.variance.unwrap() - vs).abs() <= 1e-12 * (1.0 + vs));
            } else {
                proptest::prop_assert!(s.variance.is_none());
            }
        }
    }

    #[test]
    fn photometry_truncation_mask_and_mirror() {
        let mut img = Array2::<f32>::from_elem((20, 20), 2.0);
        let var = Array2::<f32>::from_elem((20, 20), 4.0);
        // Off the left edge: half the disc is outside.
        let ap = Aperture {
            x: -0.5,
            y: 10.0,
            r: 3.0,
        };
        let s = aperture_sum(
            img.view(),
            Some(var.view()),
            None,
            &ap,
            Method::Exact,
            MaskFill::Exclude,
        );
        assert!((s.outside_area - ap.area() / 2.0).abs() < 1e-12);
        assert!((s.area - ap.area() / 2.0).abs() < 1e-12);
        assert!(s.truncated());
        // Entirely off the image.
        let far = Aperture {
            x: -50.0,
            y: 10.0,
            r: 3.0,
        };
        let s = aperture_sum(img.view(), None, None, &far, Method::Exact, MaskFill::Exclude);
        assert_eq!((s.sum, s.area, s.n_pixels, s.max_value), (0.0, 0.0, 0, None));
        assert!((s.outside_area - far.area()).abs() < 1e-12);

        // A bad pixel at (11, 10) in a star-like symmetric image.
        for iy in 0..20 {
            for ix in 0..20 {
                let d2 = (ix as f64 - 10.0).powi(2) + (iy as f64 - 10.0).powi(2);
                img[[iy, ix]] = (100.0 * (-d2 / 8.0).exp()) as f32;
            }
        }
        let clean = aperture_sum(
            img.view(),
            Some(var.view()),
            None,
            &Aperture {
                x: 10.0,
                y: 10.0,
                r: 4.0,
            },
            Method::Exact,
            MaskFill::Exclude,
        );
        let mut mask = Array2::<u8>::zeros((20, 20));
        mask[[10, 11]] = 1;
        img[[10, 11]] = 1e6; // junk under the mask
        let ap = Aperture {
            x: 10.0,
            y: 10.0,
            r: 4.0,
        };
        let ex = aperture_sum(
            img.view(),
            Some(var.view()),
            Some(mask.view()),
            &ap,
            Method::Exact,
            MaskFill::Exclude,
        );
        assert_eq!(ex.masked_area, 1.0);
        assert_eq!(ex.filled_area, 0.0);
        assert_eq!(ex.n_pixels, clean.n_pixels - 1);
        assert!((ex.sum - (clean.sum - img[[10, 9]] as f64)).abs() < 1e-9);
        assert!((ex.area - (clean.area - 1.0)).abs() < 1e-12);
        let mi = aperture_sum(
            img.view(),
            Some(var.view()),
            Some(mask.view()),
            &ap,
            Method::Exact,
            MaskFill::Mirror,
        );
        assert!((mi.sum - clean.sum).abs() < 1e-9, "{} {}", mi.sum, clean.sum);
        assert_eq!(mi.filled_area, 1.0);
        assert!((mi.area - clean.area).abs() < 1e-12);
        assert!((mi.variance.unwrap() - clean.variance.unwrap()).abs() < 1e-9);
        // NaN pixels are bad pixels too.
        img[[10, 11]] = f32::NAN;
        let na = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
        assert_eq!(na.masked_area, 1.0);
        assert!(na.sum.is_finite());
    }

    /// The mirror stencil is the bilinear one at (2 cx - ix, 2 cy - iy): four pixels and
    /// weights summing to 1, on the image up to its last row and column (a point exactly on
    /// the last column needs no pixel beyond it); a mirror image off the image's low edges
    /// (where a cast to usize would clamp to 0) or past its high edges has none.
    #[test]
    fn mirror_stencil_at_the_edges() {
        let all = |_: usize, _: usize| true;
        let dim = (10, 12); // (ny, nx)
                            // Mirror of (2, 3) through (5.25, 4.5): (8.5, 6.0).
        let st = mirror_stencil(dim, all, 5.25, 4.5, 2, 3).unwrap();
        let w: f64 = st.iter().map(|s| s.2).sum();
        assert!((w - 1.0).abs() < 1e-15);
        assert_eq!(st.map(|s| (s.0, s.1)), [(8, 6), (9, 6), (8, 7), (9, 7)]);
        assert_eq!(st.map(|s| s.2), [0.5, 0.5, 0.0, 0.0]);
        // Next to the last column: x0 = nx - 2 = 10, tx = 0.5.
        let st = mirror_stencil(dim, all, 6.25, 4.0, 2, 3).unwrap();
        assert_eq!((st[0].0, st[1].0), (10, 11));
        // Exactly on the last column and row (weights 1, 0, 0, 0).
        let st = mirror_stencil(dim, all, 6.5, 5.0, 2, 1).unwrap();
        assert_eq!((st[0].0, st[0].1, st[0].2), (11, 9, 1.0));
        // Past the high edges, and off the low ones (mirror at x = -0.5, or y = -0.5).
        assert!(mirror_stencil(dim, all, 6.5, 4.0, 1, 3).is_none());
        assert!(mirror_stencil(dim, all, 4.0, 6.5, 2, 3).is_none());
        assert!(mirror_stencil(dim, all, 1.75, 4.0, 4, 3).is_none(), "x = -0.5");
        assert!(mirror_stencil(dim, all, 5.0, 1.75, 3, 4).is_none(), "y = -0.5");
        // On the last column (row) with weight on the next, which is off the image: none,
        // though the point itself is inside (mirror at x = 11.5; at y = 9.5).
        assert!(mirror_stencil(dim, all, 6.75, 4.0, 2, 3).is_none(), "x = 11.5");
        assert!(mirror_stencil(dim, all, 5.0, 6.25, 3, 3).is_none(), "y = 9.5");
        // A stencil that would use a bad pixel or the pixel itself has none.
        assert!(mirror_stencil(dim, |x, y| (x, y) != (9, 6), 5.25, 4.5, 2, 3).is_none());
        assert!(mirror_stencil(dim, all, 2.0, 3.0, 2, 3).is_none(), "its own mirror");
    }

    /// An aperture that is not one (radius zero, negative or not finite; a centre not
    /// finite) sums nothing and reports nothing outside; an image without pixels has the
    /// whole disc outside.
    #[test]
    fn apertures_that_are_not_one_sum_nothing() {
        let img = Array2::<f32>::ones((20, 20));
        let empty = |s: &ApertureSum| {
            s.sum == 0.0 && s.area == 0.0 && s.n_pixels == 0 && s.outside_area == 0.0 && s.max_value.is_none()
        };
        for (x, y, r) in [
            (10.0, 10.0, f64::NAN),
            (10.0, 10.0, 0.0),
            (10.0, 10.0, -2.0),
            (10.0, 10.0, f64::INFINITY),
            (f64::NAN, 10.0, 3.0),
            (10.0, f64::INFINITY, 3.0),
            (f64::NEG_INFINITY, f64::NAN, 3.0),
        ] {
            let ap = Aperture { x, y, r };
            let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
            assert!(empty(&s), "({x}, {y}, {r}): {s:?}");
        }
        for dim in [(0, 20), (20, 0)] {
            let img = Array2::<f32>::ones(dim);
            let ap = Aperture { x: 3.0, y: 3.0, r: 2.0 };
            let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
            assert_eq!((s.sum, s.n_pixels, s.outside_area), (0.0, 0, ap.area()), "{dim:?}");
            assert!(s.truncated());
        }
    }

    /// The part of the disc off the image, against the geometry: the image spans
    /// -0.5 .. n - 0.5 on each axis, so a disc centred on an edge has half its area
    /// outside and one centred on a corner three quarters; the sum of an image of ones is
    /// the rest. The largest value is that of the pixels, also when all are negative.
    #[test]
    fn the_area_off_the_image_is_the_geometric_one() {
        let (ny, nx) = (30, 40);
        let img = Array2::<f32>::from_elem((ny, nx), -2.0);
        let r = 4.3;
        let full = PI * r * r;
        let (xe, ye) = (nx as f64 - 0.5, ny as f64 - 0.5);
        for (x, y, out) in [
            (-0.5, 15.0, 0.5),
            (xe, 15.0, 0.5),
            (20.0, -0.5, 0.5),
            (20.0, ye, 0.5),
            (-0.5, -0.5, 0.75),
            (xe, ye, 0.75),
            (xe, -0.5, 0.75),
            (20.0, 15.0, 0.0),
        ] {
            let ap = Aperture { x, y, r };
            let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
            assert!((s.outside_area - out * full).abs() < 1e-9, "({x}, {y}): {s:?}");
            assert!((s.sum + 2.0 * (1.0 - out) * full).abs() < 1e-9, "({x}, {y}): {s:?}");
            assert_eq!(s.truncated(), out > 0.0);
            assert_eq!(s.max_value, Some(-2.0));
        }
    }

    /// A pixel whose variance is negative or not a number is a bad pixel: the sums are
    /// those of the same image with that pixel masked instead (one in an interior run of
    /// the aperture, one on its edge).
    #[test]
    fn a_pixel_with_an_unusable_variance_is_a_masked_pixel() {
        let (ny, nx) = (30, 30);
        let img = Array2::<f32>::from_shape_fn((ny, nx), |(y, x)| 1.0 + 0.01 * (x + 2 * y) as f32);
        let mut var = Array2::<f32>::from_elem((ny, nx), 2.0);
        let mut mask = Array2::<u8>::zeros((ny, nx));
        let ap = Aperture {
            x: 15.2,
            y: 14.7,
            r: 6.0,
        };
        for (bad, (y, x)) in [(-1.0f32, (15, 14)), (f32::NAN, (12, 16)), (-0.5, (14, 21))] {
            var[[y, x]] = bad;
            mask[[y, x]] = 1;
        }
        let good_var = Array2::<f32>::from_elem((ny, nx), 2.0);
        for method in [Method::Exact, Method::Center] {
            let by_var = aperture_sum(img.view(), Some(var.view()), None, &ap, method, MaskFill::Exclude);
            let by_mask = aperture_sum(
                img.view(),
                Some(good_var.view()),
                Some(mask.view()),
                &ap,
                method,
                MaskFill::Exclude,
            );
            assert!(by_var.masked_area > 1.9, "{by_var:?}");
            for (a, b) in [
                (by_var.sum, by_mask.sum),
                (by_var.variance.unwrap(), by_mask.variance.unwrap()),
                (by_var.area, by_mask.area),
                (by_var.masked_area, by_mask.masked_area),
            ] {
                assert!(
                    (a - b).abs() < 1e-9 * b.abs().max(1.0),
                    "{method:?}: {by_var:?} vs {by_mask:?}"
                );
            }
            assert_eq!(by_var.n_pixels, by_mask.n_pixels);
        }
    }

    /// Mirror filling against a plane, where bilinear interpolation is exact: a masked
    /// interior pixel is filled with the plane's value at its mirror point through the
    /// centre, and its variance is the interpolation's, q sum b^2; edge pixels enter the
    /// variance with their weight squared.
    #[test]
    fn a_mirror_filled_pixel_has_the_planes_value_and_the_interpolations_variance() {
        let (ny, nx) = (30, 30);
        let plane = |x: f64, y: f64| 50.0 + 0.7 * x - 0.3 * y;
        let img = Array2::<f32>::from_shape_fn((ny, nx), |(y, x)| plane(x as f64, y as f64) as f32);
        let q = 3.0f32;
        let var = Array2::<f32>::from_elem((ny, nx), q);
        let mut mask = Array2::<u8>::zeros((ny, nx));
        mask[[16, 17]] = 1;
        let ap = Aperture {
            x: 15.3,
            y: 14.6,
            r: 5.5,
        };
        let full = aperture_sum(
            img.view(),
            Some(var.view()),
            None,
            &ap,
            Method::Exact,
            MaskFill::Exclude,
        );
        // Fractional edge weights: sum w^2 below sum w, and the variance q sum w^2.
        assert!(full.area_w2 < full.area - 1.0, "{full:?}");
        assert!(
            (full.variance.unwrap() - q as f64 * full.area_w2).abs() < 1e-9,
            "{full:?}"
        );
        let filled = aperture_sum(
            img.view(),
            Some(var.view()),
            Some(mask.view()),
            &ap,
            Method::Exact,
            MaskFill::Mirror,
        );
        // Mirror of (17, 16) through (15.3, 14.6): (13.6, 13.2); weights (0.4, 0.6) x (0.8, 0.2).
        let want_sum = full.sum - img[[16, 17]] as f64 + plane(13.6, 13.2);
        assert!((filled.sum - want_sum).abs() < 1e-3, "{} vs {want_sum}", filled.sum);
        let sum_b2 = (0.4f64.powi(2) + 0.6f64.powi(2)) * (0.8f64.powi(2) + 0.2f64.powi(2));
        let want_var = q as f64 * (full.area_w2 - 1.0 + sum_b2);
        assert!(
            (filled.variance.unwrap() - want_var).abs() < 1e-6,
            "{filled:?} vs {want_var}"
        );
        assert_eq!((filled.masked_area, filled.filled_area), (1.0, 1.0));
        assert!((filled.area - full.area).abs() < 1e-12 && (filled.area_w2 - full.area_w2).abs() < 1e-12);
        // An edge pixel of weight w < 1 filled from its mirror (15.6, 9.2): its value, area
        // and variance enter with w, w, w^2 as an unmasked one would.
        let mut mask = Array2::<u8>::zeros((ny, nx));
        mask[[20, 15]] = 1;
        let dropped = aperture_sum(
            img.view(),
            Some(var.view()),
            Some(mask.view()),
            &ap,
            Method::Exact,
            MaskFill::Exclude,
        );
        let w = full.area - dropped.area;
        assert!(w > 0.05 && w < 0.95, "{w}");
        let filled = aperture_sum(
            img.view(),
            Some(var.view()),
            Some(mask.view()),
            &ap,
            Method::Exact,
            MaskFill::Mirror,
        );
        let want_sum = full.sum - w * img[[20, 15]] as f64 + w * plane(15.6, 9.2);
        assert!((filled.sum - want_sum).abs() < 1e-3, "{} vs {want_sum}", filled.sum);
        assert!((filled.area_w2 - full.area_w2).abs() < 1e-12, "{filled:?}");
        let want_var = q as f64 * (full.area_w2 - w * w + w * w * sum_b2);
        assert!(
            (filled.variance.unwrap() - want_var).abs() < 1e-6,
            "{filled:?} vs {want_var}"
        );
    }

    /// The largest value is found on the aperture's edge pixels too (summed one by one,
    /// not in interior runs).
    #[test]
    fn the_largest_value_may_be_on_the_edge() {
        let mut img = Array2::<f32>::ones((30, 30));
        img[[20, 15]] = 9.0;
        let ap = Aperture {
            x: 15.3,
            y: 14.6,
            r: 5.5,
        };
        let s = aperture_sum(img.view(), None, None, &ap, Method::Exact, MaskFill::Exclude);
        assert_eq!(s.max_value, Some(9.0));
    }
}
