//! Where a night's products go, named for the catalog they belong to.
use std::path::{Path, PathBuf};

/// A file-system-safe name for an object.
pub fn slug(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' { c } else { '_' })
        .collect()
}

/// Where per-target products go for a catalog path: `<dir>/<stem>_products/`.
pub fn products_dir(catalog: &Path) -> PathBuf {
    let stem = catalog.file_stem().and_then(|s| s.to_str()).unwrap_or("catalog");
    catalog
        .parent()
        .unwrap_or(Path::new("."))
        .join(format!("{stem}_products"))
}
