//! Calendar dates and MJD (UT, proleptic Gregorian): what frame headers (`DATE-OBS`,
//! `TPL START`) and products (`created_utc`) write.

/// Days from 1970-01-01 of a proleptic Gregorian date (H. Hinnant's algorithm).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = if y >= 0 { y } else { y - 399 } / 400;
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146097 + doe - 719468
}

fn civil_from_days(z: i64) -> (i64, i64, i64) {
    let z = z + 719468;
    let era = if z >= 0 { z } else { z - 146096 } / 146097;
    let doe = z - era * 146097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    (if m <= 2 { y + 1 } else { y }, m, d)
}

/// MJD of "YYYY-MM-DD" + "HH:MM:SS" (UT).
pub fn mjd_from_date_time(date: &str, ut: &str) -> Option<f64> {
    let d: Vec<i64> = date.split('-').map(|s| s.parse().ok()).collect::<Option<_>>()?;
    let t: Vec<f64> = ut.split(':').map(|s| s.parse().ok()).collect::<Option<_>>()?;
    if d.len() != 3 || t.len() != 3 {
        return None;
    }
    let days = days_from_civil(d[0], d[1], d[2]) as f64 + 40587.0; // MJD of 1970-01-01
    Some(days + (t[0] * 3600.0 + t[1] * 60.0 + t[2]) / 86400.0)
}

/// ISO time of an MJD, to the second or the millisecond.
pub fn iso_from_mjd(mjd: f64, millis: bool) -> String {
    let day = mjd.floor();
    let mut ms = ((mjd - day) * 86_400_000.0).round() as i64;
    let mut z = day as i64 - 40587;
    if ms >= 86_400_000 {
        ms -= 86_400_000;
        z += 1;
    }
    let (y, m, d) = civil_from_days(z);
    let (h, mi, s, frac) = (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
    if millis {
        format!("{y:04}-{m:02}-{d:02}T{h:02}:{mi:02}:{s:02}.{frac:03}")
    } else {
        format!("{y:04}-{m:02}-{d:02}T{h:02}:{mi:02}:{s:02}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mjd_of_known_dates() {
        // MJD 51240 = 1999-03-03 0h UT (the reference study's run); MJD 0 = 1858-11-17.
        assert_eq!(mjd_from_date_time("1999-03-03", "00:00:00"), Some(51240.0));
        assert_eq!(mjd_from_date_time("1858-11-17", "00:00:00"), Some(0.0));
        assert_eq!(iso_from_mjd(51240.5, false), "1999-03-03T12:00:00");
        assert_eq!(
            iso_from_mjd(51240.0 + 1.0 / 86400.0 * 3725.25, true),
            "1999-03-03T01:02:05.250"
        );
    }
}
