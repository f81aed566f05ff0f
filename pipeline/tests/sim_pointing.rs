//! The simulator's pointing: sidereal time, hour angle, altitude, airmass and parallactic
//! angle against independent references, the night's schedule, and the header keywords.
use sofipol_calib::{Header, Profile};
use sofipol_pipeline::sim::pointing::{self, airmass, LA_SILLA_NTT};
use sofipol_pipeline::sim::{schedule, Scene, Simulator};

type Reference = (f64, f64, f64, f64, f64, f64, f64, f64);

/// (mjd UTC, ra_deg, dec_deg, gmst_deg, lst_deg, hour_angle_deg, alt_deg, eta_deg) for the
/// NTT at La Silla, computed with astropy 8.0.2 (TETE -> AltAz without refraction for the
/// altitude; eta as SkyCoord.position_angle from the star to the zenith; UT1 = UTC) by
/// `target/python-env/bin/python scripts/pointing_reference.py`.
const ASTROPY: [Reference; 11] = [
    // 1999-03-03 01:10 UT, east of the meridian
    (
        51240.0486, 120.0, -40.0, 177.874898, 107.140298, -12.859702, 74.95062, -48.4149,
    ),
    // 1999-03-03 04:48 UT, south, near transit
    (
        51240.2, 150.0, -60.0, 232.528125, 161.793525, 11.793525, 58.24008, 19.7974,
    ),
    // 1999-03-03 07:12 UT, north of the zenith, west
    (
        51240.3, 130.0, 5.0, 268.626690, 197.892090, 67.892090, 16.53111, 122.5278,
    ),
    // circumpolar side, east
    (
        51240.15, 200.0, -75.0, 214.478842, 143.744242, -56.255758, 36.69050, -64.7864,
    ),
    // 2015-01-02 06:00 UT, west
    (
        57023.25, 85.0, -20.0, 190.576135, 119.841535, 34.841535, 57.14033, 113.2695,
    ),
    // 2023-12-22 01:41 UT, west
    (
        60300.07, 30.0, -10.0, 115.565152, 44.830552, 14.830552, 66.26759, 146.3032,
    ),
    // 2023-12-22 01:41 UT, low in the north-west
    (
        60300.07, 330.0, 15.0, 115.565152, 44.830552, 74.830552, 5.39656, 122.2441,
    ),
    // 0.26 deg from the zenith at transit: 8 min before
    (
        51240.12, 135.0, -29.0, 203.649273, 132.914673, -2.085327, 88.15824, -98.5169,
    ),
    // 2 min before transit
    (
        51240.1244, 135.0, -29.0, 205.237610, 134.503010, -0.496990, 89.49378, -120.5823,
    ),
    // 2 min after transit
    (
        51240.1272, 135.0, -29.0, 206.248370, 135.513770, 0.513770, 89.48494, 120.0085,
    ),
    // 8 min after transit
    (
        51240.131, 135.0, -29.0, 207.620115, 136.885515, 1.885515, 88.33528, 99.3254,
    ),
];

/// Difference of two angles, deg, in (-180, 180].
fn dang(a: f64, b: f64) -> f64 {
    pointing::wrap_180(a - b)
}

#[test]
fn sidereal_time_hour_angle_altitude_and_parallactic_angle_match_astropy() {
    for &(mjd, ra, dec, gmst, lst, ha, alt, eta) in &ASTROPY {
        let p = pointing::pointing(&LA_SILLA_NTT, mjd, ra, dec);
        assert!(dang(pointing::gmst_deg(mjd), gmst).abs() < 2e-6, "GMST at {mjd}");
        assert!(
            dang(p.lst_deg, lst).abs() < 2e-6,
            "LST at {mjd}: {} vs {lst}",
            p.lst_deg
        );
        assert!(dang(p.hour_angle_deg, ha).abs() < 2e-6, "H at {mjd}");
        // astropy's hour angle of a true-equinox RA uses the apparent sidereal time, the
        // simulator the mean one (the equation of the equinoxes, ~0.6 s in 1999, is
        // neglected); polar motion and diurnal aberration add < 1": the altitudes agree to
        // 8", the parallactic angles to 0.01 deg.
        assert!((p.alt_deg - alt).abs() < 3e-3, "alt at {mjd}: {} vs {alt}", p.alt_deg);
        // Near the zenith those arcseconds turn the direction to the zenith faster: 0.13
        // deg at 0.5 deg from it.
        let tol = if alt > 88.0 { 0.15 } else { 0.01 };
        assert!(
            dang(p.parang_deg, eta).abs() < tol,
            "eta at {mjd} ({ra}, {dec}): {} vs {eta}",
            p.parang_deg
        );
        assert!(p.parang_deg > -180.0 && p.parang_deg <= 180.0);
    }
}

/// Kasten & Young (1989, Applied Optics 28, 4735) airmass, an independent fit to a model
/// atmosphere: `X = 1 / (cos z + 0.50572 (96.07995 - z)^-1.6364)`, z in deg.
fn kasten_young(z_deg: f64) -> f64 {
    1.0 / (z_deg.to_radians().cos() + 0.50572 * (96.07995 - z_deg).powf(-1.6364))
}

#[test]
fn airmass_agrees_with_kasten_and_young_to_0_05_percent_down_to_20_deg() {
    // Plane-parallel sec z is 0.15 % high at z = 50 deg and 0.7 % at 70 deg: it fails here.
    for z in (0..=70).step_by(5) {
        let z = z as f64;
        let x = airmass(90.0 - z);
        assert!(
            (x / kasten_young(z) - 1.0).abs() < 5e-4,
            "z {z}: {x} vs {}",
            kasten_young(z)
        );
    }
    assert_eq!(airmass(90.0), 1.0);
}

/// A scene of one binary and standards, no effects.
fn scene(standards: &str, start_ut: &str) -> Scene {
    let text = format!(
        r#"
name = "point"
seed = 5
[observation]
orientations_deg = [0.0, 45.0]
dithers = 5
date = "1999-03-03"
start_ut = "{start_ut}"
[[binary]]
name = "Some Binary"
separation_arcsec = 3.0
pa_deg = 40.0
flux_a = 40000.0
flux_b = 20000.0
p_a = 0.0
gamma_a_deg = 0.0
p_b = 0.0
gamma_b_deg = 0.0
{standards}
"#
    );
    Scene::from_toml(&text, "pointing scene").unwrap()
}

fn num(h: &Header, k: &str) -> f64 {
    h.get_f64(k).unwrap_or_else(|e| panic!("{k}: {e}"))
}

/// Position angle of the zenith seen from (H, dec) at latitude phi from the sine and cosine
/// rules of the astronomical triangle, given the altitude:
/// `sin eta cos a = sin H cos phi`, `cos eta cos a = sin phi cos dec - cos phi sin dec cos H`.
fn eta_from_triangle(h_deg: f64, dec_deg: f64, alt_deg: f64) -> f64 {
    let (h, d, a, p) = (
        h_deg.to_radians(),
        dec_deg.to_radians(),
        alt_deg.to_radians(),
        LA_SILLA_NTT.lat_deg.to_radians(),
    );
    let (s, c) = (
        h.sin() * p.cos() / a.cos(),
        (p.sin() * d.cos() - p.cos() * d.sin() * h.cos()) / a.cos(),
    );
    assert!((s * s + c * c - 1.0).abs() < 1e-9, "not a point of the sphere");
    s.atan2(c).to_degrees()
}

#[test]
fn header_pointing_keywords_are_consistent_with_each_other_and_with_the_exposure_time() {
    let st =
        "[[standard]]\nname = \"HD 64299\"\nflux = 1e5\nra_deg = 160.0\ndec_deg = -50.0\nstart_ut = \"03:00:00\"\n";
    let sim = Simulator::new(scene(st, "01:10:00"), Profile::sofi()).unwrap();
    let kw = Profile::sofi().keywords;
    let (frames, truth) = sim.run_in_memory();
    let exp_s = 10.0 * 6.0;
    for f in &frames {
        let h = &f.frame.header;
        let (ra, dec) = (num(h, "RA"), num(h, "DEC"));
        let (lst_s, mjd) = (num(h, "LST"), num(h, &kw.mjd_obs));
        let (p0, p1) = (num(h, &kw.parang), num(h, &kw.parang_end));
        let (x0, x1, alt) = (num(h, &kw.airmass), num(h, &kw.airmass_end), num(h, &kw.altitude));
        assert_eq!(
            h.get_str(&kw.date_obs).unwrap().len(),
            23,
            "DATE-OBS to the millisecond"
        );
        // LST (seconds) is the sidereal time of MJD-OBS; RA, DEC the target's.
        assert!((lst_s / 240.0 - pointing::lst_deg(mjd, &LA_SILLA_NTT)).abs() < 1e-9);
        let tt = truth
            .targets
            .iter()
            .chain(&truth.standards)
            .find(|t| t.frames.iter().any(|g| g.file == f.file_name));
        let tt = tt.expect("frame in the truth");
        assert_eq!((ra, dec), (tt.ra_deg, tt.dec_deg));
        // The altitude and PARANG START are the astronomical triangle at H = LST - RA.
        let h0 = lst_s / 240.0 - ra;
        let alt0 = pointing::altitude_deg(h0, dec, LA_SILLA_NTT.lat_deg);
        assert!((alt - alt0).abs() < 1e-9);
        assert!(dang(p0, eta_from_triangle(h0, dec, alt)).abs() < 1e-9);
        // PARANG END is the same triangle after the exposure: H advanced by DIT x NDIT
        // seconds at the sidereal rate (1.00273790935 x 360 deg per day).
        let h1 = h0 + 1.002_737_909_35 * 360.0 * exp_s / 86400.0;
        let alt1 = pointing::altitude_deg(h1, dec, LA_SILLA_NTT.lat_deg);
        assert!(
            dang(p1, eta_from_triangle(h1, dec, alt1)).abs() < 1e-5,
            "PARANG END {p1} vs {}",
            eta_from_triangle(h1, dec, alt1)
        );
        assert!(
            dang(p1, p0).abs() > 0.01,
            "the parallactic angle moved during the exposure"
        );
        // Airmass = Hardie(altitude) at start and end.
        assert!((x0 - airmass(alt)).abs() < 1e-12 && (x1 - airmass(alt1)).abs() < 1e-6);
        // The frame's eta in the truth is what the reduction reads from the header.
        let eta = kw.parallactic_angle_deg(h).unwrap().unwrap();
        assert!(dang(eta, f.truth.pointing.parallactic_angle_deg).abs() < 1e-12);
    }
    // TPL START of the standard is its start_ut.
    assert_eq!(truth.standards[0].tpl_start, "1999-03-03T03:00:00");
}

#[test]
fn near_the_zenith_eta_swings_through_180_within_one_sequence() {
    // Dec -29 transits 0.26 deg from the zenith: starting 6 min before transit, eta runs
    // from about -100 deg through 180 to about +100 deg in the 12.5 min of the sequence.
    let st = "[[standard]]\nname = \"Zenith Star\"\nflux = 1e5\ndec_deg = -29.0\nhour_angle_h = -0.1\nstart_ut = \"03:00:00\"\n";
    let sim = Simulator::new(scene(st, "01:10:00"), Profile::sofi()).unwrap();
    let (_, truth) = sim.run_in_memory();
    let etas: Vec<f64> = truth.standards[0]
        .frames
        .iter()
        .map(|f| f.pointing.parallactic_angle_deg)
        .collect();
    let swing: f64 = etas.windows(2).map(|w| dang(w[1], w[0])).sum();
    assert!(etas[0] < -90.0 && etas[0] > -120.0, "{etas:?}");
    assert!(etas[9] > 90.0 && etas[9] < 120.0, "{etas:?}");
    assert!(swing < -120.0 && swing > -200.0, "eta swings by {swing}: {etas:?}");
    // The hour angle changed by only ~3 deg meanwhile, and the star stayed above 88 deg.
    let fr = &truth.standards[0].frames;
    let dh = fr[9].pointing.start.hour_angle_deg - fr[0].pointing.start.hour_angle_deg;
    assert!((dh - 1.002_737_909_35 * 360.0 * 9.0 * 75.0 / 86400.0).abs() < 1e-9);
    assert!(fr.iter().all(|f| f.pointing.start.alt_deg > 88.0));
}

#[test]
fn sequences_follow_each_other_around_fixed_starts_and_default_pointings_are_high() {
    // A sequence of 10 exposures takes 10 x (60 + 15) + 120 s = 870 s.
    let fixed = "[[standard]]\nname = \"HD 98161\"\nflux = 1e5\nstart_ut = \"01:20:00\"\n[[standard]]\nname = \"HD 64299\"\nflux = 1e5\n";
    let sim = Simulator::new(scene(fixed, "01:10:00"), Profile::sofi()).unwrap();
    let (_, truth) = sim.run_in_memory();
    // The binary starts at 01:10:00 but would overlap the fixed standard at 01:20:00, so it
    // goes after it (01:34:30); the second standard follows (01:49:00).
    let starts: Vec<&str> = truth
        .targets
        .iter()
        .chain(&truth.standards)
        .map(|t| t.tpl_start.as_str())
        .collect();
    assert_eq!(
        starts,
        ["1999-03-03T01:34:30", "1999-03-03T01:20:00", "1999-03-03T01:49:00"]
    );
    // Without fixed starts: one after another from the observation's start.
    let plain = "[[standard]]\nname = \"HD 98161\"\nflux = 1e5\n";
    let (_, truth) = Simulator::new(scene(plain, "01:10:00"), Profile::sofi())
        .unwrap()
        .run_in_memory();
    assert_eq!(truth.standards[0].tpl_start, "1999-03-03T01:24:30");
    // Exposure k starts 20 s + k x 75 s after TPL START.
    let f = &truth.standards[0].frames;
    let t0 = sofipol_pipeline::sim::effects::mjd_from_date_time("1999-03-03", "01:24:30").unwrap();
    for (k, fr) in f.iter().enumerate() {
        assert!((fr.pointing.start.mjd - t0 - (20.0 + 75.0 * k as f64) / 86400.0).abs() < 1e-9);
        assert!((fr.pointing.end.mjd - fr.pointing.start.mjd - 60.0 / 86400.0).abs() < 1e-9);
    }
    // Default pointings: Dec in [-75, 5], |H| <= 3 h at the start, well above the horizon;
    // the same name gives the same declination in another scene.
    let many: String = (0..40)
        .map(|i| format!("[[standard]]\nname = \"Star {i}\"\nflux = 1e5\n"))
        .collect();
    let sim = Simulator::new(scene(&many, "01:10:00"), Profile::sofi()).unwrap();
    let mut decs = Vec::new();
    for t in 0..sim.n_sequences() {
        let plan = sim.sequence_plan(t);
        let (p, _) = schedule::exposure_pointing(sim.scene(), plan, 0);
        assert!((-75.0..=5.0).contains(&plan.dec_deg), "{t}: {}", plan.dec_deg);
        assert!(p.hour_angle_deg.abs() <= 45.5, "{t}: H {}", p.hour_angle_deg);
        assert!(p.alt_deg > 30.0, "{t}: alt {}", p.alt_deg);
        decs.push(plan.dec_deg);
    }
    assert!(
        decs.iter().any(|&d| d < -50.0) && decs.iter().any(|&d| d > -20.0),
        "{decs:?}"
    );
    let again = Simulator::new(scene(plain, "01:10:00"), Profile::sofi()).unwrap();
    assert_eq!(
        again.run_in_memory().1.standards[0].dec_deg,
        Simulator::new(scene(plain, "05:00:00"), Profile::sofi())
            .unwrap()
            .run_in_memory()
            .1
            .standards[0]
            .dec_deg
    );
}

#[test]
fn impossible_pointings_are_refused_naming_the_target_and_key() {
    let err = |st: &str| match Scene::from_toml(&format!("name = \"x\"\n{st}"), "night.toml") {
        Err(e) => e.to_string(),
        Ok(sc) => match Simulator::new(sc, Profile::sofi()) {
            Err(e) => e.to_string(),
            Ok(_) => String::new(),
        },
    };
    let std = |keys: &str| format!("[[standard]]\nname = \"S1\"\nflux = 1.0\n{keys}\n");
    let e = err(&std("ra_deg = 10.0\nhour_angle_h = 1.0"));
    assert!(e.contains("S1") && e.contains("hour_angle_h"), "{e}");
    let e = err(&std("dec_deg = -95.0"));
    assert!(e.contains("dec_deg = -95"), "{e}");
    let e = err(&std("start_ut = \"late\""));
    assert!(e.contains("start_ut") && e.contains("late"), "{e}");
    // Dec +70 never rises at La Silla (at most 90 - 70 - 29.26 = -9.3 deg).
    let e = err(&std("dec_deg = 70.0"));
    assert!(
        e.contains("night.toml") && e.contains("S1") && e.contains("below the horizon"),
        "{e}"
    );
    // Two fixed sequences 5 min apart overlap.
    let two = format!(
        "{}[[standard]]\nname = \"S2\"\nflux = 1.0\nstart_ut = \"02:05:00\"\n",
        std("start_ut = \"02:00:00\"")
    );
    let e = err(&two);
    assert!(
        e.contains("night.toml") && e.contains("S1") && e.contains("S2") && e.contains("02:05:00"),
        "{e}"
    );
    assert_eq!(err(&std("dec_deg = -30.0\nhour_angle_h = 2.0")), "");
}

/// Per standard of a scene: (name, TPL START, circular mean of its frames' eta in deg).
fn standards_eta(text: &str) -> Vec<(String, String, f64)> {
    let sim = Simulator::new(Scene::from_toml(text, "scene").unwrap(), Profile::sofi()).unwrap();
    let sc = sim.scene();
    (sc.binary.len()..sim.n_sequences())
        .map(|t| {
            let plan = sim.sequence_plan(t);
            let (mut c, mut s) = (0.0, 0.0);
            for k in 0..sim.frames_per_target() {
                let (a, b) = schedule::exposure_pointing(sc, plan, k);
                let eta = pointing::mean_angle_deg(a.parang_deg, b.parang_deg).to_radians();
                (c, s) = (c + eta.cos(), s + eta.sin());
            }
            let name = sc.standard[t - sc.binary.len()].name.clone();
            (name, plan.tpl_start.clone(), f64::atan2(s, c).to_degrees())
        })
        .collect()
}

/// The arc of the circle that the angles 2 eta cover: 360 deg minus the largest gap.
fn two_eta_coverage_deg(etas: &[f64]) -> f64 {
    let mut a: Vec<f64> = etas.iter().map(|e| (2.0 * e).rem_euclid(360.0)).collect();
    a.sort_by(f64::total_cmp);
    let gap = a
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(a[0] + 360.0 - a[a.len() - 1], f64::max);
    360.0 - gap
}

#[test]
fn telescope_polarization_nights_spread_or_bunch_their_standards_parallactic_angles() {
    let table = sofipol_pipeline::standards::StandardsTable::builtin();
    let wide = include_str!("../../testdata/scenes/telpol_night.toml");
    let same = include_str!("../../testdata/scenes/telpol_night_same_eta.toml");
    for text in [wide, same] {
        let sc = Scene::from_toml(text, "scene").unwrap();
        let tel = sc.telescope_polarization.clone().unwrap();
        assert!(sc.effects.iter().any(|e| e.name() == "telescope_polarization") && tel.p_tel > 0.005);
        assert_eq!(sc.standard.len(), 6);
        assert!(sc.binary.len() >= 3);
        // The standards are table entries with the table's values, both kinds.
        let mut pol = 0;
        for s in &sc.standard {
            let e = table
                .find(&s.name, &sc.observation.filter)
                .expect("in the built-in table");
            assert!((s.p - e.p).abs() < 1e-12 && (e.p == 0.0 || (s.gamma_deg - e.gamma_deg).abs() < 1e-12));
            pol += (e.p > 0.0) as usize;
        }
        assert!((2..=4).contains(&pol), "{pol} polarized standards");
    }
    let w = standards_eta(wide);
    let s = standards_eta(same);
    for (name, start, eta) in w.iter().chain(&s) {
        eprintln!("{name:10} {start} eta {eta:7.1}");
    }
    let cover = |v: &[(String, String, f64)]| two_eta_coverage_deg(&v.iter().map(|x| x.2).collect::<Vec<_>>());
    // Spread over the night: 2 eta covers far more than 90 deg; bunched: less than 15 deg.
    assert!(cover(&w) > 180.0, "2 eta covers {}", cover(&w));
    assert!(cover(&s) < 15.0, "2 eta covers {}", cover(&s));
    // Over the night, hours apart.
    let hours = |v: &[(String, String, f64)]| {
        let t: Vec<&str> = v.iter().map(|x| x.1.as_str()).collect();
        (t[0].to_string(), t[t.len() - 1].to_string())
    };
    assert_eq!(hours(&w), hours(&s));
    assert_eq!(hours(&w), ("1999-03-03T00:30:00".into(), "1999-03-03T08:00:00".into()));
}
