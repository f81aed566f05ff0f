//! The world night's calibration against its truth over many nights:
//! `cargo run --release -p sofipol-bench --example world_calibration -- 13-52 [tight]`
//! simulates and reduces the calibration frames of each night (seeds 13 to 52: dome flats
//! and standards, as `world` does, ~3 s a night), fits the standards with and without the
//! telescope's term, and prints each fit's theta0 error and the telescope's (a, b) (truth 0)
//! against their reported errors, then the rms pulls over the nights. `tight` also fits with
//! the table's errors 1000 times smaller (what standards exactly at their table values obey).
//! The first night also compares its two dome flats at 0 and 45 deg (one response,
//! independent lamp frames): the robust variance of their difference against the sum of
//! their variance maps.
use sofipol_bench::world::{calibration_scene, draw_instrument, world_standards_table, WorldConfig};
use sofipol_calib::flat::Flat;
use sofipol_calib::Profile;
use sofipol_pipeline::calibration::{orientation_values, CalibSetup};
use sofipol_pipeline::night::{self, NightSetup, RunOptions};
use sofipol_pipeline::sim::Simulator;
use sofipol_pipeline::stokes::calibration::joint::{fit_joint_with, JointOptions};
use sofipol_pipeline::stokes::calibration::{OrientationF, StandardObservation};

/// The night's standards as the calibration sees them (raw F per orientation, table values).
fn standards(out: &night::NightOutput, profile: &Profile) -> Vec<StandardObservation> {
    let mut obs = Vec::new();
    for s in &out.catalog.standards {
        let (Some(c), Some(e)) = (&s.measured, &s.table) else {
            continue;
        };
        let rows = orientation_values(c, profile);
        obs.push(StandardObservation {
            name: e.name.clone(),
            posang_deg: rows.iter().map(|r| r.0).collect(),
            f: rows
                .iter()
                .map(|r| OrientationF {
                    analyzer_deg: f64::NAN,
                    f: r.1,
                    sigma_f: r.2,
                })
                .collect(),
            parallactic_2eta: c.orientations.iter().flatten().map(|o| o.parallactic_2eta).collect(),
            p: e.p,
            sigma_p: e.sigma_p,
            gamma_deg: e.gamma_deg,
            sigma_gamma_deg: e.sigma_gamma_deg,
        });
    }
    obs
}

/// Robust (IQR) variance of f0 - f1, the mean of var0 + var1, and the fraction of pixels
/// where |f0 - f1| exceeds 5 sqrt(var0 + var1), over the o-target strip.
fn flat_check(f0: &Flat, f1: &Flat, profile: &Profile) -> (f64, f64, f64) {
    let g = &profile.geometry;
    let (mut d, mut v, mut far) = (Vec::new(), 0.0, 0usize);
    for y in g.o_target[0]..g.o_target[1] {
        for x in 100..900 {
            if f0.bad[(y, x)] == 0 && f1.bad[(y, x)] == 0 {
                let (di, vi) = (
                    (f0.data[(y, x)] - f1.data[(y, x)]) as f64,
                    (f0.variance[(y, x)] + f1.variance[(y, x)]) as f64,
                );
                far += usize::from(di * di > 25.0 * vi);
                d.push(di);
                v += vi;
            }
        }
    }
    let n = d.len() as f64;
    d.sort_by(f64::total_cmp);
    let q = |p: f64| d[(p * n) as usize];
    (((q(0.75) - q(0.25)) / 1.349).powi(2), v / n, far as f64 / n)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let range: Vec<u64> = args
        .get(1)
        .map_or("13-20", String::as_str)
        .split('-')
        .map(|s| s.parse().expect("seeds as A-B"))
        .collect();
    let want_tight = args.get(2).map(String::as_str) == Some("tight");
    let dir = std::env::temp_dir().join(format!("sofipol-world-calibration-{}", std::process::id()));
    let mut cfg = WorldConfig::new(&dir);
    let profile = Profile::sofi();
    let setup = NightSetup {
        profile: profile.clone(),
        params: Default::default(),
        calibration: CalibSetup {
            params: Default::default(),
            table: world_standards_table(),
            external: None,
        },
    };
    // Per (telescope fitted, tight priors): the pulls of theta0, a, b.
    let mut pulls: std::collections::BTreeMap<(bool, bool), [Vec<f64>; 3]> = Default::default();
    for seed in range[0]..=range[range.len() - 1] {
        cfg.seed = seed;
        let inst = draw_instrument(&cfg);
        let cdir = dir.join("calibration");
        let sim = Simulator::new(calibration_scene(&cfg, &inst), profile.clone()).expect("valid scene");
        sim.write_to_dir(&cdir, &|_| {}).expect("frames written");
        let plan = setup.plan(std::slice::from_ref(&cdir), None);
        let out = night::run_night(&plan, &setup, &RunOptions::default());
        let _ = std::fs::remove_dir_all(&cdir);
        if let Some(fs) = out.flats.set.as_ref().filter(|_| seed == range[0]) {
            let (d, v, far) = flat_check(&fs.flats[0], &fs.flats[1], &profile);
            println!(
                "flats at 0 and 45 deg: robust var(f0 - f1) {d:.3e}, var0 + var1 {v:.3e}, ratio {:.3}; beyond 5 sigma: {:.4} %",
                d / v,
                100.0 * far
            );
        }
        let obs = standards(&out, &profile);
        let theta0_true = inst.zero_point_deg.rem_euclid(180.0);
        for (tel, tight) in [(false, false), (true, false), (false, true), (true, true)] {
            if tight && !want_tight {
                continue;
            }
            let o: Vec<StandardObservation> = obs
                .iter()
                .map(|s| StandardObservation {
                    sigma_p: s.sigma_p * if tight { 1e-3 } else { 1.0 },
                    sigma_gamma_deg: s.sigma_gamma_deg * if tight { 1e-3 } else { 1.0 },
                    ..s.clone()
                })
                .collect();
            let opts = JointOptions {
                default_parity: profile.angles.parity,
                profile_theta0_deg: profile.angles.zero_point_deg,
                fit_telescope: tel,
                telescope_prior: None,
            };
            let Some(j) = fit_joint_with(&o, &opts) else { continue };
            let (Some(angles), cov) = (j.angles, j.covariance) else {
                continue;
            };
            let dth = (angles.theta0_deg - theta0_true + 90.0).rem_euclid(180.0) - 90.0;
            let ab = j.telescope.map(|t| t.ab());
            println!(
                "seed {seed} telescope {tel} tight {tight}: chi2/dof {:.2}/{}; theta0 - truth {dth:+.3} +- {:.3} deg; (a, b) {}",
                j.chi2,
                j.dof,
                cov[1][1].sqrt(),
                ab.map_or("not fitted".into(), |[a, b]| format!(
                    "({a:+.2e} +- {:.1e}, {b:+.2e} +- {:.1e})",
                    cov[2][2].sqrt(),
                    cov[3][3].sqrt()
                ))
            );
            let p = pulls.entry((tel, tight)).or_default();
            p[0].push(dth / cov[1][1].sqrt());
            if let Some([a, b]) = ab {
                p[1].push(a / cov[2][2].sqrt());
                p[2].push(b / cov[3][3].sqrt());
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    for ((tel, tight), p) in &pulls {
        let ab = if p[1].is_empty() {
            String::new()
        } else {
            format!(", a {:.3}, b {:.3}", rms(&p[1]), rms(&p[2]))
        };
        println!(
            "telescope {tel} tight {tight}: {} nights, rms pull theta0 {:.3}{ab}",
            p[0].len(),
            rms(&p[0])
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
