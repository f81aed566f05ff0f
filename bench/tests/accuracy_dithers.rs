//! Two, three and four dithers per orientation reproduce q and u within their errors (the
//! accuracy harness on realistic simulated nights).
use sofipol_bench::accuracy::{run, table, AccuracyConfig};
use sofipol_pipeline::reduce::TargetParams;

/// Pulls of 12 simulated targets (separations 1.6-5", the harness's realistic effects:
/// bad pixels, cosmic rays, seeing changes...) observed at `orientations` with `dithers`
/// dithers each.
fn dither_pulls(orientations: &[f64], dithers: usize) -> (f64, usize, String) {
    let cfg = AccuracyConfig {
        bins_arcsec: vec![1.6, 3.0, 5.0],
        targets_per_bin: 6,
        seed: 17,
        orientations_deg: orientations.to_vec(),
        dithers,
        ..Default::default()
    };
    let r = run(&cfg, &TargetParams::default());
    let (mut s2, mut n) = (0.0, 0usize);
    for b in &r {
        s2 += b.rms_pull.powi(2) * b.n_pulls as f64;
        n += b.n_pulls;
    }
    let missing = r.iter().map(|b| b.missing).sum();
    ((s2 / n.max(1) as f64).sqrt(), missing, table(&r))
}

/// 1, 3 and 4 dithers: with 2 dithers per orientation the target sits on the
/// same pixels in half of the frames, so the per-pixel median of the sequence used to
/// find bad pixels kept half the star, and its core was masked as a defect: fluxes a
/// tenth of the truth, rms pulls 8-220 and a quarter of the components lost. The stack is
/// now built per dither position (badpix::detect_bad_pixels_at). 2 dithers at 2 and 4
/// orientations and 3 and 4 dithers give q and u within their errors (48 pulls each:
/// rms known to ~10 %), every component measured.
#[test]
fn two_three_and_four_dithers_reproduce_q_and_u_within_their_errors() {
    for (orients, d) in [
        (&[0.0, 45.0][..], 2),
        (&[0.0, 45.0, 90.0, 135.0][..], 2),
        (&[0.0, 45.0][..], 3),
        (&[0.0, 45.0][..], 4),
    ] {
        let (rms, missing, tab) = dither_pulls(orients, d);
        assert!(
            (0.6..=1.4).contains(&rms) && missing == 0,
            "{} orientations x {d} dithers: rms pull {rms:.2}, {missing} components missing\n{tab}",
            orients.len()
        );
    }
}
