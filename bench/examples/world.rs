//! Run the world-sampling accuracy harness:
//! `cargo run --release -p sofipol-bench --example world -- [targets per bin]`, or write
//! one drawn target's frames to look at: `... --example world -- write BIN T DIR [SEED]`;
//! `-- N nocal` leaves the night's calibration unused, `-- N noinst` turns the instrument off,
//! `noell` / `nonl` only the PSF ellipticity / the non-linearity, `fg` adds the
//! interstellar foreground field (`foreground_field`; `full`: everything as default); a
//! third argument is the seed, or seeds (`13,15,21`: every night's table, then the bins
//! pooled over the nights). Environment: `WORLD_JSON=file` writes every target (conditions,
//! pulls, photometry method, dither chi2, per-orientation F) as JSON; `WORLD_BETA_FREE=1`
//! fits Moffat beta in every frame for every target (`[measure] beta_from_stack = false`);
//! `WORLD_SEPARATE_BEAMS=1` fits the o and e beams of each exposure on their own
//! (`[measure] joint_beams = false`); `WORLD_CIRCULAR=1` circular Moffats for PSF-fit pairs
//! (`[measure] psf_elliptical = false`); `WORLD_PSF_BELOW=x` sets
//! `[measure] psf_photometry_below_fwhm`.
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = std::env::temp_dir().join(format!("sofipol-world-{}", std::process::id()));
    let mut cfg = sofipol_bench::world::WorldConfig::new(&dir);
    if args.get(1).map(String::as_str) == Some("write") {
        let (bin, t): (usize, usize) = (args[2].parse().unwrap(), args[3].parse().unwrap());
        if let Some(seed) = args.get(5).and_then(|s| s.parse().ok()) {
            cfg.seed = seed;
        }
        let (lo, hi) = (cfg.bins_arcsec[bin], cfg.bins_arcsec[bin + 1]);
        let (tt, cond, _) = sofipol_bench::world::write_target(&cfg, bin, t, lo, hi, std::path::Path::new(&args[4]));
        println!("{cond:?}\n{}", serde_json::to_string_pretty(&tt.components).unwrap());
        return;
    }
    cfg.targets_per_bin = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(6);
    // `-- N nocal`: the instrument without its calibration; `-- N noinst`: no instrument effects.
    let seeds: Vec<u64> = match args.get(3) {
        Some(list) => list.split(',').map(|s| s.parse().expect("a seed")).collect(),
        None => vec![cfg.seed],
    };
    match args.get(2).map(String::as_str) {
        Some("nocal") => cfg.calibrate = false,
        Some("noinst") => cfg.instrument = false,
        Some("noell") => cfg.ellipticity = false,
        Some("nonl") => cfg.nonlinearity = false,
        Some("fg") => cfg.foreground_field = true,
        _ => {}
    }
    let t0 = std::time::Instant::now();
    let mut params = sofipol_pipeline::reduce::TargetParams::default();
    if std::env::var("WORLD_BETA_FREE").is_ok() {
        params.measure.beta_from_stack = false;
    }
    if std::env::var("WORLD_CIRCULAR").is_ok() {
        params.measure.psf_elliptical = false;
    }
    if std::env::var("WORLD_SEPARATE_BEAMS").is_ok() {
        params.measure.joint_beams = false;
    }
    if let Some(x) = std::env::var("WORLD_PSF_BELOW").ok().and_then(|s| s.parse().ok()) {
        params.measure.psf_photometry_below_fwhm = x;
    }
    let mut nights = Vec::new();
    for &seed in &seeds {
        cfg.seed = seed;
        let bins = sofipol_bench::world::run(&cfg, &params);
        println!("seed {seed}: {:?}", sofipol_bench::world::draw_instrument(&cfg));
        print!("{}", sofipol_bench::world::table(&bins, true));
        nights.push(bins);
    }
    let bins = sofipol_bench::world::pool_nights(&nights);
    if seeds.len() > 1 {
        println!("pooled over seeds {seeds:?}:");
        print!("{}", sofipol_bench::world::table(&bins, false));
    }
    // `WORLD_JSON=path`: every target's conditions, pulls and sigmas, for a closer look.
    if let Ok(p) = std::env::var("WORLD_JSON") {
        std::fs::write(&p, serde_json::to_string(&bins).unwrap()).unwrap();
    }
    println!("{:.1} s", t0.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&dir);
}
