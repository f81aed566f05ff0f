//! Histograms with integer counts (order-independent sums: the Monte Carlo merges chunk
//! histograms in any order and gets bit-identical totals).
use serde::{Deserialize, Serialize};

/// A histogram of equal-width bins on [lo, hi]; a value equal to `hi` falls in the last bin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Histogram {
    /// Lower edge of the first bin.
    pub lo: f64,
    /// Upper edge of the last bin.
    pub hi: f64,
    /// Counts per bin.
    pub counts: Vec<u64>,
}

impl Histogram {
    /// Empty histogram of `bins` equal bins on [lo, hi] (requires lo < hi, bins >= 1).
    pub fn new(lo: f64, hi: f64, bins: usize) -> Self {
        assert!(lo < hi && bins >= 1, "histogram needs lo < hi and at least one bin");
        Self {
            lo,
            hi,
            counts: vec![0; bins],
        }
    }

    /// Histogram of `values` (values outside [lo, hi] are ignored and counted in the return).
    pub fn from_values(lo: f64, hi: f64, bins: usize, values: &[f64]) -> (Self, usize) {
        let mut h = Self::new(lo, hi, bins);
        let mut outside = 0;
        for &v in values {
            if !h.add(v) {
                outside += 1;
            }
        }
        (h, outside)
    }

    /// Number of bins.
    pub fn bins(&self) -> usize {
        self.counts.len()
    }

    /// Bin width.
    pub fn width(&self) -> f64 {
        (self.hi - self.lo) / self.bins() as f64
    }

    /// Index of the bin holding `v`, None outside [lo, hi] or for NaN.
    #[inline]
    pub fn index(&self, v: f64) -> Option<usize> {
        if !(v >= self.lo && v <= self.hi) {
            return None;
        }
        // Same arithmetic as the Monte-Carlo kernel (x * bins / span), so both bin alike.
        let i = ((v - self.lo) * (self.bins() as f64 / (self.hi - self.lo))) as usize;
        Some(i.min(self.bins() - 1))
    }

    /// Count `v`; false when it is outside [lo, hi].
    pub fn add(&mut self, v: f64) -> bool {
        match self.index(v) {
            Some(i) => {
                self.counts[i] += 1;
                true
            }
            None => false,
        }
    }

    /// Add another histogram of the same binning.
    pub fn merge(&mut self, other: &Histogram) {
        assert_eq!(self.bins(), other.bins(), "merging histograms of different binning");
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += *b;
        }
    }

    /// Total count.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// The bin edges (bins + 1 values).
    pub fn edges(&self) -> Vec<f64> {
        let w = self.width();
        (0..=self.bins()).map(|i| self.lo + w * i as f64).collect()
    }

    /// The bin centres.
    pub fn centers(&self) -> Vec<f64> {
        let w = self.width();
        (0..self.bins()).map(|i| self.lo + w * (i as f64 + 0.5)).collect()
    }

    /// Probability density per unit of x (integrates to 1; all zeros when empty).
    pub fn density(&self) -> Vec<f64> {
        let t = self.total();
        if t == 0 {
            return vec![0.0; self.bins()];
        }
        let norm = 1.0 / (t as f64 * self.width());
        self.counts.iter().map(|&c| c as f64 * norm).collect()
    }

    /// Fraction of the counts per bin (sums to 1).
    pub fn fractions(&self) -> Vec<f64> {
        let t = self.total().max(1) as f64;
        self.counts.iter().map(|&c| c as f64 / t).collect()
    }

    /// Empirical CDF at x, linear inside a bin (exact at the edges).
    pub fn cdf(&self, x: f64) -> f64 {
        let t = self.total();
        if t == 0 || x <= self.lo {
            return 0.0;
        }
        if x >= self.hi {
            return 1.0;
        }
        let pos = (x - self.lo) / self.width();
        let i = (pos as usize).min(self.bins() - 1);
        let below: u64 = self.counts[..i].iter().sum();
        (below as f64 + self.counts[i] as f64 * (pos - i as f64)) / t as f64
    }

    /// Merge groups of `factor` adjacent bins (the bin count must be divisible by it).
    pub fn rebin(&self, factor: usize) -> Option<Histogram> {
        if factor == 0 || self.bins() % factor != 0 {
            return None;
        }
        let counts = self.counts.chunks(factor).map(|c| c.iter().sum()).collect();
        Some(Histogram {
            lo: self.lo,
            hi: self.hi,
            counts,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_and_last_bin_inclusive() {
        let (h, out) = Histogram::from_values(0.0, 90.0, 9, &[0.0, 9.999, 10.0, 90.0, 90.5, -1.0, f64::NAN]);
        assert_eq!(out, 3);
        assert_eq!(h.counts, vec![2, 1, 0, 0, 0, 0, 0, 0, 1]);
        assert_eq!(h.edges()[9], 90.0);
        assert!((h.cdf(10.0) - 0.5).abs() < 1e-15);
        assert!((h.cdf(5.0) - 0.25).abs() < 1e-15);
        assert_eq!(h.rebin(3).unwrap().counts, vec![3, 0, 1]);
        assert!(h.rebin(4).is_none());
        let d = h.density();
        assert!((d.iter().sum::<f64>() * h.width() - 1.0).abs() < 1e-12);
    }
}
