//! `sofipol bench sim|stages|accuracy`: benchmarks that print figures (medians of repeated
//! runs). Timing targets are checked here, never in unit tests.
use std::time::Instant;

use sofipol_calib::Profile;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{EffectKind, Scene, Simulator};

use crate::timing::median_ms;

/// Arguments of `sofipol bench accuracy` (the binary adds the reduction settings).
#[derive(clap::Args, Debug)]
pub struct AccuracyArgs {
    /// Targets per separation bin.
    #[arg(long, default_value_t = 24)]
    targets: usize,
    /// Seed (of the first night).
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Nights: the table pools this many seeds (seed, seed + 1, ...), each its own draws
    /// (one night's pull rms spreads by ~7 % at 24 targets a bin: judge over many).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..))]
    nights: u64,
    /// Simulate a pixel response non-uniformity of this rms (fraction, e.g. 0.01; no
    /// large-scale vignetting). 0: none.
    #[arg(long, default_value_t = 0.0)]
    pixel_response: f64,
    /// Flat field applied before the reduction: none, superflat (from the night's sky),
    /// dome (the nights get dome flats).
    #[arg(long, default_value = "none", value_parser = ["none", "superflat", "dome"])]
    flat: String,
    /// Hold the PSF fixed in shape (beta 3, no FWHM spread; only the 8 % seeing change).
    #[arg(long)]
    fixed_psf: bool,
    /// Write the full accuracy-against-time report (Markdown tables, JSON, PNG Pareto
    /// plots) of every trade-off into this directory instead of one table.
    #[arg(long, value_name = "DIR")]
    report: Option<std::path::PathBuf>,
    /// With --report: tiny sizes (a smoke test; the figures mean nothing).
    #[arg(long, requires = "report")]
    quick: bool,
}

const BENCH_SCENE: &str = r#"
name = "bench"
seed = 1
[observation]
orientations_deg = [0.0, 45.0]
dithers = 5
[[binary]]
name = "Bench Tau"
separation_arcsec = 2.0
pa_deg = 40.0
flux_a = 100000.0
flux_b = 50000.0
p_a = 0.05
gamma_a_deg = 30.0
p_b = 0.04
gamma_b_deg = 60.0
[[binary.field_star]]
separation_arcsec = 12.0
pa_deg = 250.0
flux = 30000.0
[[binary.field_star]]
separation_arcsec = 15.0
pa_deg = 80.0
flux = 20000.0
"#;

/// Median of `n` timings of frame simulation, ms (frames cycle through the sequence).
fn time_frames(effects: &[EffectKind], n: usize) -> (f64, f64) {
    let mut scene = Scene::from_toml(BENCH_SCENE, "bench scene").expect("valid bench scene");
    scene.effects = effects.to_vec();
    let t0 = Instant::now();
    let sim = Simulator::new(scene, Profile::sofi()).expect("valid");
    let setup_ms = t0.elapsed().as_secs_f64() * 1e3;
    let _warm = sim.frame(0, 0);
    let mut ts: Vec<f64> = (0..n)
        .map(|i| {
            let t = Instant::now();
            let f = sim.frame(0, i % sim.frames_per_target());
            let dt = t.elapsed().as_secs_f64() * 1e3;
            std::hint::black_box(&f);
            dt
        })
        .collect();
    ts.sort_by(|a, b| a.total_cmp(b));
    (ts[ts.len() / 2], setup_ms)
}

/// `sofipol bench sim`: one 1024x1024 frame with all effects, with none, and each effect
/// alone (medians of `repeats` frames).
pub fn sim(repeats: usize) {
    let threads = rayon::current_num_threads();
    println!("sofipol bench sim: one 1024x1024 frame, median of {repeats}, {threads} rayon threads");
    let (all, all_setup) = time_frames(&EffectKind::ALL, repeats);
    let (none, _) = time_frames(&[], repeats);
    println!(
        "  {:<28} {:>9.2} ms/frame   (one-off detector maps: {:.1} ms)",
        "all 15 effects", all, all_setup
    );
    println!("  {:<28} {:>9.2} ms/frame", "no effects", none);
    println!("  {:<28} {:>9}", "effect alone", "ms/frame (minus no-effect)");
    for k in EffectKind::ALL {
        let (t, setup) = time_frames(&[k], repeats);
        let extra = if setup > 1.0 {
            format!("   (setup {setup:.1} ms)")
        } else {
            String::new()
        };
        println!("  {:<28} {:>9.2} ms  (+{:.2}){extra}", k.name(), t, t - none);
    }
    println!(
        "target: all effects <= 50 ms/frame on 2 cores: {}",
        if all <= 50.0 { "met" } else { "NOT met" }
    );
}

/// `sofipol bench accuracy`: the pull table of one configuration, or with `--report` the
/// full accuracy-against-time report; `params` are the reduction settings.
pub fn accuracy(args: AccuracyArgs, params: &TargetParams) -> anyhow::Result<()> {
    let AccuracyArgs {
        targets,
        seed,
        nights,
        pixel_response,
        flat,
        fixed_psf,
        report,
        quick,
    } = args;
    if let Some(dir) = report {
        let command = sofipol_pipeline::build_info::command_line_string();
        let opts = crate::accuracy_report::ReportOptions {
            targets,
            seed,
            quick,
            command,
        };
        let t0 = Instant::now();
        crate::accuracy_report::run(&dir, params, &opts)?;
        println!(
            "sofipol bench accuracy: report written to {} in {:.1} s",
            dir.display(),
            t0.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    let cfg = crate::accuracy::AccuracyConfig::with_flat_field(
        crate::accuracy::AccuracyConfig {
            targets_per_bin: targets,
            seed,
            ..Default::default()
        },
        pixel_response,
        match flat.as_str() {
            "superflat" => crate::accuracy::FlatMode::Superflat,
            "dome" => crate::accuracy::FlatMode::Dome,
            _ => crate::accuracy::FlatMode::None,
        },
    );
    let cfg = if fixed_psf {
        crate::accuracy::AccuracyConfig {
            fwhm_spread_frac: 0.0,
            beta_range: None,
            ..cfg
        }
    } else {
        cfg
    };
    println!(
        "sofipol bench accuracy: {} nights (seeds {}-{}), {} targets per bin, seeing {}\" (FWHM spread +-{:.0} %, beta {:?}), pixel response {}, flat {:?}, effects [{}], method {:?}, aperture {} FWHM",
        nights,
        seed,
        seed + nights - 1,
        targets,
        cfg.fwhm_arcsec,
        100.0 * cfg.fwhm_spread_frac,
        cfg.beta_range.unwrap_or([3.0, 3.0]),
        pixel_response,
        cfg.flat,
        cfg.effects.join(", "),
        params.measure.method,
        params.measure.aperture_fwhm
    );
    let t0 = Instant::now();
    let seeds: Vec<u64> = (seed..seed + nights).collect();
    let (per_seed, pooled) = crate::accuracy::run_seeds(&cfg, params, &seeds);
    if nights > 1 {
        println!("rms pull per night (seeds {seeds:?}):");
        for (i, b) in pooled.iter().enumerate() {
            let rms: Vec<String> = per_seed.iter().map(|r| format!("{:.3}", r[i].rms_pull)).collect();
            println!("  {:>5.2}-{:<5.2}\"  {}", b.sep_arcsec.0, b.sep_arcsec.1, rms.join(" "));
        }
        println!("pooled over the {nights} nights:");
    }
    print!("{}", crate::accuracy::table(&pooled));
    println!("total {:.1} s (simulation included)", t0.elapsed().as_secs_f64());
    Ok(())
}

/// `sofipol bench stages`: the cost of each reduction stage on one simulated 10-frame
/// sequence (medians of `repeats`).
pub fn stages(repeats: usize) -> anyhow::Result<()> {
    use sofipol_calib::{badpix, fits, sky, stack};
    use sofipol_pipeline::reduce::{measure_sequence, target_entry, MeasureParams, SkySubtractedOrientation};
    let scene = Scene::from_toml(&crate::night::night_scene(1, 5), "bench").map_err(anyhow::Error::msg)?;
    let profile = Profile::sofi();
    let sim = Simulator::new(scene, profile.clone()).map_err(anyhow::Error::msg)?;
    let frames: Vec<_> = (0..sim.frames_per_target()).map(|k| sim.frame(0, k)).collect();
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("f.fits");
    println!(
        "sofipol bench stages: one sequence (2 orientations x 5 dithers, 1024x1024), median of {repeats}, {} threads",
        rayon::current_num_threads()
    );
    let w = median_ms(repeats, || {
        fits::write_frame(&path, &frames[0].frame, &Default::default()).expect("write")
    });
    let r = median_ms(repeats, || {
        std::hint::black_box(fits::read_frame(&path).expect("read"));
    });
    println!("  {:<44} {:>8.2} ms", "FITS write (f32, atomic, fsync) / frame", w);
    println!("  {:<44} {:>8.2} ms", "FITS read / frame", r);
    let all: Vec<&sofipol_calib::Frame> = frames.iter().map(|f| &f.frame).collect();
    let bp = median_ms(repeats, || {
        std::hint::black_box(badpix::detect_bad_pixels(&all, &profile, &Default::default()).expect("badpix"));
    });
    println!("  {:<44} {:>8.2} ms", "bad-pixel detection / sequence (10 frames)", bp);
    let (mask, _) = badpix::detect_bad_pixels(&all, &profile, &Default::default())?;
    let o0: Vec<sofipol_calib::Frame> = frames[..5]
        .iter()
        .map(|f| badpix::apply_mask(&f.frame, &mask))
        .collect::<Result<_, _>>()?;
    let views: Vec<ndarray::ArrayView2<f32>> = o0.iter().map(|f| f.data.view()).collect();
    let loo = median_ms(repeats, || {
        std::hint::black_box(stack::leave_one_out_medians(&views).expect("loo"));
    });
    println!("  {:<44} {:>8.2} ms", "leave-one-out medians / orientation (5)", loo);
    let g = &profile.geometry;
    let [r0, r1] = g.measured_rows();
    let cropped_profile = profile.cropped_rows(r0, r1);
    let o0c: Vec<sofipol_calib::Frame> = o0.iter().map(|f| f.crop_rows(r0, r1)).collect();
    let plain = sky::SkyOptions {
        cosmic_rays: None,
        ..Default::default()
    };
    let full = sky::SkyOptions::recommended();
    let rec = sky::SkyOptions::recommended();
    let s0 = median_ms(repeats, || {
        std::hint::black_box(sky::sky_subtract(&o0, &profile, &full).expect("sky"));
    });
    println!(
        "  {:<44} {:>8.2} ms",
        "sky subtraction / orientation, full frame, CR", s0
    );
    let s1 = median_ms(repeats, || {
        std::hint::black_box(sky::sky_subtract(&o0, &profile, &plain).expect("sky"));
    });
    let s2 = median_ms(repeats, || {
        std::hint::black_box(sky::sky_subtract(&o0c, &cropped_profile, &rec).expect("sky"));
    });
    println!("  {:<44} {:>8.2} ms", "sky subtraction / orientation, no CR flags", s1);
    println!(
        "  {:<44} {:>8.2} ms",
        "sky subtraction / orientation, target strips, CR", s2
    );
    let mut cal = Vec::new();
    for (i, chunk) in frames.chunks(5).enumerate() {
        let fr: Vec<sofipol_calib::Frame> = chunk
            .iter()
            .map(|f| badpix::apply_mask(&f.frame, &mask))
            .collect::<Result<_, _>>()?;
        cal.push(SkySubtractedOrientation {
            posang_deg: chunk[0].truth.posang_deg,
            analyzer_deg: chunk[0].truth.analyzer_deg,
            frames: sky::sky_subtract(&fr, &profile, &rec)?,
            offsets: chunk.iter().map(|f| f.truth.header_offset_px).collect(),
        });
        let _ = i;
    }
    let mp = MeasureParams::default();
    let m = median_ms(repeats, || {
        let m = measure_sequence(&cal, &profile, &mp).expect("measure");
        std::hint::black_box(target_entry("x", &cal, &m, &mp, &profile));
    });
    println!(
        "  {:<44} {:>8.2} ms",
        "find sources + photometry + Stokes / sequence", m
    );
    let per_seq = 10.0 * r + 2.0 * s2 + m;
    println!(
        "  => per sequence ~{per_seq:.0} ms of work (+ bad pixels {bp:.0} ms when detected per target); 49 sequences on 2 cores ~{:.1} s",
        49.0 * per_seq / 1000.0 / 2.0
    );
    Ok(())
}
