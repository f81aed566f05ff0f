//! The reduction-level cases of the numerical-stability suite. Each simulates a
//! 2-target scene (Alpha, Beta), damages Alpha in one way (or observes both in an unusual
//! way) and checks the property named by the test; the undamaged Beta must come out
//! exactly as in the clean reduction.
use sofipol_calib::{Frame, Profile};
use sofipol_pipeline::catalog::{FlagCode, Target};
use sofipol_pipeline::reduce::run::{reduce_loaded, LoadedOrientation};
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sequence::Sequence;
use sofipol_pipeline::sim::{loaded_from_sim, FrameTruth, Scene, Simulator, Truth};

/// The scene: `obs` is the `[observation]` body, `alpha` and `beta` the binaries' keys
/// after the name.
fn scene(obs: &str, effects: &str, alpha: &str) -> String {
    format!(
        r#"name = "stab"
seed = 11
effects = ["psf", "sky", "strips", "photon_noise", "read_noise"{effects}]
[observation]
{obs}
[psf]
kind = "moffat"
fwhm_arcsec = 0.8
[[binary]]
name = "Alpha"
{alpha}
[[binary]]
name = "Beta"
separation_arcsec = 3.0
pa_deg = 200.0
flux_a = 100000.0
flux_b = 70000.0
p_a = 0.03
gamma_a_deg = 60.0
p_b = 0.06
gamma_b_deg = 150.0
"#
    )
}

const ALPHA: &str = r#"separation_arcsec = 3.5
pa_deg = 30.0
flux_a = 120000.0
flux_b = 60000.0
p_a = 0.05
gamma_a_deg = 20.0
p_b = 0.04
gamma_b_deg = 110.0"#;

const OBS: &str = "orientations_deg = [0.0, 45.0]\ndithers = 4";

struct Loaded {
    seq: Sequence,
    orients: Vec<LoadedOrientation>,
    truths: Vec<FrameTruth>,
}

fn simulate(text: &str) -> (Simulator, Truth) {
    let sim = Simulator::new(Scene::from_toml(text, "stability scene").unwrap(), Profile::sofi()).unwrap();
    let truth = sim.truth(&[]);
    (sim, truth)
}

fn load(sim: &Simulator, t: usize) -> Loaded {
    load_with(sim, t, |_, _| {})
}

/// Target `t`, each simulated frame first passed to `damage(k, frame)` (k: exposure order).
fn load_with(sim: &Simulator, t: usize, damage: impl Fn(usize, &mut sofipol_pipeline::sim::SimFrame)) -> Loaded {
    let mut frames: Vec<_> = (0..sim.frames_per_target()).map(|k| sim.frame(t, k)).collect();
    for (k, f) in frames.iter_mut().enumerate() {
        damage(k, f);
    }
    let truths = frames.iter().map(|f| f.truth.clone()).collect();
    let (seq, orients) = loaded_from_sim(frames, &Profile::sofi());
    Loaded { seq, orients, truths }
}

fn reduce(l: Loaded) -> Target {
    reduce_loaded(
        &l.seq,
        l.orients,
        &Profile::sofi(),
        &TargetParams::default(),
        None,
        None,
        false,
    )
    .target
}

/// Frame `k` (exposure order) of a loaded target.
fn frame_mut(l: &mut Loaded, k: usize) -> &mut Frame {
    let mut k = k;
    for o in &mut l.orients {
        if k < o.2.len() {
            return &mut o.2[k];
        }
        k -= o.2.len();
    }
    panic!("no frame {k}")
}

/// Source `name` ("A", "B") of frame `k`: (o_xy, e_xy).
fn source(l: &Loaded, k: usize, name: &str) -> ([f64; 2], [f64; 2]) {
    let s = l.truths[k].sources.iter().find(|s| s.name == name).unwrap();
    (s.o_xy, s.e_xy)
}

/// Set pixels within `r` of `xy` to `v`.
fn paint(f: &mut Frame, xy: [f64; 2], r: f64, v: f32) {
    let (ny, nx) = f.shape();
    for y in 0..ny {
        for x in 0..nx {
            if (x as f64 - xy[0]).hypot(y as f64 - xy[1]) <= r {
                f.data[[y, x]] = v;
            }
        }
    }
}

fn describe(t: &Target) -> String {
    let mut s = format!("{} {:?} {:?} flags {:?}\n", t.object, t.status, t.error, t.flags);
    for c in &t.components {
        s += &format!(
            "  {}: q {:.4} +- {:.4} u {:.4} +- {:.4} flags {:?}\n",
            c.name, c.q, c.sigma_q, c.u, c.sigma_u, c.flags
        );
    }
    s
}

/// Every component agrees with the truth within `k` sigma (components matched by name).
fn within(t: &Target, truth: &Truth, k: f64) -> Result<(), String> {
    let tt = truth.targets.iter().find(|x| x.object == t.object).unwrap();
    for c in &t.components {
        let tc = tt.components.iter().find(|x| x.name == c.name).unwrap();
        let (pq, pu) = ((c.q - tc.q) / c.sigma_q, (c.u - tc.u) / c.sigma_u);
        if !(pq.abs() < k && pu.abs() < k) {
            return Err(format!(
                "{} {}: pulls {pq:.2} {pu:.2} (truth q {:.4} u {:.4})",
                t.object, c.name, tc.q, tc.u
            ));
        }
    }
    Ok(())
}

/// The clean reduction of both targets, checked against the truth, and Beta's.
fn clean(text: &str) -> (Simulator, Truth, Target) {
    let (sim, truth) = simulate(text);
    let a = reduce(load(&sim, 0));
    let b = reduce(load(&sim, 1));
    within(&a, &truth, 4.0).unwrap();
    within(&b, &truth, 4.0).unwrap();
    for c in a.components.iter().chain(&b.components) {
        assert!(
            c.flags.is_empty(),
            "clean run flagged: {}{}",
            describe(&a),
            describe(&b)
        );
    }
    (sim, truth, b)
}

/// Beta, reduced again, is the clean Beta (the damage to Alpha does not reach it).
fn beta_untouched(sim: &Simulator, clean_b: &Target) {
    let b = reduce(load(sim, 1));
    assert_eq!(format!("{:?}", b.components), format!("{:?}", clean_b.components));
}

fn has_flag(t: &Target, comp: &str, flag: &str) -> bool {
    t.components
        .iter()
        .any(|c| c.name == comp && c.flags.iter().any(|f| f.code.name() == flag))
}

/// Every number a component promises is finite.
fn all_finite(t: &Target) -> bool {
    t.components.iter().all(|c| {
        [
            c.q,
            c.u,
            c.sigma_q,
            c.sigma_u,
            c.p,
            c.sigma_p,
            c.p_debiased,
            c.gamma_deg,
            c.sigma_gamma_deg,
        ]
        .iter()
        .all(|v| v.is_finite())
    })
}

/// One beam saturated: the o image of A in one dither is clipped at 40000 ADU (above the
/// profile's saturation level), the e image is not. That dither is rejected and A flagged
/// `saturated`; q and u come from the other dithers, within their errors.
#[test]
fn one_saturated_beam_is_flagged_and_the_numbers_stay_right() {
    let (sim, truth, clean_b) = clean(&scene(OBS, "", ALPHA));
    let mut l = load(&sim, 0);
    let (o, _) = source(&l, 0, "A");
    paint(frame_mut(&mut l, 0), o, 2.5, 40000.0);
    let t = reduce(l);
    assert!(has_flag(&t, "A", "saturated"), "{}", describe(&t));
    assert!(all_finite(&t) && within(&t, &truth, 4.0).is_ok(), "{}", describe(&t));
    beta_untouched(&sim, &clean_b);
}

/// A dead column through B's o image in dither 1 (the column is dead in every frame, as a
/// detector defect is) and a dead 5 x 5 cluster on A's e image in dither 2: the defects
/// are found, the dithers whose apertures hold them are rejected and the components
/// flagged `bad_pixels`; q and u stay within their errors.
#[test]
fn a_component_on_a_bad_column_or_cluster_is_flagged() {
    let (sim, truth, clean_b) = clean(&scene(OBS, "", ALPHA));
    let l0 = load(&sim, 0);
    let col = source(&l0, 0, "B").0[0].round() as usize;
    let cl = source(&l0, 1, "A").1;
    let g = Profile::sofi().geometry;
    let l = load_with(&sim, 0, |_, f| {
        for y in g.o_target[0]..g.o_target[1] {
            f.frame.data[[y, col]] = 0.0;
        }
        for y in cl[1].round() as usize - 2..=cl[1].round() as usize + 2 {
            for x in cl[0].round() as usize - 2..=cl[0].round() as usize + 2 {
                f.frame.data[[y, x]] = 0.0;
            }
        }
    });
    let t = reduce(l);
    assert!(has_flag(&t, "B", "bad_pixels"), "{}", describe(&t));
    assert!(has_flag(&t, "A", "bad_pixels"), "{}", describe(&t));
    assert!(all_finite(&t) && within(&t, &truth, 4.0).is_ok(), "{}", describe(&t));
    beta_untouched(&sim, &clean_b);
}

/// f_o + f_e <= 0 in a dither: B's o and e images in dither 4 are replaced by a hole
/// (0 ADU, under the sky), so its sky-subtracted fluxes are negative. The dither is
/// rejected (never a F from a negative sum), B flagged, every number finite and right.
#[test]
fn a_dither_with_a_negative_flux_sum_is_rejected() {
    let (sim, truth, clean_b) = clean(&scene(OBS, "", ALPHA));
    let mut l = load(&sim, 0);
    let (o, e) = source(&l, 3, "B");
    let f = frame_mut(&mut l, 3);
    paint(f, o, 6.0, 0.0);
    paint(f, e, 6.0, 0.0);
    let t = reduce(l);
    eprintln!("{}", describe(&t));
    let b = t.components.iter().find(|c| c.name == "B").expect("B measured");
    assert!(
        b.flags.iter().any(|f| f.is(FlagCode::PhotometryFailed)),
        "{}",
        describe(&t)
    );
    assert!(all_finite(&t) && within(&t, &truth, 4.0).is_ok(), "{}", describe(&t));
    beta_untouched(&sim, &clean_b);
}

/// Mixed DIT within a sequence: dither 2 exposed twice as long (data x 2, DIT 20 s in its
/// header). Normalised, not refused, and said so: flag `mixed_exposure: ...`; q and u
/// within their errors.
#[test]
fn mixed_dit_within_a_sequence_is_normalised_and_flagged() {
    let (sim, truth, clean_b) = clean(&scene(OBS, "", ALPHA));
    let p = Profile::sofi();
    let l = load_with(&sim, 0, |k, f| {
        if k == 1 {
            f.frame.data.mapv_inplace(|v| 2.0 * v);
            let dit = f.frame.header.get_f64(&p.keywords.dit).unwrap();
            f.frame.header.set(&p.keywords.dit, 2.0 * dit);
        }
    });
    let t = reduce(l);
    let flags = t.flags.as_ref().unwrap();
    assert!(
        flags
            .iter()
            .any(|f| f.to_string().starts_with("mixed_exposure: DIT [10.0, 20.0]")),
        "{}",
        describe(&t)
    );
    assert!(all_finite(&t) && within(&t, &truth, 4.0).is_ok(), "{}", describe(&t));
    beta_untouched(&sim, &clean_b);
}

/// 3 orientations at angles not 45 deg apart (0, 30, 100): q and u by least squares over
/// the orientations, within their errors for both targets.
#[test]
fn three_orientations_not_45_degrees_apart_give_q_and_u_within_errors() {
    let (sim, truth) = simulate(&scene("orientations_deg = [0.0, 30.0, 100.0]\ndithers = 3", "", ALPHA));
    for t in 0..2 {
        let r = reduce(load(&sim, t));
        assert_eq!(r.components.len(), 2, "{}", describe(&r));
        assert!(all_finite(&r) && within(&r, &truth, 4.0).is_ok(), "{}", describe(&r));
    }
}

/// Apertures truncated by a strip edge: A near the bottom of the o-target strip and B
/// 6.6" below it, so that B's o image sits on the strip edge (half of it behind the focal
/// mask) in some dithers. Never silent: B is flagged `truncated` and either within its
/// errors (from the whole dithers) or failing the cut; A, whole, within its errors.
#[test]
fn an_aperture_truncated_by_a_strip_edge_is_flagged_or_refused() {
    let alpha = format!("{ALPHA}\ny_px = 366.0")
        .replace("pa_deg = 30.0", "pa_deg = 180.0")
        .replace("separation_arcsec = 3.5", "separation_arcsec = 6.6");
    let (sim, truth) = simulate(&scene(OBS, "", &alpha));
    let t = reduce(load(&sim, 0));
    assert!(all_finite(&t), "{}", describe(&t));
    let tt = &truth.targets[0].components;
    let pulls_ok = |c: &sofipol_pipeline::catalog::Component| {
        let tc = tt.iter().find(|x| x.name == c.name).unwrap();
        ((c.q - tc.q) / c.sigma_q).abs() < 4.0 && ((c.u - tc.u) / c.sigma_u).abs() < 4.0
    };
    match t.components.iter().find(|c| c.name == "B") {
        // Where every dither of an orientation is truncated the value is reported
        // (`used_flagged_dithers`, q = -0.78 for a true -0.03 here) but never passes the cut.
        Some(b) => assert!(
            b.flags.iter().any(|f| f.is(FlagCode::Truncated)) && (pulls_ok(b) || !b.passes_cut),
            "{}",
            describe(&t)
        ),
        None => assert!(!t.flags.as_ref().unwrap().is_empty(), "{}", describe(&t)),
    }
    assert!(pulls_ok(&t.components[0]), "{}", describe(&t));
}

/// 0.5" pairs of equal flux (A and B at 1.7 px, 0.6 FWHM): the labels must not change
/// between orientations or dithers. A and B have q = +0.06 and -0.06: a label swapped in
/// some frames would mix them (|q| far below 0.06); both come out within their errors.
#[test]
fn equal_pairs_at_half_an_arcsec_keep_their_labels() {
    let alpha = "separation_arcsec = 0.5\npa_deg = 30.0\nflux_a = 120000.0\nflux_b = 120000.0\n\
                 p_a = 0.06\ngamma_a_deg = 0.0\np_b = 0.06\ngamma_b_deg = 90.0";
    let (sim, truth) = simulate(&scene(OBS, "", alpha));
    let t = reduce(load(&sim, 0));
    assert_eq!(t.components.len(), 2, "{}", describe(&t));
    // Equal fluxes: the reduction may call either star A; match the truth by position angle.
    let pa = t.pa_deg.unwrap();
    let swapped = (pa - 30.0).rem_euclid(360.0) > 90.0 && (pa - 30.0).rem_euclid(360.0) < 270.0;
    let tt = &truth.targets[0].components;
    for (i, c) in t.components.iter().enumerate() {
        let tc = &tt[if swapped { 1 - i } else { i }];
        let (pq, pu) = ((c.q - tc.q) / c.sigma_q, (c.u - tc.u) / c.sigma_u);
        assert!(
            pq.abs() < 4.0 && pu.abs() < 4.0,
            "{} pulls {pq:.1} {pu:.1}\n{}",
            c.name,
            describe(&t)
        );
    }
}

/// 1:100 companions next to a bright (1e6 ADU, its core above the saturation level) or a
/// saturated (3e6 ADU) primary: the companion is measured within its errors or not
/// measured with the reason flagged; a primary whose every dither is saturated is flagged
/// `saturated` and does not pass the cut (it came out at q = -0.037 for a true +0.030,
/// passing the cut, before). Never a wild number passing the cut.
#[test]
fn faint_companions_next_to_bright_or_saturated_primaries_are_measured_or_flagged() {
    for (sep, fa, sat) in [
        (1.5, 1.0e6, ""),
        (3.0, 1.0e6, ""),
        (2.0, 3.0e6, ", \"saturation\""),
        (4.0, 3.0e6, ", \"saturation\""),
    ] {
        let alpha = format!(
            "separation_arcsec = {sep}\npa_deg = 30.0\nflux_a = {fa}\nflux_b = {}\n\
             p_a = 0.03\ngamma_a_deg = 0.0\np_b = 0.06\ngamma_b_deg = 90.0",
            fa / 100.0
        );
        let (sim, truth) = simulate(&scene(OBS, sat, &alpha));
        let t = reduce(load(&sim, 0));
        let case = format!("sep {sep} flux {fa}{sat}\n{}", describe(&t));
        assert!(all_finite(&t), "{case}");
        let tt = &truth.targets[0].components;
        for c in &t.components {
            let tc = tt.iter().find(|x| x.name == c.name).unwrap();
            let ok = ((c.q - tc.q) / c.sigma_q).abs() < 4.0 && ((c.u - tc.u) / c.sigma_u).abs() < 4.0;
            assert!(
                ok || (!c.passes_cut && !c.flags.is_empty()),
                "{} wild and passing: {case}",
                c.name
            );
        }
        if t.components.len() < 2 {
            let flags = t.flags.as_ref().unwrap();
            assert!(flags.iter().any(|f| f.code.name().starts_with("companion_")), "{case}");
        }
        if !sat.is_empty() {
            assert!(
                t.components[0].flags.iter().any(|f| f.is(FlagCode::Saturated)),
                "{case}"
            );
        }
    }
}
