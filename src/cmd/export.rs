//! `sofipol export CATALOG -o FILE [--format ecsv|fits|csv]`: the catalog as a table, one
//! row per component of a target and per measured standard, for astropy / TOPCAT
//! (docs/cli.md, "export"). The format follows the file's extension; a `--format` that
//! contradicts it is refused.
use std::path::PathBuf;
use std::process::ExitCode;

use sofipol_pipeline::catalog::Catalog;
use sofipol_pipeline::export::{self, Format};

/// Arguments of `sofipol export`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Catalog (JSON) written by `target`, `night` or `merge`.
    pub catalog: PathBuf,
    /// ecsv (astropy), fits (binary table) or csv [default: the output's extension
    /// (.ecsv, .fits/.fit/.fts, .csv); ecsv for another extension and for `-o -`].
    #[arg(long)]
    pub format: Option<Format>,
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
    let format = choose_format(&args.output, args.format)?;
    if args.output.as_os_str() == "-" {
        return to_stdout(&args, format);
    }
    // Checked before anything is read or written, as `night` and `merge` check theirs:
    // never the input (by canonical path: `./x`, `d/../x` or a symlink count), a directory,
    // a FITS file other than a table sofipol exported (a raw frame), a symbolic link or a
    // device.
    super::common::check_output(&args.output, &[&args.catalog])?;
    super::common::check_regular_output(&args.output, "; give a regular file name, or -o - for standard output")?;
    let (cat, t) = read_table(&args)?;
    export::write(&t, format, &args.output)?;
    if args.verbose {
        print_columns(&t);
    }
    if !args.quiet {
        println!("{} -> {}", summary(&cat, &t), args.output.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// The format a file's extension names (none for another extension).
fn format_of_extension(output: &std::path::Path) -> Option<Format> {
    let ext = output.extension()?.to_string_lossy().to_ascii_lowercase();
    match ext.as_str() {
        "ecsv" => Some(Format::Ecsv),
        "fits" | "fit" | "fts" => Some(Format::Fits),
        "csv" => Some(Format::Csv),
        _ => None,
    }
}

/// The format to write: `--format`, else the extension's, else ECSV. A `--format` that
/// contradicts the extension is refused: a file whose name says FITS must be FITS (astropy
/// and TOPCAT choose their reader by it).
fn choose_format(output: &std::path::Path, given: Option<Format>) -> anyhow::Result<Format> {
    let by_name = format_of_extension(output);
    match (given, by_name) {
        (Some(g), Some(n)) if g != n => anyhow::bail!(
            "{}: the extension says {} but --format {} was given; name the file .{} or give --format {}",
            output.display(),
            n.name(),
            g.name(),
            g.extension(),
            n.name()
        ),
        (Some(g), _) => Ok(g),
        (None, Some(n)) => Ok(n),
        (None, None) => Ok(Format::Ecsv),
    }
}

/// The catalog and its table.
fn read_table(args: &Args) -> anyhow::Result<(Catalog, export::Table)> {
    let cat: Catalog = sofipol_pipeline::input::read_catalog(&args.catalog)?;
    let t = export::table(&cat, &args.catalog.display().to_string());
    Ok((cat, t))
}

fn summary(cat: &Catalog, t: &export::Table) -> String {
    let components: usize = cat.targets.iter().map(|t| t.components.len()).sum();
    let field: usize = cat.targets.iter().flat_map(|t| &t.field_stars).map(Vec::len).sum();
    format!(
        "{} rows ({} components of {} targets{}, {} of {} standards; {} targets without components \
         and {} standards without a measurement not exported)",
        t.rows(),
        components,
        cat.targets.len(),
        if field > 0 {
            format!(", {field} field stars")
        } else {
            String::new()
        },
        cat.standards.len() - t.standards_without_measurement,
        cat.standards.len(),
        t.targets_without_components,
        t.standards_without_measurement
    )
}

/// `-o -`: the table on standard output (the same bytes as the file), the summary on
/// stderr. A closed stdout is not an error (docs/cli.md).
fn to_stdout(args: &Args, format: Format) -> anyhow::Result<ExitCode> {
    use std::io::Write as _;
    let (cat, t) = read_table(args)?;
    let bytes = export::to_bytes(&t, format)?;
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
