//! The half-wave-plate accuracy harness on more nights than the report runs
//! (`bench/src/accuracy_hwp.rs`): the pooled pulls and true errors of one configuration.
//!
//! ```text
//! cargo run --release -p sofipol-bench --example hwp_accuracy -- NIGHTS [OPTION...]
//!   NIGHTS     seeds 1..=NIGHTS, each a night of 6 stars
//!   ls         score the least squares over the frames instead of the catalog's component
//!   nocr       no cosmic rays
//!   cr=R       R cosmic-ray hits per frame (default 1)
//!   cycles=N   N plate cycles per star (default 2)
//!   KEY=VALUE  a profile override of the reduction (`--set` of `sofipol night`)
//! ```
use sofipol_bench::accuracy_hwp::{run_seeds, HwpAccuracyConfig, HwpEstimate};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let nights: u64 = args.first().map_or(8, |s| s.parse().expect("NIGHTS: a number"));
    let mut cfg = HwpAccuracyConfig::default();
    for a in args.iter().skip(1) {
        if a == "ls" {
            cfg.estimate = HwpEstimate::LeastSquares;
        } else if a == "nocr" {
            cfg.effects.retain(|e| e != "cosmic_rays");
        } else if let Some(c) = a.strip_prefix("cycles=") {
            cfg.cycles = c.parse().expect("cycles=N");
        } else if let Some(c) = a.strip_prefix("cr=") {
            cfg.cosmic_rays_per_frame = c.parse().expect("cr=R");
        } else {
            cfg.reduce_set.push(a.clone());
        }
    }
    let t0 = std::time::Instant::now();
    let seeds: Vec<u64> = (1..=nights).collect();
    let (b, per_night) = run_seeds(&cfg, &seeds);
    let repaired: u64 = per_night.iter().map(|n| n.repaired_pixels).sum();
    let n = b.n_pulls as f64;
    println!(
        "{nights} nights, N = {} pulls: rms {:.3} +- {:.3}, mean {:+.3} +- {:.3}; rms error {:.3e}, median sigma_q {:.3e}; \
         {} missing; {repaired} pixels repaired; {:.4} s per star; {:.1} s in all",
        b.n_pulls,
        b.rms_pull,
        1.0 / (2.0 * n).sqrt(),
        b.mean_pull,
        1.0 / n.sqrt(),
        b.rms_error,
        b.median_sigma,
        b.missing,
        b.median_reduce_s,
        t0.elapsed().as_secs_f64()
    );
    for o in &b.outliers {
        println!("  {o}");
    }
}
