//! Scene validation: values that would make a meaningless simulation are refused with
//! the section, key and value.
use super::effects::mjd_from_date_time;
use super::scene::{PsfKind, Scene};
use super::schedule::TargetPointing;
use crate::error::Error;

impl Scene {
    /// Check values that would make a meaningless simulation.
    pub fn validate(&self) -> crate::error::Result<()> {
        self.validate_counts_and_names()?;
        let o = &self.observation;
        if o.ndit == 0 || !(o.dit_s > 0.0) {
            return Err(invalid(format!(
                "observation: ndit = {} and dit_s = {} must be > 0",
                o.ndit, o.dit_s
            )));
        }
        if o.bitpix != -32 && o.bitpix != 16 {
            return Err(invalid(format!(
                "observation.bitpix = {} (expected -32 or 16)",
                o.bitpix
            )));
        }
        if !(o.overhead_s >= 0.0) {
            return Err(invalid(format!(
                "observation.overhead_s = {} must be >= 0",
                o.overhead_s
            )));
        }
        for (kind, name, p) in self
            .binary
            .iter()
            .map(|b| ("binary", &b.name, b.pointing()))
            .chain(self.standard.iter().map(|s| ("standard", &s.name, s.pointing())))
        {
            check_pointing(kind, name, &p, &o.date)?;
        }
        if let Some(t) = &self.telescope_polarization {
            if !(0.0..1.0).contains(&t.p_tel) || !t.psi_tel_deg.is_finite() {
                return Err(invalid(format!(
                    "telescope_polarization: p_tel = {} must be in [0, 1) and psi_tel_deg = {} finite",
                    t.p_tel, t.psi_tel_deg
                )));
            }
        }
        for b in &self.binary {
            for (what, v) in [("flux_a", b.flux_a), ("flux_b", b.flux_b)] {
                if !(v >= 0.0) {
                    return Err(invalid(format!("binary '{}': {what} = {v} must be >= 0", b.name)));
                }
            }
            for (what, v) in [("p_a", b.p_a), ("p_b", b.p_b)] {
                if !(0.0..=1.0).contains(&v) {
                    return Err(invalid(format!("binary '{}': {what} = {v} must be in [0, 1]", b.name)));
                }
            }
            if !(b.separation_arcsec >= 0.0) {
                return Err(invalid(format!(
                    "binary '{}': separation_arcsec = {}",
                    b.name, b.separation_arcsec
                )));
            }
        }
        for st in &self.standard {
            if !(st.flux >= 0.0) || !(0.0..1.0).contains(&st.p) {
                return Err(invalid(format!(
                    "standard '{}': flux = {} must be >= 0 and p = {} in [0, 1)",
                    st.name, st.flux, st.p
                )));
            }
        }
        if let Some(a) = &self.analyzer_angle {
            if a.parity != 1 && a.parity != -1 {
                return Err(invalid(format!(
                    "analyzer_angle.parity = {} must be +1 or -1",
                    a.parity
                )));
            }
        }
        if let Some(p) = &self.psf {
            if !(p.fwhm_arcsec > 0.0) || (p.kind == PsfKind::Moffat && !(p.beta > 1.0)) {
                return Err(invalid(format!(
                    "psf: fwhm_arcsec = {} must be > 0 and beta = {} > 1",
                    p.fwhm_arcsec, p.beta
                )));
            }
            if !(0.0..1.0).contains(&p.fwhm_spread_frac) {
                return Err(invalid(format!(
                    "psf: fwhm_spread_frac = {} must be in [0, 1)",
                    p.fwhm_spread_frac
                )));
            }
            if let Some([lo, hi]) = p.beta_range {
                if !(lo > 1.0 && hi >= lo) {
                    return Err(invalid(format!(
                        "psf: beta_range = [{lo}, {hi}] must have 1 < lo <= hi"
                    )));
                }
            }
            if let Some([lo, hi]) = p.axis_ratio_range {
                if !(lo > 0.0 && lo <= hi && hi <= 1.0) || p.kind != PsfKind::Moffat {
                    return Err(invalid(format!(
                        "psf: axis_ratio_range = [{lo}, {hi}] needs 0 < lo <= hi <= 1 and kind = \"moffat\""
                    )));
                }
            }
        }
        if let Some(d) = &self.dome_flats {
            if d.frames_on == 0 || d.frames_off == 0 || d.ndit == 0 || !(d.dit_s > 0.0) || !(d.lamp_adu > 0.0) {
                return Err(invalid(format!(
                    "dome_flats: frames_on = {}, frames_off = {}, ndit = {}, dit_s = {}, lamp_adu = {} must all be > 0",
                    d.frames_on, d.frames_off, d.ndit, d.dit_s, d.lamp_adu
                )));
            }
            if !(0.0..1.0).contains(&d.lamp_p) {
                return Err(invalid(format!("dome_flats: lamp_p = {} must be in [0, 1)", d.lamp_p)));
            }
        }
        // When and where every sequence is observed: fixed starts that overlap and targets
        // below the horizon are refused here, so that the error names the scene file.
        self.plan().map(|_| ())
    }
}

/// The pointing keys of one target: RA in [0, 360), Dec in [-90, 90], hour angle in
/// [-12, 12] h and not together with RA, a start time that parses.
fn check_pointing(kind: &str, name: &str, p: &TargetPointing, date: &str) -> crate::error::Result<()> {
    let bad = |key: &str, v: String, want: &str| Err(invalid(format!("{kind} '{name}': {key} = {v} {want}")));
    if let Some(ra) = p.ra_deg.filter(|ra| !(0.0..360.0).contains(ra)) {
        return bad("ra_deg", ra.to_string(), "must be in [0, 360)");
    }
    if let Some(dec) = p.dec_deg.filter(|d| !(-90.0..=90.0).contains(d)) {
        return bad("dec_deg", dec.to_string(), "must be in [-90, 90]");
    }
    if let Some(h) = p.hour_angle_h {
        if !(-12.0..=12.0).contains(&h) {
            return bad("hour_angle_h", h.to_string(), "must be in [-12, 12]");
        }
        if p.ra_deg.is_some() {
            return bad(
                "hour_angle_h",
                h.to_string(),
                "given together with ra_deg: give one of the two",
            );
        }
    }
    if let Some(ut) = p.start_ut {
        if mjd_from_date_time(date, ut).is_none() {
            return bad("start_ut", format!("'{ut}'"), "not understood (HH:MM:SS)");
        }
    }
    Ok(())
}

/// Most dithers per orientation of a simulated sequence.
pub const MAX_DITHERS: usize = 100;
/// Most orientations (rotator angles) of a simulated sequence.
pub const MAX_ORIENTATIONS: usize = 36;
/// Most binaries and standards of one scene, each.
pub const MAX_TARGETS: usize = 10_000;
/// Most lamp-on and lamp-off dome-flat frames per rotator angle, each.
pub const MAX_DOME_FRAMES: usize = 100;
/// Longest scene or target name, characters.
pub const MAX_NAME_CHARS: usize = 64;

impl Scene {
    /// The counts bounded (a `dithers = 100000` would write terabytes) and the names usable:
    /// not empty, at most [`MAX_NAME_CHARS`], and distinct once reduced to the file-name
    /// slugs of the frames (two targets `A/B` and `A_B` would write the same files).
    fn validate_counts_and_names(&self) -> crate::error::Result<()> {
        let o = &self.observation;
        let count = |key: &str, n: usize, max: usize| {
            if (1..=max).contains(&n) {
                Ok(())
            } else {
                Err(invalid(format!("{key} = {n} must be in 1..={max}")))
            }
        };
        count(
            "observation.orientations_deg (count)",
            o.orientations_deg.len(),
            MAX_ORIENTATIONS,
        )?;
        count("observation.dithers", o.dithers, MAX_DITHERS)?;
        for (key, n) in [
            ("binary (count)", self.binary.len()),
            ("standard (count)", self.standard.len()),
        ] {
            if n > MAX_TARGETS {
                return Err(invalid(format!("{key} = {n} must be at most {MAX_TARGETS}")));
            }
        }
        if let Some(d) = &self.dome_flats {
            count("dome_flats.frames_on", d.frames_on, MAX_DOME_FRAMES)?;
            count("dome_flats.frames_off", d.frames_off, MAX_DOME_FRAMES)?;
        }
        let names = std::iter::once(("name", &self.name))
            .chain(self.binary.iter().map(|b| ("binary name", &b.name)))
            .chain(self.standard.iter().map(|s| ("standard name", &s.name)));
        let mut slugs = std::collections::HashMap::new();
        for (i, (key, name)) in names.enumerate() {
            let n = name.chars().count();
            if n == 0 || n > MAX_NAME_CHARS {
                return Err(invalid(format!(
                    "{key} {name:?} is {n} characters long: must be 1..={MAX_NAME_CHARS}"
                )));
            }
            if i == 0 {
                continue;
            }
            if let Some(prev) = slugs.insert(super::file_slug(name), name) {
                return Err(invalid(format!(
                    "targets {prev:?} and {name:?} would write the same frame files ({}): rename one",
                    super::file_slug(name)
                )));
            }
        }
        Ok(())
    }
}

/// A scene error without its origin (added by [`Scene::from_toml`]).
fn invalid(reason: String) -> Error {
    Error::Scene {
        origin: "scene".into(),
        reason,
    }
}
