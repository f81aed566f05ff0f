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
        self.validate_foreground()?;
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

/// Most Fourier modes per Stokes parameter of a foreground field.
pub const MAX_FOREGROUND_MODES: usize = 4096;
/// Most field stars expected per binary of a `field_population`.
pub const MAX_FIELD_STARS_EXPECTED: f64 = 2000.0;

impl Scene {
    /// The sections `foreground_field` and `field_population`.
    fn validate_foreground(&self) -> crate::error::Result<()> {
        if let Some(f) = &self.foreground_field {
            let bad = |key: &str, v: String, want: &str| Err(invalid(format!("foreground_field.{key} = {v} {want}")));
            if !(0.0..1.0).contains(&f.p) {
                return bad("p", f.p.to_string(), "must be in [0, 1)");
            }
            if !f.angle_deg.is_finite() {
                return bad("angle_deg", f.angle_deg.to_string(), "must be finite");
            }
            if !(0.0..0.5).contains(&f.rms) {
                return bad("rms", f.rms.to_string(), "must be in [0, 0.5)");
            }
            if !(f.coherence_arcsec > 0.0 && f.coherence_arcsec.is_finite()) {
                return bad(
                    "coherence_arcsec",
                    f.coherence_arcsec.to_string(),
                    "must be > 0 and finite",
                );
            }
            if let Some(a) = f.structure_exponent.filter(|a| !(*a > 0.0 && *a < 2.0)) {
                return bad("structure_exponent", a.to_string(), "must be in (0, 2)");
            }
            if !(1..=MAX_FOREGROUND_MODES).contains(&f.modes) {
                return bad(
                    "modes",
                    f.modes.to_string(),
                    &format!("must be in 1..={MAX_FOREGROUND_MODES}"),
                );
            }
        }
        let Some(c) = &self.field_population else {
            return Ok(());
        };
        let bad = |key: &str, v: String, want: &str| Err(invalid(format!("field_population.{key} = {v} {want}")));
        if self.observation.zero_point_mag.is_none() {
            return Err(invalid(
                "field_population needs observation.zero_point_mag (the magnitude of 1 ADU/s) to turn K magnitudes into fluxes".into(),
            ));
        }
        if !(c.density_per_arcmin2 >= 0.0 && c.density_per_arcmin2.is_finite()) {
            return bad(
                "density_per_arcmin2",
                c.density_per_arcmin2.to_string(),
                "must be >= 0 and finite",
            );
        }
        if !(c.slope_dex_per_mag > 0.0 && c.slope_dex_per_mag <= 2.0) {
            return bad(
                "slope_dex_per_mag",
                c.slope_dex_per_mag.to_string(),
                "must be in (0, 2]",
            );
        }
        if !(c.k_min_mag.is_finite() && c.k_max_mag.is_finite() && c.k_ref_mag.is_finite() && c.k_min_mag < c.k_max_mag)
        {
            return bad(
                "k_min_mag",
                format!(
                    "{} (k_max_mag = {}, k_ref_mag = {})",
                    c.k_min_mag, c.k_max_mag, c.k_ref_mag
                ),
                "must be finite and below k_max_mag",
            );
        }
        if !(0.0..=1.0).contains(&c.polarized_fraction) {
            return bad(
                "polarized_fraction",
                c.polarized_fraction.to_string(),
                "must be in [0, 1]",
            );
        }
        let [lo, hi] = c.p_polarized;
        if !(lo >= 0.0 && lo <= hi && hi < 1.0) {
            return bad("p_polarized", format!("[{lo}, {hi}]"), "must have 0 <= lo <= hi < 1");
        }
        if !(c.exclude_arcsec >= 0.0 && c.exclude_arcsec.is_finite()) {
            return bad(
                "exclude_arcsec",
                c.exclude_arcsec.to_string(),
                "must be >= 0 and finite",
            );
        }
        // Bounded like the other counts (the profile's strips are not known here: SOFI's
        // three o strips, 1024 x 501 px at 0.288"/px, are 11.8 arcmin^2; 30 covers any
        // profile of that detector size).
        let s = c.slope_dex_per_mag;
        let per_arcmin2 = c.density_per_arcmin2
            * (10f64.powf(s * (c.k_max_mag - c.k_ref_mag)) - 10f64.powf(s * (c.k_min_mag - c.k_ref_mag)));
        if !(per_arcmin2 * 30.0 <= MAX_FIELD_STARS_EXPECTED) {
            return bad(
                "density_per_arcmin2",
                c.density_per_arcmin2.to_string(),
                &format!(
                    "gives {per_arcmin2:.0} stars per arcmin^2 between k_min_mag and k_max_mag: at most {:.0} allowed",
                    MAX_FIELD_STARS_EXPECTED / 30.0
                ),
            );
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
