//! Per-source photometry flags (bit set, photutils style: problems are flags, not errors).

use serde::{Deserialize, Serialize};

/// Bit flags of one photometric measurement. The names (see [`Flags::names`]) are stable and
/// are what the catalog writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Flags(pub u32);

impl Flags {
    /// No problem.
    pub const NONE: Flags = Flags(0);
    /// The aperture extends off the image or off the given valid region (e.g. the beam strip).
    pub const TRUNCATED: Flags = Flags(1 << 0);
    /// Masked or non-finite pixels inside the aperture (see `ApertureSum::masked_area`).
    pub const BAD_PIXELS: Flags = Flags(1 << 1);
    /// A valid pixel inside the aperture is at or above the saturation level.
    pub const SATURATED: Flags = Flags(1 << 2);
    /// Another listed source lies closer than `r_ap + companion_radius`.
    pub const COMPANION_OVERLAP: Flags = Flags(1 << 3);
    /// Signal-to-noise below the threshold, or undefined.
    pub const LOW_SNR: Flags = Flags(1 << 4);
    /// The annulus background is doubtful: too few valid pixels, no estimate, or another
    /// source inside the annulus that was not excluded.
    pub const ANNULUS_CONTAMINATED: Flags = Flags(1 << 5);

    /// Every flag with its stable name, in bit order.
    pub const ALL: [(Flags, &'static str); 6] = [
        (Flags::TRUNCATED, "truncated"),
        (Flags::BAD_PIXELS, "bad_pixels"),
        (Flags::SATURATED, "saturated"),
        (Flags::COMPANION_OVERLAP, "companion_overlap"),
        (Flags::LOW_SNR, "low_snr"),
        (Flags::ANNULUS_CONTAMINATED, "annulus_contaminated"),
    ];

    /// True if every bit of `other` is set.
    pub fn contains(self, other: Flags) -> bool {
        self.0 & other.0 == other.0
    }

    /// Sets the bits of `other`.
    pub fn insert(&mut self, other: Flags) {
        self.0 |= other.0;
    }

    /// True if no flag is set.
    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// Stable names of the set flags, in bit order.
    pub fn names(self) -> Vec<String> {
        Flags::ALL
            .iter()
            .filter(|(f, _)| self.contains(*f))
            .map(|(_, n)| n.to_string())
            .collect()
    }

    /// Inverse of [`Flags::names`]; None for an unknown name.
    pub fn from_names<S: AsRef<str>>(names: &[S]) -> Option<Flags> {
        let mut f = Flags::NONE;
        for n in names {
            let (bit, _) = Flags::ALL.iter().find(|(_, s)| *s == n.as_ref())?;
            f.insert(*bit);
        }
        Some(f)
    }
}

impl std::ops::BitOr for Flags {
    type Output = Flags;
    fn bitor(self, rhs: Flags) -> Flags {
        Flags(self.0 | rhs.0)
    }
}

impl std::ops::BitOrAssign for Flags {
    fn bitor_assign(&mut self, rhs: Flags) {
        self.0 |= rhs.0;
    }
}

/// Stable names of the set flags (same as [`Flags::names`]).
///
/// ```
/// use sofipol_pipeline::photometry::{flag_names, Flags};
/// assert_eq!(flag_names(Flags::TRUNCATED | Flags::LOW_SNR), vec!["truncated", "low_snr"]);
/// ```
pub fn flag_names(flags: Flags) -> Vec<String> {
    flags.names()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn photometry_flag_names_are_stable_and_round_trip() {
        let names: Vec<&str> = Flags::ALL.iter().map(|(_, n)| *n).collect();
        assert_eq!(
            names,
            [
                "truncated",
                "bad_pixels",
                "saturated",
                "companion_overlap",
                "low_snr",
                "annulus_contaminated"
            ]
        );
        let all = Flags(0b11_1111);
        assert_eq!(all.names().len(), 6);
        assert_eq!(Flags::from_names(&all.names()), Some(all));
        assert!(Flags::NONE.names().is_empty());
        assert_eq!(Flags::from_names(&["nope"]), None);
        assert_eq!(
            serde_json::to_string(&(Flags::SATURATED | Flags::TRUNCATED)).unwrap(),
            "5"
        );
    }
}
