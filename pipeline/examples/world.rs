//! Run the world-sampling accuracy harness: `cargo run --release -p sofipol-pipeline --example world -- [targets per bin]`.
fn main() {
    let n: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(6);
    let dir = std::env::temp_dir().join(format!("sofipol-world-{}", std::process::id()));
    let mut cfg = sofipol_pipeline::world::WorldConfig::new(&dir);
    cfg.targets_per_bin = n;
    let t0 = std::time::Instant::now();
    let bins = sofipol_pipeline::world::run(&cfg, &Default::default());
    print!("{}", sofipol_pipeline::world::table(&bins, true));
    println!("{:.1} s", t0.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&dir);
}
