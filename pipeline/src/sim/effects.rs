//! One function per effect. Each counts its calls in [`EffectCalls`] and draws from its
//! own random stream ([`super::rng::stream`]), so an effect's realisation does not depend
//! on which other effects are listed.
use ndarray::Array2;
use rand::rngs::Xoshiro256PlusPlus;
use rand::RngExt;
use rand_distr::{Distribution, Poisson};
use rayon::prelude::*;
use serde::Serialize;
use sofipol_calib::profile::Geometry;

use super::psf::Psf;
use super::rng::stream;
use super::scene::*;
use super::{normal, uniform, EffectCalls};
use crate::stokes::model::Polarization;

/// Above this many electrons the Poisson draw is replaced by a Gaussian of the same mean
/// and variance (skewness 1/sqrt(1e4) = 0.01: far below anything measurable here).
pub const POISSON_GAUSS_SWITCH_E: f64 = 1e4;

/// Fixed bad-pixel realisation.
pub struct BadPixelMap {
    /// 1 where bad.
    pub mask: Array2<u8>,
    /// (y, x, value) of pixels forced to a value (hot: high, dead: 0).
    pub forced: Vec<(usize, usize, f32)>,
    /// Counts for the truth file.
    pub summary: BadPixelSummary,
}

/// Bad-pixel counts.
#[derive(Debug, Clone, Serialize)]
pub struct BadPixelSummary {
    /// Hot pixels.
    pub hot: usize,
    /// Isolated dead pixels.
    pub dead: usize,
    /// Pixels in dead clusters.
    pub cluster_pixels: usize,
    /// Column segments as (x, y_start, length).
    pub column_segments: Vec<(usize, usize, usize)>,
    /// Total distinct bad pixels.
    pub total: usize,
}

/// Draw the detector's bad pixels (fixed for the whole scene).
pub fn bad_pixel_map(calls: &EffectCalls, seed: u64, c: &BadPixelConfig, ny: usize, nx: usize) -> BadPixelMap {
    calls.hit(EffectKind::BadPixels);
    let mut r = stream(seed, EffectKind::BadPixels, 0, 0, 0);
    let mut mask = Array2::<u8>::zeros((ny, nx));
    let mut forced = Vec::new();
    let n = (ny * nx) as f64;
    let mut put = |mask: &mut Array2<u8>, y: usize, x: usize, v: f32| {
        if mask[[y, x]] == 0 {
            mask[[y, x]] = 1;
            forced.push((y, x, v));
            true
        } else {
            false
        }
    };
    let mut hot = 0;
    for _ in 0..(c.hot_fraction * n).round() as usize {
        let (y, x) = (r.random_range(0..ny), r.random_range(0..nx));
        let level = (c.hot_level_adu * (0.5 + uniform(&mut r))) as f32;
        hot += put(&mut mask, y, x, level) as usize;
    }
    let mut dead = 0;
    for _ in 0..(c.dead_fraction * n).round() as usize {
        let (y, x) = (r.random_range(0..ny), r.random_range(0..nx));
        dead += put(&mut mask, y, x, 0.0) as usize;
    }
    let mut cluster_pixels = 0;
    for _ in 0..c.clusters {
        let (cy, cx) = (r.random_range(0..ny) as f64, r.random_range(0..nx) as f64);
        let rr = c.cluster_radius_px;
        let k = rr.ceil() as i64;
        for dy in -k..=k {
            for dx in -k..=k {
                let (y, x) = (cy as i64 + dy, cx as i64 + dx);
                if (dx * dx + dy * dy) as f64 <= rr * rr && y >= 0 && x >= 0 && (y as usize) < ny && (x as usize) < nx {
                    cluster_pixels += put(&mut mask, y as usize, x as usize, 0.0) as usize;
                }
            }
        }
    }
    let mut column_segments = Vec::new();
    for _ in 0..c.column_segments {
        let x = r.random_range(0..nx);
        let y0 = r.random_range(0..ny.saturating_sub(c.column_length_px).max(1));
        let len = c.column_length_px.min(ny - y0);
        let level = (c.hot_level_adu * 0.25) as f32;
        for y in y0..y0 + len {
            put(&mut mask, y, x, level);
        }
        column_segments.push((x, y0, len));
    }
    let total = forced.len();
    BadPixelMap {
        mask,
        forced,
        summary: BadPixelSummary {
            hot,
            dead,
            cluster_pixels,
            column_segments,
            total,
        },
    }
}

/// Force bad pixels to their values.
pub fn apply_bad_pixels(calls: &EffectCalls, img: &mut Array2<f32>, bad: &BadPixelMap) {
    calls.hit(EffectKind::BadPixels);
    for &(y, x, v) in &bad.forced {
        img[[y, x]] = v;
    }
}

/// Draw the pixel response: (1 - v r^2/r_corner^2) (1 + rms N(0,1)), fixed on the detector.
pub fn flat_field_map(calls: &EffectCalls, seed: u64, c: &FlatFieldConfig, ny: usize, nx: usize) -> Array2<f32> {
    calls.hit(EffectKind::FlatField);
    let mut out = Array2::<f32>::zeros((ny, nx));
    let (cy, cx) = ((ny as f64 - 1.0) / 2.0, (nx as f64 - 1.0) / 2.0);
    let rc2 = cx * cx + cy * cy;
    out.as_slice_mut()
        .expect("standard layout")
        .par_chunks_mut(nx)
        .enumerate()
        .for_each(|(y, row)| {
            let mut r = stream(seed, EffectKind::FlatField, y as u64, 0, 0);
            for (x, v) in row.iter_mut().enumerate() {
                let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
                *v = ((1.0 - c.vignetting * d2 / rc2) * (1.0 + c.pixel_rms * normal(&mut r))) as f32;
            }
        });
    out
}

/// True offset = header offset + N(0, rms) per axis.
pub fn pointing_error(
    calls: &EffectCalls,
    seed: u64,
    c: &PointingConfig,
    key: (u64, u64),
    header: [f64; 2],
) -> [f64; 2] {
    calls.hit(EffectKind::PointingError);
    let mut r = stream(seed, EffectKind::PointingError, key.0, key.1, 0);
    [
        header[0] + c.rms_px * normal(&mut r),
        header[1] + c.rms_px * normal(&mut r),
    ]
}

/// Transparency factor, uniform in [min, 1].
pub fn transparency(calls: &EffectCalls, seed: u64, c: &TransparencyConfig, key: (u64, u64)) -> f64 {
    calls.hit(EffectKind::Transparency);
    let mut r = stream(seed, EffectKind::Transparency, key.0, key.1, 0);
    c.min + (1.0 - c.min) * uniform(&mut r)
}

/// Sky level of one frame: level (1 + change N(0,1)).
pub fn sky_level(calls: &EffectCalls, seed: u64, c: &SkyConfig, key: (u64, u64)) -> f64 {
    calls.hit(EffectKind::Sky);
    let mut r = stream(seed, EffectKind::Sky, key.0, key.1, 0);
    c.level_adu * (1.0 + c.frame_change_frac * normal(&mut r))
}

/// Seeing of one frame: FWHM exp(N(0, rms)) x U(1 - spread, 1 + spread), and beta
/// uniform in `beta_range` when given. Each draw has its own stream (sub-keys 0, 1, 2),
/// so adding a spread or a beta range leaves the other draws unchanged.
pub fn frame_psf(calls: &EffectCalls, seed: u64, c: &PsfConfig, key: (u64, u64), scale: f64) -> Psf {
    calls.hit(EffectKind::Psf);
    let mut r = stream(seed, EffectKind::Psf, key.0, key.1, 0);
    let mut fwhm_px = c.fwhm_arcsec / scale * (c.seeing_rms_frac * normal(&mut r)).exp();
    if c.fwhm_spread_frac > 0.0 {
        let mut r = stream(seed, EffectKind::Psf, key.0, key.1, 2);
        fwhm_px *= 1.0 + c.fwhm_spread_frac * (2.0 * uniform(&mut r) - 1.0);
    }
    let beta = match c.beta_range {
        Some([lo, hi]) => {
            let mut r = stream(seed, EffectKind::Psf, key.0, key.1, 1);
            lo + (hi - lo) * uniform(&mut r)
        }
        None => c.beta,
    };
    let psf = Psf::from_fwhm(c.kind, fwhm_px, beta);
    match c.axis_ratio_range {
        Some([lo, hi]) => {
            let mut r = stream(seed, EffectKind::Psf, key.0, key.1, 3);
            let ratio = lo + (hi - lo) * uniform(&mut r);
            psf.with_ellipticity(ratio, 180.0 * uniform(&mut r))
        }
        None => psf,
    }
}

/// Fill the sky: level + gx (x - xc) + gy (y - yc), ADU per pixel.
pub fn sky(calls: &EffectCalls, img: &mut Array2<f32>, level: f64, c: &SkyConfig) {
    calls.hit(EffectKind::Sky);
    let (ny, nx) = img.dim();
    let (xc, yc) = (nx as f64 / 2.0, ny as f64 / 2.0);
    img.as_slice_mut()
        .expect("standard layout")
        .par_chunks_mut(nx)
        .enumerate()
        .for_each(|(y, row)| {
            let base = level + c.gradient_y * (y as f64 - yc);
            for (x, v) in row.iter_mut().enumerate() {
                *v += (base + c.gradient_x * (x as f64 - xc)) as f32;
            }
        });
}

/// Beam transmissions (T_o, T_e).
pub fn throughput(calls: &EffectCalls, c: &ThroughputConfig) -> (f64, f64) {
    calls.hit(EffectKind::Throughput);
    (c.t_o, c.t_e)
}

/// Instrumental polarization as the constant it adds to F = (o - e)/(o + e): the whole
/// instrument rotates, so a polarization fixed in the instrument frame adds
/// q_inst = p cos 2(angle) at every rotator angle.
pub fn instrumental_polarization(calls: &EffectCalls, c: &PolConfig) -> f64 {
    calls.hit(EffectKind::InstrumentalPolarization);
    c.p * (2.0 * c.angle_deg.to_radians()).cos()
}

/// The instrument's true analyzer angle phi = s POSANG + theta0 (effect `analyzer_angle`:
/// the profile's zero-point and parity are then wrong by what the scene says).
pub fn analyzer_angle(calls: &EffectCalls, c: &AnalyzerAngleConfig, posang_deg: f64) -> f64 {
    calls.hit(EffectKind::AnalyzerAngle);
    c.parity as f64 * posang_deg + c.zero_point_deg
}

/// The sky-frame polarization the telescope adds to every source of a frame at parallactic
/// angle `eta_deg`: `p_tel (cos 2(eta + psi_tel), sin 2(eta + psi_tel))`.
pub fn telescope_polarization(calls: &EffectCalls, c: &TelescopePolConfig, eta_deg: f64) -> Polarization {
    calls.hit(EffectKind::TelescopePolarization);
    c.model().at(eta_deg)
}

/// The sky seen through the polarizing telescope: the sky already in `img` (uniform in o
/// and e) becomes `sky (1 + F_tel)` in the o strips and `sky (1 - F_tel)` in the e strips,
/// `F_tel = q_tel cos 2phi + u_tel sin 2phi` ([`crate::stokes::model::normalized_difference`]);
/// rows outside the strips are left as they are. Without a focal mask every pixel receives
/// both beams' sky, whose sum the telescope's polarization does not change: nothing to do.
pub fn telescope_polarization_sky(calls: &EffectCalls, img: &mut Array2<f32>, g: &Geometry, f_tel: f64) {
    calls.hit(EffectKind::TelescopePolarization);
    if !g.has_mask() {
        // Every pixel sees the sky through both beams: sky (1 + F)/2 + sky (1 - F)/2.
        return;
    }
    for (name, rows) in g.strips() {
        let factor = if name.starts_with("o_") {
            1.0 + f_tel
        } else {
            1.0 - f_tel
        };
        for y in rows[0]..rows[1].min(img.nrows()) {
            img.row_mut(y).mapv_inplace(|v| (v as f64 * factor) as f32);
        }
    }
}

/// Focal mask: zero every row outside the six strips.
pub fn strips(calls: &EffectCalls, img: &mut Array2<f32>, g: &Geometry) {
    calls.hit(EffectKind::Strips);
    for (y, mut row) in img.outer_iter_mut().enumerate() {
        if !g.row_in_strip(y) {
            row.fill(0.0);
        }
    }
}

/// measured = true (1 - c true), for positive values.
pub fn nonlinearity(calls: &EffectCalls, img: &mut Array2<f32>, c: f64) {
    calls.hit(EffectKind::Nonlinearity);
    img.par_mapv_inplace(|v| {
        if v > 0.0 {
            (v as f64 * (1.0 - c * v as f64)) as f32
        } else {
            v
        }
    });
}

/// Poisson noise of the photo-electrons: value (ADU) x gain_eff -> Poisson -> / gain_eff.
pub fn photon_noise(calls: &EffectCalls, img: &mut Array2<f32>, seed: u64, key: (u64, u64), gain_eff: f64) {
    calls.hit(EffectKind::PhotonNoise);
    noise_rows(img, seed, EffectKind::PhotonNoise, key, |r, v| {
        let e = *v as f64 * gain_eff;
        if e <= 0.0 {
            return;
        }
        let draw = if e >= POISSON_GAUSS_SWITCH_E {
            e + e.sqrt() * normal(r)
        } else {
            match Poisson::new(e) {
                Ok(p) => p.sample(r),
                Err(_) => e,
            }
        };
        *v = (draw / gain_eff) as f32;
    });
}

/// Gaussian read noise of `sigma_adu` (already divided by sqrt(NDIT)).
pub fn read_noise(calls: &EffectCalls, img: &mut Array2<f32>, seed: u64, key: (u64, u64), sigma_adu: f64) {
    calls.hit(EffectKind::ReadNoise);
    noise_rows(img, seed, EffectKind::ReadNoise, key, |r, v| {
        *v += (sigma_adu * normal(r)) as f32;
    });
}

/// Apply `f` to every pixel, rows in parallel, row `y` drawing from its own random stream
/// `stream(seed, kind, key.0, key.1, y)` (pixels in row order: results do not depend on
/// the thread count).
fn noise_rows<F>(img: &mut Array2<f32>, seed: u64, kind: EffectKind, key: (u64, u64), f: F)
where
    F: Fn(&mut Xoshiro256PlusPlus, &mut f32) + Sync,
{
    let nx = img.dim().1;
    img.as_slice_mut()
        .expect("standard layout")
        .par_chunks_mut(nx)
        .enumerate()
        .for_each(|(y, row)| {
            let mut r = stream(seed, kind, key.0, key.1, y as u64);
            for v in row.iter_mut() {
                f(&mut r, v);
            }
        });
}

/// Cosmic rays: Poisson(rate) hits, each a short track of 1-4 pixels. Returns pixels hit.
pub fn cosmic_rays(calls: &EffectCalls, img: &mut Array2<f32>, seed: u64, key: (u64, u64), c: &CosmicConfig) -> usize {
    calls.hit(EffectKind::CosmicRays);
    let (ny, nx) = img.dim();
    let mut r = stream(seed, EffectKind::CosmicRays, key.0, key.1, 0);
    let n = if c.rate_per_frame > 0.0 {
        Poisson::new(c.rate_per_frame)
            .map(|p| p.sample(&mut r) as usize)
            .unwrap_or(0)
    } else {
        0
    };
    let mut hit = 0;
    for _ in 0..n {
        let (mut y, mut x) = (r.random_range(0..ny) as i64, r.random_range(0..nx) as i64);
        let len = r.random_range(1..=4);
        let (dy, dx) = [(0, 1), (1, 0), (1, 1), (1, -1)][r.random_range(0..4)];
        let peak = c.peak_adu[0] + (c.peak_adu[1] - c.peak_adu[0]) * uniform(&mut r);
        for i in 0..len {
            if y >= 0 && x >= 0 && (y as usize) < ny && (x as usize) < nx {
                img[[y as usize, x as usize]] += (peak / (1.0 + i as f64)) as f32;
                hit += 1;
            }
            y += dy;
            x += dx;
        }
    }
    hit
}

/// Clip at the saturation level.
pub fn saturation(calls: &EffectCalls, img: &mut Array2<f32>, level: f64) {
    calls.hit(EffectKind::Saturation);
    let l = level as f32;
    img.par_mapv_inplace(|v| v.min(l));
}

pub use sofipol_calib::time::{iso_from_mjd, mjd_from_date_time};
