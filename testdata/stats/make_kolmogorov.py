#!/usr/bin/env python3
"""Independent reference values of the Kolmogorov distribution.

* Q_KS(lambda) = lim P(sqrt(n) D_n > lambda) = 2 sum_{j>=1} (-1)^(j-1) exp(-2 j^2 lambda^2),
  from scipy.special.kolmogorov (the Cephes implementation, not sofipol code);
* P(D_n >= d) for odd n near the exact method's limit (n = 1000): the matrix power's odd
  steps after its rescaling against overflow. The reference is Marsaglia, Tsang & Wang's
  (2003) matrix formula evaluated here with mpmath at 50 digits (no rescaling needed; the
  slow exact sweep of the order statistics checks the formula itself at n = 9 in
  tests_pvalues.rs); scipy.stats.kstwo.sf is stored beside it: at these n it is an
  approximation good to ~1e-7 relative.

Regenerate (only on purpose) with:
    pip install scipy mpmath
    python3 testdata/stats/make_kolmogorov.py > testdata/stats/kolmogorov.json
"""
import json
import platform
import sys

import mpmath as mp
import scipy
from scipy.special import kolmogorov
from scipy.stats import kstwo

# Both sides of the switch between the two series at lambda = 1, the far tail (where 1 - sum
# loses every digit) and lambda near 0 (where the alternating series needs many terms).
LAMBDAS = [0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 1.0, 1.01, 1.1, 1.3, 1.6, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0]

mp.mp.dps = 50


def mtw_sf_mp(d, n):
    """1 - P(D_n < d) by Marsaglia, Tsang & Wang's H^n, in 50-digit arithmetic."""
    d = mp.mpf(d)
    k = int(mp.floor(n * d)) + 1
    m = 2 * k - 1
    h = k - n * d
    H = mp.matrix(m, m)
    for i in range(m):
        for j in range(m):
            if i - j + 1 >= 0:
                H[i, j] = 1
    for i in range(m):
        H[i, 0] -= h ** (i + 1)
        H[m - 1, i] -= h ** (m - i)
    if 2 * h - 1 > 0:
        H[m - 1, 0] += (2 * h - 1) ** m
    for i in range(m):
        for j in range(m):
            if i - j + 1 > 0:
                H[i, j] /= mp.factorial(i - j + 1)
    s = (H**n)[k - 1, k - 1] * mp.factorial(n) / mp.mpf(n) ** n
    return float(1 - s)


# Odd n: 999 = 2 * 499 + 1 and 997 end on an odd step after the rescaling has begun; at
# 513 the power is rescaled once (exponent 140), the smallest exponent the final loop undoes.
ODD_N = [999, 997, 513]

out = {
    "origin": {
        "script": "testdata/stats/make_kolmogorov.py",
        "python": platform.python_version(),
        "scipy": scipy.__version__,
        "mpmath": mp.__version__,
        "calls": {
            "q": "scipy.special.kolmogorov(lambda)",
            "sf": "mtw_sf_mp(d, n) (this script, 50 digits)",
            "sf_scipy": "scipy.stats.kstwo.sf(d, n)",
        },
    },
    "q": [{"lambda": x, "q": float(kolmogorov(x))} for x in LAMBDAS],
    "sf": [
        {"d": d, "n": n, "sf": mtw_sf_mp(d, n), "sf_scipy": float(kstwo.sf(d, n))}
        for n in ODD_N
        for d in [0.02, 0.03, 0.045, 0.06]
    ],
}
json.dump(out, sys.stdout, indent=1)
print()
