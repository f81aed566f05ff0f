//! `sofipol merge a.json b.json ... -o night.json`: join shard catalogs.
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sofipol_pipeline::catalog::Catalog;

/// Arguments of `sofipol merge`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Shard catalogs.
    #[arg(required = true)]
    pub catalogs: Vec<PathBuf>,
    /// Output catalog.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    super::common::check_output(&args.output, &args.catalogs)?;
    let mut parts = Vec::new();
    for p in &args.catalogs {
        let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        let c: Catalog =
            serde_json::from_str(&text).with_context(|| format!("{}: not a sofipol catalog", p.display()))?;
        parts.push((p.display().to_string(), c));
    }
    let merged = sofipol_pipeline::night::merge(parts).map_err(anyhow::Error::msg)?;
    sofipol_pipeline::io::write_json_atomic(&args.output, &merged)
        .with_context(|| format!("writing {}", args.output.display()))?;
    println!(
        "merged {} catalogs: {} targets, {} failures -> {}",
        args.catalogs.len(),
        merged.targets.len(),
        merged.failures.len(),
        args.output.display()
    );
    Ok(ExitCode::SUCCESS)
}
