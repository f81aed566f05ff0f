//! Where the telescope points: sidereal time, hour angle, altitude, airmass and the
//! parallactic angle of a target at the NTT on La Silla (docs/simulator.md, "Pointing").
//!
//! RA and Dec are equatorial coordinates of the date (no precession, nutation, aberration
//! or refraction is applied) and UT1 is taken equal to UTC: over a night the errors this
//! makes in the parallactic angle are far below the 0.1 deg that matters here.
use serde::Serialize;

/// An observatory site.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Site {
    /// Geodetic latitude, deg (south negative).
    pub lat_deg: f64,
    /// Longitude, deg (east positive, west negative).
    pub lon_deg: f64,
    /// Height above sea level, m.
    pub height_m: f64,
}

/// The NTT at La Silla.
pub const LA_SILLA_NTT: Site = Site {
    lat_deg: -29.2567,
    lon_deg: -70.7346,
    height_m: 2375.0,
};

/// MJD of the epoch J2000.0 (JD 2451545.0, 2000-01-01 12h).
const MJD_J2000: f64 = 51544.5;

/// An angle in degrees mapped into [0, 360).
pub fn wrap_360(a: f64) -> f64 {
    a.rem_euclid(360.0)
}

/// An angle in degrees mapped into (-180, 180].
pub fn wrap_180(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r > 180.0 {
        r - 360.0
    } else {
        r
    }
}

/// The mean of two angles (deg) along the shorter arc between them, in (-180, 180]: the
/// parallactic angle of an exposure from its start and end (as the reduction reads it).
pub fn mean_angle_deg(start: f64, end: f64) -> f64 {
    wrap_180(start + 0.5 * wrap_180(end - start))
}

/// Greenwich mean sidereal time, deg in [0, 360), at `mjd` (UT1 = UTC): the IAU 1982
/// expression as Meeus (Astronomical Algorithms, eq. 12.4) writes it,
/// `theta0 = 280.46061837 + 360.98564736629 d + 0.000387933 T^2 - T^3 / 38710000`,
/// d = days from J2000.0, T = d / 36525.
pub fn gmst_deg(mjd: f64) -> f64 {
    let d = mjd - MJD_J2000;
    let t = d / 36525.0;
    wrap_360(280.46061837 + 360.98564736629 * d + 0.000387933 * t * t - t * t * t / 38_710_000.0)
}

/// Local mean sidereal time, deg in [0, 360).
pub fn lst_deg(mjd: f64, site: &Site) -> f64 {
    wrap_360(gmst_deg(mjd) + site.lon_deg)
}

/// Altitude, deg: `sin a = sin phi sin dec + cos phi cos dec cos H`.
pub fn altitude_deg(hour_angle_deg: f64, dec_deg: f64, lat_deg: f64) -> f64 {
    let (h, d, p) = (hour_angle_deg.to_radians(), dec_deg.to_radians(), lat_deg.to_radians());
    (p.sin() * d.sin() + p.cos() * d.cos() * h.cos())
        .clamp(-1.0, 1.0)
        .asin()
        .to_degrees()
}

/// Parallactic angle, deg in (-180, 180]: the position angle (north through east) of the
/// direction to the zenith, `eta = atan2(sin H, tan phi cos dec - sin dec cos H)` (Meeus
/// eq. 14.1). Positive west of the meridian (H > 0), negative east of it.
pub fn parallactic_angle_deg(hour_angle_deg: f64, dec_deg: f64, lat_deg: f64) -> f64 {
    let (h, d, p) = (hour_angle_deg.to_radians(), dec_deg.to_radians(), lat_deg.to_radians());
    wrap_180(h.sin().atan2(p.tan() * d.cos() - d.sin() * h.cos()).to_degrees())
}

/// Airmass at altitude `alt_deg`: Hardie's (1962) polynomial in sec z - 1, a fit to
/// Bemporad's tables good to 0.1 % up to airmass 6.8:
/// `X = sec z - 0.0018167 (sec z - 1) - 0.002875 (sec z - 1)^2 - 0.0008083 (sec z - 1)^3`.
/// The zenith distance is held at 87 deg below altitude 3 deg (the polynomial turns over);
/// `alt_deg` is the geometric altitude (refraction is not applied).
pub fn airmass(alt_deg: f64) -> f64 {
    let z = (90.0 - alt_deg).clamp(0.0, 87.0).to_radians();
    let s = 1.0 / z.cos() - 1.0;
    1.0 + s * (0.9981833 - s * (0.002875 + 0.0008083 * s))
}

/// Where a target is at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pointing {
    /// MJD (UTC).
    pub mjd: f64,
    /// Local mean sidereal time, deg.
    pub lst_deg: f64,
    /// Hour angle, deg in (-180, 180] (positive west).
    pub hour_angle_deg: f64,
    /// Altitude, deg.
    pub alt_deg: f64,
    /// Airmass ([`airmass`]).
    pub airmass: f64,
    /// Parallactic angle, deg in (-180, 180].
    pub parang_deg: f64,
}

/// The pointing of (`ra_deg`, `dec_deg`) from `site` at `mjd`.
pub fn pointing(site: &Site, mjd: f64, ra_deg: f64, dec_deg: f64) -> Pointing {
    let lst = lst_deg(mjd, site);
    let h = wrap_180(lst - ra_deg);
    let alt = altitude_deg(h, dec_deg, site.lat_deg);
    Pointing {
        mjd,
        lst_deg: lst,
        hour_angle_deg: h,
        alt_deg: alt,
        airmass: airmass(alt),
        parang_deg: parallactic_angle_deg(h, dec_deg, site.lat_deg),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gmst_of_meeus_examples_12a_and_12b() {
        // Meeus, Astronomical Algorithms (2nd ed.), example 12.a: 1987 April 10, 0h UT,
        // theta0 = 13h10m46.3668s; example 12.b: 19h21m00s UT, theta0 = 128.7378734 deg.
        let hms = |h: f64, m: f64, s: f64| 15.0 * (h + m / 60.0 + s / 3600.0);
        assert!((gmst_deg(46895.0) - hms(13.0, 10.0, 46.3668)).abs() < 1e-6);
        assert!((gmst_deg(46895.0 + (19.0 + 21.0 / 60.0) / 24.0) - 128.7378734).abs() < 1e-6);
    }

    #[test]
    fn mean_angle_takes_the_shorter_arc() {
        assert_eq!(mean_angle_deg(-157.1, -156.9), -157.0);
        assert_eq!(mean_angle_deg(-179.0, 179.0), 180.0);
        assert_eq!(mean_angle_deg(170.0, -170.0), 180.0);
        assert_eq!(mean_angle_deg(-10.0, 30.0), 10.0);
    }

    #[test]
    fn airmass_is_sec_z_near_the_zenith_and_below_it_low_down() {
        for alt in [90.0, 80.0, 60.0] {
            let sec = 1.0 / f64::to_radians(90.0 - alt).cos();
            assert!((airmass(alt) - sec).abs() < 3e-3 * (sec - 1.0) + 1e-12, "{alt}");
        }
        assert!(airmass(20.0) < 1.0 / f64::to_radians(70.0).cos());
    }
}
