//! The catalog's flags in words (docs/catalog-schema.md lists them): a flag is a
//! snake_case name, sometimes followed by `: detail` (`companion_rejected: ...`). A flag
//! this build does not know is shown as it is.

/// Sentences for the flags the pipeline writes, by the flag's name (the part before `:`).
const FLAGS: &[(&str, &str)] = &[
    ("uncalibrated", "No instrumental calibration: q and u carry the instrumental offset and the angles the profile's zero-point."),
    ("calibration_incomplete", "The night's standards could not separate the offset c from the zero-point θ₀: θ₀ and the parity are the profile's."),
    ("zero_point_from_profile", "No polarized standard in this filter: the angle zero-point θ₀ is the profile's, and its uncertainty is carried in γ's error (not in Δγ's)."),
    ("calibration_lacks_filter", "The calibration given has no offset for this filter: q and u uncorrected."),
    ("telescope_polarization_uncorrected", "The telescope's own polarization was not removed (it turns with the parallactic angle)."),
    ("stokes_method_failed", "The chosen Stokes method could not be applied; another one was used (or none)."),
    ("bad_pixels", "A dither was dropped: bad pixels in the aperture."),
    ("cosmic_ray", "A dither was dropped: a cosmic ray in the aperture."),
    ("saturated", "A dither was dropped: saturated pixels."),
    ("truncated", "A dither was dropped: the aperture runs off the image."),
    ("no_parallactic_angle", "A dither was dropped: its frame has no usable parallactic angle, so the telescope's polarization could not be removed from it."),
    ("primary_not_found", "A dither was dropped: the primary star was not found in its frame."),
    ("photometry failed", "A dither was dropped: its photometry failed."),
    ("nonlinear", "Some pixels are in the detector's non-linear range (reported only)."),
    ("companion_overlap", "The two stars' apertures overlap (reported only)."),
    ("annulus_contaminated", "The background annulus holds light of another source (reported only)."),
    ("used_flagged_dithers", "Every dither of an orientation was flagged and all were used: never passes the cut."),
    ("ab_identity_unverified", "Which star is A is not established at some orientation: q and u may mix the two; never passes the cut."),
    ("ab_identity_from_flux", "The companion was not found at an orientation; the star found there is B by its flux."),
    ("ab_identity_from_geometry", "The companion was not significant at an orientation; A was placed by the other orientations' geometry."),
    ("ab_near_equal_flux", "The two stars have nearly equal fluxes: which one is called A is a convention."),
    ("ab_relabelled_by_flux", "The labels A and B were exchanged: A is the brighter star."),
    ("dither_clipped", "A dither was clipped from the combined F of an orientation."),
    ("excess_dither_scatter", "The dithers scatter more than their errors: the errors were inflated."),
    ("p_above_one", "The degree of polarization came out above 100 %: impossible for light, so a calibration or measurement went wrong; never passes the cut."),
    ("low_snr", "P/σ ≤ 3: below the detection cut."),
    ("companion_not_found", "The companion was not found: only the primary was measured."),
    ("companion_rejected", "The companion candidate was rejected (not significant at every orientation, or positions disagree)."),
    ("companion_position_scatter", "The companion's position scatters between orientations."),
    ("eo_offset_differs_from_profile", "The e-o beam offset measured differs from the profile's."),
    ("mixed_exposure", "The exposures of the sequence differ in DIT or NDIT (normalised, not refused)."),
    ("not_in_standards_table", "This standard star is not in the standards table."),
    ("no_table_values_for_filter", "The standards table has no values for this filter."),
    ("p_disagrees_with_table", "The measured P disagrees with the table by more than 3σ."),
    ("qu_disagrees_with_table", "The measured (q, u) of an unpolarized standard is not consistent with zero."),
    ("failed", "The reduction failed."),
];

/// The flag's name: the part before the first `:`, trimmed.
pub fn flag_name(flag: &str) -> &str {
    flag.split(':').next().unwrap_or(flag).trim()
}

/// The sentence explaining `flag` with its detail (`name: detail` -> sentence + "(detail)");
/// `None` for a flag this build does not know (the caller shows it as it is).
pub fn explain(flag: &str) -> Option<String> {
    let name = flag_name(flag);
    let (_, sentence) = FLAGS.iter().find(|(k, _)| *k == name)?;
    let detail = flag.split_once(':').map(|(_, d)| d.trim()).filter(|d| !d.is_empty());
    Some(match detail {
        Some(d) => format!("{sentence} ({d})"),
        None => sentence.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_flags_read_as_sentences_with_their_detail_and_unknown_ones_are_left_alone() {
        assert_eq!(
            explain("companion_not_found").as_deref(),
            Some("The companion was not found: only the primary was measured.")
        );
        let s = explain("p_disagrees_with_table: 4.2 sigma").unwrap();
        assert!(
            s.starts_with("The measured P disagrees") && s.ends_with("(4.2 sigma)"),
            "{s}"
        );
        assert_eq!(explain("some_future_flag"), None);
        assert_eq!(
            flag_name("stokes_method_failed: x; fell back to y"),
            "stokes_method_failed"
        );
        // Every entry is a snake_case name (or the one historical phrase) and a sentence.
        for (k, v) in FLAGS {
            assert!(k.chars().all(|c| c.is_ascii_lowercase() || c == '_' || c == ' '), "{k}");
            assert!(v.ends_with('.'), "{k}: {v}");
        }
    }
}
