//! `sofipol bench watch`: the latency of live reduction. The bench night is copied into an
//! empty folder frame by frame, in the order it was observed (MJD-OBS; the standards last
//! with `--standards-last`), one frame every `--interval` seconds, while `sofipol watch`
//! follows the folder in a child process. The catalog is read every 20 ms: each template's
//! latency is the time from its last frame's copy to its entry in the catalog. Then
//! `sofipol night` reduces the same folder and the two catalogs are compared (targets and
//! failures; the provenance differs by its command line and times).
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use sofipol_pipeline::catalog::Catalog;

/// Arguments of `sofipol bench watch`.
#[derive(clap::Args, Debug, Clone)]
pub struct WatchArgs {
    /// Targets of the bench night.
    #[arg(long, default_value_t = 49)]
    targets: usize,
    /// Seconds between two frames copied.
    #[arg(long, default_value_t = 0.2)]
    interval: f64,
    /// Add the 3 standard stars (as `bench night --with-standards`), copied after the
    /// targets: each arrival re-calibrates the night.
    #[arg(long)]
    with_standards: bool,
    /// Keep the simulated night here (reused when simulated there before).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Worker threads of `sofipol watch` [default: all cores].
    #[arg(long)]
    jobs: Option<usize>,
}

/// A frame to copy: when it was observed, its template.
struct Frame {
    path: PathBuf,
    mjd: f64,
    template: String,
}

/// The frames in observation order (standards after the targets).
fn observation_order(files: &[PathBuf]) -> anyhow::Result<Vec<Frame>> {
    let mut frames = Vec::new();
    for f in files {
        let h = sofipol_calib::fits::read_header(f).with_context(|| format!("reading {}", f.display()))?;
        let object = h.get_str("OBJECT").unwrap_or_default();
        let start = h.get_str("ESO TPL START").unwrap_or_default();
        let standard = h.get_str("ESO DPR TYPE").is_ok_and(|t| t.trim() == "STD");
        frames.push((
            standard,
            Frame {
                path: f.clone(),
                mjd: h.get_f64("MJD-OBS").unwrap_or(f64::NAN),
                template: format!("{}@{}", object.trim(), start.trim()),
            },
        ));
    }
    frames.sort_by(|(sa, a), (sb, b)| sa.cmp(sb).then(a.mjd.total_cmp(&b.mjd)).then(a.path.cmp(&b.path)));
    Ok(frames.into_iter().map(|(_, f)| f).collect())
}

/// Read the catalog every 20 ms until `stop`: when each sequence id first appeared (a
/// target, or a standard in the calibration's `standards`).
fn monitor(catalog: PathBuf, t0: Instant, stop: Arc<AtomicBool>, seen: Arc<Mutex<HashMap<String, f64>>>) {
    while !stop.load(Ordering::Relaxed) {
        if let Some(v) = std::fs::read_to_string(&catalog)
            .ok()
            .and_then(|s| serde_json::from_str::<Catalog>(&s).ok())
        {
            let now = t0.elapsed().as_secs_f64();
            let mut seen = seen.lock().unwrap_or_else(|e| e.into_inner());
            let standards = v.standards.iter().map(|s| s.sequence.as_str());
            for id in v.targets.iter().filter_map(|t| t.sequence.as_deref()).chain(standards) {
                seen.entry(id.to_string()).or_insert(now);
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Run `sofipol bench watch`.
pub fn run(a: WatchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        a.interval.is_finite() && a.interval >= 0.0,
        "--interval {}: need >= 0",
        a.interval
    );
    let tmp = tempfile::tempdir()?;
    let root = a.dir.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    let (_, files) = crate::night::prepare_night(a.targets, a.with_standards, &root)?;
    let frames = observation_order(&files)?;
    let live = root.join("live");
    if live.exists() {
        std::fs::remove_dir_all(&live).with_context(|| format!("emptying {}", live.display()))?;
    }
    std::fs::create_dir_all(&live)?;
    let catalog = root.join("watch.json");
    for p in [catalog.clone(), root.join("watch.json.state.json")] {
        std::fs::remove_file(p).ok();
    }
    let exe = std::env::current_exe().context("locating the sofipol executable")?;
    let mut cmd = std::process::Command::new(&exe);
    cmd.arg("watch")
        .arg(&live)
        .arg("-o")
        .arg(&catalog)
        .args(["--exit-when-idle", "3", "-q"])
        .stdout(std::process::Stdio::null());
    if let Some(j) = a.jobs {
        cmd.arg("--jobs").arg(j.to_string());
    }
    let mut child = cmd.spawn().context("starting sofipol watch")?;
    std::thread::sleep(Duration::from_millis(500));
    let t0 = Instant::now();
    let stop = Arc::new(AtomicBool::new(false));
    let seen = Arc::new(Mutex::new(HashMap::new()));
    let mon = {
        let (c, s, seen) = (catalog.clone(), stop.clone(), seen.clone());
        std::thread::spawn(move || monitor(c, t0, s, seen))
    };
    println!(
        "sofipol bench watch: {} frames of {} templates copied one every {} s into {}",
        frames.len(),
        frames
            .iter()
            .map(|f| &f.template)
            .collect::<std::collections::BTreeSet<_>>()
            .len(),
        a.interval,
        live.display()
    );
    let mut last_copy: BTreeMap<String, f64> = BTreeMap::new();
    for (i, f) in frames.iter().enumerate() {
        let due = t0 + Duration::from_secs_f64(a.interval * i as f64);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        let name = f.path.file_name().context("frame without a name")?;
        std::fs::copy(&f.path, live.join(name)).with_context(|| format!("copying {}", f.path.display()))?;
        last_copy.insert(f.template.clone(), t0.elapsed().as_secs_f64());
    }
    let status = child.wait().context("waiting for sofipol watch")?;
    stop.store(true, Ordering::Relaxed);
    mon.join().ok();
    anyhow::ensure!(
        matches!(status.code(), Some(0) | Some(2)),
        "sofipol watch exited with {status}"
    );
    let seen = seen.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let mut latency: Vec<(f64, &str)> = last_copy
        .iter()
        .map(|(id, t)| (seen.get(id).map(|s| s - t).unwrap_or(f64::INFINITY), id.as_str()))
        .collect();
    latency.sort_by(|a, b| a.0.total_cmp(&b.0));
    let q = |f: f64| latency[((latency.len() - 1) as f64 * f).round() as usize].0;
    println!(
        "  latency, last frame copied -> entry in the catalog, {} templates: median {:.2} s, 90 % {:.2} s, max {:.2} s ({}); {} of {} within 2 s",
        latency.len(),
        q(0.5),
        q(0.9),
        q(1.0),
        latency.last().map(|l| l.1).unwrap_or(""),
        latency.iter().filter(|l| l.0 <= 2.0).count(),
        latency.len()
    );
    compare_with_night(&exe, &live, &catalog, &root)
}

/// Reduce the folder with `sofipol night` and compare its targets and failures with the
/// live catalog's.
fn compare_with_night(exe: &Path, live: &Path, catalog: &Path, root: &Path) -> anyhow::Result<()> {
    let night = root.join("night.json");
    let t = Instant::now();
    let o = std::process::Command::new(exe)
        .arg("night")
        .arg(live)
        .arg("-o")
        .arg(&night)
        .args(["-q", "--no-png"])
        .output()
        .context("running sofipol night")?;
    let wall = t.elapsed().as_secs_f64();
    anyhow::ensure!(matches!(o.status.code(), Some(0) | Some(2)), "sofipol night failed");
    let read = |p: &Path| -> anyhow::Result<Catalog> {
        Ok(serde_json::from_str(
            &std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?,
        )?)
    };
    let (w, n) = (read(catalog)?, read(&night)?);
    // As written (NaN equal to NaN: both null).
    let same_targets = serde_json::to_value(&w.targets)? == serde_json::to_value(&n.targets)?;
    let same_failures = w.failures == n.failures;
    println!(
        "  final catalog against `sofipol night` on the same frames ({wall:.2} s): targets {}, failures {} ({} targets)",
        if same_targets { "equal" } else { "DIFFER" },
        if same_failures { "equal" } else { "DIFFER" },
        n.targets.len()
    );
    println!("  targets: every template's entry within 2 s of its last frame; the final catalog equal to night's");
    Ok(())
}
