//! The summary of a frame's pixel values ([`PixelSummary`]: non-finite count, finite
//! minimum and maximum), computed in lanes of 16 ([`SummaryLanes`]) so that it vectorises:
//! the portable build [`summary_portable`] and the run-time chosen vector build
//! [`summary_of`] (the same numbers, test `the_summary_is_the_same_in_every_vector_build`).
/// How many pixel values are not finite (NaN, +-inf), and the smallest and largest finite
/// value (`+inf` and `-inf` when there is none): what the reduction checks of every frame
/// it reads. The night's frames get it from their conversion pass
/// ([`crate::fits::read_frame_rows_with_summary`]), other arrays from [`PixelSummary::of`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSummary {
    /// Values that are NaN or infinite.
    pub non_finite: usize,
    /// Smallest finite value.
    pub min: f32,
    /// Largest finite value.
    pub max: f32,
}

impl PixelSummary {
    /// The summary of `values`, with the widest vectors this CPU has (`summary_of`; the
    /// same numbers as the portable build `summary_portable`).
    pub fn of(values: &[f32]) -> Self {
        summary_of(values)
    }
}

/// The summary of `values` through [`SummaryLanes`]: the portable build, and the
/// definition [`summary_of`] must equal bit for bit.
#[inline(always)]
pub(crate) fn summary_portable(values: &[f32]) -> PixelSummary {
    let mut l = SummaryLanes::new();
    l.add(values);
    l.finish()
}

/// [`summary_portable`] compiled for AVX2 too, the build chosen at run time.
#[multiversion::multiversion(targets("x86_64+avx2"))]
pub(crate) fn summary_of(values: &[f32]) -> PixelSummary {
    summary_portable(values)
}

/// The running [`PixelSummary`] of values added slice by slice, in lanes of 16 (vector
/// code; a value's lane is its index mod 16 within its slice, which changes nothing:
/// counts, minima and maxima do not depend on the order).
pub(crate) struct SummaryLanes {
    bad: [u32; SummaryLanes::L],
    lo: [f32; SummaryLanes::L],
    hi: [f32; SummaryLanes::L],
    /// Values of slices' remainders (not a multiple of 16).
    rest: PixelSummary,
}

impl SummaryLanes {
    const L: usize = 16;

    pub(crate) fn new() -> Self {
        SummaryLanes {
            bad: [0; Self::L],
            lo: [f32::INFINITY; Self::L],
            hi: [f32::NEG_INFINITY; Self::L],
            rest: PixelSummary {
                non_finite: 0,
                min: f32::INFINITY,
                max: f32::NEG_INFINITY,
            },
        }
    }

    #[inline(always)]
    pub(crate) fn add(&mut self, values: &[f32]) {
        const L: usize = SummaryLanes::L;
        let mut c = values.chunks_exact(L);
        for ch in &mut c {
            // `i` is the vector lane: the indexed form is what the compiler vectorizes.
            #[allow(clippy::needless_range_loop)]
            for i in 0..L {
                let v = ch[i];
                // |v| < inf is false for NaN and +-inf.
                let fin = v.abs() < f32::INFINITY;
                self.bad[i] += u32::from(!fin);
                let w = if fin { v } else { self.lo[i] };
                self.lo[i] = if w < self.lo[i] { w } else { self.lo[i] };
                let w = if fin { v } else { self.hi[i] };
                self.hi[i] = if w > self.hi[i] { w } else { self.hi[i] };
            }
        }
        for &v in c.remainder() {
            if v.is_finite() {
                self.rest.min = self.rest.min.min(v);
                self.rest.max = self.rest.max.max(v);
            } else {
                self.rest.non_finite += 1;
            }
        }
    }

    pub(crate) fn finish(self) -> PixelSummary {
        PixelSummary {
            non_finite: self.rest.non_finite + self.bad.iter().map(|&b| b as usize).sum::<usize>(),
            min: self.lo.iter().copied().fold(self.rest.min, f32::min),
            max: self.hi.iter().copied().fold(self.rest.max, f32::max),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{rngs::Xoshiro256PlusPlus, RngExt, SeedableRng};

    /// Values that test the summary's edges: NaN (both signs, a payload), infinities,
    /// signed zeros, subnormals, extremes, ordinary values.
    const SPECIAL: [f32; 12] = [
        f32::NAN,
        -f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        0.0,
        -0.0,
        1e-45,
        -1e-45,
        f32::MAX,
        f32::MIN,
        1.0,
        -1.0,
    ];

    fn bits(s: PixelSummary) -> (usize, u32, u32) {
        (s.non_finite, s.min.to_bits(), s.max.to_bits())
    }

    /// The run-time chosen build against the portable build, bit for bit (the signs of a
    /// zero minimum or maximum included).
    fn check(values: &[f32]) {
        assert_eq!(
            bits(summary_of(values)),
            bits(summary_portable(values)),
            "{} values: {values:?}",
            values.len()
        );
    }

    /// Seeded random inputs of every length up to 70 (not multiples of the 16 lanes too)
    /// and a few long ones, mixing special values into ordinary ones.
    #[test]
    fn the_summary_is_the_same_in_every_vector_build() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(2024);
        check(&[]);
        for len in (0..=70).chain([255, 256, 257, 4099]) {
            for _ in 0..40 {
                let v: Vec<f32> = (0..len)
                    .map(|_| match rng.random_range(0..4) {
                        0 => SPECIAL[rng.random_range(0..SPECIAL.len())],
                        1 => f32::from_bits(rng.random()),
                        _ => rng.random_range(-1e4f32..1e4),
                    })
                    .collect();
                check(&v);
            }
        }
        // Only zeros of both signs: the sign of the extremes depends on the order of the
        // comparisons, which must be the portable build's.
        for len in [1, 15, 16, 17, 33, 64] {
            for _ in 0..40 {
                let v: Vec<f32> = (0..len).map(|_| if rng.random() { 0.0 } else { -0.0 }).collect();
                check(&v);
            }
        }
    }

    proptest! {
        /// Any bit patterns, any length.
        #[test]
        fn the_summary_of_any_bits_is_the_same_in_every_vector_build(
            words in proptest::collection::vec(any::<u32>(), 0..200)
        ) {
            let v: Vec<f32> = words.into_iter().map(f32::from_bits).collect();
            prop_assert_eq!(bits(summary_of(&v)), bits(summary_portable(&v)));
        }
    }
}
