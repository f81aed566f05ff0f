//! Acceptance of the accuracy report's half-wave-plate row marked default: on simulated
//! NIRC2 nights under pupil tracking with cosmic rays (`sofipol_bench::accuracy_hwp`), the
//! catalog's q, u on the sky (the complete cycles combined) and its adopted error give
//! pulls whose rms, pooled over 8 nights, is what that error promises.
//!
//! The adopted error of two cycles is `sigma max(1, sqrt(chi2))`, chi2 of the two cycles'
//! difference (1 degree of freedom, independent of their weighted mean): with honest
//! propagated errors the pull is `z / max(1, sqrt(X))`, z unit normal, X chi-square of 1
//! degree of freedom, so the rms pull is `sqrt(E[1 / max(1, X)])` = 0.922 (computed below by
//! quadrature), not 1. Control: the same frames with the field's rotation ignored must
//! fail the same band.
use sofipol_bench::accuracy_hwp::{run_seeds, simulate_and_reduce, HwpAccuracyConfig};

/// `E[1 / max(1, X)]`, X chi-square of 1 degree of freedom: midpoint rule in `t = sqrt(x)`
/// (density of t: 2 phi(t), t >= 0), to 1e-6.
fn expected_pull_variance() -> f64 {
    let (n, t_max) = (200_000, 12.0);
    let dt = t_max / n as f64;
    (0..n)
        .map(|i| {
            let t = (i as f64 + 0.5) * dt;
            let phi = (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
            2.0 * phi * dt / (t * t).max(1.0)
        })
        .sum()
}

const SEEDS: [u64; 8] = [1, 2, 3, 4, 5, 6, 7, 8];

#[test]
fn half_wave_plate_default_pulls_are_what_its_errors_promise() {
    let v = expected_pull_variance();
    assert!((v - 0.849_32).abs() < 1e-4, "E[1/max(1, X)] = {v}");
    let expected = v.sqrt();
    let cfg = HwpAccuracyConfig::default();
    let (b, nights) = run_seeds(&cfg, &SEEDS);
    let n = b.n_pulls as f64;
    // Standard error of the rms of n pulls z / max(1, sqrt(X)): sqrt(Var(p^2) / n) / (2 rms),
    // Var(p^2) = E[z^4] E[1 / max(1, X)^2] - v^2 <= 3 v - v^2 (1 / max(1, X)^2 <= 1 / max(1, X)).
    let se = ((3.0 * v - v * v) / n).sqrt() / (2.0 * expected);
    let repaired: u64 = nights.iter().map(|n| n.repaired_pixels).sum();
    eprintln!(
        "default: N = {}, rms pull {:.3} (expected {expected:.3} +- {se:.3}), mean {:+.3} +- {:.3}, rms error {:.3e}, median sigma_q {:.3e}, \
         {} missing, {repaired} pixels repaired as cosmic-ray hits, {:.4} s per star\n{}",
        b.n_pulls,
        b.rms_pull,
        b.mean_pull,
        1.0 / n.sqrt(),
        b.rms_error,
        b.median_sigma,
        b.missing,
        b.median_reduce_s,
        b.outliers.join("\n")
    );
    assert_eq!(b.missing, 0, "{:?}", b.outliers);
    assert_eq!(b.n_pulls, 2 * cfg.stars * SEEDS.len());
    assert!(
        (b.rms_pull - expected).abs() < 3.0 * se,
        "rms pull {:.3}, expected {expected:.3} +- {se:.3}",
        b.rms_pull
    );
    assert!(b.mean_pull.abs() < 3.0 / n.sqrt(), "mean pull {:+.3}", b.mean_pull);
    // Cosmic rays were simulated, and the reduction repaired pixels.
    assert!(repaired > 0, "no pixel repaired");

    let rotation_ignored = HwpAccuracyConfig {
        reduce_set: vec!["field_rotation.kind=\"sky_fixed\"".into()],
        ..cfg
    };
    let (c, _) = run_seeds(&rotation_ignored, &SEEDS[..4]);
    eprintln!(
        "control, rotation ignored: N = {}, rms pull {:.2}",
        c.n_pulls, c.rms_pull
    );
    assert!(
        c.rms_pull > expected + 6.0 * se,
        "rotation ignored: rms pull {:.3}",
        c.rms_pull
    );
}

/// The same 8 nights with and without cosmic rays (the simulator adds them last, from their
/// own random stream, so the frames differ by the hits only): a frame's F may move by more
/// than 2 sigma_F through cosmic rays in at most 1 % of the frames, and the sky frames of
/// the nights without cosmic rays have no pixel repaired. A hit in a sky frame lands in the
/// matched sky of every frame at its plate position and in the flat: unrepaired, it moved
/// the F of all 48 frames of one of these nights by 4-7 sigma_F.
#[test]
fn cosmic_rays_move_few_frames() {
    let cfg = HwpAccuracyConfig::default();
    let (mut frames, mut moved, mut sky_repaired) = (0, Vec::new(), 0);
    for seed in SEEDS {
        let with = HwpAccuracyConfig { seed, ..cfg.clone() };
        let mut without = with.clone();
        without.effects.retain(|e| e != "cosmic_rays");
        let a = simulate_and_reduce(&with).1.expect("night with cosmic rays reduced");
        let b = simulate_and_reduce(&without)
            .1
            .expect("night without cosmic rays reduced");
        assert_eq!(
            b.sky_cosmic_ray_pixels, 0,
            "seed {seed}: sky pixels repaired without cosmic rays"
        );
        sky_repaired += a.sky_cosmic_ray_pixels;
        assert_eq!(a.targets.len(), b.targets.len());
        for (ta, tb) in a.targets.iter().zip(&b.targets) {
            assert_eq!(ta.frames.len(), tb.frames.len(), "seed {seed} {}", ta.name);
            for (fa, fb) in ta.frames.iter().zip(&tb.frames) {
                frames += 1;
                let z = (fa.f - fb.f) / fb.sigma_f;
                if z.abs() > 2.0 {
                    moved.push(format!(
                        "seed {seed} {} {}: F moved by {z:+.2} sigma_F (o {:+.0}, e {:+.0} ADU; pixels repaired {:?})",
                        ta.name,
                        fa.file,
                        fa.o - fb.o,
                        fa.e - fb.e,
                        fa.cosmic_ray_pixels
                    ));
                }
            }
        }
    }
    eprintln!(
        "{frames} frames, {} moved beyond 2 sigma_F by cosmic rays, {sky_repaired} sky-frame pixels repaired\n{}",
        moved.len(),
        moved.join("\n")
    );
    assert_eq!(frames, 8 * SEEDS.len() * cfg.stars);
    assert!(sky_repaired > 0, "no sky-frame pixel repaired");
    assert!(
        moved.len() as f64 <= 0.01 * frames as f64,
        "{} of {frames} frames moved beyond 2 sigma_F",
        moved.len()
    );
}
