//! What made a product: the `provenance` of a catalog, of `calibration.json` and of the
//! statistics' JSON, one type for all of them (docs/catalog-schema.md).
//!
//! Every command starts from [`Provenance::now`] (software, commit, command line, time) and
//! fills in what it knows. Reading is lenient: a key this build does not know, or a known
//! key whose value has another shape (an older or another tool's catalog), is kept in
//! `extra` as it was read and written back, so nothing a catalog carries is lost.
//!
//! Keys are declared in alphabetical order: serde writes fields in declaration order, and
//! catalogs written before this type existed (a JSON object, whose keys serde_json sorts)
//! stay byte-identical.
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// A value that is one string, or a list of them where merged inputs disagreed
/// (`software`, `commit` of a merged catalog).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum OneOrMany {
    /// One value.
    One(String),
    /// The distinct values, in order.
    Many(Vec<String>),
}

impl OneOrMany {
    /// The values, in order.
    pub fn values(&self) -> Vec<String> {
        match self {
            OneOrMany::One(s) => vec![s.clone()],
            OneOrMany::Many(v) => v.clone(),
        }
    }

    /// One string when the values are one, else the list (empty: `None`).
    pub fn from_values(values: Vec<String>) -> Option<OneOrMany> {
        match values.len() {
            0 => None,
            1 => values.into_iter().next().map(OneOrMany::One),
            _ => Some(OneOrMany::Many(values)),
        }
    }
}

/// The calibration settings a night was reduced with (`provenance.calibration`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationInputs {
    /// The calibration directory given (`--calib`), if any.
    pub calib_dir: Option<String>,
    /// The `[calibration]` settings.
    pub params: Value,
    /// The standards tables read (built-in and files).
    pub standards_table: Value,
}

/// One flat of the night (`provenance.flat.flats[]`): written by the flat stage.
pub use sofipol_calib::flat::FlatRecord;

/// A flat file that could not be read (`provenance.flat.errors[]`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FlatFileError {
    /// Why.
    pub error: String,
    /// The file.
    pub file: String,
}

/// How the night was flat-fielded (`provenance.flat`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct FlatProvenance {
    /// Flat files that could not be read (`mode` `file` or `none` after files were given).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub errors: Option<Vec<FlatFileError>>,
    /// The flats used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flats: Option<Vec<FlatRecord>>,
    /// Where flat files came from (`flat`: the settings, `calib_dir`: another night).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from: Option<String>,
    /// `dome`, `superflat`, `file`, `none` or `none (no_flat)`.
    pub mode: String,
    /// Why a filter has no superflat.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<Vec<String>>,
}

impl FlatProvenance {
    /// Flat-fielding of the given mode with nothing else known.
    pub fn mode(mode: &str) -> FlatProvenance {
        FlatProvenance {
            errors: None,
            flats: None,
            from: None,
            mode: mode.to_string(),
            notes: None,
        }
    }

    /// The flats used (none when there are none).
    pub fn flat_list(&self) -> &[FlatRecord] {
        self.flats.as_deref().unwrap_or_default()
    }
}

/// A catalog a merged catalog was joined from (`provenance.merged_from[]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MergedFrom {
    /// Its file.
    pub file: String,
    /// Its provenance.
    #[serde(default)]
    pub provenance: Provenance,
}

/// What made a product. Every field is optional: each command writes what it knows
/// (docs/catalog-schema.md lists which).
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct Provenance {
    /// The calibration settings of the reduction.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationInputs>,
    /// The statistics' input catalog (`sofipol stats`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub catalog: Option<String>,
    /// The command line, one word per entry.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub command_line: Option<Vec<String>>,
    /// Git commit of the build (a list when merged inputs disagree).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub commit: Option<OneOrMany>,
    /// When the product was written, UTC (ISO 8601).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub created_utc: Option<String>,
    /// How the night was flat-fielded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flat: Option<FlatProvenance>,
    /// The inputs as given (folders, files).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub inputs: Option<Vec<String>>,
    /// The standard sequences known to `sofipol watch` when it wrote the catalog.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live_standards: Option<Vec<String>>,
    /// The catalogs a merged catalog was joined from, each with its provenance.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub merged_from: Option<Vec<MergedFrom>>,
    /// Shards of the night that were not given to `sofipol merge`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub missing_shards: Option<Vec<String>>,
    /// The frames the night's bad-pixel mask was detected on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub night_bad_pixel_mask_from: Option<Vec<String>>,
    /// The reduction settings (or a command's parameters).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub parameters: Option<Value>,
    /// The instrument profile.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub profile: Option<Value>,
    /// The profile's angle zero-point and parity (`calibration.json`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub profile_angles: Option<Value>,
    /// `k/n` for a shard of a night; `null` for a whole night.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<Option<String>>,
    /// `sofipol <version>` (a list when merged inputs disagree).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub software: Option<OneOrMany>,
    /// The standard sequences a calibration was measured from.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub standard_sequences: Option<Vec<String>>,
    /// The standards tables read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub standards_table: Option<Value>,
    /// Keys this build does not know, or known keys of another shape: kept as read.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// This build: `sofipol <version>`.
pub fn software() -> String {
    format!("sofipol {}", env!("CARGO_PKG_VERSION"))
}

impl Provenance {
    /// What every product starts with: this build (software, commit), the command line and
    /// the time (UTC).
    pub fn now() -> Provenance {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        Provenance {
            command_line: Some(crate::build_info::command_line()),
            created_utc: Some(sofipol_calib::time::iso_from_mjd(40587.0 + now / 86400.0, false)),
            ..Provenance::build()
        }
    }

    /// This build alone (software, commit): what a product that is not tied to one command
    /// run records (the calibration measured inside a night).
    pub fn build() -> Provenance {
        Provenance {
            commit: Some(OneOrMany::One(crate::build_info::commit().to_string())),
            software: Some(OneOrMany::One(software())),
            ..Provenance::default()
        }
    }

    /// The distinct values of `software` (`commit` with [`Provenance::commits`]): this
    /// catalog's, else, for a merged catalog written without them, those of the catalogs it
    /// was merged from, recursively. Empty when none is known.
    pub fn softwares(&self) -> Vec<String> {
        self.values(|p| p.software.as_ref())
    }

    /// The distinct values of `commit` (as [`Provenance::softwares`]).
    pub fn commits(&self) -> Vec<String> {
        self.values(|p| p.commit.as_ref())
    }

    fn values(&self, key: fn(&Provenance) -> Option<&OneOrMany>) -> Vec<String> {
        fn collect(p: &Provenance, key: fn(&Provenance) -> Option<&OneOrMany>, out: &mut Vec<String>) {
            match key(p) {
                Some(v) => {
                    for s in v.values() {
                        if !out.contains(&s) {
                            out.push(s);
                        }
                    }
                }
                None => {
                    for part in p.merged_from.iter().flatten() {
                        collect(&part.provenance, key, out);
                    }
                }
            }
        }
        let mut out = Vec::new();
        collect(self, key, &mut out);
        out
    }

    /// The flat-fielding mode (`none` when not recorded).
    pub fn flat_mode(&self) -> &str {
        self.flat.as_ref().map_or("none", |f| f.mode.as_str())
    }

    /// The flats used (none when not recorded).
    pub fn flat_list(&self) -> &[FlatRecord] {
        self.flat.as_ref().map_or(&[], FlatProvenance::flat_list)
    }

    /// Whether nothing is recorded.
    pub fn is_empty(&self) -> bool {
        *self == Provenance::default()
    }
}

impl<'de> Deserialize<'de> for Provenance {
    /// Lenient: an object whose known keys have the expected shape fill the fields; every
    /// other key is kept in `extra`. `null` reads as empty; anything else that is not an
    /// object is refused.
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Provenance, D::Error> {
        let mut map = match Option::<Value>::deserialize(d)? {
            None | Some(Value::Null) => return Ok(Provenance::default()),
            Some(Value::Object(m)) => m,
            Some(other) => {
                let kind = match other {
                    Value::Array(_) => "a list",
                    Value::String(_) => "a string",
                    _ => "a number or a boolean",
                };
                return Err(serde::de::Error::custom(format_args!(
                    "provenance: expected an object, found {kind}"
                )));
            }
        };
        let mut extra = Map::new();
        let mut take = |key: &str| map.remove(key).map(|v| (key.to_string(), v));
        let mut typed = Provenance::default();
        macro_rules! field {
            ($name:ident) => {
                if let Some((k, v)) = take(stringify!($name)) {
                    match serde_json::from_value(v.clone()) {
                        Ok(x) => typed.$name = Some(x),
                        Err(_) => {
                            extra.insert(k, v);
                        }
                    }
                }
            };
        }
        field!(calibration);
        field!(catalog);
        field!(command_line);
        field!(commit);
        field!(created_utc);
        field!(flat);
        field!(inputs);
        field!(live_standards);
        field!(merged_from);
        field!(missing_shards);
        field!(night_bad_pixel_mask_from);
        field!(parameters);
        field!(profile);
        field!(profile_angles);
        field!(software);
        field!(standard_sequences);
        field!(standards_table);
        if let Some((k, v)) = take("shard") {
            match v {
                Value::Null => typed.shard = Some(None),
                Value::String(s) => typed.shard = Some(Some(s)),
                other => {
                    extra.insert(k, other);
                }
            }
        }
        extra.extend(map);
        typed.extra = extra;
        Ok(typed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A provenance as the object catalogs held before it was typed: every key written
    /// back in the same order, unknown and odd-shaped keys kept.
    #[test]
    fn a_provenance_reads_and_writes_back_unchanged() {
        let text = r#"{"calibration":{"calib_dir":null,"params":{"no_calibration":false},"standards_table":["built-in"]},"command_line":["sofipol","night","x"],"commit":"abc","created_utc":"2026-01-01T00:00:00","flat":{"flats":[{"bad_pixels":3,"detail":"d","file":null,"filter":"Ks","frames":["a.fits"],"kind":"dome","posang_deg":null}],"mode":"dome"},"inputs":["x"],"night_bad_pixel_mask_from":[],"parameters":{"a":1},"profile":{"b":2},"shard":null,"software":"sofipol 9","zzz_other_tool":{"k":[1,2]}}"#;
        let p: Provenance = serde_json::from_str(text).unwrap();
        assert_eq!(p.shard, Some(None));
        assert_eq!(p.flat_mode(), "dome");
        assert_eq!(p.flat_list()[0].posang_deg, None);
        assert_eq!(p.extra.len(), 1);
        assert_eq!(serde_json::to_string(&p).unwrap(), text);
        // A known key of another shape is kept as read, not refused.
        let odd: Provenance = serde_json::from_str(r#"{"inputs": 5, "shard": 3}"#).unwrap();
        assert_eq!(odd.inputs, None);
        assert_eq!(odd.extra["inputs"], 5);
        assert_eq!(odd.extra["shard"], 3);
        assert!(serde_json::from_str::<Provenance>("[1]").is_err());
        assert!(serde_json::from_str::<Provenance>("null").unwrap().is_empty());
    }

    /// `software` and `commit`: the catalog's own, else those it was merged from, each
    /// value once.
    #[test]
    fn software_and_commit_come_from_the_merged_inputs_when_absent() {
        let text = r#"{"merged_from":[{"file":"a","provenance":{"software":"sofipol 1","commit":"x"}},
            {"file":"b","provenance":{"software":["sofipol 1","sofipol 2"]}}]}"#;
        let p: Provenance = serde_json::from_str(text).unwrap();
        assert_eq!(p.softwares(), ["sofipol 1", "sofipol 2"]);
        assert_eq!(p.commits(), ["x"]);
        let now = Provenance::now();
        assert_eq!(now.softwares(), [software()]);
        assert!(now.created_utc.is_some() && now.command_line.is_some());
    }
}
