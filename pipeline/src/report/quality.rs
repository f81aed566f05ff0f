//! The page's frame-quality section: the night's seeing, sky and transparency against time
//! (the figure of [`crate::plots::quality`]), the medians, and one row per science frame of
//! the targets and standards, the outliers of the night marked (as in the night log).
use std::fmt::Write as _;

use super::markup::{escape, fmt, image};
use super::Image;
use crate::catalog::frame_quality::{night_frames, NightMedians, OUTLIER_SIGMA};
use crate::catalog::Catalog;
use crate::night::log_ut;

/// The section (`id="quality"`); a catalog without per-frame quality says so.
pub fn quality(h: &mut String, cat: &Catalog, figure: Option<&Image>) {
    h.push_str("<section id=\"quality\"><h2>Frame quality</h2>\n");
    let rows = night_frames(cat);
    if rows.is_empty() {
        h.push_str("<p>The catalog has no per-frame quality (written before it was kept, or no target was measured).</p>\n</section>\n");
        return;
    }
    let m = NightMedians::of(rows.iter().map(|r| r.quality));
    let _ = writeln!(
        h,
        "<p>{} science frames. Night medians: airmass <strong>{}</strong>, seeing <strong>{}″</strong>, \
         sky <strong>{} ADU</strong>, transparency <strong>{}</strong>. Marked: seeing above {}″ or \
         transparency below {} (the median ∓ {OUTLIER_SIGMA} robust σ). Seeing: the FWHM of the PSF (beta free) \
         fitted to the star; transparency: the star's o+e flux over its median over the \
         sequence's frames.</p>",
        rows.len(),
        fmt(m.airmass, 3),
        fmt(m.fwhm_arcsec, 2),
        fmt(m.sky_adu, 1),
        fmt(m.transparency, 3),
        fmt(m.fwhm_limit_arcsec, 2),
        fmt(m.transparency_limit, 3)
    );
    if let Some(img) = figure {
        image(h, &img.caption, &img.png, img.href.as_deref());
    }
    h.push_str(
        "<div class=\"scroll\"><table id=\"frame-quality\"><thead><tr><th>frame</th><th>target</th>\
         <th class=\"num\">UT</th><th class=\"num\">POSANG</th><th class=\"num\">airmass</th>\
         <th class=\"num\">seeing [″]</th><th class=\"num\">sky [ADU]</th><th class=\"num\">transparency</th>\
         <th>outlier</th></tr></thead><tbody>\n",
    );
    for r in &rows {
        let q = r.quality;
        let out = m.outlier(q);
        let name = q.file.rsplit('/').next().unwrap_or(&q.file);
        let _ = writeln!(
            h,
            "<tr><td title=\"{}\"><code>{}</code></td><td class=\"obj\">{}{}</td><td class=\"num\">{}</td>\
             <td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>\
             <td class=\"num\">{}</td><td>{}</td></tr>",
            escape(&q.file),
            escape(name),
            escape(r.source),
            if r.standard { " (standard)" } else { "" },
            log_ut(q.mjd),
            fmt(Some(q.posang_deg), 1),
            fmt(q.airmass, 3),
            fmt(q.fwhm_arcsec, 2),
            fmt(q.sky_adu, 1),
            fmt(q.transparency, 3),
            if out.any() {
                format!("<span class=\"st-partial\">{}</span>", escape(&out.words()))
            } else {
                String::new()
            }
        );
    }
    h.push_str("</tbody></table></div>\n</section>\n");
}
