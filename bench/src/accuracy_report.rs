//! `sofipol bench accuracy --report DIR`: what accuracy costs in time, for every trade-off
//! the code offers, from one command. Writes `DIR/README.md` (tables), `DIR/results.json` and
//! PNG Pareto plots (error against time, the default marked).
//!
//! A trade-off is a [`Variant`]: a group, a name, the flags that reproduce it and a closure
//! that changes the simulated night ([`AccuracyConfig`]) and/or the reduction settings
//! ([`TargetParams`]). To add rows (e.g. calibration: none / superflat / dome flat,
//! standards / ratio method), push variants in [`variants`]; a new group gets its own table
//! and plot.
use std::path::Path;
use std::time::Instant;

use serde::Serialize;
use sofipol_calib::sky::{SkyEstimator, SkyScaling};
use sofipol_pipeline::photometry::{Method, PsfModel};
use sofipol_pipeline::plots::{Figure, LegendPos, Panel, Series, Style};
use sofipol_pipeline::reduce::TargetParams;

use crate::accuracy::{AccuracyConfig, BinReport};
use crate::accuracy_hwp::{HwpAccuracyConfig, HwpEstimate};

/// Changes a SOFI variant makes to the simulated night and to the reduction settings.
pub type ApplySofi = Box<dyn Fn(&mut AccuracyConfig, &mut TargetParams) + Sync + Send>;

/// Changes a half-wave-plate variant makes to its nights and their reduction.
pub type ApplyHwp = Box<dyn Fn(&mut HwpAccuracyConfig) + Sync + Send>;

/// Changes a variant makes to the simulated night and to the reduction settings.
pub enum Apply {
    /// A SOFI night of binaries ([`crate::accuracy`]).
    Sofi(ApplySofi),
    /// A half-wave-plate night of single stars ([`crate::accuracy_hwp`]).
    HalfWavePlate(ApplyHwp),
}

/// One row of the report.
pub struct Variant {
    /// Group (one table and one plot per group).
    pub group: &'static str,
    /// Short name.
    pub name: String,
    /// How to reproduce it with `sofipol bench accuracy` / `sofipol night`.
    pub flags: String,
    /// True for the shipped default of this group.
    pub is_default: bool,
    /// What the variant changes.
    pub apply: Apply,
}

fn v(
    group: &'static str,
    name: &str,
    flags: &str,
    is_default: bool,
    apply: impl Fn(&mut AccuracyConfig, &mut TargetParams) + Sync + Send + 'static,
) -> Variant {
    Variant {
        group,
        name: name.into(),
        flags: flags.into(),
        is_default,
        apply: Apply::Sofi(Box::new(apply)),
    }
}

fn h(
    group: &'static str,
    name: &str,
    flags: &str,
    is_default: bool,
    apply: impl Fn(&mut HwpAccuracyConfig) + Sync + Send + 'static,
) -> Variant {
    Variant {
        group,
        name: name.into(),
        flags: flags.into(),
        is_default,
        apply: Apply::HalfWavePlate(Box::new(apply)),
    }
}

/// Group of the reduction choices (x axis: reduction time per target).
pub const G_REDUCTION: &str = "reduction";
/// Group of the observing choices (x axis: exposure time per target).
pub const G_EXPOSURE: &str = "exposure";

/// Group of the flat-field choices on a night with a 1 % pixel response (x axis:
/// reduction time per target).
pub const G_FLAT: &str = "flat field";
/// Group of the instrumental calibration (x axis: reduction time per target).
pub const G_INSTRUMENT: &str = "instrument calibration";
/// Group of the interstellar foreground on a calibrated night seen through a foreground
/// field, with field stars (x axis: reduction time per target; error: the binaries'
/// intrinsic q, u).
pub const G_FOREGROUND: &str = "foreground";
/// Group of the half-wave-plate reduction's choices on simulated NIRC2 nights under pupil
/// tracking (single stars; x axis: reduction time per star).
pub const G_HWP: &str = "half-wave plate";
/// Group of the half-wave-plate observing choices: plate cycles per star (x axis: exposure
/// time per star).
pub const G_HWP_EXPOSURE: &str = "half-wave-plate cycles";

/// Nights of each half-wave-plate row (seeds `seed`, `seed + 1`, ...), each of
/// [`HwpAccuracyConfig::default`]'s 6 stars: 96 pulls per row.
pub const HWP_NIGHTS: u64 = 8;

/// Every trade-off of the report. The DIT of the simulated frames is 10 s (1 NDIT).
pub fn variants() -> Vec<Variant> {
    let mut out = vec![
        v(
            G_REDUCTION,
            "Moffat (beta from stacks; elliptical for PSF-fit pairs), o and e fitted jointly, exact 1-FWHM apertures, multiplicative sky + CR flags, target strips",
            "",
            true,
            |_, _| {},
        ),
        v(
            G_REDUCTION,
            "Gaussian PSF model",
            "--params: [measure.psf_model] kind=\"gaussian\"",
            false,
            |_, p| p.measure.psf_model = PsfModel::Gaussian,
        ),
        v(
            G_REDUCTION,
            "Moffat beta fitted per frame",
            "--params: [measure] beta_from_stack=false",
            false,
            |_, p| p.measure.beta_from_stack = false,
        ),
        v(
            G_REDUCTION,
            "o and e beams fitted separately (shape and pair geometry per beam)",
            "--params: [measure] joint_beams=false",
            false,
            |_, p| p.measure.joint_beams = false,
        ),
        v(
            G_REDUCTION,
            "circular Moffat for PSF-fit pairs (no ellipticity)",
            "--params: [measure] psf_elliptical=false",
            false,
            |_, p| p.measure.psf_elliptical = false,
        ),
        v(
            G_REDUCTION,
            "center-method apertures",
            "--method center",
            false,
            |_, p| p.measure.method = Method::Center,
        ),
        v(
            G_REDUCTION,
            "subpixel 5x5 apertures",
            "--method subpixel:5",
            false,
            |_, p| p.measure.method = Method::Subpixel(5),
        ),
        v(
            G_REDUCTION,
            "aperture 0.7 FWHM",
            "--aperture-fwhm 0.7",
            false,
            |_, p| p.measure.aperture_fwhm = 0.7,
        ),
        v(
            G_REDUCTION,
            "aperture 1.5 FWHM",
            "--aperture-fwhm 1.5",
            false,
            |_, p| p.measure.aperture_fwhm = 1.5,
        ),
        v(
            G_REDUCTION,
            "sky: additive scaling",
            "--params: [sky] scaling=\"additive\"",
            false,
            |_, p| p.sky.scaling = SkyScaling::Additive,
        ),
        v(
            G_REDUCTION,
            "sky: 3-sigma clipped mean of the other dithers",
            "--params: [sky] estimator=\"clipped_mean\"",
            false,
            |_, p| p.sky.estimator = SkyEstimator::ClippedMean,
        ),
        v(
            G_REDUCTION,
            "sky: median, sources of a first pass masked (second pass)",
            "--params: [sky] mask_sources=true",
            false,
            |_, p| p.sky.mask_sources = true,
        ),
        v(
            G_REDUCTION,
            "sky: clipped mean, sources masked (second pass)",
            "--params: [sky] estimator=\"clipped_mean\" mask_sources=true",
            false,
            |_, p| {
                p.sky.estimator = SkyEstimator::ClippedMean;
                p.sky.mask_sources = true;
            },
        ),
        v(
            G_REDUCTION,
            "sky: no cosmic-ray flags",
            "--params: [sky] without cosmic_rays",
            false,
            |_, p| p.sky.cosmic_rays = None,
        ),
        v(
            G_REDUCTION,
            "sky on full frames",
            "--params: full_frame_sky=true",
            false,
            |_, p| p.full_frame_sky = true,
        ),
        v(
            G_REDUCTION,
            "no field-star detection (these scenes have no field star: the detection's cost)",
            "--param measure.field_stars=false",
            false,
            |_, p| p.measure.field_stars = false,
        ),
    ];
    for d in 2..=5usize {
        out.push(v(
            G_EXPOSURE,
            &format!("2 orientations x {d} dithers"),
            &format!("scene [observation] dithers={d}"),
            d == 5,
            move |c, _| c.dithers = d,
        ));
    }
    for d in [3usize, 5] {
        out.push(v(
            G_EXPOSURE,
            &format!("4 orientations x {d} dithers"),
            &format!("scene [observation] orientations_deg=[0,45,90,135] dithers={d}"),
            false,
            move |c, _| {
                c.orientations_deg = vec![0.0, 45.0, 90.0, 135.0];
                c.dithers = d;
            },
        ));
    }
    out.extend(calibration_variants());
    out.extend(foreground_variants());
    out.extend(hwp_variants());
    out
}

/// Half-wave-plate rows: simulated NIRC2 nights under pupil tracking (the sky turning by
/// 0.1-3 deg per frame), 6 stars of (q, u) within +-3 % each, cosmic rays, reduced by the
/// single-pointing path; the settings the profile offers (`--set` of `sofipol night`), the
/// estimate read from the catalog, and the plate cycles per star.
fn hwp_variants() -> Vec<Variant> {
    let set = |sets: &'static [&'static str]| {
        move |c: &mut HwpAccuracyConfig| c.reduce_set.extend(sets.iter().map(|s| s.to_string()))
    };
    let mut out = vec![
        h(
            G_HWP,
            "complete cycles on the sky (each fitted at its frames' own angles) combined, error max(propagated, cycle scatter); matched sky frames; 9-px aperture",
            "night --profile nirc2 (the catalog's component)",
            true,
            |_| {},
        ),
        h(
            G_HWP,
            "least squares over every frame at its own angle on the sky (q, u, c), adopted error",
            "same night: catalog half_wave_plate.least_squares_sky",
            false,
            |c| c.estimate = HwpEstimate::LeastSquares,
        ),
        h(
            G_HWP,
            "sky: median of an annulus 14-24 px about each image (no sky frames)",
            "--set single_pointing.sky=\"annulus\" --set single_pointing.sky_annulus_px=[14,24]",
            false,
            set(&["single_pointing.sky=\"annulus\"", "single_pointing.sky_annulus_px=[14.0, 24.0]"]),
        ),
        h(
            G_HWP,
            "aperture 6 px (1.3 FWHM)",
            "--set single_pointing.aperture_px=[0,6]",
            false,
            set(&["single_pointing.aperture_px=[0.0, 6.0]"]),
        ),
        h(
            G_HWP,
            "aperture 13 px (2.8 FWHM)",
            "--set single_pointing.aperture_px=[0,13]",
            false,
            set(&["single_pointing.aperture_px=[0.0, 13.0]"]),
        ),
        h(
            G_HWP,
            "field rotation ignored (the sky taken as fixed on the detector)",
            "--set field_rotation.kind=\"sky_fixed\"",
            false,
            set(&["field_rotation.kind=\"sky_fixed\""]),
        ),
        h(
            G_HWP,
            "the default, on nights with 10 cosmic-ray hits per frame (10x the density of the other rows: a condition, not a choice)",
            "scene [cosmic_rays] rate_per_frame=10",
            false,
            |c| c.cosmic_rays_per_frame = 10.0,
        ),
    ];
    for n in 1..=3usize {
        out.push(h(
            G_HWP_EXPOSURE,
            &format!("{n} cycle(s) of 4 plate positions per star"),
            &format!("scene [half_wave_plate] cycles={n}"),
            n == 2,
            move |c| c.cycles = n,
        ));
    }
    out
}

/// Foreground rows: the binaries' intrinsic polarization on a calibrated night behind a
/// foreground that varies across the sky, with or without the field stars that measure it.
fn foreground_variants() -> Vec<Variant> {
    vec![
        v(
            G_FOREGROUND,
            "field stars measured, each binary's foreground subtracted",
            "night (default); catalog foreground and delta_gamma_fg_corrected_deg",
            true,
            |c, _| *c = AccuracyConfig::with_foreground(c.clone()),
        ),
        v(
            G_FOREGROUND,
            "no field stars: the foreground left in the binaries' q, u",
            "--param measure.field_stars=false",
            false,
            |c, p| {
                *c = AccuracyConfig::with_foreground(c.clone());
                p.measure.field_stars = false;
            },
        ),
    ]
}

/// Calibration rows: the flat on a night with a 1 % pixel response, and the
/// instrument (k = 0.97, p_inst 0.3 %, zero-point 3 deg) calibrated by standards (2
/// orientations) or cancelled by the ratio method (4 orientations, no calibration data).
fn calibration_variants() -> Vec<Variant> {
    use crate::accuracy::FlatMode;
    let flat = |m: FlatMode| {
        move |c: &mut AccuracyConfig, _: &mut TargetParams| *c = AccuracyConfig::with_flat_field(c.clone(), 0.01, m)
    };
    vec![
        v(
            G_FLAT,
            "1 % pixel response, no flat",
            "bench accuracy --pixel-response 0.01 --flat none; night --no-flat",
            false,
            flat(FlatMode::None),
        ),
        v(
            G_FLAT,
            "1 % pixel response, superflat",
            "bench accuracy --pixel-response 0.01 --flat superflat (night without dome flats)",
            true,
            flat(FlatMode::Superflat),
        ),
        v(
            G_FLAT,
            "1 % pixel response, dome flats",
            "bench accuracy --pixel-response 0.01 --flat dome (night with dome flats)",
            false,
            flat(FlatMode::Dome),
        ),
        v(
            G_INSTRUMENT,
            "k 0.97 + p_inst 0.3 % + theta0 3 deg, 2 orientations, no calibration (uncalibrated)",
            "night --no-calibration",
            false,
            |c, _| *c = AccuracyConfig::with_instrument(c.clone(), false),
        ),
        v(
            G_INSTRUMENT,
            "same, 2 orientations + 2 unpolarized and 2 polarized standards",
            "night (standards in the night)",
            true,
            |c, _| *c = AccuracyConfig::with_instrument(c.clone(), true),
        ),
        v(
            G_INSTRUMENT,
            "k 0.97 + p_inst 0.3 % (zero-point 0), 4 orientations, ratio method, no calibration data",
            "night, orientations 0/45/90/135 (--stokes-method auto or ratio)",
            false,
            |c, _| {
                *c = AccuracyConfig::with_instrument(c.clone(), false);
                c.orientations_deg = vec![0.0, 45.0, 90.0, 135.0];
                // Zero-point 0 as the label says: without a polarized standard nothing
                // measures it, and the ratio method cancels k and p_inst only.
                c.effects.retain(|e| e != "analyzer_angle");
            },
        ),
    ]
}

/// The figures of one variant.
#[derive(Debug, Clone, Serialize)]
pub struct VariantResult {
    /// Group.
    pub group: String,
    /// Name.
    pub name: String,
    /// Reproduce with.
    pub flags: String,
    /// Shipped default.
    pub is_default: bool,
    /// Exposure time per target, s (frames x DIT).
    pub exposure_s: f64,
    /// Mean over bins of the median reduction time per target, s.
    pub reduce_s: f64,
    /// rms of q - q_true, u - u_true over all bins.
    pub rms_error: f64,
    /// Per-bin figures.
    pub bins: Vec<BinReport>,
    /// On the Pareto front of its group (error against the group's cost).
    pub on_front: bool,
    /// Not on the front, but within the noise of it (`near_pareto`: no other variant is
    /// both `NEAR_COST` cheaper and `NEAR_ERROR` more accurate).
    pub near_front: bool,
}

/// One Monte-Carlo size.
#[derive(Debug, Clone, Serialize)]
pub struct McRow {
    /// Pairs simulated.
    pub pairs: u64,
    /// Wall time, s.
    pub seconds: f64,
    /// Largest binomial 1-sigma error of a bin's fraction of Pi(Delta gamma), relative.
    pub max_rel_err_expected: f64,
    /// rms over bins of the relative deviation from the exact (uniform) Pi(Delta gamma).
    pub rms_rel_dev_measured: f64,
    /// KS p-value of the reference sample against this run's CDF.
    pub ks_p: f64,
    /// |p - p_exact| (p_exact: against the exact uniform CDF).
    pub ks_p_err: f64,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// The command that made it.
    pub command: String,
    /// Targets per bin.
    pub targets_per_bin: usize,
    /// Bin edges, arcsec.
    pub bins_arcsec: Vec<f64>,
    /// Variants.
    pub variants: Vec<VariantResult>,
    /// Monte-Carlo sizes.
    pub mc: Vec<McRow>,
    /// Rayon threads.
    pub threads: usize,
    /// Nights of each half-wave-plate row.
    pub hwp_nights: u64,
    /// Stars per half-wave-plate night.
    pub hwp_stars: usize,
}

/// Settings of the report.
pub struct ReportOptions {
    /// Targets per separation bin.
    pub targets: usize,
    /// Seed.
    pub seed: u64,
    /// Tiny sizes (CI smoke test).
    pub quick: bool,
    /// The command line, for the provenance.
    pub command: String,
}

/// Relative cost difference within the timing noise of one report: variants that cannot
/// cost less than the default (other aperture methods, beta fitted per frame) come out up
/// to 3 % cheaper than it on the shared machine; 10 % is about 3 times that.
const NEAR_COST: f64 = 0.10;
/// Relative error difference within the noise of 6 binaries per bin: variants that change
/// nothing on most targets (additive scaling, narrower apertures) move the rms error by 1-2 %.
const NEAR_ERROR: f64 = 0.02;

/// Near the front: no other point is clearly better, i.e. more accurate by more than
/// NEAR_ERROR for at most NEAR_COST more cost, or cheaper by more than NEAR_COST for at most
/// NEAR_ERROR more error.
fn near_pareto(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(c, e)| {
            c.is_finite()
                && e.is_finite()
                && !points.iter().any(|&(c2, e2)| {
                    (c2 <= c * (1.0 + NEAR_COST) && e2 < e * (1.0 - NEAR_ERROR))
                        || (e2 <= e * (1.0 + NEAR_ERROR) && c2 < c * (1.0 - NEAR_COST))
                })
        })
        .collect()
}

fn pareto(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(c, e)| {
            c.is_finite() && e.is_finite() && !points.iter().any(|&(c2, e2)| c2 <= c && e2 <= e && (c2 < c || e2 < e))
        })
        .collect()
}

/// Run every variant and the Monte-Carlo sizes; write the report into `dir`.
pub fn run(dir: &Path, base: &TargetParams, opts: &ReportOptions) -> anyhow::Result<Report> {
    std::fs::create_dir_all(dir)?;
    let mut base_cfg = AccuracyConfig {
        targets_per_bin: opts.targets,
        seed: opts.seed,
        ..Default::default()
    };
    if opts.quick {
        base_cfg.bins_arcsec = vec![0.8, 1.2, 2.5, 4.0];
        base_cfg.targets_per_bin = opts.targets.min(1);
    }
    let dit_s = 10.0;
    let hwp_base = HwpAccuracyConfig {
        stars: if opts.quick {
            2
        } else {
            HwpAccuracyConfig::default().stars
        },
        ..Default::default()
    };
    let hwp_seeds: Vec<u64> = (opts.seed..opts.seed + if opts.quick { 1 } else { HWP_NIGHTS }).collect();
    let mut results = Vec::new();
    let vs = variants();
    for (i, var) in vs.iter().enumerate() {
        let t0 = Instant::now();
        let (bins, exposure_s) = match &var.apply {
            Apply::Sofi(apply) => {
                let mut cfg = base_cfg.clone();
                let mut params = base.clone();
                apply(&mut cfg, &mut params);
                let mut bins = crate::accuracy::run(&cfg, &params);
                if opts.quick {
                    // Only the first and last bins were asked for.
                    bins = bins.into_iter().step_by(2).collect();
                }
                (bins, (cfg.orientations_deg.len() * cfg.dithers) as f64 * dit_s)
            }
            Apply::HalfWavePlate(apply) => {
                let mut cfg = hwp_base.clone();
                apply(&mut cfg);
                let (bin, _) = crate::accuracy_hwp::run_seeds(&cfg, &hwp_seeds);
                (vec![bin], cfg.exposure_s())
            }
        };
        let (mut se, mut ne) = (0.0, 0usize);
        for b in bins.iter().filter(|b| b.n_pulls > 0) {
            se += b.rms_error * b.rms_error * b.n_pulls as f64;
            ne += b.n_pulls;
        }
        let reduce_s = bins.iter().map(|b| b.median_reduce_s).sum::<f64>() / bins.len().max(1) as f64;
        eprintln!(
            "[{}/{}] {:<10} {:<32} {:.1} s",
            i + 1,
            vs.len(),
            var.group,
            var.name,
            t0.elapsed().as_secs_f64()
        );
        results.push(VariantResult {
            group: var.group.to_string(),
            name: var.name.clone(),
            flags: var.flags.clone(),
            is_default: var.is_default,
            exposure_s,
            reduce_s,
            // Components lost count as unmeasured: no error to average (see `missing`).
            rms_error: if ne > 0 { (se / ne as f64).sqrt() } else { f64::NAN },
            bins,
            on_front: false,
            near_front: false,
        });
    }
    let groups: Vec<String> = {
        let mut g: Vec<String> = results.iter().map(|r| r.group.clone()).collect();
        g.dedup();
        g
    };
    for g in &groups {
        let idx: Vec<usize> = (0..results.len()).filter(|&i| &results[i].group == g).collect();
        let pts: Vec<(f64, f64)> = idx.iter().map(|&i| (cost(&results[i]), results[i].rms_error)).collect();
        for (k, (f, n)) in pareto(&pts).into_iter().zip(near_pareto(&pts)).enumerate() {
            results[idx[k]].on_front = f;
            results[idx[k]].near_front = n && !f;
        }
    }
    let sizes: Vec<u64> = if opts.quick {
        vec![1_000, 10_000]
    } else {
        vec![10_000, 100_000, 1_000_000, 10_000_000, 100_000_000]
    };
    let mc = mc_rows(&sizes, opts.seed)?;
    let report = Report {
        command: opts.command.clone(),
        targets_per_bin: base_cfg.targets_per_bin,
        bins_arcsec: base_cfg.bins_arcsec.clone(),
        variants: results,
        mc,
        threads: rayon::current_num_threads(),
        hwp_nights: hwp_seeds.len() as u64,
        hwp_stars: hwp_base.stars,
    };
    write_report(dir, &report)?;
    Ok(report)
}

/// The cost axis of a result: exposure time for observing choices, reduction time else.
fn cost(r: &VariantResult) -> f64 {
    if is_exposure_group(&r.group) {
        r.exposure_s
    } else {
        r.reduce_s
    }
}

/// Groups whose cost is the exposure time.
fn is_exposure_group(group: &str) -> bool {
    group == G_EXPOSURE || group == G_HWP_EXPOSURE
}

fn cost_label(group: &str) -> &'static str {
    match group {
        G_EXPOSURE => "exposure time per target, s",
        G_HWP_EXPOSURE => "exposure time per star, s",
        G_HWP => "reduction time per star, s (median night / stars)",
        _ => "reduction time per target, s (median, 2 workers)",
    }
}

/// Monte-Carlo cost: Pi(Delta gamma) of randomly oriented pairs (exactly uniform on
/// [0, 90] deg) from `pairs` simulated pairs.
fn mc_rows(sizes: &[u64], seed: u64) -> anyhow::Result<Vec<McRow>> {
    use sofipol_pipeline::stats::{ks_one_sample, simulate, AlignmentModel, McConfig};
    // Reference sample: 40 Delta-gamma values spread like a small catalog's, fixed.
    let sample: Vec<f64> = (0..40)
        .map(|i| 90.0 * ((i as f64 * 0.618_034 + 0.1) % 1.0).powf(1.3))
        .collect();
    let exact = ks_one_sample(&sample, |x: f64| (x / 90.0).clamp(0.0, 1.0)).p_value;
    let mut rows = Vec::new();
    for &n in sizes {
        let cfg = McConfig::geometry(AlignmentModel::Random, n, seed);
        let t0 = Instant::now();
        let out = simulate(&cfg).map_err(|e| anyhow::anyhow!("{e}"))?;
        let seconds = t0.elapsed().as_secs_f64();
        let h = &out.histogram;
        let fr = h.fractions();
        let nb = fr.len() as f64;
        let p0 = 1.0 / nb;
        let max_rel_err_expected = ((1.0 - p0) / (n as f64 * p0)).sqrt();
        let rms_rel_dev_measured = (fr.iter().map(|f| ((f - p0) / p0).powi(2)).sum::<f64>() / nb).sqrt();
        let ks_p = ks_one_sample(&sample, |x: f64| h.cdf(x)).p_value;
        rows.push(McRow {
            pairs: n,
            seconds,
            max_rel_err_expected,
            rms_rel_dev_measured,
            ks_p,
            ks_p_err: (ks_p - exact).abs(),
        });
    }
    Ok(rows)
}

fn fmt_bins(bins: &[BinReport], f: impl Fn(&BinReport) -> String) -> String {
    bins.iter()
        .map(|b| if b.n_pulls == 0 { "n/a".to_string() } else { f(b) })
        .collect::<Vec<_>>()
        .join(" ")
}

fn write_report(dir: &Path, r: &Report) -> anyhow::Result<()> {
    let mut md = String::new();
    md += "# What accuracy costs in time\n\n";
    md += &format!(
        "Made by `{}` ({} rayon threads). {} simulated binaries per separation bin (bins {} arcsec; seeing 0.8\" = 2.8 px varying +-20 % and Moffat beta 2.5-4 frame to frame, all effects of `sofipol bench accuracy`). \
         Errors are true errors against the simulation: `rms err` = rms of q - q_true and u - u_true over both components and all bins; \
         `pull` = (q - q_true)/sigma_q (1 = honest errors). Times are medians per target inside the harness on a shared machine: compare within one report. \
         Pareto: `front` = no other variant of the group is at least as good in both error and time; `near` = none is clearly better \
         (more than 2 % less error for at most 10 % more time, or more than 10 % less time for at most 2 % more error: \
         about the noise of the error with 6 binaries per bin and of the timing).\n\n",
        r.command,
        r.threads,
        r.targets_per_bin,
        r.bins_arcsec.iter().map(|b| format!("{b}")).collect::<Vec<_>>().join(", ")
    );
    let mut groups: Vec<&str> = r.variants.iter().map(|v| v.group.as_str()).collect();
    groups.dedup();
    for g in &groups {
        let rows: Vec<&VariantResult> = r.variants.iter().filter(|v| v.group == *g).collect();
        md += &format!("## {g}\n\n![{g}](pareto_{}.png)\n\n", g.replace(' ', "_"));
        if *g == G_FOREGROUND {
            md += "Nights calibrated by 2 unpolarized and 2 polarized standards and seen through a foreground field \
                   (mean 2 % at 60 deg, rms 0.4 % in q and in u, coherence 90\"), with field stars from a K-band luminosity function. \
                   Here the error is against each component's **intrinsic** q, u: the binary's measured foreground subtracted \
                   and its variance added to sigma. With field stars, a binary with too few usable ones has no estimate: \
                   its components count as `missing`; without field stars the foreground stays in every binary's q, u. \
                   The cost is the field stars' detection and photometry.\n\n";
            for v in &rows {
                let dg: Vec<f64> = v
                    .bins
                    .iter()
                    .flat_map(|b| b.delta_gamma_pulls.iter().copied())
                    .collect();
                if !dg.is_empty() {
                    let rms = (dg.iter().map(|x| x * x).sum::<f64>() / dg.len() as f64).sqrt();
                    md += &format!(
                        "- {}: Delta-gamma of the intrinsic angles, {} binaries with an estimate, rms pull {rms:.2}.\n",
                        v.name,
                        dg.len()
                    );
                }
            }
            md += "\n";
        }
        if *g == G_HWP || *g == G_HWP_EXPOSURE {
            md += &hwp_paragraph(r, g, &rows);
        }
        md += &format!(
            "| variant | flags | {} | rms err (1e-3) | rms pull per bin | median sigma_q per bin (1e-3) | rms err per bin (1e-3) | mean err per bin (1e-3) | missing | Pareto |\n|---|---|---|---|---|---|---|---|---|---|\n",
            if is_exposure_group(g) {
                "exposure s"
            } else if *g == G_HWP {
                "s / star"
            } else {
                "s / target"
            }
        );
        for v in rows {
            let name = if v.is_default {
                format!("**{} (default)**", v.name)
            } else {
                v.name.clone()
            };
            md += &format!(
                "| {name} | {} | {} | {:.3} | {} | {} | {} | {} | {} | {} |\n",
                if v.flags.is_empty() {
                    "-".to_string()
                } else {
                    format!("`{}`", v.flags)
                },
                if is_exposure_group(g) {
                    format!("{:.0} ({:.3} s cpu)", v.exposure_s, v.reduce_s)
                } else {
                    format!("{:.3}", v.reduce_s)
                },
                v.rms_error * 1e3,
                fmt_bins(&v.bins, |b| format!("{:.2}", b.rms_pull)),
                fmt_bins(&v.bins, |b| format!("{:.3}", b.median_sigma * 1e3)),
                fmt_bins(&v.bins, |b| format!("{:.3}", b.rms_error * 1e3)),
                fmt_bins(&v.bins, |b| format!("{:+.3}", b.mean_error * 1e3)),
                v.bins.iter().map(|b| b.missing).sum::<usize>(),
                if v.on_front {
                    "front"
                } else if v.near_front {
                    "near"
                } else {
                    ""
                }
            );
        }
        md += "\n";
        plot_group(dir, g, &r.variants)?;
    }
    md += "## Monte Carlo of Pi(Delta gamma): pairs against time\n\n![mc](mc_cost.png)\n\n";
    md += "Randomly oriented pairs (Pi(Delta gamma) exactly uniform on [0, 90] deg, so the error is measured against the truth). \
           Expected error: largest binomial 1-sigma error of a bin's fraction; measured: rms over bins of the relative deviation from uniform; \
           KS p: p-value of a fixed 40-value sample against the run's CDF, and its error against the exact CDF's p.\n\n";
    md += "| pairs | s | expected rel. error per bin | measured rms rel. deviation | KS p | KS p error |\n|---|---|---|---|---|---|\n";
    for m in &r.mc {
        md += &format!(
            "| {:.0e} | {:.3} | {:.2e} | {:.2e} | {:.4} | {:.1e} |\n",
            m.pairs as f64, m.seconds, m.max_rel_err_expected, m.rms_rel_dev_measured, m.ks_p, m.ks_p_err
        );
    }
    plot_mc(dir, &r.mc)?;
    write_atomic(&dir.join("README.md"), md.as_bytes())?;
    write_atomic(&dir.join("results.json"), serde_json::to_string_pretty(r)?.as_bytes())?;
    Ok(())
}

/// What the half-wave-plate groups simulate, and each row's pulls pooled over the nights
/// with their standard errors.
fn hwp_paragraph(r: &Report, g: &str, rows: &[&VariantResult]) -> String {
    let mut md = format!(
        "Simulated NIRC2 nights under pupil tracking (`bench/src/accuracy_hwp.rs`: the detector shrunk to 128 x 200 px, \
         L' frames of 45 coadds of 0.45 s, Gaussian images of FWHM 4.7 px, sky 5000 ADU polarized 1 % through the plate, \
         1 % pixel response, hot pixels, cosmic-ray hits {} per frame unless the row says otherwise), {} night(s) of {} stars each (4e6 ADU, q and u uniform \
         in +-3 %, the sky turning by 0.1-3 deg per frame), two cycles of sky frames and three darks per night; each night \
         written as FITS and reduced as `sofipol night DIR --profile nirc2` does (the small detector's `--set`s in \
         `SMALL_NIRC2`). One column per row: every star of every night pooled; the time is the median over the nights \
         of the reduction's wall time (reading the files included) divided by the stars.{}\n\n",
        HwpAccuracyConfig::default().cosmic_rays_per_frame,
        r.hwp_nights,
        r.hwp_stars,
        if g == G_HWP_EXPOSURE {
            " Exposure: DIT x coadds x frames per star."
        } else {
            ""
        }
    );
    for v in rows {
        if let Some(b) = v.bins.first().filter(|b| b.n_pulls > 0) {
            let n = b.n_pulls as f64;
            md += &format!(
                "- {}: {} pulls, rms {:.3} +- {:.3}, mean {:+.3} +- {:.3}; {} star(s) missing.\n",
                v.name,
                b.n_pulls,
                b.rms_pull,
                1.0 / (2.0 * n).sqrt(),
                b.mean_pull,
                1.0 / n.sqrt(),
                b.missing
            );
        }
    }
    md + "\n"
}

fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    Ok(sofipol_pipeline::io::write_atomic(path, bytes)?)
}

fn plot_group(dir: &Path, g: &str, all: &[VariantResult]) -> anyhow::Result<()> {
    let rows: Vec<&VariantResult> = all.iter().filter(|v| v.group == g).collect();
    let mut panel = Panel::new(
        format!("{g}: true error against cost (default = large marker)"),
        cost_label(g),
        "rms(q - q_true, u - u_true), 1e-3",
    )
    .legend(LegendPos::UpperRight);
    let mut front: Vec<(f64, f64)> = rows
        .iter()
        .filter(|v| v.on_front)
        .map(|v| (cost(v), v.rms_error * 1e3))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    panel = panel.with(
        Series::line(
            "Pareto front",
            front.iter().map(|p| p.0).collect(),
            front.iter().map(|p| p.1).collect(),
        )
        .style(Style::Dashed(1))
        .color(sofipol_pipeline::plots::Rgb(120, 120, 120)),
    );
    for (i, v) in rows.iter().enumerate() {
        if !v.rms_error.is_finite() {
            continue;
        }
        let label = if v.is_default {
            format!("{} (default)", v.name)
        } else {
            v.name.clone()
        };
        panel = panel.with(
            Series::line(label, vec![cost(v)], vec![v.rms_error * 1e3])
                .style(Style::Points(if v.is_default { 9 } else { 5 }))
                .color(sofipol_pipeline::plots::palette(i)),
        );
    }
    let xmax = rows.iter().map(|v| cost(v)).fold(0.0, f64::max);
    let ymax = rows
        .iter()
        .map(|v| v.rms_error * 1e3)
        .filter(|y| y.is_finite())
        .fold(0.0, f64::max);
    panel = panel
        .x_range(0.0, 1.6 * xmax.max(1e-9))
        .y_range(0.0, 1.1 * ymax.max(1e-9));
    Figure::single(panel).save_png(&dir.join(format!("pareto_{}.png", g.replace(' ', "_"))))?;
    Ok(())
}

fn plot_mc(dir: &Path, mc: &[McRow]) -> anyhow::Result<()> {
    let x: Vec<f64> = mc.iter().map(|m| (m.seconds.max(1e-6)).log10()).collect();
    let panel = Panel::new(
        "Monte Carlo: statistical error against time",
        "log10(wall time, s)",
        "log10(relative error)",
    )
    .legend(LegendPos::UpperRight)
    .with(Series::line(
        "Pi(Delta gamma) per bin, measured rms",
        x.clone(),
        mc.iter().map(|m| m.rms_rel_dev_measured.max(1e-12).log10()).collect(),
    ))
    .with(
        Series::line(
            "Pi(Delta gamma) per bin, binomial",
            x.clone(),
            mc.iter().map(|m| m.max_rel_err_expected.max(1e-12).log10()).collect(),
        )
        .style(Style::Dashed(2)),
    )
    .with(Series::line(
        "KS p-value error",
        x,
        mc.iter().map(|m| m.ks_p_err.max(1e-12).log10()).collect(),
    ));
    Figure::single(panel).save_png(&dir.join("mc_cost.png"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let f = pareto(&[(1.0, 5.0), (2.0, 3.0), (2.0, 4.0), (3.0, 3.0), (0.5, 9.0)]);
        assert_eq!(f, vec![true, true, false, false, true]);
        assert_eq!(pareto(&[(1.0, f64::NAN), (2.0, 1.0)]), vec![false, true]);
    }

    #[test]
    fn near_front_allows_only_the_noise() {
        // (2.0, 4.0): the same cost as (2.0, 3.0) and 33 % more error: not near.
        // (1.02, 5.05): 2 % / 1 % off (1.0, 5.0): near. (3.0, 3.05): 1.7 % more error than
        // (2.0, 3.0) at 1.5x its cost: not near. (2.1, 3.02): 5 % / 0.7 % off: near.
        let pts = [
            (1.0, 5.0),
            (2.0, 3.0),
            (2.0, 4.0),
            (1.02, 5.05),
            (3.0, 3.05),
            (3.0, 3.2),
            (2.1, 3.02),
        ];
        let near = near_pareto(&pts);
        assert_eq!(near, vec![true, true, false, true, false, false, true]);
        assert_eq!(near_pareto(&[(1.0, f64::NAN)]), vec![false]);
    }

    #[test]
    fn every_group_has_exactly_one_default() {
        let vs = variants();
        let mut groups: Vec<&str> = vs.iter().map(|v| v.group).collect();
        groups.dedup();
        for g in groups {
            assert_eq!(vs.iter().filter(|v| v.group == g && v.is_default).count(), 1, "{g}");
        }
    }
}
