//! # The night report: one self-contained HTML page of a catalog
//!
//! `sofipol report CATALOG -o night.html` (and `sofipol night --report FILE`) write it:
//! the night's summary (targets ok / partial / failed, the inputs not used and why), a
//! sortable, filterable table of targets and components, the per-target figures of the
//! night's products folder, the frame quality (seeing, sky, airmass and transparency of
//! every science frame, with a figure against time: `quality.rs`, [`quality_figure`]),
//! the calibration (flats, standards and their residuals, c,
//! theta0, the telescope's polarization), the Delta-gamma statistics of `sofipol stats`
//! (the same library calls, [`crate::stats::setup`]) with their figures, and the
//! provenance. Images are embedded as `data:` URIs and the page loads nothing: a
//! Content-Security-Policy forbids any network access. Every figure is also a link to its
//! PNG file, to open it at full size: a per-target figure to its file in the night's
//! products folder ([`links::href`], relative to the page's folder), the page's own figures
//! (frame quality, statistics) to the files [`write_figures`] writes into the folder beside
//! the page named after it ([`report_figures_dir`]: `night.html` -> `night_figures/`).
//!
//! The page reads at a desktop width (every table's columns visible) and on a phone (the
//! page never scrolls sideways: the targets table becomes one card per row, the other tables
//! scroll in their own boxes, the figures take the column's width); `page.css` holds the
//! layout.
//!
//! [`collect`] gathers what the page shows (reads the figures, runs the statistics);
//! [`html::render`] turns it into the page (pure: the unit tests call it); [`write()`] writes
//! it atomically. Every text from the catalog is HTML-escaped ([`markup::escape`]).
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::catalog::Catalog;
use crate::error::{Error, Result};
use crate::stats::alignment::AlignmentReport;
use crate::stats::figures::{ism_figure, observed_figure};
use crate::stats::sample::BinarySample;
use crate::stats::setup;

mod half_wave_plate;
pub mod html;
pub mod links;
pub mod markup;
mod quality;
mod sections;

/// Bins of the observed Delta-gamma histogram (as `sofipol stats`' default).
pub const OBSERVED_BINS: usize = 9;
/// Monte-Carlo pairs per ISM level of the report's statistics by default: `sofipol stats`'
/// own, so that with the same seed the page's statistics are the numbers `stats` prints
/// (about 0.4 s more for a 50-binary night than the 2e5 pairs used before, whose KS p-values
/// differed from `stats`' in the third digit).
pub const DEFAULT_REPORT_PAIRS: u64 = crate::stats::setup::DEFAULT_PAIRS;

/// A figure of the page's own (frame quality, statistics): embedded in the page, and
/// written as a PNG file into the page's figures folder ([`report_figures_dir`]), to which
/// it links.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// What it shows (the `alt` text and the caption).
    pub caption: String,
    /// The PNG file's bytes.
    pub png: Vec<u8>,
    /// Its file's name in the page's figures folder (one of [`REPORT_FIGURES`]).
    pub file: &'static str,
    /// The link to that file, relative to the page's folder (`None`: the page has no
    /// folder, as on standard output, and the figure is not written).
    pub href: Option<String>,
}

/// The names of the files the page writes into its figures folder ([`report_figures_dir`]):
/// the frame quality and the two statistics figures (as `sofipol stats` names them).
pub const REPORT_FIGURES: [&str; 3] = ["quality.png", "observed.png", "ism_levels.png"];

/// The statistics section: the sample, the tests and verdict, and their figures.
#[derive(Debug, Clone)]
pub struct StatsSection {
    /// The binaries both of whose components pass the cut.
    pub sample: BinarySample,
    /// What `sofipol stats` reports.
    pub report: AlignmentReport,
    /// The Monte Carlo in words (the ISM figure's subtitle).
    pub mc: String,
    /// The observed histograms and the Delta-gamma histogram against the predictions.
    pub figures: Vec<Image>,
}

/// A per-target figure: embedded in the page, and linked to its file.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetFigure {
    /// The link to the PNG file, relative to the page's folder ([`links::href`]).
    pub href: String,
    /// The PNG file's bytes.
    pub png: Vec<u8>,
}

/// Everything the page shows.
#[derive(Debug)]
pub struct ReportInput {
    /// The catalog.
    pub catalog: Catalog,
    /// Where it was read from (as given).
    pub catalog_path: String,
    /// The folder the per-target figures were looked for in (`None`: not looked for).
    pub figures_dir: Option<String>,
    /// Per-target figures by sequence id (those found).
    pub target_figures: BTreeMap<String, TargetFigure>,
    /// The statistics, or why they could not be computed.
    pub stats: Result<StatsSection>,
    /// The night's seeing, sky and transparency against time (None: no frame has quality
    /// and a time, or the figure could not be drawn).
    pub quality_figure: Option<Image>,
    /// The command line that wrote the page.
    pub command_line: String,
}

/// Gather the page's content: the figures `<slug(sequence id)>.png` (else
/// `<slug(object)>.png`) found in `figures_dir` (the night's products folder,
/// `night::products_dir(catalog)`, by default; `None`: the night was reduced without
/// figures), each linked from the folder of `page`, the file the page is written to
/// (`None`: the page has no folder, as on standard output: absolute `file:` URLs), the
/// frame-quality figure and the statistics of the sample run with `opts` (in the current
/// rayon pool) with their figures, linked to their files in the page's figures folder
/// ([`report_figures_dir`], written by [`write_figures`]). A figure that cannot be read is
/// left out; statistics that cannot be computed are replaced by the reason.
pub fn collect(
    catalog: Catalog,
    catalog_path: &Path,
    figures_dir: Option<&Path>,
    page: Option<&Path>,
    opts: &setup::Options,
    command_line: String,
) -> ReportInput {
    let page_dir = page.map(|p| match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    });
    let mut target_figures = BTreeMap::new();
    for (t, dir) in catalog.targets.iter().filter_map(|t| Some((t, figures_dir?))) {
        let id = t.sequence_id();
        // `night` names a figure by the sequence id, `demo` and `target` by the object.
        let found = [id, t.object.as_str()].iter().find_map(|name| {
            let file = dir.join(format!("{}.png", crate::products::slug(name)));
            Some((read_png_figure(&file)?, file))
        });
        if let Some((png, file)) = found {
            let href = links::href(&file, page_dir);
            target_figures.insert(id.to_string(), TargetFigure { href, png });
        }
    }
    let mut stats = statistics(&catalog, &catalog_path.display().to_string(), opts);
    let mut quality_figure = quality_figure(&catalog);
    if let Some(page) = page {
        let link = |img: &mut Image| img.href = Some(own_figure_href(page, img.file));
        quality_figure.iter_mut().for_each(link);
        if let Ok(s) = &mut stats {
            s.figures.iter_mut().for_each(link);
        }
    }
    ReportInput {
        catalog,
        catalog_path: catalog_path.display().to_string(),
        figures_dir: figures_dir.map(|d| d.display().to_string()),
        target_figures,
        stats,
        quality_figure,
        command_line,
    }
}

/// The frame-quality figure of `catalog` ([`crate::plots::quality`]), `None` when no frame
/// has quality and an MJD or it could not be drawn.
pub fn quality_figure(catalog: &Catalog) -> Option<Image> {
    let rows = crate::catalog::frame_quality::night_frames(catalog);
    let png = crate::plots::quality::quality_png(&rows).ok()??;
    Some(Image {
        caption: "Seeing, sky level and transparency of every science frame over the night, coloured by target                   (standards grey); dashed: the night's median, thin dashed: the outlier limits"
            .into(),
        png,
        file: REPORT_FIGURES[0],
        href: None,
    })
}

/// The folder beside the page at `page` that holds the page's own figures (the frame
/// quality, the statistics): `<stem>_figures/` (`night.html` -> `night_figures/`).
pub fn report_figures_dir(page: &Path) -> PathBuf {
    let stem = page
        .file_stem()
        .map_or_else(|| "report".into(), |s| s.to_string_lossy().into_owned());
    page.with_file_name(format!("{stem}_figures"))
}

/// Where the page at `page` writes its frame-quality figure:
/// `<stem>_figures/quality.png` ([`report_figures_dir`]).
pub fn quality_figure_path(page: &Path) -> PathBuf {
    report_figures_dir(page).join(REPORT_FIGURES[0])
}

/// The link from the page at `page` to its own figure `file`: relative, into the folder
/// beside it (both move together), percent-escaped.
fn own_figure_href(page: &Path, file: &str) -> String {
    let dir = report_figures_dir(page);
    let name = dir
        .file_name()
        .map_or_else(|| "report_figures".into(), |n| n.to_os_string());
    links::escape_path(&Path::new(&name).join(file))
}

/// Write the page's own figures (those of `input` that have a link, [`Image::href`]) into
/// its figures folder ([`report_figures_dir`] of `page`), each atomically, before the page
/// that links to them; a figure of [`REPORT_FIGURES`] that this page does not show (left by
/// an earlier page of the same name) is removed, so that the folder holds what the page
/// shows. The files written; the error names the file.
pub fn write_figures(page: &Path, input: &ReportInput) -> Result<Vec<PathBuf>> {
    let images: Vec<&Image> = input
        .quality_figure
        .iter()
        .chain(input.stats.iter().flat_map(|s| &s.figures))
        .filter(|i| i.href.is_some())
        .collect();
    let dir = report_figures_dir(page);
    let io = |path: &Path, e: std::io::Error| Error::Io {
        path: path.to_path_buf(),
        source: e,
    };
    if images.is_empty() && !dir.is_dir() {
        return Ok(Vec::new());
    }
    std::fs::create_dir_all(&dir).map_err(|e| io(&dir, e))?;
    let mut written = Vec::new();
    for img in &images {
        let path = dir.join(img.file);
        crate::io::write_atomic(&path, &img.png).map_err(|e| Error::calib("writing a figure of the HTML report", e))?;
        written.push(path);
    }
    for name in REPORT_FIGURES {
        let path = dir.join(name);
        if !written.contains(&path) && path.is_file() {
            std::fs::remove_file(&path).map_err(|e| io(&path, e))?;
        }
    }
    Ok(written)
}

/// The largest figure file the page takes, bytes: a target's figure is a few hundred kB.
pub const MAX_FIGURE_BYTES: u64 = 32 << 20;

/// The PNG at `path` when it is a regular file of at most [`MAX_FIGURE_BYTES`] that starts
/// like a PNG; `None` otherwise. The type and size are checked before the file is opened,
/// so a named pipe (which would block the open for ever) or a huge file is never read.
pub fn read_png_figure(path: &Path) -> Option<Vec<u8>> {
    use std::io::Read;
    let meta = std::fs::metadata(path).ok()?;
    if !meta.is_file() || meta.len() > MAX_FIGURE_BYTES {
        return None;
    }
    let mut png = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path)
        .ok()?
        .take(MAX_FIGURE_BYTES + 1)
        .read_to_end(&mut png)
        .ok()?;
    (png.len() as u64 <= MAX_FIGURE_BYTES && png.starts_with(b"\x89PNG\r\n\x1a\n")).then_some(png)
}

/// The statistics of `sofipol stats` with `opts`, and the observed and ISM figures (drawn
/// by the same functions into a temporary folder and read back; not yet linked: [`collect`]
/// links them, [`write_figures`] writes them beside the page).
pub fn statistics(catalog: &Catalog, source: &str, opts: &setup::Options) -> Result<StatsSection> {
    let sample = BinarySample::from_catalog(catalog, None);
    let params = setup::params(&sample, opts, source)?;
    let report = setup::analyse_sample(&sample, &params)?;
    let mc = setup::mc_subtitle(&params);
    let tmp = tempfile::tempdir().map_err(|e| Error::Io {
        path: std::env::temp_dir(),
        source: e,
    })?;
    let read = |p: PathBuf| {
        std::fs::read(&p).map_err(|e| Error::Io {
            path: p.clone(),
            source: e,
        })
    };
    let mut figures = Vec::new();
    if !sample.is_empty() {
        let p = tmp.path().join(REPORT_FIGURES[1]);
        observed_figure(&p, &sample, OBSERVED_BINS, &setup::observed_notes(&report))?;
        figures.push(Image {
            caption: "Observed: P of the sample's components, Δγ of its binaries (with the tests), Δγ per binary with its ±σ and its 68 % interval".into(),
            png: read(p)?,
            file: REPORT_FIGURES[1],
            href: None,
        });
    }
    if !report.ism.is_empty() {
        let p = tmp.path().join(REPORT_FIGURES[2]);
        ism_figure(&p, &report.ism, &sample.delta_gamma_deg(), OBSERVED_BINS, &mc)?;
        figures.push(Image {
            caption: "Observed Δγ histogram against the predictions of random disks with interstellar polarization"
                .into(),
            png: read(p)?,
            file: REPORT_FIGURES[2],
            href: None,
        });
    }
    Ok(StatsSection {
        sample,
        report,
        mc,
        figures,
    })
}

/// Write the page atomically (temporary file in the same folder, renamed); the error names
/// the file.
pub fn write(path: &Path, page: &str) -> Result<()> {
    crate::io::write_atomic(path, page.as_bytes()).map_err(|e| Error::calib("writing the HTML report", e))
}

/// Standard base64 (RFC 4648, with padding) of `bytes`, for `data:` URIs.
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                s.push(A[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_layout;
