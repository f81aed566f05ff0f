//! What the page's layout rests on, in its markup: the figures' links to their files, the
//! sequence ids that break only after '@', the targets table's cells labelled for the
//! phone's card layout. The layout itself is measured in a real browser by
//! tests/report_browser.rs.
use std::path::Path;

use super::html::render;
use super::links::{href, relative};
use super::markup::{breakable_at, sequence_id};
use super::tests::{assert_balanced, binary, comp, input, not_computed};
use super::*;
use crate::catalog::{Catalog, StandardResult};

#[test]
fn a_figure_is_linked_relative_to_the_page_and_escaped_as_a_url() {
    let rel = |f: &str, d: &str| relative(Path::new(f), Path::new(d)).unwrap();
    assert_eq!(rel("/n/cat_products/A.png", "/n"), Path::new("cat_products/A.png"));
    assert_eq!(
        rel("/n/cat_products/A.png", "/n/pages/x"),
        Path::new("../../cat_products/A.png")
    );
    assert_eq!(rel("/n/A.png", "/n"), Path::new("A.png"));
    let dir = tempfile::tempdir().unwrap();
    let products = dir.path().join("my night #2/cat_products");
    std::fs::create_dir_all(&products).unwrap();
    let file = products.join("HD_1_1999-03-03T01_00_00.png");
    std::fs::write(&file, b"\x89PNG\r\n\x1a\n").unwrap();
    assert_eq!(
        href(&file, Some(&dir.path().join("my night #2"))),
        "cat_products/HD_1_1999-03-03T01_00_00.png"
    );
    assert_eq!(
        href(&file, Some(dir.path())),
        "my%20night%20%232/cat_products/HD_1_1999-03-03T01_00_00.png"
    );
    let page = dir.path().join("pages");
    std::fs::create_dir_all(&page).unwrap();
    assert_eq!(
        href(&file, Some(&page)),
        "../my%20night%20%232/cat_products/HD_1_1999-03-03T01_00_00.png"
    );
    // Without a folder (the page on standard output): an absolute file URL.
    let abs = href(&file, None);
    assert!(abs.starts_with("file:///"), "{abs}");
    assert!(
        abs.ends_with("/my%20night%20%232/cat_products/HD_1_1999-03-03T01_00_00.png"),
        "{abs}"
    );
}

#[test]
fn collect_links_each_figure_it_finds_from_the_page_folder() {
    let dir = tempfile::tempdir().unwrap();
    let products = dir.path().join("cat_products");
    std::fs::create_dir_all(&products).unwrap();
    let t = binary(
        "Alpha",
        comp("A", 0.03, 0.0, 0.001, &[]),
        comp("B", 0.0, 0.02, 0.001, &[]),
    );
    std::fs::write(products.join("Alpha_1999-03-03T01_00_00.png"), b"\x89PNG\r\n\x1a\nx").unwrap();
    let cat = Catalog {
        targets: vec![t],
        ..Default::default()
    };
    let opts = setup::Options {
        pairs: 1000,
        ..Default::default()
    };
    let input = collect(
        cat,
        &dir.path().join("cat.json"),
        Some(&products),
        Some(&dir.path().join("cat.html")),
        &opts,
        String::new(),
    );
    let f = &input.target_figures["Alpha@1999-03-03T01:00:00"];
    assert_eq!(f.href, "cat_products/Alpha_1999-03-03T01_00_00.png");
    let page = render(&input);
    assert!(
        page.contains("<a href=\"cat_products/Alpha_1999-03-03T01_00_00.png\" title=\"open the figure at full size\"><img alt=\"Alpha (Alpha@1999-03-03T01:00:00)\" src=\"data:image/png;base64,"),
        "the figure is not a link to its file"
    );
    assert_balanced(&page);
}

#[test]
fn a_hostile_link_is_escaped() {
    let mut inp = input(Catalog::default(), Err(not_computed("none")));
    let mut t = binary("T", comp("A", 0.03, 0.0, 0.001, &[]), comp("B", 0.0, 0.02, 0.001, &[]));
    t.sequence = Some("T@1".into());
    inp.catalog.targets.push(t);
    inp.target_figures.insert(
        "T@1".into(),
        TargetFigure {
            href: "\"><script>x</script>".into(),
            png: b"\x89PNG".to_vec(),
        },
    );
    let page = render(&inp);
    assert!(page.contains("<a href=\"&quot;&gt;&lt;script&gt;x&lt;/script&gt;\""));
    assert_balanced(&page);
}

#[test]
fn sequence_ids_break_only_after_the_at_sign_and_flags_between_words() {
    assert_eq!(
        sequence_id("HD 64299@1999-03-03T00:10:00"),
        "<span>HD 64299@</span><wbr><span>1999-03-03T00:10:00</span>"
    );
    assert_eq!(sequence_id("a@b@c"), "<span>a@b@</span><wbr><span>c</span>");
    assert_eq!(sequence_id("<x>"), "<span>&lt;x&gt;</span>");
    assert_eq!(breakable_at("a_b<c", '_'), "a_<wbr>b&lt;c");
    let mut cat = Catalog::default();
    let standard: StandardResult = serde_json::from_value(serde_json::json!({
        "name": "HD 64299", "object": "HD 64299", "sequence": "HD 64299@1999-03-03T00:10:00",
        "filter": "Ks", "status": "ok"
    }))
    .unwrap();
    cat.standards.push(standard);
    let page = render(&input(cat, Err(not_computed("none"))));
    assert!(
        page.contains("<span class=\"muted seq\"><span>HD 64299@</span><wbr><span>1999-03-03T00:10:00</span></span>")
    );
    assert_balanced(&page);
}

#[test]
fn every_cell_of_the_targets_table_carries_its_column_name() {
    let cat = Catalog {
        targets: vec![binary(
            "Alpha",
            comp("A", 0.03, 0.0, 0.001, &["low_snr"]),
            comp("B", 0.0, 0.02, 0.001, &[]),
        )],
        ..Default::default()
    };
    let page = render(&input(cat, Err(not_computed("none"))));
    let rows: Vec<&str> = page.lines().filter(|l| l.starts_with("<tr data-status")).collect();
    assert_eq!(rows.len(), 2);
    let headers = [
        "Target",
        "Status",
        "Comp.",
        "P [%]",
        "σP [%]",
        "γ [deg]",
        "σγ [deg]",
        "P/σ",
        "Cut",
        "Δγ [deg]",
        "σΔγ [deg]",
        "Mag",
        "Filter",
        "Flags",
    ];
    for row in rows {
        assert_eq!(row.matches("<td").count(), headers.len(), "{row}");
        let labels: Vec<&str> = row
            .split("<td data-label=\"")
            .skip(1)
            .map(|s| &s[..s.find('"').unwrap()])
            .collect();
        assert_eq!(labels, headers, "{row}");
    }
}

#[test]
fn the_pages_own_figures_are_files_beside_it_and_every_image_is_a_link() {
    let dir = tempfile::tempdir().unwrap();
    let mut targets = Vec::new();
    for (i, g) in [10.0_f64, 40.0, 75.0].iter().enumerate() {
        let r = (2.0 * g.to_radians()).sin_cos();
        targets.push(binary(
            &format!("B{i}"),
            comp("A", 0.03, 0.0, 0.001, &[]),
            comp("B", 0.02 * r.1, 0.02 * r.0, 0.001, &[]),
        ));
    }
    let cat = Catalog {
        targets,
        ..Default::default()
    };
    let opts = setup::Options {
        pairs: 1000,
        ..Default::default()
    };
    let page_path = dir.path().join("my night.html");
    let input = collect(
        cat,
        &dir.path().join("cat.json"),
        None,
        Some(&page_path),
        &opts,
        String::new(),
    );
    let figs = &input.stats.as_ref().expect("statistics").figures;
    assert_eq!(figs.len(), 2, "the observed and the ISM figures");
    // A figure left by an earlier page of that name that this one does not show: removed.
    let own = report_figures_dir(&page_path);
    assert_eq!(own, dir.path().join("my night_figures"));
    std::fs::create_dir_all(&own).unwrap();
    std::fs::write(own.join("quality.png"), b"old").unwrap();
    let written = write_figures(&page_path, &input).unwrap();
    assert_eq!(written, vec![own.join("observed.png"), own.join("ism_levels.png")]);
    assert!(!own.join("quality.png").exists(), "a stale figure is left");
    let page = render(&input);
    for (f, file) in figs.iter().zip(&written) {
        let href = f.href.as_deref().unwrap();
        assert_eq!(href, format!("my%20night_figures/{}", f.file));
        assert_eq!(std::fs::read(file).unwrap(), f.png, "{}", file.display());
        assert!(page.contains(&format!(
            "<a href=\"{href}\" title=\"open the figure at full size\"><img alt="
        )));
    }
    assert_eq!(page.matches("<img ").count(), 2);
    assert_eq!(
        page.matches("<img ").count(),
        page.matches("title=\"open the figure at full size\"><img ").count(),
        "an image that is not a link"
    );
    // On standard output: no folder, nothing to link to.
    let input = collect(
        input.catalog,
        &dir.path().join("cat.json"),
        None,
        None,
        &opts,
        String::new(),
    );
    assert!(input.stats.unwrap().figures.iter().all(|f| f.href.is_none()));
}
