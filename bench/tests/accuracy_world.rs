//! Acceptance of the reduction on conditions drawn from the ranges real nights show
//! (bench/src/world/): seeing per target with FWHM +-20 % and Moffat beta 2.5-4 and
//! axis ratio 0.9-1 drawn per frame, fractional and tilted e-o offsets, the primary anywhere
//! in the strip, fluxes from 2e3 ADU, 2 and 4 orientations, float and 16-bit FITS read back
//! through the file path, and every instrument effect of one night (1 % pixel response with
//! vignetting, k = T_e/T_o 0.96-0.99, instrumental polarization 0.3 %, analyzer zero-point
//! and parity, non-linearity, saturation) with the calibration the same night provides
//! (dome flats and four standards through the same detector). Both sides are asserted:
//! errors neither too small nor too large. Eight nights (seeds 13, 15, 17-22: each its own
//! instrument, calibration and targets), 16 targets per bin each, pooled per bin: a night's
//! calibration is common to all its targets, so one night's rms per bin spreads by ~0.2 and
//! only many nights can carry a band (docs/accuracy.md shows the same band on eight other
//! nights, seeds 31-38).
use sofipol_bench::world::{pool_nights, run, table, WorldBin, WorldConfig};

fn pooled(bins: &[WorldBin]) -> (f64, f64, usize) {
    let all: Vec<f64> = bins
        .iter()
        .flat_map(|b| b.targets.iter().flat_map(|t| t.pulls.iter().copied()))
        .collect();
    let n = all.len() as f64;
    (
        (all.iter().map(|p| p * p).sum::<f64>() / n).sqrt(),
        all.iter().sum::<f64>() / n,
        all.len(),
    )
}

#[test]
fn pulls_are_unit_wide_and_unbiased_on_a_sampled_night_with_its_calibration() {
    let mut nights = Vec::new();
    let mut report = String::new();
    for seed in [13, 15, 17, 18, 19, 20, 21, 22] {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = WorldConfig::new(dir.path());
        cfg.targets_per_bin = 16;
        cfg.seed = seed;
        let bins = run(&cfg, &Default::default());
        report += &format!("night seed {seed}:\n{}", table(&bins, true));
        nights.push(bins);
    }
    let bins = pool_nights(&nights);
    report += &format!("the eight nights:\n{}", table(&bins, false));
    eprintln!("{report}");
    for b in &bins {
        // ~450 pulls per bin: the rms of unit Gaussian pulls spreads by 1/sqrt(2n) = 3.3 %
        // (1 sigma), and the nights' calibrations add their share. Measured: 0.906-1.075 on
        // these nights, 0.958-1.063 on seeds 31-38; 0.88-1.12 holds both with room.
        assert!(b.n_pulls >= 400, "{report}");
        // Every bin, close pairs too, both sides: errors neither too small nor too large.
        assert!(
            (0.88..=1.12).contains(&b.rms_pull),
            "bin {:?}: rms {}\n{report}",
            b.sep_arcsec,
            b.rms_pull
        );
        // The mean of n unit pulls spreads by 1/sqrt(n) (0.047 for 450): 3 sigma per bin; the
        // pooled mean below is held to 0.1.
        let lim = 3.0 / (b.n_pulls as f64).sqrt();
        assert!(
            b.mean_pull.abs() <= lim,
            "bin {:?}: mean {} (limit {lim})\n{report}",
            b.sep_arcsec,
            b.mean_pull
        );
        assert_eq!(b.relabelled, 0, "{report}");
    }
    // Pooled over every bin (~2700 pulls, 1-sigma spread of the rms 1.4 %, of the mean 0.02).
    let (rms, mean, n) = pooled(&bins);
    eprintln!("pooled: {n} pulls, rms {rms:.3}, mean {mean:+.3}");
    assert!((0.9..=1.1).contains(&rms), "pooled rms {rms}\n{report}");
    assert!(mean.abs() <= 0.1, "pooled mean {mean}\n{report}");
    for b in &bins {
        for t in &b.targets {
            if t.saturated {
                // A saturated star is refused (flagged `saturated`) or not measured, never
                // silently measured.
                assert!(
                    t.refused + t.missing >= 1,
                    "{}: saturated A measured without flag: {}\n{report}",
                    t.object,
                    t.note
                );
            } else if t.missing > 0 || t.refused > 0 {
                // Components lost only where they are hard to detect: pairs closer than 0.8"
                // or B fainter than 3e3 ADU.
                let hard = t.separation_arcsec < 0.8 || t.flux_a_adu * t.flux_ratio < 3e3;
                assert!(hard, "{} lost a component: {}\n{report}", t.object, t.note);
            }
        }
    }
    assert!(bins.iter().any(|b| b.targets.iter().any(|t| t.saturated)));
}
