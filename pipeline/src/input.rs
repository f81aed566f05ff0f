//! Catalogs given as inputs (`merge`, `export`, `stats`, `mc --p-int catalog:FILE`): a
//! regular file of at most [`MAX_CATALOG_BYTES`], JSON of a sofipol catalog, of a schema
//! version this build reads (the same major version). Every error names the file.
use std::path::Path;

use crate::catalog::{Catalog, SCHEMA_VERSION};
use crate::error::{Error, Result};
pub use sofipol_calib::input::{MAX_CATALOG_BYTES, MAX_OPTION_FILE_BYTES};

/// Whether a catalog of schema `version` can be read by this build: the same major version
/// (an empty version is none: [`read_catalog`] refuses it by name).
pub fn schema_readable(version: &str) -> bool {
    !version.is_empty() && version.split('.').next() == SCHEMA_VERSION.split('.').next()
}

/// Read a catalog (see the module documentation).
pub fn read_catalog(path: &Path) -> Result<Catalog> {
    let text = sofipol_calib::input::read_to_string(path, MAX_CATALOG_BYTES).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |reason: String| Error::CatalogFile {
        path: path.to_path_buf(),
        reason,
    };
    let cat: Catalog = serde_json::from_str(&text).map_err(|e| bad(format!("not a sofipol catalog: {e}")))?;
    if cat.schema_version.trim().is_empty() {
        return Err(bad(format!(
            "no schema_version: every catalog sofipol writes has one (this sofipol reads schema {SCHEMA_VERSION}); \
             this JSON was not written by sofipol, or was cut"
        )));
    }
    if !schema_readable(&cat.schema_version) {
        return Err(bad(format!(
            "schema_version = '{}': this sofipol ({}) reads catalogs of schema {SCHEMA_VERSION} (major version {})",
            cat.schema_version,
            env!("CARGO_PKG_VERSION"),
            SCHEMA_VERSION.split('.').next().unwrap_or(SCHEMA_VERSION)
        )));
    }
    for t in &cat.targets {
        if let Some(stars) = &t.field_stars {
            crate::catalog::field_stars::validate(stars)
                .map_err(|e| bad(format!("target {:?}: field_stars: {e}", t.sequence_id())))?;
        }
    }
    Ok(cat)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn catalogs_of_another_major_schema_version_or_not_catalogs_are_refused_by_name() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("c.json");
        let cat = |v: &str| format!(r#"{{"schema_version": "{v}", "targets": []}}"#);
        for ok in [SCHEMA_VERSION, "1.7"] {
            std::fs::write(&f, cat(ok)).unwrap();
            assert!(read_catalog(&f).is_ok(), "{ok}");
        }
        // Empty or missing: not a catalog sofipol wrote.
        for text in [cat(""), r#"{"targets": []}"#.to_string()] {
            std::fs::write(&f, text).unwrap();
            let e = read_catalog(&f).unwrap_err().to_string();
            assert!(e.contains("c.json") && e.contains("no schema_version"), "{e}");
        }
        std::fs::write(&f, cat("9.0")).unwrap();
        let e = read_catalog(&f).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("schema_version = '9.0'"), "{e}");
        std::fs::write(&f, "{\"rows\": 3}").unwrap();
        let e = read_catalog(&f).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("not a sofipol catalog"), "{e}");
        let e = read_catalog(d.path()).unwrap_err().to_string();
        assert!(e.contains("a directory, not a regular file"), "{e}");
    }
}
