use super::*;

/// Minimal well-formedness check: every start tag is closed in order (a stack over
/// `<name ...>`, `</name>`, `<name .../>`), one root `svg`. Returns the element count.
fn check_xml(doc: &str) -> usize {
    let mut stack: Vec<String> = Vec::new();
    let mut elements = 0;
    let mut rest = doc;
    while let Some(start) = rest.find('<') {
        let end = rest[start..].find('>').expect("unterminated tag") + start;
        let tag = &rest[start + 1..end];
        rest = &rest[end + 1..];
        if tag.starts_with('?') || tag.starts_with('!') {
            continue;
        }
        if let Some(name) = tag.strip_prefix('/') {
            assert_eq!(stack.pop().as_deref(), Some(name.trim()), "mismatched </{name}>");
        } else {
            elements += 1;
            let name = tag.split_whitespace().next().unwrap().trim_end_matches('/').to_string();
            assert!(!name.is_empty());
            if elements == 1 {
                assert_eq!(name, "svg");
            } else {
                assert!(!stack.is_empty(), "second root element <{name}>");
            }
            if !tag.ends_with('/') {
                stack.push(name);
            }
        }
    }
    assert!(stack.is_empty(), "unclosed {stack:?}");
    elements
}

#[test]
fn svg_is_well_formed_has_the_labels_and_is_written_atomically() {
    let dir = tempfile::tempdir().unwrap();
    let edges: Vec<f64> = (0..=9).map(|i| 10.0 * i as f64).collect();
    let panel = Panel::new("Observed Δγ & co", "Δγ [deg]", "N binaries")
        .with(Series::bars(
            "data",
            edges,
            vec![9.0, 7.0, 5.0, 4.0, 3.0, 2.0, 2.0, 1.0, 1.0],
        ))
        .note("KS p < 0.001");
    let fig = Figure::grid(Some("vector test".into()), vec![panel], 1, SINGLE_COLUMN_MM, 60.0);
    let svg = fig.render_svg().unwrap();
    assert!(check_xml(&svg) > 20);
    assert_eq!(svg.matches("<text").count(), svg.matches("</text>").count());
    for label in [
        "Δγ [deg]",
        "N binaries",
        "vector test",
        "Observed Δγ &amp; co",
        "KS p &lt; 0.001",
    ] {
        assert!(svg.contains(label), "{label} missing");
    }
    // The checker rejects a broken document.
    assert!(std::panic::catch_unwind(|| check_xml("<svg><g></svg>")).is_err());
    let path = dir.path().join("f.svg");
    fig.save(&path).unwrap();
    assert_eq!(std::fs::read_to_string(&path).unwrap(), svg);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 1, "no temporary file left: {names:?}");
    // `save` with another extension still writes a PNG.
    let png = dir.path().join("f.png");
    fig.save(&png).unwrap();
    assert_eq!(&std::fs::read(&png).unwrap()[..4], b"\x89PNG");
}

#[test]
fn renders_a_grid_with_text_and_writes_atomically() {
    let dir = tempfile::tempdir().unwrap();
    let edges: Vec<f64> = (0..=9).map(|i| 10.0 * i as f64).collect();
    let a = Panel::new("Observed Δγ", "Δγ [deg]", "N")
        .with(Series::bars(
            "data",
            edges.clone(),
            vec![9.0, 7.0, 5.0, 4.0, 3.0, 2.0, 2.0, 1.0, 1.0],
        ))
        .note("KS p = 0.001");
    let b = Panel::new("Π(Δγ)", "Δγ [deg]", "density")
        .with(Series::line("flat", vec![0.0, 90.0], vec![1.0 / 90.0, 1.0 / 90.0]))
        .with(
            Series::steps("mc", edges, vec![0.012; 9])
                .style(Style::Steps(1))
                .color(sequential(3, 5)),
        );
    let fig = Figure::grid(Some("test".into()), vec![a, b], 2, DOUBLE_COLUMN_MM, 60.0);
    let (w, h, rgb) = fig.render_rgb().unwrap();
    // 180 mm at 300 dpi; one row of 60 mm and the title's line.
    assert_eq!((w, h), fig.pixel_size().unwrap());
    assert_eq!(w, 2126);
    assert!(h > mm_to_px(60.0) && h < mm_to_px(60.0) + 80, "{h}");
    // Something besides white was drawn, and some of it is dark (text, axes).
    assert!(rgb.chunks(3).filter(|p| p[0] < 60 && p[1] < 60 && p[2] < 60).count() > 500);
    let path = dir.path().join("f.png");
    fig.save_png(&path).unwrap();
    let img = image::open(&path).unwrap();
    assert_eq!((img.width(), img.height()), (w, h));
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().filter_map(|e| e.ok()).collect();
    assert_eq!(leftovers.len(), 1, "no temporary file left behind");
}

#[test]
fn mismatched_series_is_an_error() {
    let p = Panel::new("x", "x", "y").with(Series::steps("s", vec![0.0, 1.0], vec![1.0, 2.0]));
    assert!(matches!(Figure::single(p).render_rgb(), Err(Error::Input(_))));
}

#[test]
fn ticks_are_short() {
    assert_eq!(tick(10.0), "10");
    assert_eq!(tick(0.25), "0.25");
    assert_eq!(tick(0.0), "0");
    assert_eq!(tick(1e-5), "1e-5");
}
