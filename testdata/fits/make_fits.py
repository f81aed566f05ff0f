"""Write the sample FITS files of testdata/fits/ with an independent writer (astropy).

sofipol's own FITS writer is not used, so that `calib/tests/testdata.rs` checks sofipol's
reader against files it did not make. Run once, on purpose (the files are committed):

    python3 -m venv /tmp/astro && /tmp/astro/bin/pip install astropy numpy
    /tmp/astro/bin/python testdata/fits/make_fits.py

Written with astropy 8.0.2 and numpy 2.4.6 (Python 3.11). The content is defined here
and restated in testdata/fits/README.md; the Rust test recomputes it from that statement.
"""
import os

import numpy as np
from astropy.io import fits

HERE = os.path.dirname(os.path.abspath(__file__))
NY, NX = 64, 64


def image():
    """Tilted background 1000 + 0.5 x + 0.25 y plus two Gaussian spots (sigma 2 px) of
    8000 and 7000 ADU at (x, y) = (25.6, 28.8) and (25.6, 39.04); rounded to integers
    (numpy.round: ties to even; the background has exact .5 values),
    computed in float64. Array index [y, x]; row 0 is FITS row 1."""
    y, x = np.mgrid[0:NY, 0:NX].astype(np.float64)
    bg = 1000.0 + 0.5 * x + 0.25 * y

    def star(cx, cy, a):
        return a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 8.0)

    return np.round(bg + star(25.6, 28.8, 8000.0) + star(25.6, 39.04, 7000.0))


def header(posang_deg=45.0, expno=6):
    h = fits.Header()
    h["INSTRUME"] = ("SOFI", "instrument used")
    h["OBJECT"] = "HK Tau"
    h["DATE-OBS"] = "1999-03-03T02:11:05.123"
    h["MJD-OBS"] = 51240.0911236111
    h["EXPTIME"] = 10.0
    h["RA"] = 67.86
    h["DEC"] = 24.41
    for key, value in [
        ("ESO DPR CATG", "SCIENCE"),
        ("ESO DPR TYPE", "OBJECT"),
        ("ESO DPR TECH", "POLARIMETRY"),
        ("ESO TPL ID", "SOFI_img_obs_Polarimetry"),
        ("ESO TPL START", "1999-03-03T02:10:41"),
        ("ESO TPL NEXP", 10),
        ("ESO TPL EXPNO", expno),
        ("ESO OBS TARG NAME", "HK_Tau"),
        ("ESO INS FILT1 ID", "Ks"),
        ("ESO INS OPTI1 ID", "MASK_POL"),
        ("ESO INS OPTI3 ID", "WOLLASTON"),
        ("ESO INS PIXSCALE", 0.288),
        ("ESO ADA POSANG", posang_deg),
        ("ESO SEQ CUMOFFSETX", 86.8),
        ("ESO SEQ CUMOFFSETY", 0.0),
        ("ESO DET DIT", 10.0),
        ("ESO DET NDIT", 6),
        ("ESO TEL PARANG START", -157.1),
        ("ESO TEL AIRM START", 1.04),
    ]:
        h["HIERARCH " + key] = value
    h.add_history("written by testdata/fits/make_fits.py with astropy " + __import__("astropy").__version__)
    return h


def main():
    img = image()
    # BITPIX 16 with BZERO 32768 / BSCALE 1, as raw SOFI data: astropy writes uint16 so.
    fits.PrimaryHDU(img.astype(np.uint16), header=header()).writeto(
        os.path.join(HERE, "sofi_pol_64x64_i16.fits"), overwrite=True, checksum=False)
    # The same frame Rice tile-compressed: empty primary HDU, image in HDU 1.
    comp = fits.CompImageHDU(img.astype(np.uint16), header=header(), compression_type="RICE_1")
    fits.HDUList([fits.PrimaryHDU(), comp]).writeto(
        os.path.join(HERE, "sofi_pol_64x64_i16.fits.fz"), overwrite=True)
    # BITPIX -32 float, big-endian as FITS requires (astropy converts).
    fits.PrimaryHDU(img.astype(np.float32), header=header(posang_deg=0.0, expno=1)).writeto(
        os.path.join(HERE, "sofi_pol_64x64_f32.fits"), overwrite=True)
    for name in ["sofi_pol_64x64_i16.fits", "sofi_pol_64x64_i16.fits.fz", "sofi_pol_64x64_f32.fits"]:
        with fits.open(os.path.join(HERE, name)) as hl:
            hdu = hl[1] if name.endswith(".fz") else hl[0]
            d = hdu.data.astype(np.float64)
            print(name, os.path.getsize(os.path.join(HERE, name)), "B; sum", d.sum(),
                  "; [28, 25] =", d[28, 25], "; [0, 63] =", d[0, 63])


if __name__ == "__main__":
    main()
