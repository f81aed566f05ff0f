#!/usr/bin/env python3
"""Synthetic catalogs for `sofipol stats` tests and examples (not observations).

    python3 testdata/stats/make_catalogs.py   # writes catalog_aligned.json, catalog_one.json

catalog_aligned.json: 40 targets; the 34 whose components both pass P/sigma > 3 have the
Delta-gamma values of reference.json's "skewed_n34" data set (strongly aligned); 4 have a
weak component, 1 failed, 1 has a single component. P in fractions, angles in degrees.
catalog_one.json: one usable binary.
"""
import json
import math
import os

import numpy as np

here = os.path.dirname(os.path.abspath(__file__))
ref = json.load(open(os.path.join(here, "reference.json")))
dg = next(e for e in ref["one_sample"] if e["name"] == "skewed_n34")["data"]
rng = np.random.default_rng(7)


def comp(name, p, sigma, gamma):
    q, u = p * math.cos(math.radians(2 * gamma)), p * math.sin(math.radians(2 * gamma))
    pdb = math.sqrt(max(p * p - sigma * sigma, 0.0))
    return {"name": name, "q": q, "u": u, "sigma_q": sigma, "sigma_u": sigma, "p": p, "sigma_p": sigma,
            "p_debiased": pdb, "gamma_deg": gamma % 180.0, "sigma_gamma_deg": 28.65 * sigma / p,
            "passes_cut": p / sigma > 3.0, "flags": []}


def fold(a, b):
    d = (a - b) % 180.0
    return 180.0 - d if d > 90.0 else d


targets = []
for i, d in enumerate(dg):
    ga = float(np.round(rng.uniform(0, 180), 2))
    gb = (ga + (d if rng.random() < 0.5 else -d)) % 180.0
    a = comp("A", float(np.round(rng.uniform(0.015, 0.09), 4)), 0.003, ga)
    b = comp("B", float(np.round(rng.uniform(0.015, 0.09), 4)), 0.004, gb)
    targets.append({"object": f"SYN-{i + 1:02d}", "status": "ok", "components": [a, b],
                    "delta_gamma_deg": fold(a["gamma_deg"], b["gamma_deg"])})
for i in range(4):
    a = comp("A", 0.04, 0.003, 30.0 * i)
    b = comp("B", 0.006, 0.004, 100.0)
    targets.append({"object": f"WEAK-{i + 1}", "status": "ok", "components": [a, b], "delta_gamma_deg": None})
targets.append({"object": "FAILED-1", "status": "failed", "error": "no frames", "components": []})
targets.append({"object": "SINGLE-1", "status": "partial", "error": "companion lost",
                "components": [comp("A", 0.03, 0.003, 12.0)]})
prov = {"software": "testdata/stats/make_catalogs.py", "note": "synthetic, not observations"}
cat = {"schema_version": "1.0", "targets": targets, "failures": [], "provenance": prov}
json.dump(cat, open(os.path.join(here, "catalog_aligned.json"), "w"), indent=1)
one = {"schema_version": "1.0", "targets": targets[:1] + targets[-2:], "failures": [], "provenance": prov}
json.dump(one, open(os.path.join(here, "catalog_one.json"), "w"), indent=1)
