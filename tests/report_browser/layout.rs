//! The page's layout at a desktop width (1400 px) and on a phone (390 px), measured in the
//! real browser by the test's own probe (`probe.js`, inserted into a copy of the page beside
//! it, so that the figures' relative links still resolve): the page never scrolls sideways,
//! no cell is cut off, at the desktop width every table shows all its columns without
//! scrolling (on the phone the targets table does, a card per row; the others may scroll in
//! their boxes), the standards' sequence ids are laid out on at most two lines broken only
//! at '@', and every figure on the page is a link to its own PNG file (the per-target ones
//! into the night's products folder, as wide as the column on the phone; the frame quality
//! and the statistics into the folder beside the page named after it).
//!
//! Headless Chromium's window is at least 500 px wide: narrower widths are an `<iframe>` of
//! that width in a page of the test, to which the probe posts its measurements.
use std::path::{Path, PathBuf};

use serde_json::Value;

const PROBE: &str = include_str!("probe.js");

/// Below this width the page is laid out for a phone (the CSS's `max-width: 640px`).
const PHONE_PX: u64 = 640;

/// The probe's measurements of `page` in a window (or frame) `width` px wide.
pub fn measure(chromium: &Path, work: &Path, page: &Path, width: u64) -> Value {
    let html = std::fs::read_to_string(page).unwrap();
    let at = html.rfind("</body>").expect("no </body> in the page");
    let probed = page.with_file_name("report-probe.html");
    std::fs::write(
        &probed,
        format!("{}<script>\n{PROBE}</script>\n{}", &html[..at], &html[at..]),
    )
    .unwrap();
    let (url, window) = if width >= 500 {
        (format!("file://{}", probed.display()), width)
    } else {
        let frame = page.with_file_name(format!("frame-{width}.html"));
        std::fs::write(
            &frame,
            format!(
                "<!DOCTYPE html><html><body style=\"margin:0\">\
                 <iframe src=\"report-probe.html\" style=\"border:0;width:{width}px;height:900px\"></iframe>\
                 <pre id=\"layout-probe\"></pre><script>window.addEventListener(\"message\", \
                 function (e) {{ document.getElementById(\"layout-probe\").textContent = e.data; }});\
                 </script></body></html>"
            ),
        )
        .unwrap();
        (format!("file://{}", frame.display()), 500)
    };
    let dom = super::headless(
        chromium,
        work,
        &[
            "--virtual-time-budget=5000".into(),
            format!("--window-size={window},900"),
            "--dump-dom".into(),
        ],
        &url,
    );
    let start = dom
        .rfind("<pre id=\"layout-probe\"")
        .unwrap_or_else(|| panic!("no layout probe in the DOM at {width} px"));
    let body = &dom[start + dom[start..].find('>').unwrap() + 1..];
    let text = body[..body.find("</pre>").unwrap()]
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&nbsp;", "\u{a0}")
        .replace("&amp;", "&");
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("probe output at {width} px {text:?}: {e}"))
}

/// The file a `file://` URL names (percent-escapes decoded).
fn file_of(url: &str) -> PathBuf {
    let path = url
        .strip_prefix("file://")
        .unwrap_or_else(|| panic!("not a file URL: {url}"));
    let bytes = path.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            out.push(u8::from_str_radix(&path[i + 1..i + 3], 16).unwrap());
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    PathBuf::from(String::from_utf8(out).unwrap())
}

/// What is wrong with the layout at `width` px (nothing: empty); `figures` is the folder of
/// the per-target PNGs, `own_figures` the folder of the page's own (frame quality,
/// statistics).
pub fn problems(m: &Value, width: u64, figures: &Path, own_figures: &Path) -> Vec<String> {
    let mut bad = Vec::new();
    if let Some(e) = m.get("error") {
        return vec![format!("at {width} px: {e}")];
    }
    let n = |k: &str| m[k].as_u64().unwrap_or_else(|| panic!("{k}: {m}"));
    assert_eq!(n("inner_width"), width, "the viewport");
    if n("page_width") > width {
        bad.push(format!(
            "at {width} px the page scrolls sideways: {} px wide",
            n("page_width")
        ));
    }
    for c in m["clipped"].as_array().unwrap() {
        bad.push(format!("at {width} px a cell is cut off: {}", c.as_str().unwrap()));
    }
    // At the desktop width every table shows all its columns; on the phone the other tables
    // may scroll in their boxes, but the targets table is laid out to be read without.
    for b in m["boxes"].as_array().unwrap() {
        if width > PHONE_PX || b["table"] == "targets" {
            if let (Some(bx), Some(c)) = (b["box"].as_u64(), b["content"].as_u64()) {
                if c > bx {
                    bad.push(format!(
                        "at {width} px table #{} needs sideways scrolling to be read: {c} px in a box of {bx} px",
                        b["table"].as_str().unwrap()
                    ));
                }
            }
        }
    }

    let seqs = m["sequences"].as_array().unwrap();
    assert!(!seqs.is_empty(), "no standards' sequence ids: {m}");
    for s in seqs {
        let text = s["text"].as_str().unwrap().trim();
        let lines: Vec<&str> = s["lines"]
            .as_array()
            .unwrap()
            .iter()
            .map(|l| l.as_str().unwrap())
            .collect();
        if lines.len() > 2 || (lines.len() == 2 && !lines[0].ends_with('@')) {
            bad.push(format!(
                "at {width} px the sequence id {text:?} is laid out on {lines:?} (at most two lines, broken at '@')"
            ));
        }
    }

    let on_disk: Vec<PathBuf> = std::fs::read_dir(figures)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "png"))
        .map(|p| p.canonicalize().unwrap())
        .collect();
    let all = m["figures"].as_array().unwrap();
    let per_target: Vec<&Value> = all.iter().filter(|f| f["section"] == "figures").collect();
    assert_eq!(per_target.len(), on_disk.len(), "a figure per PNG: {per_target:?}");
    assert!(
        all.len() > per_target.len(),
        "the page's own figures (frame quality, statistics): {all:?}"
    );
    // Every figure on the page, in any section, is a link to its own PNG file: the per-target
    // ones to the night's products folder, the page's own (frame quality, statistics) to the
    // folder beside the page named after it; the file is the figure shown (its width is the
    // image's natural width).
    // (Not there: every link into it is reported below as missing.)
    let own = own_figures.canonicalize().unwrap_or_else(|_| own_figures.to_path_buf());
    let (mut linked, mut linked_own) = (Vec::new(), Vec::new());
    for f in all {
        let Some(href) = f["href"].as_str() else {
            bad.push(format!(
                "at {width} px a figure of section #{} is not a link: {}",
                f["section"].as_str().unwrap_or(""),
                f["alt"]
            ));
            continue;
        };
        let file = file_of(href);
        match std::fs::read(&file) {
            Ok(png) if png.starts_with(b"\x89PNG\r\n\x1a\n") && png.len() > 24 => {
                let w = u32::from_be_bytes(png[16..20].try_into().unwrap());
                if Some(u64::from(w)) != f["natural_width"].as_u64() {
                    bad.push(format!(
                        "{href} is {w} px wide, the figure it is the link of {} px: {}",
                        f["natural_width"], f["alt"]
                    ));
                }
                let file = file.canonicalize().unwrap();
                if f["section"] == "figures" {
                    linked.push(file);
                } else if file.parent() == Some(own.as_path()) {
                    linked_own.push(file);
                } else {
                    bad.push(format!("{href} is not in {}: {}", own.display(), f["alt"]));
                }
            }
            Ok(_) => bad.push(format!("{href} is not a PNG")),
            Err(e) => bad.push(format!("{href} ({}): {e}", file.display())),
        }
        if f["section"] != "figures" {
            continue;
        }
        let (w, col) = (f["width"].as_u64().unwrap(), f["column"].as_u64().unwrap());
        if width <= PHONE_PX && w + 2 < col {
            bad.push(format!(
                "at {width} px a figure is {w} px wide in a column of {col} px: {}",
                f["alt"]
            ));
        }
    }
    if bad.is_empty() {
        linked.sort();
        let mut on_disk = on_disk;
        on_disk.sort();
        assert_eq!(linked, on_disk, "each figure links to its own PNG file");
        let n = linked_own.len();
        linked_own.sort();
        linked_own.dedup();
        assert_eq!(linked_own.len(), n, "two figures link to one file");
    }
    bad
}
