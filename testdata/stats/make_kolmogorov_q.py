#!/usr/bin/env python3
"""Independent reference values of the limiting Kolmogorov distribution Q_KS(lambda).

Q_KS(lambda) = lim P(sqrt(n) D_n > lambda) = 2 sum_{j>=1} (-1)^(j-1) exp(-2 j^2 lambda^2),
from scipy.special.kolmogorov (the Cephes implementation, not sofipol code).

Regenerate (only on purpose) with:
    pip install scipy
    python3 testdata/stats/make_kolmogorov_q.py > testdata/stats/kolmogorov_q.json
"""
import json
import platform
import sys

import scipy
from scipy.special import kolmogorov

# Both sides of the switch between the two series at lambda = 1, the far tail (where 1 - sum
# loses every digit) and lambda near 0 (where the alternating series needs many terms).
LAMBDAS = [0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 1.0, 1.01, 1.1, 1.3, 1.6, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0]

out = {
    "origin": {
        "script": "testdata/stats/make_kolmogorov_q.py",
        "python": platform.python_version(),
        "scipy": scipy.__version__,
        "call": "scipy.special.kolmogorov(lambda)",
    },
    "q": [{"lambda": x, "q": float(kolmogorov(x))} for x in LAMBDAS],
}
json.dump(out, sys.stdout, indent=1)
print()
