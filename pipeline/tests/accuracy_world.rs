//! Acceptance of the reduction on conditions drawn from the ranges real nights show
//! (pipeline/src/world.rs: seeing and beta per target with frame-to-frame seeing changes,
//! fractional and tilted e-o offsets, the primary anywhere in the strip, fluxes from 2e3
//! ADU, 2 and 4 orientations, float and 16-bit FITS read back through the file path).
//! Both sides are asserted: errors neither too small nor too large.
use sofipol_pipeline::world::{run, table, WorldConfig};

#[test]
fn pulls_are_unit_wide_and_unbiased_on_sampled_conditions() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = WorldConfig::new(dir.path());
    cfg.targets_per_bin = 8;
    let bins = run(&cfg, &Default::default());
    let report = table(&bins, true);
    eprintln!("{report}");
    let mut all = Vec::new();
    for b in &bins {
        // ~30 pulls per bin: the rms of unit Gaussians spreads by 13 % (1 sigma).
        assert!(b.n_pulls >= 24, "{report}");
        assert!(
            (0.7..=1.35).contains(&b.rms_pull),
            "bin {:?}: rms {}\n{report}",
            b.sep_arcsec,
            b.rms_pull
        );
        assert!(
            b.mean_pull.abs() <= 0.45,
            "bin {:?}: mean {}\n{report}",
            b.sep_arcsec,
            b.mean_pull
        );
        assert_eq!(b.relabelled, 0, "{report}");
        for t in &b.targets {
            all.extend(t.pulls.iter().copied());
        }
    }
    // Pooled over every bin (~190 pulls, 1-sigma spread of the rms 5 %).
    let n = all.len() as f64;
    let rms = (all.iter().map(|p| p * p).sum::<f64>() / n).sqrt();
    let mean = all.iter().sum::<f64>() / n;
    assert!((0.85..=1.15).contains(&rms), "pooled rms {rms}\n{report}");
    assert!(mean.abs() <= 0.2, "pooled mean {mean}\n{report}");
    // Components lost only where they are hard to detect: pairs closer than 0.8" or B
    // fainter than 3e3 ADU.
    for b in &bins {
        for t in &b.targets {
            if t.missing > 0 {
                let hard = t.separation_arcsec < 0.8 || t.flux_a_adu * t.flux_ratio < 3e3;
                assert!(hard, "{} lost a component: {}\n{report}", t.object, t.note);
            }
        }
    }
}
