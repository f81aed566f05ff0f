//! The catalog's flags as a type: a [`FlagCode`] (what happened) and an optional detail
//! (where, by how much). Each code carries its name as the catalog writes it and a
//! sentence in plain words, so the report and the night log explain a flag from the code
//! that wrote it, and readers match codes instead of strings.
//!
//! In the JSON a flag is one string, exactly as earlier builds wrote it: mostly
//! `name` or `name: detail` (`p_disagrees_with_table: 4.2 sigma`); some target-level flags
//! are sentences whose fixed words identify them (`primary not found in FILE`). A string
//! this build does not recognise (from an older or newer catalog) is kept verbatim
//! ([`FlagCode::Unknown`]) and written back unchanged: reading and writing a catalog never
//! changes its flags.
use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// How a code's detail joins its name in the catalog's string.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Form {
    /// `name`, or `name: detail`.
    Named,
    /// `name detail` (a sentence that starts with the name), or `name` alone.
    Leading,
    /// `name detail` where the detail holds these words (the name alone is too common).
    LeadingWith(&'static str),
    /// `detail name` (a sentence that ends with the name).
    Trailing,
}

macro_rules! flag_codes {
    ($($(#[doc = $doc:literal])* $code:ident = $name:literal, $form:expr, $why:literal;)*) => {
        /// Every flag this build writes, target, component and standard level
        /// (docs/catalog-schema.md lists them), and [`FlagCode::Unknown`] for the others.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum FlagCode {
            $($(#[doc = $doc])* $code,)*
            /// A flag this build does not know (read from another build's catalog): its
            /// whole text is the detail, written back as read.
            Unknown,
        }

        impl FlagCode {
            /// Every known code (not [`FlagCode::Unknown`]), in the order of the schema.
            pub const ALL: &'static [FlagCode] = &[$(FlagCode::$code,)*];

            /// The code's name as the catalog writes it (empty for [`FlagCode::Unknown`]).
            pub const fn name(self) -> &'static str {
                match self {
                    $(FlagCode::$code => $name,)*
                    FlagCode::Unknown => "",
                }
            }

            /// The flag in plain words: what happened and what it means for the values.
            pub const fn explanation(self) -> &'static str {
                match self {
                    $(FlagCode::$code => $why,)*
                    FlagCode::Unknown => "A flag this build does not know: shown as written.",
                }
            }

            const fn form(self) -> Form {
                match self {
                    $(FlagCode::$code => $form,)*
                    FlagCode::Unknown => Form::Named,
                }
            }
        }
    };
}

use Form::{Leading, LeadingWith, Named, Trailing};

flag_codes! {
    // Component level: calibration.
    /// Two orientations and no instrumental calibration.
    Uncalibrated = "uncalibrated", Named,
        "No instrumental calibration: q and u carry the instrumental offset and the angles the profile's zero-point.";
    /// The night's standards could not separate c from theta0.
    CalibrationIncomplete = "calibration_incomplete", Named,
        "The night's standards could not separate the offset c from the zero-point θ₀: θ₀ and the parity are the profile's.";
    /// No polarized standard in the filter: theta0 is the profile's.
    ZeroPointFromProfile = "zero_point_from_profile", Named,
        "No polarized standard in this filter: the angle zero-point θ₀ is the profile's, and its uncertainty is carried in γ's error (not in Δγ's).";
    /// `--calib` has no offset for the component's filter.
    CalibrationLacksFilter = "calibration_lacks_filter", Named,
        "The calibration given has no offset for this filter: q and u uncorrected.";
    /// The telescope's own polarization was not removed.
    TelescopeUncorrected = "telescope_polarization_uncorrected", Named,
        "The telescope's own polarization was not removed (it turns with the parallactic angle).";
    /// The telescope's polarization was removed at the value fitted with the mirror's prior.
    TelescopeFromPrior = "telescope_polarization_from_prior", Named,
        "The night's standards did not separate the telescope's polarization: it was removed at the value fitted with the mirror's Fresnel prior, whose width is carried in the errors.";
    /// The telescope's polarization was neither removed nor carried in the error.
    TelescopeUnaccounted = "telescope_polarization_unaccounted", Named,
        "The telescope's polarization was neither removed nor carried in the error (the profile gives no mirror index for this filter): never passes the cut unless uncalibrated values are allowed.";
    /// The chosen Stokes method could not be applied.
    StokesMethodFailed = "stokes_method_failed", Named,
        "The chosen Stokes method could not be applied; another one was used (or none).";
    // Component level: dithers dropped (also a dither's `reason` in `dropped_dithers`).
    /// Bad pixels in a dither's aperture.
    BadPixels = "bad_pixels", Named,
        "A dither was dropped: bad pixels in the aperture.";
    /// A cosmic ray in a dither's aperture.
    CosmicRay = "cosmic_ray", Named,
        "A dither was dropped: a cosmic ray in the aperture.";
    /// Saturated pixels in a dither's aperture.
    Saturated = "saturated", Named,
        "A dither was dropped: saturated pixels.";
    /// A dither's aperture runs off the image.
    Truncated = "truncated", Named,
        "A dither was dropped: the aperture runs off the image.";
    /// Pixels in the detector's non-linear range.
    Nonlinear = "nonlinear", Named,
        "Some pixels are in the detector's non-linear range (reported only).";
    /// A dither's frame has no usable parallactic angle.
    NoParallacticAngle = "no_parallactic_angle", Named,
        "A dither was dropped: its frame has no usable parallactic angle, so the telescope's polarization could not be removed from it.";
    /// The primary star was not found in a dither's frame.
    PrimaryNotFound = "primary_not_found", Named,
        "A dither was dropped: the primary star was not found in its frame.";
    /// A dither's photometry gave no value.
    PhotometryFailed = "photometry failed", Named,
        "A dither was dropped: its photometry failed.";
    // Component level: reported only, or refused by the cut.
    /// The two stars' apertures overlap.
    CompanionOverlap = "companion_overlap", Named,
        "The two stars' apertures overlap (reported only).";
    /// The background annulus holds another source's light.
    AnnulusContaminated = "annulus_contaminated", Named,
        "The background annulus holds light of another source (reported only).";
    /// Every dither of an orientation was flagged and all were used.
    UsedFlaggedDithers = "used_flagged_dithers", Named,
        "Every dither of an orientation was flagged and all were used: never passes the cut.";
    /// Which star is A is not established (component and target level).
    AbIdentityUnverified = "ab_identity_unverified", Named,
        "Which star is A is not established at some orientation: q and u may mix the two; never passes the cut.";
    /// A dither was clipped from an orientation's combined F.
    DitherClipped = "dither_clipped", Named,
        "A dither was clipped from the combined F of an orientation.";
    /// The dithers scatter more than their errors.
    ExcessDitherScatter = "excess_dither_scatter", Named,
        "The dithers scatter more than their errors: the errors were inflated.";
    /// P above 1.
    PAboveOne = "p_above_one", Named,
        "The degree of polarization came out above 100 %: impossible for light, so a calibration or measurement went wrong; never passes the cut.";
    /// P/sigma_P at or below the cut.
    LowSnr = "low_snr", Named,
        "P/σ ≤ 3: below the detection cut.";
    /// The orientations do not constrain q and u.
    UndefinedPolarization = "undefined_polarization", Named,
        "The orientations measured do not constrain q and u: no polarization.";
    // Field stars (a field star's `flags`, with the component flags above).
    /// A field star beyond the strips or the detector in some dithers.
    OutsideField = "outside_field", Named,
        "A field star fell beyond the strips or the detector in some dithers (jitter, rotation between orientations): those dithers have no value.";
    /// A field star's aperture crosses a strip or detector edge in some dithers.
    StripEdge = "strip_edge", Named,
        "A field star's aperture crosses a strip or detector edge in some dithers: those dithers were dropped (not usable when every dither of an orientation was).";
    /// Another source lies within 3 FWHM of a field star.
    Blended = "blended", Named,
        "Another source (a field star or a component of the binary) lies within 3 FWHM of this field star: apertures and wings overlap; not usable.";
    /// A field star's mean flux is measured at S/N below 10.
    Faint = "faint", Named,
        "The field star's mean o+e flux has S/N below 10: not usable.";
    // Target level: the companion and the labels A and B.
    /// The companion was not found.
    CompanionNotFound = "companion_not_found", Named,
        "The companion was not found: only the primary was measured.";
    /// The companion candidate was rejected.
    CompanionRejected = "companion_rejected", Named,
        "The companion candidate was rejected (not significant at every orientation, or positions disagree).";
    /// The companion's position scatters between orientations.
    CompanionPositionScatter = "companion_position_scatter", Named,
        "The companion's position scatters between orientations.";
    /// Another source of comparable flux within the companion search radius.
    CompanionCandidates = "companion_candidates", Named,
        "Another source of comparable or greater flux lies within the companion search radius: B is the candidate least likely to be a chance alignment (the fewest field stars expected at least as bright within its separation); the other, named by its separation and PA from A, is not B (a field star when field stars are measured).";
    /// The star found at an orientation is B by its flux.
    AbIdentityFromFlux = "ab_identity_from_flux", Named,
        "The companion was not found at an orientation; the star found there is B by its flux.";
    /// A placed by the other orientations' geometry.
    AbIdentityFromGeometry = "ab_identity_from_geometry", Named,
        "The companion was not significant at an orientation; A was placed by the other orientations' geometry.";
    /// The two stars have nearly equal fluxes.
    AbNearEqualFlux = "ab_near_equal_flux", Named,
        "The two stars have nearly equal fluxes: which one is called A is a convention.";
    /// The labels A and B were exchanged.
    AbRelabelledByFlux = "ab_relabelled_by_flux", Named,
        "The labels A and B were exchanged: A is the brighter star.";
    /// The e-o beam offset differs from the profile's.
    EoOffsetDiffersFromProfile = "eo_offset_differs_from_profile", Named,
        "The e-o beam offset measured differs from the profile's.";
    /// A source brighter than the target in its strip, away from the pointing.
    BrighterSourceInStrip = "brighter_source_in_strip", Named,
        "A source brighter than the target lies in its strip away from the pointing: the target is the source at the pointing, the brighter one was left alone.";
    /// The primary star was not found in a frame (the frame is named).
    PrimaryNotFoundIn = "primary not found in", Leading,
        "The primary star was not found in this frame: its dithers were dropped.";
    // Target level: the interstellar foreground.
    /// Too few usable field stars for the foreground estimate.
    ForegroundTooFewFieldStars = "foreground_too_few_field_stars", Named,
        "Too few usable field stars to estimate the interstellar foreground: no foreground is subtracted.";
    // Target level: frames, orientations and the sequence.
    /// The exposures of the sequence differ in DIT or NDIT.
    MixedExposure = "mixed_exposure", Named,
        "The exposures of the sequence differ in DIT or NDIT (normalised, not refused).";
    /// A frame whose sky level cannot be used was dropped.
    DitherDropped = "dither of POSANG", Leading,
        "A frame whose sky level cannot be used was left out; the other dithers of its orientation carry on.";
    /// An orientation was dropped (too few dithers, its mask or its sky failed).
    OrientationDropped = "orientation POSANG", Leading,
        "An orientation was left out: too few readable dithers for the sky, or its sky subtraction failed.";
    /// No flat for an orientation.
    NoFlat = "no flat for POSANG", Leading,
        "No flat matches this orientation and filter: it was reduced without a flat.";
    /// The flat does not fit an orientation's frames.
    FlatDoesNotFit = "POSANG", LeadingWith(" not flat-fielded: "),
        "The flat does not fit this orientation's frames: it was reduced without a flat.";
    /// The night's bad-pixel mask does not fit the frames.
    NightMaskUnfit = "night bad-pixel mask is", Leading,
        "The night's bad-pixel mask does not fit the frames: defects were detected on this sequence instead.";
    /// The detection of bad pixels on the sequence failed.
    BadPixelDetectionFailed = "bad-pixel detection failed", Named,
        "Bad pixels could not be detected on this sequence: reduced without a bad-pixel mask of its own.";
    /// A frame's parallactic angle could not be used.
    ParallacticAngleNotUsed = "parallactic angle not used", Named,
        "A frame's parallactic angle is missing or unreadable: its dithers cannot have the telescope's polarization removed.";
    /// The directory for the intermediate frames could not be created.
    IntermediateDirNotCreated = "could not create", Leading,
        "The directory for the intermediate frames could not be created (the values are unaffected).";
    /// An intermediate frame could not be written.
    IntermediateNotWritten = "could not write intermediate", Leading,
        "An intermediate frame could not be written (the values are unaffected).";
    /// A FITS product was not written (`--fits-products`).
    FitsProductNotWritten = "fits_product_not_written", Named,
        "A FITS product of this target could not be written (the values are unaffected).";
    /// Every dither of an orientation at one position.
    StationaryDithers = "all dithers at POSANG", Leading,
        "Every dither of an orientation sits at one position: the sky median contains the star.";
    /// An orientation with a single dither.
    OneDither = "only", LeadingWith(" dither at POSANG "),
        "An orientation has a single dither: its sky cannot come from the data itself.";
    /// The orientations have different numbers of dithers.
    UnequalDithers = "unequal dithers per orientation", Named,
        "The orientations have different numbers of dithers.";
    /// Fewer exposures than the template announced.
    MissingExposures = "exposures of the template present (TPL NEXP)", Trailing,
        "Some exposures of the template are missing.";
    /// The frames' dates span more than a template can.
    MjdSpread = "MJD-OBS of the frames spans", Leading,
        "The frames' dates span more than one template can: some dates are wrong.";
    /// The frames of the sequence have different filters.
    MixedFilters = "mixed filters", Leading,
        "The frames of the sequence were taken through different filters.";
    // Standards.
    /// A standard not in the standards table.
    NotInStandardsTable = "not_in_standards_table", Named,
        "This standard star is not in the standards table.";
    /// The table has no values for the standard's filter.
    NoTableValuesForFilter = "no_table_values_for_filter", Named,
        "The standards table has no values for this filter.";
    /// The standard's reduction failed.
    Failed = "failed", Named,
        "The reduction failed.";
    /// A polarized standard's P disagrees with the table.
    PDisagreesWithTable = "p_disagrees_with_table", Named,
        "The measured P disagrees with the table by more than 3σ.";
    /// An unpolarized standard's (q, u) is not consistent with zero.
    QuDisagreesWithTable = "qu_disagrees_with_table", Named,
        "The measured (q, u) of an unpolarized standard is not consistent with zero.";
}

impl FlagCode {
    /// The detail of `text` when it is a flag of this code (`Some(None)`: the code alone).
    fn detail_of(self, text: &str) -> Option<Option<&str>> {
        let (name, form) = (self.name(), self.form());
        if text == name && !matches!(form, LeadingWith(_)) {
            return Some(None);
        }
        match form {
            Named => text.strip_prefix(name)?.strip_prefix(": ").map(Some),
            Leading => text.strip_prefix(name)?.strip_prefix(' ').map(Some),
            LeadingWith(words) => {
                let detail = text.strip_prefix(name)?.strip_prefix(' ')?;
                detail.contains(words).then_some(Some(detail))
            }
            Trailing => text.strip_suffix(name)?.strip_suffix(' ').map(Some),
        }
    }
}

/// One flag: its code and the detail written after (or around) the code's name.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct Flag {
    /// What happened.
    pub code: FlagCode,
    /// Where, why, by how much (for [`FlagCode::Unknown`]: the whole text as read).
    pub detail: Option<String>,
}

impl Flag {
    /// The flag `code` alone.
    pub fn new(code: FlagCode) -> Flag {
        Flag { code, detail: None }
    }

    /// The flag `code` with its detail.
    pub fn with_detail(code: FlagCode, detail: impl Into<String>) -> Flag {
        Flag {
            code,
            detail: Some(detail.into()),
        }
    }

    /// The flag a catalog string stands for: the known code whose name it carries (the
    /// longest, should two fit), else [`FlagCode::Unknown`] with the string as it is.
    pub fn parse(text: &str) -> Flag {
        FlagCode::ALL
            .iter()
            .filter_map(|&code| code.detail_of(text).map(|d| (code, d)))
            .max_by_key(|(code, _)| code.name().len())
            .map_or_else(
                || Flag::with_detail(FlagCode::Unknown, text),
                |(code, detail)| Flag {
                    code,
                    detail: detail.map(str::to_string),
                },
            )
    }

    /// Whether this flag is of `code`.
    pub fn is(&self, code: FlagCode) -> bool {
        self.code == code
    }

    /// Whether this is the flag of a Stokes method that fell back to a solve without offset
    /// correction (`stokes_method_failed: ...; fell back to ... (uncalibrated)`): such a value
    /// never passes the cut.
    pub fn is_uncalibrated_fallback(&self) -> bool {
        self.is(FlagCode::StokesMethodFailed)
            && self
                .detail
                .as_deref()
                .is_some_and(|d| d.ends_with(crate::stokes::calibration::FALLBACK_UNCALIBRATED))
    }

    /// The name a reader looks for: a named flag's name (`p_disagrees_with_table`), the
    /// whole text of a sentence-like or unknown flag.
    pub fn label(&self) -> String {
        match self.code.form() {
            Named if self.code != FlagCode::Unknown => self.code.name().to_string(),
            _ => self.to_string(),
        }
    }

    /// The flag in plain words, with a named flag's detail in parentheses; `None` for a
    /// flag this build does not know (shown as it is).
    pub fn explain(&self) -> Option<String> {
        let sentence = self.code.explanation();
        match (self.code, self.code.form(), self.detail.as_deref().map(str::trim)) {
            (FlagCode::Unknown, ..) => None,
            (_, Named, Some(d)) if !d.is_empty() => Some(format!("{sentence} ({d})")),
            _ => Some(sentence.to_string()),
        }
    }
}

/// Whether `flags` hold one of `code`.
pub fn has(flags: &[Flag], code: FlagCode) -> bool {
    flags.iter().any(|f| f.is(code))
}

/// The flags as the catalog writes them, joined by `sep` (CSV and FITS columns, tables).
pub fn join(flags: &[Flag], sep: &str) -> String {
    flags.iter().map(Flag::to_string).collect::<Vec<_>>().join(sep)
}

impl fmt::Display for Flag {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (name, detail) = (self.code.name(), self.detail.as_deref());
        match (self.code.form(), detail) {
            (_, None) => f.write_str(name),
            (_, Some(d)) if self.code == FlagCode::Unknown => f.write_str(d),
            (Named, Some(d)) => write!(f, "{name}: {d}"),
            (Leading | LeadingWith(_), Some(d)) => write!(f, "{name} {d}"),
            (Trailing, Some(d)) => write!(f, "{d} {name}"),
        }
    }
}

/// Test messages show the flag as the catalog writes it.
impl fmt::Debug for Flag {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.to_string())
    }
}

impl FromStr for Flag {
    type Err = std::convert::Infallible;

    fn from_str(s: &str) -> Result<Flag, Self::Err> {
        Ok(Flag::parse(s))
    }
}

impl From<FlagCode> for Flag {
    fn from(code: FlagCode) -> Flag {
        Flag::new(code)
    }
}

impl Serialize for Flag {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Flag {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Flag, D::Error> {
        let text = String::deserialize(deserializer)?;
        Ok(Flag::parse(&text))
    }
}

#[cfg(test)]
mod tests;
