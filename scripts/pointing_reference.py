"""Reference values of the simulator's pointing model (pipeline/src/sim/pointing.rs),
computed independently with astropy for the NTT at La Silla.

    target/python-env/bin/python scripts/pointing_reference.py

(`bash scripts/python-env.sh` creates the venv.) Prints the Rust table stored in
pipeline/tests/sim_pointing.rs. For each (MJD UTC, RA, Dec): Greenwich mean sidereal time
(IAU 1982), local sidereal time, hour angle, altitude and the parallactic angle eta. The
altitude comes from astropy's own frame transformation (TETE -> AltAz, no refraction), and
eta is the position angle (north through east) of the zenith seen from the star, taken on
the sky with SkyCoord.position_angle: neither uses the formulas of pointing.rs. RA and Dec
are given in the true-equator-and-equinox frame of the date (TETE), which is what the
simulator's RA and DEC stand for; UT1 is taken equal to UTC as in the simulator. astropy
refers a true-equinox RA to the apparent sidereal time, the simulator to the mean one: the
equation of the equinoxes (< 1.2 s) is the largest difference left (arcseconds in the
altitude, < 0.01 deg in eta away from the zenith).
"""
from astropy.coordinates import TETE, AltAz, EarthLocation, SkyCoord
from astropy.time import Time
from astropy.utils import iers
import astropy.units as u

iers.conf.auto_download = False
SITE = EarthLocation.from_geodetic(lon=-70.7346 * u.deg, lat=-29.2567 * u.deg, height=2375 * u.m)

CASES = [
    # (MJD UTC, RA deg, Dec deg, what)
    (51240.0486, 120.0, -40.0, "1999-03-03 01:10 UT, east of the meridian"),
    (51240.2000, 150.0, -60.0, "1999-03-03 04:48 UT, south, near transit"),
    (51240.3000, 130.0, 5.0, "1999-03-03 07:12 UT, north of the zenith, west"),
    (51240.1500, 200.0, -75.0, "circumpolar side, east"),
    (57023.2500, 85.0, -20.0, "2015-01-02 06:00 UT, west"),
    (60300.0700, 30.0, -10.0, "2023-12-22 01:41 UT, west"),
    (60300.0700, 330.0, 15.0, "2023-12-22 01:41 UT, low in the north-west"),
    (51240.1200, 135.0, -29.0, "0.26 deg from the zenith at transit: 8 min before"),
    (51240.1244, 135.0, -29.0, "2 min before transit"),
    (51240.1272, 135.0, -29.0, "2 min after transit"),
    (51240.1310, 135.0, -29.0, "8 min after transit"),
]

print("// (mjd, ra_deg, dec_deg, gmst_deg, lst_deg, hour_angle_deg, alt_deg, eta_deg)")
for mjd, ra, dec, what in CASES:
    t = Time(mjd, format="mjd", scale="utc", location=SITE)
    t.delta_ut1_utc = 0.0
    gmst = t.sidereal_time("mean", "greenwich", model="IAU1982").deg
    lst = t.sidereal_time("mean", model="IAU1982").deg
    ha = (lst - ra + 180.0) % 360.0 - 180.0
    frame = TETE(obstime=t, location=SITE)
    star = SkyCoord(ra * u.deg, dec * u.deg, frame=frame)
    altaz = AltAz(obstime=t, location=SITE)
    alt = star.transform_to(altaz).alt.deg
    zenith = SkyCoord(alt=90 * u.deg, az=0 * u.deg, frame=altaz).transform_to(frame)
    eta = star.position_angle(zenith).deg
    eta = (eta + 180.0) % 360.0 - 180.0
    print(f"    ({mjd}, {ra}, {dec}, {gmst:.6f}, {lst:.6f}, {ha:.6f}, {alt:.5f}, {eta:.4f}), // {what}")
