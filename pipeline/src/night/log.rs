//! The night log: a plain-text file beside the catalog saying, frame by frame, what each
//! input was used for and what happened to it (used, dropped and why, not used and why),
//! then every science frame's observing conditions (airmass, seeing, sky, transparency:
//! `log/quality.rs`), then each target's outcome with its flags in words. Everything in it
//! comes from the catalog, so the log of any catalog can be written again (`sofipol report
//! --log`).
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use crate::catalog::{Catalog, Flag, Status};

/// What one input file was used for and what happened to it.
#[derive(Default)]
struct FrameEntry {
    /// "target HK Tau", "standard HD 64299 (offset)", "superflat Ks", "bad-pixel mask".
    roles: Vec<String>,
    /// Why the frame was dropped or not used (the catalog's failures naming it).
    problems: Vec<String>,
    /// The components whose combined F left this frame's dither out, with why.
    left_out: Vec<String>,
}

/// Where a night log goes for a catalog path: the catalog's name with `.log` in place of
/// its extension (`night.json` -> `night.log`; a catalog named `*.log` gets `*.log.log`).
pub fn log_path(catalog: &Path) -> std::path::PathBuf {
    let p = catalog.with_extension("log");
    if p == catalog {
        catalog.with_extension("log.log")
    } else {
        p
    }
}

/// Where the set-of-frames file of a catalog goes: the catalog's name with `.frames` in
/// place of its extension (`night.json` -> `night.frames`).
pub fn frame_list_path(catalog: &Path) -> std::path::PathBuf {
    let p = catalog.with_extension(crate::frame_list::EXTENSION);
    if p == catalog {
        catalog.with_extension("frames.frames")
    } else {
        p
    }
}

/// Write the night log of `cat` beside the catalog at `catalog` (atomically: a temporary
/// file renamed), and the set-of-frames file of the frames it used ([`night_frame_list`],
/// at [`frame_list_path`]; not when that is one of the run's inputs), returning the log's
/// path.
pub fn write_night_log(catalog: &Path, cat: &Catalog) -> sofipol_calib::Result<std::path::PathBuf> {
    let path = log_path(catalog);
    let name = catalog
        .file_name()
        .map_or_else(|| catalog.display().to_string(), |n| n.to_string_lossy().into());
    let frames = frame_list_path(catalog);
    // Never over an input (`night night.frames -o night.json`: the list given, with its
    // comments and its dark and sky lines, stays as it is).
    let same = |a: &Path, b: &Path| match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    };
    let is_input = cat
        .provenance
        .inputs
        .iter()
        .flatten()
        .any(|i| same(Path::new(i), &frames));
    if !is_input {
        let dir = frames.parent().unwrap_or(Path::new(""));
        crate::io::write_atomic(&frames, night_frame_list(cat, &name, dir).as_bytes())?;
    }
    crate::io::write_atomic(&path, night_log(cat, &name).as_bytes())?;
    Ok(path)
}

/// The set-of-frames file ([`crate::frame_list`]) of the frames the catalog's run used: the
/// frames of its targets (`science`), of its standards (`standard`) and its dome flats
/// (`flat`), so that `sofipol night FILE` repeats the run on the same frames. Paths are
/// relative when the catalog's paths are relative and the file goes to the working
/// directory (`dir` empty or `.`), absolute otherwise (relative paths made absolute with
/// the working directory).
pub fn night_frame_list(cat: &Catalog, catalog_name: &str, dir: &Path) -> String {
    use crate::frame_list::FrameRole;
    let here = dir.as_os_str().is_empty() || dir == Path::new(".");
    let shown = |f: &str| {
        let p = Path::new(f);
        if p.is_absolute() || here {
            p.to_path_buf()
        } else {
            std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
        }
    };
    let mut frames: Vec<(std::path::PathBuf, FrameRole)> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    // The targets' frames, with the target's name where a half-wave-plate run may have
    // taken it from a set-of-frames file (`target=`) rather than the header.
    let mut named: Vec<(std::path::PathBuf, FrameRole, Option<String>)> = Vec::new();
    let mut add_named = |f: &str, role: FrameRole, target: Option<&str>, named: &mut Vec<_>| {
        if seen.insert(f.to_string()) {
            named.push((shown(f), role, target.map(str::to_string)));
        }
    };
    for t in &cat.targets {
        let target = t.half_wave_plate.as_ref().map(|_| t.object.as_str());
        for f in t.input_files.iter().flatten() {
            add_named(f, FrameRole::Science, target, &mut named);
        }
    }
    for hw in cat.targets.iter().filter_map(|t| t.half_wave_plate.as_ref()) {
        for f in &hw.darks {
            add_named(f, FrameRole::Dark, None, &mut named);
        }
        for f in &hw.skies {
            add_named(f, FrameRole::Sky, None, &mut named);
        }
    }
    let mut add = |f: &str, role: FrameRole, frames: &mut Vec<_>| {
        if seen.insert(f.to_string()) {
            frames.push((shown(f), role));
        }
    };
    for st in &cat.standards {
        for f in st.input_files.iter().flatten() {
            add(f, FrameRole::Standard, &mut frames);
        }
    }
    for fl in cat.provenance.flat_list() {
        if fl.kind == "dome" {
            for f in &fl.frames {
                add(f, FrameRole::Flat, &mut frames);
            }
        }
    }
    let mut header = vec![
        format!("sofipol set of frames of {catalog_name}: the frames its run used, with their roles"),
        "`sofipol night THIS_FILE -o CATALOG`: the same run on the same frames (docs/cli.md)".to_string(),
    ];
    if !named.is_empty() && cat.targets.iter().any(|t| t.half_wave_plate.is_some()) {
        for f in &cat.failures {
            header.push(format!(
                "not listed, not used by the run: {}: {}",
                f.file,
                one_line(&f.error)
            ));
        }
    }
    named.extend(frames.into_iter().map(|(p, r)| (p, r, None)));
    let listed: Vec<_> = named.iter().map(|(p, r, t)| (p.clone(), *r, t.as_deref())).collect();
    crate::frame_list::write_with_targets(&header, &listed)
}

/// The night log of `cat` (see the module's documentation), `catalog_name` naming the
/// catalog it belongs to.
pub fn night_log(cat: &Catalog, catalog_name: &str) -> String {
    let frames = frame_entries(cat);
    let root = common_dir(frames.keys().map(String::as_str));
    let shown = |f: &str| one_line(f.strip_prefix(root.as_str()).unwrap_or(f).trim_start_matches('/'));
    let mut s = String::new();
    header(&mut s, cat, catalog_name, &root);
    let n_used = frames
        .values()
        .filter(|e| !e.roles.is_empty() && e.problems.is_empty() && e.left_out.is_empty())
        .count();
    let n_partly = frames
        .values()
        .filter(|e| !e.roles.is_empty() && e.problems.is_empty() && !e.left_out.is_empty())
        .count();
    let n_dropped = frames
        .values()
        .filter(|e| !e.roles.is_empty() && !e.problems.is_empty())
        .count();
    let n_unused = frames.values().filter(|e| e.roles.is_empty()).count();
    let _ = writeln!(
        s,
        "\n## Frames: {} in all, {n_used} used, {n_partly} used in part, {n_dropped} dropped, {n_unused} not used\n",
        frames.len()
    );
    let width = frames
        .keys()
        .map(|f| shown(f).chars().count())
        .max()
        .unwrap_or(5)
        .max(5);
    let _ = writeln!(s, "{:<width$}  OUTCOME  USED FOR / WHY", "FRAME");
    for (file, e) in &frames {
        let outcome = match (e.roles.is_empty(), e.problems.is_empty(), e.left_out.is_empty()) {
            (false, true, true) => "used",
            (false, true, false) => "in part",
            (false, false, _) => "dropped",
            (true, _, _) => "not used",
        };
        let mut what = e.roles.join("; ");
        for l in &e.left_out {
            what.push_str(&format!("; {l}"));
        }
        for p in &e.problems {
            if !what.is_empty() {
                what.push_str(" | ");
            }
            what.push_str(p);
        }
        let _ = writeln!(s, "{:<width$}  {outcome:<7}  {}", shown(file), one_line(&what));
    }
    quality::quality_table(&mut s, cat, &|f: &str| shown(f));
    targets(&mut s, cat);
    s
}

/// Every file the catalog names, with what it was used for and its problems.
fn frame_entries(cat: &Catalog) -> BTreeMap<String, FrameEntry> {
    let mut frames: BTreeMap<String, FrameEntry> = BTreeMap::new();
    for t in &cat.targets {
        for f in t.input_files.iter().flatten() {
            frames
                .entry(f.clone())
                .or_default()
                .roles
                .push(format!("target {}", t.object));
        }
        if let Some(hw) = &t.half_wave_plate {
            let mut role = |f: &str, what: String| {
                let e = frames.entry(f.to_string()).or_default();
                if !e.roles.contains(&what) {
                    e.roles.push(what);
                }
            };
            for f in &hw.darks {
                role(f, "dark (master dark)".into());
            }
            for f in &hw.skies {
                let flat = if hw.flat_from.contains(f) { " and flat" } else { "" };
                role(f, format!("sky frame (matched sky{flat})"));
            }
        }
        for c in &t.components {
            for d in c.dropped_dithers.iter().flatten() {
                frames
                    .entry(d.file.clone())
                    .or_default()
                    .left_out
                    .push(format!("{} left out of {}: {}", t.object, c.name, d.reason));
            }
        }
    }
    for st in &cat.standards {
        let used = if st.used_for.is_empty() {
            "not used by the calibration".to_string()
        } else {
            format!("calibration: {}", st.used_for.join(", "))
        };
        for f in st.input_files.iter().flatten() {
            frames
                .entry(f.clone())
                .or_default()
                .roles
                .push(format!("standard {} ({used})", st.name));
        }
    }
    let prov = &cat.provenance;
    for fl in prov.flat_list() {
        let kind = match fl.kind.as_str() {
            "superflat" => "superflat",
            k => &format!("{k} flat"),
        };
        let filter = fl.filter.as_deref().unwrap_or("");
        let angle = fl.posang_deg.map(|a| format!(" POSANG {a}")).unwrap_or_default();
        for f in &fl.frames {
            frames
                .entry(f.to_string())
                .or_default()
                .roles
                .push(format!("{kind} {filter}{angle}").trim_end().to_string());
        }
    }
    for f in prov.night_bad_pixel_mask_from.iter().flatten() {
        frames
            .entry(f.to_string())
            .or_default()
            .roles
            .push("bad-pixel mask".into());
    }
    for fail in &cat.failures {
        frames
            .entry(fail.file.clone())
            .or_default()
            .problems
            .push(fail.error.clone());
    }
    frames
}

/// The directory (ending in `/`) all `files` share, or "" when none.
fn common_dir<'a>(files: impl Iterator<Item = &'a str>) -> String {
    let mut common: Option<&str> = None;
    for f in files {
        let dir = f.rfind('/').map_or("", |i| &f[..=i]);
        common = Some(match common {
            None => dir,
            Some(c) => {
                let n = c
                    .char_indices()
                    .zip(dir.chars())
                    .take_while(|((_, a), b)| a == b)
                    .last()
                    .map_or(0, |((i, a), _)| i + a.len_utf8());
                // Back to the last '/' of the shared prefix.
                c[..n].rfind('/').map_or("", |i| &c[..=i])
            }
        });
    }
    common.unwrap_or("").to_string()
}

fn header(s: &mut String, cat: &Catalog, catalog_name: &str, root: &str) {
    let prov = &cat.provenance;
    let join = |v: Vec<String>| {
        if v.is_empty() {
            "unknown".to_string()
        } else {
            v.join(", ")
        }
    };
    let _ = writeln!(s, "# sofipol night log of {catalog_name}");
    let _ = writeln!(
        s,
        "software: {} (commit {})",
        join(prov.softwares()),
        join(prov.commits())
    );
    if let Some(t) = &prov.created_utc {
        let _ = writeln!(s, "created: {t} UTC");
    }
    if let Some(cmd) = &prov.command_line {
        let _ = writeln!(s, "command: {}", cmd.join(" "));
    }
    if !root.is_empty() {
        let _ = writeln!(s, "frames under: {root}");
    }
    if let Some(flat) = &prov.flat {
        let n = flat.flat_list().len();
        let _ = writeln!(s, "flat field: {} ({n} flat(s))", flat.mode);
    }
    if let Some(m) = &prov.night_bad_pixel_mask_from {
        let _ = writeln!(s, "night bad-pixel mask: from {} frame(s)", m.len());
    }
    let n_std = cat.standards.iter().filter(|st| !st.used_for.is_empty()).count();
    let _ = writeln!(
        s,
        "calibration: {} standard(s) observed, {n_std} used",
        cat.standards.len()
    );
    let photometry = cat.calibration.as_ref().map_or_else(
        || vec!["no magnitudes: no calibration (fluxes in ADU only)".to_string()],
        |c| c.photometry_lines(),
    );
    for l in photometry {
        let _ = writeln!(s, "photometry: {}", one_line(&l));
    }
}

fn targets(s: &mut String, cat: &Catalog) {
    let _ = writeln!(s, "\n## Targets: {}\n", cat.targets.len());
    for t in &cat.targets {
        let status = match t.status {
            Status::Ok => "ok",
            Status::Partial => "partial",
            Status::Failed => "failed",
        };
        let seq = t.sequence.as_deref().map(|q| format!(" [{q}]")).unwrap_or_default();
        let _ = write!(s, "{}: {status}", one_line(&format!("{}{seq}", t.object)));
        if let Some(e) = &t.error {
            let _ = write!(s, " ({})", one_line(e));
        }
        let _ = writeln!(s);
        for c in &t.components {
            let snr = c.p_debiased / c.sigma_p;
            let cut = if c.passes_cut {
                "passes the cut"
            } else {
                "below the cut"
            };
            let brightness = match (c.mag, c.sigma_mag, c.flux_adu) {
                (Some(m), Some(sm), _) => format!(", {} = {m:.3} +- {sm:.3} mag", t.filter.as_deref().unwrap_or("mag")),
                (_, _, Some(f)) if f.is_finite() => format!(", flux = {f:.0} ADU"),
                _ => String::new(),
            };
            let _ = writeln!(
                s,
                "  {}: P = {:.2} +- {:.2} %, gamma = {:.1} +- {:.1} deg, P/sigma = {:.1}, {cut}{brightness}",
                c.name,
                100.0 * c.p,
                100.0 * c.sigma_p,
                c.gamma_deg,
                c.sigma_gamma_deg,
                snr
            );
            for f in &c.flags {
                let _ = writeln!(s, "    {}: {}", c.name, flag_line(f));
            }
        }
        for f in t.flags.iter().flatten() {
            let _ = writeln!(s, "  {}", flag_line(f));
        }
        if let Some(hw) = &t.half_wave_plate {
            half_wave_plate_lines(s, hw);
        }
    }
}

/// A half-wave-plate target's cycles, their agreement and the zero point, under its
/// component.
fn half_wave_plate_lines(s: &mut String, hw: &crate::catalog::HalfWavePlateResult) {
    let pol = |p: &crate::catalog::half_wave_plate::Pol| {
        format!(
            "q = {:+.3} +- {:.3} %, u = {:+.3} +- {:.3} %, P = {:.3} +- {:.3} %, angle = {:.1} +- {:.1} deg",
            100.0 * p.q,
            100.0 * p.sigma_q,
            100.0 * p.u,
            100.0 * p.sigma_u,
            100.0 * p.p,
            100.0 * p.sigma_p,
            p.angle_deg,
            p.sigma_angle_deg
        )
    };
    let _ = writeln!(
        s,
        "  half-wave plate: {} frame(s), {} complete cycle(s), the component from the {}; zero point {} +- {} deg ({})",
        hw.frames.len(),
        hw.cycles.len(),
        if hw.component_from == crate::catalog::half_wave_plate::FROM_CYCLES {
            "cycles combined"
        } else {
            "least squares over the frames"
        },
        hw.zero_point.deg,
        hw.zero_point.sigma_deg,
        one_line(&hw.zero_point.source)
    );
    if let Some(i) = &hw.instrument {
        let _ = writeln!(s, "    instrument frame: {}", pol(i));
    }
    for (k, c) in hw.cycles.iter().enumerate() {
        let _ = writeln!(s, "    cycle {} on the sky: {}", k + 1, pol(&c.sky));
    }
    if let Some(a) = &hw.cycle_agreement {
        let _ = writeln!(
            s,
            "    cycles' chi2: q {:.1}, u {:.1} for {} dof",
            a.chi2_q, a.chi2_u, a.dof
        );
    }
    if !hw.left_out.is_empty() {
        let _ = writeln!(s, "    in no complete cycle: {}", one_line(&hw.left_out.join(", ")));
    }
}

/// A flag as written, with its sentence when this build knows it.
fn flag_line(flag: &Flag) -> String {
    match flag.explain() {
        Some(sentence) => format!("{} -- {}", one_line(&flag.label()), one_line(&sentence)),
        None => one_line(&flag.to_string()),
    }
}

/// `text` on one line (newlines and tabs as spaces), every other non-printable character
/// escaped as on the terminal.
fn one_line(text: &str) -> String {
    sofipol_calib::text::printable(&text.split_whitespace().collect::<Vec<_>>().join(" ")).into_owned()
}

mod quality;
pub use quality::ut as log_ut;
#[cfg(test)]
mod tests;
