//! Cosmic rays in the apertures of the half-wave-plate reduction: each frame's image of a
//! star is compared with the same beam's images of that star in the target's other frames.
//!
//! The star lies on the same pixels of every frame (a single pointing; the frames' centres
//! differ by the guiding, fractions of a pixel to a few pixels) and its image changes from
//! frame to frame only by its flux (the plate turns the polarization, the sky's
//! transparency changes) and a little by the seeing. So at each aperture pixel `p` of frame
//! `i`, the other frames' values at the same offset from their own centres (bicubic), each
//! scaled by the ratio of the beam's aperture fluxes `flux_i / flux_j`, predict frame `i`'s
//! value; their median is the prediction `m` and 1.4826 x their median absolute deviation
//! `s` its spread (the other frames' noise, the seeing's changes and the interpolation's
//! error together). The residual `I_i - m` still holds frame `i`'s own change of the
//! seeing, a smooth pattern as large as many sigma in the core of a bright star: its
//! weighted least-squares fit by a constant, `m`'s two gradients and its three second
//! derivatives over the aperture (a change of the sky, of the centring, of the width and
//! the elongation) is added to `m`. What is left less the median of the ring 2 px about `p`
//! (the speckles' changes) is `r`, and the pixel is hit when
//!
//! ```text
//! r > K sqrt(Var_i(p) + s^2 + (f m)^2)   K = 6 (one-sided: a hit adds charge), f = 0.005
//! ```
//!
//! (`f m` the prediction's own error: the bicubic interpolation of a core a few pixels
//! wide, the flat's pixel errors; without it single pixels of the simulated nights' cores
//! reached 7-8 sigma; 0.02 hid a 6-sigma_F hit 3-4 px from a bright star's centre).
//!
//! and the pixels next to a hit (8-connected) are hit too when above `K_GROW` = 3 of the
//! same: a hit spreads its charge over a few pixels. A hit pixel is repaired, its value
//! replaced by `m` (its variance kept), and the beam's aperture flux summed again; the frame's
//! catalog entry counts the pixels repaired per beam (`cosmic_ray_pixels`). The median of 7
//! other frames is unmoved by a hit in one of them, and K = 6 keeps honest pixels: over an
//! aperture of 4000 pixels in 16 images the chance of repairing a clean pixel is below 1 %
//! per night. A target with fewer than 3 frames is not checked (no median to compare with).
//!
//! Hits outside the aperture need no test: the sky fit clips them (4 sigma, `image::fit_sky`),
//! the annulus sky is a median.
use super::image::{self, Img};
use super::FrameResult;
use crate::stokes::hwp::{self, PlateFrame};

/// Threshold of a hit, in units of `sqrt(Var + s^2)`.
pub const K_HIT: f64 = 6.0;
/// The prediction's own error as a fraction of it, added in quadrature to the noise: the
/// bicubic interpolation of a core a few pixels wide, the flat's pixel errors.
pub const REL_FLOOR: f64 = 0.005;
/// Threshold of a hit's neighbour.
pub const K_GROW: f64 = 3.0;

/// A box of one frame about one image of the star: the reduced values, their variances and
/// the pixels not to use (bad, not finite).
#[derive(Debug, Clone)]
pub struct Cutout {
    /// Column of the box's first pixel in the frame.
    pub x0: usize,
    /// Row of its first pixel.
    pub y0: usize,
    /// Values.
    pub img: Img,
    /// Variances.
    pub var: Img,
    /// Bad or not finite.
    pub mask: Vec<bool>,
    /// The image's centre, in the box's pixels.
    pub centre: (f64, f64),
}

impl Cutout {
    /// The box of half-size `half` px about `centre` (frame pixels), clipped to the frame.
    pub fn new(img: &Img, var: &Img, bad: &[bool], centre: (f64, f64), half: f64) -> Cutout {
        let lo = |c: f64| (c - half).floor().max(0.0) as usize;
        let (x0, y0) = (lo(centre.0), lo(centre.1));
        let x1 = ((centre.0 + half).ceil() as usize + 1).min(img.nx);
        let y1 = ((centre.1 + half).ceil() as usize + 1).min(img.ny);
        let (nx, ny) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        let mut out = Cutout {
            x0,
            y0,
            img: Img::filled(nx, ny, f64::NAN),
            var: Img::filled(nx, ny, f64::NAN),
            mask: vec![true; nx * ny],
            centre: (centre.0 - x0 as f64, centre.1 - y0 as f64),
        };
        for y in 0..ny {
            for x in 0..nx {
                let (i, k) = ((y0 + y) * img.nx + x0 + x, y * nx + x);
                out.img.v[k] = img.v[i];
                out.var.v[k] = var.v[i];
                out.mask[k] = bad[i] || !img.v[i].is_finite() || !var.v[i].is_finite();
            }
        }
        out
    }
}

/// Find and repair cosmic-ray hits in the apertures (`aperture_px` = [r_in, r_out]) of one
/// target's frames (`cuts[i]`: frame i's o and e boxes); each frame whose pixels are
/// repaired gets its fluxes, F and errors again and `cosmic_ray_pixels` set.
pub fn repair(frames: &mut [FrameResult], cuts: &[&[Cutout; 2]], aperture_px: [f64; 2]) {
    let n = frames.len();
    if n < 3 || cuts.len() != n {
        return;
    }
    let [r_in, r_out] = aperture_px;
    for beam in 0..2 {
        let flux = |f: &FrameResult| if beam == 0 { f.o } else { f.e };
        let fluxes: Vec<f64> = frames.iter().map(flux).collect();
        for i in 0..n {
            let me = &cuts[i][beam];
            let hits = hits(me, i, &fluxes, cuts, beam, r_in, r_out);
            if hits.is_empty() {
                continue;
            }
            let mut img = me.img.clone();
            for &(k, m) in &hits {
                img.v[k] = m;
            }
            let (s, sigma) = image::annulus_sum(&img, &me.var, &me.mask, me.centre, r_in, r_out);
            if !(s.is_finite() && sigma.is_finite()) {
                continue;
            }
            let f = &mut frames[i];
            if beam == 0 {
                (f.o, f.sigma_o) = (s, sigma);
            } else {
                (f.e, f.sigma_e) = (s, sigma);
            }
            f.cosmic_ray_pixels[beam] = hits.len();
            if let Some((fv, sf)) = hwp::frame_f(&PlateFrame {
                plate_deg: f.plate_deg,
                o: f.o,
                sigma_o: f.sigma_o,
                e: f.e,
                sigma_e: f.sigma_e,
            }) {
                (f.f, f.sigma_f) = (fv, sf);
            }
        }
    }
}

/// The hit pixels of frame `i`'s box `me` (index in the box, the predicted value).
fn hits(
    me: &Cutout,
    i: usize,
    fluxes: &[f64],
    cuts: &[&[Cutout; 2]],
    beam: usize,
    r_in: f64,
    r_out: f64,
) -> Vec<(usize, f64)> {
    let (nx, ny) = (me.img.nx, me.img.ny);
    // Per pixel of the aperture and 3 px about it: the residual from the prediction, its
    // noise and the prediction.
    let mut res = vec![f64::NAN; nx * ny];
    let mut noise = vec![f64::NAN; nx * ny];
    let mut pred = vec![f64::NAN; nx * ny];
    let mut vals = Vec::with_capacity(cuts.len());
    for y in 0..ny {
        for x in 0..nx {
            let k = y * nx + x;
            let (dx, dy) = (x as f64 - me.centre.0, y as f64 - me.centre.1);
            let r = dx.hypot(dy);
            if me.mask[k] || r > r_out + 3.75 || r < r_in - 3.75 {
                continue;
            }
            vals.clear();
            for (j, c) in cuts.iter().enumerate() {
                if j == i || !(fluxes[j] > 0.0) {
                    continue;
                }
                let o = &c[beam];
                let v = image::interp_unmasked(&o.img, &o.mask, o.centre.0 + dx, o.centre.1 + dy);
                if let Some(v) = v {
                    vals.push(v * fluxes[i] / fluxes[j]);
                }
            }
            if vals.len() < 2 {
                continue;
            }
            let m = image::median(&mut vals.clone());
            let mut dev: Vec<f64> = vals.iter().map(|v| (v - m).abs()).collect();
            let s = 1.4826 * image::median(&mut dev);
            let sd = (me.var.v[k] + s * s + (REL_FLOOR * m).powi(2)).sqrt();
            if sd > 0.0 {
                res[k] = me.img.v[k] - m;
                noise[k] = sd;
                pred[k] = m;
            }
        }
    }
    // The smooth part of the residual: a change of the seeing, of the focus or of the
    // centring changes the image as a whole, the prediction's gradients and second
    // derivatives times a few numbers. Removed by weighted least squares over the aperture
    // (pixels beyond K_GROW left out and the fit made again), what is left is sharp.
    smooth_fit(&mut res, &mut pred, &noise, nx, ny, |k| {
        let (dx, dy) = ((k % nx) as f64 - me.centre.0, (k / nx) as f64 - me.centre.1);
        let r = dx.hypot(dy);
        r <= r_out + 0.75 && r >= r_in - 0.75
    });
    // The residual less the median of its ring 2 px away (16 pixels, at least 8 usable):
    // a hit is sharp, what the fit left of the speckles' changes is not.
    let mut z = vec![f64::NAN; nx * ny];
    let mut ring = Vec::with_capacity(16);
    for y in 2..ny.saturating_sub(2) {
        for x in 2..nx.saturating_sub(2) {
            let k = y * nx + x;
            let (dx, dy) = (x as f64 - me.centre.0, y as f64 - me.centre.1);
            let r = dx.hypot(dy);
            if !res[k].is_finite() || r > r_out + 0.75 || r < r_in - 0.75 {
                continue;
            }
            ring.clear();
            for oy in -2i64..=2 {
                for ox in -2i64..=2 {
                    if ox.abs() == 2 || oy.abs() == 2 {
                        let kk = (y as i64 + oy) as usize * nx + (x as i64 + ox) as usize;
                        if res[kk].is_finite() {
                            ring.push(res[kk]);
                        }
                    }
                }
            }
            if ring.len() >= 8 {
                let bg = image::median(&mut ring);
                z[k] = (res[k] - bg) / noise[k];
                pred[k] += bg;
            }
        }
    }
    let mut hit = vec![false; nx * ny];
    for (h, &zk) in hit.iter_mut().zip(&z) {
        *h = zk > K_HIT;
    }
    let core = hit.clone();
    for y in 0..ny {
        for x in 0..nx {
            let k = y * nx + x;
            if !core[k] {
                continue;
            }
            for (oy, ox) in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
                let (xx, yy) = (x as i64 + ox, y as i64 + oy);
                if xx >= 0 && yy >= 0 && (xx as usize) < nx && (yy as usize) < ny {
                    let kk = yy as usize * nx + xx as usize;
                    if z[kk] > K_GROW {
                        hit[kk] = true;
                    }
                }
            }
        }
    }
    hit.iter()
        .enumerate()
        .filter(|(_, &h)| h)
        .map(|(k, _)| (k, pred[k]))
        .collect()
}

/// Subtract from the residuals `res` (and add to the predictions `pred`) their least-squares
/// fit, weights `1 / noise^2`, made over the pixels `use_px` where all are finite, by
///
/// ```text
/// res ~ c0 + c1 d(pred)/dx + c2 d(pred)/dy + c3 d2(pred)/dx2 + c4 d2(pred)/dy2 + c5 d2(pred)/dxdy
/// ```
///
/// (finite differences of the prediction): a Gaussian image whose width changes by
/// `d sigma` changes by `sigma d sigma lap(P)` (an elongated change weights the second
/// derivatives apart), one that moves by `(ex, ey)` by `-ex dP/dx - ey dP/dy`, a sky offset
/// by a constant. Pixels beyond `K_GROW` of the fit
/// (a hit) are left out and the fit made again, twice. Nothing is changed when fewer than
/// 16 pixels can be used or the normal equations are singular.
fn smooth_fit(res: &mut [f64], pred: &mut [f64], noise: &[f64], nx: usize, ny: usize, use_px: impl Fn(usize) -> bool) {
    let at = |x: usize, y: usize| pred[y * nx + x];
    // Every pixel with a residual is corrected; those of `use_px` make the fit.
    let mut rows: Vec<(usize, [f64; NB], bool)> = Vec::new();
    for y in 1..ny.saturating_sub(1) {
        for x in 1..nx.saturating_sub(1) {
            let k = y * nx + x;
            if !res[k].is_finite() || !(noise[k] > 0.0) {
                continue;
            }
            let (l, r, d, u) = (at(x - 1, y), at(x + 1, y), at(x, y - 1), at(x, y + 1));
            let c = pred[k];
            let dxy = 0.25 * (at(x + 1, y + 1) + at(x - 1, y - 1) - at(x + 1, y - 1) - at(x - 1, y + 1));
            let b = [1.0, 0.5 * (r - l), 0.5 * (u - d), l + r - 2.0 * c, d + u - 2.0 * c, dxy];
            if b.iter().all(|v| v.is_finite()) {
                rows.push((k, b, use_px(k)));
            }
        }
    }
    let mut keep: Vec<bool> = rows.iter().map(|r| r.2).collect();
    if keep.iter().filter(|&&u| u).count() < 16 {
        return;
    }
    let mut coef = [0.0; NB];
    for _ in 0..3 {
        let mut a = [[0.0; NB]; NB];
        let mut rhs = [0.0; NB];
        for ((k, b, _), _) in rows.iter().zip(&keep).filter(|(_, &kp)| kp) {
            let w = 1.0 / (noise[*k] * noise[*k]);
            for i in 0..NB {
                rhs[i] += w * b[i] * res[*k];
                for j in 0..NB {
                    a[i][j] += w * b[i] * b[j];
                }
            }
        }
        match solve(a, rhs) {
            Some(c) => coef = c,
            None => return,
        }
        for ((k, b, u), kp) in rows.iter().zip(keep.iter_mut()) {
            let f: f64 = b.iter().zip(&coef).map(|(b, c)| b * c).sum();
            *kp = *u && ((res[*k] - f) / noise[*k]).abs() <= K_GROW;
        }
    }
    for (k, b, _) in &rows {
        let f: f64 = b.iter().zip(&coef).map(|(b, c)| b * c).sum();
        res[*k] -= f;
        pred[*k] += f;
    }
}

/// The terms of the residual's smooth fit ([`smooth_fit`]).
const NB: usize = 6;

/// Solve the NB x NB system `a c = b` by Gaussian elimination with partial pivoting; `None`
/// when it is singular.
fn solve(mut a: [[f64; NB]; NB], mut b: [f64; NB]) -> Option<[f64; NB]> {
    let scale = (0..NB).map(|i| a[i][i].abs()).fold(0.0, f64::max);
    for c in 0..NB {
        let p = (c..NB).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if !(a[p][c].abs() > 1e-12 * scale) {
            return None;
        }
        a.swap(c, p);
        b.swap(c, p);
        for r in c + 1..NB {
            let f = a[r][c] / a[c][c];
            let pivot = a[c];
            for (arj, pj) in a[r].iter_mut().zip(pivot).skip(c) {
                *arj -= f * pj;
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = [0.0; NB];
    for c in (0..NB).rev() {
        let s: f64 = (c + 1..NB).map(|j| a[c][j] * x[j]).sum();
        x[c] = (b[c] - s) / a[c][c];
    }
    Some(x)
}

/// Repair cosmic-ray hits in the dark-subtracted sky frames `skies` before they make the
/// flat and the matched skies; returns the pixels repaired in each frame.
///
/// A hit in a sky frame is in every science frame of its plate position (the matched sky
/// is the mean of that position's sky frames) and, at an eighth of its size, in the flat:
/// on the pixels of the stars' images it moves their fluxes in every frame alike, which the
/// cycle-to-cycle scatter cannot reveal. The sky frames have no star at the science
/// frames' positions and their images differ by the sky's level only (its polarization
/// through the plate, its drift), so in each beam's rows (`rows`) each frame `j` is compared
/// with the others scaled to its level: `L_j` is the median of the frame over the rows,
/// `m` the median over the other frames of `v_k / L_k`, and the residual
/// `d = v_j - L_j m` is hit when
///
/// ```text
/// d > K_HIT s_j    s_j = 1.4826 x the median absolute residual of frame j over the rows
/// ```
///
/// (its 8-connected neighbours when above `K_GROW s_j`), and replaced by `L_j m`. The
/// pixels `bad` and those not finite are neither tested nor used. Fewer than 3 frames are
/// not checked.
pub fn repair_sky_frames(skies: &mut [Img], rows: &[[usize; 2]], bad: &[bool]) -> Vec<usize> {
    let n = skies.len();
    let mut repaired = vec![0; n];
    if n < 3 {
        return repaired;
    }
    let (nx, ny) = (skies[0].nx, skies[0].ny);
    for &[r0, r1] in rows {
        let (r0, r1) = (r0.min(ny), r1.min(ny));
        let px: Vec<usize> = (r0 * nx..r1 * nx)
            .filter(|&k| !bad[k] && skies.iter().all(|s| s.v[k].is_finite()))
            .collect();
        if px.len() < 16 {
            continue;
        }
        let levels: Vec<f64> = skies
            .iter()
            .map(|s| image::median(&mut px.iter().map(|&k| s.v[k]).collect::<Vec<_>>()))
            .collect();
        if !levels.iter().all(|l| *l > 0.0) {
            continue;
        }
        // Per pixel and frame: the prediction from the other frames and the residual.
        let mut pred = vec![vec![f64::NAN; nx * ny]; n];
        let mut res = vec![vec![f64::NAN; nx * ny]; n];
        let mut others = Vec::with_capacity(n);
        for &k in &px {
            for j in 0..n {
                others.clear();
                others.extend((0..n).filter(|&i| i != j).map(|i| skies[i].v[k] / levels[i]));
                let p = levels[j] * image::median(&mut others);
                pred[j][k] = p;
                res[j][k] = skies[j].v[k] - p;
            }
        }
        for j in 0..n {
            let mut dev: Vec<f64> = px.iter().map(|&k| res[j][k].abs()).collect();
            let s = 1.4826 * image::median(&mut dev);
            if !(s > 0.0) {
                continue;
            }
            let z = |k: usize| res[j][k] / s;
            let mut hit = vec![false; nx * ny];
            for &k in &px {
                if z(k) > K_HIT {
                    hit[k] = true;
                    let (x, y) = ((k % nx) as i64, (k / nx) as i64);
                    for (oy, ox) in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
                        let (xx, yy) = (x + ox, y + oy);
                        if xx >= 0 && (xx as usize) < nx && yy >= r0 as i64 && (yy as usize) < r1 {
                            let kk = yy as usize * nx + xx as usize;
                            if z(kk) > K_GROW {
                                hit[kk] = true;
                            }
                        }
                    }
                }
            }
            for (k, _) in hit.iter().enumerate().filter(|(_, &h)| h) {
                skies[j].v[k] = pred[j][k];
                repaired[j] += 1;
            }
        }
    }
    repaired
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Eight sky frames of 40 x 40 pixels, two beams of 20 rows: a common pixel pattern
    /// (1 % response) times each frame's own level per beam, plus noise of 50 ADU.
    fn skies(seed: u64) -> Vec<Img> {
        let mut r = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed);
        let unit = Normal::new(0.0, 1.0).unwrap();
        let pattern: Vec<f64> = (0..1600).map(|_| 1.0 + 0.01 * unit.sample(&mut r)).collect();
        (0..8)
            .map(|j| {
                let levels = [5000.0 * (1.0 + 0.01 * j as f64), 5200.0 * (1.0 - 0.01 * j as f64)];
                let v = (0..1600)
                    .map(|k| levels[k / 800] * pattern[k] + 50.0 * unit.sample(&mut r))
                    .collect();
                Img { nx: 40, ny: 40, v }
            })
            .collect()
    }

    #[test]
    fn sky_frames_without_hits_are_left_alone_and_a_hit_is_repaired() {
        let rows = [[0, 20], [20, 40]];
        let bad = vec![false; 1600];
        // No hit: 8 frames x 1600 pixels tested at 6 sigma, none repaired.
        for seed in 0..4 {
            let mut s = skies(seed);
            let before = s.clone();
            assert_eq!(repair_sky_frames(&mut s, &rows, &bad), vec![0; 8], "seed {seed}");
            assert!(s.iter().zip(&before).all(|(a, b)| a.v == b.v));
        }
        // A track of 3 pixels (1000, 500, 333 ADU: 20, 10 and 7 sigma; the simulator's track)
        // in frame 3's e beam: all three repaired, to within 4 sigma of the clean value.
        let clean = skies(7);
        let mut s = clean.clone();
        let track = [(25 * 40 + 10, 1000.0), (25 * 40 + 11, 500.0), (25 * 40 + 12, 333.0)];
        for &(k, a) in &track {
            s[3].v[k] += a;
        }
        let n = repair_sky_frames(&mut s, &rows, &bad);
        assert_eq!(n, vec![0, 0, 0, 3, 0, 0, 0, 0]);
        for &(k, _) in &track {
            assert!(
                (s[3].v[k] - clean[3].v[k]).abs() < 4.0 * 50.0,
                "pixel {k}: {} vs {}",
                s[3].v[k],
                clean[3].v[k]
            );
        }
        // Fewer than 3 frames: not checked.
        let mut two = s[..2].to_vec();
        two[0].v[5] += 1e4;
        assert_eq!(repair_sky_frames(&mut two, &rows, &bad), vec![0, 0]);
    }
}
