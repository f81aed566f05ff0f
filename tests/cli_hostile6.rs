//! Hostile inputs, fifth part: set-of-frames files (docs/frame-format.md, "A set of frames
//! as a file") given to `night` and `target`: missing files, a file listed twice, an
//! unknown role, an angle that is not a finite number, bytes that are not UTF-8, a very
//! long line, a list given with a directory, an empty list. Each must end with exit code 1
//! and one message naming the file, the line, the key and the value, never a panic and
//! never a catalog.
use std::path::Path;

mod common;
use common::run;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn hostile_frame_lists_are_refused_with_file_line_key_and_value() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(d.path().join("a.fits"), b"SIMPLE  =").unwrap();
    std::fs::write(d.path().join("b.fits"), b"SIMPLE  =").unwrap();
    let long = format!("a.fits science target={}", "y".repeat(100_000));
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "missing",
            b"a.fits science\nnot_there.fits science\n".to_vec(),
            ":2: path = \"not_there.fits\"",
        ),
        (
            "twice",
            b"a.fits science\nb.fits flat\n./a.fits science\n".to_vec(),
            ":3: path = \"./a.fits\": the same file as line 1",
        ),
        ("role", b"a.fits bias\n".to_vec(), ":1: role = \"bias\": unknown role"),
        (
            "nan",
            b"a.fits science angle=NaN\n".to_vec(),
            ":1: angle = \"NaN\": not a finite angle",
        ),
        (
            "inf",
            b"a.fits science angle=-inf\n".to_vec(),
            ":1: angle = \"-inf\": not a finite angle",
        ),
        (
            "utf8",
            b"a.fits science\n\xfe\xff.fits science\n".to_vec(),
            ":2: line = ",
        ),
        ("long", long.into_bytes(), ":1: line = "),
        ("nul", b"a.fits science target=\x01x\n".to_vec(), ":1: target = "),
    ];
    for (name, text, expected) in cases {
        let list = d.path().join(format!("{name}.txt"));
        std::fs::write(&list, &text).unwrap();
        for cmd in ["night", "target"] {
            let out = d.path().join(format!("{name}_{cmd}.json"));
            let (code, stdout, err) = run(&[cmd, s(&list), "-o", s(&out)]);
            assert_eq!(code, 1, "{cmd} {name}: {err}");
            assert!(!err.contains("panicked"), "{cmd} {name}: {err}");
            assert!(
                err.contains(&format!("{}{expected}", list.display())),
                "{cmd} {name}: {err}"
            );
            assert!(err.len() < 2000, "{cmd} {name}: message of {} bytes", err.len());
            assert!(stdout.is_empty() && !out.exists(), "{cmd} {name}");
        }
    }
    // A list with a directory: refused, naming the list.
    let list = d.path().join("ok.txt");
    std::fs::write(&list, b"a.fits science\n").unwrap();
    let (code, _, err) = run(&["night", s(&list), s(d.path()), "-o", s(&d.path().join("x.json"))]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("ok.txt") && err.contains("given alone"), "{err}");
    // An empty list: nothing to reduce, said.
    let list = d.path().join("empty.txt");
    std::fs::write(&list, b"# nothing yet\n").unwrap();
    let (code, _, err) = run(&["night", s(&list), "-o", s(&d.path().join("y.json"))]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("empty.txt"), "{err}");
    // A listed file that is not FITS: not a panic, the night names it (exit 2, a catalog).
    let list = d.path().join("notfits.txt");
    std::fs::write(d.path().join("c.fits"), b"observing notes").unwrap();
    std::fs::write(&list, b"c.fits science\n").unwrap();
    let (code, _, err) = run(&["night", s(&list), "-o", s(&d.path().join("z.json"))]);
    assert!(code == 1 || code == 2, "{code}: {err}");
    assert!(!err.contains("panicked"), "{err}");
}
