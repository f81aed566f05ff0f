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
    /// Output file (`-`: standard output).
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.output.as_os_str() == "-" {
        return to_stdout(&args);
    }
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
    super::common::check_regular_output(&args.output, "; give a regular file name, or -o - for standard output")?;
    let (cat, t) = read_table(&args)?;
    export::write(&t, args.format, &args.output)?;
    println!("{} -> {}", summary(&cat, &t), args.output.display());
    Ok(ExitCode::SUCCESS)
}

/// The catalog and its table.
fn read_table(args: &Args) -> anyhow::Result<(Catalog, export::Table)> {
    let text = std::fs::read_to_string(&args.catalog).with_context(|| format!("reading {}", args.catalog.display()))?;
    let cat: Catalog =
        serde_json::from_str(&text).with_context(|| format!("{}: not a sofipol catalog", args.catalog.display()))?;
    let t = export::table(&cat, &args.catalog.display().to_string());
    Ok((cat, t))
}

fn summary(cat: &Catalog, t: &export::Table) -> String {
    format!(
        "{} rows ({} components of {} targets; {} targets without components not exported)",
        t.rows(),
        t.rows(),
        cat.targets.len(),
        t.targets_without_components
    )
}

/// `-o -`: the table on standard output (the same bytes as the file), the summary on
/// stderr. A closed stdout is not an error (docs/cli.md).
fn to_stdout(args: &Args) -> anyhow::Result<ExitCode> {
    use std::io::Write as _;
    let (cat, t) = read_table(args)?;
    let bytes = export::to_bytes(&t, args.format)?;
    let mut out = std::io::stdout().lock();
    let _ = out.write_all(&bytes).and_then(|_| out.flush());
    eprintln!("{} -> standard output", summary(&cat, &t));
    Ok(ExitCode::SUCCESS)
}
