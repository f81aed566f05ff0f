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
    /// Reduction accuracy on simulated nights: pull widths by separation bin, and time.
    Accuracy {
        /// Targets per separation bin.
        #[arg(long, default_value_t = 24)]
        targets: usize,
        /// Seed.
        #[arg(long, default_value_t = 7)]
        seed: u64,
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
            println!("  {:<28} {:>9.2} ms/frame   (one-off detector maps: {:.1} ms)", "all 15 effects", all, all_setup);
            println!("  {:<28} {:>9.2} ms/frame", "no effects", none);
            println!("  {:<28} {:>9}", "effect alone", "ms/frame (minus no-effect)");
            for k in EffectKind::ALL {
                let (t, setup) = time_frames(&[k], repeats);
                let extra = if setup > 1.0 { format!("   (setup {setup:.1} ms)") } else { String::new() };
                println!("  {:<28} {:>9.2} ms  (+{:.2}){extra}", k.name(), t, t - none);
            }
            println!("target: all effects <= 50 ms/frame on 2 cores: {}", if all <= 50.0 { "met" } else { "NOT met" });
        }
        What::Accuracy { targets, seed, reduce } => {
            let params = reduce.params()?;
            let cfg = sofipol_pipeline::accuracy::AccuracyConfig { targets_per_bin: targets, seed, ..Default::default() };
            println!(
                "sofipol bench accuracy: {} targets per bin, seeing {}\", effects [{}], method {:?}, aperture {} FWHM",
                targets, cfg.fwhm_arcsec, cfg.effects.join(", "), params.measure.method, params.measure.aperture_fwhm
            );
            let t0 = Instant::now();
            let r = sofipol_pipeline::accuracy::run(&cfg, &params);
            print!("{}", sofipol_pipeline::accuracy::table(&r));
            println!("total {:.1} s (simulation included)", t0.elapsed().as_secs_f64());
        }
    }
    Ok(ExitCode::SUCCESS)
}
