//! `sofipol bench night`: a 49-target night (half float, half 16-bit frames) reduced by
//! `sofipol night` in a child process against the `cat` floor and, with `--python`, against
//! the expert Python reduction of bench/python/ (timed in the same run, catalogs compared).
//! The child is the current executable ([`std::env::current_exe`]): [`run`] is meant to be
//! called from the `sofipol` binary.
use std::time::Instant;

use sofipol_calib::Profile;
use sofipol_pipeline::sim::{Scene, Simulator};

use crate::python::{print_python, run_python, NightSummary};

/// Arguments of `sofipol bench night`.
#[derive(clap::Args, Debug, Clone)]
pub struct NightArgs {
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
    /// there earlier with the same --targets, standards and pixel types is reused).
    #[arg(long)]
    dir: Option<std::path::PathBuf>,
    /// Add 3 standard stars (2 unpolarized, 1 polarized, from the built-in table) and the
    /// instrumental effects they calibrate (k = 0.97, p_inst 0.3 %, zero-point 3 deg):
    /// shows what calibration adds to the night.
    #[arg(long)]
    with_standards: bool,
    /// Python interpreter with numpy, scipy, astropy and photutils: also time the expert
    /// Python reduction (bench/python/reduce_night.py) on the same night, print the ratios
    /// and compare its q, u with sofipol's (default: $SOFIPOL_PYTHON; not run without).
    #[arg(long, value_name = "PYTHON")]
    python: Option<std::path::PathBuf>,
    /// Run the Python reduction on the first N targets only and scale its times to the
    /// whole night (it is one run, single-threaded; the output says when it was scaled).
    #[arg(long, value_name = "N")]
    python_targets: Option<usize>,
    /// Also time the night with its per-target PNG figures, alternated with the run
    /// without (`--no-png`) in each repeat, and print the figures' share of the wall time
    /// (target: under 10 %).
    #[arg(long)]
    figures: bool,
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

/// Tag of a complete cached night in `--dir`: the targets, standards and the pixel-type mix
/// (a night simulated with another mix, e.g. all float by an older sofipol, is re-simulated).
fn night_tag(a: &NightArgs) -> String {
    format!(
        "{} targets{}; BITPIX -32 for even targets, 16 (BZERO 32768) for odd ones\n",
        a.targets,
        if a.with_standards { " with standards" } else { "" }
    )
}

/// The scene of the bench night (with the standards and their effects when asked).
fn night_scene_text(a: &NightArgs) -> String {
    let mut text = night_scene(a.targets, 2001);
    if a.with_standards {
        text = text.replacen(
            "\"cosmic_rays\"]",
            "\"cosmic_rays\", \"throughput\", \"instrumental_polarization\", \"analyzer_angle\"]",
            1,
        );
        text += "[throughput]\nt_e = 0.97\n[instrumental_polarization]\np = 0.003\nangle_deg = 0.0\n[analyzer_angle]\nzero_point_deg = 3.0\n";
        text +=
            "[[standard]]\nname = \"HD 64299\"\nflux = 150000.0\n[[standard]]\nname = \"HD 98161\"\nflux = 150000.0\n";
        text += "[[standard]]\nname = \"HD 204827\"\nflux = 150000.0\np = 0.0088\ngamma_deg = 58.7\n";
    }
    text
}

/// A progress bar on stderr when it is a terminal (as the binary's), hidden otherwise.
fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let pb = indicatif::ProgressBar::new(len);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{prefix:>10} [{bar:40}] {pos}/{len} {msg} ({elapsed}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_prefix(what.to_string());
    pb
}

/// Simulate the night into `raw` as SOFI writes it: half the targets float (BITPIX -32),
/// half 16-bit (BITPIX 16, BZERO 32768, BSCALE 1), alternating so that any first N targets
/// hold both. Also writes `pairs.csv`, the binaries' nominal separation and PA (what an
/// observer takes from the literature). Returns (frames, f32 frames).
fn simulate_mixed_night(text: &str, raw: &std::path::Path) -> anyhow::Result<(usize, usize)> {
    use rayon::prelude::*;
    use sofipol_calib::fits::{write_frame, Bitpix, WriteOptions};
    let scene = Scene::from_toml(text, "bench night").map_err(anyhow::Error::msg)?;
    let n_targets = scene.binary.len() + scene.standard.len();
    let mut pairs = String::from("name,separation_arcsec,pa_deg\n");
    for b in &scene.binary {
        pairs += &format!("{},{},{}\n", b.name, b.separation_arcsec, b.pa_deg);
    }
    let sim = Simulator::new(scene, Profile::sofi()).map_err(anyhow::Error::msg)?;
    std::fs::create_dir_all(raw)?;
    // Frames of an earlier bench night (another size or mix) go first.
    for e in std::fs::read_dir(raw)?.flatten() {
        if e.file_name().to_string_lossy().starts_with("SOFI_bench_") {
            std::fs::remove_file(e.path())?;
        }
    }
    let n = sim.frames_per_target();
    let jobs: Vec<(usize, usize)> = (0..n_targets).flat_map(|t| (0..n).map(move |k| (t, k))).collect();
    let pb = progress(jobs.len() as u64, "simulate");
    jobs.par_iter().try_for_each(|&(t, k)| -> anyhow::Result<()> {
        let f = sim.frame(t, k);
        let opts = WriteOptions {
            bitpix: if t % 2 == 0 { Bitpix::F32 } else { Bitpix::I16 },
            ..Default::default()
        };
        write_frame(&raw.join(&f.file_name), &f.frame, &opts)?;
        pb.inc(1);
        Ok(())
    })?;
    pb.finish_and_clear();
    sofipol_pipeline::io::write_atomic(&raw.join("pairs.csv"), pairs.as_bytes())?;
    let f32_frames = n_targets.div_ceil(2) * n;
    Ok((jobs.len(), f32_frames))
}

/// The night in `raw`: reused when `--dir` holds one with the same tag, simulated otherwise.
fn ensure_night(a: &NightArgs, raw: &std::path::Path, keep: bool) -> anyhow::Result<()> {
    let reuse = raw.join(".bench-night-complete");
    let tag = night_tag(a);
    if std::fs::read_to_string(&reuse).ok().as_deref() == Some(tag.as_str()) && raw.join("pairs.csv").exists() {
        println!(
            "sofipol bench night: reusing the {}-target night simulated earlier in {} ({})",
            a.targets,
            raw.display(),
            tag.trim()
        );
        return Ok(());
    }
    std::fs::remove_file(&reuse).ok();
    let t0 = Instant::now();
    let (nframes, nf32) = simulate_mixed_night(&night_scene_text(a), raw)?;
    println!(
        "sofipol bench night: simulated {} targets, {nframes} frames of 1024x1024 ({nf32} float BITPIX -32, {} 16-bit BITPIX 16) in {:.1} s (not timed below)",
        a.targets,
        nframes - nf32,
        t0.elapsed().as_secs_f64()
    );
    if keep {
        sofipol_pipeline::io::write_atomic(&reuse, tag.as_bytes())?;
    }
    Ok(())
}

/// The night's FITS files, sorted.
fn fits_files(raw: &std::path::Path) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(raw)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "fits"))
        .collect();
    files.sort();
    Ok(files)
}

/// The bench night of `targets` binaries (with the 3 standards and their instrumental
/// effects when `with_standards`) simulated into `root/raw` (reused when simulated there
/// before), and its frames, sorted by name.
pub fn prepare_night(
    targets: usize,
    with_standards: bool,
    root: &std::path::Path,
) -> anyhow::Result<(std::path::PathBuf, Vec<std::path::PathBuf>)> {
    let a = NightArgs {
        targets,
        jobs: None,
        repeats: 1,
        dir: Some(root.to_path_buf()),
        with_standards,
        python: None,
        python_targets: None,
        figures: false,
    };
    let raw = root.join("raw");
    ensure_night(&a, &raw, true)?;
    let files = fits_files(&raw)?;
    Ok((raw, files))
}

/// Run `sofipol bench night`.
pub fn run(a: NightArgs) -> anyhow::Result<()> {
    let tmp = tempfile::tempdir()?;
    let keep = a.dir.is_some();
    let root = a.dir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    let raw = root.join("raw");
    ensure_night(&a, &raw, keep)?;
    let files = fits_files(&raw)?;
    let (runs, last) = time_sofipol_night(&a, &raw, &root, &files)?;
    let s = print_night_runs(&runs, &files, &last);
    let python = a
        .python
        .clone()
        .or_else(|| std::env::var_os("SOFIPOL_PYTHON").map(std::path::PathBuf::from));
    match python {
        Some(py) => {
            let n = a.python_targets.unwrap_or(a.targets).clamp(1, a.targets.max(1));
            match run_python(&py, &raw, &root, n) {
                Ok(p) => {
                    let scene = Scene::from_toml(&night_scene_text(&a), "bench night").ok();
                    let catalog = root.join(format!("catalog{}.json", runs.len() - 1));
                    print_python(&p, &s, a.targets, &catalog, scene.as_ref())
                }
                Err(e) => println!("  Python reference: FAILED ({e:#}); not compared"),
            }
        }
        None => println!(
            "  Python reference: not run (give --python PATH or set SOFIPOL_PYTHON to an interpreter with numpy, scipy, astropy, photutils)"
        ),
    }
    println!("  targets: wall <= 5x cat, >= 50x faster than the Python reduction, peak RSS <= 1 GB");
    Ok(())
}

/// Runs `sofipol night` `--repeats` times in a child process, each followed by the floors.
/// Returns the runs and the last run's stderr.
fn time_sofipol_night(
    a: &NightArgs,
    raw: &std::path::Path,
    root: &std::path::Path,
    files: &[std::path::PathBuf],
) -> anyhow::Result<(Vec<NightRun>, String)> {
    use anyhow::Context;
    let exe = std::env::current_exe().context("locating the sofipol executable")?;
    let mut runs: Vec<NightRun> = Vec::new();
    let mut last = String::new();
    // One child `sofipol night` (with its figures when `figures`); its wall time and stderr.
    let night = |out: &std::path::Path, figures: bool, extra: &[&str]| -> anyhow::Result<(f64, String)> {
        let mut cmd = std::process::Command::new(&exe);
        cmd.arg("night").arg(raw).arg("-o").arg(out).arg("-q").arg("-v");
        if !figures {
            cmd.arg("--no-png");
        }
        cmd.args(extra);
        if let Some(j) = a.jobs {
            cmd.arg("--jobs").arg(j.to_string());
        }
        let t = Instant::now();
        let o = cmd.output().context("running sofipol night")?;
        let wall = t.elapsed().as_secs_f64();
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        anyhow::ensure!(
            o.status.code() == Some(0) || o.status.code() == Some(2),
            "sofipol night {} failed: {stderr}",
            extra.join(" ")
        );
        Ok((wall, stderr))
    };
    // Warm the page cache first: the reduction reads only the target strips' rows, so
    // without this the first repeat reads from disk and its `cat` floor reads the rest.
    cat_floor(files)?;
    for r in 0..a.repeats.max(1) {
        let (wall, stderr) = night(&root.join(format!("catalog{r}.json")), false, &[])?;
        // The floors, in the same run, page cache warm (the reduction just read the files).
        let cat = cat_floor(files)?;
        let read = read_floor(files)?;
        // The same night without any calibration (no flat, no standards), right after: what
        // calibration costs is the difference.
        let (base_wall, base_err) = night(
            &root.join("catalog-uncalibrated.json"),
            false,
            &["--no-flat", "--no-calibration"],
        )?;
        // With the figures, right after the same run without them.
        let figures_wall = if a.figures {
            night(&root.join("catalog-figures.json"), true, &[])?.0
        } else {
            f64::NAN
        };
        last = stderr.clone();
        runs.push(NightRun {
            figures_wall,
            wall,
            cat,
            read,
            stages: parse_stage_line(&stderr),
            base_wall,
            base: parse_stage_line(&base_err),
        });
    }
    Ok((runs, last))
}

/// Prints the sofipol runs: wall, CPU, floors, ratios, stages, RSS.
fn print_night_runs(runs: &[NightRun], files: &[std::path::PathBuf], last: &str) -> NightSummary {
    let bytes: u64 = files.iter().filter_map(|p| p.metadata().ok()).map(|m| m.len()).sum();
    let med = |f: &dyn Fn(&NightRun) -> f64| -> f64 {
        let mut v: Vec<f64> = runs.iter().map(f).filter(|x| x.is_finite()).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let list = |f: &dyn Fn(&NightRun) -> f64, digits: usize| -> String {
        runs.iter()
            .map(|r| format!("{:.*}", digits, f(r)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    println!(
        "  files: {} ({:.0} MB), read once first to warm the page cache; medians over {} runs, each run = reduction + floors right after it",
        files.len(),
        bytes as f64 / 1e6,
        runs.len()
    );
    for line in last
        .lines()
        .filter(|l| l.contains("stage time") || l.contains("calibration") || l.starts_with("flats: "))
    {
        println!("  last run: {line}");
    }
    let s = NightSummary {
        wall: med(&|r| r.wall),
        cpu: med(&|r| r.stages.get("cpu")),
        cat: med(&|r| r.cat),
    };
    println!(
        "  reduction wall (child process, incl. start-up): {:.2} s   [{}]",
        s.wall,
        list(&|r| r.wall, 2)
    );
    println!(
        "  reduction CPU (user+sys):                       {:.2} s   [{}]",
        s.cpu,
        list(&|r| r.stages.get("cpu"), 2)
    );
    println!(
        "  `cat` floor (cat FILES > /dev/null):             {:.3} s  [{}]",
        s.cat,
        list(&|r| r.cat, 3)
    );
    println!(
        "  in-process read floor (std::fs::read each file): {:.3} s  [{}]",
        med(&|r| r.read),
        list(&|r| r.read, 3)
    );
    println!(
        "  ratio wall / cat (per run, same run):           {:.1}x  [{}]",
        med(&|r| r.wall / r.cat),
        list(&|r| r.wall / r.cat, 1)
    );
    println!(
        "  ratio CPU / cat:                                 {:.1}x",
        med(&|r| r.stages.get("cpu") / r.cat)
    );
    print_stages(runs);
    println!(
        "  peak RSS: {:.0} MB (max over runs)",
        runs.iter().map(|r| r.stages.get("rss")).fold(0.0, f64::max)
    );
    s
}

/// Median per-stage times and the cost of calibration (<= 15 % of the night).
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
    // What calibration costs: each calibrated run against the uncalibrated run right after
    // it (`--no-flat --no-calibration`), CPU and wall.
    let pct = |a: f64, b: f64| 100.0 * (a / b - 1.0);
    let list = |f: &dyn Fn(&NightRun) -> f64| {
        runs.iter()
            .map(|r| format!("{:+.1}", f(r)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    println!(
        "  calibration (target: adds <= 15 %): night without flat and standards {:.2} CPU-s / {:.2} s wall (median); \
         calibration adds {:+.1} % CPU [{}], {:+.1} % wall [{}] (median of per-run ratios; flat build {:.2} s, \
         flat check {:.2} s, standards {:.2} s; the flat is divided out in the sky stage's pass)",
        med(&|r| r.base.get("cpu")),
        med(&|r| r.base_wall),
        med(&|r| pct(g(r, "cpu"), r.base.get("cpu"))),
        list(&|r| pct(g(r, "cpu"), r.base.get("cpu"))),
        med(&|r| pct(r.wall, r.base_wall)),
        list(&|r| pct(r.wall, r.base_wall)),
        med(&|r| g(r, "flat build")),
        med(&|r| g(r, "flat")),
        med(&|r| g(r, "calibration")),
    );
    if runs.iter().any(|r| r.figures_wall.is_finite()) {
        let share = |r: &NightRun| 100.0 * (r.figures_wall - r.wall) / r.figures_wall;
        println!(
            "  figures (target: under 10 % of the night's wall): {:.3} s with them, {:.3} s without (medians); \
             their share {:.1} % (median of per-run shares [{}])",
            med(&|r| r.figures_wall),
            med(&|r| r.wall),
            med(&share),
            runs.iter()
                .map(|r| format!("{:.1}", share(r)))
                .collect::<Vec<_>>()
                .join(" "),
        );
    }
}

/// One repeat of `bench night`.
struct NightRun {
    wall: f64,
    cat: f64,
    read: f64,
    stages: StageLine,
    /// Wall time of the uncalibrated night run right after (`--no-flat --no-calibration`).
    base_wall: f64,
    /// Its stage line.
    base: StageLine,
    /// Wall time of the same night with its figures, run right after (`--figures`; NaN
    /// without).
    figures_wall: f64,
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
