//! Per-pixel medians of a few values (one per frame), many pixels side by side: each
//! pixel's values are sorted by the same fixed sorting network, so a block of
//! [`LANES`] neighbouring pixels is sorted with vector min/max instructions and no
//! branch. Values are compared as integer keys in the order of `f32::total_cmp`, so the
//! median is the element [`super::median_f32`] picks, bit for bit.

/// Pixels sorted side by side.
pub(super) const LANES: usize = 16;

/// Integer key of an `f32` whose order is `f32::total_cmp`'s.
#[inline(always)]
pub(crate) fn key(x: f32) -> i32 {
    let b = x.to_bits() as i32;
    b ^ (((b >> 31) as u32) >> 1) as i32
}

/// The `f32` of a [`key`].
#[inline(always)]
pub(crate) fn from_key(k: i32) -> f32 {
    f32::from_bits((k ^ (((k >> 31) as u32) >> 1) as i32) as u32)
}

/// The key that sorts after every value: a slot without a value holds it.
pub(super) const NO_VALUE: i32 = i32::MAX;

/// Compare-exchange pairs `(i, j)`, `i < j`, of Batcher's odd-even merge sort for `n`
/// inputs ([`crate::stack::batcher_pairs`]): pairs touching an input at `n` or beyond are
/// left out, which is right here too, as a slot without a value holds [`NO_VALUE`], the
/// largest key.
pub(super) fn sorting_network(n: usize) -> Vec<(u16, u16)> {
    crate::stack::batcher_pairs(n)
}

/// Sort every lane of `keys` (`keys[i][lane]`: value `i` of the pixel in `lane`) by the
/// network `net` of `keys.len()` inputs: the portable build, and the definition
/// [`sort_lanes`] must equal bit for bit.
#[inline(always)]
pub(crate) fn sort_lanes_portable(keys: &mut [[i32; LANES]], net: &[(u16, u16)]) {
    for &(a, b) in net {
        let (lo, hi) = keys.split_at_mut(b as usize);
        let (x, y) = (&mut lo[a as usize], &mut hi[0]);
        for l in 0..LANES {
            let (p, q) = (x[l], y[l]);
            x[l] = p.min(q);
            y[l] = p.max(q);
        }
    }
}

/// [`sort_lanes_portable`] with the widest integer vectors this CPU has (AVX2: 8 integer
/// lanes with one min and one max instruction each; SSE2 has no 32-bit integer min/max),
/// chosen at run time. `net` comes from [`sorting_network`] of `keys.len()`.
#[multiversion::multiversion(targets("x86_64+avx2"))]
pub(crate) fn sort_lanes(keys: &mut [[i32; LANES]], net: &[(u16, u16)]) {
    sort_lanes_portable(keys, net)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{rngs::Xoshiro256PlusPlus, RngExt, SeedableRng};

    /// The 0-1 principle: a comparator network sorts every input iff it sorts every 0/1
    /// input. Checked exhaustively up to 14 inputs (the pruning included).
    #[test]
    fn the_network_sorts_every_zero_one_input() {
        for n in 1..=14usize {
            let net = sorting_network(n);
            let cases = 1usize << n;
            let mut keys = vec![[NO_VALUE; LANES]; n];
            for base in (0..cases).step_by(LANES) {
                for l in 0..LANES {
                    let c = (base + l) % cases;
                    for (i, k) in keys.iter_mut().enumerate() {
                        k[l] = ((c >> i) & 1) as i32;
                    }
                }
                sort_lanes(&mut keys, &net);
                for l in 0..LANES {
                    let col: Vec<i32> = keys.iter().map(|k| k[l]).collect();
                    assert!(col.windows(2).all(|w| w[0] <= w[1]), "n {n}: {col:?}");
                }
            }
        }
    }

    /// Larger networks sort random keys like `sort` does; slots without a value stay last.
    #[test]
    fn the_network_sorts_like_sort() {
        let mut state = 99u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as i32 - (1 << 30)
        };
        for n in [15usize, 16, 17, 25, 31, 32, 33, 50, 64, 100] {
            let net = sorting_network(n);
            for _ in 0..20 {
                let mut keys = vec![[0i32; LANES]; n];
                for k in keys.iter_mut() {
                    for v in k.iter_mut() {
                        *v = next() % 50;
                    }
                }
                // Some slots hold no value in some lanes.
                for l in (0..LANES).step_by(3) {
                    keys[n - 1][l] = NO_VALUE;
                }
                let mut want: Vec<Vec<i32>> = (0..LANES).map(|l| keys.iter().map(|k| k[l]).collect()).collect();
                want.iter_mut().for_each(|w| w.sort());
                sort_lanes(&mut keys, &net);
                for (l, w) in want.iter().enumerate() {
                    let col: Vec<i32> = keys.iter().map(|k| k[l]).collect();
                    assert_eq!(&col, w, "n {n} lane {l}");
                }
            }
        }
    }

    /// Keys of seeded random values: special floats (NaN of both signs, infinities, signed
    /// zeros, subnormals), random bit patterns, ties, and slots without a value.
    fn random_keys(rng: &mut Xoshiro256PlusPlus, n: usize) -> Vec<[i32; LANES]> {
        const SPECIAL: [f32; 10] = [
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
        ];
        (0..n)
            .map(|_| {
                std::array::from_fn(|_| match rng.random_range(0..5) {
                    0 => key(SPECIAL[rng.random_range(0..SPECIAL.len())]),
                    1 => key(f32::from_bits(rng.random())),
                    2 => NO_VALUE,
                    _ => key(rng.random_range(0..8) as f32 * 0.5),
                })
            })
            .collect()
    }

    /// The run-time chosen build of the sort against the portable build, bit for bit, for
    /// every input count from 0 (no value) to 40 and a few larger ones.
    #[test]
    fn the_sort_is_the_same_in_every_vector_build() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(31);
        for n in (0..=40).chain([63, 64, 65, 100]) {
            let net = sorting_network(n);
            for _ in 0..30 {
                let keys = random_keys(&mut rng, n);
                let (mut fast, mut portable) = (keys.clone(), keys);
                sort_lanes(&mut fast, &net);
                sort_lanes_portable(&mut portable, &net);
                assert_eq!(fast, portable, "n {n}");
            }
        }
    }

    proptest::proptest! {
        /// Any keys, any count up to 48.
        #[test]
        fn the_sort_of_any_keys_is_the_same_in_every_vector_build(
            flat in proptest::collection::vec(proptest::prelude::any::<i32>(), 0..48 * LANES)
        ) {
            let keys: Vec<[i32; LANES]> = flat
                .chunks_exact(LANES)
                .map(|c| std::array::from_fn(|l| c[l]))
                .collect();
            let net = sorting_network(keys.len());
            let (mut fast, mut portable) = (keys.clone(), keys);
            sort_lanes(&mut fast, &net);
            sort_lanes_portable(&mut portable, &net);
            proptest::prop_assert_eq!(fast, portable);
        }
    }

    /// Keys order floats like `total_cmp` and convert back bit for bit.
    #[test]
    fn keys_are_total_cmp_order() {
        let xs = [
            f32::NEG_INFINITY,
            -3.0e38,
            -1.0,
            -1e-40,
            -0.0,
            0.0,
            1e-40,
            0.97,
            1.0,
            f32::INFINITY,
            f32::NAN,
            -f32::NAN,
        ];
        for &a in &xs {
            assert_eq!(from_key(key(a)).to_bits(), a.to_bits());
            for &b in &xs {
                assert_eq!(key(a).cmp(&key(b)), a.total_cmp(&b), "{a} {b}");
            }
        }
        assert!(key(f32::NAN) < NO_VALUE);
    }
}
