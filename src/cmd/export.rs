//! `sofipol export CATALOG --format ecsv|fits|csv -o FILE`: the catalog as a table, one
//! row per component, for astropy / TOPCAT (docs/cli.md, "export").
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sofipol_pipeline::catalog::Catalog;
use sofipol_pipeline::export::{self, Format};

/// Arguments of `sofipol export`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Catalog (JSON) written by `target`, `night` or `merge`.
    pub catalog: PathBuf,
    /// ecsv (astropy), fits (binary table) or csv.
    #[arg(long, default_value = "ecsv")]
    pub format: Format,
    /// Output file.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    // Never overwrite the input (by canonical path: `./x`, `d/../x` or a symlink count),
    // checked before anything is read or written.
    anyhow::ensure!(
        !args.output.is_dir(),
        "-o {}: is a directory; give a file name",
        args.output.display()
    );
    if let (Ok(a), Ok(b)) = (
        std::fs::canonicalize(&args.output),
        std::fs::canonicalize(&args.catalog),
    ) {
        anyhow::ensure!(
            a != b,
            "-o {}: is the input catalog ({}); sofipol never overwrites its inputs",
            args.output.display(),
            args.catalog.display()
        );
    }
    let text = std::fs::read_to_string(&args.catalog).with_context(|| format!("reading {}", args.catalog.display()))?;
    let cat: Catalog =
        serde_json::from_str(&text).with_context(|| format!("{}: not a sofipol catalog", args.catalog.display()))?;
    let t = export::table(&cat, &args.catalog.display().to_string());
    export::write(&t, args.format, &args.output)?;
    println!(
        "{} rows ({} components of {} targets; {} targets without components not exported) -> {}",
        t.rows(),
        t.rows(),
        cat.targets.len(),
        t.targets_without_components,
        args.output.display()
    );
    Ok(ExitCode::SUCCESS)
}
