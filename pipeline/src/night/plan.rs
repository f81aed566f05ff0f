//! What a night holds: scan the directories, classify every file by its header, group the
//! science frames into sequences, set the standards apart, choose the frames for the
//! night-wide bad-pixel mask and superflat (before sharding, so every shard builds the
//! same ones) and keep the sequences of one shard.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use sofipol_calib::Profile;

use crate::catalog::Failure;
use crate::scan;
use crate::sequence::{self, Sequence};
/// A deterministic partition of the work: shard `k` (1-based) of `n`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// 1-based index.
    pub k: usize,
    /// Number of shards.
    pub n: usize,
}

impl std::str::FromStr for Shard {
    type Err = crate::error::Error;
    fn from_str(s: &str) -> crate::error::Result<Self> {
        let bad = |reason: &str| crate::error::Error::Merge {
            file: format!("shard '{s}'"),
            reason: reason.to_string(),
        };
        let (a, b) = s.split_once('/').ok_or_else(|| bad("expected K/N, e.g. 2/8"))?;
        let k: usize = a.trim().parse().map_err(|_| bad("K is not a number"))?;
        let n: usize = b.trim().parse().map_err(|_| bad("N is not a number"))?;
        if n == 0 || k == 0 || k > n {
            return Err(bad("need 1 <= K <= N"));
        }
        Ok(Shard { k, n })
    }
}

/// FNV-1a 64-bit hash: stable across runs, platforms and Rust versions (unlike std's).
pub fn stable_hash(s: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in s.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl Shard {
    /// Whether an item with this key belongs to the shard.
    pub fn owns(&self, key: &str) -> bool {
        (stable_hash(key) % self.n as u64) as usize == self.k - 1
    }
}

/// What a night holds.
#[derive(Debug, Default)]
pub struct NightPlan {
    /// Science sequences to reduce (this shard's), in a stable order.
    pub sequences: Vec<Sequence>,
    /// Standard-star sequences (`DPR TYPE` 'STD'), all of them whatever the shard: every
    /// shard calibrates with all of them.
    pub standards: Vec<Sequence>,
    /// Inputs that cannot be used (unreadable, duplicates), with the reason.
    pub failures: Vec<Failure>,
    /// Readable FITS files that are not SOFI polarimetric frames (foreign, other modes),
    /// with the reason.
    pub not_science: Vec<Failure>,
    /// Files found.
    pub n_files: usize,
    /// Every input file found (each once), whether used or not: outputs must not
    /// overwrite any of them.
    pub files: Vec<PathBuf>,
    /// Frames for the night's bad-pixel detection, chosen from every sequence of the
    /// night before sharding, so that every shard finds the same mask.
    pub mask_frames: Vec<PathBuf>,
    /// Dome-flat frames of the whole night (before sharding: every shard builds the same
    /// flats).
    pub dome_flats: Vec<PathBuf>,
    /// Frames for the superflat, by filter, from every sequence of the night (before
    /// sharding), cycling through the dither positions like `mask_frames`.
    pub superflat_frames: BTreeMap<String, Vec<PathBuf>>,
    /// Sequences set aside by the caller's `keep` ([`plan_listing`]; live reduction holds
    /// back templates still being observed): not reduced, not in the mask or superflat
    /// picks. Empty for [`plan`].
    pub held: Vec<Sequence>,
    /// The scan ran out of file handles (the first such error): the plan is incomplete and
    /// must not be reduced ([`crate::scan::Scan::out_of_file_handles`]).
    pub out_of_file_handles: Option<String>,
}

/// Frames for a superflat, by filter: sequence `i` contributes its exposure
/// `(i + round) mod n` (all orientations in turn), round after round, at most `max` per
/// filter, so the stars of the night fall on different pixels in different frames.
pub fn pick_superflat_frames(sequences: &[Sequence], max: usize) -> BTreeMap<String, Vec<PathBuf>> {
    let mut out: BTreeMap<String, Vec<PathBuf>> = Default::default();
    let longest = sequences
        .iter()
        .map(|q| q.orientations.iter().map(|o| o.exposures.len()).sum::<usize>())
        .max()
        .unwrap_or(0);
    for round in 0..longest {
        for (i, q) in sequences.iter().enumerate() {
            let all: Vec<&PathBuf> = q
                .orientations
                .iter()
                .flat_map(|o| o.exposures.iter().map(|e| &e.path))
                .collect();
            let picks = out.entry(q.filter.clone()).or_default();
            if round >= all.len() || picks.len() >= max {
                continue;
            }
            let p = all[(i + round) % all.len()];
            if !picks.contains(p) {
                picks.push(p.clone());
            }
        }
    }
    out
}

/// Frames for the bad-pixel median stack. Every target of a night sits at the same
/// detector position for a given dither, so taking the same dither of every sequence would
/// stack the stars onto each other and mask them as defects: sequence `i` contributes its
/// dither `(i + round) mod n` (first orientation), so the picks cycle through all dither
/// positions and no position holds more than about 1/n of the frames. At most `max`.
fn pick_mask_frames(sequences: &[Sequence], max: usize) -> Vec<PathBuf> {
    let mut picks: Vec<PathBuf> = Vec::new();
    // A sequence whose dithers do not move keeps its star on the same pixels: it would
    // be taken for a defect. Such sequences give no frame to the mask.
    let moving: Vec<&Sequence> = sequences
        .iter()
        .filter(|q| q.stationary_orientations().is_empty())
        .collect();
    for round in 0..8 {
        for (i, q) in moving.iter().enumerate() {
            let Some(o) = q.orientations.first() else { continue };
            let n = o.exposures.len();
            if round >= n || picks.len() >= max {
                continue;
            }
            let e = &o.exposures[(i + round) % n];
            if !picks.contains(&e.path) {
                picks.push(e.path.clone());
            }
        }
    }
    picks
}

/// Scan `roots`, classify, keep each exposure once, group, and set the standards apart
/// (`is_standard`, e.g. [`crate::calibration::is_standard_sequence`]). The frames of the
/// night-wide mask (at most 15) and superflat (at most `max_superflat_frames` per filter)
/// are chosen from every sequence, standards included, before `shard` keeps its science
/// sequences and failures. Unreadable directories, unreadable files and duplicates (the
/// same file by two paths, a copy of the same exposure) are `failures`, foreign files
/// `not_science`, by path.
pub fn plan(
    roots: &[PathBuf],
    profile: &Profile,
    max_superflat_frames: usize,
    shard: Option<Shard>,
    is_standard: impl Fn(&Sequence) -> bool,
) -> NightPlan {
    plan_listing(
        scan::list(roots),
        profile,
        max_superflat_frames,
        shard,
        is_standard,
        |_| true,
        &sofipol_calib::fits::read_header,
    )
}

/// [`plan`] of files already listed, keeping only the sequences `keep` accepts (the others
/// are `held`, and give no frame to the mask or the superflat): with every file listed
/// and every sequence kept, exactly [`plan`]. Headers are read with `read_header`.
pub fn plan_listing(
    listing: scan::Listing,
    profile: &Profile,
    max_superflat_frames: usize,
    shard: Option<Shard>,
    is_standard: impl Fn(&Sequence) -> bool,
    keep: impl Fn(&Sequence) -> bool,
    read_header: &scan::ReadHeader<'_>,
) -> NightPlan {
    let (s, files) = scan::scan_listing_with(listing, profile, read_header);
    plan_scanned(s, files, profile, max_superflat_frames, shard, is_standard, keep)
}

/// The plan of the frames a set-of-frames file lists ([`crate::frame_list`]): only those
/// files, with their roles as given. A frame listed as `science` or `standard` must still
/// be a polarimetric frame by its header (else it is not used, with the header's reason
/// and the line); its `angle=` and `target=` replace the header's POSANG and OBJECT; a
/// sequence with a frame listed as `standard` is a standard, one with a frame listed as
/// `science` is not, whatever the header says (others: `is_standard`). `flat` frames go to
/// the dome-flat builder when the header has the lamp keyword; `dark` and `sky` frames are
/// listed as not used.
pub fn plan_frame_list(
    list: &crate::frame_list::FrameList,
    profile: &Profile,
    max_superflat_frames: usize,
    shard: Option<Shard>,
    is_standard: impl Fn(&Sequence) -> bool,
) -> NightPlan {
    use crate::frame_list::FrameRole;
    use std::collections::HashMap;
    let listing = scan::Listing {
        files: list.frames.iter().map(|f| f.path.clone()).collect(),
        ..Default::default()
    };
    let (mut s, files) = scan::scan_listing_with(listing, profile, &sofipol_calib::fits::read_header);
    let by_path: HashMap<&Path, &crate::frame_list::ListedFrame> =
        list.frames.iter().map(|f| (f.path.as_path(), f)).collect();
    let at = |f: &crate::frame_list::ListedFrame| format!("{}:{}", list.file.display(), f.line);
    // Science frames: overrides, or out when listed as something else.
    let mut science = Vec::new();
    for mut info in std::mem::take(&mut s.science) {
        let Some(lf) = by_path.get(info.path.as_path()) else {
            science.push(info);
            continue;
        };
        match lf.role {
            FrameRole::Science | FrameRole::Standard => {
                if let Some(a) = lf.angle_deg {
                    info.posang_deg = a;
                }
                if let Some(t) = &lf.target {
                    info.object = t.clone();
                    info.sequence = format!("{}@{}", info.object, info.tpl_start);
                }
                science.push(info);
            }
            FrameRole::Flat => match sofipol_calib::fits::read_header(&info.path)
                .map_err(|e| e.to_string())
                .and_then(|h| sofipol_calib::flat::dome_flat_info(&h, profile).map_err(|e| e.to_string()))
            {
                Ok(Some(_)) => s.dome_flats.push(info.path),
                Ok(None) => s.other.push(Failure {
                    file: info.path.display().to_string(),
                    error: format!(
                        "listed as flat ({}) but the header has no lamp keyword of a dome flat",
                        at(lf)
                    ),
                }),
                Err(e) => s.other.push(Failure {
                    file: info.path.display().to_string(),
                    error: format!("listed as flat ({}): {e}", at(lf)),
                }),
            },
            FrameRole::Dark | FrameRole::Sky => s.other.push(Failure {
                file: info.path.display().to_string(),
                error: format!("listed as {} ({}): not used by this reduction", lf.role.name(), at(lf)),
            }),
        }
    }
    s.science = science;
    // Dome flats listed as something else.
    let mut flats = Vec::new();
    for p in std::mem::take(&mut s.dome_flats) {
        match by_path.get(p.as_path()).map(|lf| (lf.role, at(lf))) {
            Some((FrameRole::Flat, _)) | None => flats.push(p),
            Some((role, line)) => s.other.push(Failure {
                file: p.display().to_string(),
                error: format!(
                    "listed as {} ({line}) but its header is a dome flat's: not used",
                    role.name()
                ),
            }),
        }
    }
    s.dome_flats = flats;
    // Frames the header does not take as science: say what they were listed as.
    for f in &mut s.other {
        if let Some(lf) = by_path.get(Path::new(&f.file)) {
            if matches!(lf.role, FrameRole::Science | FrameRole::Standard | FrameRole::Flat)
                && !f.error.starts_with("listed as")
            {
                f.error = format!("listed as {} ({}), but {}", lf.role.name(), at(lf), f.error);
            } else if matches!(lf.role, FrameRole::Dark | FrameRole::Sky) && !f.error.starts_with("listed as") {
                f.error = format!("listed as {} ({}): not used by this reduction", lf.role.name(), at(lf));
            }
        }
    }
    let roles: HashMap<PathBuf, FrameRole> = list.frames.iter().map(|f| (f.path.clone(), f.role)).collect();
    let standard = |q: &Sequence| {
        let listed: Vec<FrameRole> = q
            .orientations
            .iter()
            .flat_map(|o| &o.exposures)
            .filter_map(|e| roles.get(&e.path).copied())
            .collect();
        if listed.contains(&FrameRole::Standard) {
            true
        } else if listed.contains(&FrameRole::Science) {
            false
        } else {
            is_standard(q)
        }
    };
    plan_scanned(s, files, profile, max_superflat_frames, shard, standard, |_| true)
}

/// The plan from a finished scan ([`plan_listing`] after its scan).
fn plan_scanned(
    s: scan::Scan,
    files: Vec<PathBuf>,
    profile: &Profile,
    max_superflat_frames: usize,
    shard: Option<Shard>,
    is_standard: impl Fn(&Sequence) -> bool,
    keep: impl Fn(&Sequence) -> bool,
) -> NightPlan {
    let n_files = files.len();
    let mut failures: Vec<Failure> = s.unreadable;
    failures.extend(s.duplicates);
    let mut not_science = s.other;
    let (all, held): (Vec<Sequence>, Vec<Sequence>) =
        sequence::group(s.science, profile).into_iter().partition(|q| keep(q));
    let mask_frames = pick_mask_frames(&all, 15);
    let superflat_frames = pick_superflat_frames(&all, max_superflat_frames);
    let (mut sequences, standards): (Vec<Sequence>, Vec<Sequence>) = all.into_iter().partition(|q| !is_standard(q));
    if let Some(sh) = shard {
        sequences.retain(|q| sh.owns(&q.id));
        failures.retain(|f| sh.owns(&f.file));
        not_science.retain(|f| sh.owns(&f.file));
    }
    failures.sort_by(|a, b| a.file.cmp(&b.file));
    not_science.sort_by(|a, b| a.file.cmp(&b.file));
    NightPlan {
        sequences,
        standards,
        failures,
        not_science,
        n_files,
        files,
        mask_frames,
        dome_flats: s.dome_flats,
        superflat_frames,
        held,
        out_of_file_handles: s.out_of_file_handles,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_frames_cycle_through_dither_positions() {
        // Regression: every target sits at the same detector position for a given dither;
        // taking dither 1 of every sequence stacked the stars and masked them as defects.
        let profile = Profile::sofi();
        let mut infos = Vec::new();
        for t in 0..6 {
            for k in 1..=5u32 {
                infos.push(sofipol_calib::classify::ScienceInfo {
                    path: format!("T{t}_{k}.fits").into(),
                    object: format!("T{t}"),
                    tpl_start: format!("1999-03-03T0{t}:00:00"),
                    sequence: String::new(),
                    posang_deg: 0.0,
                    offset_px: [k as f64 * 86.8, 0.0],
                    filter: "Ks".into(),
                    wollaston: "WOLLASTON".into(),
                    dit_s: 10.0,
                    ndit: 6,
                    expno: Some(k),
                    nexp: Some(5),
                    mjd: None,
                    ra_deg: None,
                    dec_deg: None,
                    pixscale_arcsec: 0.288,
                });
            }
        }
        let seqs = sequence::group(infos, &profile);
        let picks = pick_mask_frames(&seqs, 15);
        assert_eq!(picks.len(), 15);
        let mut per_dither = [0usize; 6];
        for p in &picks {
            let k: usize = p
                .to_str()
                .unwrap()
                .trim_end_matches(".fits")
                .rsplit('_')
                .next()
                .unwrap()
                .parse()
                .unwrap();
            per_dither[k] += 1;
        }
        assert!(per_dither.iter().all(|&c| c <= 4), "{per_dither:?}");
    }

    #[test]
    fn shards_partition_deterministically() {
        let ids: Vec<String> = (0..200).map(|i| format!("T{i}@1999-03-03T0{}:00:00", i % 10)).collect();
        let n = 4;
        let mut counts = vec![0; n];
        for id in &ids {
            let owners: Vec<usize> = (1..=n).filter(|&k| Shard { k, n }.owns(id)).collect();
            assert_eq!(owners.len(), 1);
            counts[owners[0] - 1] += 1;
        }
        assert!(counts.iter().all(|&c| c > 25), "{counts:?}");
        // FNV-1a 64 reference values (offset basis for ""; "a" and "foobar" from the
        // published FNV test vectors, http://www.isthe.com/chongo/src/fnv/test_fnv.c).
        assert_eq!(stable_hash(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(stable_hash("a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(stable_hash("foobar"), 0x8594_4171_f739_67e8);
        assert!("0/4".parse::<Shard>().is_err() && "5/4".parse::<Shard>().is_err() && "2/4".parse::<Shard>().is_ok());
    }
}
