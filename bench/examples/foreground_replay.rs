//! The foreground's estimate replayed on nights already reduced: each night's catalog
//! (`sN.json`) and the simulator's truth (`sN_raw/truth.json`), as `tests/cli_foreground.rs`
//! keeps them with `SOFIPOL_FG_DIR=DIR`. The night's fields are estimated again from the
//! catalog's field stars as `sofipol night` does ([`estimate_night`], the usable,
//! calibrated stars with their total errors) and the foreground at each binary compared
//! with the field at A: the pulls' rms, and by the flat prior's share of the night's
//! prior. Seconds instead of the minutes of reducing the frames again, so the estimator can
//! be studied on the end-to-end nights' field stars. A night's targets are taken as one
//! filter's fields (as in those nights).
//!
//! `cargo run --release -p sofipol-bench --example foreground_replay -- DIR [--stat]
//! [--seed N] [--verbose]` (`--stat`: the field stars' measurement errors instead of their
//! total errors; `--seed N`: that night only; `--verbose`: each binary's pulls, errors,
//! stars used and the kriging's posterior means).
use serde_json::Value;
use sofipol_pipeline::catalog::Catalog;
use sofipol_pipeline::foreground::{estimate_night, EstimateParams, FieldStarQu, Outcome};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let usage = "usage: DIR [--stat] [--seed N] [--verbose]";
    let dir = std::path::PathBuf::from(args.next().ok_or_else(|| anyhow::anyhow!(usage))?);
    let (mut stat, mut verbose, mut only) = (false, false, None);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--stat" => stat = true,
            "--verbose" => verbose = true,
            "--seed" => {
                let v = args.next().ok_or_else(|| anyhow::anyhow!("--seed needs a value"))?;
                only = Some(v.parse::<u64>().map_err(|e| anyhow::anyhow!("--seed {v}: {e}"))?);
            }
            other => anyhow::bail!("{other}: unknown argument ({usage})"),
        }
    }
    let mut pulls: Vec<(f64, f64)> = Vec::new();
    let mut nights = 0;
    for seed in 1u64.. {
        let cat_path = dir.join(format!("s{seed}.json"));
        let truth_path = dir.join(format!("s{seed}_raw/truth.json"));
        if !cat_path.exists() || !truth_path.exists() {
            break;
        }
        nights += 1;
        if only.is_some_and(|o| o != seed) {
            continue;
        }
        let cat: Catalog = serde_json::from_str(&std::fs::read_to_string(&cat_path)?)?;
        let truth: Value = serde_json::from_str(&std::fs::read_to_string(&truth_path)?)?;
        let mut fields: Vec<(f64, f64, Vec<FieldStarQu>)> = Vec::new();
        let mut names = Vec::new();
        for t in &cat.targets {
            let (Some(ra), Some(dec), Some(stars)) = (t.ra_deg, t.dec_deg, t.field_stars.as_ref()) else {
                continue;
            };
            let qu: Vec<FieldStarQu> = stars
                .iter()
                .map(|s| {
                    let c = &s.star;
                    let (sq, su) = if stat {
                        (
                            c.sigma_q_stat.unwrap_or(c.pol.sigma_q),
                            c.sigma_u_stat.unwrap_or(c.pol.sigma_u),
                        )
                    } else {
                        (c.pol.sigma_q, c.pol.sigma_u)
                    };
                    FieldStarQu {
                        id: s.id.clone(),
                        q: c.pol.q,
                        u: c.pol.u,
                        sigma_q: sq,
                        sigma_u: su,
                        cov_qu: c.cov_qu.unwrap_or(0.0),
                        ra_deg: s.ra_deg.unwrap_or(f64::NAN),
                        dec_deg: s.dec_deg.unwrap_or(f64::NAN),
                        usable: s.usable && c.calibration.is_some_and(|k| k.complete_for_the_cut()),
                    }
                })
                .collect();
            fields.push((ra, dec, qu));
            names.push(t.object.clone());
        }
        let input: Vec<(f64, f64, &[FieldStarQu])> = fields.iter().map(|(r, d, s)| (*r, *d, s.as_slice())).collect();
        let out = estimate_night(&input, &EstimateParams::default());
        for (name, o) in names.iter().zip(out) {
            let Outcome::Estimated(e) = o else { continue };
            let tt = truth["targets"]
                .as_array()
                .and_then(|a| a.iter().find(|t| t["object"] == name.as_str()))
                .ok_or_else(|| anyhow::anyhow!("seed {seed}: {name} not in the truth"))?;
            let share = e.spatial.and_then(|s| s.flat_share).unwrap_or(f64::NAN);
            if verbose {
                let tq = tt["foreground"]["q"].as_f64().unwrap_or(f64::NAN);
                let tu = tt["foreground"]["u"].as_f64().unwrap_or(f64::NAN);
                let (nugget, slope, exponent) = e.spatial.map_or(([f64::NAN; 2], [f64::NAN; 2], [f64::NAN; 2]), |s| {
                    (s.nugget, s.slope, s.exponent)
                });
                println!(
                    "seed {seed} {name}: {} stars, share {share:.2}, pulls {:+.2} {:+.2}, sigma {:.4} {:.4}, \
                     nugget {:.4} {:.4}, slope {:.4} {:.4}, exponent {:.2} {:.2}",
                    e.used.len(),
                    (e.q - tq) / e.cov.var_q.sqrt(),
                    (e.u - tu) / e.cov.var_u.sqrt(),
                    e.cov.var_q.sqrt(),
                    e.cov.var_u.sqrt(),
                    nugget[0],
                    nugget[1],
                    slope[0],
                    slope[1],
                    exponent[0],
                    exponent[1],
                );
            }
            for (k, (v, var)) in [("q", (e.q, e.cov.var_q)), ("u", (e.u, e.cov.var_u))] {
                let t = tt["foreground"][k].as_f64().unwrap_or(f64::NAN);
                pulls.push(((v - t) / var.sqrt(), share));
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let all: Vec<f64> = pulls.iter().map(|p| p.0).collect();
    println!(
        "{nights} nights, {} pulls, rms {:.3} +- {:.3}{}",
        all.len(),
        rms(&all),
        rms(&all) / (2.0 * all.len() as f64).sqrt(),
        if stat { " (measurement errors)" } else { "" }
    );
    let mut shares: Vec<f64> = pulls.iter().map(|p| p.1).filter(|s| s.is_finite()).collect();
    shares.sort_by(f64::total_cmp);
    shares.dedup();
    for s in shares {
        let v: Vec<f64> = pulls.iter().filter(|p| p.1 == s).map(|p| p.0).collect();
        println!("  flat share {s:.2}: {} pulls, rms {:.3}", v.len(), rms(&v));
    }
    Ok(())
}
