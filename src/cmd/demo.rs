//! `sofipol demo`: simulate the embedded demo scene into ./sofipol-demo/ and report.
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use sofipol_pipeline::catalog::provenance::FlatProvenance;
use sofipol_pipeline::catalog::Catalog;
use sofipol_pipeline::night::{self, NightSetup, RunOptions};
use sofipol_pipeline::products::OutputChoice;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{Scene, Simulator, Truth};

use super::common::ProfileArgs;

/// The embedded demo scene (testdata/scenes/demo.toml).
pub const DEMO_SCENE: &str = include_str!("../../testdata/scenes/demo.toml");

/// Arguments of `sofipol demo`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output directory.
    #[arg(short, long, default_value = "sofipol-demo")]
    pub output: PathBuf,
    /// No progress bars.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let scene = Scene::from_toml(DEMO_SCENE, "embedded demo scene").map_err(anyhow::Error::msg)?;
    let profile = ProfileArgs::default().load()?;
    let raw = args.output.join("raw");
    let sim = Simulator::new(scene, profile.clone()).map_err(anyhow::Error::msg)?;
    check_demo_dir(&args.output, &sim.file_names())?;
    let scene = sim.scene();
    let t0 = std::time::Instant::now();
    println!(
        "sofipol demo: simulating the embedded scene '{}' (seed {}) into {}",
        scene.name,
        scene.seed,
        raw.display()
    );
    println!(
        "  effects: {}",
        scene.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", ")
    );
    let truth = super::simulate::simulate_with(&sim, &raw, None, args.quiet)?;
    let nframes: usize = truth.targets.iter().map(|t| t.frames.len()).sum();
    let nstd: usize = truth.standards.iter().map(|t| t.frames.len()).sum();
    println!(
        "  wrote {nframes} target frames, {nstd} frames of {} standards, {} dome flats and truth.json in {:.2} s",
        truth.standards.len(),
        truth.dome_flats.len(),
        t0.elapsed().as_secs_f64()
    );

    // Reduce the night exactly as `sofipol night` does ([`night::run_night`]): scan,
    // classify, group; the night's bad-pixel mask and flats; the targets; the standards
    // and the calibration.
    let t1 = std::time::Instant::now();
    let params = TargetParams::default();
    let calibration = super::setup::CalibArgs::default().setup(&params.calibration)?;
    let setup = NightSetup {
        profile,
        params,
        calibration,
    };
    let plan = setup.plan(std::slice::from_ref(&raw), None);
    // The figures go where `night` puts them, so that `sofipol report` finds them.
    let cat_path = args.output.join("catalog.json");
    let choice = OutputChoice {
        figures: true,
        ..OutputChoice::default()
    };
    let outputs = super::common::outputs(&cat_path, choice, &setup)?;
    let fig_dir = outputs.figures_dir().map(Path::to_path_buf).unwrap_or_default();
    let opts = RunOptions {
        night_mask: true,
        inputs: vec![raw.clone()],
        outputs: Some(&outputs),
        ..Default::default()
    };
    let out = night::run_night(&plan, &setup, &opts);
    let (cat, summary, stds) = (out.catalog, out.summary, plan.standards);
    let flats = out.flats;
    sofipol_pipeline::io::write_json_atomic(&cat_path, &cat)?;
    println!(
        "  reduced {} sequences and {} standards in {:.2} s -> {}",
        cat.targets.len(),
        stds.len(),
        t1.elapsed().as_secs_f64(),
        cat_path.display()
    );
    println!(
        "{}",
        calibration_report(&truth, &flats.provenance, &cat, &summary.lines)
    );

    println!(
        "  {:<11} {:>5} {:>4} | {:>6} {:>15} {:>6} | {:>6} {:>13} {:>6} | {}",
        "target", "sep\"", "comp", "P true", "Pdb found [%]", "pull", "g true", "gamma found", "pull", "cut"
    );
    for tt in &truth.targets {
        let Some(t) = cat.targets.iter().find(|t| t.object == tt.object) else {
            continue;
        };
        // Match components by position angle: near-equal pairs may be labelled either way.
        let swapped = t.pa_deg.is_some_and(|pa| {
            let d = (pa - tt.pa_deg).rem_euclid(360.0);
            d > 90.0 && d < 270.0
        });
        for (i, c) in t.components.iter().enumerate() {
            let tc = &tt.components[if swapped { 1 - i } else { i }];
            let dg = (c.gamma_deg - tc.gamma_deg + 90.0).rem_euclid(180.0) - 90.0;
            println!(
                "  {:<11} {:>5.2} {:>4} | {:>6.2} {:>7.2} +- {:<5.2} {:>6.1} | {:>6.1} {:>6.1} +- {:<4.1} {:>6.1} | {}",
                if i == 0 { tt.object.as_str() } else { "" },
                tt.separation_arcsec,
                c.name,
                100.0 * tc.p,
                100.0 * c.p_debiased,
                100.0 * c.sigma_p,
                (c.p - tc.p) / c.sigma_p,
                tc.gamma_deg,
                c.gamma_deg,
                c.sigma_gamma_deg,
                dg / c.sigma_gamma_deg,
                if c.passes_cut { "pass" } else { "fail (P/sigma <= 3)" }
            );
        }
        // The science product: the binary's angle difference against the truth.
        if tt.components.len() == 2 {
            let truth_dg =
                sofipol_pipeline::catalog::fold_delta_gamma(tt.components[0].gamma_deg, tt.components[1].gamma_deg);
            match (t.delta_gamma_deg, t.sigma_delta_gamma_deg) {
                (Some(dg), Some(s)) if s > 0.0 => println!(
                    "  {:<11} {:>5} {:>4} | Delta-gamma true {:.1} deg, found {:.1} +- {:.1} deg (pull {:+.1})",
                    "",
                    "",
                    "",
                    truth_dg,
                    dg,
                    s,
                    (dg - truth_dg) / s
                ),
                (Some(dg), _) => println!(
                    "  {:<11} {:>5} {:>4} | Delta-gamma true {:.1} deg, found {:.1} deg",
                    "", "", "", truth_dg, dg
                ),
                (None, _) => println!(
                    "  {:<11} {:>5} {:>4} | Delta-gamma true {:.1} deg, none (a component fails the cut)",
                    "", "", "", truth_dg
                ),
            }
        }
    }
    println!("\n  (Pdb: P debiased (Wardle & Kronberg); P: not debiased, as in `sofipol night`; pulls use P.)");
    println!("  catalog: {}   figures: {}", cat_path.display(), fig_dir.display());
    println!(
        "  next: sofipol report {cat} -o {dir}/report.html   (the night on one page)\n        \
         sofipol stats {cat}   (Delta-gamma against random orientation)",
        cat = cat_path.display(),
        dir = cat_path
            .parent()
            .map_or_else(|| ".".into(), |p| p.display().to_string())
    );
    let incomplete = super::common::finish_outputs(outputs, true, true, "demo");
    let problems = check_against_truth(&truth.targets, &cat, PULL_LIMIT);
    if problems.is_empty() {
        println!("  check: every component's q and u within {PULL_LIMIT} sigma of the truth");
        if incomplete {
            return Ok(ExitCode::from(2));
        }
        Ok(ExitCode::SUCCESS)
    } else {
        for p in &problems {
            eprintln!("sofipol demo: check failed: {p}");
        }
        Ok(ExitCode::from(DEMO_CHECK_FAILED))
    }
}

/// Refuse, before anything is written, an output folder the demo would mix with or
/// overwrite foreign data: the demo reduces every frame of `DIR/raw`, so `DIR/raw` may hold
/// only files the demo writes itself (`names`: its frames and truth.json, or their
/// temporaries), and `DIR/catalog.json` is replaced only in the folder of an earlier demo
/// (one with `DIR/raw/truth.json`). An empty or new folder is always fine.
pub fn check_demo_dir(dir: &std::path::Path, names: &[String]) -> anyhow::Result<()> {
    let raw = dir.join("raw");
    if raw.exists() {
        let entries =
            std::fs::read_dir(&raw).map_err(|e| anyhow::anyhow!("-o {}: {}: {e}", dir.display(), raw.display()))?;
        for e in entries {
            let e = e.map_err(|e| anyhow::anyhow!("-o {}: {}: {e}", dir.display(), raw.display()))?;
            let name = e.file_name().to_string_lossy().into_owned();
            let ours = names
                .iter()
                .any(|n| *n == name || name.strip_prefix(&format!(".{n}.tmp-")).is_some());
            anyhow::ensure!(
                ours && e.file_type().is_ok_and(|t| t.is_file()),
                "-o {}: {} is not a file of the demo: the demo would reduce it with its own frames; \
                 give an empty or new folder",
                dir.display(),
                e.path().display()
            );
        }
    }
    let cat = dir.join("catalog.json");
    if cat.exists() || cat.is_symlink() {
        anyhow::ensure!(
            cat.is_file() && raw.join("truth.json").is_file(),
            "-o {}: {} exists and the folder is not an earlier demo's (no raw/truth.json): not overwritten; \
             give an empty or new folder",
            dir.display(),
            cat.display()
        );
    }
    Ok(())
}

/// What the calibration found against what the scene simulated: the flat, the offset c
/// (true (T_o - T_e)/(T_o + T_e) + p_inst cos 2 angle), the angle zero-point, parity, and
/// each standard against its table values.
pub fn calibration_report(truth: &Truth, flat: &FlatProvenance, cat: &Catalog, lines: &[String]) -> String {
    let mut out = String::from("\n  calibration derived from the night:\n");
    let mode = &flat.mode;
    let list = flat.flat_list();
    let nframes: usize = list.iter().map(|f| f.frames.len()).sum();
    let rms = truth.detector.flat_field.map(|f| f.rms);
    out += &format!(
        "    flat: {mode}, {} flat(s) from {nframes} frames{}\n",
        list.len(),
        rms.map(|r| format!("; simulated pixel response rms {:.2} %", 100.0 * r))
            .unwrap_or_default()
    );
    let c_true = truth.detector.offset_c();
    let aa = truth.scene.analyzer_angle.clone().unwrap_or_default();
    let filters = cat
        .calibration
        .as_ref()
        .and_then(|c| c.calibration())
        .map_or(&[][..], |c| &c.filters);
    if filters.is_empty() {
        out += "    no calibration (no usable standards)\n";
    }
    for f in filters {
        let name = &f.filter;
        if let Some(o) = &f.offset {
            let (c, s) = (o.c, o.sigma_c);
            out += &format!(
                "    {name}: offset c = {:.4} +- {:.4}{}\n",
                c,
                s,
                c_true
                    .map(|t| format!(" (simulated {t:.4}: {:+.1} sigma)", (c - t) / s))
                    .unwrap_or_default()
            );
        }
        if let Some(a) = &f.angles {
            let (t0, st) = (a.theta0_deg, a.sigma_theta0_deg);
            out += &format!(
                "    {name}: angle zero-point theta0 = {t0:.2} +- {st:.2} deg (simulated {:.2}: {:+.1} sigma), parity {} ({}; simulated {:+})\n",
                aa.zero_point_deg,
                (t0 - aa.zero_point_deg) / st,
                a.parity,
                if a.parity_measured { "measured" } else { "profile" },
                aa.parity
            );
        }
    }
    for s in &cat.standards {
        let m = s.measured.as_ref();
        out += &format!(
            "    standard {:<10} P = {:.2} +- {:.2} % (table {}), gamma {} {}\n",
            sofipol_calib::text::printable(&s.name),
            m.map_or(f64::NAN, |m| 100.0 * m.p),
            m.map_or(f64::NAN, |m| 100.0 * m.sigma_p),
            s.table
                .as_ref()
                .map(|t| format!("{:.2} +- {:.2} %", 100.0 * t.p, 100.0 * t.sigma_p))
                .unwrap_or_else(|| "none".into()),
            match (m, s.residual_gamma_deg) {
                (Some(m), Some(r)) => format!(
                    "{:.1} +- {:.1} deg (table {:+.1} deg off)",
                    m.gamma_deg, m.sigma_gamma_deg, r
                ),
                _ => "-".into(),
            },
            s.used_for.join(", ")
        );
    }
    for l in lines {
        out += &format!("    {}\n", sofipol_calib::text::printable(l));
    }
    out
}

/// A recovered q or u further than this many sigma from the truth fails the demo.
pub const PULL_LIMIT: f64 = 5.0;

/// Exit code of a demo whose reduction disagrees with the simulated truth (docs/cli.md).
pub const DEMO_CHECK_FAILED: u8 = 3;

/// Compare the catalog with the simulated truth: every true component must be in the
/// catalog with finite q, u and errors, and its q and u within `limit` sigma of the truth.
/// Components are matched by name after undoing an A/B swap (position angle of B off by
/// more than 90 deg from the truth). Returns one line per problem.
pub fn check_against_truth(truth: &[sofipol_pipeline::sim::TargetTruth], cat: &Catalog, limit: f64) -> Vec<String> {
    let mut problems = Vec::new();
    for tt in truth {
        let Some(t) = cat.targets.iter().find(|t| t.object == tt.object) else {
            problems.push(format!("{}: not in the catalog", tt.object));
            continue;
        };
        let swapped = t.pa_deg.is_some_and(|pa| {
            let d = (pa - tt.pa_deg).rem_euclid(360.0);
            d > 90.0 && d < 270.0
        });
        for (i, tc) in tt.components.iter().enumerate() {
            let j = if swapped { 1 - i.min(1) } else { i };
            let Some(c) = t.components.get(j) else {
                problems.push(format!(
                    "{} {}: component not measured ({:?})",
                    tt.object, tc.name, t.status
                ));
                continue;
            };
            for (what, got, want, sigma) in [("q", c.q, tc.q, c.sigma_q), ("u", c.u, tc.u, c.sigma_u)] {
                let pull = (got - want) / sigma;
                if !pull.is_finite() || pull.abs() > limit {
                    problems.push(format!(
                        "{} {}: {what} = {got:.5} +- {sigma:.5}, truth {want:.5}: pull {pull:.1} (limit {limit})",
                        tt.object, tc.name
                    ));
                }
            }
        }
    }
    problems
}

#[cfg(test)]
mod tests {
    use super::*;
    use sofipol_pipeline::catalog::Target;
    use sofipol_pipeline::sim::{ComponentTruth, TargetTruth};
    use sofipol_pipeline::stokes::model::Polarization;

    fn truth(q: [f64; 2], u: [f64; 2]) -> TargetTruth {
        let comp = |n: &str, i: usize| ComponentTruth {
            name: n.into(),
            flux: 1e5,
            intrinsic: Polarization { q: q[i], u: u[i] },
            q: q[i],
            u: u[i],
            p: q[i].hypot(u[i]),
            gamma_deg: 0.5 * u[i].atan2(q[i]).to_degrees().rem_euclid(360.0),
        };
        TargetTruth {
            object: "T".into(),
            tpl_start: "x".into(),
            ra_deg: 0.0,
            dec_deg: 0.0,
            separation_arcsec: 2.0,
            pa_deg: 30.0,
            components: vec![comp("A", 0), comp("B", 1)],
            frames: vec![],
            foreground: None,
            field_stars: vec![],
        }
    }

    fn catalog(q: [f64; 2], u: [f64; 2], sigma: f64, pa_deg: f64) -> Catalog {
        let comps: Vec<_> = ["A", "B"]
            .iter()
            .enumerate()
            .map(|(i, n)| {
                serde_json::json!({"name": n, "q": q[i], "u": u[i], "sigma_q": sigma, "sigma_u": sigma,
                    "p": q[i].hypot(u[i]), "sigma_p": sigma, "p_debiased": q[i].hypot(u[i]),
                    "gamma_deg": 0.0, "sigma_gamma_deg": 1.0, "passes_cut": true})
            })
            .collect();
        let t: Target = serde_json::from_value(serde_json::json!({
            "object": "T", "status": "ok", "components": comps, "pa_deg": pa_deg
        }))
        .unwrap();
        Catalog {
            targets: vec![t],
            ..Default::default()
        }
    }

    /// The demo's standards are entries of the built-in table with the table's values
    /// (polarized: the simulated P and angle are the table's Ks values), so the demo
    /// calibrates with the same table a user's night does.
    #[test]
    fn demo_scene_standards_are_builtin_table_entries() {
        let scene = Scene::from_toml(DEMO_SCENE, "demo").unwrap();
        let table = sofipol_pipeline::standards::StandardsTable::builtin();
        let filter = &scene.observation.filter;
        assert!(scene.standard.len() >= 3);
        let (mut unpol, mut pol) = (0, 0);
        for s in &scene.standard {
            let e = table
                .find(&s.name, filter)
                .unwrap_or_else(|| panic!("{} not in the table", s.name));
            assert!((s.p - e.p).abs() < 1e-9, "{}: scene p {} table {}", s.name, s.p, e.p);
            if e.p > 0.0 {
                pol += 1;
                assert!((s.gamma_deg - e.gamma_deg).abs() < 1e-9, "{}", s.name);
            } else {
                unpol += 1;
            }
        }
        assert!(unpol >= 2 && pol >= 1, "{unpol} unpolarized, {pol} polarized");
    }

    #[test]
    fn the_demo_folder_may_be_new_or_an_earlier_demos_but_holds_no_foreign_data() {
        let d = tempfile::tempdir().unwrap();
        let names = vec!["SOFI_demo_T_01.fits".to_string(), "truth.json".to_string()];
        let dir = d.path().join("out");
        check_demo_dir(&dir, &names).unwrap();
        // An earlier demo's folder (its files, a temporary of an interrupted write, its
        // catalog) is fine: re-running the demo replaces them.
        std::fs::create_dir_all(dir.join("raw")).unwrap();
        for n in ["SOFI_demo_T_01.fits", "truth.json", ".SOFI_demo_T_01.fits.tmp-12-0"] {
            std::fs::write(dir.join("raw").join(n), b"x").unwrap();
        }
        std::fs::write(dir.join("catalog.json"), b"{}").unwrap();
        check_demo_dir(&dir, &names).unwrap();
        // A frame of another night in raw/.
        std::fs::write(dir.join("raw/night1_0001.fits"), b"x").unwrap();
        let e = check_demo_dir(&dir, &names).unwrap_err().to_string();
        assert!(
            e.contains("night1_0001.fits") && e.contains("not a file of the demo"),
            "{e}"
        );
        std::fs::remove_file(dir.join("raw/night1_0001.fits")).unwrap();
        std::fs::create_dir(dir.join("raw/sub")).unwrap();
        assert!(check_demo_dir(&dir, &names).is_err());
        // A catalog in a folder that is not a demo's.
        let other = d.path().join("other");
        std::fs::create_dir(&other).unwrap();
        std::fs::write(other.join("catalog.json"), b"{}").unwrap();
        let e = check_demo_dir(&other, &names).unwrap_err().to_string();
        assert!(e.contains("catalog.json") && e.contains("not overwritten"), "{e}");
    }

    #[test]
    fn demo_check_passes_within_limit_and_fails_beyond_it() {
        let t = truth([0.05, -0.02], [0.01, 0.03]);
        // 4.9 sigma off in q of A: passes; 5.1 sigma: fails, naming the component and value.
        let ok = catalog([0.05 + 4.9e-3, -0.02], [0.01, 0.03], 1e-3, 30.0);
        assert!(check_against_truth(std::slice::from_ref(&t), &ok, 5.0).is_empty());
        let bad = catalog([0.05 + 5.1e-3, -0.02], [0.01, 0.03], 1e-3, 30.0);
        let p = check_against_truth(std::slice::from_ref(&t), &bad, 5.0);
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(p[0].contains("T A: q") && p[0].contains("pull 5.1"), "{p:?}");
        // u of B off by -6 sigma.
        let bad_u = catalog([0.05, -0.02], [0.01, 0.03 - 6e-3], 1e-3, 30.0);
        assert!(check_against_truth(std::slice::from_ref(&t), &bad_u, 5.0)[0].contains("T B: u"));
    }

    #[test]
    fn demo_check_undoes_an_ab_swap_and_reports_lost_components() {
        let t = truth([0.05, -0.02], [0.01, 0.03]);
        // The reduction labelled the stars the other way round (PA off by 180 deg).
        let swapped = catalog([-0.02, 0.05], [0.03, 0.01], 1e-3, 210.0);
        assert!(check_against_truth(std::slice::from_ref(&t), &swapped, 5.0).is_empty());
        // ... but the same values without the PA flip are 70 sigma off.
        let wrong = catalog([-0.02, 0.05], [0.03, 0.01], 1e-3, 30.0);
        assert_eq!(check_against_truth(std::slice::from_ref(&t), &wrong, 5.0).len(), 4);
        // A component missing, a target missing, a NaN error.
        let mut one = catalog([0.05, -0.02], [0.01, 0.03], 1e-3, 30.0);
        one.targets[0].components.pop();
        assert!(check_against_truth(std::slice::from_ref(&t), &one, 5.0)[0].contains("not measured"));
        assert!(
            check_against_truth(std::slice::from_ref(&t), &Catalog::default(), 5.0)[0].contains("not in the catalog")
        );
        let mut nan = catalog([0.05, -0.02], [0.01, 0.03], 1e-3, 30.0);
        nan.targets[0].components[1].sigma_u = f64::NAN;
        let p = check_against_truth(&[t], &nan, 5.0);
        assert!(p.len() == 1 && p[0].contains("T B: u"), "{p:?}");
    }
}
