//! A small, fast, portable random-number generator for the Monte Carlo.
//!
//! Why our own: the Monte Carlo must give bit-identical results for a given seed on every
//! machine, every thread count and every future build. `rand`'s `SmallRng` is explicitly
//! not portable across versions, so the few lines of xoshiro256++ (Blackman & Vigna 2021,
//! "Scrambled linear pseudorandom number generators", ACM TOMS 47, 36) and splitmix64
//! (Steele, Lea & Flood 2014) are written here and frozen.
//!
//! Streams: the Monte Carlo splits its pairs into fixed-size chunks and gives chunk `i`
//! the generator [`Xoshiro256pp::for_stream`]`(seed, i)`, whose state is four splitmix64
//! outputs started from a mix of `seed` and `i`.

pub use crate::numeric::mix64;

/// Pairs per chunk (one RNG stream each) of the Monte Carlo and of the error convolution. Part of the definition of a seeded result:
/// changing it changes every seeded histogram.
pub const CHUNK_PAIRS: u64 = 1 << 16;

/// splitmix64: used only to expand a 64-bit seed into a xoshiro state.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// Generator started at `seed`.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// Next 64-bit output.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.state)
    }
}

/// xoshiro256++ 1.0: 256-bit state, period 2^256 - 1, passes BigCrush.
#[derive(Debug, Clone)]
pub struct Xoshiro256pp {
    s: [u64; 4],
}

/// 2^-53: turns the top 53 bits of a u64 into a double in [0, 1).
const TWO_POW_M53: f64 = 1.0 / (1u64 << 53) as f64;

impl Xoshiro256pp {
    /// Generator seeded from one 64-bit seed through splitmix64 (never the all-zero state).
    pub fn from_seed(seed: u64) -> Self {
        let mut sm = SplitMix64::new(seed);
        let s = [sm.next_u64(), sm.next_u64(), sm.next_u64(), sm.next_u64()];
        // splitmix64 outputs are a bijection of distinct states: four zeros cannot happen.
        Self { s }
    }

    /// Generator of stream `stream` (e.g. a chunk index) for the run seed `seed`.
    pub fn for_stream(seed: u64, stream: u64) -> Self {
        Self::from_seed(mix64(seed ^ 0x5851_F42D_4C95_7F2D) ^ mix64(stream.wrapping_add(0x1405_7B7E_F767_814F)))
    }

    /// Next 64-bit output.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform double in [0, 1) with 53 random bits.
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * TWO_POW_M53
    }

    /// Uniform double in [-1, 1) with 53 random bits.
    #[inline]
    pub fn uniform_pm1(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (2.0 * TWO_POW_M53) - 1.0
    }

    /// Uniform integer in [0, n) (Lemire's multiply-shift; bias < n / 2^64, negligible here).
    #[inline]
    pub fn below(&mut self, n: u64) -> u64 {
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// Isotropic unit vector on the sphere, Marsaglia (1972): no trigonometry.
    #[inline]
    pub fn unit_vector(&mut self) -> [f64; 3] {
        loop {
            let a = self.uniform_pm1();
            let b = self.uniform_pm1();
            let s = a * a + b * b;
            if s < 1.0 {
                let f = 2.0 * (1.0 - s).sqrt();
                return [a * f, b * f, 1.0 - 2.0 * s];
            }
        }
    }

    /// Uniform direction on the unit circle, returned as (cos, sin): a point uniform in the
    /// unit disk has a uniform polar angle phi, and (x^2 - y^2, 2xy)/r^2 = (cos 2phi, sin 2phi)
    /// is then uniform too. No trigonometry.
    #[inline]
    pub fn unit_circle(&mut self) -> (f64, f64) {
        loop {
            let a = self.uniform_pm1();
            let b = self.uniform_pm1();
            let s = a * a + b * b;
            if s < 1.0 && s > 1e-300 {
                let inv = 1.0 / s;
                return ((a * a - b * b) * inv, 2.0 * a * b * inv);
            }
        }
    }

    /// Two independent standard normal deviates (Marsaglia polar method).
    #[inline]
    pub fn normal_pair(&mut self) -> (f64, f64) {
        loop {
            let a = self.uniform_pm1();
            let b = self.uniform_pm1();
            let s = a * a + b * b;
            if s < 1.0 && s > 0.0 {
                let f = (-2.0 * s.ln() / s).sqrt();
                return (a * f, b * f);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xoshiro_matches_reference_vector() {
        // Reference: the C code of Blackman & Vigna (xoshiro256plusplus.c) started from the
        // state {1, 2, 3, 4}; the same vector is in the tests of the `rand_xoshiro` crate.
        let mut g = Xoshiro256pp { s: [1, 2, 3, 4] };
        let out: Vec<u64> = (0..4).map(|_| g.next_u64()).collect();
        assert_eq!(out, [41943041, 58720359, 3588806011781223, 3591011842654386]);
    }

    #[test]
    fn splitmix_matches_reference_vector() {
        // Reference: splitmix64.c seeded with 1234567, first three outputs (Rosetta Code,
        // "Pseudo-random numbers/Splitmix64").
        let mut g = SplitMix64::new(1234567);
        let out: Vec<u64> = (0..3).map(|_| g.next_u64()).collect();
        assert_eq!(out, [6457827717110365317, 3203168211198807973, 9817491932198370423]);
    }

    #[test]
    fn streams_differ_and_repeat() {
        let a: Vec<u64> = {
            let mut g = Xoshiro256pp::for_stream(7, 0);
            (0..8).map(|_| g.next_u64()).collect()
        };
        let b: Vec<u64> = {
            let mut g = Xoshiro256pp::for_stream(7, 1);
            (0..8).map(|_| g.next_u64()).collect()
        };
        let c: Vec<u64> = {
            let mut g = Xoshiro256pp::for_stream(7, 0);
            (0..8).map(|_| g.next_u64()).collect()
        };
        assert_ne!(a, b);
        assert_eq!(a, c);
    }

    #[test]
    fn unit_vectors_are_unit_and_isotropic_in_moments() {
        let mut g = Xoshiro256pp::from_seed(3);
        let n = 200_000;
        let (mut mz, mut mz2, mut mx2) = (0.0, 0.0, 0.0);
        for _ in 0..n {
            let v = g.unit_vector();
            let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((r - 1.0).abs() < 1e-12);
            mz += v[2];
            mz2 += v[2] * v[2];
            mx2 += v[0] * v[0];
        }
        let n = n as f64;
        // Isotropic: E z = 0 (sd 1/sqrt(3n)), E z^2 = E x^2 = 1/3 (sd sqrt(4/45 / n)).
        assert!((mz / n).abs() < 5.0 * (1.0 / (3.0 * n)).sqrt());
        let sd2 = (4.0 / 45.0 / n).sqrt();
        assert!((mz2 / n - 1.0 / 3.0).abs() < 5.0 * sd2);
        assert!((mx2 / n - 1.0 / 3.0).abs() < 5.0 * sd2);
    }

    #[test]
    fn normal_pair_has_unit_variance() {
        let mut g = Xoshiro256pp::from_seed(11);
        let n = 200_000;
        let (mut m, mut v) = (0.0, 0.0);
        for _ in 0..n / 2 {
            let (a, b) = g.normal_pair();
            m += a + b;
            v += a * a + b * b;
        }
        let n = n as f64;
        assert!((m / n).abs() < 5.0 / n.sqrt());
        assert!((v / n - 1.0).abs() < 5.0 * (2.0 / n).sqrt());
    }
}
