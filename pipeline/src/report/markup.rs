//! HTML fragments shared by the page (`html.rs`) and its sections (`sections.rs`):
//! escaping, numbers, the status in words, flag lists and embedded images.
use std::fmt::Write as _;

use super::base64;
use crate::catalog::{Flag, Status};

/// `s` with `&`, `<`, `>`, `"` and `'` replaced by their character references: safe in
/// element content and in quoted attribute values.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A number with `decimals` decimals, "–" when absent or not finite.
pub fn fmt(x: Option<f64>, decimals: usize) -> String {
    match x {
        Some(v) if v.is_finite() => format!("{v:.decimals$}"),
        _ => "–".to_string(),
    }
}

/// A fraction as percent (P = 0.0123 -> "1.23").
pub fn pct(x: Option<f64>) -> String {
    fmt(x.map(|v| 100.0 * v), 2)
}

/// The status in words, as the table and the counts show it.
pub fn status_word(s: Status) -> &'static str {
    match s {
        Status::Ok => "ok",
        Status::Partial => "partial",
        Status::Failed => "failed",
    }
}

/// The flags as a list: each in words ([`Flag::explain`]), with the flag itself as the
/// tooltip; an unknown flag as it is.
pub fn flag_list(h: &mut String, all: &[&Flag]) {
    if all.is_empty() {
        return;
    }
    h.push_str("<ul class=\"flags\">");
    for f in all {
        match f.explain() {
            Some(words) => {
                let _ = write!(
                    h,
                    "<li title=\"{}\"><code>{}</code>: {}</li>",
                    escape(&f.to_string()),
                    escape(&f.label()),
                    escape(&words)
                );
            }
            None => {
                let _ = write!(h, "<li><code>{}</code></li>", escape(&f.to_string()));
            }
        }
    }
    h.push_str("</ul>");
}

/// An `<img>` of PNG bytes as a `data:` URI, with its caption.
pub fn image(h: &mut String, caption: &str, png: &[u8]) {
    let _ = writeln!(
        h,
        "<figure><img alt=\"{c}\" src=\"data:image/png;base64,{}\"><figcaption>{c}</figcaption></figure>",
        base64(png),
        c = escape(caption)
    );
}
