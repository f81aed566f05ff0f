#!/usr/bin/env python3
"""Independent reduction of the Keck/NIRC2 L' polarimetry of AB Aur (photutils).

The reference that sofipol's reduction of the same real frames is compared against: a
short, self-contained script written before sofipol could read NIRC2 frames, with numpy,
scipy, astropy and photutils only. It shares no code with sofipol and copies none from the
public NIRC2 pipeline (UCSB-Exoplanet-Polarimetry-Lab/NIRC2Pol-DPP, read at commit
6cd9db7c266842df46cfea74064b428552c034f7, cited below where a convention or a value was
taken from it).

Data (../shared/real/nirc2-abaur-lprime relative to the repository root): NIRC2 narrow
camera, L' + Wollaston, rotating half-wave plate (HWP) angle in `PCUPR`; n0932-n0939 AB Aur
(two complete cycles 0, 45, 22.5, 67.5 deg), n0902-n0905 sky frames at the same four HWP
angles (one cycle, OBJECT 'sky_flat_hwp_*', taken 34 min before, 7.3" away), n0984-n0986
darks (shutter closed, same ITIME 0.45 s x COADDS 45, SAMPMODE 3 MCDS). Pixel values are
ADU summed over the coadds (the darks' frame-to-frame noise is 33 ADU = 8 e-/ADU x 40 e- x
sqrt(45) / 8: DETGAIN and DETRN per coadd, summed).

Steps
 1. Classify the frames from their headers (shutter closed: dark; OBJECT with 'sky': sky
    frame; else science) and check ITIME, COADDS, SAMPMODE, MULTISAM agree.
 2. Master dark: median of the 3 darks. Bad pixels: |dark - median| > 300 ADU (hot/dead,
    ~10 robust sigma), flat response outside [0.5, 1.5] or differing from its 5x5 median by
    more than 20 %, and non-finite pixels. Masked in the photometry (photutils `mask`).
 3. Flat: the mean of the four dark-subtracted sky frames (one whole HWP cycle, so the
    sky's own polarization -- the thermal background is modulated by ~2 % between HWP
    angles -- averages out), normalised to median 1 separately in each beam's region
    (bottom rows 0-469, top rows 545-1023; rows 470-544 are the strip where the two beams'
    skies overlap). Why per beam: the cycle-averaged sky is 9.7 % brighter in the top
    region than in the bottom one, while AB Aur's own light is ~15 % fainter in the top
    beam than in the bottom (raw; 0.928 after this flat, the same from 18-40 to 18-160 px,
    so not a PSF difference): the sky's step between the beams is illumination (e.g.
    polarized thermal emission of optics between the HWP and the Wollaston, which the
    HWP does not modulate), not detector response, and a global normalisation would turn
    it into a false gain step. The remaining starlight imbalance (F constant c = -3.7 %)
    is diattenuation after the HWP plus the beams' transmissions; the double difference
    cancels any constant beam ratio (first order), so q, u do not depend on this choice,
    the per-frame F and the fitted c do (the JSON gives the ratio both ways).
 4. Sky: for each science frame and beam region, the sky frame at the same HWP angle
    (the sky's level changes by up to 3.8 % with the HWP angle, differently in the two
    beams) scaled and offset, S = a K + b, fitted on region pixels more than 200 px from
    the star (4-sigma clipped least squares), then subtracted; the result is divided by
    the flat. AB Aur's halo is still ~0.2 % of the sky at 160-180 px, so no local
    background annulus is used (it would subtract halo light).
 5. Positions: the star's core is saturated (MCDS: the core reads low, a dark hole of
    radius ~5 px inside a ring), so no peak or centroid: each beam's centre is the point
    of 180-degree symmetry of the image between 9 and 40 px (least squares of the image
    against itself rotated by 180 deg, cubic interpolation, Nelder-Mead). o/e pairing: the
    brightest source in each beam region; checked against the expected Wollaston offset
    (dy, dx) = (+505, +13) px within 3 px and a flux ratio within 20 %.
 6. Photometry: photutils `aperture_photometry` with `CircularAnnulus` (exact overlap),
    per-pixel error map and bad-pixel mask, centred on each beam's own centre. The
    inner radius excludes every pixel above the linearity limit (4500 ADU per coadd, the
    NIRC2Pol-DPP post-2023 value, nirc2pol/instruments/nirc2.toml `saturation_after`):
    r_in = 1 px beyond the farthest such pixel over all frames and both beams (18 px on
    these frames). Main aperture: r_in to 40 px (0.4"); curve of growth at r_out = 25,
    30, 40, 60, 80 px and a second inner radius r_in + 5. The flux measured is thus AB
    Aur's PSF wings plus the unresolved and inner disk within 0.4", not the core.
 7. Errors: per pixel, variance (ADU^2) = photon noise of the science frame (its
    dark-subtracted value / gain) + COADDS x (RN/gain)^2, plus the same for the
    subtracted sky frame times a^2, divided by flat^2; gain = DETGAIN = 8 e-/ADU, RN =
    DETRN = 40 e- per coadd read (header values; a photon-transfer check on the sky gives
    9-10 e-/ADU, inflated by interpixel capacitance; DETGAIN is used). Note the two
    cycles share the four sky frames, so the cycle-to-cycle scatter does not see that
    part of the noise.
 8. Polarimetry. o = top beam, e = bottom beam, F = (o - e)/(o + e) per frame (the
    NIRC2Pol-DPP sign, nirc2pol/polarimetry/stokes.py: Q = I_top - I_bottom at HWP 0,
    which its fast-axis zero point below refers to). HWP angle h = PCUPR.
    (a) Double difference per complete cycle: q = (F_0 - F_45)/2, u = (F_22.5 - F_67.5)/2;
        combined = mean of the cycles; errors propagated, and the scatter |x1 - x2|/2.
    (b) Weighted least squares over all 8 frames: F_i = c + q cos 4h_i + u sin 4h_i (c:
        beam imbalance); errors from the covariance, and scaled by sqrt(chi2/5).
    P = sqrt(q^2 + u^2) (not debiased: P/sigma_P >> 3), angle = atan2(u, q)/2 in
    [0, 180), sigma_angle = 28.65 deg sigma_P/P. Instrument frame: angle from the
    Wollaston's top-beam axis, HWP zero point unknown.
 9. Sky frame, following NIRC2Pol-DPP's idealized rotation model
    (nirc2pol/instruments/nirc2.py `qu_rotation_angle`, stokes.py `rotate_qu`):
    theta_rot = -2 PARANG + 2 EL + 2 ROTPDEST + 4 theta_off, with Q' = Q cos theta_rot +
    U sin theta_rot, U' = -Q sin theta_rot + U cos theta_rot. The EL and ROTPDEST terms
    say the HWP sits upstream of the AO image rotator (K-mirror, physical angle OBRT =
    ROTPDEST/2); in 'vertical angle' (pupil-tracking) mode ROTPDEST = EL + ROTPOSN, so
    theta_rot = -2 PARANG + 4 EL + 2 ROTPOSN + 4 theta_off. theta_off = -13.0 deg is the
    HWP fast-axis offset NIRC2Pol-DPP's tutorial uses "for this epoch of AB Aur"
    (examples/tutorial.ipynb; -13.1 in instpol.py for 23 cycles): it was fitted on this
    disk's butterfly pattern assuming azimuthal polarization, has no independent
    calibration, and is ambiguous by 45 deg. Everything on the sky depends on it (each
    degree of theta_off turns the sky angle by 2 deg); with DPP's radial-Stokes
    convention (phi = atan2(y, x), north up, east left after derotation) the angle
    atan2(U', Q')/2 is east of north. The sky values come from the double difference
    rotated by each cycle's mean theta_rot, and from the least squares
    F_i = c + q' cos(4h_i - theta_rot,i) + u' sin(4h_i - theta_rot,i) (the instrument frame
    turns by ~19 deg in Q/U over the 8 frames). No instrumental-polarization
    correction: NIRC2Pol-DPP's own estimate on this night (ipq = -0.76 %, instpol.py,
    fitted on the disk with the same assumption) is of the size of the result.

Literature check (no published L' aperture value of AB Aur was found): Li et al. 2016
(ApJ, GTC/CanariCam, 10.3 um) find ~0.44 % from the inner disk (r < 80 au), ~1.4 % further
out; optical values of Herbig Ae stars are a few 0.1 % and variable. The 0.7-1.1 % found
here (aperture-dependent, instrumental polarization included) is of that order, no more.

Output: a JSON (default testdata/real/nirc2_abaur_reference.json): per frame the headers
used, centres, fluxes and F; per cycle and combined q, u, P, angle with both errors, in
the instrument and the sky frame; the curve of growth; method, versions, date, inputs.

Run: python bench/python/nirc2_reference.py [DIR] [-o OUT.json]
(exits 0 with "skipped: ... absent" when DIR is missing).
"""
import argparse
import datetime
import json
import math
import os
import sys

import numpy as np

try:
    import astropy
    import photutils
    import scipy
    from astropy.io import fits
    from photutils.aperture import CircularAnnulus, aperture_photometry
    from scipy import ndimage, optimize
except ImportError as err:  # pragma: no cover - environment problem, said plainly
    sys.exit(f"nirc2_reference.py needs numpy, scipy, astropy, photutils: {err}")

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_DIR = os.path.join(REPO, "..", "shared", "real", "nirc2-abaur-lprime")
DEFAULT_OUT = os.path.join(REPO, "testdata", "real", "nirc2_abaur_reference.json")

BOTTOM_ROWS = (0, 470)      # bottom beam region (0-based, half-open)
TOP_ROWS = (545, 1024)      # top beam region; 470-544 is the overlap strip of both skies
BEAM_OFFSET = (505.0, 13.0)  # expected top - bottom (dy, dx), px (NIRC2Pol-DPP finds 504, 13)
LIN_LIMIT = 4500.0          # ADU per coadd (NIRC2Pol-DPP nirc2.toml saturation_after)
SKY_FIT_RMIN = 200.0        # px: sky scale/offset fitted beyond this radius from the star
SYM_RIN, SYM_ROUT = 9.0, 40.0  # px: annulus of the symmetry centring
R_OUT_MAIN = 40.0
R_OUT_GROWTH = (25.0, 30.0, 40.0, 60.0, 80.0)
THETA_OFF_DPP = -13.0       # deg, NIRC2Pol-DPP tutorial value for this epoch (see docstring)
HOT_ADU = 300.0


def load(path):
    with fits.open(path) as hdul:
        return hdul[0].data.astype(np.float64), hdul[0].header.copy()


def classify(directory):
    darks, skies, sci = [], [], []
    for name in sorted(os.listdir(directory)):
        if not name.endswith((".fits", ".fits.gz")):
            continue
        data, hdr = load(os.path.join(directory, name))
        rec = {"file": name, "data": data, "hdr": hdr}
        if str(hdr.get("SHRNAME", "")).strip().lower() == "closed":
            darks.append(rec)
        elif "sky" in str(hdr.get("OBJECT", "")).lower():
            skies.append(rec)
        else:
            sci.append(rec)
    return darks, skies, sci


def check_setup(frames):
    keys = ("ITIME", "COADDS", "SAMPMODE", "MULTISAM")
    ref = frames[0]
    for f in frames[1:]:
        for k in keys:
            if f["hdr"].get(k) != ref["hdr"].get(k):
                sys.exit(f"{f['file']}: {k} = {f['hdr'].get(k)!r} differs from "
                         f"{ref['file']} ({ref['hdr'].get(k)!r})")


def region_mask(shape, rows):
    m = np.zeros(shape, bool)
    m[rows[0]:rows[1], :] = True
    return m


def sym_center(img, guess, rin=SYM_RIN, rout=SYM_ROUT):
    """Centre of 180-degree symmetry of img between rin and rout (px), (y, x)."""
    half = int(rout) + 1
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    r = np.hypot(yy, xx)
    sel = (r > rin) & (r < rout)
    dy, dx = yy[sel].astype(float), xx[sel].astype(float)
    # a cut-out around the guess, spline-filtered once (cubic interpolation)
    pad = half + 16
    y0, x0 = int(round(guess[0])) - pad, int(round(guess[1])) - pad
    cut = ndimage.spline_filter(img[y0:y0 + 2 * pad + 1, x0:x0 + 2 * pad + 1], order=3)

    def cost(p):
        cy, cx = p[0] - y0, p[1] - x0
        a = ndimage.map_coordinates(cut, [cy + dy, cx + dx], order=3, prefilter=False)
        b = ndimage.map_coordinates(cut, [cy - dy, cx - dx], order=3, prefilter=False)
        return float(np.sum((a - b) ** 2))

    # coarse 1-px grid over +-12 px first: the saturated ring fools a local start
    grid = [(guess[0] + gy, guess[1] + gx) for gy in range(-12, 13) for gx in range(-12, 13)]
    start = min(grid, key=cost)
    res = optimize.minimize(cost, start, method="Nelder-Mead",
                            options={"xatol": 1e-3, "fatol": 1e-12, "maxiter": 2000})
    return float(res.x[0]), float(res.x[1])


def brightest(img, rows, bad):
    """Rough position of the brightest smoothed source in a beam region (y, x)."""
    clean = np.where(bad, 0.0, img)[rows[0]:rows[1], :]
    sub = ndimage.uniform_filter(ndimage.median_filter(clean, 5), 15)
    sub[:20, :] = -np.inf
    sub[-20:, :] = -np.inf
    sub[:, :20] = -np.inf
    sub[:, -20:] = -np.inf
    y, x = np.unravel_index(np.argmax(sub), sub.shape)
    return float(y + rows[0]), float(x)


def fit_sky(sci, sky, region, center, bad):
    """S ~ a K + b on region pixels beyond SKY_FIT_RMIN from the star (4-sigma clipped)."""
    yy, xx = np.indices(sci.shape)
    use = region & ~bad & (np.hypot(yy - center[0], xx - center[1]) > SKY_FIT_RMIN)
    s, k = sci[use], sky[use]
    good = np.ones(s.size, bool)
    for _ in range(6):
        A = np.vstack([k[good], np.ones(good.sum())]).T
        (a, b), *_ = np.linalg.lstsq(A, s[good], rcond=None)
        res = s - (a * k + b)
        sig = 1.4826 * np.median(np.abs(res[good]))
        new = np.abs(res) < 4 * sig
        if np.array_equal(new, good):
            break
        good = new
    return float(a), float(b), float(sig), int(good.sum())


def wls(F, sF, cols):
    """Weighted least squares F = X p; returns p, covariance, chi2."""
    X = np.column_stack(cols)
    w = 1.0 / sF ** 2
    cov = np.linalg.inv(X.T @ (X * w[:, None]))
    p = cov @ (X.T @ (w * F))
    chi2 = float(np.sum(w * (F - X @ p) ** 2))
    return p, cov, chi2


def pol(q, u, sq, su):
    P = math.hypot(q, u)
    sP = math.sqrt((q * sq) ** 2 + (u * su) ** 2) / P if P > 0 else math.hypot(sq, su)
    ang = math.degrees(0.5 * math.atan2(u, q)) % 180.0
    sang = math.degrees(0.5 * sP / P) if P > 0 else 90.0
    return {"p": P, "sigma_p": sP, "angle_deg": ang, "sigma_angle_deg": sang}


def rotate(q, u, theta_deg):
    t = math.radians(theta_deg)
    return q * math.cos(t) + u * math.sin(t), -q * math.sin(t) + u * math.cos(t)


def theta_rot(h, theta_off=THETA_OFF_DPP):
    """NIRC2Pol-DPP idealized Q/U rotation (nirc2pol/instruments/nirc2.py, 6cd9db7)."""
    parang = h["PARANG"] + (360.0 if h["PARANG"] < 0 else 0.0)
    return -2.0 * parang + 2.0 * h["EL"] + 2.0 * h["ROTPDEST"] + 4.0 * theta_off


def circ_mean_deg(angles, period=360.0):
    a = np.radians(np.asarray(angles) * 360.0 / period)
    return float(np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean())) * period / 360.0)


def entry(q, u, sq, su, sq_scatter=None, su_scatter=None):
    d = {"q": q, "u": u, "sigma_q": sq, "sigma_u": su}
    d.update(pol(q, u, sq, su))
    if sq_scatter is not None:
        d["sigma_q_scatter"] = sq_scatter
        d["sigma_u_scatter"] = su_scatter
        d["scatter"] = {k: v for k, v in pol(q, u, sq_scatter, su_scatter).items()
                        if k.startswith("sigma")}
    return d


def photometry(img, err, bad, center, r_in, r_out):
    ap = CircularAnnulus((center[1], center[0]), r_in=r_in, r_out=r_out)
    t = aperture_photometry(img, ap, error=err, mask=bad, method="exact")
    return float(t["aperture_sum"][0]), float(t["aperture_sum_err"][0])


def reduce_all(directory, sky_mode="matched", flat_norm="beam"):
    darks, skies, sci = classify(directory)
    if len(darks) < 1 or len(skies) != 4 or len(sci) < 4:
        sys.exit(f"{directory}: expected darks, 4 sky frames and science frames; found "
                 f"{len(darks)}, {len(skies)}, {len(sci)}")
    check_setup(darks + skies + sci)
    h0 = sci[0]["hdr"]
    gain, rn, coadds = float(h0["DETGAIN"]), float(h0["DETRN"]), int(h0["COADDS"])

    dark = np.median([d["data"] for d in darks], axis=0)
    dmed = np.median(dark)
    bad = ~np.isfinite(dark) | (np.abs(dark - dmed) > HOT_ADU)

    sky_by_angle = {}
    for s in skies:
        ang = round(float(s["hdr"]["PCUPR"]) / 22.5) * 22.5 % 180.0
        sky_by_angle[ang] = s
    if sorted(sky_by_angle) != [0.0, 22.5, 45.0, 67.5]:
        sys.exit(f"{directory}: sky frames do not form one HWP cycle: {sorted(sky_by_angle)}")
    K = {a: s["data"] - dark for a, s in sky_by_angle.items()}
    flat_raw = np.mean([K[a] for a in K], axis=0)
    shape = dark.shape
    reg = {"top": region_mask(shape, TOP_ROWS), "bottom": region_mask(shape, BOTTOM_ROWS)}
    flat = np.ones(shape)
    flat_levels = {}
    for name, m in reg.items():
        flat_levels[name] = float(np.median(flat_raw[m]))
    both = float(np.median(flat_raw[reg["top"] | reg["bottom"]]))
    for name, m in reg.items():
        flat[m] = flat_raw[m] / (flat_levels[name] if flat_norm == "beam" else both)
    strip = ~(reg["top"] | reg["bottom"])
    flat[strip] = flat_raw[strip] / np.mean(list(flat_levels.values()))
    local = ndimage.median_filter(flat, 5)
    bad |= ~np.isfinite(flat) | (flat < 0.5) | (flat > 1.5) | (np.abs(flat / local - 1) > 0.2)
    flat_safe = np.where(bad, 1.0, flat)

    frames = []
    for s in sorted(sci, key=lambda r: r["hdr"]["MJD"]):
        h = s["hdr"]
        hwp = float(h["PCUPR"])
        key = round(hwp / 22.5) * 22.5 % 180.0
        if abs(((hwp - key + 90) % 180) - 90) > 1.0 or key not in K:
            sys.exit(f"{s['file']}: PCUPR = {hwp} is not a critical HWP angle")
        S = s["data"] - dark
        Ksky = K[key] if sky_mode == "matched" else flat_raw
        rough = {"bottom": brightest(S - Ksky, BOTTOM_ROWS, bad),
                 "top": brightest(S - Ksky, TOP_ROWS, bad)}
        img = np.zeros(shape)
        var = np.zeros(shape)
        sky_fit = {}
        for name in ("bottom", "top"):
            a, b, sig, n = fit_sky(S, Ksky, reg[name], rough[name], bad)
            sky_fit[name] = {"scale": a, "offset_adu": b, "resid_sigma_adu": sig, "npix": n}
            m = reg[name]
            img[m] = ((S - a * Ksky - b) / flat_safe)[m]
            # the cycle-mean sky averages 4 frames: a quarter of one frame's variance
            nsky = 1.0 if sky_mode == "matched" else float(len(K))
            v = (np.clip(S, 0, None) / gain + coadds * (rn / gain) ** 2
                 + a * a * (np.clip(Ksky, 0, None) / gain + coadds * (rn / gain) ** 2) / nsky)
            var[m] = (v / flat_safe ** 2)[m]
        centers = {name: sym_center(img, rough[name]) for name in ("bottom", "top")}
        d = (centers["top"][0] - centers["bottom"][0], centers["top"][1] - centers["bottom"][1])
        if abs(d[0] - BEAM_OFFSET[0]) > 3 or abs(d[1] - BEAM_OFFSET[1]) > 3:
            sys.exit(f"{s['file']}: top - bottom offset {d} is not the Wollaston's "
                     f"{BEAM_OFFSET} within 3 px: o/e pairing failed")
        # raw level per coadd, for the saturation radius
        sat_r = 0.0
        yy, xx = np.indices(shape)
        for name in ("bottom", "top"):
            c = centers[name]
            r = np.hypot(yy - c[0], xx - c[1])
            near = (r < 60) & ~bad
            over = near & (S / coadds > LIN_LIMIT)
            if over.any():
                sat_r = max(sat_r, float(r[over].max()))
        frames.append({"file": s["file"], "hdr": h, "hwp": hwp, "img": img,
                       "err": np.sqrt(var), "centers": centers, "offset": d,
                       "sky_fit": sky_fit, "sat_r": sat_r,
                       "raw_max_per_coadd": float(np.max(S[~bad]) / coadds)})
    return frames, bad, flat_levels, gain, rn, coadds, [d["file"] for d in darks], \
        [s["file"] for s in skies]


def polarimetry(frames, r_in, r_out, bad):
    rows = []
    for f in frames:
        o, so = photometry(f["img"], f["err"], bad, f["centers"]["top"], r_in, r_out)
        e, se = photometry(f["img"], f["err"], bad, f["centers"]["bottom"], r_in, r_out)
        if abs(o / e - 1.0) > 0.2:
            sys.exit(f"{f['file']}: top/bottom flux ratio {o / e:.3f} is not within 20 % of 1: "
                     "the two images found are not the o and e images of one star")
        F = (o - e) / (o + e)
        sF = 2.0 * math.sqrt((e * so) ** 2 + (o * se) ** 2) / (o + e) ** 2
        rows.append({"o": o, "sigma_o": so, "e": e, "sigma_e": se, "F": F, "sigma_F": sF})
    hwp = np.array([f["hwp"] for f in frames])
    F = np.array([r["F"] for r in rows])
    sF = np.array([r["sigma_F"] for r in rows])

    # (a) double difference per complete cycle (frames in time order, 4 per cycle)
    cycles = []
    for c0 in range(0, len(frames) - 3, 4):
        idx = {round(hwp[i] / 22.5) * 22.5 % 180.0: i for i in range(c0, c0 + 4)}
        if sorted(idx) != [0.0, 22.5, 45.0, 67.5]:
            sys.exit(f"frames {c0}..{c0 + 3} are not one complete HWP cycle")
        q = 0.5 * (F[idx[0.0]] - F[idx[45.0]])
        u = 0.5 * (F[idx[22.5]] - F[idx[67.5]])
        sq = 0.5 * math.hypot(sF[idx[0.0]], sF[idx[45.0]])
        su = 0.5 * math.hypot(sF[idx[22.5]], sF[idx[67.5]])
        th = circ_mean_deg([theta_rot(frames[i]["hdr"]) for i in range(c0, c0 + 4)])
        qs, us = rotate(q, u, th)
        cycles.append({"frames": [frames[i]["file"] for i in range(c0, c0 + 4)],
                       "instrument": entry(q, u, sq, su),
                       "theta_rot_deg": th,
                       "sky": entry(qs, us, sq, su)})
    n = len(cycles)

    def combine(frame_key):
        qs = np.array([c[frame_key]["q"] for c in cycles])
        us = np.array([c[frame_key]["u"] for c in cycles])
        sq = math.sqrt(sum(c[frame_key]["sigma_q"] ** 2 for c in cycles)) / n
        su = math.sqrt(sum(c[frame_key]["sigma_u"] ** 2 for c in cycles)) / n
        scq = float(np.std(qs, ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
        scu = float(np.std(us, ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
        return entry(float(qs.mean()), float(us.mean()), sq, su, scq, scu)

    dd = {"instrument": combine("instrument"), "sky": combine("sky")}

    # (b) least squares over all frames, with a constant (beam imbalance)
    ones = np.ones_like(F)
    p, cov, chi2 = wls(F, sF, [ones, np.cos(np.radians(4 * hwp)), np.sin(np.radians(4 * hwp))])
    dof = len(F) - 3
    scale = math.sqrt(chi2 / dof)
    lsq_inst = entry(float(p[1]), float(p[2]), math.sqrt(cov[1, 1]), math.sqrt(cov[2, 2]),
                     math.sqrt(cov[1, 1]) * scale, math.sqrt(cov[2, 2]) * scale)
    lsq_inst.update({"c": float(p[0]), "sigma_c": math.sqrt(cov[0, 0]), "chi2": chi2, "dof": dof})
    th = np.array([theta_rot(f["hdr"]) for f in frames])
    arg = np.radians(4 * hwp - th)
    p2, cov2, chi22 = wls(F, sF, [ones, np.cos(arg), np.sin(arg)])
    scale2 = math.sqrt(chi22 / dof)
    lsq_sky = entry(float(p2[1]), float(p2[2]), math.sqrt(cov2[1, 1]), math.sqrt(cov2[2, 2]),
                    math.sqrt(cov2[1, 1]) * scale2, math.sqrt(cov2[2, 2]) * scale2)
    lsq_sky.update({"c": float(p2[0]), "sigma_c": math.sqrt(cov2[0, 0]), "chi2": chi22,
                    "dof": dof})
    return rows, cycles, dd, {"instrument": lsq_inst, "sky": lsq_sky}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("directory", nargs="?", default=DEFAULT_DIR)
    ap.add_argument("-o", "--output", default=DEFAULT_OUT)
    ap.add_argument("--sky", choices=("matched", "cycle-mean"), default="matched",
                    help="sky frame subtracted: the one at the same HWP angle (default) or "
                         "the mean of the cycle (a systematics check)")
    ap.add_argument("--flat-norm", choices=("beam", "global"), default="beam",
                    help="flat normalised per beam region (default) or once (a check)")
    ap.add_argument("--no-checks", dest="checks", action="store_false",
                    help="skip the reruns with the other sky and flat choices")
    args = ap.parse_args()
    directory = os.path.normpath(args.directory)
    if not os.path.isdir(directory):
        print(f"skipped: {directory} absent")
        return 0

    frames, bad, flat_levels, gain, rn, coadds, dark_files, sky_files = reduce_all(
        directory, sky_mode=args.sky, flat_norm=args.flat_norm)
    r_in = float(math.ceil(max(f["sat_r"] for f in frames) + 1.0))

    rows, cycles, dd, lsq = polarimetry(frames, r_in, R_OUT_MAIN, bad)

    checks = {}
    if args.checks and args.sky == "matched" and args.flat_norm == "beam":
        for label, kw in (("sky_cycle_mean", {"sky_mode": "cycle-mean"}),
                          ("flat_global", {"flat_norm": "global"})):
            fr_c, bad_c, *_ = reduce_all(directory, **kw)
            _, _, dd_c, lsq_c = polarimetry(fr_c, r_in, R_OUT_MAIN, bad_c)
            checks[label] = {"double_difference": dd_c, "least_squares": lsq_c}

    growth = []
    for r_i in (r_in, r_in + 5.0):
        for r_o in R_OUT_GROWTH:
            if r_o <= r_i + 2:
                continue
            _, _, ddg, lsqg = polarimetry(frames, r_i, r_o, bad)
            growth.append({"r_in": r_i, "r_out": r_o,
                           "dd_instrument": {k: ddg["instrument"][k] for k in
                                             ("q", "u", "sigma_q", "sigma_u",
                                              "sigma_q_scatter", "sigma_u_scatter",
                                              "p", "angle_deg")},
                           "lsq_instrument": {k: lsqg["instrument"][k] for k in
                                              ("q", "u", "sigma_q", "sigma_u", "c", "chi2")}})

    # beam flux ratio top/bottom averaged over the cycles (step 3's argument); the other
    # normalisation divides the top by a flat g = 1.097 times higher (or lower)
    ratio = float(np.mean([r["o"] / r["e"] for r in rows]))
    g = flat_levels["top"] / flat_levels["bottom"]
    ratio_beam = ratio if args.flat_norm == "beam" else ratio * g
    ratio_global = ratio_beam / g
    out_frames = []
    for f, r in zip(frames, rows):
        h = f["hdr"]
        out_frames.append({
            "file": f["file"], "object": h["OBJECT"], "pcupr_deg": f["hwp"],
            "mjd": h["MJD"], "parang_deg": h["PARANG"], "el_deg": h["EL"],
            "rotpdest_deg": h["ROTPDEST"], "rotposn_deg": h["ROTPOSN"],
            "theta_rot_deg": theta_rot(h),
            "center_top_yx": list(f["centers"]["top"]),
            "center_bottom_yx": list(f["centers"]["bottom"]),
            "offset_top_minus_bottom_yx": list(f["offset"]),
            "sky_fit": f["sky_fit"], "max_adu_per_coadd": f["raw_max_per_coadd"],
            "saturation_radius_px": f["sat_r"], **r})

    result = {
        "origin": {
            "script": "bench/python/nirc2_reference.py",
            "python": sys.version.split()[0], "numpy": np.__version__,
            "scipy": scipy.__version__, "astropy": astropy.__version__,
            "photutils": photutils.__version__,
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
            "data": "../shared/real/nirc2-abaur-lprime (NIRC2Pol-DPP "
                    "examples/tutorial_data/raw, Keck II NIRC2, 2025-12-08 UT)",
            "inputs": {"science": [f["file"] for f in frames], "sky": sorted(sky_files),
                       "dark": sorted(dark_files)},
            "conventions_from": "UCSB-Exoplanet-Polarimetry-Lab/NIRC2Pol-DPP commit "
                                "6cd9db7c266842df46cfea74064b428552c034f7",
        },
        "method": {
            "summary": "dark (median of 3); flat = mean of the 4 dark-subtracted sky frames "
                       "(one HWP cycle) normalised to median 1 per beam region; sky = "
                       "matched-HWP sky frame scaled+offset per beam region (fit beyond "
                       f"{SKY_FIT_RMIN:.0f} px), then /flat; centres = 180-deg symmetry "
                       f"({SYM_RIN:.0f}-{SYM_ROUT:.0f} px); photutils CircularAnnulus exact, "
                       "r_in beyond the saturated core; F = (top - bottom)/(top + bottom); "
                       "double difference per cycle and weighted least squares "
                       "F = c + q cos4h + u sin4h over all frames",
            "sky_subtraction": args.sky, "flat_normalisation": args.flat_norm,
            "o_beam": "top", "e_beam": "bottom",
            "beam_regions_rows": {"bottom": list(BOTTOM_ROWS), "top": list(TOP_ROWS)},
            "gain_e_per_adu": gain, "gain_source": "DETGAIN",
            "read_noise_e_per_coadd": rn, "read_noise_source": "DETRN", "coadds": coadds,
            "linearity_limit_adu_per_coadd": LIN_LIMIT,
            "aperture": {"shape": "CircularAnnulus", "r_in_px": r_in,
                         "r_out_px": R_OUT_MAIN, "method": "exact",
                         "r_in_rule": "1 px beyond the farthest pixel above the linearity "
                                      "limit (any frame, either beam), rounded up"},
            "flat_levels_adu": flat_levels,
            "beam_ratio_top_over_bottom_per_beam_flat": ratio_beam,
            "beam_ratio_top_over_bottom_global_flat": ratio_global,
            "sky_frame": {
                "rotation": "theta_rot = -2 PARANG + 2 EL + 2 ROTPDEST + 4 theta_off; "
                            "Q' = Q cos theta_rot + U sin theta_rot, "
                            "U' = -Q sin theta_rot + U cos theta_rot (NIRC2Pol-DPP)",
                "theta_off_deg": THETA_OFF_DPP,
                "theta_off_source": "NIRC2Pol-DPP examples/tutorial.ipynb, fitted on AB Aur's "
                                    "disk assuming azimuthal polarization; 45-deg ambiguous",
                "angle": "east of north if theta_off is right",
                "instrumental_polarization": "not corrected",
            },
            "literature": "no published L' aperture polarization of AB Aur found; Li et al. "
                          "2016 (ApJ, CanariCam 10.3 um): ~0.44 % inner disk (r < 80 au), "
                          "~1.4 % beyond",
        },
        "frames": out_frames,
        "cycles": cycles,
        "combined": {"double_difference": dd, "least_squares": lsq},
        "curve_of_growth": growth,
        "checks": checks,
    }
    out = os.path.abspath(args.output)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(result, fh, indent=1, allow_nan=False)  # strict JSON for serde
        fh.write("\n")

    print(f"{len(frames)} science frames, r_in = {r_in:.0f} px, r_out = {R_OUT_MAIN:.0f} px; "
          f"gain {gain} e-/ADU, RN {rn} e-/coadd")
    print(f"top/bottom flux ratio {ratio_beam:.4f} (per-beam flat), {ratio_global:.4f} "
          f"(global flat)")
    for f, r in zip(out_frames, rows):
        print(f"  {f['file']} h={f['pcupr_deg']:7.3f} F={r['F']:+.5f} +- {r['sigma_F']:.5f} "
              f"offset=({f['offset_top_minus_bottom_yx'][0]:.2f}, "
              f"{f['offset_top_minus_bottom_yx'][1]:.2f})")
    for i, c in enumerate(cycles):
        ci, cs = c["instrument"], c["sky"]
        print(f"cycle {i + 1}: q={ci['q']:+.5f} u={ci['u']:+.5f} +- {ci['sigma_q']:.5f} "
              f"P={ci['p']:.5f} ang={ci['angle_deg']:.1f} | sky q={cs['q']:+.5f} "
              f"u={cs['u']:+.5f} ang={cs['angle_deg']:.1f}")
    for name, block in (("DD", dd), ("LSQ", lsq)):
        for fr in ("instrument", "sky"):
            b = block[fr]
            print(f"{name:3s} {fr:10s} q={b['q']:+.5f} u={b['u']:+.5f} "
                  f"(phot {b['sigma_q']:.5f}/{b['sigma_u']:.5f}, scatter "
                  f"{b['sigma_q_scatter']:.5f}/{b['sigma_u_scatter']:.5f}) "
                  f"P={b['p'] * 100:.3f} % +- {b['sigma_p'] * 100:.3f} "
                  f"angle={b['angle_deg']:.1f} deg" +
                  (f" c={b['c']:+.5f} chi2={b['chi2']:.1f}/{b['dof']}" if "c" in b else ""))
    for g_ in growth:
        b = g_["dd_instrument"]
        print(f"growth r={g_['r_in']:.0f}-{g_['r_out']:.0f}: q={b['q']:+.5f} u={b['u']:+.5f} "
              f"P={b['p'] * 100:.3f} % angle={b['angle_deg']:.1f} (scatter "
              f"{b['sigma_q_scatter']:.5f}/{b['sigma_u_scatter']:.5f})")
    for label, blk in checks.items():
        b = blk["double_difference"]["instrument"]
        print(f"check {label}: DD q={b['q']:+.5f} u={b['u']:+.5f} P={b['p'] * 100:.3f} % "
              f"angle={b['angle_deg']:.1f}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
