//! A Savart-plate-like imager (testdata/profiles/savart_like.toml: no focal mask, the e
//! image of every source 30.6 px from its o image along a diagonal, both images of every
//! star on the whole detector) in a crowded field (testdata/scenes/savart_like.toml: ~190
//! field stars per target, one half way between the target's two images): the reduction
//! finds the target by its position and its e image by the offset vector, and its q, u
//! errors are honest. The pulls `(q - q_true) / sigma_q` and `(u - u_true) / sigma_u` of
//! both components of six binaries, pooled over eight seeds (96 components, 192 pulls), have
//! a standard deviation within [0.9, 1.1] and a mean within 3 standard errors of 0; the
//! usable field stars' pulls a standard deviation within [0.9, 1.1] (1.17 before the o-e
//! residual of each star was searched for sources on one of its images), none beyond 6.
use sofipol_calib::Profile;
use sofipol_pipeline::catalog::{FlagCode, Status, Target};
use sofipol_pipeline::reduce::run::reduce_loaded;
use sofipol_pipeline::reduce::TargetParams;
use sofipol_pipeline::sim::{loaded_from_sim, Scene, Simulator, Truth};

fn repo(rel: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(rel)
}

fn savart_profile() -> Profile {
    Profile::sofi_with_override(&repo("testdata/profiles/savart_like.toml")).unwrap()
}

fn scene(seed: u64) -> Scene {
    let text = std::fs::read_to_string(repo("testdata/scenes/savart_like.toml")).unwrap();
    let text = text.replacen("seed = 1\n", &format!("seed = {seed}\n"), 1);
    Scene::from_toml(&text, "savart_like.toml").unwrap()
}

/// Every target of the scene simulated with `sim_profile` and reduced with `profile`.
fn night(seed: u64, sim_profile: &Profile, profile: &Profile) -> (Vec<Target>, Truth) {
    let sim = Simulator::new(scene(seed), sim_profile.clone()).unwrap();
    let n = sim.frames_per_target();
    let mut truths = Vec::new();
    let mut targets = Vec::new();
    for t in 0..sim.n_sequences() {
        let frames: Vec<_> = (0..n).map(|k| sim.frame(t, k)).collect();
        truths.push(frames.iter().map(|f| f.truth.clone()).collect::<Vec<_>>());
        let (seq, orients) = loaded_from_sim(frames, sim_profile);
        targets.push(reduce_loaded(&seq, orients, profile, &TargetParams::default(), None, None, false).target);
    }
    (targets, sim.truth(&truths))
}

/// The pulls of q and u of every component measured, and the number of components the
/// truth holds that were not measured.
fn pulls(targets: &[Target], truth: &Truth) -> (Vec<f64>, usize) {
    let mut out = Vec::new();
    let mut missing = 0;
    for (t, tt) in targets.iter().zip(&truth.targets) {
        if t.status == Status::Failed || t.components.len() != tt.components.len() {
            missing += tt.components.len();
            continue;
        }
        for (c, ct) in t.components.iter().zip(&tt.components) {
            let (pq, pu) = ((c.pol.q - ct.q) / c.pol.sigma_q, (c.pol.u - ct.u) / c.pol.sigma_u);
            if pq.abs().max(pu.abs()) > 4.0 {
                eprintln!(
                    "{} {}: q {:.4} (true {:.4}) u {:.4} (true {:.4}) pulls {pq:.1} {pu:.1}; flags {:?} {:?}",
                    t.object, c.name, c.pol.q, ct.q, c.pol.u, ct.u, c.flags, t.flags
                );
            }
            out.push(pq);
            out.push(pu);
        }
    }
    (out, missing)
}

/// Whether a field star is `blended` by the o-e residual alone: every source its flag
/// names is one found on the o-e residual, and nothing else makes it unusable.
fn blended_by_residual_only(f: &sofipol_pipeline::catalog::FieldStar) -> bool {
    let blend = f.star.flags.iter().find(|g| g.is(FlagCode::Blended));
    let others_unusable = f.star.flags.iter().any(|g| {
        !g.is(FlagCode::Blended)
            && sofipol_pipeline::catalog::field_stars::UNUSABLE
                .iter()
                .any(|&c| g.is(c))
    });
    blend.and_then(|g| g.detail.as_deref()).is_some_and(|d| {
        d.split(", ")
            .all(|part| part.starts_with("a source on the o-e residual"))
    }) && !others_unusable
        && f.star.pol.q.is_finite()
}

/// The pulls of q and u of the usable field stars not flagged `blended` that match a
/// simulated one (same sky position within 0.6"), the number of usable field stars
/// matching none (a false pair: an o image paired with another star's e image), and the
/// number matched: usable, and usable but for a `blended` flag of the o-e residual alone.
fn field_pulls(targets: &[Target], truth: &Truth) -> (Vec<f64>, usize, usize, usize) {
    let en = |sep: f64, pa: f64| {
        let a = pa.to_radians();
        (sep * a.sin(), sep * a.cos())
    };
    let (mut out, mut false_pairs, mut matched, mut residual) = (Vec::new(), 0, 0, 0);
    for (t, tt) in targets.iter().zip(&truth.targets) {
        residual += t
            .field_stars
            .iter()
            .flatten()
            .filter(|f| blended_by_residual_only(f))
            .filter_map(|f| matching_star(tt, en(f.separation_arcsec, f.pa_deg)).map(|s| (f, s)))
            .inspect(|(f, s)| {
                let (pq, pu) = (
                    (f.star.pol.q - s.q) / f.star.pol.sigma_q,
                    (f.star.pol.u - s.u) / f.star.pol.sigma_u,
                );
                if pq.abs().max(pu.abs()) > 4.0 {
                    eprintln!(
                        "{} {} at {:.2}\" PA {:.1}, blended by the o-e residual: pulls {pq:.1} {pu:.1}; flags {:?}",
                        t.object, f.id, f.separation_arcsec, f.pa_deg, f.star.flags
                    );
                }
            })
            .count();
        for f in t.field_stars.iter().flatten().filter(|f| f.usable) {
            let m = en(f.separation_arcsec, f.pa_deg);
            let found = matching_star(tt, m);
            match found {
                Some(_) if f.star.flags.iter().any(|g| g.is(FlagCode::Blended)) => matched += 1,
                Some(s) => {
                    matched += 1;
                    let (pq, pu) = (
                        (f.star.pol.q - s.q) / f.star.pol.sigma_q,
                        (f.star.pol.u - s.u) / f.star.pol.sigma_u,
                    );
                    if pq.abs().max(pu.abs()) > 4.0 {
                        eprintln!(
                            "{} {} at {:.2}\" PA {:.1}: q {:.4} (true {:.4}) u {:.4} (true {:.4}) pulls {pq:.1} {pu:.1}; flags {:?}",
                            t.object, f.id, f.separation_arcsec, f.pa_deg, f.star.pol.q, s.q, f.star.pol.u, s.u, f.star.flags
                        );
                    }
                    out.push(pq);
                    out.push(pu);
                }
                None => false_pairs += 1,
            }
        }
    }
    (out, false_pairs, matched, residual)
}

/// The simulated field star that a star measured at sky offset `m` from A (arcsec east,
/// north) is: the brightest within 0.6" (a much fainter one at the same place adds a
/// trace of light; the first found could be that one).
fn matching_star(
    tt: &sofipol_pipeline::sim::TargetTruth,
    m: (f64, f64),
) -> Option<&sofipol_pipeline::sim::FieldStarTruth> {
    tt.field_stars
        .iter()
        .filter(|s| {
            let a = s.pa_deg.to_radians();
            let e = (s.separation_arcsec * a.sin(), s.separation_arcsec * a.cos());
            (e.0 - m.0).hypot(e.1 - m.1) < 0.6
        })
        .max_by(|a, b| a.flux.total_cmp(&b.flux))
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    (m, (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt())
}

#[test]
fn savart_like_crowded_field_gives_honest_pulls_over_eight_seeds() {
    let profile = savart_profile();
    assert!(!profile.geometry.has_mask());
    let mut all = Vec::new();
    let mut missing = 0;
    let (mut field, mut false_pairs, mut matched, mut by_residual) = (Vec::new(), 0, 0, 0);
    for seed in 1..=8u64 {
        let (targets, truth) = night(seed, &profile, &profile);
        let (fp, fa, fm, fr) = field_pulls(&targets, &truth);
        field.extend(fp);
        false_pairs += fa;
        matched += fm;
        by_residual += fr;
        let (p, m) = pulls(&targets, &truth);
        let (mean, sd) = mean_sd(&p);
        eprintln!(
            "seed {seed}: {} pulls, mean {mean:.3}, sd {sd:.3}, {m} components missing",
            p.len()
        );
        all.extend(p);
        missing += m;
    }
    let (mean, sd) = mean_sd(&all);
    let n = all.len();
    let worst = all.iter().fold(0f64, |a, b| a.max(b.abs()));
    eprintln!("pooled: {n} pulls, mean {mean:.3}, sd {sd:.3}, |pull| max {worst:.2}, {missing} components missing");
    let (fmean, fsd) = mean_sd(&field);
    let fworst = field.iter().fold(0f64, |a, b| a.max(b.abs()));
    let flagged = by_residual as f64 / (matched + by_residual) as f64;
    eprintln!(
        "field stars: {matched} usable matched ({} pulls, mean {fmean:.3}, sd {fsd:.3}, |pull| max {fworst:.2}), \
         {false_pairs} usable matching no simulated star; {by_residual} more matched but blended by the o-e \
         residual alone ({:.1} % of {})",
        field.len(),
        100.0 * flagged,
        matched + by_residual
    );
    assert_eq!(missing, 0, "every component of every target measured");
    // Field stars are paired by the offset vector: none pairs images of two stars.
    assert!(matched > 500, "{matched} field stars matched");
    assert_eq!(false_pairs, 0, "field stars matching no simulated star");
    // The usable field stars' errors: without a focal mask another star's image of the
    // other beam can fall on a star's o or e image (an o-e overlap no sky distance shows);
    // unflagged and unsubtracted it gave pulls of sd 2.0. Those within 3 FWHM of a peak
    // of the stack are `blended` (not usable), those within reach fitted and subtracted;
    // that left sd 1.17 (one u pull of 16.5), from sources too faint for the stack's peaks
    // or on a star's wing. The o-e residual of each star (its o image minus its e image
    // moved onto it) finds those and makes the star `blended`: sd 1.093 (1432 pulls), a
    // widening of the whole distribution (flux for flux), not a tail. At most a quarter of
    // the stars usable before may be `blended` by the residual alone (12.5 % measured).
    let nf = field.len() as f64;
    assert!((0.9..=1.1).contains(&fsd), "field-star pull sd {fsd:.3} over {nf}");
    assert!(fworst < 6.0, "field-star |pull| max {fworst:.2}");
    assert!(
        flagged <= 0.25,
        "{by_residual} of {} blended by the o-e residual alone",
        matched + by_residual
    );
    assert!(
        fmean.abs() < 3.0 * fsd / nf.sqrt(),
        "field-star pull mean {fmean:.3} over {nf}"
    );
    assert_eq!(n, 8 * 6 * 2 * 2);
    assert!((0.9..=1.1).contains(&sd), "pooled pull sd {sd:.3} over {n}");
    assert!(
        mean.abs() < 3.0 / (n as f64).sqrt(),
        "pooled pull mean {mean:.3} over {n}"
    );
}

/// The e image is found by the offset vector, not by its length nor by the nearest star:
/// reduced with the offset turned by 90 degrees (the same length, the wrong direction),
/// the same nights give no honest q, u. Each target either fails (no e image at the
/// offset) or is flagged for an offset far from the profile's, or its pulls are far
/// wider than 1.
#[test]
fn the_offset_direction_matters() {
    let profile = savart_profile();
    let mut turned = profile.clone();
    let [dx, dy] = profile.geometry.eo_offset_px;
    turned.geometry.eo_offset_px = [-dy, dx];
    let (targets, truth) = night(1, &profile, &turned);
    let (p, missing) = pulls(&targets, &truth);
    let flagged = targets
        .iter()
        .filter(|t| {
            t.flags.as_ref().is_some_and(|f| {
                f.iter()
                    .any(|f| f.is(sofipol_pipeline::catalog::FlagCode::EoOffsetDiffersFromProfile))
            })
        })
        .count();
    let sd = if p.len() > 1 { mean_sd(&p).1 } else { f64::NAN };
    eprintln!(
        "turned offset: {} pulls, sd {sd:.2}, {missing} components missing, {flagged} targets flagged",
        p.len()
    );
    assert!(missing > 0 || flagged > 0 || sd > 3.0, "{} pulls, sd {sd}", p.len());
}
