//! Catalog export to table formats astronomers load in one line (docs/cli.md, "export"):
//! ECSV (astropy `Table.read`), FITS binary table (astropy, TOPCAT, fitsio) and plain CSV.
//!
//! One row per component; targets without components (failed) have no row. Units are in
//! the column metadata (ECSV header YAML `unit`; FITS `TUNITn`, descriptions in `TCOMMn`);
//! flags are one string (`;`-separated); every row carries its target, status, the
//! software that made the catalog and the catalog file. All files are written to a
//! temporary file in the same directory and renamed.
use std::path::Path;

use crate::catalog::Catalog;

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

/// Column data.
#[derive(Debug, Clone, PartialEq)]
pub enum Data {
    /// Text.
    Str(Vec<String>),
    /// Numbers (NaN where the catalog has no value).
    F64(Vec<f64>),
    /// Booleans (FITS: int16 0/1).
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

/// Build the table of `cat` (read from `source`, stored in the provenance columns).
pub fn table(cat: &Catalog, source: &str) -> Table {
    let software = cat
        .provenance
        .get("software")
        .and_then(|v| v.as_str())
        .unwrap_or("unknown")
        .to_string();
    let (mut target, mut status, mut comp, mut flags, mut tflags) = (vec![], vec![], vec![], vec![], vec![]);
    let mut num: Vec<Vec<f64>> = vec![Vec::new(); 22];
    let mut cut = vec![];
    let mut without = 0;
    for t in &cat.targets {
        if t.components.is_empty() {
            without += 1;
        }
        let st = serde_json::to_value(t.status)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default();
        let tf = t.target_flags().join(";");
        for c in &t.components {
            target.push(t.object.clone());
            status.push(st.clone());
            comp.push(c.name.clone());
            flags.push(c.flags.join(";"));
            tflags.push(tf.clone());
            cut.push(c.passes_cut);
            let vals = [
                c.q,
                c.sigma_q,
                c.u,
                c.sigma_u,
                c.cov_qu.unwrap_or(f64::NAN),
                c.sigma_q_stat.unwrap_or(f64::NAN),
                c.sigma_u_stat.unwrap_or(f64::NAN),
                c.cov_qu_stat.unwrap_or(f64::NAN),
                c.p,
                c.sigma_p,
                c.p_debiased,
                c.gamma_deg,
                c.sigma_gamma_deg,
                c.sigma_gamma_stat_deg.unwrap_or(f64::NAN),
                c.sigma_gamma_zero_point_deg.unwrap_or(f64::NAN),
                c.sigma_gamma_nkc_deg.unwrap_or(f64::NAN),
                c.snr.unwrap_or(f64::NAN),
                t.delta_gamma_deg.unwrap_or(f64::NAN),
                t.sigma_delta_gamma_deg.unwrap_or(f64::NAN),
                t.delta_gamma_interval_deg.map_or(f64::NAN, |i| i[0]),
                t.delta_gamma_interval_deg.map_or(f64::NAN, |i| i[1]),
                c.flux_adu.unwrap_or(f64::NAN),
            ];
            for (col, v) in num.iter_mut().zip(vals) {
                col.push(v);
            }
        }
    }
    let n = target.len();
    let mut num = num.into_iter();
    let mut f = |name, unit, description| Column {
        name,
        unit,
        description,
        data: Data::F64(num.next().unwrap()),
    };
    let columns = vec![
        Column {
            name: "target",
            unit: "",
            description: "object name",
            data: Data::Str(target),
        },
        Column {
            name: "status",
            unit: "",
            description: "target status: ok, partial, failed",
            data: Data::Str(status),
        },
        Column {
            name: "component",
            unit: "",
            description: "A (brighter) or B",
            data: Data::Str(comp),
        },
        f("q", "", "normalised Stokes q, sky frame (fraction)"),
        f("sigma_q", "", "1-sigma error of q: measurement and calibration"),
        f("u", "", "normalised Stokes u, sky frame (fraction)"),
        f("sigma_u", "", "1-sigma error of u: measurement and calibration"),
        f("cov_qu", "", "covariance of q and u: measurement and calibration"),
        f("sigma_q_stat", "", "1-sigma error of q from the measurement alone"),
        f("sigma_u_stat", "", "1-sigma error of u from the measurement alone"),
        f("cov_qu_stat", "", "covariance of q and u from the measurement alone"),
        f("p", "", "P = hypot(q, u), not debiased (fraction)"),
        f("sigma_p", "", "1-sigma error of P from the full q-u covariance"),
        f(
            "p_debiased",
            "",
            "debiased P (fraction), estimator in the catalog provenance",
        ),
        f("gamma", "deg", "polarization angle, east of north, [0, 180)"),
        f(
            "sigma_gamma",
            "deg",
            "1-sigma angle error, full q-u covariance (measurement+calibration)",
        ),
        f(
            "sigma_gamma_stat",
            "deg",
            "1-sigma angle error from the measurement alone",
        ),
        f(
            "sigma_gamma_zero_point",
            "deg",
            "1-sigma angle error from the night's calibration (c, theta0)",
        ),
        f(
            "sigma_gamma_nkc",
            "deg",
            "68.27% half-width, Naghizadeh-Khouei & Clarke at the debiased S/N",
        ),
        f("snr", "", "P / sigma_P"),
        f(
            "delta_gamma",
            "deg",
            "target: |gamma_A - gamma_B| folded to [0, 90]; NaN unless both pass",
        ),
        f(
            "sigma_delta_gamma",
            "deg",
            "target: 1-sigma error of delta_gamma (theta0 cancels, c does not)",
        ),
        f(
            "delta_gamma_lo",
            "deg",
            "target: low end of the central 68.27% interval of delta_gamma",
        ),
        f(
            "delta_gamma_hi",
            "deg",
            "target: high end of the central 68.27% interval of delta_gamma",
        ),
        f("flux", "adu", "mean o+e flux per dither"),
        Column {
            name: "passes_cut",
            unit: "",
            description: "P / sigma_P > 3",
            data: Data::Bool(cut),
        },
        Column {
            name: "flags",
            unit: "",
            description: "component flags, ';'-separated",
            data: Data::Str(flags),
        },
        Column {
            name: "target_flags",
            unit: "",
            description: "target flags, ';'-separated",
            data: Data::Str(tflags),
        },
        Column {
            name: "software",
            unit: "",
            description: "software that made the catalog",
            data: Data::Str(vec![software.clone(); n]),
        },
        Column {
            name: "catalog",
            unit: "",
            description: "catalog file exported",
            data: Data::Str(vec![source.to_string(); n]),
        },
    ];
    let meta = vec![
        ("software", software),
        ("catalog", source.to_string()),
        ("schema_version", cat.schema_version.clone()),
        ("exported_by", format!("sofipol export {}", env!("CARGO_PKG_VERSION"))),
    ];
    Table {
        columns,
        meta,
        targets_without_components: without,
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
            let tmp = sofipol_calib::atomic::TempFile::new(path).map_err(|e| werr(e.to_string()))?;
            write_fits(t, &tmp.path).map_err(|e| werr(format!("cfitsio: {e}")))?;
            tmp.commit(path).map_err(|e| werr(e.to_string()))
        }
    }
}

fn write_fits(t: &Table, path: &Path) -> Result<(), fitsio::errors::Error> {
    use fitsio::tables::{ColumnDataType, ColumnDescription};
    let mut f = fitsio::FitsFile::create(path).open()?;
    let mut descs = Vec::new();
    for c in &t.columns {
        let mut d = ColumnDescription::new(c.name);
        match &c.data {
            Data::Str(v) => {
                let w = v.iter().map(|s| s.len()).max().unwrap_or(1).max(1);
                d.with_type(ColumnDataType::String).that_repeats(w);
            }
            Data::F64(_) => {
                d.with_type(ColumnDataType::Double);
            }
            Data::Bool(_) => {
                d.with_type(ColumnDataType::Short);
            }
        }
        descs.push(d.create()?);
    }
    let hdu = f.create_table("SOFIPOL".to_string(), &descs)?;
    for (i, c) in t.columns.iter().enumerate() {
        match &c.data {
            Data::Str(v) => {
                hdu.write_col(&mut f, c.name, v)?;
            }
            Data::F64(v) => {
                hdu.write_col(&mut f, c.name, v)?;
            }
            Data::Bool(v) => {
                let ints: Vec<i16> = v.iter().map(|&b| b as i16).collect();
                hdu.write_col(&mut f, c.name, &ints)?;
            }
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
