//! The table of polarimetric standard stars: built-in entries
//! (`pipeline/standards/builtin.toml`, each with its band and literature reference) plus a
//! user file (`--standards FILE`) in the same TOML format that adds entries or overrides
//! them by name and filter (docs/frame-format.md, "Standard stars and the standards table").
//!
//! Names match an OBJECT or OBS TARG NAME ignoring case, spaces and '_' ("HD_64299",
//! "hd64299" and "HD 64299" are one star). Filter "*" applies to every filter; an entry for
//! the exact filter (ignoring case) wins over "*".
use std::path::Path;

use crate::error::{Error, Result};

use serde::{Deserialize, Serialize};

/// The built-in table (TOML text).
pub const BUILTIN_TOML: &str = include_str!("../standards/builtin.toml");

/// One standard in one filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StandardStar {
    /// Name as in the literature.
    pub name: String,
    /// Filter the values are for ("*": any).
    pub filter: String,
    /// Degree of linear polarization (fraction, sky frame); 0 for unpolarized standards.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub p: f64,
    /// 1-sigma error of p.
    #[serde(deserialize_with = "crate::nullable::num")]
    pub sigma_p: f64,
    /// Polarization angle, degrees east of north (ignored when p = 0).
    #[serde(default, deserialize_with = "crate::nullable::num")]
    pub gamma_deg: f64,
    /// 1-sigma error of the angle, deg.
    #[serde(default = "default_sigma_gamma", deserialize_with = "crate::nullable::num")]
    pub sigma_gamma_deg: f64,
    /// Band the values were measured in (or how they were derived).
    #[serde(default)]
    pub band: String,
    /// Literature reference.
    #[serde(default)]
    pub reference: String,
    /// Magnitude of the star in this entry's filter (a photometric standard; absent: the
    /// entry calibrates polarimetry only). Only for an entry of one filter, never `"*"`.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub mag: Option<f64>,
    /// 1-sigma error of `mag`, mag (required with `mag`).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::nullable::opt"
    )]
    pub sigma_mag: Option<f64>,
    /// The photometric system and band of `mag` (e.g. `"2MASS Ks"`).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub mag_band: String,
    /// Where `mag` comes from.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub mag_reference: String,
}

/// The range a standard's `mag` may take: the brightest stars are near -1.5 mag in the
/// near-infrared, and a standard fainter than 25 mag is not one a 3.6 m telescope measures.
pub const MAG_RANGE: std::ops::RangeInclusive<f64> = -2.0..=25.0;
/// The largest `sigma_mag` a standard may give, mag.
pub const MAX_SIGMA_MAG: f64 = 1.0;

fn default_sigma_gamma() -> f64 {
    1.0
}

impl StandardStar {
    /// Whether the table calls it polarized (p > 3 sigma_p).
    pub fn polarized(&self) -> bool {
        self.p > 0.0 && self.p > 3.0 * self.sigma_p
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    standard: Vec<StandardStar>,
}

/// A standards table.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct StandardsTable {
    /// Entries (built-in first, user entries replacing same name and filter).
    pub entries: Vec<StandardStar>,
    /// Where the entries came from ("builtin", file paths).
    pub sources: Vec<String>,
}

/// A name reduced for matching: lower case, without spaces and '_'.
pub fn match_key(name: &str) -> String {
    name.chars()
        .filter(|c| !c.is_whitespace() && *c != '_')
        .flat_map(|c| c.to_lowercase())
        .collect()
}

/// The key an entry is matched by: its name reduced by [`match_key`] and its filter
/// (trimmed, lower case).
fn entry_key(s: &StandardStar) -> (String, String) {
    (match_key(&s.name), s.filter.trim().to_ascii_lowercase())
}

/// Largest degree of polarization (and error) a standards table may give, as a fraction:
/// the most polarized standards reach ~9 % in the optical and less in the infrared, so a
/// larger number is a value written in per cent.
pub const MAX_STANDARD_P: f64 = 0.1;

/// The entries of a table file, each checked: a name, a filter (`"*"` for any), `p` in
/// [0, [`MAX_STANDARD_P`]], `sigma_p` in (0, [`MAX_STANDARD_P`]], `gamma_deg` in [0, 180),
/// `sigma_gamma_deg` in (0, 90] (the standard deviation of a uniform angle is 52 deg),
/// every number finite; and no two entries of the same star and filter in one file
/// ([`entry_key`]: `HD 204827` and `HD_204827` are one star), where the second would
/// silently replace the first. Errors name the file (`origin`), the entry
/// (`standard[i] 'NAME' (filter 'F')`), the key and the value.
fn parse(text: &str, origin: &str) -> Result<Vec<StandardStar>> {
    let err = |reason: String| Error::Standards {
        origin: origin.to_string(),
        reason,
    };
    let f: File = toml::from_str(text).map_err(|e| err(e.to_string()))?;
    let mut seen: std::collections::HashMap<(String, String), usize> = Default::default();
    for (i, s) in f.standard.iter().enumerate() {
        let entry = format!(
            "standard[{i}] '{}' (filter '{}')",
            sofipol_calib::text::short_text(&s.name, 60),
            sofipol_calib::text::short_text(&s.filter, 20)
        );
        if match_key(&s.name).is_empty() {
            return Err(err(format!("{entry}: name is empty")));
        }
        if s.filter.trim().is_empty() {
            return Err(err(format!("{entry}: filter is empty (\"*\" applies to every filter)")));
        }
        let checks: [(&str, f64, bool, &str); 4] = [
            (
                "p",
                s.p,
                (0.0..=MAX_STANDARD_P).contains(&s.p),
                "a fraction in [0, 0.1] (0.0088 for 0.88 %; no polarimetric standard exceeds 10 %)",
            ),
            (
                "sigma_p",
                s.sigma_p,
                s.sigma_p > 0.0 && s.sigma_p <= MAX_STANDARD_P,
                "a fraction in (0, 0.1] (0.0005 for 0.05 %)",
            ),
            (
                "gamma_deg",
                s.gamma_deg,
                (0.0..180.0).contains(&s.gamma_deg),
                "in [0, 180) deg",
            ),
            (
                "sigma_gamma_deg",
                s.sigma_gamma_deg,
                s.sigma_gamma_deg > 0.0 && s.sigma_gamma_deg <= 90.0,
                "in (0, 90] deg",
            ),
        ];
        if let Some((key, v, _, want)) = checks.iter().find(|c| !c.2) {
            return Err(err(format!(
                "{entry}: {key} = {}: must be {want}",
                sofipol_calib::text::short_number(*v)
            )));
        }
        check_magnitude(s).map_err(|why| err(format!("{entry}: {why}")))?;
        if let Some(j) = seen.insert(entry_key(s), i) {
            let first = &f.standard[j];
            return Err(err(format!(
                "{entry}: the same star and filter as standard[{j}] '{}' (filter '{}') (names match ignoring \
                 case, spaces and '_'): the second entry would silently replace the first; keep one",
                first.name, first.filter
            )));
        }
    }
    Ok(f.standard)
}

/// An entry's photometric fields: `mag` and `sigma_mag` together, `mag` in [`MAG_RANGE`],
/// `sigma_mag` in (0, [`MAX_SIGMA_MAG`]], both finite, and only on an entry of one filter
/// (a magnitude is for one band); the band and reference only with a magnitude.
fn check_magnitude(s: &StandardStar) -> std::result::Result<(), String> {
    use sofipol_calib::text::short_number;
    match (s.mag, s.sigma_mag) {
        (None, None) => {
            if !s.mag_band.is_empty() || !s.mag_reference.is_empty() {
                return Err("mag_band or mag_reference without mag: give mag and sigma_mag".into());
            }
            Ok(())
        }
        (Some(m), None) => Err(format!(
            "mag = {}: needs sigma_mag (its 1-sigma error, mag)",
            short_number(m)
        )),
        (None, Some(e)) => Err(format!("sigma_mag = {}: without mag", short_number(e))),
        (Some(m), Some(e)) => {
            if !MAG_RANGE.contains(&m) {
                return Err(format!(
                    "mag = {}: must be a finite magnitude in [{}, {}]",
                    short_number(m),
                    MAG_RANGE.start(),
                    MAG_RANGE.end()
                ));
            }
            if !(e > 0.0 && e <= MAX_SIGMA_MAG) {
                return Err(format!(
                    "sigma_mag = {}: must be in (0, {MAX_SIGMA_MAG}] mag",
                    short_number(e)
                ));
            }
            if s.filter.trim() == "*" {
                return Err(format!(
                    "mag = {}: a magnitude is for one band, and filter is \"*\": give the entry for its filter (filter = \"Ks\")",
                    short_number(m)
                ));
            }
            Ok(())
        }
    }
}

impl StandardsTable {
    /// The built-in table.
    pub fn builtin() -> StandardsTable {
        StandardsTable {
            entries: parse(BUILTIN_TOML, "builtin standards").expect("the built-in table parses (tested)"),
            sources: vec!["builtin".into()],
        }
    }

    /// Add or override entries (same name and filter) from TOML text.
    pub fn merge_toml(&mut self, text: &str, origin: &str) -> Result<()> {
        for s in parse(text, origin)? {
            let k = entry_key(&s);
            match self.entries.iter_mut().find(|e| entry_key(e) == k) {
                Some(e) => *e = s,
                None => self.entries.push(s),
            }
        }
        self.sources.push(origin.to_string());
        Ok(())
    }

    /// The built-in table plus a user file.
    pub fn with_file(path: &Path) -> Result<StandardsTable> {
        let text = sofipol_calib::input::read_to_string(path, sofipol_calib::input::MAX_OPTION_FILE_BYTES).map_err(
            |source| Error::Io {
                path: path.to_path_buf(),
                source,
            },
        )?;
        let mut t = StandardsTable::builtin();
        t.merge_toml(&text, &path.display().to_string())?;
        Ok(t)
    }

    /// The entry for a name (OBJECT or OBS TARG NAME) and filter: the exact filter first,
    /// then "*".
    pub fn find(&self, name: &str, filter: &str) -> Option<&StandardStar> {
        let k = match_key(name);
        let mine = self.entries.iter().filter(|e| match_key(&e.name) == k);
        let exact = mine.clone().find(|e| e.filter.eq_ignore_ascii_case(filter.trim()));
        exact.or_else(|| mine.clone().find(|e| e.filter.trim() == "*"))
    }

    /// Whether the name is in the table in any filter.
    pub fn knows(&self, name: &str) -> bool {
        let k = match_key(name);
        self.entries.iter().any(|e| match_key(&e.name) == k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_table_parses_and_every_entry_has_a_reference_and_band() {
        let t = StandardsTable::builtin();
        assert!(t.entries.len() >= 6);
        assert!(t.entries.iter().filter(|e| e.p == 0.0).count() >= 2);
        assert!(t.entries.iter().filter(|e| e.polarized()).count() >= 2);
        for e in &t.entries {
            assert!(!e.reference.is_empty() && !e.band.is_empty(), "{}", e.name);
        }
    }

    /// The built-in polarized Ks values are Serkowski-law extrapolations (builtin.toml):
    /// recompute each from its optical inputs, P(l) = Pmax exp(-K ln^2(lmax/l)),
    /// K = 1.66 lmax + 0.01 (Whittet et al. 1992), l = 2.16 um, and check the 25 % error.
    #[test]
    fn builtin_polarized_values_follow_the_serkowski_law_from_their_optical_inputs() {
        let t = StandardsTable::builtin();
        // (name, Pmax, lmax um): Serkowski 1974 list via UKIRT/IRPOL for the first two;
        // unverified inputs for HD 161056 (see its reference field).
        let inputs = [
            ("HD 204827", 0.056, 0.46),
            ("HD 154445", 0.037, 0.57),
            ("HD 161056", 0.0401, 0.58),
        ];
        for (name, pmax, lmax) in inputs {
            let k = 1.66 * lmax + 0.01;
            let pk = pmax * (-k * (lmax / 2.16f64).ln().powi(2)).exp();
            let e = t.find(name, "Ks").unwrap();
            assert!((e.p - pk).abs() < 5e-5, "{name}: table {} vs Serkowski {pk:.5}", e.p);
            assert!((e.sigma_p / e.p - 0.25).abs() < 0.02, "{name}: sigma_p {}", e.sigma_p);
            assert!(e.reference.contains("Whittet et al. 1992"), "{name}");
        }
        // Every polarized entry is one of those, or a J or H value measured by Whittet et
        // al. 1992 (checked against their table in pipeline/tests/real_data.rs); every
        // unpolarized one is p = 0 in any filter.
        for e in &t.entries {
            let measured = ["J", "H"].contains(&e.filter.as_str())
                && e.reference
                    .starts_with(&format!("Whittet et al. 1992, ApJ 386, 562, {} band", e.filter));
            if e.polarized() {
                assert!(
                    inputs.iter().any(|i| i.0 == e.name) || measured,
                    "{} has no recorded inputs",
                    e.name
                );
            } else {
                assert_eq!((e.p, e.filter.as_str()), (0.0, "*"), "{}", e.name);
            }
        }
    }

    #[test]
    fn names_match_ignoring_case_spaces_and_underscores() {
        let t = StandardsTable::builtin();
        for n in ["HD 64299", "HD_64299", "hd64299", " Hd 642_99 "] {
            assert_eq!(t.find(n, "Ks").map(|e| e.name.as_str()), Some("HD 64299"), "{n}");
        }
        assert!(t.find("HD 204827", "Ks").is_some_and(|e| e.polarized()));
        assert!(t.find("HD 204827", "J").is_none(), "polarized values are per filter");
        assert!(t.find("HK Tau", "Ks").is_none());
    }

    #[test]
    fn user_file_adds_and_overrides() {
        let mut t = StandardsTable::builtin();
        let n0 = t.entries.len();
        t.merge_toml(
            r#"
[[standard]]
name = "HD_204827"
filter = "ks"
p = 0.0120
sigma_p = 0.0003
gamma_deg = 60.0
sigma_gamma_deg = 0.5

[[standard]]
name = "My Std"
filter = "Ks"
p = 0.0
sigma_p = 0.0005
"#,
            "user.toml",
        )
        .unwrap();
        assert_eq!(t.entries.len(), n0 + 1);
        let e = t.find("HD 204827", "Ks").unwrap();
        assert_eq!((e.p, e.gamma_deg), (0.012, 60.0));
        assert!(t.find("MY_STD", "Ks").is_some());
        assert_eq!(t.sources, vec!["builtin".to_string(), "user.toml".to_string()]);
        // Errors name the file, the star and the value.
        let e = t
            .merge_toml(
                "[[standard]]\nname = \"X\"\nfilter = \"Ks\"\np = 1.5\nsigma_p = 0.1\n",
                "bad.toml",
            )
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad.toml") && e.contains("'X'") && e.contains("1.5"), "{e}");
        assert!(t
            .merge_toml("[[standard]]\nname = \"X\"\n", "bad2.toml")
            .unwrap_err()
            .to_string()
            .contains("bad2.toml"));
    }

    /// Every number of an entry is checked (finite, in range) and two entries of one star
    /// and filter in one file are refused, each naming the file, the entry and the key; a
    /// user entry replacing a built-in one is not a duplicate.
    #[test]
    fn out_of_range_numbers_and_duplicate_entries_are_refused_by_file_entry_and_key() {
        let entry = |k: &str, v: &str| {
            let fields = [
                ("name", "\"HD 204827\""),
                ("filter", "\"Ks\""),
                ("p", "0.0088"),
                ("sigma_p", "0.0022"),
                ("gamma_deg", "58.7"),
                ("sigma_gamma_deg", "2.0"),
            ];
            let body: Vec<String> = fields
                .iter()
                .map(|&(key, value)| format!("{key} = {}", if key == k { v } else { value }))
                .collect();
            format!("[[standard]]\n{}\n", body.join("\n"))
        };
        let mut t = StandardsTable::builtin();
        t.merge_toml(&entry("gamma_deg", "60.0"), "ok.toml").unwrap();
        assert_eq!(t.find("HD 204827", "Ks").unwrap().gamma_deg, 60.0);
        for (key, v) in [
            ("p", "nan"),
            ("p", "-0.01"),
            ("sigma_p", "0.0"),
            ("sigma_p", "inf"),
            ("sigma_p", "2.0"),
            ("gamma_deg", "nan"),
            ("gamma_deg", "-inf"),
            ("gamma_deg", "180.0"),
            ("gamma_deg", "-5.0"),
            ("sigma_gamma_deg", "1e200"),
            ("sigma_gamma_deg", "inf"),
            ("sigma_gamma_deg", "0.0"),
            ("sigma_gamma_deg", "-1.0"),
            ("sigma_gamma_deg", "nan"),
            ("sigma_gamma_deg", "90.5"),
        ] {
            let e = t.merge_toml(&entry(key, v), "bad.toml").unwrap_err().to_string();
            assert!(
                e.starts_with("bad.toml: standard[0] 'HD 204827' (filter 'Ks'): ") && e.contains(&format!("{key} = ")),
                "{key} = {v}: {e}"
            );
        }
        let e = t
            .merge_toml(&entry("name", "\"\""), "bad.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("name is empty"), "{e}");
        let e = t
            .merge_toml(&entry("filter", "\" \""), "bad.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("filter is empty"), "{e}");
        // The same star twice in one file (name spelt another way, filter in another case).
        let two = format!(
            "{}{}",
            entry("gamma_deg", "58.7"),
            entry("name", "\"HD_204827\"").replace("\"Ks\"", "\"ks\"")
        );
        let before = t.clone();
        let e = t.merge_toml(&two, "dup.toml").unwrap_err().to_string();
        assert!(
            e.starts_with(
                "dup.toml: standard[1] 'HD_204827' (filter 'ks'): the same star and filter as standard[0] 'HD 204827'"
            ),
            "{e}"
        );
        assert_eq!(t, before, "a refused file changes nothing");
        // Photometric fields: checked, named, and only for one filter.
        let with = |extra: &str| format!("{}{extra}\n", entry("p", "0.0088"));
        t.merge_toml(
            &with("mag = 7.25\nsigma_mag = 0.02\nmag_band = \"2MASS Ks\""),
            "mag.toml",
        )
        .unwrap();
        let e = t.find("HD 204827", "Ks").unwrap();
        assert_eq!(
            (e.mag, e.sigma_mag, e.mag_band.as_str()),
            (Some(7.25), Some(0.02), "2MASS Ks")
        );
        for (extra, want) in [
            ("mag = 7.25", "mag = 7.25: needs sigma_mag"),
            ("sigma_mag = 0.02", "sigma_mag = 0.02: without mag"),
            ("mag = nan\nsigma_mag = 0.02", "mag = NaN: must be a finite magnitude"),
            ("mag = 30.0\nsigma_mag = 0.02", "mag = 30: must be a finite magnitude"),
            ("mag = 7.0\nsigma_mag = 0.0", "sigma_mag = 0: must be in (0, 1]"),
            ("mag = 7.0\nsigma_mag = inf", "sigma_mag = inf: must be in (0, 1]"),
            ("mag_band = \"2MASS Ks\"", "mag_band or mag_reference without mag"),
        ] {
            let e = t.merge_toml(&with(extra), "bad.toml").unwrap_err().to_string();
            assert!(
                e.starts_with("bad.toml: standard[0] 'HD 204827' (filter 'Ks'): ") && e.contains(want),
                "{extra}: {e}"
            );
        }
        let star = with("mag = 7.0\nsigma_mag = 0.02").replace("\"Ks\"", "\"*\"");
        let e = t.merge_toml(&star, "bad.toml").unwrap_err().to_string();
        assert!(
            e.contains("mag = 7: a magnitude is for one band, and filter is \"*\""),
            "{e}"
        );
        assert!(
            StandardsTable::builtin().entries.iter().all(|e| e.mag.is_none()),
            "no built-in magnitude: none was verified"
        );
        // The same star in two filters is two entries.
        let two_filters = format!("{}{}", entry("p", "0.0088"), entry("filter", "\"H\""));
        t.merge_toml(&two_filters, "filters.toml").unwrap();
        assert!(t.find("HD 204827", "H").is_some());
    }
}
