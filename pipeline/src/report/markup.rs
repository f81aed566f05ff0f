//! HTML fragments shared by the page (`html.rs`) and its sections (`sections.rs`):
//! escaping, numbers, the status in words, flag lists, sequence ids and embedded images.
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
                    breakable_at(&f.label(), '_'),
                    escape(&words)
                );
            }
            None => {
                let _ = write!(h, "<li><code>{}</code></li>", breakable_at(&f.to_string(), '_'));
            }
        }
    }
    h.push_str("</ul>");
}

/// `s` escaped, with a line-break opportunity (`<wbr>`) after each `at`: a flag such as
/// `telescope_polarization_from_prior` breaks between its words, not inside one.
pub fn breakable_at(s: &str, at: char) -> String {
    let sep = escape(&at.to_string());
    s.split(at).map(escape).collect::<Vec<_>>().join(&format!("{sep}<wbr>"))
}

/// A sequence id (`object@start`) that breaks, when it must, only after its last '@': two
/// unbreakable halves (class `seq`, the CSS's `white-space: nowrap`) with a `<wbr>` between.
/// An id without '@' is one unbreakable piece.
pub fn sequence_id(s: &str) -> String {
    match s.rfind('@') {
        Some(i) => format!(
            "<span>{}</span><wbr><span>{}</span>",
            escape(&s[..=i]),
            escape(&s[i + 1..])
        ),
        None => format!("<span>{}</span>", escape(s)),
    }
}

/// An `<img>` of PNG bytes as a `data:` URI, with its caption; inside a link to `href` (the
/// image's file, opened at full size) when there is one.
pub fn image(h: &mut String, caption: &str, png: &[u8], href: Option<&str>) {
    let img = format!(
        "<img alt=\"{}\" src=\"data:image/png;base64,{}\">",
        escape(caption),
        base64(png)
    );
    let shown = match href {
        Some(href) => format!(
            "<a href=\"{}\" title=\"open the figure at full size\">{img}</a>",
            escape(href)
        ),
        None => img,
    };
    let _ = writeln!(
        h,
        "<figure>{shown}<figcaption>{}</figcaption></figure>",
        escape(caption)
    );
}
