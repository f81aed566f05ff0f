#!/usr/bin/env python3
"""Generate testdata/photometry/photutils_reference.json.

Independent reference for sofipol's aperture photometry
(pipeline/src/photometry): aperture sums computed by photutils'
``aperture_photometry`` with method='exact', 'center' and 'subpixel'
(subpixels=5), plus a few per-pixel exact weight masks.

This is a generator, not part of the build. Regenerate only on purpose:

    python3 -m venv /tmp/phvenv && /tmp/phvenv/bin/pip install photutils numpy
    /tmp/phvenv/bin/python testdata/photometry/make_reference.py > testdata/photometry/photutils_reference.json

Conventions (identical in photutils and sofipol): arrays indexed [y, x];
pixel (ix, iy) covers [ix-0.5, ix+0.5] x [iy-0.5, iy+0.5], i.e. pixel centres
at integer 0-based coordinates.

Images are float32: each formula is evaluated in float64 with numpy and then
cast to float32. The exact float32 pixel values are stored in the JSON too
(so the Rust test does not depend on libm's exp), and the formula is kept
for the reader. photutils multiplies the float32 data by float64 weights and
sums in float64.
"""
import datetime
import json
import sys

import numpy as np
import photutils
import astropy
from photutils.aperture import CircularAperture, aperture_photometry


def ramp(ny, nx):
    y, x = np.mgrid[0:ny, 0:nx].astype(np.float64)
    return (1.0 + 0.01 * x + 0.003 * y + 0.0001 * x * y).astype(np.float32)


def star(ny, nx):
    y, x = np.mgrid[0:ny, 0:nx].astype(np.float64)
    g = np.exp(-((x - 10.3) ** 2 + (y - 9.8) ** 2) / (2.0 * 1.7 ** 2))
    return (5.0 + 1000.0 * g).astype(np.float32)


def checker(ny, nx):
    y, x = np.mgrid[0:ny, 0:nx]
    return (1.0 + 2.0 * ((x + y) % 2)).astype(np.float32)


IMAGES = [
    ("ramp", (20, 24), ramp,
     "float32(1 + 0.01*x + 0.003*y + 0.0001*x*y), evaluated in float64 then cast"),
    ("star", (21, 21), star,
     "float32(5 + 1000*exp(-((x-10.3)^2 + (y-9.8)^2) / (2*1.7^2))), float64 then cast"),
    ("checker", (16, 16), checker,
     "float32(1 + 2*((x + y) mod 2)): 1 on even x+y, 3 on odd"),
]

# (x, y, r): awkward cases on purpose.
APERTURES = [
    (10.0, 9.0, 3.0),    # centred on a pixel centre
    (10.5, 9.0, 3.0),    # centre on a vertical pixel edge
    (10.5, 9.5, 2.5),    # centre on a pixel corner
    (7.3, 8.6, 0.3),     # tiny circle inside one pixel
    (7.5, 8.5, 0.5),     # r = 0.5 on a corner
    (7.0, 8.0, 0.5),     # r = 0.5 inscribed in a pixel (tangent to 4 edges)
    (7.2, 6.9, 0.5),     # r = 0.5 off-centre
    (1.2, 3.7, 4.0),     # partly off the left edge
    (14.6, 14.9, 3.3),   # partly off the top-right corner of the 16x16 image
    (11.7, 9.2, 9.5),    # large, partly off
    (12.0, 10.0, 30.0),  # huge: covers every image entirely
    (5.25, 12.75, 1.0),  # quarter-pixel offsets
    (0.0, 0.0, 2.0),     # on the first pixel centre, 3/4 off the image
    (-0.5, 5.0, 1.5),    # centre on the image's left edge
    (9.9, 10.1, 6.01),   # generic
    (3.0, 4.0, 1.4142135623730951),  # passes exactly through pixel corners
]

METHODS = [("exact", {}), ("center", {}), ("subpixel", {"subpixels": 5})]

# Per-pixel exact weights (photutils ApertureMask) for a few apertures.
MASK_CASES = [(10.5, 9.5, 2.5), (7.2, 6.9, 0.5), (5.25, 12.75, 1.0), (9.9, 10.1, 6.01)]


def main():
    out = {
        "origin": {
            "generator": "testdata/photometry/make_reference.py",
            "photutils": photutils.__version__,
            "numpy": np.__version__,
            "astropy": astropy.__version__,
            "python": sys.version.split()[0],
            "date": datetime.date.today().isoformat(),
            "function": "photutils.aperture.aperture_photometry(data, "
                        "CircularAperture((x, y), r), method=..., subpixels=5)",
            "conventions": "arrays [y, x]; pixel centres at integer 0-based "
                           "coordinates; images float32, sums float64",
            "script": open(__file__).read(),
        },
        "images": [],
        "masks": [],
    }
    for name, (ny, nx), fn, formula in IMAGES:
        data = fn(ny, nx)
        cases = []
        for (x, y, r) in APERTURES:
            ap = CircularAperture((x, y), r=r)
            row = {"x": x, "y": y, "r": r}
            for meth, kw in METHODS:
                key = meth if meth != "subpixel" else "subpixel5"
                t = aperture_photometry(data, ap, method=meth, **kw)
                row[key] = float(t["aperture_sum"][0])
            cases.append(row)
        out["images"].append({
            "name": name, "ny": ny, "nx": nx, "dtype": "float32",
            "formula": formula,
            "values_row_major": [float(v) for v in data.ravel()],
            "cases": cases,
        })
    for (x, y, r) in MASK_CASES:
        m = CircularAperture((x, y), r=r).to_mask(method="exact")
        out["masks"].append({
            "x": x, "y": y, "r": r,
            "ixmin": int(m.bbox.ixmin), "iymin": int(m.bbox.iymin),
            "ny": int(m.data.shape[0]), "nx": int(m.data.shape[1]),
            "weights_row_major": [float(v) for v in m.data.ravel()],
        })
    json.dump(out, sys.stdout, indent=1)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
