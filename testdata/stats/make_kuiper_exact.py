#!/usr/bin/env python3
"""Independent references for the exact small-n Kuiper p-value of sofipol.

Regenerate (only on purpose) with:
    pip install numpy mpmath astropy
    python3 testdata/stats/make_kuiper_exact.py > testdata/stats/kuiper_exact.json

Nothing here uses sofipol code. Two independent references per n = 5, 9, 12, 20:
- "monte_carlo": P(V_n >= v) from 10^7 samples of n iid uniforms (numpy PCG64, seed
  20261123), V = max(i/n - u_(i)) + max(u_(i) - (i-1)/n); with its binomial standard error.
  Used where p >= 0.02 so that the standard error is <= 0.25 % of p.
- "stephens1965_exact": the exact upper tail of Stephens (1965, Biometrika 52, 309,
  eq. for V > 1/2 (n even) or V > (n-1)/(2n) (n odd), as quoted by Paltani 2004 and in
  astropy.stats.kuiper_false_positive_probability), summed here in 50-digit mpmath.
astropy's kuiper_false_positive_probability (exact in the tail, asymptotic series with
1/sqrt(n) corrections in the middle) is stored for comparison only.
"""
import json
import platform
import sys

import astropy
import mpmath
import numpy as np
from astropy.stats import kuiper_false_positive_probability

mpmath.mp.dps = 50
REPS = 10_000_000
SEED = 20261123


def kuiper_v(u):
    u = np.sort(u, axis=-1)
    n = u.shape[-1]
    i = np.arange(1, n + 1)
    return np.max(i / n - u, axis=-1) + np.max(u - (i - 1) / n, axis=-1)


def mc_p(vs, n, rng):
    hits = np.zeros(len(vs), dtype=np.int64)
    done = 0
    batch = 500_000
    while done < REPS:
        b = min(batch, REPS - done)
        v = kuiper_v(rng.random((b, n)))
        for j, x in enumerate(vs):
            hits[j] += int(np.count_nonzero(v >= x))
        done += b
    p = hits / REPS
    return p, np.sqrt(p * (1 - p) / REPS)


def stephens_exact_tail(v, n):
    """P(V_n >= v), exact for v > 1/2 (n even) or v > (n-1)/(2n) (n odd)."""
    v = mpmath.mpf(v)
    N = mpmath.mpf(n)
    s = mpmath.mpf(0)
    for t in range(int(mpmath.floor(N * (1 - v))) + 1):
        y = v + t / N
        tt = y ** (t - 3) * (
            y**3 * N - y**2 * t * (3 - 2 / N) + y * t * (t - 1) * (3 - 2 / N) / N - t * (t - 1) * (t - 2) / N**2
        )
        s += mpmath.binomial(n, t) * (1 - v - t / N) ** (n - t - 1) * tt
    return s


def tail_valid(v, n):
    return v > 0.5 if n % 2 == 0 else v > (n - 1) / (2 * n)


# V values: two in the body (Monte Carlo), two in the exact tail.
CASES = {
    5: [0.55, 0.70, 0.80, 0.90],
    9: [0.45, 0.55, 0.62, 0.75],
    12: [0.40, 0.48, 0.55, 0.65],
    20: [0.30, 0.38, 0.52, 0.60],
}


def main():
    rng = np.random.Generator(np.random.PCG64(SEED))
    out = {
        "origin": {
            "script": "testdata/stats/make_kuiper_exact.py",
            "python": platform.python_version(),
            "numpy": np.__version__,
            "mpmath": mpmath.__version__,
            "astropy": astropy.__version__,
            "monte_carlo_reps": REPS,
            "seed": SEED,
            "formula": "Stephens 1965 Biometrika 52, 309 (exact upper tail), 50-digit mpmath",
        },
        "cases": [],
    }
    for n, vs in CASES.items():
        p, se = mc_p(vs, n, rng)
        for j, v in enumerate(vs):
            e = {"n": n, "v": v, "monte_carlo": float(p[j]), "monte_carlo_se": float(se[j])}
            if tail_valid(v, n):
                e["stephens1965_exact"] = float(stephens_exact_tail(v, n))
            e["astropy"] = float(kuiper_false_positive_probability(v, n))
            out["cases"].append(e)
            print(e, file=sys.stderr)
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
