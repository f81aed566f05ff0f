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
    catalog: Compared,
}

/// What the comparison reads of a catalog, sofipol's or the Python reduction's (which
/// writes the same keys for targets and components, plus its versions and times).
#[derive(serde::Deserialize, Default)]
#[serde(default)]
struct Compared {
    targets: Vec<ComparedTarget>,
    failures: Vec<serde_json::Value>,
    /// Python: the versions of numpy, scipy, astropy, photutils.
    versions: std::collections::BTreeMap<String, String>,
    /// Python: its CPU time, s.
    #[serde(deserialize_with = "number")]
    cpu_s: f64,
    /// Python: wall time of the reduction itself (start-up excluded), s.
    #[serde(deserialize_with = "number")]
    wall_s: f64,
    /// Python: CPU time of its start-up and imports, s.
    #[serde(deserialize_with = "number")]
    startup_cpu_s: f64,
}

#[derive(serde::Deserialize, Default)]
#[serde(default)]
struct ComparedTarget {
    object: String,
    tpl_start: Option<String>,
    status: Option<String>,
    photometry: Option<String>,
    components: Vec<ComparedComponent>,
}

#[derive(serde::Deserialize, Default)]
#[serde(default)]
struct ComparedComponent {
    name: String,
    #[serde(deserialize_with = "number")]
    q: f64,
    #[serde(deserialize_with = "number")]
    u: f64,
    #[serde(deserialize_with = "number")]
    sigma_q: f64,
    #[serde(deserialize_with = "number")]
    sigma_u: f64,
}

/// A number; `null` or another value as NaN.
fn number<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    use serde::Deserialize as _;
    Ok(serde_json::Value::deserialize(d)?.as_f64().unwrap_or(f64::NAN))
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
    let catalog: Compared = serde_json::from_str(&text).with_context(|| format!("parsing {}", out.display()))?;
    Ok(PythonRun {
        wall,
        cpu: catalog.cpu_s,
        sequences: catalog.targets.len() + catalog.failures.len(),
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
    let v = |k: &str| p.catalog.versions.get(k).map_or("?", |s| s.as_str());
    println!(
        "  Python reference (bench/python/reduce_night.py: numpy {}, scipy {}, astropy {}, photutils {}; one process, 1 thread), one run on {} of {} targets{}:",
        v("numpy"),
        v("scipy"),
        v("astropy"),
        v("photutils"),
        p.sequences,
        targets,
        if scale > 1.0 {
            format!(", reduction times scaled x{scale:.2} to the whole night (start-up once)")
        } else {
            String::new()
        }
    );
    // Interpreter start-up and imports once, the reduction itself scaled.
    let or = |x: f64, default: f64| if x.is_finite() { x } else { default };
    let work_wall = or(p.catalog.wall_s, p.wall).min(p.wall);
    let startup_cpu = or(p.catalog.startup_cpu_s, 0.0).min(p.cpu);
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
        .and_then(|t| serde_json::from_str::<Compared>(&t).ok())
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
fn compare_catalogs(sofipol: &Compared, python: &Compared) -> Vec<Diff> {
    let mut out = Vec::new();
    for pt in &python.targets {
        let key = (&pt.object, &pt.tpl_start);
        let Some(st) = sofipol.targets.iter().find(|t| (&t.object, &t.tpl_start) == key) else {
            continue;
        };
        for pc in &pt.components {
            let Some(sc) = st.components.iter().find(|c| c.name == pc.name) else {
                continue;
            };
            let dq = (pc.q - sc.q) / sc.sigma_q;
            let du = (pc.u - sc.u) / sc.sigma_u;
            if dq.is_finite() && du.is_finite() {
                out.push(Diff {
                    object: pt.object.clone(),
                    component: pc.name.clone(),
                    photometry: st.photometry.clone().unwrap_or_default(),
                    status: st.status.clone().unwrap_or_else(|| "ok".into()),
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
fn truth_pulls(catalog: &Compared, scene: &Scene, only: Option<&Compared>) -> Vec<(String, f64)> {
    let wanted: Vec<&str> = only
        .map(|c| c.targets.iter().map(|t| t.object.as_str()).collect())
        .unwrap_or_default();
    let qu = |p: f64, g: f64| [p * (2.0 * g.to_radians()).cos(), p * (2.0 * g.to_radians()).sin()];
    let mut out = Vec::new();
    for t in &catalog.targets {
        let obj = t.object.as_str();
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
        for c in &t.components {
            let tr = if c.name == "A" { bright } else { faint };
            for (k, x, s, v) in [("q", c.q, c.sigma_q, tr[0]), ("u", c.u, c.sigma_u, tr[1])] {
                let pull = (x - v) / s;
                if pull.is_finite() {
                    out.push((format!("{obj} {} {k}", c.name), pull));
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
