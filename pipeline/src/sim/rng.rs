//! Deterministic, independent random streams.
//!
//! Every random draw belongs to one effect and one place (target, frame, row...). Its
//! stream is seeded by hashing (scene seed, effect, indices) with SplitMix64, so adding or
//! removing one effect never changes another effect's realisation, and results do not
//! depend on the number of threads or the order work is done in.
use rand::rngs::Xoshiro256PlusPlus;
use rand::SeedableRng;

use super::scene::EffectKind;

pub use crate::numeric::splitmix64;

/// The stream of `effect` at indices `a`, `b`, `c` for a scene seed.
pub fn stream(seed: u64, effect: EffectKind, a: u64, b: u64, c: u64) -> Xoshiro256PlusPlus {
    let mut h = splitmix64(seed ^ 0x5350_4F4C); // "SPOL"
    for v in [effect.index() as u64 + 1, a, b, c] {
        h = splitmix64(h ^ v);
    }
    Xoshiro256PlusPlus::seed_from_u64(h)
}
