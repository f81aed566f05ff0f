//! `sofipol export CATALOG --format ecsv|fits|csv -o FILE`: the catalog as a table, one
//! row per component of a target and per measured standard, for astropy / TOPCAT (docs/cli.md, "export").
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
    /// Output file (`-`: standard output; required).
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Print only errors (not the summary line).
    #[arg(short, long)]
    pub quiet: bool,
    /// Also list the columns written, with their units (on stderr).
    #[arg(short, long)]
    pub verbose: bool,
}

/// Run.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.output.as_os_str() == "-" {
        return to_stdout(&args);
    }
    // Checked before anything is read or written, as `night` and `merge` check theirs:
    // never the input (by canonical path: `./x`, `d/../x` or a symlink count), a directory,
    // a FITS file other than a table sofipol exported (a raw frame), a symbolic link or a
    // device.
    super::common::check_output(&args.output, &[&args.catalog])?;
    super::common::check_regular_output(&args.output, "; give a regular file name, or -o - for standard output")?;
    let (cat, t) = read_table(&args)?;
    export::write(&t, args.format, &args.output)?;
    if args.verbose {
        print_columns(&t);
    }
    if !args.quiet {
        println!("{} -> {}", summary(&cat, &t), args.output.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// The catalog and its table.
fn read_table(args: &Args) -> anyhow::Result<(Catalog, export::Table)> {
    let cat: Catalog = sofipol_pipeline::input::read_catalog(&args.catalog)?;
    let t = export::table(&cat, &args.catalog.display().to_string());
    Ok((cat, t))
}

fn summary(cat: &Catalog, t: &export::Table) -> String {
    let components: usize = cat.targets.iter().map(|t| t.components.len()).sum();
    format!(
        "{} rows ({} components of {} targets, {} of {} standards; {} targets without components \
         and {} standards without a measurement not exported)",
        t.rows(),
        components,
        cat.targets.len(),
        cat.standards.len() - t.standards_without_measurement,
        cat.standards.len(),
        t.targets_without_components,
        t.standards_without_measurement
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
    if args.verbose {
        print_columns(&t);
    }
    if !args.quiet {
        eprintln!("{} -> standard output", summary(&cat, &t));
    }
    Ok(ExitCode::SUCCESS)
}

/// `-v`: the columns written, `name [unit]`, and the table's metadata keys, on stderr.
fn print_columns(t: &export::Table) {
    let cols: Vec<String> = t
        .columns
        .iter()
        .map(|c| {
            if c.unit.is_empty() {
                c.name.to_string()
            } else {
                format!("{} [{}]", c.name, c.unit)
            }
        })
        .collect();
    eprintln!("columns ({}): {}", cols.len(), cols.join(", "));
    let meta: Vec<&str> = t.meta.iter().map(|(k, _)| *k).collect();
    eprintln!("metadata: {}", meta.join(", "));
}
