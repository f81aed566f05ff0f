//! An accuracy harness that samples the world instead of our defaults.
//!
//! Every target of every separation bin draws its own observing conditions from the ranges
//! real SOFI nights show, is written to FITS (float or 16-bit) and is reduced through the
//! same file path as `sofipol night` ([`reduce_sequence`]):
//!
//! | condition | drawn from |
//! |---|---|
//! | seeing FWHM | 0.6-1.1", and +-20 % (2 sigma) frame to frame |
//! | Moffat beta | 2.5-4 per target |
//! | e-o beam offset | x -1..+1 px (tilt), y 165.5-168.5 px (the reducer starts from the profile's 0, 167) |
//! | primary position | x 250-774 px, y anywhere in the o-target strip with room for the pair |
//! | flux of A | 2e3-2e5 ADU, log-uniform; B 25-100 % of A |
//! | polarization | P 1-8 % each, angles uniform |
//! | orientations | 2 (0/45) or 4 (0/45/90/135), alternating |
//! | file format | BITPIX -32 or 16 (BZERO 32768), alternating |
//! | effects | psf, sky (gradient, 3 % level changes), strips, photon and read noise, bad pixels, transparency, pointing error, cosmic rays |
//!
//! Pulls are `(q - q_true)/sigma_q` and `(u - u_true)/sigma_u` of both components; the A/B
//! labels of the catalog are matched to the truth by position angle, and a swap of a pair
//! whose flux ratio is below [`RELABEL_RATIO`] is counted as a relabelling error.
use std::path::{Path, PathBuf};

use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use serde::Serialize;
use sofipol_calib::Profile;

use crate::catalog::Target;
use crate::reduce::run::reduce_sequence;
use crate::reduce::TargetParams;
use crate::sim::{Scene, Simulator, TargetTruth};
use crate::{scan, sequence};

/// A/B swaps of pairs fainter than this flux ratio B/A are labelling errors (closer to
/// equal, noise may legitimately reorder them).
pub const RELABEL_RATIO: f64 = 0.8;

/// What to draw.
#[derive(Debug, Clone)]
pub struct WorldConfig {
    /// Separation bin edges, arcsec.
    pub bins_arcsec: Vec<f64>,
    /// Targets per bin.
    pub targets_per_bin: usize,
    /// Seed.
    pub seed: u64,
    /// Scratch directory for the FITS frames (one sub-folder per target, removed after).
    pub work_dir: PathBuf,
    /// Lowest flux of A, ADU.
    pub min_flux_adu: f64,
}

impl WorldConfig {
    /// The default draw, frames under `work_dir`.
    pub fn new(work_dir: &Path) -> Self {
        WorldConfig {
            bins_arcsec: vec![0.5, 0.8, 1.2, 1.6, 2.5, 4.0, 5.3],
            targets_per_bin: 12,
            seed: 13,
            work_dir: work_dir.to_path_buf(),
            min_flux_adu: 2e3,
        }
    }
}

/// The conditions one target drew.
#[derive(Debug, Clone, Serialize)]
pub struct Conditions {
    /// Seeing FWHM, arcsec (median over frames).
    pub fwhm_arcsec: f64,
    /// Moffat beta.
    pub beta: f64,
    /// e-o offset (x, y), px.
    pub eo_offset_px: [f64; 2],
    /// Primary position (x, y) at zero offset, px.
    pub primary_xy_px: [f64; 2],
    /// Rotator angles.
    pub orientations_deg: Vec<f64>,
    /// BITPIX of the files.
    pub bitpix: i32,
}

/// One reduced target.
#[derive(Debug, Clone, Serialize)]
pub struct WorldTarget {
    /// Object name.
    pub object: String,
    /// True separation, arcsec.
    pub separation_arcsec: f64,
    /// Flux ratio B/A.
    pub flux_ratio: f64,
    /// Flux of A, ADU.
    pub flux_a_adu: f64,
    /// The conditions.
    pub conditions: Conditions,
    /// Pulls (q, u of A then B; only measured components).
    pub pulls: Vec<f64>,
    /// sigma_q of the measured components.
    pub sigmas: Vec<f64>,
    /// Components not measured.
    pub missing: usize,
    /// Catalog labels swapped against the truth for a pair of flux ratio below [`RELABEL_RATIO`].
    pub relabelled: bool,
    /// Catalog status and flags, for the report.
    pub note: String,
}

/// Pull statistics of one bin.
#[derive(Debug, Clone, Serialize)]
pub struct WorldBin {
    /// Bin edges, arcsec.
    pub sep_arcsec: (f64, f64),
    /// Pulls.
    pub n_pulls: usize,
    /// rms pull.
    pub rms_pull: f64,
    /// Mean pull.
    pub mean_pull: f64,
    /// Median sigma_q.
    pub median_sigma: f64,
    /// Components not measured.
    pub missing: usize,
    /// Pairs relabelled.
    pub relabelled: usize,
    /// The targets.
    pub targets: Vec<WorldTarget>,
}

fn draw_scene(cfg: &WorldConfig, bin: usize, t: usize, lo: f64, hi: f64) -> (Scene, Conditions, f64) {
    let mut r =
        rand::rngs::Xoshiro256PlusPlus::seed_from_u64(cfg.seed ^ ((bin as u64) << 32) ^ (t as u64 * 0x9E37_79B9));
    let sep = lo + (hi - lo) * r.random::<f64>();
    let fwhm = 0.6 + 0.5 * r.random::<f64>();
    let beta = 2.5 + 1.5 * r.random::<f64>();
    let eo = [-1.0 + 2.0 * r.random::<f64>(), 165.5 + 3.0 * r.random::<f64>()];
    let g = Profile::sofi().geometry;
    let margin = 30.0;
    let xy = [
        250.0 + 524.0 * r.random::<f64>(),
        g.o_target[0] as f64 + margin + (g.o_target[1] - g.o_target[0]) as f64 * 0.0 + {
            let span = (g.o_target[1] - g.o_target[0]) as f64 - 2.0 * margin;
            span * r.random::<f64>()
        },
    ];
    let fa = cfg.min_flux_adu * (2e5 / cfg.min_flux_adu).powf(r.random::<f64>());
    let ratio = 0.25 + 0.75 * r.random::<f64>();
    let (pa_, pb) = (0.01 + 0.07 * r.random::<f64>(), 0.01 + 0.07 * r.random::<f64>());
    let (ga, gb) = (180.0 * r.random::<f64>(), 180.0 * r.random::<f64>());
    let pa = 360.0 * r.random::<f64>();
    let orientations: Vec<f64> = if t % 2 == 0 {
        vec![0.0, 45.0]
    } else {
        vec![0.0, 45.0, 90.0, 135.0]
    };
    let bitpix = if (t / 2) % 2 == 0 { -32 } else { 16 };
    let text = format!(
        r#"name = "world{bin}_{t}"
seed = {seed}
effects = ["psf", "sky", "strips", "photon_noise", "read_noise", "bad_pixels", "transparency", "pointing_error", "cosmic_rays"]
[observation]
orientations_deg = {orientations:?}
dithers = 5
bitpix = {bitpix}
[psf]
kind = "moffat"
fwhm_arcsec = {fwhm}
beta = {beta}
seeing_rms_frac = 0.1
[transparency]
min = 0.9
[[binary]]
name = "W{bin}_{t}"
separation_arcsec = {sep}
pa_deg = {pa}
flux_a = {fa}
flux_b = {fb}
p_a = {pa_}
gamma_a_deg = {ga}
p_b = {pb}
gamma_b_deg = {gb}
x_px = {x}
y_px = {y}
"#,
        seed = cfg.seed.wrapping_mul(1000).wrapping_add((bin * 100 + t) as u64),
        fb = fa * ratio,
        x = xy[0],
        y = xy[1],
    );
    let scene = Scene::from_toml(&text, "world scene").expect("valid generated scene");
    let cond = Conditions {
        fwhm_arcsec: fwhm,
        beta,
        eo_offset_px: eo,
        primary_xy_px: xy,
        orientations_deg: orientations,
        bitpix,
    };
    (scene, cond, ratio)
}

/// Match the catalog's components to the truth and compute the pulls.
fn score(target: &Target, tt: &TargetTruth, ratio: f64) -> (Vec<f64>, Vec<f64>, usize, bool) {
    let found_pa = target.extra.get("pa_deg").and_then(|v| v.as_f64());
    let swapped = found_pa.is_some_and(|pa| {
        let d = (pa - tt.pa_deg).rem_euclid(360.0);
        d > 90.0 && d < 270.0
    });
    let mut truth = tt.components.clone();
    if swapped {
        truth.swap(0, 1);
    }
    let (mut pulls, mut sigmas, mut missing) = (Vec::new(), Vec::new(), 0);
    for (i, tc) in truth.iter().enumerate() {
        match target.components.get(i) {
            Some(c) if c.q.is_finite() && c.sigma_q > 0.0 && c.sigma_u > 0.0 => {
                pulls.push((c.q - tc.q) / c.sigma_q);
                pulls.push((c.u - tc.u) / c.sigma_u);
                sigmas.push(c.sigma_q);
            }
            _ => missing += 1,
        }
    }
    (pulls, sigmas, missing, swapped && ratio < RELABEL_RATIO)
}

/// Draw target `t` of bin `bin` (separations `lo`..`hi`) and write its frames and
/// truth.json into `dir` (e.g. to look at one case with `sofipol target`).
pub fn write_target(
    cfg: &WorldConfig,
    bin: usize,
    t: usize,
    lo: f64,
    hi: f64,
    dir: &Path,
) -> (TargetTruth, Conditions, f64) {
    let (scene, cond, ratio) = draw_scene(cfg, bin, t, lo, hi);
    let mut sim_profile = Profile::sofi();
    sim_profile.geometry.eo_offset_px = cond.eo_offset_px;
    let sim = Simulator::new(scene, sim_profile).expect("valid scene");
    let truth = sim.write_to_dir(dir, &|_| {}).expect("frames written");
    (truth.targets[0].clone(), cond, ratio)
}

fn one_target(cfg: &WorldConfig, params: &TargetParams, bin: usize, t: usize, lo: f64, hi: f64) -> WorldTarget {
    let dir = cfg.work_dir.join(format!("w{bin}_{t}"));
    let (tt, cond, ratio) = write_target(cfg, bin, t, lo, hi, &dir);
    let tt = &tt;
    // Reduce as `sofipol night` would: scan, classify, group, reduce from the files, with the
    // instrument profile's defaults (not the drawn e-o offset).
    let profile = Profile::sofi();
    let files = scan::find_files(&dir).expect("scratch folder");
    let s = scan::classify_all(&files, &profile);
    let seqs = sequence::group(s.science, &profile);
    let out = reduce_sequence(&seqs[0], &profile, params, None, None, false);
    let _ = std::fs::remove_dir_all(&dir);
    let (pulls, sigmas, missing, relabelled) = score(&out.target, tt, ratio);
    WorldTarget {
        object: tt.object.clone(),
        separation_arcsec: tt.separation_arcsec,
        flux_ratio: ratio,
        flux_a_adu: tt.components[0].flux,
        conditions: cond,
        pulls,
        sigmas,
        missing,
        relabelled,
        note: format!(
            "{:?} {} flags {:?} err {:?}",
            out.target.status,
            out.target
                .components
                .iter()
                .map(|c| format!("{}[{}]", c.name, c.flags.join(",")))
                .collect::<Vec<_>>()
                .join(" "),
            out.target.extra.get("flags"),
            out.target.error
        ),
    }
}

/// Draw, write, reduce and score every target, bin by bin (targets in parallel).
pub fn run(cfg: &WorldConfig, params: &TargetParams) -> Vec<WorldBin> {
    cfg.bins_arcsec
        .windows(2)
        .enumerate()
        .map(|(bin, w)| {
            let targets: Vec<WorldTarget> = (0..cfg.targets_per_bin)
                .into_par_iter()
                .map(|t| one_target(cfg, params, bin, t, w[0], w[1]))
                .collect();
            let pulls: Vec<f64> = targets.iter().flat_map(|t| t.pulls.iter().copied()).collect();
            let mut sig: Vec<f64> = targets.iter().flat_map(|t| t.sigmas.iter().copied()).collect();
            sig.sort_by(f64::total_cmp);
            let np = pulls.len().max(1) as f64;
            WorldBin {
                sep_arcsec: (w[0], w[1]),
                n_pulls: pulls.len(),
                rms_pull: (pulls.iter().map(|p| p * p).sum::<f64>() / np).sqrt(),
                mean_pull: pulls.iter().sum::<f64>() / np,
                median_sigma: sig.get(sig.len() / 2).copied().unwrap_or(f64::NAN),
                missing: targets.iter().map(|t| t.missing).sum(),
                relabelled: targets.iter().filter(|t| t.relabelled).count(),
                targets,
            }
        })
        .collect()
}

/// A table of the bins; with `detail`, one line per target whose worst pull exceeds 4 or
/// that lost a component.
pub fn table(bins: &[WorldBin], detail: bool) -> String {
    let mut s = format!(
        "{:>11} {:>6} {:>9} {:>9} {:>10} {:>8} {:>10}\n",
        "sep [\"]", "pulls", "rms pull", "mean", "med sig_q", "missing", "relabelled"
    );
    for b in bins {
        s += &format!(
            "{:>5.2}-{:<5.2} {:>6} {:>9.3} {:>9.3} {:>10.5} {:>8} {:>10}\n",
            b.sep_arcsec.0, b.sep_arcsec.1, b.n_pulls, b.rms_pull, b.mean_pull, b.median_sigma, b.missing, b.relabelled
        );
        if detail {
            for t in &b.targets {
                let worst = t.pulls.iter().fold(0.0f64, |a, p| a.max(p.abs()));
                if worst > 4.0 || t.missing > 0 || t.relabelled {
                    s += &format!(
                        "    {} sep {:.2}\" A {:.0} ADU B/A {:.2} {:?}: worst pull {:.1}, missing {} | {}\n",
                        t.object,
                        t.separation_arcsec,
                        t.flux_a_adu,
                        t.flux_ratio,
                        t.conditions,
                        worst,
                        t.missing,
                        t.note
                    );
                }
            }
        }
    }
    s
}
