//! What was calibrated of one component, term by term, and how: the instrument's offset c,
//! the analyzer's zero-point theta0 and the telescope's own polarization. The state decides
//! the cut (a component passes only when every term that does not cancel for its Stokes
//! method is measured or carried in its error) and is written with the component.
use serde::{Deserialize, Serialize};

/// How one calibration term of a component was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TermSource {
    /// Measured from this night's standards and removed; its error carried.
    Measured,
    /// Measured on another night (`--calib`) and removed; its error carried.
    OtherNight,
    /// Fitted from the component's own orientations (the free-offset method).
    Fitted,
    /// Cancels in the component's Stokes method (c with balanced orientations).
    Cancelled,
    /// From the instrument profile: a value with its stated uncertainty, carried in the
    /// error (the zero-point of a filter without a polarized standard; the telescope's term
    /// where the standards did not separate it, fitted with the mirror's prior).
    Prior,
    /// Not removed; its expected size carried in the error (the telescope's term).
    Carried,
    /// Neither removed nor carried: the values are biased by an unknown amount.
    Missing,
}

impl TermSource {
    /// Whether the values are free of this term or carry it in their errors.
    pub fn accounted(self) -> bool {
        self != TermSource::Missing
    }

    /// The snake_case name (as written in the catalog).
    pub fn name(self) -> &'static str {
        match self {
            TermSource::Measured => "measured",
            TermSource::OtherNight => "other_night",
            TermSource::Fitted => "fitted",
            TermSource::Cancelled => "cancelled",
            TermSource::Prior => "prior",
            TermSource::Carried => "carried",
            TermSource::Missing => "missing",
        }
    }

    /// Measured on another night instead of this one (a calibration read with `--calib`).
    pub fn from_another_night(self) -> TermSource {
        match self {
            TermSource::Measured => TermSource::OtherNight,
            other => other,
        }
    }
}

/// One component's calibration, term by term.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CalibrationState {
    /// The instrument's offset c of F (beam ratio and instrumental polarization).
    pub offset: TermSource,
    /// The telescope's polarization, turning with the parallactic angle.
    pub telescope: TermSource,
    /// The analyzer's zero-point theta0 (turns the angles; P and Delta-gamma do not depend
    /// on it, so the cut does not either).
    pub zero_point: TermSource,
}

impl CalibrationState {
    /// The terms that bias P and are neither removed nor carried in the error: the reason
    /// the component cannot pass the cut. Empty when it may.
    pub fn missing_for_the_cut(&self) -> Vec<&'static str> {
        let mut out = Vec::new();
        if !self.offset.accounted() {
            out.push("offset c");
        }
        if !self.telescope.accounted() {
            out.push("telescope polarization");
        }
        out
    }

    /// Whether every term that biases P is removed or carried.
    pub fn complete_for_the_cut(&self) -> bool {
        self.missing_for_the_cut().is_empty()
    }

    /// The same state for a calibration read from another night.
    pub fn from_another_night(self) -> CalibrationState {
        CalibrationState {
            offset: self.offset.from_another_night(),
            telescope: self.telescope.from_another_night(),
            zero_point: self.zero_point.from_another_night(),
        }
    }

    /// "offset measured, zero-point prior, telescope carried".
    pub fn describe(&self) -> String {
        format!(
            "offset {}, zero-point {}, telescope {}",
            self.offset.name(),
            self.zero_point.name(),
            self.telescope.name()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_missing_offset_or_telescope_term_refuses_the_cut_and_names_round_trip() {
        let all = [
            TermSource::Measured,
            TermSource::OtherNight,
            TermSource::Fitted,
            TermSource::Cancelled,
            TermSource::Prior,
            TermSource::Carried,
            TermSource::Missing,
        ];
        for t in all {
            let json = serde_json::to_string(&t).unwrap();
            assert_eq!(json, format!("\"{}\"", t.name()));
            assert_eq!(serde_json::from_str::<TermSource>(&json).unwrap(), t);
        }
        let ok = CalibrationState {
            offset: TermSource::Cancelled,
            telescope: TermSource::Carried,
            zero_point: TermSource::Missing,
        };
        assert!(ok.complete_for_the_cut(), "theta0 does not enter P");
        let bad = CalibrationState {
            offset: TermSource::Missing,
            telescope: TermSource::Missing,
            ..ok
        };
        assert_eq!(bad.missing_for_the_cut(), vec!["offset c", "telescope polarization"]);
        let other = CalibrationState {
            offset: TermSource::Measured,
            telescope: TermSource::Prior,
            zero_point: TermSource::Measured,
        }
        .from_another_night();
        assert_eq!(other.offset, TermSource::OtherNight);
        assert_eq!(other.telescope, TermSource::Prior);
        assert_eq!(
            serde_json::to_string(&other).unwrap(),
            r#"{"offset":"other_night","telescope":"prior","zero_point":"other_night"}"#
        );
    }
}
