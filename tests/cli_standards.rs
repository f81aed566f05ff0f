//! The standards table given with `--standards`: a number out of range (an angle error of
//! 1e200 deg made every sigma null while the cut still passed) or the same star and filter
//! twice in one file is refused before anything is read or written, naming the file, the
//! entry and the key.
//!
//! `SOFIPOL_BIN=/path/to/sofipol cargo test --test cli_standards` runs these tests against
//! another build (how they were checked to fail before the fix).
use std::path::Path;

mod common;
use common::run;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

const ENTRY: &str = r#"[[standard]]
name = "HD 204827"
filter = "Ks"
p = 0.0088
sigma_p = 0.0022
gamma_deg = 58.7
sigma_gamma_deg = 2.0
"#;

#[test]
fn a_standards_table_with_absurd_numbers_or_duplicates_is_refused_by_entry_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let night = d.join("night");
    std::fs::create_dir(&night).unwrap();
    let cases: Vec<(&str, String, &str)> = vec![
        (
            "sigma_gamma_huge",
            ENTRY.replace("sigma_gamma_deg = 2.0", "sigma_gamma_deg = 1e200"),
            "standard[0] 'HD 204827' (filter 'Ks'): sigma_gamma_deg = 1e200: must be in (0, 90] deg",
        ),
        (
            "gamma_nan",
            ENTRY.replace("gamma_deg = 58.7", "gamma_deg = nan"),
            "standard[0] 'HD 204827' (filter 'Ks'): gamma_deg = NaN: must be in [0, 180) deg",
        ),
        (
            "gamma_out",
            ENTRY.replace("gamma_deg = 58.7", "gamma_deg = 400.0"),
            "gamma_deg = 400:",
        ),
        (
            "p_in_per_cent",
            ENTRY.replace("p = 0.0088", "p = 0.88"),
            "p = 0.88: must be a fraction in [0, 0.1] (0.0088 for 0.88 %",
        ),
        (
            "sigma_p_inf",
            ENTRY.replace("sigma_p = 0.0022", "sigma_p = inf"),
            "sigma_p = inf",
        ),
        (
            "duplicate",
            format!(
                "{ENTRY}{}",
                ENTRY.replace("HD 204827", "HD_204827").replace("58.7", "149.7")
            ),
            "standard[1] 'HD_204827' (filter 'Ks'): the same star and filter as standard[0] 'HD 204827'",
        ),
    ];
    for (name, body, want) in cases {
        let table = d.join(format!("{name}.toml"));
        std::fs::write(&table, body).unwrap();
        let out = d.join(format!("{name}.json"));
        for cmd in ["night", "calib"] {
            let (code, _, err) = run(&[cmd, s(&night), "-o", s(&out), "--standards", s(&table)]);
            assert_eq!(code, 1, "{cmd} {name}: {err}");
            assert!(
                err.contains(&format!("{name}.toml: standard[")) && err.contains(want),
                "{cmd} {name}: {err}"
            );
            assert!(!out.exists(), "{cmd} {name}");
        }
    }
    // Overriding a built-in entry is allowed: the night is then refused for having no frames.
    let table = d.join("override.toml");
    std::fs::write(&table, ENTRY.replace("58.7", "60.0")).unwrap();
    let (code, _, err) = run(&["night", s(&night), "-o", s(&d.join("o.json")), "--standards", s(&table)]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("no FITS files") && !err.contains("override.toml"), "{err}");
}
