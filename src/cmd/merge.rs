//! `sofipol merge a.json b.json ... -o night.json`: join shard catalogs.
//!
//! The catalogs must form one run: the same instrument profile, reduction parameters and
//! calibration settings (`provenance.calibration`: `--standards`, `--calib`,
//! `--stokes-method`, `--no-calibration`; always refused otherwise), and shards of the
//! same inputs must have applied the same calibration (the catalogs' `calibration`: a
//! standards file edited between the shards). Shards of the same inputs must have the same N, each K
//! once, and every K of 1..=N present; a missing shard is refused unless
//! `--allow-partial`, which merges what is there, lists the missing shards in the
//! provenance (`missing_shards`) and exits 2. A catalog written without `--shard` is a
//! whole run and complete by itself (several nights can be merged).
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use serde_json::Value;
use sofipol_calib::text::printable;
use sofipol_pipeline::catalog::{AppliedCalibration, Catalog, Provenance};

/// Arguments of `sofipol merge`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Shard catalogs.
    #[arg(required = true)]
    pub catalogs: Vec<PathBuf>,
    /// Output catalog (JSON, written atomically; required).
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Merge even when shards are missing; the missing shards are listed in the
    /// provenance and the exit code is 2.
    #[arg(long)]
    pub allow_partial: bool,
    /// Print only errors (the exit code still says 2 when shards are missing).
    #[arg(short, long)]
    pub quiet: bool,
    /// Also print each input catalog: its shard, targets, failures and software (on stderr).
    #[arg(short, long)]
    pub verbose: bool,
}

/// The shards' coverage: `Ok(missing "K/N of inputs")` or the reason the set cannot be merged. Parts
/// are (name, provenance).
pub fn check_shards(parts: &[(String, &Provenance)], allow_partial: bool) -> anyhow::Result<Vec<String>> {
    // One run: identical profile, parameters and calibration settings.
    let settings = |p: &Provenance| {
        [
            ("parameters", serde_json::json!(p.parameters)),
            ("profile", serde_json::json!(p.profile)),
            ("calibration", serde_json::json!(p.calibration)),
        ]
    };
    let (first_name, first) = &parts[0];
    let first = settings(first);
    for (name, p) in &parts[1..] {
        for ((key, a), (_, b)) in first.iter().zip(settings(p)) {
            if *a != b {
                let detail = first_difference(a, &b, key);
                anyhow::bail!(
                    "{name} and {first_name} were reduced with different {key} ({detail}): not one run; \
                     reduce the shards again with the same settings"
                );
            }
        }
    }
    // Shards are checked per night (the `inputs` they scanned): every K of 1..=N once.
    // A catalog without a shard is a whole run, complete by itself.
    let mut nights: std::collections::BTreeMap<String, (usize, std::collections::BTreeMap<usize, &str>)> =
        std::collections::BTreeMap::new();
    for (name, p) in parts {
        let Some(Some(sh)) = &p.shard else { continue };
        let sh: sofipol_pipeline::night::Shard = sh
            .parse()
            .map_err(|e| anyhow::anyhow!("{name}: provenance.shard: {e}"))?;
        let (n, have) = nights
            .entry(inputs_key(p))
            .or_insert_with(|| (sh.n, Default::default()));
        if *n != sh.n {
            anyhow::bail!(
                "{name} is shard {}/{} but other shards of the same inputs are shards of {n}",
                sh.k,
                sh.n
            );
        }
        if let Some(prev) = have.insert(sh.k, name) {
            anyhow::bail!("{name} and {prev} are both shard {}/{}", sh.k, sh.n);
        }
    }
    let mut missing = Vec::new();
    for (inputs, (n, have)) in &nights {
        for k in (1..=*n).filter(|k| !have.contains_key(k)) {
            missing.push(format!("{k}/{n} of {inputs}"));
        }
    }
    if !missing.is_empty() && !allow_partial {
        anyhow::bail!(
            "shard(s) {} missing: their targets would be lost silently (use --allow-partial to merge anyway)",
            missing.join(", ")
        );
    }
    Ok(missing)
}

/// Shards of the same inputs measure the same standards with the same settings: the
/// calibrations they applied (each catalog's `calibration`) must be identical. `parts` are
/// (name, provenance, calibration). A catalog written without `--shard` is a whole run,
/// calibrated by its own night.
pub fn check_calibrations(parts: &[(String, &Provenance, Option<&AppliedCalibration>)]) -> anyhow::Result<()> {
    let mut first: std::collections::BTreeMap<String, (&str, Value)> = Default::default();
    for (name, p, cal) in parts {
        if !matches!(p.shard, Some(Some(_))) {
            continue;
        }
        let cal = serde_json::json!(cal);
        let (first_name, first_cal) = first.entry(inputs_key(p)).or_insert((name.as_str(), cal.clone()));
        if cal != *first_cal {
            let detail = first_difference(first_cal, &cal, "calibration");
            anyhow::bail!(
                "{name} and {first_name} are shards of the same inputs but applied different calibrations \
                 ({detail}): not one run; reduce the shards again with the same standards table and \
                 calibration files"
            );
        }
    }
    Ok(())
}

/// The inputs a shard scanned, as one text: shards of the same night have the same.
fn inputs_key(p: &Provenance) -> String {
    serde_json::json!(p.inputs).to_string()
}

/// A short description of where two JSON values first differ (the key path).
fn first_difference(a: &Value, b: &Value, path: &str) -> String {
    match (a, b) {
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => match x.iter().zip(y).position(|(v, w)| v != w) {
            Some(i) => first_difference(&x[i], &y[i], &format!("{path}[{i}]")),
            None => path.to_string(),
        },
        (Value::Object(x), Value::Object(y)) => {
            for (k, v) in x {
                match y.get(k) {
                    Some(w) if w == v => {}
                    Some(w) => return first_difference(v, w, &format!("{path}.{k}")),
                    None => return format!("{path}.{k} only in one"),
                }
            }
            match y.keys().find(|k| !x.contains_key(*k)) {
                Some(k) => format!("{path}.{k} only in one"),
                None => path.to_string(),
            }
        }
        _ => format!("{path}: {a} vs {b}"),
    }
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    super::common::check_output(&args.output, &args.catalogs)?;
    let mut parts = Vec::new();
    for p in &args.catalogs {
        let c: Catalog = sofipol_pipeline::input::read_catalog(p)?;
        parts.push((p.display().to_string(), c));
    }
    if args.verbose {
        for (name, c) in &parts {
            let prov = &c.provenance;
            let shard = match &prov.shard {
                Some(Some(s)) => format!("shard {s}"),
                _ => "whole night".to_string(),
            };
            eprintln!(
                "{}: {shard}, {} targets, {} standards, {} failures; {} (commit {})",
                printable(name),
                c.targets.len(),
                c.standards.len(),
                c.failures.len(),
                prov.softwares().join(", "),
                prov.commits().join(", ")
            );
        }
    }
    let provs: Vec<(String, &Provenance)> = parts.iter().map(|(n, c)| (n.clone(), &c.provenance)).collect();
    let missing = check_shards(&provs, args.allow_partial)?;
    let cals: Vec<(String, &Provenance, Option<&AppliedCalibration>)> = parts
        .iter()
        .map(|(n, c)| (n.clone(), &c.provenance, c.calibration.as_ref()))
        .collect();
    check_calibrations(&cals)?;
    let mut merged = sofipol_pipeline::night::merge(parts).map_err(anyhow::Error::msg)?;
    merged.provenance.missing_shards = Some(missing.clone());
    // The merge's own run: when and how this file was written (the software and commit
    // stay the inputs').
    let now = Provenance::now();
    merged.provenance.command_line = now.command_line;
    merged.provenance.created_utc = now.created_utc;
    sofipol_pipeline::io::write_json_atomic(&args.output, &merged)
        .with_context(|| format!("writing {}", args.output.display()))?;
    if !args.quiet {
        println!(
            "merged {} catalogs: {} targets, {} failures -> {}",
            args.catalogs.len(),
            merged.targets.len(),
            merged.failures.len(),
            args.output.display()
        );
    }
    if !missing.is_empty() {
        if !args.quiet {
            eprintln!(
                "sofipol merge: warning: shard(s) {} missing (--allow-partial)",
                missing.join(", ")
            );
        }
        return Ok(ExitCode::from(2));
    }
    Ok(ExitCode::SUCCESS)
}
