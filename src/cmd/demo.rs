//! `sofipol demo`: simulate the embedded demo scene into ./sofipol-demo/ and report.
use std::path::PathBuf;
use std::process::ExitCode;

use sofipol_pipeline::sim::Scene;

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
    println!("sofipol demo: simulating the embedded scene '{}' (seed {}) into {}", scene.name, scene.seed, raw.display());
    println!("  effects: {}", scene.effects.iter().map(|e| e.name()).collect::<Vec<_>>().join(", "));
    let truth = super::simulate::simulate_into(scene, profile, &raw, None, args.quiet)?;
    let nframes: usize = truth.targets.iter().map(|t| t.frames.len()).sum();
    println!("  wrote {nframes} frames and truth.json in {:.2} s", t0.elapsed().as_secs_f64());
    println!("\n  {:<12} {:>7} {:>4} {:>8} {:>9}", "target", "sep\"", "comp", "P true", "gamma true");
    for t in &truth.targets {
        for c in &t.components {
            println!("  {:<12} {:>7.2} {:>4} {:>7.2}% {:>8.1}°", t.object, t.separation_arcsec, c.name, 100.0 * c.p, c.gamma_deg);
        }
    }
    Ok(ExitCode::SUCCESS)
}
