//! Joining the catalogs of the shards of one night.
use crate::catalog::{Catalog, SCHEMA_VERSION};

/// Join shard catalogs: targets ordered by sequence, failures by file, duplicates (the same
/// sequence in two shards) refused.
pub fn merge(parts: Vec<(String, Catalog)>) -> crate::error::Result<Catalog> {
    let mut out = Catalog {
        schema_version: SCHEMA_VERSION.into(),
        ..Default::default()
    };
    let mut provs = Vec::new();
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
        if out.calibration.is_none() {
            out.calibration = c.calibration;
        }
        provs.push(serde_json::json!({"file": name, "provenance": c.provenance}));
    }
    out.targets.sort_by(|a, b| a.sequence_id().cmp(b.sequence_id()));
    out.failures.sort_by(|a, b| a.file.cmp(&b.file));
    out.failures.dedup();
    out.provenance = serde_json::json!({"merged_from": provs});
    Ok(out)
}
