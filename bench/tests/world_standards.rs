//! The world night's standards are drawn from their table values and errors: over many
//! nights, the true (q, u) of each standard of the calibration scene scatter about the
//! table's as its errors say (the calibration's covariance counts that scatter: standards
//! exactly at their table values make every calibrated sigma_q too large).
use sofipol_bench::world::{
    calibration_scene, draw_instrument, world_standards_table, WorldConfig, WORLD_NIGHT_STANDARDS,
};

/// Mean and standard deviation.
fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    (m, (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)).sqrt())
}

#[test]
fn the_world_standards_scatter_about_their_table_values_as_its_errors_say() {
    let n = 2000;
    let dir = std::env::temp_dir();
    let table = world_standards_table();
    // Per standard: the drawn (p, gamma), and (q, u).
    let mut draws: Vec<Vec<(f64, f64)>> = vec![Vec::new(); WORLD_NIGHT_STANDARDS.len()];
    for seed in 0..n as u64 {
        let mut cfg = WorldConfig::new(&dir);
        cfg.seed = seed;
        let scene = calibration_scene(&cfg, &draw_instrument(&cfg));
        assert_eq!(scene.standard.len(), WORLD_NIGHT_STANDARDS.len());
        for (i, s) in scene.standard.iter().enumerate() {
            assert_eq!(s.name, WORLD_NIGHT_STANDARDS[i]);
            draws[i].push((s.p, s.gamma_deg));
        }
    }
    for (name, d) in WORLD_NIGHT_STANDARDS.iter().zip(&draws) {
        let e = table.find(name, "Ks").unwrap();
        if e.polarized() {
            // p ~ N(p, sigma_p), gamma ~ N(gamma, sigma_gamma).
            let (mp, sp) = mean_sd(&d.iter().map(|x| x.0).collect::<Vec<_>>());
            let (mg, sg) = mean_sd(&d.iter().map(|x| x.1).collect::<Vec<_>>());
            eprintln!(
                "{name}: p {mp:.5} sd {sp:.5} (table {} +- {}); gamma {mg:.3} sd {sg:.3} (table {} +- {})",
                e.p, e.sigma_p, e.gamma_deg, e.sigma_gamma_deg
            );
            let tol = 4.0 / (n as f64).sqrt();
            assert!((mp - e.p).abs() < tol * e.sigma_p, "{name}: mean p {mp}");
            assert!(
                (mg - e.gamma_deg).abs() < tol * e.sigma_gamma_deg,
                "{name}: mean gamma {mg}"
            );
            // The sd of n Gaussian draws has a relative error of 1/sqrt(2n) (1.6 %).
            assert!(
                (sp / e.sigma_p - 1.0).abs() < 0.07,
                "{name}: sd p {sp} vs {}",
                e.sigma_p
            );
            assert!(
                (sg / e.sigma_gamma_deg - 1.0).abs() < 0.07,
                "{name}: sd gamma {sg} vs {}",
                e.sigma_gamma_deg
            );
        } else {
            // (q, u) ~ table (q, u) + N(0, sigma_p^2 / 2) each.
            let t = 2.0 * e.gamma_deg.to_radians();
            let (q0, u0) = (e.p * t.cos(), e.p * t.sin());
            let qu = |k: usize| -> Vec<f64> {
                d.iter()
                    .map(|&(p, g)| {
                        let a = 2.0 * g.to_radians();
                        if k == 0 {
                            p * a.cos() - q0
                        } else {
                            p * a.sin() - u0
                        }
                    })
                    .collect()
            };
            let k = e.sigma_p / 2f64.sqrt();
            for (c, v) in ["q", "u"].iter().zip([qu(0), qu(1)]) {
                let (m, s) = mean_sd(&v);
                eprintln!("{name}: {c} - table {m:.2e} sd {s:.2e} (sigma_p/sqrt 2 = {k:.2e})");
                assert!(m.abs() < 4.0 * k / (n as f64).sqrt(), "{name}: mean {c} {m}");
                assert!((s / k - 1.0).abs() < 0.07, "{name}: sd {c} {s} vs {k}");
            }
        }
    }
    // The standards of a night are drawn independently of each other.
    let p0: Vec<f64> = draws[2].iter().map(|x| x.0).collect();
    let p1: Vec<f64> = draws[3].iter().map(|x| x.0).collect();
    let ((m0, s0), (m1, s1)) = (mean_sd(&p0), mean_sd(&p1));
    let corr = p0.iter().zip(&p1).map(|(a, b)| (a - m0) * (b - m1)).sum::<f64>() / ((n - 1) as f64 * s0 * s1);
    assert!(
        corr.abs() < 4.0 / (n as f64).sqrt(),
        "corr of the two polarized standards' p: {corr}"
    );
}
