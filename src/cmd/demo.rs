//! `sofipol demo`: simulate the embedded demo scene into ./sofipol-demo/ and report.
use std::path::PathBuf;
use std::process::ExitCode;

use rayon::prelude::*;
use sofipol_pipeline::catalog::{Catalog, SCHEMA_VERSION};
use sofipol_pipeline::reduce::run::reduce_sequence;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::Scene;
use sofipol_pipeline::{scan, sequence};

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
    let truth = super::simulate::simulate_into(scene, profile.clone(), &raw, None, args.quiet)?;
    let nframes: usize = truth.targets.iter().map(|t| t.frames.len()).sum();
    println!(
        "  wrote {nframes} frames and truth.json in {:.2} s",
        t0.elapsed().as_secs_f64()
    );

    // Reduce the night exactly as a user would: scan, classify, group, reduce.
    let t1 = std::time::Instant::now();
    let params = TargetParams::default();
    let files = scan::find_files(&raw)?;
    let s = scan::classify_all(&files, &profile);
    let seqs = sequence::group(s.science, &profile);
    let fig_dir = args.output.join("figures");
    std::fs::create_dir_all(&fig_dir)?;
    let outs: Vec<_> = seqs
        .par_iter()
        .map(|q| {
            let out = reduce_sequence(q, &profile, &params, None, None, true);
            let png = fig_dir.join(format!("{}.png", sofipol_pipeline::night::slug(&q.object)));
            if let Err(e) = sofipol_pipeline::plots::target::outcome_png(&png, &out) {
                eprintln!("sofipol: warning: {}: {e}", png.display());
            }
            out
        })
        .collect();
    let mut cat = Catalog {
        schema_version: SCHEMA_VERSION.into(),
        ..Default::default()
    };
    cat.failures.extend(s.unreadable);
    for o in outs {
        cat.failures.extend(o.failures);
        cat.targets.push(o.target);
    }
    cat.provenance = super::report::provenance(&profile, &params);
    let cat_path = args.output.join("catalog.json");
    sofipol_pipeline::io::write_json_atomic(&cat_path, &cat)?;
    println!(
        "  reduced {} sequences in {:.2} s -> {}\n",
        cat.targets.len(),
        t1.elapsed().as_secs_f64(),
        cat_path.display()
    );

    println!(
        "  {:<11} {:>5} {:>4} | {:>6} {:>15} {:>6} | {:>6} {:>13} {:>6} | {}",
        "target", "sep\"", "comp", "P true", "P found [%]", "pull", "g true", "gamma found", "pull", "cut"
    );
    for tt in &truth.targets {
        let Some(t) = cat.targets.iter().find(|t| t.object == tt.object) else {
            continue;
        };
        // Match components by position angle: near-equal pairs may be labelled either way.
        let swapped = t.extra.get("pa_deg").and_then(|v| v.as_f64()).is_some_and(|pa| {
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
    }
    println!("\n  (P found is debiased (Wardle & Kronberg); pulls use the raw P.)");
    println!("  catalog: {}   figures: {}", cat_path.display(), fig_dir.display());
    Ok(ExitCode::SUCCESS)
}
