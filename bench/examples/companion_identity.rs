//! Which source the companion search takes for B on the accuracy harness's foreground
//! nights (field stars of a K-band luminosity function): every binary reduced, its
//! separation and PA compared with the truth, and each one whose B is another source
//! listed with the field stars within the companion search radius.
//!
//! `cargo run --release -p sofipol-bench --example companion_identity -- [SEEDS...]`
//! (default: seeds 41 and 42, the separation bins and targets of the foreground acceptance
//! test `bench/tests/accuracy_foreground.rs`; `--bins 0.5,0.8,...` and `--targets N` to
//! change them).
use rayon::prelude::*;
use sofipol_bench::accuracy::{scene_for, AccuracyConfig};
use sofipol_calib::Profile;
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{loaded_from_sim, Simulator};

/// B is the true companion when the separation is within this, arcsec ...
const SEP_TOL_ARCSEC: f64 = 0.2;
/// ... and the PA within this (either label order), deg.
const PA_TOL_DEG: f64 = 5.0;

fn main() -> anyhow::Result<()> {
    let mut seeds: Vec<u64> = Vec::new();
    let mut bins = vec![1.6, 2.5, 4.0];
    let mut targets = 6usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--bins" => {
                let v = args.next().ok_or_else(|| anyhow::anyhow!("--bins needs a value"))?;
                bins = v
                    .split(',')
                    .map(|s| s.parse::<f64>().map_err(|e| anyhow::anyhow!("--bins {v}: {e}")))
                    .collect::<anyhow::Result<_>>()?;
            }
            "--targets" => {
                let v = args.next().ok_or_else(|| anyhow::anyhow!("--targets needs a value"))?;
                targets = v.parse().map_err(|e| anyhow::anyhow!("--targets {v}: {e}"))?;
            }
            s => seeds.push(s.parse().map_err(|e| anyhow::anyhow!("seed {s}: {e}"))?),
        }
    }
    if seeds.is_empty() {
        seeds = vec![41, 42];
    }
    let profile = Profile::sofi();
    let params = TargetParams::default();
    let search = params.measure.companion_search_arcsec;
    let (mut n, mut wrong, mut not_found, mut flagged) = (0usize, 0usize, 0usize, 0usize);
    for &seed in &seeds {
        let cfg = AccuracyConfig::with_foreground(AccuracyConfig {
            bins_arcsec: bins.clone(),
            targets_per_bin: targets,
            seed,
            ..Default::default()
        });
        for (bin, w) in cfg.bins_arcsec.windows(2).enumerate() {
            let (scene, _) = scene_for(&cfg, w[0], w[1], bin);
            let sim = Simulator::new(scene, profile.clone())?;
            let nf = sim.frames_per_target();
            let truth = sim.truth(&[]);
            let lines: Vec<(bool, bool, bool, String)> = (0..targets)
                .into_par_iter()
                .map(|t| {
                    let (seq, orients) = loaded_from_sim((0..nf).map(|k| sim.frame(t, k)).collect(), &profile);
                    let out = reduce_loaded(&seq, orients, &profile, &params, None, None, false);
                    let tt = &truth.targets[t];
                    let tg = &out.target;
                    let flags: Vec<String> = tg.flags.iter().flatten().map(|f| f.to_string()).collect();
                    let ambiguous = flags.iter().any(|f| f.starts_with("companion_candidates"));
                    let (ok, found) = match (tg.separation_arcsec, tg.pa_deg) {
                        (Some(s), Some(p)) => {
                            let d = (p - tt.pa_deg).rem_euclid(360.0);
                            let dpa = d.min(360.0 - d).min((d - 180.0).abs());
                            ((s - tt.separation_arcsec).abs() <= SEP_TOL_ARCSEC && dpa <= PA_TOL_DEG, true)
                        }
                        _ => (false, false),
                    };
                    let near: Vec<String> = tt
                        .field_stars
                        .iter()
                        .filter(|f| f.separation_arcsec <= search + 1.0)
                        .map(|f| format!("{:.2}\" PA {:.0} flux {:.0}", f.separation_arcsec, f.pa_deg, f.flux))
                        .collect();
                    let line = format!(
                        "seed {seed} {}: true {:.2}\" PA {:.0} (B flux {:.0}), found {:?}\" PA {:?}; field stars near: [{}]; flags {:?}",
                        tt.object,
                        tt.separation_arcsec,
                        tt.pa_deg,
                        tt.components.get(1).map_or(f64::NAN, |c| c.flux),
                        tg.separation_arcsec.map(|s| (s * 100.0).round() / 100.0),
                        tg.pa_deg.map(|p| p.round()),
                        near.join("; "),
                        flags
                    );
                    (ok, found, ambiguous, line)
                })
                .collect();
            for (ok, found, ambiguous, line) in lines {
                n += 1;
                wrong += usize::from(found && !ok);
                not_found += usize::from(!found);
                flagged += usize::from(ambiguous);
                let tag = match (found, ok) {
                    (true, true) => "ok",
                    (true, false) => "WRONG",
                    _ => "none",
                };
                println!("{tag:5} {line}");
            }
        }
    }
    println!(
        "{n} binaries (seeds {seeds:?}, bins {bins:?}): {wrong} with another source taken for B, {not_found} without a companion, {flagged} flagged companion_candidates"
    );
    Ok(())
}
