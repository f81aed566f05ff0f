//! Run the world-sampling accuracy harness:
//! `cargo run --release -p sofipol-bench --example world -- [targets per bin]`, or write
//! one drawn target's frames to look at: `... --example world -- write BIN T DIR`;
//! `-- N nocal` leaves the night's calibration unused, `-- N noinst` turns the instrument off,
//! `noell` / `nonl` only the PSF ellipticity / the non-linearity (`full`: everything); a
//! third argument is the seed. Environment: `WORLD_JSON=file` writes every target (conditions,
//! pulls, photometry method, dither chi2, per-orientation F) as JSON; `WORLD_BETA_FREE=1`
//! fits Moffat beta in every frame for every target (`[measure] beta_from_stack = false`).
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::env::temp_dir().join(format!("sofipol-world-{}", std::process::id()));
    let mut cfg = sofipol_bench::world::WorldConfig::new(&dir);
    if args.get(1).map(String::as_str) == Some("write") {
        let (bin, t): (usize, usize) = (args[2].parse().unwrap(), args[3].parse().unwrap());
        let (lo, hi) = (cfg.bins_arcsec[bin], cfg.bins_arcsec[bin + 1]);
        let (tt, cond, _) = sofipol_bench::world::write_target(&cfg, bin, t, lo, hi, std::path::Path::new(&args[4]));
        println!("{cond:?}\n{}", serde_json::to_string_pretty(&tt.components).unwrap());
        return;
    }
    cfg.targets_per_bin = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(6);
    // `-- N nocal`: the instrument without its calibration; `-- N noinst`: no instrument effects.
    if let Some(seed) = args.get(3).and_then(|s| s.parse().ok()) {
        cfg.seed = seed;
    }
    match args.get(2).map(String::as_str) {
        Some("nocal") => cfg.calibrate = false,
        Some("noinst") => cfg.instrument = false,
        Some("noell") => cfg.ellipticity = false,
        Some("nonl") => cfg.nonlinearity = false,
        _ => {}
    }
    let t0 = std::time::Instant::now();
    let mut params = sofipol_pipeline::reduce::TargetParams::default();
    if std::env::var("WORLD_BETA_FREE").is_ok() {
        params.measure.beta_from_stack = false;
    }
    let bins = sofipol_bench::world::run(&cfg, &params);
    println!("{:?}", sofipol_bench::world::draw_instrument(&cfg));
    print!("{}", sofipol_bench::world::table(&bins, true));
    // `WORLD_JSON=path`: every target's conditions, pulls and sigmas, for a closer look.
    if let Ok(p) = std::env::var("WORLD_JSON") {
        std::fs::write(&p, serde_json::to_string(&bins).unwrap()).unwrap();
    }
    println!("{:.1} s", t0.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&dir);
}
