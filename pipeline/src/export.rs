//! Catalog export to table formats astronomers load in one line (docs/cli.md, "export"):
//! ECSV (astropy `Table.read`), FITS binary table (astropy, TOPCAT, fitsio) and plain CSV.
//!
//! One row per component of a target (`kind` = `target`) followed by one per field star of
//! that target (`kind` = `field_star`), then one per measured standard star
//! (`kind` = `standard`); targets without components (failed) and unmeasured
//! standards have no row. Units are in the column metadata (ECSV header YAML `unit`; FITS
//! `TUNITn`, descriptions in `TCOMMn`); flags are one string (`;`-separated); every row
//! carries its target, sequence, filter, pointing and time, status, the software that
//! made the catalog and the catalog file. All files are written to a
//! temporary file in the same directory and renamed.
use std::path::{Path, PathBuf};

use crate::catalog::flags::join;
use crate::catalog::{Catalog, Component, Status};

/// Output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// Enhanced CSV 1.0 (astropy).
    Ecsv,
    /// FITS binary table (extension `SOFIPOL`).
    Fits,
    /// Plain CSV, one header line (units only in the docs).
    Csv,
}

impl std::str::FromStr for Format {
    type Err = crate::error::SettingError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "ecsv" => Ok(Format::Ecsv),
            "fits" | "fit" => Ok(Format::Fits),
            "csv" => Ok(Format::Csv),
            _ => Err(crate::error::SettingError {
                key: "format",
                value: format!("{s:?}"),
                allowed: "ecsv, fits or csv",
            }),
        }
    }
}

impl Format {
    /// Its name for `--format`.
    pub fn name(self) -> &'static str {
        match self {
            Format::Ecsv => "ecsv",
            Format::Fits => "fits",
            Format::Csv => "csv",
        }
    }

    /// The file extension that names it.
    pub fn extension(self) -> &'static str {
        self.name()
    }
}

/// Column data.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    /// Text.
    Str(Vec<String>),
    /// Numbers (NaN where the catalog has no value).
    F64(Vec<f64>),
    /// Booleans (FITS: a logical column, T/F).
    Bool(Vec<bool>),
}

/// One column with its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Column {
    /// Name.
    pub name: &'static str,
    /// Unit (astropy/FITS string; empty = dimensionless or none).
    pub unit: &'static str,
    /// Description.
    pub description: &'static str,
    /// Values, one per row.
    pub data: Data,
}

/// The table of a catalog.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    /// Columns, all of the same length.
    pub columns: Vec<Column>,
    /// Table-level metadata (software, source catalog, schema version).
    pub meta: Vec<(&'static str, String)>,
    /// Targets without any component (not in the table).
    pub targets_without_components: usize,
    /// Standards without a measurement (not in the table).
    pub standards_without_measurement: usize,
}

impl Table {
    /// Number of rows.
    pub fn rows(&self) -> usize {
        match self.columns.first().map(|c| &c.data) {
            Some(Data::Str(v)) => v.len(),
            Some(Data::F64(v)) => v.len(),
            Some(Data::Bool(v)) => v.len(),
            None => 0,
        }
    }
}

/// The numeric columns, in table order: (name, unit, description).
const NUMERIC: [(&str, &str, &str); 36] = [
    (
        "ra",
        "deg",
        "right ascension of this star (ICRS): A and standards at the pointing (mean over the frames), \
         B and field stars offset from A by their measured separation and position angle",
    ),
    (
        "dec",
        "deg",
        "declination of this star (ICRS): A and standards at the pointing (mean over the frames), \
         B and field stars offset from A by their measured separation and position angle",
    ),
    ("mjd", "d", "mean MJD-OBS of the sequence's frames"),
    (
        "separation",
        "arcsec",
        "target: separation of B from A found; field_star: of the star from A",
    ),
    (
        "pa",
        "deg",
        "target: position angle of B from A found, east of north; field_star: of the star from A",
    ),
    ("q", "", "normalised Stokes q, sky frame (fraction)"),
    ("sigma_q", "", "1-sigma error of q: measurement and calibration"),
    ("u", "", "normalised Stokes u, sky frame (fraction)"),
    ("sigma_u", "", "1-sigma error of u: measurement and calibration"),
    ("cov_qu", "", "covariance of q and u: measurement and calibration"),
    ("sigma_q_stat", "", "1-sigma error of q from the measurement alone"),
    ("sigma_u_stat", "", "1-sigma error of u from the measurement alone"),
    ("cov_qu_stat", "", "covariance of q and u from the measurement alone"),
    ("p", "", "P = hypot(q, u), not debiased (fraction)"),
    ("sigma_p", "", "1-sigma error of P from the full q-u covariance"),
    (
        "p_debiased",
        "",
        "debiased P (fraction), estimator in the catalog provenance",
    ),
    ("gamma", "deg", "polarization angle, east of north, [0, 180)"),
    (
        "sigma_gamma",
        "deg",
        "1-sigma angle error, full q-u covariance (measurement+calibration)",
    ),
    (
        "sigma_gamma_stat",
        "deg",
        "1-sigma angle error from the measurement alone",
    ),
    (
        "sigma_gamma_zero_point",
        "deg",
        "1-sigma angle error from the night's calibration (c, theta0)",
    ),
    (
        "sigma_gamma_nkc",
        "deg",
        "68.27% half-width, Naghizadeh-Khouei & Clarke at the debiased S/N",
    ),
    ("snr", "", "P / sigma_P"),
    (
        "delta_gamma",
        "deg",
        "target: |gamma_A - gamma_B| folded to [0, 90]; NaN unless both pass",
    ),
    (
        "sigma_delta_gamma",
        "deg",
        "target: 1-sigma error of delta_gamma (theta0 cancels, c does not)",
    ),
    (
        "delta_gamma_lo",
        "deg",
        "target: low end of the central 68.27% interval of delta_gamma",
    ),
    (
        "delta_gamma_hi",
        "deg",
        "target: high end of the central 68.27% interval of delta_gamma",
    ),
    (
        "fg_q",
        "",
        "target: interstellar foreground q at the target (the catalog's foreground); NaN without one",
    ),
    ("fg_u", "", "target: interstellar foreground u at the target"),
    (
        "sigma_fg_q",
        "",
        "target: 1-sigma error of fg_q (error of the field stars' mean + their dispersion)",
    ),
    ("sigma_fg_u", "", "target: 1-sigma error of fg_u"),
    (
        "delta_gamma_fg_corrected",
        "deg",
        "target: delta_gamma after subtracting the foreground from both components; NaN without one",
    ),
    (
        "sigma_delta_gamma_fg_corrected",
        "deg",
        "target: 1-sigma error of delta_gamma_fg_corrected (the foreground's error common to both)",
    ),
    ("flux", "adu", "mean o+e flux per dither"),
    (
        "sigma_flux",
        "adu",
        "1-sigma error of flux (propagated, or the dithers' scatter when larger)",
    ),
    (
        "mag",
        "mag",
        "magnitude in the filter from the night's photometric zero-point; NaN without one",
    ),
    ("sigma_mag", "mag", "1-sigma error of mag: flux and zero-point"),
];

/// One row of the table: a component of a target, or a standard star's measurement.
struct Row {
    target: String,
    kind: &'static str,
    sequence: String,
    filter: String,
    status: String,
    component: String,
    num: [f64; NUMERIC.len()],
    passes_cut: bool,
    flags: String,
    target_flags: String,
}

/// The row of component `c` of a target or standard: its sequence's values `seq`
/// (RA, Dec, MJD, separation, PA) and its target's Delta-gamma `dg` (value, error, interval,
/// then the foreground q, u and their errors, and the Delta-gamma after subtracting it with its error).
fn row_values(c: &Component, seq: [Option<f64>; 5], dg: [Option<f64>; 10]) -> [f64; NUMERIC.len()] {
    let o = |v: Option<f64>| v.unwrap_or(f64::NAN);
    [
        o(seq[0]),
        o(seq[1]),
        o(seq[2]),
        o(seq[3]),
        o(seq[4]),
        c.q,
        c.sigma_q,
        c.u,
        c.sigma_u,
        o(c.cov_qu),
        o(c.sigma_q_stat),
        o(c.sigma_u_stat),
        o(c.cov_qu_stat),
        c.p,
        c.sigma_p,
        c.p_debiased,
        c.gamma_deg,
        c.sigma_gamma_deg,
        o(c.sigma_gamma_stat_deg),
        o(c.sigma_gamma_zero_point_deg),
        o(c.sigma_gamma_nkc_deg),
        o(c.snr),
        o(dg[0]),
        o(dg[1]),
        o(dg[2]),
        o(dg[3]),
        o(dg[4]),
        o(dg[5]),
        o(dg[6]),
        o(dg[7]),
        o(dg[8]),
        o(dg[9]),
        o(c.flux_adu),
        o(c.sigma_flux_adu),
        o(c.mag),
        o(c.sigma_mag),
    ]
}

/// A status as the catalog writes it.
fn status_text(s: Status) -> String {
    serde_json::to_value(s)
        .ok()
        .and_then(|v| v.as_str().map(String::from))
        .unwrap_or_default()
}

/// The sky position (ra, dec in deg, ra in [0, 360)) `sep_arcsec` from (`ra_deg`, `dec_deg`)
/// at position angle `pa_deg` (east of north): the great circle's destination,
/// `sin d1 = sin d0 cos r + cos d0 sin r cos pa`,
/// `ra1 = ra0 + atan2(sin pa sin r cos d0, cos r - sin d0 sin d1)`.
pub fn offset_position(ra_deg: f64, dec_deg: f64, sep_arcsec: f64, pa_deg: f64) -> (f64, f64) {
    let (d0, r, pa) = (
        dec_deg.to_radians(),
        (sep_arcsec / 3600.0).to_radians(),
        pa_deg.to_radians(),
    );
    let d1 = (d0.sin() * r.cos() + d0.cos() * r.sin() * pa.cos())
        .clamp(-1.0, 1.0)
        .asin();
    let dra = (pa.sin() * r.sin() * d0.cos()).atan2(r.cos() - d0.sin() * d1.sin());
    ((ra_deg + dra.to_degrees()).rem_euclid(360.0), d1.to_degrees())
}

/// The rows of the targets' components, then of the standards' measurements, in catalog
/// order; and the number of targets without a component and of standards without a
/// measurement (no row).
fn rows(cat: &Catalog) -> (Vec<Row>, usize, usize) {
    let mut rows = Vec::new();
    let mut without = 0;
    for t in &cat.targets {
        if t.components.is_empty() {
            without += 1;
        }
        let seq = [t.ra_deg, t.dec_deg, t.mjd_mean, t.separation_arcsec, t.pa_deg];
        let interval = t.delta_gamma_interval_deg;
        let dg = [
            t.delta_gamma_deg,
            t.sigma_delta_gamma_deg,
            interval.map(|i| i[0]),
            interval.map(|i| i[1]),
            t.foreground.as_ref().map(|f| f.q),
            t.foreground.as_ref().map(|f| f.u),
            t.foreground.as_ref().map(|f| f.sigma_q),
            t.foreground.as_ref().map(|f| f.sigma_u),
            t.delta_gamma_fg_corrected_deg,
            t.sigma_delta_gamma_fg_corrected_deg,
        ];
        for (k, c) in t.components.iter().enumerate() {
            // Each star's own position: A at the pointing, B where the measured geometry
            // puts it (the separation and PA are of B from A).
            let mut seq = seq;
            if k == 1 {
                let b = match (t.ra_deg, t.dec_deg, t.separation_arcsec, t.pa_deg) {
                    (Some(ra), Some(dec), Some(sep), Some(pa)) => Some(offset_position(ra, dec, sep, pa)),
                    _ => None,
                };
                seq[0] = b.map(|b| b.0);
                seq[1] = b.map(|b| b.1);
            }
            rows.push(Row {
                target: t.object.clone(),
                kind: "target",
                sequence: t.sequence_id().to_string(),
                filter: t.filter.clone().unwrap_or_default(),
                status: status_text(t.status),
                component: c.name.clone(),
                num: row_values(c, seq, dg),
                passes_cut: c.passes_cut,
                flags: join(&c.flags, ";"),
                target_flags: join(t.target_flags(), ";"),
            });
        }
        // Its field stars, after the components: each at its own sky position, with its
        // separation and PA from A; `passes_cut` only when usable too.
        for f in t.field_stars.iter().flatten() {
            let c = &f.star;
            let seq = [
                f.ra_deg,
                f.dec_deg,
                t.mjd_mean,
                Some(f.separation_arcsec),
                Some(f.pa_deg),
            ];
            let mut flags = join(&c.flags, ";");
            if !f.usable {
                flags = if flags.is_empty() {
                    "unusable".into()
                } else {
                    format!("unusable;{flags}")
                };
            }
            rows.push(Row {
                target: t.object.clone(),
                kind: "field_star",
                sequence: t.sequence_id().to_string(),
                filter: t.filter.clone().unwrap_or_default(),
                status: status_text(t.status),
                component: f.id.clone(),
                num: row_values(c, seq, [None; 10]),
                passes_cut: c.passes_cut && f.usable,
                flags,
                target_flags: join(t.target_flags(), ";"),
            });
        }
    }
    let mut unmeasured = 0;
    for s in &cat.standards {
        let Some(c) = &s.measured else {
            unmeasured += 1;
            continue;
        };
        rows.push(Row {
            target: s.name.clone(),
            kind: "standard",
            sequence: s.sequence.clone(),
            filter: s.filter.clone(),
            status: status_text(s.status),
            component: String::new(),
            num: row_values(c, [s.ra_deg, s.dec_deg, s.mjd_mean, None, None], [None; 10]),
            passes_cut: c.passes_cut,
            flags: join(&c.flags, ";"),
            target_flags: join(&s.flags, ";"),
        });
    }
    (rows, without, unmeasured)
}

/// Build the table of `cat` (read from `source`, stored in the provenance columns).
pub fn table(cat: &Catalog, source: &str) -> Table {
    let software = provenance_text(cat.provenance.softwares());
    let commit = provenance_text(cat.provenance.commits());
    let (rows, without, unmeasured) = rows(cat);
    let n = rows.len();
    let text = |name, description, f: fn(&Row) -> String| Column {
        name,
        unit: "",
        description,
        data: Data::Str(rows.iter().map(f).collect()),
    };
    let mut columns = vec![
        text("target", "object name (standards: name in the standards table)", |r| {
            r.target.clone()
        }),
        text(
            "kind",
            "target (a binary's component), field_star (another star of the target's field) or standard",
            |r| r.kind.into(),
        ),
        text("sequence", "sequence id, object@TPL START", |r| r.sequence.clone()),
        text("filter", "filter", |r| r.filter.clone()),
        text("status", "target status: ok, partial, failed", |r| r.status.clone()),
        text(
            "component",
            "A (brighter) or B; a field star's id (F1, F2...); empty for a standard",
            |r| r.component.clone(),
        ),
    ];
    for (i, (name, unit, description)) in NUMERIC.into_iter().enumerate() {
        columns.push(Column {
            name,
            unit,
            description,
            data: Data::F64(rows.iter().map(|r| r.num[i]).collect()),
        });
    }
    columns.push(Column {
        name: "passes_cut",
        unit: "",
        description: "P / sigma_P > 3",
        data: Data::Bool(rows.iter().map(|r| r.passes_cut).collect()),
    });
    columns.push(text("flags", "component flags, ';'-separated", |r| r.flags.clone()));
    columns.push(text("target_flags", "target (or standard) flags, ';'-separated", |r| {
        r.target_flags.clone()
    }));
    columns.push(Column {
        name: SOFTWARE,
        unit: "",
        description: "software that made the catalog",
        data: Data::Str(vec![software.clone(); n]),
    });
    columns.push(Column {
        name: "catalog",
        unit: "",
        description: "catalog file exported",
        data: Data::Str(vec![source.to_string(); n]),
    });
    let meta = vec![
        (SOFTWARE, software),
        ("commit", commit),
        ("catalog", source.to_string()),
        ("schema_version", cat.schema_version.clone()),
        ("exported_by", format!("sofipol export {}", env!("CARGO_PKG_VERSION"))),
    ];
    Table {
        columns,
        meta,
        targets_without_components: without,
        standards_without_measurement: unmeasured,
    }
}

/// The column and table keyword naming the software that made the catalog.
const SOFTWARE: &str = "software";

/// A provenance entry as one text: the catalog's values of `software` or `commit` (for a
/// merged catalog the distinct values of the catalogs it was merged from,
/// [`crate::catalog::Provenance::softwares`]) joined by `; `; `unknown` when there is none.
fn provenance_text(v: Vec<String>) -> String {
    if v.is_empty() {
        "unknown".into()
    } else {
        v.join("; ")
    }
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) || s.starts_with('#') || s.trim() != s {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// A text cell of a plain CSV file, safe to open in a spreadsheet: a cell starting with
/// `=`, `+`, `-`, `@`, a tab or a carriage return would be read as a formula (CSV formula
/// injection: an OBJECT of `=HYPERLINK(...)`), so it gets a leading `'`, which
/// spreadsheets show as text. Only text columns: numbers (a negative q) stay numbers.
/// ECSV and FITS keep the value (astropy reads them as data, never as formulas).
fn spreadsheet_safe(s: &str) -> std::borrow::Cow<'_, str> {
    if s.starts_with(['=', '+', '-', '@', '\t', '\r']) {
        format!("'{s}").into()
    } else {
        s.into()
    }
}

fn cell(c: &Column, i: usize, csv: bool) -> String {
    match &c.data {
        Data::Str(v) if csv => csv_field(&spreadsheet_safe(&v[i])),
        Data::Str(v) => csv_field(&v[i]),
        // `{}` prints the shortest string that parses back to the same f64.
        Data::F64(v) => {
            if v[i].is_nan() {
                "nan".into()
            } else {
                format!("{}", v[i])
            }
        }
        Data::Bool(v) => (if v[i] { "True" } else { "False" }).into(),
    }
}

/// The header line and the rows; `csv`: plain CSV, whose text cells are made
/// [`spreadsheet_safe`].
fn body(t: &Table, csv: bool) -> String {
    let mut s = t.columns.iter().map(|c| c.name).collect::<Vec<_>>().join(",");
    s.push('\n');
    for i in 0..t.rows() {
        s += &t.columns.iter().map(|c| cell(c, i, csv)).collect::<Vec<_>>().join(",");
        s.push('\n');
    }
    s
}

/// JSON string (a valid YAML flow scalar).
fn y(s: &str) -> String {
    serde_json::Value::String(s.to_string()).to_string()
}

/// The ECSV 1.0 text of the table (delimiter ',').
pub fn to_ecsv(t: &Table) -> String {
    let mut h = String::from("# %ECSV 1.0\n# ---\n# delimiter: ','\n# datatype:\n");
    for c in &t.columns {
        let dt = match c.data {
            Data::Str(_) => "string",
            Data::F64(_) => "float64",
            Data::Bool(_) => "bool",
        };
        h += &format!("# - {{name: {}, ", c.name);
        if !c.unit.is_empty() {
            h += &format!("unit: {}, ", c.unit);
        }
        h += &format!("datatype: {dt}, description: {}}}\n", y(c.description));
    }
    h += "# meta: !!omap\n";
    for (k, v) in &t.meta {
        h += &format!("# - {{{k}: {}}}\n", y(v));
    }
    h += "# schema: astropy-2.0\n";
    h + &body(t, false)
}

/// The plain CSV text of the table (text cells made spreadsheet-safe).
pub fn to_csv(t: &Table) -> String {
    body(t, true)
}

/// Errors of the export.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Writing failed.
    #[error("writing {path}: {reason}")]
    Write {
        /// The file.
        path: String,
        /// What went wrong.
        reason: String,
    },
}

/// The bytes [`write()`] would write (`-o -`: standard output). FITS goes through a file in
/// a private temporary directory (cfitsio writes files).
pub fn to_bytes(t: &Table, format: Format) -> Result<Vec<u8>, Error> {
    match format {
        Format::Ecsv => Ok(to_ecsv(t).into_bytes()),
        Format::Csv => Ok(to_csv(t).into_bytes()),
        Format::Fits => {
            let werr = |reason: String| Error::Write {
                path: "standard output".into(),
                reason,
            };
            let dir = tempfile::tempdir().map_err(|e| werr(format!("temporary directory: {e}")))?;
            let p = dir.path().join("table.fits");
            write_fits(t, &p).map_err(|e| werr(format!("cfitsio: {e}")))?;
            std::fs::read(&p).map_err(|e| werr(e.to_string()))
        }
    }
}

/// Write `t` to `path` in `format`, atomically (temporary file in the same directory, renamed).
pub fn write(t: &Table, format: Format, path: &Path) -> Result<(), Error> {
    let werr = |reason: String| Error::Write {
        path: path.display().to_string(),
        reason,
    };
    match format {
        Format::Ecsv => crate::io::write_atomic(path, to_ecsv(t).as_bytes()).map_err(|e| werr(e.to_string())),
        Format::Csv => crate::io::write_atomic(path, to_csv(t).as_bytes()).map_err(|e| werr(e.to_string())),
        Format::Fits => {
            // cfitsio creates the file by name: in a private directory next to `path`.
            let mut tmp = sofipol_calib::atomic::TempFile::new(path).map_err(|e| werr(e.to_string()))?;
            let name = tmp.ascii_path().map(PathBuf::from).unwrap_or_else(|| tmp.path.clone());
            write_fits(t, &name).map_err(|e| werr(format!("cfitsio: {e}")))?;
            tmp.commit(path).map_err(|e| werr(e.to_string()))
        }
    }
}

/// The longest text a FITS table cell holds, characters (a value cut to it says how long
/// it was; the JSON catalog keeps it whole).
pub const MAX_FITS_TEXT: usize = 1024;

/// A text value as a FITS table cell can hold it: control characters (a NUL would end the
/// C string cfitsio writes) escaped as `printable` shows them, and at most
/// [`MAX_FITS_TEXT`] characters, a longer value cut saying how long it was.
pub fn fits_text(s: &str) -> String {
    let p = sofipol_calib::text::printable(s);
    let n = p.chars().count();
    if n <= MAX_FITS_TEXT {
        return p.into_owned();
    }
    let note = format!("...({n} characters)");
    let head: String = p.chars().take(MAX_FITS_TEXT - note.len()).collect();
    head + &note
}

/// Column `colnum` (1-based) of the current table HDU, a logical ('L') column, written as
/// T/F cells (astropy reads them as bool; TOPCAT as Boolean). fitsio writes no logical
/// column, so this calls cfitsio's `ffpcll` directly.
fn write_logical_col(f: &mut fitsio::FitsFile, colnum: usize, values: &[bool]) -> Result<(), fitsio::errors::Error> {
    if values.is_empty() {
        return Ok(());
    }
    let mut cells: Vec<std::os::raw::c_char> = values
        .iter()
        .map(|&b| std::os::raw::c_char::from(b as u8 as i8))
        .collect();
    let colnum = i32::try_from(colnum).map_err(|_| fitsio::errors::Error::Message(format!("column {colnum}")))?;
    let mut status = 0;
    // SAFETY: `f` is an open file whose current HDU is the table just created (every
    // `write_col` before this one made it current); `cells` holds `cells.len()` elements,
    // which cfitsio reads and does not keep; `status` outlives the call.
    #[allow(unsafe_code)]
    unsafe {
        fitsio::sys::ffpcll(
            f.as_raw(),
            colnum,
            1,
            1,
            cells.len() as i64,
            cells.as_mut_ptr(),
            &mut status,
        );
    }
    fitsio::errors::check_status(status)
}

fn write_fits(t: &Table, path: &Path) -> Result<(), fitsio::errors::Error> {
    use fitsio::tables::{ColumnDataType, ColumnDescription};
    let mut f = fitsio::FitsFile::create(path).open()?;
    let mut descs = Vec::new();
    for c in &t.columns {
        let mut d = ColumnDescription::new(c.name);
        match &c.data {
            Data::Str(v) => {
                let w = v.iter().map(|s| fits_text(s).len()).max().unwrap_or(1).max(1);
                d.with_type(ColumnDataType::String).that_repeats(w);
            }
            Data::F64(_) => {
                d.with_type(ColumnDataType::Double);
            }
            Data::Bool(_) => {
                d.with_type(ColumnDataType::Logical);
            }
        }
        descs.push(d.create()?);
    }
    let hdu = f.create_table("SOFIPOL".to_string(), &descs)?;
    for (i, c) in t.columns.iter().enumerate() {
        match &c.data {
            Data::Str(v) => {
                let v: Vec<String> = v.iter().map(|s| fits_text(s)).collect();
                hdu.write_col(&mut f, c.name, &v)?;
            }
            Data::F64(v) => {
                hdu.write_col(&mut f, c.name, v)?;
            }
            Data::Bool(v) => write_logical_col(&mut f, i + 1, v)?,
        }
        if !c.unit.is_empty() {
            hdu.write_key(&mut f, &format!("TUNIT{}", i + 1), c.unit)?;
        }
        hdu.write_key(&mut f, &format!("TCOMM{}", i + 1), c.description)?;
    }
    for (k, v) in &t.meta {
        let key: String = k.to_ascii_uppercase().chars().take(8).collect();
        hdu.write_key(&mut f, &key, v.as_str())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
