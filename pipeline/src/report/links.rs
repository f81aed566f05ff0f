//! Links from the page to files beside it: the per-target figures, opened at full size by a
//! plain `<a href>` around their embedded image. Browsers refuse to open a `data:` URI from a
//! link, so the link names the PNG file itself: relative to the page's folder (the page and
//! the night's products folder move together), or an absolute `file:` URL when the page has
//! no folder (written to standard output).
use std::path::{Component, Path, PathBuf};

/// The URL of `file` as seen from a page in `page_dir`: a relative URL when both are on the
/// same root, else (or without `page_dir`) an absolute `file://` URL; percent-escaped, so
/// that spaces, `#`, `?` and `%` in names survive.
pub fn href(file: &Path, page_dir: Option<&Path>) -> String {
    let file = real(file);
    match page_dir.map(real).and_then(|dir| relative(&file, &dir)) {
        Some(rel) => escape_path(&rel),
        None => format!("file://{}", escape_path(&file)),
    }
}

/// `p` absolute with its symbolic links resolved when it exists, else made absolute as written.
fn real(p: &Path) -> PathBuf {
    p.canonicalize()
        .or_else(|_| std::path::absolute(p))
        .unwrap_or_else(|_| p.to_path_buf())
}

/// The path of `file` relative to `dir` (both absolute): `..` for each of `dir`'s components
/// past their common start. `None` when they have different roots (Windows drives).
pub fn relative(file: &Path, dir: &Path) -> Option<PathBuf> {
    let (f, d): (Vec<Component>, Vec<Component>) = (file.components().collect(), dir.components().collect());
    if f.first() != d.first() {
        return None;
    }
    let common = f.iter().zip(&d).take_while(|(a, b)| a == b).count();
    let mut rel: PathBuf = d[common..].iter().map(|_| Component::ParentDir).collect();
    rel.extend(&f[common..]);
    Some(rel)
}

/// A path as a URL path: `/` between components (also on Windows), every byte outside
/// letters, digits and `-._~` percent-escaped.
pub fn escape_path(p: &Path) -> String {
    let mut out = String::new();
    for (i, c) in p.components().enumerate() {
        if i > 0 && !out.ends_with('/') {
            out.push('/');
        }
        match c {
            Component::RootDir => out.push('/'),
            Component::Prefix(x) => out.push_str(&escape_segment(&x.as_os_str().to_string_lossy())),
            Component::CurDir => out.push('.'),
            Component::ParentDir => out.push_str(".."),
            Component::Normal(s) => out.push_str(&escape_segment(&s.to_string_lossy())),
        }
    }
    out
}

fn escape_segment(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}
