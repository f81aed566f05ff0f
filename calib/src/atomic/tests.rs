use super::*;

#[test]
fn atomic_write_replaces_and_leaves_no_temporaries() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("sub").join("cat.json");
    assert!(write_atomic(&p, b"first").is_err(), "the directory must exist");
    write_json_atomic(&p, &1).unwrap();
    write_atomic(&p, b"second").unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), b"second");
    let names: Vec<_> = std::fs::read_dir(p.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 1, "{names:?}");
}

#[test]
fn dropped_temporary_leaves_destination_untouched() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("cat.json");
    write_atomic(&p, b"old").unwrap();
    let tmp = TempFile::new(&p).unwrap();
    std::fs::write(&tmp.path, b"partial").unwrap();
    drop(tmp);
    assert_eq!(std::fs::read(&p).unwrap(), b"old");
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
}

/// The names the temporaries used to have, `.NAME.tmp-PID-N`, planted in advance (as
/// another user of a shared directory could) as directories and as symbolic links to a
/// file of the victim: every write still succeeds, and neither the victim nor the planted
/// entries are touched (with predictable names the planted directories made every write
/// fail, and a link re-planted between the old code's removal and creation was followed).
#[cfg(unix)]
#[test]
fn planted_entries_at_predictable_names_are_neither_followed_nor_in_the_way() {
    let d = tempfile::tempdir().unwrap();
    let victim = d.path().join("victim.txt");
    std::fs::write(&victim, b"precious").unwrap();
    let pid = std::process::id();
    for name in ["cat.json", "frame.fits"] {
        for n in 0..2000 {
            let planted = d.path().join(format!(".{name}.tmp-{pid}-{n}"));
            if n % 2 == 0 {
                std::fs::create_dir(&planted).unwrap();
            } else {
                std::os::unix::fs::symlink(&victim, &planted).unwrap();
            }
        }
    }
    let cat = d.path().join("cat.json");
    for i in 0..20 {
        write_atomic(&cat, format!("catalog {i}").as_bytes()).unwrap();
    }
    assert_eq!(std::fs::read(&cat).unwrap(), b"catalog 19");
    let frame = d.path().join("frame.fits");
    for _ in 0..3 {
        let f = crate::Frame::new(ndarray::Array2::from_elem((4, 6), 7.0), crate::Header::new(""));
        crate::fits::write_frame(&frame, &f, &Default::default()).unwrap();
    }
    assert_eq!(crate::fits::read_frame(&frame).unwrap().data[[1, 1]], 7.0);
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    // 4000 planted entries, the victim, the two outputs: no temporary left behind.
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 4003);
}

/// The private directory of a [`TempFile`] is the writer's alone (mode 0700) and fresh
/// each time; the file's own permissions follow the umask like any file's.
#[cfg(unix)]
#[test]
fn temporaries_are_private_and_outputs_follow_the_umask() {
    use std::os::unix::fs::PermissionsExt;
    let d = tempfile::tempdir().unwrap();
    let dest = d.path().join("frame.fits");
    let (a, b) = (TempFile::new(&dest).unwrap(), TempFile::new(&dest).unwrap());
    let dir_a = a.path.parent().unwrap();
    assert_ne!(dir_a, b.path.parent().unwrap());
    assert_eq!(std::fs::metadata(dir_a).unwrap().permissions().mode() & 0o777, 0o700);
    let reference = d.path().join("reference");
    std::fs::File::create(&reference).unwrap();
    let out = d.path().join("out.json");
    write_atomic(&out, b"x").unwrap();
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&out), mode(&reference));
}

/// A symbolic link, a named pipe or a directory at the destination is refused, named and
/// left as it was (the rename would have replaced it with a regular file); a dangling
/// link too. A regular file is replaced.
#[cfg(unix)]
#[test]
fn a_destination_that_is_not_a_regular_file_is_refused_and_left_alone() {
    let d = tempfile::tempdir().unwrap();
    let target = d.path().join("target.txt");
    std::fs::write(&target, b"target").unwrap();
    let link = d.path().join("link.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let dangling = d.path().join("dangling.json");
    std::os::unix::fs::symlink(d.path().join("nowhere"), &dangling).unwrap();
    let fifo = d.path().join("pipe.json");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    let sub = d.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    let mut cases = vec![
        (link.clone(), "a symbolic link (to "),
        (dangling.clone(), "a symbolic link"),
        (sub, "a directory"),
    ];
    if made.is_ok_and(|s| s.success()) {
        cases.push((fifo.clone(), "a named pipe"));
    }
    for (dest, what) in cases {
        let e = write_atomic(&dest, b"new").unwrap_err().to_string();
        assert!(e.contains(&dest.display().to_string()) && e.contains(what), "{e}");
        let f = crate::Frame::new(ndarray::Array2::from_elem((2, 2), 1.0), crate::Header::new(""));
        let e = crate::fits::write_frame(&dest, &f, &Default::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains(what), "{e}");
    }
    assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
    assert!(std::fs::symlink_metadata(&dangling).unwrap().file_type().is_symlink());
    assert!(!d.path().join("nowhere").exists());
    assert_eq!(std::fs::read(&target).unwrap(), b"target");
    let plain = d.path().join("plain.json");
    std::fs::write(&plain, b"old").unwrap();
    write_atomic(&plain, b"new").unwrap();
    assert_eq!(std::fs::read(&plain).unwrap(), b"new");
}

#[test]
fn deferred_writes_land_whole_and_sync_together_naming_what_failed() {
    let d = tempfile::tempdir().unwrap();
    let sub = d.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    // More files than sync threads, in two directories, one of them replacing a file.
    let mut files: Vec<PathBuf> = (0..40)
        .map(|i| {
            if i % 3 == 0 {
                sub.join(format!("f{i}.png"))
            } else {
                d.path().join(format!("f{i}.png"))
            }
        })
        .collect();
    std::fs::write(&files[1], b"old").unwrap();
    for (i, p) in files.iter().enumerate() {
        write_atomic_deferred(p, &vec![i as u8; 1000 + i]).unwrap();
    }
    for (i, p) in files.iter().enumerate() {
        assert_eq!(std::fs::read(p).unwrap(), vec![i as u8; 1000 + i], "{}", p.display());
    }
    assert!(sync_files(&files).is_empty());
    // Only the destinations are left: no temporary beside them.
    let n = |dir: &Path| std::fs::read_dir(dir).unwrap().count();
    assert_eq!(n(d.path()), 26 + 1, "26 files and `sub`");
    assert_eq!(n(&sub), 14);
    // A file gone before the sync is named, the others are still synced.
    let gone = d.path().join("gone.png");
    files.push(gone.clone());
    let errors = sync_files(&files);
    assert_eq!(errors.len(), 1);
    assert!(errors[0].to_string().contains("gone.png"), "{}", errors[0]);
    assert!(sync_files(&[]).is_empty());
}
