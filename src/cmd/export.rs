//! `sofipol export CATALOG --format ecsv|fits|csv -o FILE`: the catalog as a table, one
//! row per component, for astropy / TOPCAT (docs/cli.md, "export").
use std::path::PathBuf;
use std::process::ExitCode;

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
    // Checked before anything is read or written, as `night` and `merge` check theirs:
    // never the input (by canonical path: `./x`, `d/../x` or a symlink count), a directory,
    // or a FITS file other than a table sofipol exported (a raw frame).
    super::common::check_output(&args.output, &[&args.catalog])?;
    let cat: Catalog = sofipol_pipeline::input::read_catalog(&args.catalog)?;
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
