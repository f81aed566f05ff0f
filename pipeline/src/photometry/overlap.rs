//! Pixel weights of a circle on the pixel grid: exact overlap area, pixel centre, sub-pixel.
//!
//! Geometry (all lengths in pixels): pixel `(ix, iy)` is the unit square
//! `[ix-0.5, ix+0.5] x [iy-0.5, iy+0.5]`; the circle is centred on `(cx, cy)`.
//!
//! ## The exact method
//!
//! Work relative to the circle centre and cut the plane into horizontal strips, one per pixel
//! row, `v in [y0, y1]`. For `t >= 0` define the *strip tail*
//!
//! ```text
//! R(t) = area of { (u, v) in disc : v in [y0, y1], u >= t } = ∫_{y0}^{y1} max(0, s(v) - t) dv,
//! s(v) = sqrt(r^2 - v^2)   (half chord).
//! ```
//!
//! `s(v) > t` on `|v| < sqrt(r^2 - t^2)`, so the integrand has a single closed form on one
//! interval `[a, b]`, and `∫_a^b s = 1/2 [b s(b) - a s(a) + r^2 Δθ]` where `Δθ` is the angle
//! between the radius vectors `(s(a), a)` and `(s(b), b)`, computed with one `atan2` of their
//! cross and dot products (no difference of two large `asin`s, so the absolute error stays at a
//! few ulp of `r`, not of `r^2`). By the mirror symmetry of the disc the area of the pixel
//! `[x0, x1]` in the strip is then `R(x0) - R(x1)` (right of the centre), `R(-x1) - R(-x0)`
//! (left of it) or `2 R(0) - R(x1) - R(-x0)` (straddling it).
//!
//! Along a row the pixels fully inside the disc (all four corners inside) take weight 1 and
//! those whose x-range misses the strip's chord take weight 0 without any trigonometry; only
//! the boundary pixels evaluate `R`, once per pixel edge (edges are shared by neighbours).

use serde::{Deserialize, Serialize};

/// How the weight of a pixel in a circular aperture is computed (as photutils' `method`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "MethodToml", into = "String")]
pub enum Method {
    /// Exact fraction of the pixel area covered by the disc.
    Exact,
    /// 1 if the pixel centre is strictly inside the circle (`d < r`), else 0.
    Center,
    /// Fraction of the `n x n` sub-pixel centres strictly inside the circle.
    /// `Subpixel(0)` and `Subpixel(1)` are the same as [`Method::Center`].
    Subpixel(u32),
}

/// The spellings of [`Method`], the same in TOML and on the command line.
pub const METHOD_SPELLINGS: &str = "exact, center or subpixel:N with N >= 1";

/// `exact`, `center`, `subpixel:N`: the one spelling of TOML and the command line.
impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Method::Exact => f.write_str("exact"),
            Method::Center => f.write_str("center"),
            Method::Subpixel(n) => write!(f, "subpixel:{n}"),
        }
    }
}

/// Parses what [`Method`]'s `Display` writes (case-insensitive, so the old TOML `"Exact"` is read).
impl std::str::FromStr for Method {
    type Err = crate::error::SettingError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || crate::error::SettingError {
            key: "measure.method",
            value: format!("{s:?}"),
            allowed: METHOD_SPELLINGS,
        };
        let t = s.trim().to_ascii_lowercase();
        match t.as_str() {
            "exact" => Ok(Method::Exact),
            "center" => Ok(Method::Center),
            _ => match t.strip_prefix("subpixel:").map(|n| n.trim().parse::<u32>()) {
                Some(Ok(n)) if n >= 1 => Ok(Method::Subpixel(n)),
                _ => Err(bad()),
            },
        }
    }
}

/// What TOML may hold for a [`Method`]: the one spelling, or the old `{ Subpixel = N }` table.
#[derive(Deserialize)]
#[serde(untagged)]
enum MethodToml {
    Text(String),
    Table {
        #[serde(rename = "Subpixel")]
        subpixel: u32,
    },
}

impl TryFrom<MethodToml> for Method {
    type Error = crate::error::SettingError;
    fn try_from(m: MethodToml) -> Result<Self, Self::Error> {
        match m {
            MethodToml::Text(s) => s.parse(),
            MethodToml::Table { subpixel } => format!("subpixel:{subpixel}").parse(),
        }
    }
}

impl From<Method> for String {
    fn from(m: Method) -> String {
        m.to_string()
    }
}

/// Half chord `sqrt(r^2 - y^2)`, 0 outside `|y| < r`; `(r-y)(r+y)` keeps accuracy near `|y| = r`.
#[inline]
fn half_chord(r: f64, y: f64) -> f64 {
    let p = (r - y) * (r + y);
    if p > 0.0 {
        p.sqrt()
    } else {
        0.0
    }
}

/// `∫_a^b sqrt(r^2 - v^2) dv` for `-r <= a <= b <= r`, given `sa = s(a)`, `sb = s(b)`.
#[inline]
fn chord_integral(r: f64, a: f64, sa: f64, b: f64, sb: f64) -> f64 {
    // Angle from (sa, a) to (sb, b), in [0, pi]; the cross product is >= 0 mathematically.
    let cross = b * sa - a * sb;
    let cross = if cross > 0.0 { cross } else { 0.0 };
    let dot = sa * sb + a * b;
    // atan is cheaper than atan2 and as accurate for angles below pi/2.
    let angle = if dot > 0.0 {
        (cross / dot).atan()
    } else {
        cross.atan2(dot)
    };
    0.5 * (b * sb - a * sa + r * r * angle)
}

/// One pixel row (strip `v in [y0, y1]`, relative to the centre) of a disc of radius `r`.
#[derive(Debug, Clone, Copy)]
struct Strip {
    r: f64,
    y0: f64,
    s0: f64,
    y1: f64,
    s1: f64,
    /// Pixels with `[x0, x1]` inside `[-s_in, s_in]` are fully inside the disc.
    s_in: f64,
    /// The disc meets the strip only for `|u| < s_out`.
    s_out: f64,
}

impl Strip {
    #[inline]
    fn new(r: f64, y0: f64, y1: f64) -> Strip {
        let s0 = half_chord(r, y0);
        let s1 = half_chord(r, y1);
        let s_out = if y0 < 0.0 && y1 > 0.0 { r } else { s0.max(s1) };
        Strip {
            r,
            y0,
            s0,
            y1,
            s1,
            s_in: s0.min(s1),
            s_out,
        }
    }

    /// `R(t)`, `t >= 0`: area of the disc in this strip to the right of `u = t`.
    #[inline]
    fn tail(&self, t: f64) -> f64 {
        let r = self.r;
        if t >= r {
            return 0.0;
        }
        let vb = half_chord(r, t);
        let (a, sa) = if self.y0 > -vb { (self.y0, self.s0) } else { (-vb, t) };
        let (b, sb) = if self.y1 < vb { (self.y1, self.s1) } else { (vb, t) };
        if a >= b {
            return 0.0;
        }
        let area = chord_integral(r, a, sa, b, sb) - t * (b - a);
        if area > 0.0 {
            area
        } else {
            0.0
        }
    }

    /// Area of the disc inside `[x0, x1] x [y0, y1]`, from the tails at both edges.
    #[inline]
    fn area_between(&self, x0: f64, t0: f64, x1: f64, t1: f64) -> f64 {
        // t0 = R(|x0|), t1 = R(|x1|)
        let a = if x0 >= 0.0 {
            t0 - t1
        } else if x1 <= 0.0 {
            t1 - t0
        } else {
            2.0 * self.tail(0.0) - t1 - t0
        };
        a.clamp(0.0, (x1 - x0) * (self.y1 - self.y0))
    }
}

/// Exact area of the intersection of the disc `(cx, cy, r)` with the rectangle
/// `[x0, x1] x [y0, y1]` (pixel units; area in pixel^2). Zero for `r <= 0` or an empty rectangle.
///
/// ```
/// use sofipol_pipeline::photometry::overlap_circle_rect;
/// let quarter = overlap_circle_rect(0.0, 0.0, 2.0, 0.0, 0.0, 5.0, 5.0);
/// assert!((quarter - std::f64::consts::PI).abs() < 1e-14);
/// ```
pub fn overlap_circle_rect(cx: f64, cy: f64, r: f64, x0: f64, y0: f64, x1: f64, y1: f64) -> f64 {
    if r.is_nan() || r <= 0.0 || x1 <= x0 || y1 <= y0 {
        return 0.0;
    }
    let strip = Strip::new(r, y0 - cy, y1 - cy);
    let (u0, u1) = (x0 - cx, x1 - cx);
    strip.area_between(u0, strip.tail(u0.abs()), u1, strip.tail(u1.abs()))
}

/// Exact fraction (in `[0, 1]`) of pixel `(ix, iy)` covered by the disc `(cx, cy, r)`.
///
/// ```
/// use sofipol_pipeline::photometry::overlap_circle_pixel;
/// // A circle of radius 0.5 inscribed in pixel (3, 4) covers pi/4 of it.
/// let f = overlap_circle_pixel(3.0, 4.0, 0.5, 3, 4);
/// assert!((f - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
/// ```
pub fn overlap_circle_pixel(cx: f64, cy: f64, r: f64, ix: i64, iy: i64) -> f64 {
    let (xl, yl) = (ix as f64 - 0.5, iy as f64 - 0.5);
    // The relative edges are rounded, so the rectangle's area may exceed 1 by an ulp.
    overlap_circle_rect(cx, cy, r, xl, yl, ix as f64 + 0.5, iy as f64 + 0.5).min(1.0)
}

/// Weight of pixel `(ix, iy)` in the circular aperture `(cx, cy, r)` with the given method.
pub fn pixel_weight(method: Method, cx: f64, cy: f64, r: f64, ix: i64, iy: i64) -> f64 {
    match method {
        Method::Exact => overlap_circle_pixel(cx, cy, r, ix, iy),
        Method::Center | Method::Subpixel(0) | Method::Subpixel(1) => center_weight(cx, cy, r, ix, iy),
        Method::Subpixel(n) => {
            let x0 = (ix as f64 - 0.5) - cx;
            let y0 = (iy as f64 - 0.5) - cy;
            subpixel_weight(x0, (ix as f64 + 0.5) - cx, y0, (iy as f64 + 0.5) - cy, r, n)
        }
    }
}

#[inline]
fn center_weight(cx: f64, cy: f64, r: f64, ix: i64, iy: i64) -> f64 {
    let (dx, dy) = (ix as f64 - cx, iy as f64 - cy);
    if dx * dx + dy * dy < r * r {
        1.0
    } else {
        0.0
    }
}

/// Fraction of `n x n` sub-pixel centres of `[x0, x1] x [y0, y1]` (relative to the centre)
/// strictly inside radius `r`. The sample positions are accumulated (`x += dx`) in the same
/// order as photutils' `circular_overlap_single_subpixel`, so that samples lying exactly on the
/// circle are decided identically.
#[inline]
fn subpixel_weight(x0: f64, x1: f64, y0: f64, y1: f64, r: f64, n: u32) -> f64 {
    let dx = (x1 - x0) / n as f64;
    let dy = (y1 - y0) / n as f64;
    let r2 = r * r;
    let mut count = 0u32;
    let mut x = x0 - 0.5 * dx;
    for _ in 0..n {
        x += dx;
        let mut y = y0 - 0.5 * dy;
        for _ in 0..n {
            y += dy;
            if x * x + y * y < r2 {
                count += 1;
            }
        }
    }
    count as f64 / (n as f64 * n as f64)
}

/// Calls `visit(ix, iy, w)` for every pixel of the (unbounded) grid with weight `w > 0` in the
/// circular aperture `(cx, cy, r)`, row by row (increasing `iy`, then `ix`). Pixels off any
/// image are visited too: the caller decides what they mean.
///
/// Only pixels with `cols.0 <= ix <= cols.1` and `rows.0 <= iy <= rows.1` are visited (pass
/// `(i64::MIN, i64::MAX)` for no limit), so the cost is bounded by the image, not by `r`.
///
/// ```
/// use sofipol_pipeline::photometry::{for_each_weight, Method};
/// let mut area = 0.0;
/// let all = (i64::MIN, i64::MAX);
/// for_each_weight(3.2, 4.9, 2.5, Method::Exact, all, all, |_ix, _iy, w| area += w);
/// assert!((area - std::f64::consts::PI * 6.25).abs() < 1e-12);
/// ```
pub fn for_each_weight<F: FnMut(i64, i64, f64)>(
    cx: f64,
    cy: f64,
    r: f64,
    method: Method,
    cols: (i64, i64),
    rows: (i64, i64),
    mut visit: F,
) {
    for_each_run(cx, cy, r, method, cols, rows, |iy, ix0, ix1, w| {
        for ix in ix0..=ix1 {
            visit(ix, iy, w);
        }
    });
}

/// Like [`for_each_weight`], but a row's pixels fully inside the circle come as one run:
/// `visit(iy, ix_first, ix_last, w)` means every pixel of `ix_first..=ix_last` has weight
/// `w` (1 for interior runs; boundary pixels come as runs of length one).
pub(crate) fn for_each_run<F: FnMut(i64, i64, i64, f64)>(
    cx: f64,
    cy: f64,
    r: f64,
    method: Method,
    cols: (i64, i64),
    rows: (i64, i64),
    mut visit: F,
) {
    if r.is_nan() || r <= 0.0 || !cx.is_finite() || !cy.is_finite() || !r.is_finite() || cols.0 > cols.1 {
        return;
    }
    let iy_lo = ((cy - r - 0.5).floor() as i64).max(rows.0);
    let iy_hi = ((cy + r + 0.5).ceil() as i64).min(rows.1);
    let method = match method {
        Method::Subpixel(0) | Method::Subpixel(1) => Method::Center,
        m => m,
    };
    for iy in iy_lo..=iy_hi {
        let y0 = (iy as f64 - 0.5) - cy;
        let y1 = (iy as f64 + 0.5) - cy;
        if y0 >= r || y1 <= -r {
            continue;
        }
        let strip = Strip::new(r, y0, y1);
        let edges = |ix: i64| ((ix as f64 - 0.5) - cx, (ix as f64 + 0.5) - cx);
        let inside = |ix: i64| {
            let (x0, x1) = edges(ix);
            x0 >= -strip.s_in && x1 <= strip.s_in
        };
        // A generous column range; every pixel in it is classified exactly below.
        let ix_lo = ((cx - strip.s_out - 0.5).floor() as i64).max(cols.0);
        let ix_hi = ((cx + strip.s_out + 0.5).ceil() as i64).min(cols.1);
        if ix_lo > ix_hi {
            continue;
        }
        // The pixels fully inside form an interval (the disc is convex): find it from the
        // closed form, then settle the ends with the same per-pixel test.
        let (mut a, mut b) = (
            (cx - strip.s_in + 0.5).ceil() as i64,
            (cx + strip.s_in - 0.5).floor() as i64,
        );
        if a <= b {
            while a <= b && !inside(a) {
                a += 1;
            }
            while a <= b && !inside(b) {
                b -= 1;
            }
            while a <= b && inside(a - 1) {
                a -= 1;
            }
            while a <= b && inside(b + 1) {
                b += 1;
            }
        }
        let (run_lo, run_hi) = if a <= b {
            (a.max(ix_lo), b.min(ix_hi))
        } else {
            (ix_hi + 1, ix_hi)
        };
        let interior_empty = run_lo > run_hi;

        // Cached tail at the left edge of the current pixel: (edge index, R(|x|)).
        let mut cached: Option<(i64, f64)> = None;
        let mut boundary = |ix: i64, visit: &mut F| {
            let (x0, x1) = edges(ix);
            if x1 <= -strip.s_out || x0 >= strip.s_out {
                return;
            }
            let w = match method {
                Method::Exact => {
                    let t0 = match cached {
                        Some((k, t)) if k == ix => t,
                        _ => strip.tail(x0.abs()),
                    };
                    let t1 = strip.tail(x1.abs());
                    cached = Some((ix + 1, t1));
                    strip.area_between(x0, t0, x1, t1).min(1.0)
                }
                Method::Center => center_weight(cx, cy, r, ix, iy),
                Method::Subpixel(n) => subpixel_weight(x0, x1, y0, y1, r, n),
            };
            if w > 0.0 {
                visit(iy, ix, ix, w);
            }
        };
        if interior_empty {
            for ix in ix_lo..=ix_hi {
                boundary(ix, &mut visit);
            }
        } else {
            for ix in ix_lo..run_lo {
                boundary(ix, &mut visit);
            }
            visit(iy, run_lo, run_hi, 1.0);
            for ix in run_hi + 1..=ix_hi {
                boundary(ix, &mut visit);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    const ALL: (i64, i64) = (i64::MIN, i64::MAX);

    /// Slow, obviously correct reference: the area of disc ∩ pixel is the integral over x of
    /// the length of [y0, y1] ∩ [cy - s(x), cy + s(x)], integrated by adaptive Simpson.
    fn reference_overlap(cx: f64, cy: f64, r: f64, ix: i64, iy: i64) -> f64 {
        let (x0, x1) = (ix as f64 - 0.5, ix as f64 + 0.5);
        let (y0, y1) = (iy as f64 - 0.5, iy as f64 + 0.5);
        let chord = |x: f64| -> f64 {
            let d2 = r * r - (x - cx) * (x - cx);
            if d2 <= 0.0 {
                return 0.0;
            }
            let s = d2.sqrt();
            ((cy + s).min(y1) - (cy - s).max(y0)).max(0.0)
        };
        // The integrand vanishes outside the circle's x-support.
        let (a, b) = (x0.max(cx - r), x1.min(cx + r));
        if a >= b {
            return 0.0;
        }
        let panels = 16;
        let h = (b - a) / panels as f64;
        (0..panels)
            .map(|k| {
                let (p, q) = (a + k as f64 * h, a + (k + 1) as f64 * h);
                adaptive_simpson(&chord, p, q, 1e-14, 48)
            })
            .sum()
    }

    fn adaptive_simpson(f: &dyn Fn(f64) -> f64, a: f64, b: f64, tol: f64, depth: u32) -> f64 {
        fn simpson(fa: f64, fm: f64, fb: f64, a: f64, b: f64) -> f64 {
            (b - a) / 6.0 * (fa + 4.0 * fm + fb)
        }
        /// An interval `[a, b]` with the integrand at its ends and middle, and its Simpson
        /// estimate (what each level of the recursion hands to the next).
        #[derive(Clone, Copy)]
        struct Panel {
            a: f64,
            b: f64,
            fa: f64,
            fm: f64,
            fb: f64,
            whole: f64,
        }
        fn rec(f: &dyn Fn(f64) -> f64, p: Panel, tol: f64, depth: u32) -> f64 {
            let Panel {
                a,
                b,
                fa,
                fm,
                fb,
                whole,
            } = p;
            let m = 0.5 * (a + b);
            let (lm, rm) = (0.5 * (a + m), 0.5 * (m + b));
            let (flm, frm) = (f(lm), f(rm));
            let left = simpson(fa, flm, fm, a, m);
            let right = simpson(fm, frm, fb, m, b);
            let delta = left + right - whole;
            if depth == 0 || delta.abs() <= 15.0 * tol {
                left + right + delta / 15.0
            } else {
                let lp = Panel {
                    a,
                    b: m,
                    fa,
                    fm: flm,
                    fb: fm,
                    whole: left,
                };
                let rp = Panel {
                    a: m,
                    b,
                    fa: fm,
                    fm: frm,
                    fb,
                    whole: right,
                };
                rec(f, lp, (0.5 * tol).max(1e-17), depth - 1) + rec(f, rp, (0.5 * tol).max(1e-17), depth - 1)
            }
        }
        let m = 0.5 * (a + b);
        let (fa, fm, fb) = (f(a), f(m), f(b));
        let whole = simpson(fa, fm, fb, a, b);
        rec(
            f,
            Panel {
                a,
                b,
                fa,
                fm,
                fb,
                whole,
            },
            tol,
            depth,
        )
    }

    #[test]
    fn photometry_overlap_known_values() {
        // Circle inside a pixel.
        assert!((overlap_circle_pixel(2.1, 3.2, 0.2, 2, 3) - PI * 0.04).abs() < 1e-15);
        // Pixel inside a circle.
        assert_eq!(overlap_circle_pixel(0.0, 0.0, 5.0, 1, 1), 1.0);
        // Far away and tangent.
        assert_eq!(overlap_circle_pixel(0.0, 0.0, 1.0, 5, 5), 0.0);
        assert_eq!(overlap_circle_pixel(0.0, 0.0, 0.5, 1, 0), 0.0);
        // Centre on a corner: each of the 4 pixels gets a quarter.
        for (ix, iy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let f = overlap_circle_pixel(0.5, 0.5, 0.5, ix, iy);
            assert!((f - PI / 16.0).abs() < 1e-15, "{f}");
        }
        // Centre on an edge, r = 0.5: half disc in each of two pixels.
        assert!((overlap_circle_pixel(0.5, 0.0, 0.5, 0, 0) - PI / 8.0).abs() < 1e-15);
        // Circle through the four corners (r = sqrt(1/2)): pixel fully inside.
        assert!((overlap_circle_pixel(0.0, 0.0, 0.5f64.sqrt(), 0, 0) - 1.0).abs() < 1e-15);
        // Degenerate radii.
        assert_eq!(overlap_circle_pixel(0.0, 0.0, 0.0, 0, 0), 0.0);
        assert_eq!(overlap_circle_pixel(0.0, 0.0, -1.0, 0, 0), 0.0);
        assert_eq!(overlap_circle_pixel(0.0, 0.0, f64::NAN, 0, 0), 0.0);
        // Huge radius, pixel far inside / straddling the boundary.
        assert_eq!(overlap_circle_pixel(0.0, 0.0, 1e6, 10, -3), 1.0);
        // Straddling the edge of r = 1e4: 1/2 minus the sagitta term 1/(24 r).
        let f = overlap_circle_pixel(0.0, 0.0, 1e4, 10_000, 0);
        assert!((f - (0.5 - 1.0 / 24e4)).abs() < 1e-11, "{f}");
    }

    #[test]
    fn photometry_subpixel_and_center_weights() {
        assert_eq!(pixel_weight(Method::Center, 0.0, 0.0, 1.0, 1, 0), 0.0); // d == r: out
        assert_eq!(pixel_weight(Method::Center, 0.0, 0.0, 1.0 + 1e-12, 1, 0), 1.0);
        assert_eq!(pixel_weight(Method::Subpixel(1), 0.3, 0.0, 0.5, 0, 0), 1.0);
        // r = 0.5 at the pixel centre with 2x2 samples at (+-0.25, +-0.25): all inside.
        assert_eq!(pixel_weight(Method::Subpixel(2), 0.0, 0.0, 0.5, 0, 0), 1.0);
        // Subpixel converges to exact.
        let e = pixel_weight(Method::Exact, 0.3, 0.1, 0.8, 1, 0);
        let s = pixel_weight(Method::Subpixel(400), 0.3, 0.1, 0.8, 1, 0);
        assert!((e - s).abs() < 2e-4, "{e} {s}");
    }

    #[test]
    fn photometry_visitor_matches_single_pixel_function() {
        for &(cx, cy, r) in &[(3.3, 4.7, 2.9), (0.5, 0.5, 0.5), (10.0, 10.0, 7.0), (1.0, 2.0, 0.05)] {
            for method in [Method::Exact, Method::Center, Method::Subpixel(5)] {
                let mut seen = std::collections::HashMap::new();
                for_each_weight(cx, cy, r, method, ALL, ALL, |ix, iy, w| {
                    assert!(seen.insert((ix, iy), w).is_none());
                });
                let (lo, hi) = ((cy - r).floor() as i64 - 2, (cy + r).ceil() as i64 + 2);
                let (xlo, xhi) = ((cx - r).floor() as i64 - 2, (cx + r).ceil() as i64 + 2);
                for iy in lo..=hi {
                    for ix in xlo..=xhi {
                        let w = pixel_weight(method, cx, cy, r, ix, iy);
                        let v = seen.get(&(ix, iy)).copied().unwrap_or(0.0);
                        assert!((w - v).abs() < 1e-13, "{method:?} {cx} {cy} {r} {ix} {iy}: {w} vs {v}");
                    }
                }
            }
        }
    }

    fn total_weight(cx: f64, cy: f64, r: f64) -> f64 {
        let mut s = 0.0;
        for_each_weight(cx, cy, r, Method::Exact, ALL, ALL, |_, _, w| s += w);
        s
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

        #[test]
        fn photometry_prop_overlap_matches_quadrature(
            cx in -1.5f64..1.5, cy in -1.5f64..1.5, r in 0.001f64..3.0,
            ix in -2i64..=2, iy in -2i64..=2,
        ) {
            let fast = overlap_circle_pixel(cx, cy, r, ix, iy);
            let slow = reference_overlap(cx, cy, r, ix, iy);
            prop_assert!((fast - slow).abs() <= 1e-9, "fast {} slow {}", fast, slow);
            prop_assert!((0.0..=1.0).contains(&fast));
        }

        #[test]
        fn photometry_prop_overlap_boundary_pixels_large_r(
            cx in -0.5f64..0.5, cy in -0.5f64..0.5, r in 3.0f64..300.0, phi in 0.0f64..std::f64::consts::TAU,
        ) {
            // A pixel on the circle's boundary at polar angle phi.
            let ix = (cx + r * phi.cos()).round() as i64;
            let iy = (cy + r * phi.sin()).round() as i64;
            let fast = overlap_circle_pixel(cx, cy, r, ix, iy);
            let slow = reference_overlap(cx, cy, r, ix, iy);
            prop_assert!((fast - slow).abs() <= 1e-9, "fast {} slow {}", fast, slow);
        }

        #[test]
        fn photometry_prop_overlaps_sum_to_circle_area(
            cx in -50.0f64..50.0, cy in -50.0f64..50.0, r in 0.0f64..40.0,
        ) {
            let area = PI * r * r;
            let s = total_weight(cx, cy, r);
            prop_assert!((s - area).abs() <= 1e-10 * area.max(1e-3), "{} vs {}", s, area);
        }

        #[test]
        fn photometry_prop_overlap_symmetries(
            cx in -3.0f64..3.0, cy in -3.0f64..3.0, r in 0.0f64..4.0,
            ix in -4i64..=4, iy in -4i64..=4,
        ) {
            let f = overlap_circle_pixel(cx, cy, r, ix, iy);
            prop_assert!((0.0..=1.0).contains(&f));
            let mx = overlap_circle_pixel(-cx, cy, r, -ix, iy);
            let my = overlap_circle_pixel(cx, -cy, r, ix, -iy);
            let tr = overlap_circle_pixel(cy, cx, r, iy, ix);
            let sh = overlap_circle_pixel(cx + 7.0, cy - 3.0, r, ix + 7, iy - 3);
            for g in [mx, my, tr, sh] {
                prop_assert!((f - g).abs() <= 1e-13, "{} vs {}", f, g);
            }
        }
    }
}
