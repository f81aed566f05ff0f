//! Real numbers: q, u of unpolarized standards measured with SOFI in Z at 14 parallactic
//! angles (Higgins, Covino & Wiersema's SOFI polarimetry calibration), fitted with the joint
//! calibration fit a night's standards go through (`stokes::calibration::joint::fit_joint_with`,
//! telescope term on); the Fresnel polarization of a bare aluminium mirror at 45 deg (Rakic
//! 1995 optical constants) against what that fit measures; and the built-in table's J and H
//! standards against Whittet et al. (1992)'s table they were entered from.
//!
//! The files are read from `../shared/real/` beside the repository (or the folder named by
//! `SOFIPOL_REAL`); never copied into the repository. Where they are absent the tests say
//! so and pass without checking.
use std::path::PathBuf;

use sofipol_pipeline::calibration::TelescopeCalibration;
use sofipol_pipeline::standards::StandardsTable;
use sofipol_pipeline::stokes::calibration::joint::{fit_joint_with, JointOptions};
use sofipol_pipeline::stokes::calibration::{OrientationF, StandardObservation};
use sofipol_pipeline::stokes::fresnel::{mirror_polarization, TelescopePrior};

/// The real-data folder, or `None` (said on stderr) when it is not there.
fn real(sub: &str) -> Option<PathBuf> {
    let base = std::env::var_os("SOFIPOL_REAL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/real"));
    let d = base.join(sub);
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!("SKIPPED: {} is absent: the real-data check did not run", d.display());
        None
    }
}

/// One row of pz_standards.txt: parallactic angle (deg), q, sigma_q, u, sigma_u.
type Row = (f64, f64, f64, f64, f64);

fn z_table(dir: &std::path::Path) -> Vec<Row> {
    let text = std::fs::read_to_string(dir.join("pz_standards.txt")).unwrap();
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            assert_eq!(v.len(), 6, "{l}");
            (v[1], v[2], v[3], v[4], v[5])
        })
        .collect()
}

/// A star of the table as a night's standard: the four instrument angles 0/45/90/135
/// with F = (F0 - F90)/2 = q and (F45 - F135)/2 = u reproduced exactly (the constant c,
/// which cancels in q and u, set to 0; sigma_F = sqrt(2) sigma_q so that sigma_q comes
/// back), all at the star's parallactic angle; unpolarized in the table (0 +- 0.05 %, as
/// the built-in unpolarized standards).
fn standard((eta, q, sq, u, su): Row) -> StandardObservation {
    let two_eta = 2.0 * eta.to_radians();
    let of = |f: f64, s: f64| OrientationF {
        analyzer_deg: f64::NAN,
        f,
        sigma_f: 2f64.sqrt() * s,
    };
    StandardObservation {
        name: format!("Z standard at eta {eta}"),
        posang_deg: vec![0.0, 45.0, 90.0, 135.0],
        f: vec![of(q, sq), of(u, su), of(-q, sq), of(-u, su)],
        p: 0.0,
        sigma_p: 0.0005,
        gamma_deg: 0.0,
        sigma_gamma_deg: 90.0,
        parallactic_2eta: vec![Some([two_eta.cos(), two_eta.sin()]); 4],
    }
}

/// The relative width stated for the Fresnel prior of the telescope's polarization: the
/// mirror's oxide layer, its age and dust, and the spread of published optical constants
/// move p_tel by this much (1 sigma).
const FRESNEL_PRIOR_WIDTH: f64 = 0.20;

/// Aluminium's (n, k) at `lambda_um`, linear between the table's wavelengths.
fn aluminium(dir: &std::path::Path, lambda_um: f64) -> (f64, f64) {
    let text = std::fs::read_to_string(dir.join("aluminium_rakic_nk.csv")).unwrap();
    let mut rows: Vec<(f64, f64, f64)> = text
        .lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            (v[0], v[1], v[2])
        })
        .collect();
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let i = rows.iter().position(|r| r.0 >= lambda_um).unwrap();
    let (a, b) = (rows[i - 1], rows[i]);
    let t = (lambda_um - a.0) / (b.0 - a.0);
    (a.1 + t * (b.1 - a.1), a.2 + t * (b.2 - a.2))
}

#[test]
fn the_telescope_fit_reproduces_the_real_sofi_z_standards_and_fresnel_agrees() {
    let Some(dir) = real("sofi-z-unpolarized-standards") else {
        return;
    };
    let rows = z_table(&dir);
    assert_eq!(rows.len(), 14);
    let stds: Vec<StandardObservation> = rows.iter().copied().map(standard).collect();
    let profile = sofipol_calib::Profile::sofi();
    let prior = TelescopePrior::of(&profile.telescope, "Z").expect("the profile's mirror in Z");
    let opts = JointOptions {
        default_parity: 1,
        profile_theta0_deg: 0.0,
        fit_telescope: true,
        telescope_prior: Some(prior),
    };
    let j = fit_joint_with(&stds, &opts).expect("a fit");
    assert!(j.telescope_problem.is_none(), "{:?}", j.telescope_problem);
    // 14 parallactic angles measure the term alone: the prior is not used.
    assert!(j.telescope_from_prior.is_none(), "{:?}", j.telescope_from_prior);
    let t = j.telescope.expect("the telescope's term");
    // p_tel, psi_tel and their errors as a night's catalog writes them.
    let tc = TelescopeCalibration::from_fit(&t, &j.covariance);
    let [a, b] = tc.ab();
    let (sigma_p, sigma_psi) = (tc.sigma_p_tel, tc.sigma_psi_tel_deg);
    let chi2_dof = j.chi2 / j.dof as f64;
    eprintln!(
        "SOFI Z, 14 unpolarized standards: p_tel = {:.3} +- {:.3} %, psi_tel = {:.2} +- {:.2} deg, \
         chi2/dof = {:.2} ({:.1}/{}), c = {:.5}",
        100.0 * t.p_tel,
        100.0 * sigma_p,
        t.psi_tel_deg,
        sigma_psi,
        chi2_dof,
        j.chi2,
        j.dof,
        j.offset.map_or(f64::NAN, |o| o.c)
    );
    // An independent fit of the same rows (q, u) = R(2 eta) (a, b), weighted least squares
    // by hand: the normal equations are diagonal up to the weights.
    let (mut saa, mut sab, mut sbb, mut ya, mut yb) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(eta, q, sq, u, su) in &rows {
        let (s, c) = (2.0 * eta.to_radians()).sin_cos();
        // q = a c - b s, u = a s + b c
        for (ra, rb, y, w) in [(c, -s, q, sq.powi(-2)), (s, c, u, su.powi(-2))] {
            saa += w * ra * ra;
            sab += w * ra * rb;
            sbb += w * rb * rb;
            ya += w * ra * y;
            yb += w * rb * y;
        }
    }
    let det = saa * sbb - sab * sab;
    let (a2, b2) = ((sbb * ya - sab * yb) / det, (saa * yb - sab * ya) / det);
    // The joint fit also carries each star's own polarization (prior 0.05 %) and c: its
    // (a, b) agree with the plain fit to well within the error.
    assert!(
        (a - a2).abs() < 0.2 * sigma_p && (b - b2).abs() < 0.2 * sigma_p,
        "({a}, {b}) vs ({a2}, {b2})"
    );
    // The published picture: about 4.4 % turning with the parallactic angle.
    assert!((t.p_tel - 0.044).abs() < 0.002, "p_tel {}", t.p_tel);
    assert!(sigma_p > 0.0 && sigma_p < 0.001, "{sigma_p}");
    assert!(chi2_dof < 3.0, "chi2/dof {chi2_dof}");

    // Fresnel at 0.90 um, aluminium at 45 deg, within the prior's stated width of the fit.
    let Some(al) = real("aluminium-nk") else { return };
    let (n, k) = aluminium(&al, 0.90);
    let p_fresnel = mirror_polarization(n, k, 45.0);
    eprintln!(
        "Fresnel, bare aluminium at 45 deg, 0.90 um (n {n:.3}, k {k:.3}): p = {:.3} %; fit/Fresnel = {:.3}",
        100.0 * p_fresnel,
        t.p_tel / p_fresnel
    );
    let width = FRESNEL_PRIOR_WIDTH * p_fresnel;
    assert!(
        (t.p_tel - p_fresnel).abs() < width,
        "fit {} against Fresnel {p_fresnel} +- {width}",
        t.p_tel
    );
    // The profile's prior in Z (its stored n, k) is this Fresnel value, and the fit lies
    // within the prior's stated widths: p_tel within relative_width, psi_tel within
    // sigma_psi_deg of the mirror's angle.
    assert!((prior.p_tel - p_fresnel).abs() < 1e-4, "{} vs {p_fresnel}", prior.p_tel);
    assert!(
        (t.p_tel - prior.p_tel).abs() < prior.sigma_p_tel,
        "{} vs {prior:?}",
        t.p_tel
    );
    let dpsi = (t.psi_tel_deg - prior.psi_tel_deg + 90.0).rem_euclid(180.0) - 90.0;
    assert!(
        dpsi.abs() < prior.sigma_psi_tel_deg,
        "psi_tel {} vs {prior:?}",
        t.psi_tel_deg
    );
    // Every filter of the profile's mirror holds Rakic's n, k at its wavelength.
    for (band, index) in &profile.telescope.filters {
        let (n, k) = aluminium(&al, index.wavelength_um);
        assert!(
            (index.n - n).abs() < 2e-3 && (index.k - k).abs() < 2e-3,
            "profile telescope.filters.{band}: ({}, {}) against the table's ({n:.4}, {k:.4})",
            index.n,
            index.k
        );
    }
    // And the filters of the K-band work, for the record (docs/calibration.md).
    for (band, lambda) in [("J", 1.25), ("H", 1.65), ("Ks", 2.16)] {
        let (n, k) = aluminium(&al, lambda);
        eprintln!(
            "Fresnel {band} ({lambda} um): p = {:.3} %",
            100.0 * mirror_polarization(n, k, 45.0)
        );
    }
}

/// A fixed-width field of a catalogue line, by the columns of metadata.json (inclusive).
fn field<'a>(line: &'a str, cols: &serde_json::Value, key: &str) -> &'a str {
    let a = cols[key][0].as_u64().unwrap() as usize;
    let b = cols[key][1].as_u64().unwrap() as usize;
    line.get(a..(b + 1).min(line.len())).unwrap_or("").trim()
}

#[test]
fn the_builtin_j_and_h_standards_are_whittet_1992s_values() {
    let Some(dir) = real("whittet1992-standards") else {
        return;
    };
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("metadata.json")).unwrap()).unwrap();
    let cols = &meta["tables"][0]["columns"];
    let text = std::fs::read_to_string(dir.join("catalogue.txt")).unwrap();
    let table = StandardsTable::builtin();
    let mut checked = 0;
    for e in table
        .entries
        .iter()
        .filter(|e| e.reference.starts_with("Whittet et al. 1992, ApJ 386, 562,"))
    {
        let line = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .find(|l| field(l, cols, "name") == e.name)
            .unwrap_or_else(|| panic!("{} is not in Whittet et al.'s table", e.name));
        let b = e.filter.as_str();
        let num = |k: String| -> f64 { field(line, cols, &k).parse().unwrap() };
        assert!(
            (e.p - num(format!("pol_percent_{b}")) / 100.0).abs() < 1e-9,
            "{} {b} p",
            e.name
        );
        assert!(
            (e.sigma_p - num(format!("pol_percent_{b}_err")) / 100.0).abs() < 1e-9,
            "{} {b} sigma_p",
            e.name
        );
        assert!(
            (e.gamma_deg - num(format!("pol_angle_{b}"))).abs() < 1e-9,
            "{} {b} angle",
            e.name
        );
        assert!(
            (e.sigma_gamma_deg - num(format!("pol_angle_{b}_err"))).abs() < 1e-9,
            "{} {b} angle error",
            e.name
        );
        // Their K (2.04 um) is quoted, never entered as Ks.
        assert!(table
            .find(&e.name, "Ks")
            .is_none_or(|k| k.p == 0.0 || !k.reference.starts_with("Whittet")));
        checked += 1;
    }
    assert_eq!(checked, 12, "six stars in J and H");
    eprintln!("{checked} built-in J and H entries equal Whittet et al. (1992)'s table");
}
