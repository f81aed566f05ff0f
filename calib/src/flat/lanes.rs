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

/// The `k`-th smallest of `keys` (0-based; `k < keys.len()`): the element
/// `keys.select_nth_unstable(k)` gives, the same value. Large inputs (sky levels: ~40k
/// keys per frame) are first bracketed by two order statistics of every 16th key, a few
/// standard deviations of their rank around k; one branch-free pass counts the keys below
/// the bracket and gathers those inside it (~10 %), and only they are selected among. When
/// the k-th is not inside the bracket (never seen on real data), it is selected plainly.
/// `keys` is left reordered.
pub(crate) fn kth_key(keys: &mut [i32], k: usize) -> i32 {
    /// Below this many keys the plain selection is as fast.
    const MIN_LEN: usize = 4096;
    /// One key in this many forms the subsample.
    const STEP: usize = 16;
    let n = keys.len();
    assert!(k < n, "order {k} of {n} keys");
    if n < MIN_LEN {
        return *keys.select_nth_unstable(k).1;
    }
    let mut sub: Vec<i32> = keys.iter().step_by(STEP).copied().collect();
    let m = sub.len();
    // The k-th key's rank in the subsample is ~ m k / n, binomial: half-width 6 sigma (the
    // sigma is at most sqrt(m) / 2) plus one.
    let centre = ((k as f64 / n as f64) * m as f64) as usize;
    let half = 3 * (m as f64).sqrt().ceil() as usize + 1;
    let (i_lo, i_hi) = (centre.saturating_sub(half), (centre + half).min(m - 1));
    let lo = *sub.select_nth_unstable(i_lo).1;
    let hi = *sub[i_lo..].select_nth_unstable(i_hi - i_lo).1;
    let mut inside = vec![0i32; n];
    let (mut below, mut n_in) = (0usize, 0usize);
    for &x in keys.iter() {
        below += usize::from(x < lo);
        inside[n_in] = x;
        n_in += usize::from(lo <= x && x <= hi);
    }
    if (below..below + n_in).contains(&k) {
        return *inside[..n_in].select_nth_unstable(k - below).1;
    }
    *keys.select_nth_unstable(k).1
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
/// network `net` of `keys.len()` inputs.
#[inline(always)]
fn sort_lanes_generic(keys: &mut [[i32; LANES]], net: &[(u16, u16)]) {
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

/// [`sort_lanes_generic`] compiled for AVX2 (8 integer lanes with one min and one max
/// instruction each; SSE2 has no 32-bit integer min/max).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn sort_lanes_avx2(keys: &mut [[i32; LANES]], net: &[(u16, u16)]) {
    sort_lanes_generic(keys, net)
}

/// Sort every lane of `keys` by the network `net` (from [`sorting_network`] of
/// `keys.len()`), with the widest integer vectors this CPU has.
pub(super) fn sort_lanes(keys: &mut [[i32; LANES]], net: &[(u16, u16)]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above); the only unsafe operation here.
            #[allow(unsafe_code)]
            return unsafe { sort_lanes_avx2(keys, net) };
        }
    }
    sort_lanes_generic(keys, net)
}

#[cfg(test)]
mod kth_tests {
    use super::kth_key;
    use rand::{RngExt, SeedableRng};

    /// The bracketed selection gives the plain selection's value, for every k tried, on
    /// sky-like values (narrow spread), heavy ties, sorted and reversed inputs, outliers on
    /// one side (the bracket off centre), and sizes around the threshold; and a bracket that
    /// misses (a subsample unlike the rest) still gives the right value.
    #[test]
    fn the_bracketed_selection_equals_the_plain_one() {
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(3);
        let mut cases: Vec<Vec<i32>> = Vec::new();
        for n in [1, 2, 100, 4095, 4096, 4097, 40_000, 123_457] {
            cases.push((0..n).map(|_| rng.random_range(1_000_000..1_003_000)).collect());
            cases.push((0..n).map(|_| rng.random_range(-3..3)).collect());
            let mut s: Vec<i32> = (0..n).map(|_| rng.random_range(i32::MIN..i32::MAX)).collect();
            s.sort();
            cases.push(s.clone());
            s.reverse();
            cases.push(s);
            cases.push(
                (0..n)
                    .map(|i| if i % 3 == 0 { i32::MAX - i as i32 } else { rng.random_range(0..1000) })
                    .collect(),
            );
            // Every 16th key (the subsample) far above the others: the bracket misses.
            cases.push((0..n).map(|i| if i % 16 == 0 { 1 << 30 } else { i as i32 }).collect());
        }
        for v in &cases {
            let n = v.len();
            for k in [0, n / 4, n / 2, n / 2 + 1, n - 1].into_iter().filter(|&k| k < n) {
                let want = *v.clone().select_nth_unstable(k).1;
                assert_eq!(kth_key(&mut v.clone(), k), want, "n {n} k {k}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
