//! Acceptance of the accuracy report's foreground rows: on calibrated nights seen through a
//! foreground field (mean 2 %, rms 0.4 % per q and u, coherence 90") with field stars from
//! a K-band luminosity function, the binaries' intrinsic q, u come out with honest errors
//! once each binary's measured foreground is subtracted (its covariance added), and are
//! far off without field stars (the foreground left in). Two nights, wide pairs (each bin
//! is a night of its own, with its standards).
use sofipol_bench::accuracy::{run_seeds, AccuracyConfig, BinReport};
use sofipol_pipeline::reduce::TargetParams;

/// Pulls, rms pull, rms true error and Delta-gamma pulls pooled over the bins.
fn pooled(r: &[BinReport]) -> (usize, f64, f64, Vec<f64>, usize) {
    let (mut p2, mut e2, mut n) = (0.0, 0.0, 0usize);
    for b in r.iter().filter(|b| b.n_pulls > 0) {
        p2 += b.rms_pull.powi(2) * b.n_pulls as f64;
        e2 += b.rms_error.powi(2) * b.n_pulls as f64;
        n += b.n_pulls;
    }
    let dg = r.iter().flat_map(|b| b.delta_gamma_pulls.iter().copied()).collect();
    let missing = r.iter().map(|b| b.missing).sum();
    (
        n,
        (p2 / n.max(1) as f64).sqrt(),
        (e2 / n.max(1) as f64).sqrt(),
        dg,
        missing,
    )
}

fn run(field_stars: bool) -> (usize, f64, f64, Vec<f64>, String) {
    // missing: components of binaries without a foreground estimate (too few field stars).
    let cfg = AccuracyConfig::with_foreground(AccuracyConfig {
        bins_arcsec: vec![1.6, 2.5, 4.0],
        targets_per_bin: 6,
        ..Default::default()
    });
    let mut params = TargetParams::default();
    params.measure.field_stars = field_stars;
    let (_, bins) = run_seeds(&cfg, &params, &[41, 42]);
    let (n, rms, err, dg, missing) = pooled(&bins);
    eprintln!("field stars {field_stars}: {missing} components missing");
    let outliers: Vec<String> = bins.iter().flat_map(|b| b.outliers.iter().cloned()).collect();
    (
        n,
        rms,
        err,
        dg,
        format!("{}{}", sofipol_bench::accuracy::table(&bins), outliers.join("\n")),
    )
}

#[test]
fn the_measured_foreground_makes_the_intrinsic_polarization_honest() {
    let (n, rms, err, dg, t) = run(true);
    let (n0, rms0, err0, _, t0) = run(false);
    let dg_rms = (dg.iter().map(|x| x * x).sum::<f64>() / dg.len().max(1) as f64).sqrt();
    eprintln!(
        "field stars: {n} pulls, rms {rms:.3}, rms error {:.3e}; Delta-gamma {} pulls rms {dg_rms:.3}\n{t}\
         no field stars: {n0} pulls, rms {rms0:.3}, rms error {:.3e}\n{t0}",
        err,
        dg.len(),
        err0
    );
    assert!(n >= 40 && n0 >= 40, "too few pulls: {n} {n0}");
    assert!(
        (0.75..=1.3).contains(&rms),
        "rms pull {rms:.3} with the foreground subtracted\n{t}"
    );
    assert!(
        rms0 > 3.0 && err0 > 3.0 * err,
        "without field stars: rms pull {rms0:.3}, error {err0:.3e} vs {err:.3e}\n{t0}"
    );
    assert!(dg.len() >= 6, "{} binaries with a corrected Delta-gamma", dg.len());
}
