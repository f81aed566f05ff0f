//! The half-wave-plate reduction of single pointings (`sofipol night DIR --profile nirc2`,
//! or any profile whose `[modulation] kind` is `half_wave_plate` or `per_file`): one star
//! per frame on the same pixels, a Wollaston's two beams on separate detector rows, a plate
//! turning the polarization between frames (docs/instruments.md).
//!
//! 1. Files sorted by the profile's `[classify]` keyword tests: darks, sky frames, science
//!    (the plate in the beam: `modulation.in_beam`); every other file is listed as not used,
//!    with the test it failed.
//! 2. Master dark: the per-pixel median of the darks of the science frames' exposure time
//!    and coadds; a pixel more than `single_pointing.hot_pixel_adu` from its median is bad.
//! 3. Flat: the mean of the dark-subtracted sky frames of the complete plate cycles only
//!    (a polarized sky modulates with the plate; a whole cycle averages that out),
//!    normalised to median 1 in each beam's rows; pixels outside [0.5, 1.5] or more than 20 %
//!    off their 5 x 5 median are bad.
//! 4. Each science frame (time order): dark subtracted; the sky frame of the same plate
//!    position scaled and offset per beam by a clipped least-squares fit beyond
//!    `sky_fit_min_radius_px` from the star (`sky = "sky_frames"`), or the median of an
//!    annulus about each image (`sky = "annulus"`); divided by the flat. The variance:
//!    photon noise (gain from the header), the read noise of NDIT summed coadds, the sky
//!    frame's own noise.
//! 5. The star: the brightest 15 x 15 box mean in each beam's rows, then the centre of
//!    180-degree symmetry (`centre_annulus_px`; a saturated core reads low and has no peak;
//!    bad and NaN pixels filled from their neighbours or left out by pairs:
//!    [`image::symmetry_centre`]).
//!    The two images are one star's when their offset is `geometry.eo_offset_px` within
//!    `beams.offset_tolerance_px` and their fluxes agree within `beams.flux_ratio_tolerance`;
//!    otherwise the frame stops the reduction, named.
//! 6. Photometry: exact-area annulus `aperture_px` (r_in outside every pixel above the
//!    linear limit, checked per frame; the annulus inside the frame and its beam's rows,
//!    else the frame is not used, named), bad and NaN pixels left out; cosmic-ray hits in
//!    the apertures found against the target's other frames and repaired ([`cosmic`]).
//! 7. Stokes: [`crate::stokes::hwp`]: F per frame, the double difference of each complete
//!    plate cycle and their combination with the cycle-to-cycle scatter, the least squares
//!    over every frame; once in the instrument frame (theta0 = 0) and once on the sky
//!    (`modulation.zero_point_deg` plus each frame's field rotation, `[field_rotation]`).
pub mod cosmic;
pub mod image;
pub mod output;

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sofipol_calib::header::Header;
use sofipol_calib::profile::{ModulationKind, Role, SkySource};
use sofipol_calib::Profile;

pub use crate::catalog::half_wave_plate::{
    CycleAgreement, CycleResult, FrameResult, LeastSquares, NotUsed, Pol, SkyFit, ZeroPoint,
};
use crate::catalog::provenance::Provenance;
use crate::error::{Error, Result};
use crate::stokes::hwp::{self, CycleMethod, HwpStokes, PlateFrame};
use image::Img;

/// What the half-wave-plate reduction measured: the night writes it as sofipol's catalog
/// ([`output::to_catalog`]; docs/instruments.md, "The catalog").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SinglePointingCatalog {
    /// What this is ([`CATALOG_KIND`]).
    pub kind: String,
    /// Software, commit, command line, time.
    pub provenance: Provenance,
    /// The profile's name.
    pub profile: String,
    /// `half_wave_plate` or `per_file`.
    pub modulation: String,
    /// `sky_fixed` or `pupil_tracking`, with the keywords of the angle on the sky.
    pub field_rotation: String,
    /// The analyzer zero point used for the angles on the sky.
    pub zero_point: ZeroPoint,
    /// Dark frames used.
    pub darks: Vec<String>,
    /// Sky frames used (sky of matching plate position).
    pub skies: Vec<String>,
    /// Sky frames averaged into the flat (complete plate cycles only).
    pub flat_from: Vec<String>,
    /// Bad pixels (dark, flat).
    pub bad_pixels: usize,
    /// Pixels of the sky frames repaired as cosmic-ray hits before the flat and the matched
    /// skies were made of them (all sky frames).
    pub sky_cosmic_ray_pixels: usize,
    /// Files not used, with why.
    pub not_used: Vec<NotUsed>,
    /// One entry per target and filter.
    pub targets: Vec<TargetResult>,
}

/// The kind string of [`SinglePointingCatalog`].
pub const CATALOG_KIND: &str = "sofipol half-wave-plate single-pointing result";

/// One target in one filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetResult {
    /// The target's name (`keywords.targ_name`, else `keywords.object`).
    pub name: String,
    /// The filter.
    pub filter: String,
    /// Mean MJD of its frames.
    pub mjd: f64,
    /// The cycles combined (double difference, weighted mean, adopted errors include the
    /// cycle-to-cycle scatter), instrument frame (theta0 = 0, no instrumental polarization
    /// removed). `None` without a complete cycle.
    pub instrument: Option<Pol>,
    /// The same on the sky (zero point and field rotation applied).
    pub sky: Option<Pol>,
    /// The systematic error of the angle on the sky from the zero point, deg.
    pub sigma_angle_zero_point_deg: f64,
    /// Each complete cycle.
    pub cycles: Vec<CycleResult>,
    /// Their agreement.
    pub cycle_agreement: Option<CycleAgreement>,
    /// Least squares over every usable frame, instrument frame.
    pub least_squares_instrument: Option<LeastSquares>,
    /// The same on the sky.
    pub least_squares_sky: Option<LeastSquares>,
    /// Frames in no complete cycle.
    pub left_out: Vec<String>,
    /// Per frame.
    pub frames: Vec<FrameResult>,
}

fn err(file: impl Into<String>, reason: impl Into<String>) -> Error {
    Error::SinglePointing {
        file: file.into(),
        reason: reason.into(),
    }
}

fn calib(file: &Path) -> impl Fn(sofipol_calib::Error) -> Error + '_ {
    move |e| {
        let f = file.display().to_string();
        err(f.clone(), without_path(e.to_string(), &f))
    }
}

/// `msg` without the leading `"FILE: "` (as often as it repeats): for an error that is
/// named by its file once more.
fn without_path(msg: String, file: &str) -> String {
    let prefix = format!("{file}: ");
    let mut m = msg.as_str();
    while let Some(rest) = m.strip_prefix(&prefix) {
        m = rest;
    }
    m.to_string()
}

/// One input file, with what a set-of-frames file says of it (docs/frame-format.md, "A set
/// of frames as a file"): its role, its modulation angle and its target in place of the
/// header's.
#[derive(Debug, Clone, PartialEq)]
pub struct InputFile {
    /// The file.
    pub path: PathBuf,
    /// Its role (`None`: from the header by the profile's `[classify]`).
    pub role: Option<Role>,
    /// `angle=`: the modulation angle, deg (the plate angle; the analyzer angle of a
    /// `per_file` modulation).
    pub angle_deg: Option<f64>,
    /// `target=`: the target's name.
    pub target: Option<String>,
}

/// The input files under `inputs`: every FITS file of a folder (recursively), or the
/// frames of a set-of-frames file with their roles (`science`, `dark`, `sky`; a `flat` or
/// `standard` frame is listed as not used, with why).
pub fn input_files(inputs: &[PathBuf]) -> Result<Vec<InputFile>> {
    let mut out = Vec::new();
    let mut folders = Vec::new();
    for i in inputs {
        if crate::frame_list::is_frame_list(i) {
            let list = crate::frame_list::read(i).map_err(|e| err(i.display().to_string(), e.to_string()))?;
            for f in list.frames {
                use crate::frame_list::FrameRole as R;
                let role = match f.role {
                    R::Science => Role::Science,
                    R::Dark => Role::Dark,
                    R::Sky => Role::Sky,
                    R::Flat | R::Standard => Role::NotUsed(format!(
                        "listed as {} in {} (line {}): the half-wave-plate reduction takes its flat from the sky frames and has no standards",
                        f.role.name(),
                        list.file.display(),
                        f.line
                    )),
                };
                out.push(InputFile {
                    path: f.path,
                    role: Some(role),
                    angle_deg: f.angle_deg,
                    target: f.target,
                });
            }
        } else {
            folders.push(i.clone());
        }
    }
    if !folders.is_empty() {
        out.extend(crate::scan::list(&folders).files.into_iter().map(|path| InputFile {
            path,
            role: None,
            angle_deg: None,
            target: None,
        }));
    }
    Ok(out)
}

struct Raw {
    path: PathBuf,
    header: Header,
    img: Img,
    angle_deg: Option<f64>,
    target: Option<String>,
}

fn read(f: &InputFile) -> Result<Raw> {
    let path = &f.path;
    let fr = sofipol_calib::fits::read_frame(path).map_err(calib(path))?;
    let (ny, nx) = fr.shape();
    Ok(Raw {
        path: path.to_path_buf(),
        header: fr.header,
        img: Img {
            nx,
            ny,
            v: fr.data.iter().map(|&v| v as f64).collect(),
        },
        angle_deg: f.angle_deg,
        target: f.target.clone(),
    })
}

/// The plate angle of a frame: `angle=` of a set-of-frames file, else the header's.
fn plate_of(r: &Raw, m: &sofipol_calib::profile::Modulation) -> Result<f64> {
    match (r.angle_deg, m.kind) {
        (Some(a), ModulationKind::PerFile) => Ok(0.5 * a),
        (Some(a), _) => Ok(a),
        (None, _) => m.plate_deg(&r.header).map_err(calib(&r.path)),
    }
}

/// The night's summary in a few lines: per target q, u, P, angle in the instrument frame
/// and on the sky, the zero point, the cycles' agreement; the files not used.
pub fn summary_lines(cat: &SinglePointingCatalog) -> Vec<String> {
    let pct = |v: f64| 100.0 * v;
    let pol = |p: &Pol| {
        format!(
            "q {:+.3} +- {:.3} %, u {:+.3} +- {:.3} %, P {:.3} +- {:.3} %, angle {:.1} +- {:.1} deg",
            pct(p.q),
            pct(p.sigma_q),
            pct(p.u),
            pct(p.sigma_u),
            pct(p.p),
            pct(p.sigma_p),
            p.angle_deg,
            p.sigma_angle_deg
        )
    };
    let mut lines = vec![format!(
        "profile {} ({}, {}): {} dark(s), {} sky frame(s) ({} in the flat, {} pixels repaired as cosmic-ray hits), {} bad pixels, {} file(s) not used",
        cat.profile,
        cat.modulation,
        cat.field_rotation,
        cat.darks.len(),
        cat.skies.len(),
        cat.flat_from.len(),
        cat.sky_cosmic_ray_pixels,
        cat.bad_pixels,
        cat.not_used.len()
    )];
    for n in &cat.not_used {
        lines.push(format!("not used: {}: {}", n.file, n.reason));
    }
    for t in &cat.targets {
        let head = format!(
            "{} {} ({} frames, {} cycles)",
            t.name,
            t.filter,
            t.frames.len(),
            t.cycles.len()
        );
        match (&t.instrument, &t.sky) {
            (Some(i), Some(s)) => {
                lines.push(format!("{head}: instrument {}", pol(i)));
                lines.push(format!(
                    "{head}: sky {} (zero point {} +- {} deg: the angle's systematic error)",
                    pol(s),
                    cat.zero_point.deg,
                    cat.zero_point.sigma_deg
                ));
            }
            _ => lines.push(format!(
                "{head}: no complete plate cycle; see the least squares in the catalog"
            )),
        }
        // With the field turning, the least squares over every frame beside the cycles'
        // combination (both take each frame's own rotation).
        if let (true, Some(ls)) = (cat.field_rotation.starts_with("pupil_tracking"), &t.least_squares_sky) {
            lines.push(format!(
                "{head}: sky, least squares over the frames, each at its own rotation {} (chi2 {:.1} for {} dof)",
                pol(&ls.pol),
                ls.chi2,
                ls.dof
            ));
        }
        if let Some(why) = t.least_squares_sky.as_ref().and_then(|l| l.c_not_fitted.as_ref()) {
            lines.push(format!("{head}: least squares: {why}"));
        }
        for (k, c) in t.cycles.iter().enumerate() {
            lines.push(format!("{head}: cycle {} instrument {}", k + 1, pol(&c.instrument)));
        }
        if let Some(a) = &t.cycle_agreement {
            let f = |v: &[f64]| v.iter().map(|x| format!("{x:+.1}")).collect::<Vec<_>>().join(", ");
            lines.push(format!(
                "{head}: consecutive cycles differ by {} sigma in q, {} sigma in u ({}; photometric errors; the adopted errors include the scatter)",
                f(&a.q_difference_sigma),
                f(&a.u_difference_sigma),
                if cat.field_rotation.starts_with("pupil_tracking") { "on the sky" } else { "instrument frame" }
            ));
        }
    }
    lines
}

fn name(p: &Path) -> String {
    p.file_name()
        .map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into_owned())
}

/// Reduce every target under `roots` (folders or set-of-frames files) with a
/// half-wave-plate profile.
pub fn reduce(roots: &[PathBuf], profile: &Profile) -> Result<SinglePointingCatalog> {
    reduce_inputs(&input_files(roots)?, roots, profile)
}

/// [`reduce`] of the files given (`roots`: the inputs as given, for the provenance).
pub fn reduce_inputs(files: &[InputFile], roots: &[PathBuf], profile: &Profile) -> Result<SinglePointingCatalog> {
    let night = roots
        .iter()
        .map(|r| r.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let kind = profile.modulation_kind();
    if kind == ModulationKind::RotateInstrument {
        return Err(err(
            &night,
            format!(
                "profile {}: modulation.kind is rotate_instrument, not a half-wave plate",
                profile.name
            ),
        ));
    }
    let (m, cls, beams, sp) = match (
        &profile.modulation,
        &profile.classify,
        &profile.beams,
        &profile.single_pointing,
    ) {
        (Some(m), Some(c), Some(b), Some(s)) => (m, c, b, s),
        _ => {
            return Err(err(
                &night,
                "the profile lacks [modulation], [classify], [beams] or [single_pointing]",
            ))
        }
    };
    let kw = &profile.keywords;
    let field = profile.field_rotation.clone().unwrap_or_default();
    // 1. Roles.
    let mut not_used = Vec::new();
    let (mut darks, mut skies, mut science) = (Vec::new(), Vec::new(), Vec::new());
    for input in files {
        let p = &input.path;
        let h = match sofipol_calib::fits::read_header(p) {
            Ok(h) => h,
            Err(e) => {
                not_used.push(NotUsed {
                    file: name(p),
                    reason: e.to_string(),
                });
                continue;
            }
        };
        match input.role.clone().unwrap_or_else(|| cls.role(&h)) {
            Role::Dark => darks.push(input.clone()),
            Role::Sky => skies.push(input.clone()),
            Role::Science => match &m.in_beam {
                Some(r) if !r.matches(&h) => not_used.push(NotUsed {
                    file: name(p),
                    reason: format!("the modulator is not in the beam: {} fails", r.describe()),
                }),
                _ => science.push(input.clone()),
            },
            Role::NotUsed(reason) => not_used.push(NotUsed { file: name(p), reason }),
        }
    }
    if science.is_empty() {
        return Err(err(
            &night,
            "no science frame (see the profile's [classify] science rules)",
        ));
    }
    let read_all = |v: &[InputFile]| -> Result<Vec<Raw>> { v.par_iter().map(read).collect() };
    let mut sci = read_all(&science)?;
    let mjd = |r: &Raw| r.header.get_f64(&kw.mjd_obs).map_err(calib(&r.path));
    for r in &sci {
        mjd(r)?;
    }
    sci.sort_by(|a, b| mjd(a).unwrap_or(0.0).total_cmp(&mjd(b).unwrap_or(0.0)));
    let (nx, ny) = (sci[0].img.nx, sci[0].img.ny);
    for r in &sci {
        if (r.img.nx, r.img.ny) != (nx, ny) {
            return Err(err(
                name(&r.path),
                format!(
                    "{} x {} px, not {nx} x {ny} as {}",
                    r.img.nx,
                    r.img.ny,
                    name(&sci[0].path)
                ),
            ));
        }
    }
    if beams.o_rows[1] > ny || beams.e_rows[1] > ny {
        return Err(err(
            name(&sci[0].path),
            format!("{ny} rows: fewer than the profile's [beams] rows"),
        ));
    }
    let setup = |h: &Header| (h.opt_str(&kw.dit), h.opt_str(&kw.ndit));
    let sci_setup = setup(&sci[0].header);
    for r in &sci {
        if setup(&r.header) != sci_setup {
            return Err(err(
                name(&r.path),
                format!(
                    "{} / {} differ from {}'s: one exposure setup per night",
                    kw.dit,
                    kw.ndit,
                    name(&sci[0].path)
                ),
            ));
        }
    }
    // 2. Dark.
    let mut dark_raw = Vec::new();
    for r in read_all(&darks)? {
        if setup(&r.header) != sci_setup || (r.img.nx, r.img.ny) != (nx, ny) {
            not_used.push(NotUsed {
                file: name(&r.path),
                reason: format!(
                    "a dark of another {} / {} or size than the science frames",
                    kw.dit, kw.ndit
                ),
            });
        } else {
            dark_raw.push(r);
        }
    }
    let dark = if dark_raw.is_empty() {
        Img::filled(nx, ny, 0.0)
    } else {
        image::median_stack(&dark_raw.iter().map(|r| &r.img).collect::<Vec<_>>())
    };
    let dark_median = image::median(&mut dark.v.clone());
    let mut bad: Vec<bool> = dark
        .v
        .iter()
        .map(|&d| !d.is_finite() || (d - dark_median).abs() > sp.hot_pixel_adu)
        .collect();
    let sub_dark = |r: &Raw| -> Img {
        Img {
            nx,
            ny,
            v: r.img.v.iter().zip(&dark.v).map(|(a, d)| a - d).collect(),
        }
    };
    // 3. Sky frames, flat.
    let mut sky_raw = Vec::new();
    for r in read_all(&skies)? {
        let usable = setup(&r.header) == sci_setup && (r.img.nx, r.img.ny) == (nx, ny);
        // A sky frame without its plate angle or time is left out, not the night.
        let (plate, t) = match plate_of(&r, m).and_then(|p| Ok((p, mjd(&r)?))) {
            Ok(v) => v,
            Err(e) => {
                not_used.push(NotUsed {
                    file: name(&r.path),
                    reason: without_path(
                        without_path(e.to_string(), &r.path.display().to_string()),
                        &name(&r.path),
                    ),
                });
                continue;
            }
        };
        match (usable, hwp::cycle_position(plate, m.tolerance_deg)) {
            (true, Some(pos)) => sky_raw.push((t, pos, plate, r)),
            (false, _) => not_used.push(NotUsed {
                file: name(&r.path),
                reason: format!(
                    "a sky frame of another {} / {} or size than the science frames",
                    kw.dit, kw.ndit
                ),
            }),
            (true, None) => not_used.push(NotUsed {
                file: name(&r.path),
                reason: format!("sky frame at plate angle {plate} deg: not a cycle position"),
            }),
        }
    }
    sky_raw.sort_by(|a, b| a.0.total_cmp(&b.0));
    let plates: Vec<f64> = sky_raw.iter().map(|s| s.2).collect();
    let grouping = hwp::complete_cycles(&plates, &vec![true; plates.len()], m.tolerance_deg);
    if grouping.cycles.is_empty() {
        return Err(err(
            &night,
            format!(
                "{} sky frame(s) hold no complete plate cycle (0, 22.5, 45, 67.5 deg): the flat must average whole cycles",
                sky_raw.len()
            ),
        ));
    }
    let mut sky_sub: Vec<Img> = sky_raw.iter().map(|s| sub_dark(&s.3)).collect();
    // Cosmic rays in the sky frames repaired against each other before the flat and the
    // matched skies are made of them.
    let sky_repaired = cosmic::repair_sky_frames(&mut sky_sub, &[beams.o_rows, beams.e_rows], &bad);
    let in_cycles: Vec<usize> = grouping.cycles.iter().flatten().copied().collect();
    let mut flat = Img::filled(nx, ny, 0.0);
    for &i in &in_cycles {
        for (f, s) in flat.v.iter_mut().zip(&sky_sub[i].v) {
            *f += s / in_cycles.len() as f64;
        }
    }
    let region_median = |img: &Img, rows: [usize; 2]| image::median(&mut img.v[rows[0] * nx..rows[1] * nx].to_vec());
    let (lo, le) = (region_median(&flat, beams.o_rows), region_median(&flat, beams.e_rows));
    if !(lo > 0.0 && le > 0.0) {
        return Err(err(
            &night,
            format!("the sky frames' median level is {lo} (o rows), {le} (e rows) ADU: no flat"),
        ));
    }
    for y in 0..ny {
        let level = if (beams.o_rows[0]..beams.o_rows[1]).contains(&y) {
            lo
        } else if (beams.e_rows[0]..beams.e_rows[1]).contains(&y) {
            le
        } else {
            0.5 * (lo + le)
        };
        for v in &mut flat.v[y * nx..(y + 1) * nx] {
            *v /= level;
        }
    }
    let local = image::median_filter(&flat, 2);
    for ((b, &f), &l) in bad.iter_mut().zip(&flat.v).zip(&local.v) {
        if !f.is_finite() || !(0.5..=1.5).contains(&f) || (f / l - 1.0).abs() > 0.2 {
            *b = true;
        }
    }
    for (f, &b) in flat.v.iter_mut().zip(&bad) {
        if b {
            *f = 1.0;
        }
    }
    // The matched sky of each cycle position: the mean of the sky frames there.
    let mut matched: Vec<Option<(Img, usize)>> = vec![None, None, None, None];
    for (s, img) in sky_raw.iter().zip(&sky_sub) {
        let slot = &mut matched[s.1];
        match slot {
            None => *slot = Some((img.clone(), 1)),
            Some((acc, n)) => {
                for (a, v) in acc.v.iter_mut().zip(&img.v) {
                    *a += v;
                }
                *n += 1;
            }
        }
    }
    for (acc, n) in matched.iter_mut().flatten() {
        for a in acc.v.iter_mut() {
            *a /= *n as f64;
        }
    }
    // 4-6. Science frames.
    let ctx = FrameContext {
        profile,
        dark: &dark,
        flat: &flat,
        bad: &bad,
        matched: &matched,
        field: &field,
    };
    // A science frame that cannot be measured (a missing keyword, no pair of images...) is
    // listed as not used with why; the night goes on with the others.
    let results: Vec<Result<(FrameResult, [cosmic::Cutout; 2])>> =
        sci.par_iter().map(|r| measure_frame(r, &ctx)).collect();
    let mut measured: Vec<FrameResult> = Vec::new();
    let mut cutouts: Vec<[cosmic::Cutout; 2]> = Vec::new();
    let mut kept: Vec<&Raw> = Vec::new();
    let mut first_error = None;
    for (r, res) in sci.iter().zip(results) {
        match res {
            Ok((f, cuts)) => {
                measured.push(f);
                cutouts.push(cuts);
                kept.push(r);
            }
            Err(e) => {
                not_used.push(NotUsed {
                    file: name(&r.path),
                    reason: without_path(
                        without_path(e.to_string(), &r.path.display().to_string()),
                        &name(&r.path),
                    ),
                });
                first_error.get_or_insert(e);
            }
        }
    }
    if let (true, Some(e)) = (measured.is_empty(), first_error) {
        return Err(e);
    }
    // 7. Per target and filter, in time order.
    let target_of = |r: &Raw| {
        let h = &r.header;
        r.target
            .clone()
            .or_else(|| h.opt_str(&kw.targ_name))
            .or_else(|| h.opt_str(&kw.object))
            .map_or_else(|| "unnamed".to_string(), |s| s.trim().to_string())
    };
    let filter_of = |h: &Header| h.opt_str(&kw.filter).map_or_else(String::new, |s| s.trim().to_string());
    let mut keys: Vec<(String, String)> = Vec::new();
    for r in &kept {
        let k = (target_of(r), filter_of(&r.header));
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    let targets = keys
        .into_iter()
        .map(|(t, f)| {
            let idx: Vec<usize> = (0..kept.len())
                .filter(|&i| target_of(kept[i]) == t && filter_of(&kept[i].header) == f)
                .collect();
            let mut frames: Vec<FrameResult> = idx.iter().map(|&i| measured[i].clone()).collect();
            let cuts: Vec<&[cosmic::Cutout; 2]> = idx.iter().map(|&i| &cutouts[i]).collect();
            cosmic::repair(&mut frames, &cuts, sp.aperture_px);
            target_result(t, f, frames, m.zero_point_deg, m.sigma_zero_point_deg, m.tolerance_deg)
        })
        .collect();
    let field_words = match field.kind {
        sofipol_calib::profile::FieldRotationKind::SkyFixed => "sky_fixed".to_string(),
        sofipol_calib::profile::FieldRotationKind::PupilTracking => {
            let mut s = format!(
                "pupil_tracking: analyzer angle on the sky = 2 x {} + zero point + {}",
                m.keyword.as_deref().unwrap_or_default(),
                field.parang_keyword.as_deref().unwrap_or_default()
            );
            for t in &field.terms {
                s += &format!(
                    " {} {} x {}",
                    if t.factor < 0.0 { "-" } else { "+" },
                    t.factor.abs(),
                    t.keyword
                );
            }
            s
        }
    };
    Ok(SinglePointingCatalog {
        kind: CATALOG_KIND.into(),
        provenance: Provenance {
            inputs: Some(roots.iter().map(|r| r.display().to_string()).collect()),
            ..Provenance::now()
        },
        profile: profile.name.clone(),
        modulation: kind.name().into(),
        field_rotation: field_words,
        zero_point: ZeroPoint {
            deg: m.zero_point_deg,
            sigma_deg: m.sigma_zero_point_deg,
            source: m.zero_point_source.clone(),
        },
        darks: dark_raw.iter().map(|r| name(&r.path)).collect(),
        skies: sky_raw.iter().map(|s| name(&s.3.path)).collect(),
        flat_from: in_cycles.iter().map(|&i| name(&sky_raw[i].3.path)).collect(),
        bad_pixels: bad.iter().filter(|&&b| b).count(),
        sky_cosmic_ray_pixels: sky_repaired.iter().sum(),
        not_used,
        targets,
    })
}

struct FrameContext<'a> {
    profile: &'a Profile,
    dark: &'a Img,
    flat: &'a Img,
    bad: &'a [bool],
    matched: &'a [Option<(Img, usize)>],
    field: &'a sofipol_calib::profile::FieldRotation,
}

fn measure_frame(r: &Raw, c: &FrameContext<'_>) -> Result<(FrameResult, [cosmic::Cutout; 2])> {
    let p = c.profile;
    let (m, beams, sp) = (
        p.modulation.as_ref().expect("checked"),
        p.beams.as_ref().expect("checked"),
        p.single_pointing.as_ref().expect("checked"),
    );
    let file = name(&r.path);
    let h = &r.header;
    // This frame's bad pixels: the night's, and its own pixels that are not finite (NaN).
    let bad_f: Vec<bool> = c.bad.iter().zip(&r.img.v).map(|(&b, v)| b || !v.is_finite()).collect();
    let (nx, ny) = (r.img.nx, r.img.ny);
    let plate = plate_of(r, m)?;
    let pos = hwp::cycle_position(plate, m.tolerance_deg);
    let sky_offset = c.field.sky_offset_deg(h).map_err(calib(&r.path))?;
    let mjd = h.get_f64(&p.keywords.mjd_obs).map_err(calib(&r.path))?;
    let gain = p.detector.gain_of(h).map_err(calib(&r.path))?;
    let rn = p.detector.read_noise_of(h).map_err(calib(&r.path))?;
    let ndit = match h.contains(&p.keywords.ndit) {
        true => match h.get_i64(&p.keywords.ndit).map_err(calib(&r.path))? {
            n if n >= 1 => n as f64,
            n => {
                return Err(err(
                    &file,
                    format!("{} = {n}: the number of coadds must be >= 1", p.keywords.ndit),
                ))
            }
        },
        false => 1.0,
    };
    // Read-noise variance of the frame, ADU^2: NDIT reads summed, or averaged.
    let read_var = if p.detector.coadds_summed {
        ndit * (rn / gain).powi(2)
    } else {
        (rn / gain).powi(2) / ndit
    };
    // Photon noise: a summed frame holds gain x value electrons; an averaged one NDIT x that.
    let eff_gain = if p.detector.coadds_summed { gain } else { gain * ndit };
    let s = Img {
        nx,
        ny,
        v: r.img.v.iter().zip(&c.dark.v).map(|(a, d)| a - d).collect(),
    };
    let sky = match sp.sky {
        SkySource::SkyFrames => {
            let pos = pos.ok_or_else(|| {
                err(
                    &file,
                    format!("plate angle {plate} deg is not a cycle position: no matched sky frame"),
                )
            })?;
            Some(c.matched[pos].as_ref().ok_or_else(|| {
                err(
                    &file,
                    format!("no sky frame at plate position {} deg", hwp::CYCLE_POSITIONS_DEG[pos]),
                )
            })?)
        }
        SkySource::Annulus => None,
    };
    let diff = match sky {
        Some((k, _)) => Img {
            nx,
            ny,
            v: s.v.iter().zip(&k.v).map(|(a, b)| a - b).collect(),
        },
        None => s.clone(),
    };
    let rough = |rows: [usize; 2]| -> Result<(f64, f64)> {
        let bx = image::boxcar_in_rows(&diff, &bad_f, rows, 15);
        let mut best = (f64::NEG_INFINITY, 0usize, 0usize);
        for y in rows[0]..rows[1] {
            for x in 0..nx {
                let v = bx.at(x, y);
                if v > best.0 {
                    best = (v, x, y);
                }
            }
        }
        if best.0.is_finite() {
            Ok((best.1 as f64, best.2 as f64))
        } else {
            Err(err(&file, format!("no source in rows {}..{}", rows[0], rows[1])))
        }
    };
    let (rough_o, rough_e) = (rough(beams.o_rows)?, rough(beams.e_rows)?);
    let mut img = Img::filled(nx, ny, f64::NAN);
    let mut var = Img::filled(nx, ny, f64::NAN);
    let mut fit_beam = |rows: [usize; 2], centre: (f64, f64)| -> Result<SkyFit> {
        let (a, b, sig, n, nsky) = match sky {
            Some((k, nsky)) => {
                let (a, b, sig, n) =
                    image::fit_sky(&s, k, &bad_f, rows, centre, sp.sky_fit_min_radius_px).ok_or_else(|| {
                        err(
                            &file,
                            format!("sky fit in rows {}..{}: too few pixels", rows[0], rows[1]),
                        )
                    })?;
                (a, b, sig, n, *nsky as f64)
            }
            None => (0.0, 0.0, f64::NAN, 0, 1.0),
        };
        for y in rows[0]..rows[1] {
            for x in 0..nx {
                let i = y * nx + x;
                let kv = sky.map_or(0.0, |(k, _)| k.v[i]);
                let f = c.flat.v[i];
                img.v[i] = (s.v[i] - a * kv - b) / f;
                let v = s.v[i].max(0.0) / eff_gain + read_var + a * a * (kv.max(0.0) / eff_gain + read_var) / nsky;
                var.v[i] = v / (f * f);
            }
        }
        Ok(SkyFit {
            scale: if sky.is_some() { a } else { 1.0 },
            offset_adu: b,
            sigma_adu: sig,
            pixels: n,
        })
    };
    let mut sky_o = fit_beam(beams.o_rows, rough_o)?;
    let mut sky_e = fit_beam(beams.e_rows, rough_e)?;
    let [ci, co] = sp.centre_annulus_px;
    let centre = |g: (f64, f64)| {
        image::symmetry_centre(&img, &bad_f, g, ci, co, sp.search_radius_px)
            .ok_or_else(|| err(&file, format!("no centre of symmetry near ({:.0}, {:.0})", g.0, g.1)))
    };
    let (co_, ce_) = (centre(rough_o)?, centre(rough_e)?);
    if sky.is_none() {
        // Annulus sky: the median of the annulus about each image, with its error.
        let [a0, a1] = sp.sky_annulus_px;
        for (cen, rows, fit) in [(co_, beams.o_rows, &mut sky_o), (ce_, beams.e_rows, &mut sky_e)] {
            let mut vals = Vec::new();
            for y in rows[0]..rows[1] {
                for x in 0..nx {
                    let r = (x as f64 - cen.0).hypot(y as f64 - cen.1);
                    let i = y * nx + x;
                    if r >= a0 && r <= a1 && !bad_f[i] && img.v[i].is_finite() {
                        vals.push(img.v[i]);
                    }
                }
            }
            if vals.len() < 10 {
                return Err(err(
                    &file,
                    format!("sky annulus {a0}-{a1} px: {} pixels in the beam's rows", vals.len()),
                ));
            }
            let med = image::median(&mut vals.clone());
            let mut dev: Vec<f64> = vals.iter().map(|v| (v - med).abs()).collect();
            let sig = 1.4826 * image::median(&mut dev);
            // Var of a median = (pi/2) sigma^2 / n; correlated over the aperture's area.
            let [r_in, r_out] = sp.aperture_px;
            let area = std::f64::consts::PI * (r_out * r_out - r_in * r_in);
            let var_sky = std::f64::consts::FRAC_PI_2 * sig * sig / vals.len() as f64;
            for y in rows[0]..rows[1] {
                for x in 0..nx {
                    let i = y * nx + x;
                    img.v[i] -= med;
                    var.v[i] += var_sky * area;
                }
            }
            *fit = SkyFit {
                scale: 1.0,
                offset_adu: med,
                sigma_adu: sig,
                pixels: vals.len(),
            };
        }
    }
    let eo = [ce_.0 - co_.0, ce_.1 - co_.1];
    let want = p.geometry.eo_offset_px;
    if (eo[0] - want[0]).abs() > beams.offset_tolerance_px || (eo[1] - want[1]).abs() > beams.offset_tolerance_px {
        return Err(err(
            &file,
            format!(
                "e - o offset ({:.2}, {:.2}) px is not geometry.eo_offset_px ({}, {}) within {} px: the o and e images were not paired",
                eo[0], eo[1], want[0], want[1], beams.offset_tolerance_px
            ),
        ));
    }
    // Pixels above the linear limit: the aperture must lie outside them.
    let limit = p.detector.linear_limit_adu * if p.detector.coadds_summed { ndit } else { 1.0 };
    let mut sat_r: f64 = 0.0;
    for cen in [co_, ce_] {
        let (x0, x1) = ((cen.0 - 60.0).max(0.0) as usize, ((cen.0 + 60.0) as usize).min(nx - 1));
        let (y0, y1) = ((cen.1 - 60.0).max(0.0) as usize, ((cen.1 + 60.0) as usize).min(ny - 1));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let i = y * nx + x;
                let r = (x as f64 - cen.0).hypot(y as f64 - cen.1);
                if r < 60.0 && !bad_f[i] && s.v[i] > limit {
                    sat_r = sat_r.max(r);
                }
            }
        }
    }
    let [r_in, r_out] = sp.aperture_px;
    if sat_r > 0.0 && r_in <= sat_r + 0.5 {
        return Err(err(
            &file,
            format!(
                "a pixel above the linear limit ({} ADU per read) lies {sat_r:.1} px from a centre, inside the aperture's r_in = {r_in} px: raise single_pointing.aperture_px",
                p.detector.linear_limit_adu
            ),
        ));
    }
    for (cen, rows, beam) in [(co_, beams.o_rows, "o"), (ce_, beams.e_rows, "e")] {
        if !image::inside(&img, cen, r_out) {
            return Err(err(
                &file,
                format!(
                    "the aperture of radius {r_out} px about ({:.1}, {:.1}) leaves the frame",
                    cen.0, cen.1
                ),
            ));
        }
        // The aperture must lie within its beam's rows (outside them the image holds the
        // other beam or nothing: no flux of this star's beam to sum).
        if cen.1 - r_out < rows[0] as f64 - 0.5 || cen.1 + r_out > rows[1] as f64 - 0.5 {
            return Err(err(
                &file,
                format!(
                    "the {beam} image's aperture (single_pointing.aperture_px outer radius {r_out} px) about ({:.1}, {:.1}) \
                     crosses the {beam} beam's rows {}..{} (beams.{beam}_rows): a smaller aperture or a star farther from the beam's edge",
                    cen.0, cen.1, rows[0], rows[1]
                ),
            ));
        }
    }
    let (o, so) = image::annulus_sum(&img, &var, &bad_f, co_, r_in, r_out);
    let (e, se) = image::annulus_sum(&img, &var, &bad_f, ce_, r_in, r_out);
    if ![o, so, e, se].iter().all(|v| v.is_finite()) {
        return Err(err(
            &file,
            format!("the aperture sums are not finite (o {o} +- {so}, e {e} +- {se} ADU): a pixel of the sky fit or the flat is not finite"),
        ));
    }
    if !(o > 0.0 && e > 0.0) || (o / e - 1.0).abs() > beams.flux_ratio_tolerance {
        return Err(err(
            &file,
            format!(
                "o/e flux ratio {:.3} (o {o:.4e}, e {e:.4e} ADU) is not within beams.flux_ratio_tolerance = {} of 1: \
                 the two images are not one star's, or the star is polarized by more than about {:.0} % \
                 (then raise beams.flux_ratio_tolerance)",
                o / e,
                beams.flux_ratio_tolerance,
                // |o/e - 1| = t at F = t / (2 + t): a star polarized beyond that F fails.
                100.0 * beams.flux_ratio_tolerance / (2.0 + beams.flux_ratio_tolerance)
            ),
        ));
    }
    let (f, sf) = hwp::frame_f(&PlateFrame {
        plate_deg: plate,
        o,
        sigma_o: so,
        e,
        sigma_e: se,
    })
    .ok_or_else(|| err(&file, "F undefined (fluxes or errors not finite)"))?;
    // Boxes about both images for the cosmic-ray test against the other frames (guiding
    // moves the star by a few pixels at most).
    let cuts = [co_, ce_].map(|cen| cosmic::Cutout::new(&img, &var, &bad_f, cen, r_out + 8.0));
    let result = FrameResult {
        file,
        plate_deg: plate,
        mjd,
        sky_offset_deg: sky_offset,
        o_centre: [co_.0, co_.1],
        e_centre: [ce_.0, ce_.1],
        eo_offset: eo,
        sky_o,
        sky_e,
        saturation_radius_px: sat_r,
        o,
        sigma_o: so,
        e,
        sigma_e: se,
        f,
        sigma_f: sf,
        cosmic_ray_pixels: [0, 0],
    };
    Ok((result, cuts))
}

fn least_squares(r: &HwpStokes) -> Option<LeastSquares> {
    r.least_squares.map(|ls| LeastSquares {
        pol: Pol::new(
            ls.fit.q,
            ls.fit.u,
            ls.adopted_sigma_q(),
            ls.adopted_sigma_u(),
            ls.fit.var_q.sqrt(),
            ls.fit.var_u.sqrt(),
        ),
        c: ls.offset.map(|o| o.c),
        c_not_fitted: ls.offset_note(),
        chi2: ls.fit.chi2,
        dof: ls.dof,
    })
}

fn combined(r: &HwpStokes) -> Option<Pol> {
    r.combined.map(|c| {
        Pol::new(
            c.q.value,
            c.u.value,
            c.adopted_sigma_q(),
            c.adopted_sigma_u(),
            c.q.sigma,
            c.u.sigma,
        )
    })
}

/// (q, u) of one target's frames, in the instrument frame and on the sky.
fn target_result(
    name: String,
    filter: String,
    frames: Vec<FrameResult>,
    zero_point: f64,
    sigma_zero_point: f64,
    tolerance: f64,
) -> TargetResult {
    let pf: Vec<PlateFrame> = frames
        .iter()
        .map(|f| PlateFrame {
            plate_deg: f.plate_deg,
            o: f.o,
            sigma_o: f.sigma_o,
            e: f.e,
            sigma_e: f.sigma_e,
        })
        .collect();
    let offsets: Vec<f64> = frames.iter().map(|f| f.sky_offset_deg).collect();
    let inst = hwp::reduce(&pf, 0.0, tolerance, CycleMethod::DoubleDifference);
    let sky = hwp::reduce_on_sky(&pf, &offsets, zero_point, tolerance, CycleMethod::DoubleDifference);
    let pol_of = |c: &hwp::Cycle| {
        let (sq, su) = (c.fit.var_q.sqrt(), c.fit.var_u.sqrt());
        Pol::new(c.fit.q, c.fit.u, sq, su, sq, su)
    };
    let cycles: Vec<CycleResult> = inst
        .cycles
        .iter()
        .zip(&sky.cycles)
        .map(|(a, b)| CycleResult {
            frames: a.frames.iter().map(|&i| frames[i].file.clone()).collect(),
            instrument: pol_of(a),
            sky: pol_of(b),
        })
        .collect();
    // With the field turning (pupil tracking) the star's (q, u) turns in the instrument frame
    // from cycle to cycle: the cycles are compared on the sky, where it stands still.
    let turning = offsets.iter().any(|&d| d != offsets[0]);
    let cycle_agreement = (cycles.len() >= 2).then(|| {
        let frame = |c: &CycleResult| if turning { c.sky } else { c.instrument };
        let diff = |get: &dyn Fn(&Pol) -> (f64, f64)| -> Vec<f64> {
            cycles
                .windows(2)
                .map(|w| {
                    let ((a, sa), (b, sb)) = (get(&frame(&w[0])), get(&frame(&w[1])));
                    (b - a) / sa.hypot(sb)
                })
                .collect()
        };
        let cb = if turning { sky.combined } else { inst.combined }.expect("cycles combined");
        CycleAgreement {
            q_difference_sigma: diff(&|p: &Pol| (p.q, p.sigma_q)),
            u_difference_sigma: diff(&|p: &Pol| (p.u, p.sigma_u)),
            chi2_q: cb.q.chi2,
            chi2_u: cb.u.chi2,
            dof: cycles.len() - 1,
        }
    });
    TargetResult {
        name,
        filter,
        mjd: frames.iter().map(|f| f.mjd).sum::<f64>() / frames.len().max(1) as f64,
        instrument: combined(&inst),
        sky: combined(&sky),
        sigma_angle_zero_point_deg: sigma_zero_point,
        cycles,
        cycle_agreement,
        least_squares_instrument: least_squares(&inst),
        least_squares_sky: least_squares(&sky),
        left_out: inst.left_out.iter().map(|&i| frames[i].file.clone()).collect(),
        frames,
    }
}
