//! The page builder: escaping, completeness, number formats, flags in words, degenerate
//! catalogs, base64 against RFC 4648's vectors.
use super::html::render;
use super::markup::escape;
use super::*;
use crate::catalog::{Catalog, Component, Failure, Flag, FlagCode, Status, Target};
use crate::stokes::inversion::{Debias, LinearPolarization};

const HOSTILE: &str = "<script>alert(\"x\")</script> & 'q' </td></table>";

pub(super) fn comp(name: &str, q: f64, u: f64, sigma: f64, flags: &[&str]) -> Component {
    let mut c = Component::new(
        name,
        LinearPolarization::from_qu(q, u, sigma, sigma, Debias::WardleKronberg).pol,
    );
    c.passes_cut = c.p / c.sigma_p > 3.0;
    c.snr = Some(c.p / c.sigma_p);
    c.flags = flags.iter().map(|f| Flag::parse(f)).collect();
    c
}

pub(super) fn binary(object: &str, a: Component, b: Component) -> Target {
    let mut t = Target::new(object, Status::Ok);
    t.sequence = Some(format!("{object}@1999-03-03T01:00:00"));
    t.components = vec![a, b];
    t.update_delta_gamma(None);
    t
}

/// Statistics that could not be computed: a statistics table named `why` unreadable.
pub(super) fn not_computed(why: &str) -> Error {
    Error::Stats(crate::error::StatsError::Table {
        table: why.into(),
        reason: "unreadable".into(),
    })
}

pub(super) fn input(catalog: Catalog, stats: Result<StatsSection>) -> ReportInput {
    ReportInput {
        catalog,
        catalog_path: "night/catalog.json".into(),
        figures_dir: Some("night/catalog_products".into()),
        target_figures: Default::default(),
        stats,
        quality_figure: None,
        command_line: "sofipol report night/catalog.json".into(),
    }
}

/// Non-void elements open and close in order (script and style content skipped): the
/// page is well-formed as far as its structure goes.
pub(super) fn assert_balanced(page: &str) {
    const VOID: [&str; 7] = ["meta", "br", "wbr", "img", "input", "hr", "link"];
    let mut stack: Vec<String> = Vec::new();
    let mut rest = page;
    while let Some(i) = rest.find('<') {
        rest = &rest[i + 1..];
        if rest.starts_with('!') {
            continue;
        }
        let end = rest.find('>').expect("unclosed tag");
        let tag = &rest[..end];
        let closing = tag.starts_with('/');
        let name: String = tag
            .trim_start_matches('/')
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric())
            .collect::<String>()
            .to_ascii_lowercase();
        rest = &rest[end + 1..];
        if closing {
            assert_eq!(
                stack.pop().as_deref(),
                Some(name.as_str()),
                "</{name}> closes the wrong element"
            );
        } else if !VOID.contains(&name.as_str()) {
            if name == "script" || name == "style" {
                let close = format!("</{name}>");
                rest = &rest[rest.find(&close).expect("script or style not closed") + close.len()..];
            } else {
                stack.push(name);
            }
        }
    }
    assert!(stack.is_empty(), "not closed: {stack:?}");
}

#[test]
fn base64_matches_the_rfc_4648_test_vectors() {
    for (plain, coded) in [
        ("", ""),
        ("f", "Zg=="),
        ("fo", "Zm8="),
        ("foo", "Zm9v"),
        ("foob", "Zm9vYg=="),
        ("fooba", "Zm9vYmE="),
        ("foobar", "Zm9vYmFy"),
    ] {
        assert_eq!(base64(plain.as_bytes()), coded, "{plain}");
    }
    assert_eq!(base64(&[0xff, 0xfe, 0x00]), "//4A");
}

#[test]
fn hostile_names_are_escaped_everywhere() {
    let mut failed = Target::new(HOSTILE, Status::Failed);
    failed.error = Some(format!("no sources in {HOSTILE}"));
    let mut cat = Catalog {
        targets: vec![
            binary(
                HOSTILE,
                comp("A\"><b>", 0.03, 0.01, 0.002, &[HOSTILE]),
                comp("B", 0.0, 0.04, 0.002, &[]),
            ),
            failed,
        ],
        failures: vec![Failure {
            file: format!("{HOSTILE}.fits"),
            error: HOSTILE.into(),
        }],
        provenance: serde_json::from_value(
            serde_json::json!({"command_line": ["sofipol", HOSTILE], "software": HOSTILE}),
        )
        .unwrap(),
        ..Default::default()
    };
    cat.schema_version = HOSTILE.into();
    let mut inp = input(cat, Err(not_computed(HOSTILE)));
    inp.catalog_path = HOSTILE.into();
    inp.command_line = HOSTILE.into();
    let page = render(&inp);
    assert!(!page.contains("<script>alert"), "an object name became a script");
    assert!(!page.contains("A\"><b>"));
    assert_eq!(page.matches("<script").count(), 2, "the page's own two scripts only");
    assert!(page.contains("&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; &#39;q&#39;"));
    assert_balanced(&page);
    assert_eq!(escape("a&b<c>d\"e'f"), "a&amp;b&lt;c&gt;d&quot;e&#39;f");
}

#[test]
fn every_target_and_component_has_a_row_with_its_numbers_in_percent_and_degrees() {
    // P = 0.05 (q = 0.03, u = 0.04), gamma = 26.565 deg; B: P = 0.02, gamma = 45 deg.
    let a = comp("A", 0.03, 0.04, 0.001, &[]);
    let b = comp("B", 0.0, 0.02, 0.001, &[]);
    let mut partial = binary(
        "Beta",
        comp("A", -0.01, 0.0, 0.001, &[]),
        comp("B", 0.0, -0.001, 0.001, &["low_snr"]),
    );
    partial.status = Status::Partial;
    let mut failed = Target::new("Gamma", Status::Failed);
    failed.error = Some("primary not found".into());
    let cat = Catalog {
        targets: vec![binary("Alpha", a.clone(), b.clone()), partial, failed],
        ..Default::default()
    };
    let page = render(&input(cat, Err(not_computed("not run"))));
    for (t, c) in [
        ("Alpha", "A"),
        ("Alpha", "B"),
        ("Beta", "A"),
        ("Beta", "B"),
        ("Gamma", ""),
    ] {
        assert_eq!(
            page.matches(&format!("data-target=\"{t}\" data-comp=\"{c}\"")).count(),
            1,
            "{t}/{c}"
        );
    }
    assert_eq!(page.matches("<tr data-status=").count(), 5);
    assert!(page.contains("<tr data-status=\"failed\" data-target=\"Gamma\""));
    assert!(page.contains("<tr data-status=\"partial\" data-target=\"Beta\""));
    // P in percent (debiased), gamma in degrees, Delta gamma folded.
    let pd = 100.0 * a.p_debiased;
    assert!(page.contains(&format!("data-v=\"{pd}\">{pd:.2}</td>")), "P of Alpha A");
    assert!((a.gamma_deg - 26.565).abs() < 1e-3 && (b.gamma_deg - 45.0).abs() < 1e-9);
    assert!(page.contains(&format!("data-v=\"{}\">26.6</td>", a.gamma_deg)));
    assert!(page.contains(">18.4</td>"), "Delta gamma = 45 - 26.57");
    assert!(page.contains(">primary not found<"));
    assert!(page.contains("1 partial") && page.contains("1 failed") && page.contains("3 targets"));
    assert_balanced(&page);
}

#[test]
fn flags_are_explained_in_words_and_unknown_ones_shown_as_they_are() {
    let mut t = binary(
        "Alpha",
        comp("A", 0.03, 0.04, 0.001, &["companion_overlap", "a_flag_from_the_future"]),
        comp(
            "B",
            0.0,
            0.02,
            0.001,
            &["stokes_method_failed: no angles; fell back to least_squares"],
        ),
    );
    t.flags = Some(vec![Flag::new(FlagCode::CompanionNotFound)]);
    let cat = Catalog {
        targets: vec![t],
        ..Default::default()
    };
    let page = render(&input(cat, Err(not_computed("not run"))));
    assert!(page.contains("The two stars&#39; apertures overlap (reported only)."));
    assert!(page.contains("The companion was not found"));
    assert!(page.contains("<li><code>a_<wbr>flag_<wbr>from_<wbr>the_<wbr>future</code></li>"));
    assert!(page.contains("another one was used (or none). (no angles; fell back to least_squares)"));
}

#[test]
fn an_empty_catalog_and_one_of_failures_only_give_whole_pages() {
    let empty = render(&input(Catalog::default(), Err(not_computed("no sample"))));
    assert_balanced(&empty);
    assert!(empty.contains("The catalog has no targets."));
    assert!(empty.contains("No per-target figures were found"));
    let mut f = Target::new("Alpha", Status::Failed);
    f.error = Some("no frames".into());
    let cat = Catalog {
        targets: vec![f],
        failures: vec![Failure {
            file: "x.fits".into(),
            error: "truncated".into(),
        }],
        ..Default::default()
    };
    let stats = statistics(
        &cat,
        "failures only",
        &setup::Options {
            pairs: 1000,
            ..Default::default()
        },
    );
    let s = stats.expect("the statistics of an empty sample");
    assert_eq!(s.sample.len(), 0);
    assert!(s.figures.is_empty());
    let page = render(&input(cat, Ok(s)));
    assert_balanced(&page);
    assert!(page.contains("<code>x.fits</code></td><td class=\"prose\">truncated</td>"));
    assert!(page.contains("0 binaries with both components above the cut"));
}

#[test]
fn the_statistics_section_is_what_sofipol_stats_computes_with_its_figures_embedded() {
    // Five aligned binaries: Delta gamma small for all.
    let targets: Vec<Target> = (0..5)
        .map(|i| {
            let g = 0.3 * i as f64;
            let a = comp("A", 0.04 * g.cos(), 0.04 * g.sin(), 0.002, &[]);
            let b = comp("B", 0.03 * (g + 0.1).cos(), 0.03 * (g + 0.1).sin(), 0.002, &[]);
            binary(&format!("T{i}"), a, b)
        })
        .collect();
    let cat = Catalog {
        targets,
        ..Default::default()
    };
    let opts = setup::Options {
        pairs: 5000,
        ism_levels_percent: vec![0.5, 2.0],
        ..Default::default()
    };
    let s = statistics(&cat, "test", &opts).unwrap();
    // The same call as `sofipol stats`.
    let sample = BinarySample::from_catalog(&cat, None);
    let direct = setup::analyse_sample(&sample, &setup::params(&sample, &opts, "test").unwrap()).unwrap();
    assert_eq!(s.report.verdict, direct.verdict);
    assert_eq!(s.report.n, 5);
    assert_eq!(s.figures.len(), 2);
    assert!(s.figures.iter().all(|f| f.png.starts_with(b"\x89PNG")));
    let page = render(&input(cat, Ok(s)));
    assert_eq!(page.matches("src=\"data:image/png;base64,iVBORw0KGgo").count(), 2);
    assert!(page.contains(&escape(&direct.verdict)));
    assert!(page.contains("KS against uniform"));
    assert_balanced(&page);
}

/// A summary count is coloured only when it is not zero: "0 failed" is not red, "1 failed"
/// is; the same for partial targets and unused inputs.
#[test]
fn zero_counts_in_the_summary_are_not_coloured() {
    let ok = || {
        binary(
            "Good",
            comp("A", 0.02, 0.0, 0.001, &[]),
            comp("B", 0.0, 0.03, 0.001, &[]),
        )
    };
    let page = render(&input(
        Catalog {
            targets: vec![ok()],
            ..Default::default()
        },
        Err(not_computed("none")),
    ));
    assert!(page.contains("<li class=\"st-ok\">1 ok</li>"), "{page}");
    for zero in ["<li>0 partial</li>", "<li>0 failed</li>", "<li>0 inputs not used</li>"] {
        assert!(page.contains(zero), "{zero} missing");
    }
    let mut cat = Catalog {
        targets: vec![ok(), Target::new("Lost", Status::Failed)],
        ..Default::default()
    };
    cat.failures.push(Failure {
        file: "x.fits".into(),
        error: "unreadable".into(),
    });
    let page = render(&input(cat, Err(not_computed("none"))));
    assert!(page.contains("<li class=\"st-failed\">1 failed</li>"), "{page}");
    assert!(
        page.contains("<li class=\"st-partial\">1 inputs not used</li>"),
        "{page}"
    );
}

#[test]
fn the_quality_section_has_a_row_per_frame_the_outliers_marked_and_the_figure() {
    let mut t = binary(
        "HK <Tau>",
        comp("A", 0.03, 0.0, 0.003, &[]),
        comp("B", 0.0, 0.02, 0.003, &[]),
    );
    let q = |i: usize, fwhm: f64, transparency: f64| crate::catalog::FrameQuality {
        file: format!("/night/raw/hk_{i}.fits"),
        posang_deg: if i < 3 { 0.0 } else { 45.0 },
        dither: 1 + i % 3,
        mjd: Some(61005.1 + 0.01 * i as f64),
        airmass: Some(1.2),
        fwhm_arcsec: Some(fwhm),
        sky_adu: Some(1400.0 + 10.0 * i as f64),
        transparency: Some(transparency),
    };
    t.frame_quality = Some(vec![
        q(0, 0.8, 1.0),
        q(1, 0.80, 0.99),
        q(2, 1.5, 1.01),
        q(3, 0.79, 1.0),
        q(4, 0.81, 0.6),
        q(5, 0.8, 1.0),
    ]);
    let cat = Catalog {
        targets: vec![t],
        ..Default::default()
    };
    let mut inp = input(cat, Err(not_computed("none")));
    inp.quality_figure = quality_figure(&inp.catalog);
    let png = &inp.quality_figure.as_ref().expect("a figure").png;
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));
    let page = render(&inp);
    assert_balanced(&page);
    let section = page
        .split("<section id=\"quality\">")
        .nth(1)
        .unwrap()
        .split("</section>")
        .next()
        .unwrap();
    assert_eq!(section.matches("<tr><td title=").count(), 6, "{section}");
    assert!(
        section.contains("HK &lt;Tau&gt;") && !section.contains("HK <Tau>"),
        "{section}"
    );
    assert!(section.contains("seeing <strong>0.80″</strong>"), "{section}");
    let marked: Vec<&str> = section
        .lines()
        .filter(|l| l.contains("<span class=\"st-partial\">"))
        .collect();
    assert_eq!(marked.len(), 2, "{section}");
    assert!(
        marked[0].contains("hk_2.fits") && marked[0].contains(">seeing</span>"),
        "{}",
        marked[0]
    );
    assert!(
        marked[1].contains("hk_4.fits") && marked[1].contains(">transparency</span>"),
        "{}",
        marked[1]
    );
    assert!(
        section.contains("<img alt=\"Seeing, sky level and transparency"),
        "{section}"
    );
    assert!(page.contains("<a href=\"#quality\">"), "no link to the section");
    assert_eq!(
        quality_figure_path(Path::new("out/night.html")),
        Path::new("out/night_figures/quality.png")
    );
}

#[test]
fn a_catalog_without_frame_quality_says_so_and_has_no_figure() {
    let cat = Catalog {
        targets: vec![binary(
            "X",
            comp("A", 0.03, 0.0, 0.003, &[]),
            comp("B", 0.0, 0.02, 0.003, &[]),
        )],
        ..Default::default()
    };
    assert!(quality_figure(&cat).is_none());
    let page = render(&input(cat, Err(not_computed("none"))));
    assert!(page.contains("The catalog has no per-frame quality"), "{page}");
}

/// A target with a foreground gets a row in the foreground section with the Delta-gamma
/// before and after the subtraction; a catalog without any has no such section.
#[test]
fn the_foreground_section_shows_delta_gamma_before_and_after() {
    let mut t = binary(
        "Fg Tau",
        comp("A", 0.03, 0.0, 0.001, &[]),
        comp("B", 0.02, 0.01, 0.001, &[]),
    );
    let plain = render(&input(
        Catalog {
            targets: vec![t.clone()],
            ..Catalog::default()
        },
        Err(not_computed("none")),
    ));
    assert!(!plain.contains("id=\"foreground\""));
    let mut f = crate::catalog::Foreground::new(0.02, 0.0, 0.001, 0.001, 0.0);
    f.n_used = Some(12);
    f.source = Some("field stars, n = 12".into());
    t.foreground = Some(f);
    t.update_delta_gamma(None);
    let page = render(&input(
        Catalog {
            targets: vec![t.clone()],
            ..Catalog::default()
        },
        Err(not_computed("none")),
    ));
    assert_balanced(&page);
    let section = &page[page.find("id=\"foreground\"").expect("a foreground section")..];
    let row = &section[section.find("<td>Fg Tau</td>").expect("its row")..];
    let row = &row[..row.find("</tr>").unwrap()];
    let after = format!("{:.1}", t.delta_gamma_fg_corrected_deg.unwrap());
    let before = format!("{:.1}", t.delta_gamma_deg.unwrap());
    assert!(
        row.contains(&after) && row.contains(&before) && row.contains("<td>12</td>"),
        "{row}"
    );
    assert_ne!(after, before);
}

/// A half-wave-plate target's section: its rows in both frames, the zero point's source and
/// the agreement where the cycles were compared, escaped, the page balanced; none for SOFI.
#[test]
fn the_half_wave_plate_section_shows_a_target_s_cycles_and_only_there() {
    use crate::catalog::half_wave_plate::{CycleAgreement, CycleResult, HalfWavePlateResult, Pol, ZeroPoint};
    let p = Pol::new(0.01, -0.02, 0.001, 0.001, 0.001, 0.001);
    let mut t = Target::new("Single <Star>", Status::Ok);
    t.components = vec![comp("A", p.q, p.u, p.sigma_q, &[])];
    t.half_wave_plate = Some(HalfWavePlateResult {
        component_from: "cycles".into(),
        zero_point: ZeroPoint {
            deg: 26.0,
            sigma_deg: 12.0,
            source: HOSTILE.into(),
        },
        profile: "NIRC2".into(),
        modulation: "half_wave_plate".into(),
        field_rotation: "sky_fixed".into(),
        darks: vec![],
        skies: vec![],
        flat_from: vec![],
        sky_cosmic_ray_pixels: 0,
        bad_pixels: 3,
        instrument: Some(p),
        sky: Some(p),
        cycles: vec![CycleResult {
            frames: vec!["a.fits".into()],
            instrument: p,
            sky: p,
        }],
        cycle_agreement: Some(CycleAgreement {
            q_difference_sigma: vec![1.5],
            u_difference_sigma: vec![-0.5],
            chi2_q: 2.25,
            chi2_u: 0.25,
            dof: 1,
        }),
        least_squares_instrument: None,
        least_squares_sky: None,
        left_out: vec!["late.fits".into()],
        frames: vec![],
    });
    let sofi = Catalog {
        targets: vec![binary(
            "Alpha",
            comp("A", 0.03, 0.0, 0.002, &[]),
            comp("B", 0.0, 0.03, 0.002, &[]),
        )],
        ..Catalog::default()
    };
    let mut cat = sofi.clone();
    cat.targets.push(t);
    let page = render(&input(cat, Err(not_computed("x"))));
    assert_balanced(&page);
    let i = page.find("<section id=\"half-wave-plate\">").expect("the section");
    let section = &page[i..i + page[i..].find("</section>").unwrap()];
    assert!(section.contains("Single &lt;Star&gt;") && section.contains(&escape(HOSTILE)));
    assert!(!section.contains("<script>"));
    // Sky-fixed: the cycles compared in the instrument frame, the chi2 on that row.
    assert!(
        section.contains("<td>cycles combined</td><td>instrument</td>"),
        "{section}"
    );
    assert!(
        section.contains("q 2.2, u 0.2 / 1") || section.contains("q 2.3, u 0.3 / 1"),
        "{section}"
    );
    assert!(section.contains("<td>cycles combined ★</td><td>sky</td>"), "{section}");
    assert!(section.contains("1.5 σ in q") && section.contains("instrument frame") && section.contains("late.fits"));
    let page = render(&input(sofi, Err(not_computed("x"))));
    assert!(!page.contains("half-wave-plate"));
}
