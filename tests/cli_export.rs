//! `sofipol export`: the files read back (fitsio for FITS, a small parser for ECSV and
//! CSV, astropy when importable) equal the catalog, with units in the column metadata.
use std::path::Path;
use std::process::Command;

use serde_json::Value;

mod common;
use common::{sofipol, testdata};

fn export(format: &str, out: &Path) {
    let o = sofipol()
        .args(["export", &testdata("catalog_aligned.json"), "--format", format, "-o"])
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    assert!(o.stderr.is_empty());
}

/// Components of the catalog in order: (target, component, gamma_deg, p, passes_cut, flags).
fn expected() -> Vec<(String, String, f64, f64, bool, String)> {
    let cat: Value = serde_json::from_str(&std::fs::read_to_string(testdata("catalog_aligned.json")).unwrap()).unwrap();
    let mut v = Vec::new();
    for t in cat["targets"].as_array().unwrap() {
        for c in t["components"].as_array().unwrap() {
            let flags: Vec<&str> = c["flags"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_str().unwrap())
                .collect();
            v.push((
                t["object"].as_str().unwrap().to_string(),
                c["name"].as_str().unwrap().to_string(),
                c["gamma_deg"].as_f64().unwrap(),
                c["p"].as_f64().unwrap(),
                c["passes_cut"].as_bool().unwrap(),
                flags.join(";"),
            ));
        }
    }
    v
}

/// Split one CSV line (quotes with "" escapes).
fn split_csv(line: &str) -> Vec<String> {
    let (mut out, mut cur, mut q) = (Vec::new(), String::new(), false);
    let mut it = line.chars().peekable();
    while let Some(c) = it.next() {
        match (c, q) {
            ('"', true) if it.peek() == Some(&'"') => {
                cur.push('"');
                it.next();
            }
            ('"', _) => q = !q,
            (',', false) => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    out
}

fn check_rows(header: &[String], rows: &[Vec<String>]) {
    let col = |name: &str| {
        header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}"))
    };
    let exp = expected();
    assert_eq!(rows.len(), exp.len());
    for (r, e) in rows.iter().zip(&exp) {
        assert_eq!(r.len(), header.len());
        assert_eq!(r[col("target")], e.0);
        assert_eq!(r[col("component")], e.1);
        assert_eq!(r[col("gamma")].parse::<f64>().unwrap(), e.2, "exact float round trip");
        assert_eq!(r[col("p")].parse::<f64>().unwrap(), e.3);
        assert_eq!(r[col("passes_cut")], if e.4 { "True" } else { "False" });
        assert_eq!(r[col("flags")], e.5);
    }
}

#[test]
fn csv_and_ecsv_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let (csv, ecsv) = (dir.path().join("t.csv"), dir.path().join("t.ecsv"));
    export("csv", &csv);
    export("ecsv", &ecsv);
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let header = split_csv(lines.next().unwrap());
    let rows: Vec<Vec<String>> = lines.map(split_csv).collect();
    check_rows(&header, &rows);

    let text = std::fs::read_to_string(&ecsv).unwrap();
    assert!(text.starts_with("# %ECSV 1.0\n# ---\n"));
    let head: Vec<&str> = text.lines().take_while(|l| l.starts_with('#')).collect();
    // Units and types in the YAML header.
    assert!(head.contains(&"# - {name: gamma, unit: deg, datatype: float64, description: \"polarization angle, east of north, [0, 180)\"}"));
    assert!(head
        .iter()
        .any(|l| l.starts_with("# - {name: passes_cut, datatype: bool")));
    assert!(head.iter().any(|l| l.starts_with("# - {software: ")));
    let n_cols = head.iter().filter(|l| l.starts_with("# - {name: ")).count();
    let mut data = text.lines().skip(head.len());
    let header = split_csv(data.next().unwrap());
    assert_eq!(header.len(), n_cols);
    let rows: Vec<Vec<String>> = data.map(split_csv).collect();
    check_rows(&header, &rows);
}

#[test]
fn fits_reads_back_with_units() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.fits");
    export("fits", &path);
    // Atomic write: nothing but the file is left in the directory.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    let mut f = fitsio::FitsFile::open(&path).unwrap();
    let hdu = f.hdu("SOFIPOL").unwrap();
    let target: Vec<String> = hdu.read_col(&mut f, "target").unwrap();
    let comp: Vec<String> = hdu.read_col(&mut f, "component").unwrap();
    let gamma: Vec<f64> = hdu.read_col(&mut f, "gamma").unwrap();
    let p: Vec<f64> = hdu.read_col(&mut f, "p").unwrap();
    let flags: Vec<String> = hdu.read_col(&mut f, "flags").unwrap();
    let exp = expected();
    assert_eq!(target.len(), exp.len());
    for (i, e) in exp.iter().enumerate() {
        assert_eq!((&target[i], &comp[i]), (&e.0, &e.1));
        assert_eq!((gamma[i], p[i]), (e.2, e.3), "doubles are stored exactly");
        assert_eq!(flags[i].trim_end(), e.5);
    }
    // Units: find the gamma column's TUNITn.
    let ttype: Vec<String> = (1..=999)
        .map_while(|i| hdu.read_key::<String>(&mut f, &format!("TTYPE{i}")).ok())
        .collect();
    let gi = ttype.iter().position(|t| t == "gamma").unwrap() + 1;
    assert_eq!(hdu.read_key::<String>(&mut f, &format!("TUNIT{gi}")).unwrap(), "deg");
    // passes_cut is a logical column (T/F), which astropy reads as bool, not an integer (its
    // values: `astropy_reads_ecsv_and_fits`; fitsio 0.21 reads no logical column, and reading
    // one as text crashes it).
    let ci = ttype.iter().position(|t| t == "passes_cut").unwrap() + 1;
    let tform = hdu.read_key::<String>(&mut f, &format!("TFORM{ci}")).unwrap();
    assert!(tform.trim().ends_with('L'), "TFORM{ci} = {tform}");
    assert!(hdu.read_key::<String>(&mut f, "SOFTWARE").is_ok());
}

#[test]
fn astropy_reads_ecsv_and_fits() {
    let Some(python) = common::python_with("astropy", "astropy_reads_ecsv_and_fits") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (ecsv, fits) = (dir.path().join("t.ecsv"), dir.path().join("t.fits"));
    export("ecsv", &ecsv);
    export("fits", &fits);
    let script = r#"
import sys
from astropy.table import Table
a = Table.read(sys.argv[1], format="ascii.ecsv")
b = Table.read(sys.argv[2], hdu="SOFIPOL")
assert str(a["gamma"].unit) == "deg" and str(b["gamma"].unit) == "deg", (a["gamma"].unit, b["gamma"].unit)
assert len(a) == len(b)
assert list(a["target"]) == [s.strip() for s in b["target"]]
assert all(x == y for x, y in zip(a["gamma"], b["gamma"]))
assert a["passes_cut"].dtype == bool
assert b["passes_cut"].dtype == bool, b["passes_cut"].dtype
assert list(a["passes_cut"]) == list(b["passes_cut"])
print(len(a), "rows")
"#;
    let o = Command::new(&python)
        .args(["-c", script])
        .arg(&ecsv)
        .arg(&fits)
        .output()
        .unwrap();
    assert!(o.status.success(), "astropy: {}", String::from_utf8_lossy(&o.stderr));
    let n = expected().len();
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), format!("{n} rows"));
}

/// `catalog_aligned.json` with a pointing, a time and a geometry for every target and two
/// standards (one measured: its component is the first target's A), written to `path`;
/// returns the values set, one per component (row), (ra, dec, mjd, separation, pa).
fn with_standards(path: &Path) -> Vec<[f64; 5]> {
    let mut cat: Value =
        serde_json::from_str(&std::fs::read_to_string(testdata("catalog_aligned.json")).unwrap()).unwrap();
    let mut set = Vec::new();
    for (i, t) in cat["targets"].as_array_mut().unwrap().iter_mut().enumerate() {
        let v = [
            10.0 + 7.25 * i as f64,
            -30.5 + i as f64,
            51240.0 + 0.015625 * i as f64,
            2.5 + i as f64,
            15.0 * i as f64,
        ];
        for (key, x) in ["ra_deg", "dec_deg", "mjd_mean", "separation_arcsec", "pa_deg"]
            .iter()
            .zip(v)
        {
            t[*key] = x.into();
        }
        set.extend(std::iter::repeat_n(v, t["components"].as_array().unwrap().len()));
    }
    let measured = cat["targets"][0]["components"][0].clone();
    cat["standards"] = serde_json::json!([
        {"name": "HD 64299", "object": "HD 64299", "sequence": "HD 64299@1999-03-03T05:00:00",
         "filter": "Ks", "status": "ok", "measured": measured, "used_for": ["offset"],
         "flags": [], "ra_deg": 98.5, "dec_deg": -23.25, "mjd_mean": 51240.25},
        {"name": "HD 98161", "object": "HD 98161", "sequence": "HD 98161@1999-03-03T06:00:00",
         "filter": "Ks", "status": "failed", "measured": null, "used_for": [], "flags": ["failed: x"]}
    ]);
    std::fs::write(path, serde_json::to_string(&cat).unwrap()).unwrap();
    set
}

/// astropy reads the position, time and geometry columns with their units (deg, d,
/// arcsec) from ECSV and FITS, and the measured standard as a row of kind `standard`; each
/// B lies at the catalog's separation and position angle from its A by astropy's
/// `SkyCoord.separation` and `position_angle`.
#[test]
fn astropy_reads_the_position_time_and_standards() {
    let Some(python) = common::python_with("astropy", "astropy_reads_the_position_time_and_standards") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cat = dir.path().join("cat.json");
    let set = with_standards(&cat);
    let (ecsv, fits) = (dir.path().join("t.ecsv"), dir.path().join("t.fits"));
    for (format, out) in [("ecsv", &ecsv), ("fits", &fits)] {
        let o = sofipol()
            .args(["export", cat.to_str().unwrap(), "--format", format, "-q", "-o"])
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    }
    let script = r#"
import sys, json
import astropy.units as u
from astropy.coordinates import SkyCoord
from astropy.table import Table
want = json.loads(sys.argv[3])
for t in (Table.read(sys.argv[1], format="ascii.ecsv"), Table.read(sys.argv[2], hdu="SOFIPOL")):
    for name, unit in [("ra", u.deg), ("dec", u.deg), ("mjd", u.d), ("separation", u.arcsec), ("pa", u.deg)]:
        assert t[name].unit == unit, (name, t[name].unit)
    kind = [str(k).strip() for k in t["kind"]]
    targets = t[[k == "target" for k in kind]]
    stds = t[[k == "standard" for k in kind]]
    assert len(stds) == 1, kind
    assert str(stds["target"][0]).strip() == "HD 64299"
    assert stds["ra"].quantity[0] == 98.5 * u.deg and stds["mjd"].quantity[0] == 51240.25 * u.d
    assert stds["q"][0] == targets["q"][0]
    assert len(targets) == len(want)
    last_a = None
    for row, (ra, dec, mjd, sep, pa) in zip(targets, want):
        assert (row["mjd"], row["separation"], row["pa"]) == (mjd, sep, pa), row
        if str(row["component"]).strip() == "A":
            assert (row["ra"], row["dec"]) == (ra, dec), row
            last_a = SkyCoord(row["ra"] * u.deg, row["dec"] * u.deg)
        else:
            # B's own position: at the measured separation and PA from A (astropy's
            # spherical trigonometry, independent of sofipol's).
            b = SkyCoord(row["ra"] * u.deg, row["dec"] * u.deg)
            assert abs(last_a.separation(b).arcsec - sep) < 1e-6, (last_a.separation(b).arcsec, sep)
            d = (last_a.position_angle(b).deg - pa + 180) % 360 - 180
            assert abs(d) < 1e-5, (last_a.position_angle(b).deg, pa)
    assert targets["separation"].quantity.to(u.deg)[0] == want[0][3] / 3600 * u.deg
    print(len(targets), len(stds))
"#;
    let o = Command::new(&python)
        .args(["-c", script])
        .arg(&ecsv)
        .arg(&fits)
        .arg(serde_json::to_string(&set).unwrap())
        .output()
        .unwrap();
    assert!(o.status.success(), "astropy: {}", String::from_utf8_lossy(&o.stderr));
    let n = expected().len();
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), format!("{n} 1\n{n} 1"));
}

#[test]
fn export_errors_name_the_file() {
    let o = sofipol()
        .args(["export", "no/such.json", "--format", "csv", "-o", "x.csv"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no/such.json"));
    let o = sofipol()
        .args(["export", &testdata("catalog_one.json"), "--format", "xls", "-o", "x"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
}

/// The format follows the output's extension; a `--format` that contradicts it is refused
/// before anything is written (an ECSV text named `.fits` is no table astropy can read).
#[test]
fn the_format_follows_the_extension_and_a_contradiction_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cat = testdata("catalog_aligned.json");
    let run = |args: &[&str]| sofipol().arg("export").arg(&cat).args(args).output().unwrap();
    for (name, starts) in [
        ("t.fits", "SIMPLE  ="),
        ("t.FIT", "SIMPLE  ="),
        ("t.ecsv", "# %ECSV 1.0"),
        ("t.csv", "target,"),
    ] {
        let out = dir.path().join(name);
        let o = run(&["-q", "-o", out.to_str().unwrap()]);
        assert!(o.status.success(), "{name}: {}", String::from_utf8_lossy(&o.stderr));
        let head = std::fs::read(&out).unwrap();
        assert!(
            head.starts_with(starts.as_bytes()),
            "{name}: {:?}",
            String::from_utf8_lossy(&head[..20])
        );
    }
    // No extension that names a format: ECSV, as before.
    let out = dir.path().join("t.txt");
    assert!(run(&["-q", "-o", out.to_str().unwrap()]).status.success());
    assert!(std::fs::read(&out).unwrap().starts_with(b"# %ECSV"));
    // A contradiction: exit 1, the file and both formats named, nothing written.
    let out = dir.path().join("c.fits");
    let o = run(&["--format", "ecsv", "-o", out.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("c.fits") && err.contains("says fits") && err.contains("--format ecsv"),
        "{err}"
    );
    assert!(!out.exists());
    // The same format by name and by extension is fine.
    assert!(run(&[
        "-q",
        "--format",
        "csv",
        "-o",
        dir.path().join("d.csv").to_str().unwrap()
    ])
    .status
    .success());
}
