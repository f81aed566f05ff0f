//! `sofipol bench night --python`: the expert Python reduction of bench/python/ run on the
//! same night, timed against sofipol, and its catalog compared with sofipol's and with the
//! simulated truth.
use std::time::Instant;

use sofipol_pipeline::sim::Scene;

/// The expert Python reduction (bench/python/reduce_night.py), embedded so that the bench
/// runs from any directory.
const PYTHON_REDUCTION: &str = include_str!("../python/reduce_night.py");

/// Medians of the sofipol runs that the Python comparison needs.
pub(crate) struct NightSummary {
    pub(crate) wall: f64,
    pub(crate) cpu: f64,
    pub(crate) cat: f64,
}

/// One run of the Python reduction.
pub(crate) struct PythonRun {
    /// Wall time of the child process (interpreter start-up and imports included), s.
    wall: f64,
    /// The child's CPU time (user + sys, its own getrusage at exit), s.
    cpu: f64,
    /// Sequences it reduced (and failed).
    sequences: usize,
    /// Its catalog.
    catalog: serde_json::Value,
}

/// Runs the Python reduction on the first `n` sequences of `raw`, single-threaded (one
/// process; BLAS/OpenMP threads pinned to 1).
pub(crate) fn run_python(
    py: &std::path::Path,
    raw: &std::path::Path,
    root: &std::path::Path,
    n: usize,
) -> anyhow::Result<PythonRun> {
    use anyhow::Context;
    let script = root.join("reduce_night.py");
    sofipol_pipeline::io::write_atomic(&script, PYTHON_REDUCTION.as_bytes())?;
    let out = root.join("catalog_python.json");
    std::fs::remove_file(&out).ok();
    let mut cmd = std::process::Command::new(py);
    cmd.arg(&script)
        .arg(raw)
        .arg("-o")
        .arg(&out)
        .arg("--pairs")
        .arg(raw.join("pairs.csv"))
        .arg("--targets")
        .arg(n.to_string())
        .arg("-q");
    for v in ["OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"] {
        cmd.env(v, "1");
    }
    let t = Instant::now();
    let o = cmd
        .output()
        .with_context(|| format!("running {} {}", py.display(), script.display()))?;
    let wall = t.elapsed().as_secs_f64();
    if !o.status.success() {
        let err = String::from_utf8_lossy(&o.stderr);
        let tail: Vec<&str> = err.lines().rev().take(3).collect();
        anyhow::bail!("{} exited with {}: {}", py.display(), o.status, tail.join(" | "));
    }
    let text = std::fs::read_to_string(&out).with_context(|| format!("reading {}", out.display()))?;
    let catalog: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", out.display()))?;
    let count = |k: &str| catalog[k].as_array().map_or(0, |v| v.len());
    Ok(PythonRun {
        wall,
        cpu: catalog["cpu_s"].as_f64().unwrap_or(f64::NAN),
        sequences: count("targets") + count("failures"),
        catalog,
    })
}

/// Prints the Python timings (scaled to the whole night when it ran on fewer targets), the
/// ratios against sofipol and the comparison of the two catalogs.
pub(crate) fn print_python(
    p: &PythonRun,
    s: &NightSummary,
    targets: usize,
    sofipol_catalog: &std::path::Path,
    scene: Option<&Scene>,
) {
    let scale = targets as f64 / p.sequences.max(1) as f64;
    let v = &p.catalog["versions"];
    println!(
        "  Python reference (bench/python/reduce_night.py: numpy {}, scipy {}, astropy {}, photutils {}; one process, 1 thread), one run on {} of {} targets{}:",
        v["numpy"].as_str().unwrap_or("?"),
        v["scipy"].as_str().unwrap_or("?"),
        v["astropy"].as_str().unwrap_or("?"),
        v["photutils"].as_str().unwrap_or("?"),
        p.sequences,
        targets,
        if scale > 1.0 {
            format!(", reduction times scaled x{scale:.2} to the whole night (start-up once)")
        } else {
            String::new()
        }
    );
    // Interpreter start-up and imports once, the reduction itself scaled.
    let work_wall = p.catalog["wall_s"].as_f64().unwrap_or(p.wall).min(p.wall);
    let startup_cpu = p.catalog["startup_cpu_s"].as_f64().unwrap_or(0.0).min(p.cpu);
    let wall = p.wall - work_wall + work_wall * scale;
    let cpu = startup_cpu + (p.cpu - startup_cpu) * scale;
    println!(
        "    Python wall {:.2} s (measured {:.2} s, incl. start-up), CPU {:.2} s (measured {:.2} s)",
        wall, p.wall, cpu, p.cpu
    );
    println!(
        "    ratio Python / sofipol: wall {:.1}x, CPU {:.1}x; Python wall / cat {:.0}x",
        wall / s.wall,
        cpu / s.cpu,
        wall / s.cat
    );
    match std::fs::read_to_string(sofipol_catalog)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
    {
        Some(sp) => {
            print_comparison(&compare_catalogs(&sp, &p.catalog));
            if let Some(sc) = scene {
                for (who, cat) in [("sofipol", &sp), ("Python", &p.catalog)] {
                    print_truth_pulls(who, &truth_pulls(cat, sc, Some(&p.catalog)));
                }
            }
        }
        None => println!("    comparison: cannot read {}", sofipol_catalog.display()),
    }
}

/// One component measured by both reductions: q and u differences in sofipol's sigma.
pub struct Diff {
    /// Target (OBJECT).
    pub object: String,
    /// "A" (the brighter) or "B".
    pub component: String,
    /// sofipol's photometry: "aperture" or "psf_fit".
    pub photometry: String,
    /// sofipol's target status ("ok", "partial", ...).
    pub status: String,
    /// (q_python - q_sofipol) / sigma_q_sofipol.
    pub dq: f64,
    /// (u_python - u_sofipol) / sigma_u_sofipol.
    pub du: f64,
}

/// Differences of q and u between the Python and the sofipol catalog, per component of every
/// target both measured (matched by OBJECT and TPL START, components by name).
pub fn compare_catalogs(sofipol: &serde_json::Value, python: &serde_json::Value) -> Vec<Diff> {
    let empty = Vec::new();
    let sp_targets = sofipol["targets"].as_array().unwrap_or(&empty);
    let mut out = Vec::new();
    for pt in python["targets"].as_array().unwrap_or(&empty) {
        let key = (pt["object"].as_str(), pt["tpl_start"].as_str());
        let Some(st) = sp_targets
            .iter()
            .find(|t| (t["object"].as_str(), t["tpl_start"].as_str()) == key)
        else {
            continue;
        };
        for pc in pt["components"].as_array().unwrap_or(&empty) {
            let Some(sc) = st["components"]
                .as_array()
                .unwrap_or(&empty)
                .iter()
                .find(|c| c["name"] == pc["name"])
            else {
                continue;
            };
            let f = |c: &serde_json::Value, k: &str| c[k].as_f64().unwrap_or(f64::NAN);
            let dq = (f(pc, "q") - f(sc, "q")) / f(sc, "sigma_q");
            let du = (f(pc, "u") - f(sc, "u")) / f(sc, "sigma_u");
            if dq.is_finite() && du.is_finite() {
                out.push(Diff {
                    object: key.0.unwrap_or("").to_string(),
                    component: pc["name"].as_str().unwrap_or("").to_string(),
                    photometry: st["photometry"].as_str().unwrap_or("").to_string(),
                    status: st["status"].as_str().unwrap_or("ok").to_string(),
                    dq,
                    du,
                });
            }
        }
    }
    out
}

/// (values, rms, max |x|, values within 1)
fn spread(v: &[f64]) -> (usize, f64, f64, usize) {
    let rms = (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let max = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    (v.len(), rms, max, v.iter().filter(|x| x.abs() <= 1.0).count())
}

fn print_comparison(d: &[Diff]) {
    if d.is_empty() {
        println!("    comparison: no component measured by both");
        return;
    }
    for (label, photometry) in [
        ("all", None),
        ("sofipol aperture", Some("aperture")),
        ("sofipol psf_fit", Some("psf_fit")),
    ] {
        let v: Vec<f64> = d
            .iter()
            .filter(|x| x.status == "ok" && photometry.is_none_or(|p| x.photometry == p))
            .flat_map(|x| [x.dq, x.du])
            .collect();
        let (n, rms, max, within) = spread(&v);
        if n > 0 {
            println!(
                "    Python - sofipol, q and u in units of sofipol's sigma ({label}, sofipol status ok): {n} values, rms {rms:.2}, max |d| {max:.2}, {within} within 1 sigma"
            );
        }
    }
    let mut worst: Vec<&Diff> = d.iter().collect();
    worst.sort_by(|a, b| b.dq.abs().max(b.du.abs()).total_cmp(&a.dq.abs().max(a.du.abs())));
    let w: Vec<String> = worst
        .iter()
        .take(3)
        .map(|x| {
            format!(
                "{} {} ({}, {}) dq {:+.2} du {:+.2}",
                x.object, x.component, x.photometry, x.status, x.dq, x.du
            )
        })
        .collect();
    println!("    largest differences: {}", w.join("; "));
    let not_ok: Vec<String> = d
        .iter()
        .filter(|x| x.status != "ok")
        .map(|x| {
            format!(
                "{} {} ({}) dq {:+.2} du {:+.2}",
                x.object, x.component, x.status, x.dq, x.du
            )
        })
        .collect();
    if !not_ok.is_empty() {
        println!(
            "    targets sofipol did not reduce fully (left out above): {}",
            not_ok.join("; ")
        );
    }
}

/// Pulls (value - true) / sigma of q and u of every component of `catalog` against the
/// scene, over the targets the Python catalog holds (A = the brighter true component).
/// Returns (object and component, pull) pairs.
fn truth_pulls(catalog: &serde_json::Value, scene: &Scene, only: Option<&serde_json::Value>) -> Vec<(String, f64)> {
    let empty = Vec::new();
    let wanted: Vec<&str> = only
        .and_then(|c| c["targets"].as_array())
        .map(|v| v.iter().filter_map(|t| t["object"].as_str()).collect())
        .unwrap_or_default();
    let qu = |p: f64, g: f64| [p * (2.0 * g.to_radians()).cos(), p * (2.0 * g.to_radians()).sin()];
    let mut out = Vec::new();
    for t in catalog["targets"].as_array().unwrap_or(&empty) {
        let Some(obj) = t["object"].as_str() else { continue };
        let Some(b) = scene.binary.iter().find(|b| b.name == obj) else {
            continue;
        };
        if only.is_some() && !wanted.contains(&obj) {
            continue;
        }
        let (a_true, b_true) = (qu(b.p_a, b.gamma_a_deg), qu(b.p_b, b.gamma_b_deg));
        let (bright, faint) = if b.flux_a >= b.flux_b {
            (a_true, b_true)
        } else {
            (b_true, a_true)
        };
        for c in t["components"].as_array().unwrap_or(&empty) {
            let tr = if c["name"] == "A" { bright } else { faint };
            for (k, s, v) in [("q", "sigma_q", tr[0]), ("u", "sigma_u", tr[1])] {
                let pull = (c[k].as_f64().unwrap_or(f64::NAN) - v) / c[s].as_f64().unwrap_or(f64::NAN);
                if pull.is_finite() {
                    out.push((format!("{obj} {} {k}", c["name"].as_str().unwrap_or("?")), pull));
                }
            }
        }
    }
    out
}

fn print_truth_pulls(who: &str, p: &[(String, f64)]) {
    let v: Vec<f64> = p.iter().map(|x| x.1).collect();
    let (n, rms, max, within) = spread(&v);
    let worst = p.iter().max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
    println!(
        "    {who:<7} against the simulated truth, (value - true) / sigma of q and u: {n} values, rms {rms:.2}, max |pull| {max:.2}{}, {within} within 1 sigma",
        worst.map_or(String::new(), |w| format!(" ({})", w.0))
    );
}
