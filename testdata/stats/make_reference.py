#!/usr/bin/env python3
"""Independent reference numbers for sofipol's KS, Kuiper and binomial tests.

Regenerate (only on purpose) with:
    pip install scipy astropy mpmath numpy
    python3 testdata/stats/make_reference.py > testdata/stats/reference.json

Nothing here uses sofipol code. Datasets are drawn once with numpy's PCG64 and stored
rounded, so the JSON (not this script) is the reference; the tests read the JSON.
"""
import json
import platform
import sys

import astropy
import mpmath
import numpy as np
import scipy
from astropy.stats import kuiper as astropy_kuiper
from scipy import stats

mpmath.mp.dps = 40


def kuiper_q_mpmath(lam):
    """Q_KP(lambda) = 2 sum_{j>=1} (4 j^2 lambda^2 - 1) exp(-2 j^2 lambda^2), 40 digits."""
    lam = mpmath.mpf(lam)
    s = mpmath.nsum(lambda j: (4 * j**2 * lam**2 - 1) * mpmath.exp(-2 * j**2 * lam**2), [1, mpmath.inf])
    return float(2 * s)


def kuiper_stephens_p(v, n):
    """Stephens (1970) / Numerical Recipes: Q_KP((sqrt n + 0.155 + 0.24/sqrt n) V)."""
    sn = mpmath.sqrt(n)
    return kuiper_q_mpmath((sn + mpmath.mpf("0.155") + mpmath.mpf("0.24") / sn) * mpmath.mpf(v))


def kuiper_v(u):
    u = np.sort(u, axis=-1)
    n = u.shape[-1]
    i = np.arange(1, n + 1)
    return np.max(i / n - u, axis=-1) + np.max(u - (i - 1) / n, axis=-1)


def kuiper_mc_p(v, n, reps, rng):
    hits = 0
    batch = 100_000
    done = 0
    while done < reps:
        b = min(batch, reps - done)
        hits += int(np.sum(kuiper_v(rng.random((b, n))) >= v))
        done += b
    p = hits / reps
    return p, float(np.sqrt(max(p * (1 - p), 1.0 / reps) / reps))


rng = np.random.default_rng(20010101)
datasets = {
    "skewed_n34": np.round(90.0 * rng.beta(0.7, 1.6, 34), 2),
    "uniform_n12": np.round(rng.uniform(0, 90, 12), 2),
    "n5": np.round(rng.uniform(0, 90, 5), 2),
    "near_uniform_n2000": np.round(90.0 * rng.beta(1.0, 1.08, 2000), 4),
}
mc_rng = np.random.default_rng(424242)
one_sample = []
for name, x in datasets.items():
    x = [float(v) for v in x]
    n = len(x)
    ks = stats.kstest(x, "uniform", args=(0.0, 90.0), method="exact")
    ks_asymp = stats.kstest(x, "uniform", args=(0.0, 90.0), method="asymp")
    v, fpp_astropy = astropy_kuiper(np.array(x) / 90.0)
    entry = {
        "name": name,
        "data": x,
        "ks_d": float(ks.statistic),
        "ks_p_exact": float(ks.pvalue),
        "ks_p_asymp_scipy": float(ks_asymp.pvalue),
        "kuiper_v": float(v),
        "kuiper_p_stephens_mpmath": kuiper_stephens_p(float(v), n),
        "kuiper_p_astropy_paltani": float(fpp_astropy),
    }
    if n <= 100:
        p, se = kuiper_mc_p(float(v), n, 1_000_000, mc_rng)
        entry["kuiper_p_monte_carlo"] = p
        entry["kuiper_p_monte_carlo_se"] = se
    one_sample.append(entry)

# Two-sample KS: scipy's asymptotic method = kstwo.sf(D, round(n1 n2 / (n1 + n2))).
a = datasets["skewed_n34"]
b = np.round(rng.uniform(0, 90, 500), 2)
c = np.concatenate([np.round(rng.uniform(0, 90, 20), 0), [10.0, 10.0, 20.0]])
two_sample = []
for name, (x, y) in {"skewed34_vs_uniform500": (a, b), "ties_23_vs_34": (c, a)}.items():
    r = stats.ks_2samp(x, y, method="asymp")
    two_sample.append({
        "name": name, "a": [float(v) for v in x], "b": [float(v) for v in y],
        "d": float(r.statistic), "p_asymp": float(r.pvalue),
    })

kolmogorov_sf = []
for d, n in [(0.05, 100), (0.2, 34), (0.3, 34), (0.45, 34), (0.6, 34), (0.75, 20), (0.03, 1000), (0.06, 1000), (0.5, 3)]:
    kolmogorov_sf.append({"d": d, "n": n, "sf": float(stats.kstwo.sf(d, n))})

asymptotic_kolmogorov = []
for d, n in [(0.02, 2000), (0.03, 2000), (0.01, 20000)]:
    asymptotic_kolmogorov.append({"d": d, "n": n, "sf_scipy_kstwo": float(stats.kstwo.sf(d, n))})

kuiper_q = [{"lambda": lam, "q": kuiper_q_mpmath(lam)} for lam in [0.3, 0.5, 0.8, 0.99, 1.0, 1.01, 1.5, 2.5, 4.0]]

binomial = []
for k, n in [(21, 34), (11, 34), (12, 34), (0, 5), (5, 5), (3, 9)]:
    g = stats.binomtest(k, n, 1.0 / 3.0, alternative="greater").pvalue
    t = stats.binomtest(k, n, 1.0 / 3.0, alternative="two-sided").pvalue
    binomial.append({"k": k, "n": n, "p0": 1.0 / 3.0, "p_greater": float(g), "p_two_sided": float(t)})

out = {
    "origin": {
        "script": "testdata/stats/make_reference.py",
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "astropy": astropy.__version__,
        "mpmath": mpmath.__version__,
        "calls": {
            "ks_p_exact": "scipy.stats.kstest(data, 'uniform', args=(0, 90), method='exact')",
            "ks_p_asymp_scipy": "scipy.stats.kstest(..., method='asymp')",
            "kuiper_v / kuiper_p_astropy_paltani": "astropy.stats.kuiper(data / 90) (p: Paltani 2004 formulas, can be up to 1.5x high)",
            "kuiper_p_stephens_mpmath": "Q_KP((sqrt n + 0.155 + 0.24/sqrt n) V), series summed with mpmath.nsum at 40 digits",
            "kuiper_p_monte_carlo": "fraction of 10^6 uniform samples of size n with V >= observed (numpy PCG64 seed 424242)",
            "two_sample p_asymp": "scipy.stats.ks_2samp(a, b, method='asymp')",
            "kolmogorov_sf": "scipy.stats.kstwo.sf(d, n)",
            "kuiper_q": "mpmath series as above",
            "binomial": "scipy.stats.binomtest(k, n, 1/3, alternative='greater' | 'two-sided').pvalue",
        },
    },
    "one_sample": one_sample,
    "two_sample": two_sample,
    "kolmogorov_sf": kolmogorov_sf,
    "asymptotic_kolmogorov": asymptotic_kolmogorov,
    "kuiper_q": kuiper_q,
    "binomial": binomial,
}
json.dump(out, sys.stdout, indent=1)
print()
