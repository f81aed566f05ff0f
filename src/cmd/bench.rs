//! `sofipol bench ...`: benchmarks that print figures (medians of repeated runs).
//! Timing targets are checked here, never in unit tests.
use std::process::ExitCode;
use std::time::Instant;

use sofipol_calib::Profile;
use sofipol_pipeline::sim::{EffectKind, Scene, Simulator};

/// Arguments of `sofipol bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(clap::Subcommand, Debug)]
enum What {
    /// Simulator: one 1024x1024 frame with all effects, with none, and each effect alone.
    Sim {
        /// Frames timed per configuration (the median is reported).
        #[arg(long, default_value_t = 21)]
        repeats: usize,
    },
    /// A 49-target night (490 frames of 1024x1024): simulate it (not timed), then time
    /// `sofipol night` on it in a child process: wall and CPU time, per-stage breakdown, peak
    /// RSS, and right after each run the `cat` floor (time `cat` needs to read the same files,
    /// page cache warm) and the ratio wall / cat.
    Night {
        /// Targets.
        #[arg(long, default_value_t = 49)]
        targets: usize,
        /// Worker threads for the reduction (default: all cores).
        #[arg(long)]
        jobs: Option<usize>,
        /// Repeats of the reduction (median reported).
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        /// Keep the simulated night here instead of a temporary directory (a night simulated
        /// there earlier with the same --targets is reused).
        #[arg(long)]
        dir: Option<std::path::PathBuf>,
        /// Add 3 standard stars (2 unpolarized, 1 polarized, from the built-in table) and the
        /// instrumental effects they calibrate (k = 0.97, p_inst 0.3 %, zero-point 3 deg):
        /// shows what calibration adds to the night.
        #[arg(long)]
        with_standards: bool,
    },
    /// Cost of each reduction stage on one simulated 10-frame sequence (medians).
    Stages {
        /// Repeats per stage.
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// Reduction accuracy on simulated nights: pull widths by separation bin, and time.
    Accuracy {
        /// Targets per separation bin.
        #[arg(long, default_value_t = 24)]
        targets: usize,
        /// Seed.
        #[arg(long, default_value_t = 7)]
        seed: u64,
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
        #[command(flatten)]
        reduce: super::target::ReduceArgs,
    },
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

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    match args.what {
        What::Sim { repeats } => {
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
        What::Night {
            targets,
            jobs,
            repeats,
            dir,
            with_standards,
        } => bench_night(targets, jobs, repeats, dir, with_standards)?,
        What::Stages { repeats } => bench_stages(repeats)?,
        What::Accuracy {
            targets,
            seed,
            report: Some(dir),
            quick,
            reduce,
            ..
        } => {
            let params = reduce.params()?;
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let opts = super::accuracy_report::ReportOptions {
                targets,
                seed,
                quick,
                command,
            };
            let t0 = Instant::now();
            super::accuracy_report::run(&dir, &params, &opts)?;
            println!(
                "sofipol bench accuracy: report written to {} in {:.1} s",
                dir.display(),
                t0.elapsed().as_secs_f64()
            );
        }
        What::Accuracy {
            targets,
            seed,
            report: None,
            reduce,
            pixel_response,
            flat,
            fixed_psf,
            ..
        } => {
            let params = reduce.params()?;
            let cfg = sofipol_pipeline::accuracy::AccuracyConfig::with_flat_field(
                sofipol_pipeline::accuracy::AccuracyConfig {
                    targets_per_bin: targets,
                    seed,
                    ..Default::default()
                },
                pixel_response,
                match flat.as_str() {
                    "superflat" => sofipol_pipeline::accuracy::FlatMode::Superflat,
                    "dome" => sofipol_pipeline::accuracy::FlatMode::Dome,
                    _ => sofipol_pipeline::accuracy::FlatMode::None,
                },
            );
            let cfg = if fixed_psf {
                sofipol_pipeline::accuracy::AccuracyConfig {
                    fwhm_spread_frac: 0.0,
                    beta_range: None,
                    ..cfg
                }
            } else {
                cfg
            };
            println!(
                "sofipol bench accuracy: {} targets per bin, seeing {}\" (FWHM spread +-{:.0} %, beta {:?}), pixel response {}, flat {:?}, effects [{}], method {:?}, aperture {} FWHM",
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
            let r = sofipol_pipeline::accuracy::run(&cfg, &params);
            print!("{}", sofipol_pipeline::accuracy::table(&r));
            println!("total {:.1} s (simulation included)", t0.elapsed().as_secs_f64());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// A night of `n` binaries like the reference study's: separations 0.5-5.3", K-band fluxes
/// and polarizations spread as in a real sample, realistic effects.
pub fn night_scene(n: usize, seed: u64) -> String {
    let mut s = format!(
        "name = \"bench\"\nseed = {seed}\neffects = [\"psf\", \"sky\", \"strips\", \"photon_noise\", \"read_noise\", \"bad_pixels\", \"transparency\", \"pointing_error\", \"cosmic_rays\"]\n[psf]\nkind = \"moffat\"\nfwhm_arcsec = 0.8\n"
    );
    for i in 0..n {
        let f = i as f64 / n.max(1) as f64;
        s += &format!(
            "[[binary]]\nname = \"Bench {i:02}\"\nseparation_arcsec = {:.3}\npa_deg = {:.1}\nflux_a = {:.0}\nflux_b = {:.0}\np_a = {:.4}\ngamma_a_deg = {:.1}\np_b = {:.4}\ngamma_b_deg = {:.1}\n",
            0.5 + 4.8 * f,
            (i * 47 % 360) as f64,
            60000.0 + 90000.0 * ((i * 7 % 10) as f64 / 10.0),
            30000.0 + 50000.0 * ((i * 3 % 10) as f64 / 10.0),
            0.01 + 0.06 * ((i * 5 % 11) as f64 / 11.0),
            (i * 37 % 180) as f64,
            0.01 + 0.06 * ((i * 9 % 11) as f64 / 11.0),
            (i * 71 % 180) as f64
        );
    }
    s
}

fn bench_night(
    targets: usize,
    jobs: Option<usize>,
    repeats: usize,
    dir: Option<std::path::PathBuf>,
    with_standards: bool,
) -> anyhow::Result<()> {
    use anyhow::Context;
    let tmp = tempfile::tempdir()?;
    let keep = dir.is_some();
    let root = dir.unwrap_or_else(|| tmp.path().to_path_buf());
    let raw = root.join("raw");
    let mut text = night_scene(targets, 2001);
    if with_standards {
        text = text.replacen(
            "\"cosmic_rays\"]",
            "\"cosmic_rays\", \"throughput\", \"instrumental_polarization\", \"analyzer_angle\"]",
            1,
        );
        text += "[throughput]\nt_e = 0.97\n[instrumental_polarization]\np = 0.003\nangle_deg = 0.0\n[analyzer_angle]\nzero_point_deg = 3.0\n";
        text +=
            "[[standard]]\nname = \"HD 64299\"\nflux = 150000.0\n[[standard]]\nname = \"HD 98161\"\nflux = 150000.0\n";
        text += "[[standard]]\nname = \"HD 204827\"\nflux = 150000.0\np = 0.0084\ngamma_deg = 58.7\n";
    }
    let reuse = raw.join(".bench-night-complete");
    let tag = format!("{targets}{}\n", if with_standards { " with standards" } else { "" });
    if std::fs::read_to_string(&reuse).ok().as_deref() == Some(tag.as_str()) {
        println!(
            "sofipol bench night: reusing the {targets}-target night simulated earlier in {}",
            raw.display()
        );
    } else {
        let scene = Scene::from_toml(&text, "bench night").map_err(anyhow::Error::msg)?;
        let t0 = Instant::now();
        let truth = super::simulate::simulate_into(scene, Profile::sofi(), &raw, None, true)?;
        std::fs::remove_file(raw.join("truth.json")).ok();
        let nframes: usize = truth.targets.iter().map(|t| t.frames.len()).sum();
        println!("sofipol bench night: simulated {targets} targets, {nframes} frames (1024x1024 f32) in {:.1} s (not timed below)", t0.elapsed().as_secs_f64());
        if keep {
            std::fs::write(&reuse, &tag)?;
        }
    }
    let exe = std::env::current_exe().context("locating the sofipol executable")?;
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(&raw)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "fits"))
        .collect();
    files.sort();
    let bytes: u64 = files.iter().filter_map(|p| p.metadata().ok()).map(|m| m.len()).sum();
    let mut runs: Vec<NightRun> = Vec::new();
    let mut last = String::new();
    for r in 0..repeats.max(1) {
        let out = root.join(format!("catalog{r}.json"));
        let mut cmd = std::process::Command::new(&exe);
        cmd.arg("night")
            .arg(&raw)
            .arg("-o")
            .arg(&out)
            .arg("-q")
            .arg("-v")
            .arg("--no-png");
        if let Some(j) = jobs {
            cmd.arg("--jobs").arg(j.to_string());
        }
        let t = Instant::now();
        let o = cmd.output().context("running sofipol night")?;
        let wall = t.elapsed().as_secs_f64();
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        anyhow::ensure!(
            o.status.code() == Some(0) || o.status.code() == Some(2),
            "sofipol night failed: {stderr}"
        );
        // The floors, in the same run, page cache warm (the reduction just read the files).
        let cat = cat_floor(&files)?;
        let read = read_floor(&files)?;
        last = stderr.clone();
        runs.push(NightRun {
            wall,
            cat,
            read,
            stages: parse_stage_line(&stderr),
        });
    }
    let med = |f: &dyn Fn(&NightRun) -> f64| -> f64 {
        let mut v: Vec<f64> = runs.iter().map(f).filter(|x| x.is_finite()).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let list = |f: &dyn Fn(&NightRun) -> f64| -> String {
        runs.iter()
            .map(|r| format!("{:.2}", f(r)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let n = runs.len();
    println!(
        "  files: {} ({:.0} MB); medians over {n} runs, each run = reduction + floors right after it",
        files.len(),
        bytes as f64 / 1e6
    );
    for line in last
        .lines()
        .filter(|l| l.contains("stage time") || l.contains("calibration") || l.starts_with("flats: "))
    {
        println!("  last run: {line}");
    }
    println!(
        "  reduction wall (child process, incl. start-up): {:.2} s   [{}]",
        med(&|r| r.wall),
        list(&|r| r.wall)
    );
    println!(
        "  reduction CPU (user+sys):                       {:.2} s   [{}]",
        med(&|r| r.stages.get("cpu")),
        list(&|r| r.stages.get("cpu"))
    );
    println!(
        "  `cat` floor (cat FILES > /dev/null):             {:.3} s  [{}]",
        med(&|r| r.cat),
        runs.iter()
            .map(|r| format!("{:.3}", r.cat))
            .collect::<Vec<_>>()
            .join(" ")
    );
    println!(
        "  in-process read floor (std::fs::read each file): {:.3} s  [{}]",
        med(&|r| r.read),
        runs.iter()
            .map(|r| format!("{:.3}", r.read))
            .collect::<Vec<_>>()
            .join(" ")
    );
    println!(
        "  ratio wall / cat (per run, same run):           {:.1}x  [{}]",
        med(&|r| r.wall / r.cat),
        runs.iter()
            .map(|r| format!("{:.1}", r.wall / r.cat))
            .collect::<Vec<_>>()
            .join(" ")
    );
    println!(
        "  ratio CPU / cat:                                 {:.1}x",
        med(&|r| r.stages.get("cpu") / r.cat)
    );
    print_stages(&runs);
    println!(
        "  peak RSS: {:.0} MB (max over runs)",
        runs.iter().map(|r| r.stages.get("rss")).fold(0.0, f64::max)
    );
    println!("  Python reference: no expert Python reduction of a night is in this repository; not compared");
    println!("  targets (issue 10): wall <= 5x cat, peak RSS <= 1 GB");
    Ok(())
}

/// Median per-stage times and the cost of calibration (issue 8: <= 15 % of the night).
fn print_stages(runs: &[NightRun]) {
    let med = |f: &dyn Fn(&NightRun) -> f64| -> f64 {
        let mut v: Vec<f64> = runs.iter().map(f).filter(|x| x.is_finite()).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let g = |r: &NightRun, k: &str| r.stages.get(k);
    println!(
        "  stage times (s, wall time per target summed over targets, both workers; median): read {:.2}, bad pixels {:.2}, flat {:.2}, sky {:.2}, measure {:.2}, write {:.2}",
        med(&|r| g(r, "read")),
        med(&|r| g(r, "bad pixels")),
        med(&|r| g(r, "flat")),
        med(&|r| g(r, "sky")),
        med(&|r| g(r, "measure")),
        med(&|r| g(r, "write"))
    );
    // Share of the night: the flat stage's share of the summed stage times, plus the
    // night-wide steps (flat build, standards: run on the whole pool) as a share of the wall.
    let share = |r: &NightRun| {
        let stages: f64 = ["read", "bad pixels", "flat", "sky", "measure", "write"]
            .iter()
            .map(|k| g(r, k))
            .filter(|v| v.is_finite())
            .sum();
        let build = g(r, "flat build").max(0.0) + g(r, "calibration").max(0.0);
        100.0 * (g(r, "flat") / stages + build / g(r, "wall"))
    };
    println!(
        "  calibration (issue 8: <= 15 % of the night): flat build {:.2} s + flat stage {:.2} s + standards {:.2} s = {:.1} % of the night (median)",
        med(&|r| g(r, "flat build")),
        med(&|r| g(r, "flat")),
        med(&|r| g(r, "calibration")),
        med(&share)
    );
}

/// One repeat of `bench night`.
struct NightRun {
    wall: f64,
    cat: f64,
    read: f64,
    stages: StageLine,
}

/// The figures of the child's `-v` line.
#[derive(Default)]
struct StageLine(Vec<(String, f64)>);

impl StageLine {
    fn get(&self, k: &str) -> f64 {
        self.0.iter().find(|(n, _)| n == k).map_or(f64::NAN, |(_, v)| *v)
    }
}

/// Parses `stage time summed over targets: read 0.94 s, ...; cpu 3.1 s; peak RSS 145 MB`.
fn parse_stage_line(stderr: &str) -> StageLine {
    let Some(line) = stderr.lines().find(|l| l.contains("stage time")) else {
        return StageLine::default();
    };
    let body = line.split_once(':').map_or(line, |(_, b)| b);
    let mut out = Vec::new();
    for part in body.split([',', ';']) {
        let words: Vec<&str> = part.split_whitespace().collect();
        // "<name words> <value> <unit>"
        if words.len() >= 3 {
            if let Ok(v) = words[words.len() - 2].parse::<f64>() {
                let name = words[..words.len() - 2].join(" ");
                let name = if name == "peak RSS" { "rss".to_string() } else { name };
                out.push((name, v));
            }
        }
    }
    // `flats: superflat in 0.59 s` (the night's flats, built before the targets).
    if let Some(v) = stderr
        .lines()
        .find_map(|l| l.strip_prefix("flats: "))
        .and_then(|l| l.rsplit_once(" in "))
        .and_then(|(_, t)| t.trim_end_matches(" s").trim().parse::<f64>().ok())
    {
        out.push(("flat build".into(), v));
    }
    StageLine(out)
}

/// Seconds `cat` needs to read `files` to /dev/null (one process, like `cat *.fits`).
fn cat_floor(files: &[std::path::PathBuf]) -> anyhow::Result<f64> {
    use anyhow::Context;
    let t = Instant::now();
    let st = std::process::Command::new("cat")
        .args(files)
        .stdout(std::process::Stdio::null())
        .status()
        .context("running cat")?;
    anyhow::ensure!(st.success(), "cat failed");
    Ok(t.elapsed().as_secs_f64())
}

/// Seconds to read every file fully into memory, in this process, one thread.
fn read_floor(files: &[std::path::PathBuf]) -> anyhow::Result<f64> {
    use std::io::Read;
    let t = Instant::now();
    let mut buf = Vec::new();
    let mut total = 0usize;
    for f in files {
        buf.clear();
        total += std::fs::File::open(f)?.read_to_end(&mut buf)?;
    }
    std::hint::black_box(total);
    Ok(t.elapsed().as_secs_f64())
}

fn bench_stages(repeats: usize) -> anyhow::Result<()> {
    use sofipol_calib::{badpix, fits, sky, stack};
    use sofipol_pipeline::reduce::{measure_sequence, target_entry, CalibratedOrientation, MeasureParams};
    let scene = Scene::from_toml(&night_scene(1, 5), "bench").map_err(anyhow::Error::msg)?;
    let profile = Profile::sofi();
    let sim = Simulator::new(scene, profile.clone()).map_err(anyhow::Error::msg)?;
    let frames: Vec<_> = (0..sim.frames_per_target()).map(|k| sim.frame(0, k)).collect();
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("f.fits");
    println!(
        "sofipol bench stages: one sequence (2 orientations x 5 dithers, 1024x1024), median of {repeats}, {} threads",
        rayon::current_num_threads()
    );
    let w = stack::median_ms(repeats, || {
        fits::write_frame(&path, &frames[0].frame, &Default::default()).expect("write")
    });
    let r = stack::median_ms(repeats, || {
        std::hint::black_box(fits::read_frame(&path).expect("read"));
    });
    println!("  {:<44} {:>8.2} ms", "FITS write (f32, atomic, fsync) / frame", w);
    println!("  {:<44} {:>8.2} ms", "FITS read / frame", r);
    let all: Vec<&sofipol_calib::Frame> = frames.iter().map(|f| &f.frame).collect();
    let bp = stack::median_ms(repeats, || {
        std::hint::black_box(badpix::detect_bad_pixels(&all, &profile, &Default::default()).expect("badpix"));
    });
    println!("  {:<44} {:>8.2} ms", "bad-pixel detection / sequence (10 frames)", bp);
    let (mask, _) = badpix::detect_bad_pixels(&all, &profile, &Default::default())?;
    let o0: Vec<sofipol_calib::Frame> = frames[..5]
        .iter()
        .map(|f| badpix::apply_mask(&f.frame, &mask))
        .collect::<Result<_, _>>()?;
    let views: Vec<ndarray::ArrayView2<f32>> = o0.iter().map(|f| f.data.view()).collect();
    let loo = stack::median_ms(repeats, || {
        std::hint::black_box(stack::leave_one_out_medians(&views).expect("loo"));
    });
    println!("  {:<44} {:>8.2} ms", "leave-one-out medians / orientation (5)", loo);
    let g = &profile.geometry;
    let (r0, r1) = (g.o_target[0], g.e_target[1]);
    let cropped_profile = profile.cropped_rows(r0, r1);
    let o0c: Vec<sofipol_calib::Frame> = o0.iter().map(|f| f.crop_rows(r0, r1)).collect();
    let plain = sky::SkyOptions {
        cosmic_rays: None,
        ..Default::default()
    };
    let full = sky::SkyOptions::recommended();
    let rec = sky::SkyOptions::recommended();
    let s0 = stack::median_ms(repeats, || {
        std::hint::black_box(sky::sky_subtract(&o0, &profile, &full).expect("sky"));
    });
    println!(
        "  {:<44} {:>8.2} ms",
        "sky subtraction / orientation, full frame, CR", s0
    );
    let s1 = stack::median_ms(repeats, || {
        std::hint::black_box(sky::sky_subtract(&o0, &profile, &plain).expect("sky"));
    });
    let s2 = stack::median_ms(repeats, || {
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
        cal.push(CalibratedOrientation {
            posang_deg: chunk[0].truth.posang_deg,
            analyzer_deg: chunk[0].truth.analyzer_deg,
            frames: sky::sky_subtract(&fr, &profile, &rec)?,
            offsets: chunk.iter().map(|f| f.truth.header_offset_px).collect(),
        });
        let _ = i;
    }
    let mp = MeasureParams::default();
    let m = stack::median_ms(repeats, || {
        let m = measure_sequence(&cal, &profile, &mp).expect("measure");
        std::hint::black_box(target_entry("x", &cal, &m, &mp));
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
