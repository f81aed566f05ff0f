//! Joining the catalogs of the shards of one night.
use crate::catalog::provenance::{MergedFrom, OneOrMany};
use crate::catalog::{AppliedCalibration, Catalog, Provenance, Target, SCHEMA_VERSION};

/// Join shard catalogs: targets in the order `night` gives them (TPL START, then object),
/// failures by file, duplicates (the same
/// sequence in two shards) refused. The merged `calibration` is the catalogs' when they
/// all applied the same one (shards of one night: the caller checks that), else (whole
/// runs of several nights, each calibrated by its own standards) `{"source":
/// "per_catalog", "catalogs": [{"file", "calibration"}, ...]}`, every catalog's.
pub fn merge(parts: Vec<(String, Catalog)>) -> crate::error::Result<Catalog> {
    let mut out = Catalog {
        schema_version: SCHEMA_VERSION.into(),
        ..Default::default()
    };
    let mut provs = Vec::new();
    let mut cals: Vec<(String, Option<AppliedCalibration>)> = Vec::new();
    let mut seen = std::collections::BTreeMap::new();
    for (name, c) in parts {
        if !c.schema_version.is_empty() && c.schema_version.split('.').next() != SCHEMA_VERSION.split('.').next() {
            return Err(crate::error::Error::Merge {
                file: name,
                reason: format!(
                    "schema version {} is not compatible with {}",
                    c.schema_version, SCHEMA_VERSION
                ),
            });
        }
        for t in c.targets {
            let key = t.sequence_id().to_string();
            if let Some(prev) = seen.insert(key.clone(), name.clone()) {
                return Err(crate::error::Error::Merge {
                    reason: format!("sequence {key} appears in both {prev} and {name}"),
                    file: name,
                });
            }
            out.targets.push(t);
        }
        out.failures.extend(c.failures);
        // Every shard reduces all standards and calibrates with them: keep one copy.
        for s in c.standards {
            if !out.standards.iter().any(|o| o.sequence == s.sequence) {
                out.standards.push(s);
            }
        }
        cals.push((name.clone(), c.calibration));
        provs.push(MergedFrom {
            file: name.clone(),
            provenance: c.provenance,
        });
    }
    let same = |a: &Option<AppliedCalibration>, b: &Option<AppliedCalibration>| match (a, b) {
        (Some(a), Some(b)) => a.same_as(b),
        (a, b) => a.is_none() && b.is_none(),
    };
    out.calibration = if cals.iter().all(|(_, c)| same(c, &cals[0].1)) {
        cals.into_iter().next().and_then(|(_, c)| c)
    } else {
        Some(AppliedCalibration::per_catalog(cals))
    };
    // The order of `night`: sequences by (TPL START, object) (crate::sequence::group).
    out.targets.sort_by(|a, b| night_order(a).cmp(&night_order(b)));
    out.failures.sort_by(|a, b| a.file.cmp(&b.file));
    out.failures.dedup();
    out.provenance = merged_provenance(provs);
    Ok(out)
}

/// Where `night` puts a target: by (TPL START, object); the sequence id breaks ties (and
/// orders the targets of catalogs written without `tpl_start`).
fn night_order(t: &Target) -> (&str, &str, &str) {
    (t.tpl_start.as_deref().unwrap_or(""), &t.object, t.sequence_id())
}

/// The merged provenance: `software` and `commit` of the inputs (one string when they
/// agree, else the list of the distinct values) and every input's provenance
/// (`merged_from`).
fn merged_provenance(provs: Vec<MergedFrom>) -> Provenance {
    let from = Provenance {
        merged_from: Some(provs),
        ..Provenance::default()
    };
    Provenance {
        software: OneOrMany::from_values(from.softwares()),
        commit: OneOrMany::from_values(from.commits()),
        ..from
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(name: &str, seq: &str, cal: serde_json::Value) -> (String, Catalog) {
        let cal = serde_json::from_value(cal).unwrap();
        let mut t = crate::catalog::Target::new(seq.to_string(), crate::catalog::Status::Ok);
        t.sequence = Some(format!("{seq}@2000"));
        let c = Catalog {
            targets: vec![t],
            calibration: Some(cal),
            ..Default::default()
        };
        (name.into(), c)
    }

    /// The merged calibration is the common one, or every catalog's when they differ
    /// (never the first one alone).
    #[test]
    fn the_merged_calibration_is_the_common_one_or_every_catalogs() {
        let a = serde_json::json!({"source": "night", "calibration": {"filters": [{"c": 0.018}]}});
        let b = serde_json::json!({"source": "night", "calibration": {"filters": [{"c": 0.021}]}});
        let m = merge(vec![part("a.json", "X", a.clone()), part("b.json", "Y", a.clone())]).unwrap();
        assert_eq!(serde_json::json!(m.calibration), a);
        let m = merge(vec![part("a.json", "X", a.clone()), part("b.json", "Y", b.clone())]).unwrap();
        assert_eq!(
            serde_json::json!(m.calibration),
            serde_json::json!({"source": "per_catalog", "catalogs": [
                {"file": "a.json", "calibration": a},
                {"file": "b.json", "calibration": b},
            ]})
        );
    }
}
