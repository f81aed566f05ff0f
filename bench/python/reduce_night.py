#!/usr/bin/env python3
"""Reduce a night of SOFI dual-beam imaging polarimetry of binaries, as an astronomer
would with numpy + scipy + astropy + photutils (the Python reference of `sofipol bench
night`; an independent cross-check of sofipol's catalog).

Steps, per target sequence (template run: 2 or more rotator angles x N dithers):
 1. Group the frames by their headers: OBJECT (or OBS TARG NAME) and TPL START give the
    sequence, ADA POSANG the orientation, TPL EXPNO the order of the dithers.
 2. Read the two target strips (o-target rows [345,512), e-target [512,679)), as float32
    (16-bit frames are scaled by BZERO/BSCALE by astropy).
 3. Bad pixels: pixels of the per-sequence median frame (the stars dither away) that stand
    out from a 5x5 median filter of it by more than 8 robust sigma.
 4. Sky: each dither minus the median of the other dithers of its orientation, then minus
    the sigma-clipped median of each strip (residual sky level); the sigma-clipped rms of
    the strip is the per-pixel background noise.
 5. Sources: DAOStarFinder on the o strip finds the primary (brightest source); the
    companion is the second source within 8" or, with --pairs, the literature separation
    and position angle (needed below ~1 FWHM, where no finder splits the pair).
 6. Both components in both beams: a joint fit of two Moffat profiles (shared alpha, beta,
    a constant background; scipy least_squares, weights from the noise model) gives the
    positions and the FWHM. Pairs closer than 2 FWHM are measured by these PSF fluxes;
    wider pairs by photutils aperture photometry (CircularAperture, exact overlap, radius
    1 FWHM) after subtracting the fitted companion, local background from a sigma-clipped
    annulus (3-5 FWHM, the other component masked). A dither whose aperture holds a bad
    pixel is dropped for that component.
 7. Polarimetry (docs/polarimetry.md): F = (f_o - f_e)/(f_o + f_e) per dither with
    sigma_F = 2 sqrt(f_e^2 s_o^2 + f_o^2 s_e^2)/(f_o + f_e)^2; dithers more than 5 sigma
    from the orientation's median are rejected (cosmic rays); weighted least squares of
    F_i = q cos 2phi_i + u sin 2phi_i over every dither of every orientation (phi = POSANG
    + theta0); P, gamma = atan2(u, q)/2 in [0, 180), sigma_P, sigma_gamma = 28.65 deg
    sigma_P / P. No instrumental calibration (two orientations: q, u carry the offset).

Output: a JSON catalog (and a CSV next to it) with the run's wall and CPU time.
"""
import argparse
import csv
import json
import math
import os
import resource
import sys
import time
import warnings
from collections import defaultdict

import numpy as np
from astropy.io import fits
from astropy.stats import SigmaClip, sigma_clipped_stats
from photutils.aperture import ApertureStats, CircularAnnulus, CircularAperture, aperture_photometry
from photutils.detection import DAOStarFinder
from scipy.ndimage import median_filter
from scipy.optimize import least_squares

T0_WALL = time.perf_counter()
# CPU spent so far: interpreter start-up and imports (counted once when a bench scales).
_RU0 = resource.getrusage(resource.RUSAGE_SELF)
STARTUP_CPU = _RU0.ru_utime + _RU0.ru_stime

# SOFI profile (frame-format.md): 0-based rows, half-open.
O_TARGET = (345, 512)
E_TARGET = (512, 679)
STRIP = O_TARGET[1] - O_TARGET[0]
GAIN = 5.4  # e-/ADU
PIXSCALE = 0.288


def hval(h, key, default=None):
    try:
        return h[key]
    except KeyError:
        return default


def scan(raw_dir):
    """Headers of every polarimetric science/standard frame, grouped into sequences."""
    seqs = defaultdict(list)
    skipped = []
    for name in sorted(os.listdir(raw_dir)):
        if not (name.endswith(".fits") or name.endswith(".fits.fz") or name.endswith(".fit")):
            continue
        path = os.path.join(raw_dir, name)
        try:
            with fits.open(path) as hdul:
                h = hdul[0].header if hdul[0].header.get("NAXIS", 0) == 2 else hdul[1].header
        except (OSError, IndexError) as e:
            skipped.append(f"{name}: {e}")
            continue
        tech = str(hval(h, "HIERARCH ESO DPR TECH", ""))
        typ = str(hval(h, "HIERARCH ESO DPR TYPE", ""))
        if "POLARIMETRY" not in tech or typ.startswith("FLAT"):
            continue
        obj = str(hval(h, "OBJECT", "")).strip()
        if obj in ("", "STD"):
            obj = str(hval(h, "HIERARCH ESO OBS TARG NAME", name))
        key = (obj, str(hval(h, "HIERARCH ESO TPL START", "")))
        seqs[key].append(
            dict(
                path=path,
                posang=float(h["HIERARCH ESO ADA POSANG"]),
                expno=int(hval(h, "HIERARCH ESO TPL EXPNO", 0)),
                offx=float(hval(h, "HIERARCH ESO SEQ CUMOFFSETX", 0.0)),
                ndit=int(hval(h, "HIERARCH ESO DET NDIT", 1)),
                scale=float(hval(h, "HIERARCH ESO INS PIXSCALE", PIXSCALE)),
                standard=typ.startswith("STD"),
                filter=str(hval(h, "HIERARCH ESO INS FILT1 ID", "")).strip(),
            )
        )
    return seqs, skipped


def read_strips(path):
    """Rows [345, 679) of the primary image (both target strips), float32."""
    with fits.open(path, memmap=False) as hdul:
        hdu = hdul[0] if hdul[0].header.get("NAXIS", 0) == 2 else hdul[1]
        return np.asarray(hdu.data[O_TARGET[0] : E_TARGET[1]], dtype=np.float32)


def bad_pixel_map(stack):
    """Hot and dead pixels of a sequence: outliers of its median frame against a 5x5
    median filter of it (stars dither away in the median)."""
    med = np.median(stack, axis=0)
    resid = med - median_filter(med, size=5, mode="nearest")
    _, m, s = sigma_clipped_stats(resid[::2, ::2], sigma=4.0, maxiters=3)
    return np.abs(resid - m) > 8.0 * max(s, 1e-6)


def sky_subtract(frames):
    """Each frame minus the median of the other frames of its orientation, then minus each
    strip's residual level; returns the frames and each strip's background rms."""
    n = len(frames)
    out = np.empty_like(frames)
    rms = np.empty((n, 2))
    for i in range(n):
        others = np.delete(frames, i, axis=0)
        out[i] = frames[i] - np.median(others, axis=0)
        for b, (r0, r1) in enumerate(((0, STRIP), (STRIP, 2 * STRIP))):
            _, m, s = sigma_clipped_stats(out[i, r0:r1:2, ::2], sigma=3.0, maxiters=5)
            out[i, r0:r1] -= m
            rms[i, b] = s
    return out, rms


def moffat(x, y, x0, y0, flux, alpha, beta):
    r2 = ((x - x0) ** 2 + (y - y0) ** 2) / (alpha * alpha)
    return flux * (beta - 1.0) / (math.pi * alpha * alpha) * (1.0 + r2) ** (-beta)


def fwhm_of(alpha, beta):
    return 2.0 * alpha * math.sqrt(2.0 ** (1.0 / beta) - 1.0)


def fit_pair(img, bad, pos, sky_rms, gain_eff, two):
    """Joint fit of one or two Moffat profiles (shared alpha, beta) plus a constant on a
    window around `pos` [(x, y), ...]. Returns params, flux errors, ok."""
    xs = [p[0] for p in pos[: 2 if two else 1]]
    ys = [p[1] for p in pos[: 2 if two else 1]]
    half = 9
    x0, x1 = int(max(0, min(xs) - half)), int(min(img.shape[1], max(xs) + half + 1))
    y0, y1 = int(max(0, min(ys) - half)), int(min(img.shape[0], max(ys) + half + 1))
    win = img[y0:y1, x0:x1].astype(np.float64)
    good = ~bad[y0:y1, x0:x1] & np.isfinite(win)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    xg, yg, d = xx[good].astype(float), yy[good].astype(float), win[good]
    peak = max(float(np.nanmax(win)), 1.0)
    fwhm0 = 2.8
    alpha0 = fwhm0 / (2.0 * math.sqrt(2.0 ** (1.0 / 3.0) - 1.0))
    p0 = [alpha0, 3.0, 0.0]
    lo = [0.5, 1.2, -np.inf]
    hi = [15.0, 20.0, np.inf]
    for k in range(2 if two else 1):
        f0 = max(peak * 1.5 * alpha0 * alpha0 * (0.5 if k else 1.0), 1.0)
        p0 += [xs[k], ys[k], f0]
        lo += [xs[k] - 3.0, ys[k] - 3.0, -np.inf]
        hi += [xs[k] + 3.0, ys[k] + 3.0, np.inf]

    def model(p):
        m = np.full_like(d, p[2])
        for k in range(3, len(p), 3):
            m += moffat(xg, yg, p[k], p[k + 1], p[k + 2], p[0], p[1])
        return m

    var0 = sky_rms * sky_rms

    def resid(p):
        m = model(p)
        return (d - m) / np.sqrt(var0 + np.maximum(m - p[2], 0.0) / gain_eff)

    try:
        r = least_squares(resid, p0, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=200)
    except ValueError:
        return None, None, False
    try:
        cov = np.linalg.inv(r.jac.T @ r.jac)
        errs = np.sqrt(np.abs(np.diag(cov)))
    except np.linalg.LinAlgError:
        errs = np.full(len(r.x), np.nan)
    return r.x, errs, r.success


def find_primary(o_img, sky_rms):
    finder = DAOStarFinder(threshold=10.0 * sky_rms, fwhm=2.8, exclude_border=True)
    tab = finder(o_img[4:-4])
    if tab is None or len(tab) == 0:
        return None, []
    tab.sort("flux", reverse=True)
    xs = np.asarray(tab["x_centroid" if "x_centroid" in tab.colnames else "xcentroid"])
    ys = np.asarray(tab["y_centroid" if "y_centroid" in tab.colnames else "ycentroid"]) + 4
    fl = np.asarray(tab["flux"])
    return (xs[0], ys[0], fl[0]), list(zip(xs[1:], ys[1:], fl[1:]))


def companion_guess(o_img, prim, others, lit, posang, scale):
    """Position of the companion on the o strip, or None."""
    if lit is not None:
        sep, pa = lit
        th = math.radians(pa - posang)
        dx, dy = -sep * math.sin(th) / scale, sep * math.cos(th) / scale
        # The literature primary may be the fainter one here: take the brighter candidate.
        cands = [(prim[0] + dx, prim[1] + dy), (prim[0] - dx, prim[1] - dy)]
        h, w = o_img.shape

        def value(c):
            xi, yi = int(round(c[0])), int(round(c[1]))
            if not (0 <= xi < w and 0 <= yi < h):
                return -np.inf
            return float(o_img[max(yi - 1, 0) : yi + 2, max(xi - 1, 0) : xi + 2].sum())

        return max(cands, key=value)
    max_sep = 8.0 / scale
    near = [s for s in others if math.hypot(s[0] - prim[0], s[1] - prim[1]) < max_sep and s[2] > 0.03 * prim[2]]
    return (near[0][0], near[0][1]) if near else None


def aperture_fluxes(img, bad, comps, model_params, r_ap, sky_rms, gain_eff):
    """Aperture flux and error of each component (others' fitted profiles subtracted)."""
    a, b = model_params[0], model_params[1]
    n = len(comps)
    fluxes, errs, hit_bad = [], [], []
    h, w = img.shape
    for k, (x, y) in enumerate(comps):
        sub = img
        if n == 2:
            ox, oy, of = model_params[3 + 3 * (1 - k) : 6 + 3 * (1 - k)]
            if math.hypot(ox - x, oy - y) < 6.0 * r_ap:
                # Subtract the neighbour's fitted Moffat on a box around this source.
                r = int(5 * r_ap) + 2
                y0, y1, x0, x1 = max(0, int(y) - r), min(h, int(y) + r + 1), max(0, int(x) - r), min(w, int(x) + r + 1)
                yy, xx = np.mgrid[y0:y1, x0:x1]
                sub = img.copy() if sub is img else sub
                sub[y0:y1, x0:x1] -= moffat(xx, yy, ox, oy, of, a, b).astype(np.float32)
        ap = CircularAperture((x, y), r=r_ap)
        ann = CircularAnnulus((x, y), r_in=3.0 * r_ap, r_out=5.0 * r_ap)
        mask = bad.copy()
        if n == 2:
            ox, oy = comps[1 - k]
            yy, xx = np.ogrid[:h, :w]
            mask |= (xx - ox) ** 2 + (yy - oy) ** 2 < (2.5 * r_ap) ** 2
        st = ApertureStats(sub, ann, mask=mask, sigma_clip=SigmaClip(sigma=3.0, maxiters=5))
        bkg = float(st.median) if np.isfinite(st.median) else 0.0
        n_sky = max(int(st.sum_aper_area.value), 1)
        ph = aperture_photometry(sub, ap, method="exact")
        area = ap.area
        f = float(ph["aperture_sum"][0]) - bkg * area
        var = max(f, 0.0) / gain_eff + area * sky_rms**2 + area**2 * sky_rms**2 / n_sky
        fluxes.append(f)
        errs.append(math.sqrt(var))
        apm = ap.to_mask(method="center").to_image((h, w))
        hit_bad.append(bool(apm is not None and (bad & (apm > 0)).any()))
    return fluxes, errs, hit_bad


def measure_frame(img, bad, rms_o, rms_e, gain_eff, lit, posang, scale, eo, standard, use_psf_sep):
    """Fluxes of A (and B) in both beams of one sky-subtracted frame (o strip rows
    [0, STRIP), e strip [STRIP, 2 STRIP))."""
    o_img = img[:STRIP]
    prim, others = find_primary(o_img, rms_o)
    if prim is None:
        return None
    comp = None if standard else companion_guess(o_img, prim, others, lit, posang, scale)
    two = comp is not None
    pos_o = [(prim[0], prim[1])] + ([comp] if two else [])
    out = {"two": two}
    po, eo_err, ok_o = fit_pair(img, bad, pos_o, rms_o, gain_eff, two)
    if po is None:
        return None
    pos_o = [(po[3], po[4])] + ([(po[6], po[7])] if two else [])
    pos_e = [(x + eo[0], y + eo[1]) for x, y in pos_o]
    pe, ee_err, ok_e = fit_pair(img, bad, pos_e, rms_e, gain_eff, two)
    if pe is None:
        return None
    pos_e = [(pe[3], pe[4])] + ([(pe[6], pe[7])] if two else [])
    fwhm = 0.5 * (fwhm_of(po[0], po[1]) + fwhm_of(pe[0], pe[1]))
    out.update(pos_o=pos_o, pos_e=pos_e, fwhm=fwhm, eo=(pe[3] - po[3], pe[4] - po[4]))
    sep = math.hypot(pos_o[1][0] - pos_o[0][0], pos_o[1][1] - pos_o[0][1]) if two else math.inf
    out["sep_px"] = sep
    if two and sep < use_psf_sep * fwhm:
        out["method"] = "psf_fit"
        out["f_o"] = [po[5], po[8]]
        out["s_o"] = [eo_err[5], eo_err[8]]
        out["f_e"] = [pe[5], pe[8]]
        out["s_e"] = [ee_err[5], ee_err[8]]
        out["bad"] = [False, False]
        for k in range(2):
            for (x, y) in (pos_o[k], pos_e[k]):
                xi, yi = int(round(x)), int(round(y))
                if bad[max(yi - 1, 0) : yi + 2, max(xi - 1, 0) : xi + 2].any():
                    out["bad"][k] = True
    else:
        out["method"] = "aperture"
        r_ap = fwhm
        fo, so, bo = aperture_fluxes(img, bad, pos_o, po, r_ap, rms_o, gain_eff)
        fe, se, be = aperture_fluxes(img, bad, pos_e, pe, r_ap, rms_e, gain_eff)
        out.update(f_o=fo, s_o=so, f_e=fe, s_e=se, bad=[x or y for x, y in zip(bo, be)])
        out["r_ap"] = r_ap
    return out


def stokes(samples, theta0):
    """Weighted least squares of F = q cos 2phi + u sin 2phi over (phi, F, sigma_F)."""
    phi = np.radians(np.array([s[0] for s in samples]) + theta0)
    F = np.array([s[1] for s in samples])
    sF = np.array([s[2] for s in samples])
    A = np.column_stack([np.cos(2 * phi), np.sin(2 * phi)]) / sF[:, None]
    cov = np.linalg.inv(A.T @ A)
    q, u = cov @ (A.T @ (F / sF))
    sq, su = math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])
    p = math.hypot(q, u)
    sp = math.sqrt(q * q * sq * sq + u * u * su * su) / p if p > 0 else math.hypot(sq, su) / math.sqrt(2)
    gamma = (0.5 * math.degrees(math.atan2(u, q))) % 180.0
    return dict(
        q=float(q),
        u=float(u),
        sigma_q=sq,
        sigma_u=su,
        cov_qu=float(cov[0, 1]),
        p=p,
        sigma_p=sp,
        p_debiased=math.sqrt(p * p - sp * sp) if p > sp else 0.0,
        gamma_deg=gamma,
        sigma_gamma_deg=28.6479 * sp / p if p > 0 else 90.0,
    )


def reduce_sequence(obj, tpl, frames, args, lit):
    frames = sorted(frames, key=lambda f: (f["expno"], f["path"]))
    stack = np.stack([read_strips(f["path"]) for f in frames])
    bad = bad_pixel_map(stack)
    by_pa = defaultdict(list)
    for i, f in enumerate(frames):
        by_pa[f["posang"]].append(i)
    standard = frames[0]["standard"]
    ndit = frames[0]["ndit"]
    gain_eff = args.gain * ndit
    scale = frames[0]["scale"]
    eo = (0.0, float(STRIP))
    flags = []
    per = {"A": [], "B": []}  # (posang, F, sigma_F, dither) per component
    fluxes = {"A": [], "B": []}
    fwhms, seps, methods, eos = [], [], [], []
    for pa, idx in sorted(by_pa.items()):
        if len(idx) < 2:
            flags.append(f"POSANG {pa}: {len(idx)} dither(s), cannot sky-subtract")
            continue
        sub, rms = sky_subtract(stack[idx])
        vals = {"A": [], "B": []}
        for j, i in enumerate(idx):
            m = measure_frame(
                sub[j], bad, rms[j, 0], rms[j, 1], gain_eff, lit, pa, scale, eo, standard, args.psf_below_fwhm
            )
            if m is None:
                flags.append(f"primary not found in {os.path.basename(frames[i]['path'])}")
                continue
            eos.append(m["eo"])
            fwhms.append(m["fwhm"])
            methods.append(m["method"])
            if m["two"]:
                seps.append((pa, m["pos_o"][1][0] - m["pos_o"][0][0], m["pos_o"][1][1] - m["pos_o"][0][1]))
            ncomp = 2 if m["two"] else 1
            # A is the brighter component of this frame.
            tot = [m["f_o"][k] + m["f_e"][k] for k in range(ncomp)]
            order = sorted(range(ncomp), key=lambda k: -tot[k])
            for name, k in zip("AB", order):
                fo, fe, so, se = m["f_o"][k], m["f_e"][k], m["s_o"][k], m["s_e"][k]
                if m["bad"][k] or fo + fe <= 0 or not np.isfinite(so * se):
                    continue
                F = (fo - fe) / (fo + fe)
                sF = 2.0 * math.sqrt(fe * fe * so * so + fo * fo * se * se) / (fo + fe) ** 2
                vals[name].append((pa, F, sF, j))
                fluxes[name].append(fo + fe)
        for name in "AB":
            v = vals[name]
            if len(v) >= 3:
                med = np.median([x[1] for x in v])
                keep = [x for x in v if abs(x[1] - med) <= 5.0 * x[2]]
                if len(keep) < len(v):
                    flags.append(f"{name} POSANG {pa}: {len(v) - len(keep)} dither(s) rejected (> 5 sigma)")
                v = keep
            per[name].extend(v)
    comps = []
    for name in "AB":
        pas = {x[0] for x in per[name]}
        if len(pas) < 2:
            if name == "A" or (name == "B" and not standard and per["B"]):
                flags.append(f"{name}: measured at {len(pas)} orientation(s)")
            continue
        c = {"name": name}
        c.update(stokes(per[name], args.theta0))
        c["flux_adu"] = float(np.median(fluxes[name]))
        c["n_dithers"] = len(per[name])
        c["passes_cut"] = c["p"] / c["sigma_p"] > 3.0 if c["sigma_p"] > 0 else False
        comps.append(c)
    t = dict(object=obj, tpl_start=tpl, n_frames=len(frames), components=comps, flags=flags)
    t["fwhm_px"] = float(np.median(fwhms)) if fwhms else None
    t["photometry"] = max(set(methods), key=methods.count) if methods else None
    if eos:
        t["eo_offset_px"] = [float(np.median([e[0] for e in eos])), float(np.median([e[1] for e in eos]))]
    if seps:
        # Separation and PA of B from A on the sky (frame-format.md geometry).
        pa_sky = []
        for pa, dx, dy in seps:
            psi = (pa + math.degrees(math.atan2(-dx, dy))) % 360.0
            pa_sky.append(psi)
        t["separation_arcsec"] = float(np.median([math.hypot(dx, dy) for _, dx, dy in seps]) * scale)
        t["pa_deg"] = float(np.degrees(np.angle(np.mean(np.exp(1j * np.radians(pa_sky))))) % 360.0)
    if len(comps) == 2:
        d = abs(comps[0]["gamma_deg"] - comps[1]["gamma_deg"]) % 180.0
        t["delta_gamma_deg"] = min(d, 180.0 - d)
    return t


def load_pairs(path):
    """Literature geometry: CSV with columns name, separation_arcsec, pa_deg."""
    out = {}
    if not path:
        return out
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            out[row["name"].strip()] = (float(row["separation_arcsec"]), float(row["pa_deg"]))
    return out


def write_atomic(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("raw", help="directory of raw frames")
    ap.add_argument("-o", "--output", required=True, help="catalog JSON (a .csv is written next to it)")
    ap.add_argument("--pairs", help="CSV of literature geometry: name, separation_arcsec, pa_deg")
    ap.add_argument("--targets", type=int, default=0, help="reduce only the first N sequences (by TPL START)")
    ap.add_argument("--gain", type=float, default=GAIN, help="e-/ADU (default 5.4, SOFI)")
    ap.add_argument("--theta0", type=float, default=0.0, help="analyzer zero-point, deg")
    ap.add_argument("--psf-below-fwhm", type=float, default=2.0, help="PSF fluxes for pairs closer than this (FWHM)")
    ap.add_argument("-q", "--quiet", action="store_true")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    seqs, skipped = scan(args.raw)
    keys = sorted(seqs, key=lambda k: (k[1], k[0]))
    if args.targets > 0:
        keys = keys[: args.targets]
    lit = load_pairs(args.pairs)
    targets, failures = [], []
    for n, (obj, tpl) in enumerate(keys):
        try:
            targets.append(reduce_sequence(obj, tpl, seqs[(obj, tpl)], args, lit.get(obj)))
        except Exception as e:  # one bad sequence never ends the night
            failures.append({"object": obj, "tpl_start": tpl, "error": f"{type(e).__name__}: {e}"})
        if not args.quiet:
            print(f"\r[{n + 1}/{len(keys)}] {obj}", end="", file=sys.stderr, flush=True)
    if not args.quiet:
        print(file=sys.stderr)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    wall = time.perf_counter() - T0_WALL
    import astropy
    import photutils
    import scipy

    cat = dict(
        software="sofipol bench/python/reduce_night.py",
        versions=dict(
            python=sys.version.split()[0],
            numpy=np.__version__,
            scipy=scipy.__version__,
            astropy=astropy.__version__,
            photutils=photutils.__version__,
        ),
        command=" ".join(sys.argv),
        targets=targets,
        failures=failures,
        skipped_files=skipped,
        wall_s=wall,
        cpu_s=ru.ru_utime + ru.ru_stime,
        startup_cpu_s=STARTUP_CPU,
        peak_rss_mb=ru.ru_maxrss / 1024.0,
    )
    write_atomic(args.output, json.dumps(cat, indent=1))
    rows = []
    for t in targets:
        for c in t["components"]:
            rows.append(
                [t["object"], t["tpl_start"], c["name"]]
                + [f"{c[k]:.6g}" for k in ("q", "u", "sigma_q", "sigma_u", "p", "sigma_p", "gamma_deg", "sigma_gamma_deg", "flux_adu")]
                + [c["n_dithers"], t["photometry"]]
            )
    csv_path = os.path.splitext(args.output)[0] + ".csv"
    tmp = csv_path + ".tmp"
    with open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["object", "tpl_start", "component", "q", "u", "sigma_q", "sigma_u", "p", "sigma_p", "gamma_deg", "sigma_gamma_deg", "flux_adu", "n_dithers", "photometry"]
        )
        w.writerows(rows)
    os.replace(tmp, csv_path)
    print(
        f"python reduction: {len(targets)} sequence(s), {len(failures)} failed; wall {wall:.2f} s; cpu {cat['cpu_s']:.2f} s; peak RSS {cat['peak_rss_mb']:.0f} MB"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
