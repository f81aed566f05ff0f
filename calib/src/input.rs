//! Reading the small text inputs (settings, profiles, tables, scenes, catalogs) the way the
//! night's scanner reads frames: a regular file only (a named pipe would wait for a
//! writer, `/dev/zero` never ends) and at most a given size, checked before and while
//! reading. Errors say what is wrong; the caller names the file.
use std::io::Read;
use std::path::Path;

/// Most bytes of a settings file, instrument profile, standards table, scene, Monte-Carlo
/// table or `calibration.json` (real ones are a few kB).
pub const MAX_OPTION_FILE_BYTES: u64 = 4 << 20;

/// Most bytes of a catalog read by `merge`, `export`, `stats` and `mc` (a night of a
/// thousand targets is about 10 MB).
pub const MAX_CATALOG_BYTES: u64 = 256 << 20;

/// What kind of file system object `meta` is, for messages ("a directory", "a named pipe").
pub fn kind_of(meta: &std::fs::Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        return "a directory";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a named pipe";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_file() {
        "a regular file"
    } else {
        "not a regular file"
    }
}

/// A size in words: "4194304 bytes (4 MiB)".
fn bytes(n: u64) -> String {
    if n >= 1 << 20 {
        format!("{n} bytes ({} MiB)", n >> 20)
    } else {
        format!("{n} bytes")
    }
}

/// `std::fs::read_to_string` for inputs: refuses anything but a regular file (symlinks are
/// followed) and a file of more than `max_bytes` (also when it grows while being read), with
/// an error of kind `InvalidInput` saying why. The caller names the file.
pub fn read_to_string(path: &Path, max_bytes: u64) -> std::io::Result<String> {
    let bad = |msg: String| std::io::Error::new(std::io::ErrorKind::InvalidInput, msg);
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(bad(format!("{}, not a regular file", kind_of(&meta))));
    }
    if meta.len() > max_bytes {
        return Err(bad(format!(
            "{}, more than the {} such an input may hold",
            bytes(meta.len()),
            bytes(max_bytes)
        )));
    }
    let mut text = Vec::new();
    std::fs::File::open(path)?.take(max_bytes + 1).read_to_end(&mut text)?;
    if text.len() as u64 > max_bytes {
        return Err(bad(format!(
            "more than the {} such an input may hold (the file grew while being read)",
            bytes(max_bytes)
        )));
    }
    String::from_utf8(text).map_err(|e| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "not UTF-8 text (invalid byte at offset {})",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regular_files_up_to_the_limit_are_read_and_the_rest_refused_with_the_reason() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("p.toml");
        std::fs::write(&f, "x = 1\n").unwrap();
        assert_eq!(read_to_string(&f, 6).unwrap(), "x = 1\n");
        // One byte over the limit.
        let e = read_to_string(&f, 5).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::InvalidInput);
        assert!(e.to_string().contains("6 bytes, more than the 5 bytes"), "{e}");
        // A directory, a character device that never ends, a named pipe without a writer
        // (which would block forever if opened).
        let e = read_to_string(d.path(), 1 << 20).unwrap_err();
        assert!(e.to_string().contains("a directory, not a regular file"), "{e}");
        #[cfg(unix)]
        {
            let e = read_to_string(Path::new("/dev/zero"), 1 << 20).unwrap_err();
            assert!(e.to_string().contains("a character device"), "{e}");
            let fifo = d.path().join("pipe.toml");
            let ok = std::process::Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .map(|s| s.success());
            if ok.unwrap_or(false) {
                let e = read_to_string(&fifo, 1 << 20).unwrap_err();
                assert!(e.to_string().contains("a named pipe"), "{e}");
            }
        }
        let bin = d.path().join("bin.toml");
        std::fs::write(&bin, [b'a', 0xff, b'b']).unwrap();
        let e = read_to_string(&bin, 100).unwrap_err();
        assert!(
            e.to_string().contains("not UTF-8") && e.to_string().contains("offset 1"),
            "{e}"
        );
        assert_eq!(
            read_to_string(&d.path().join("missing"), 10).unwrap_err().kind(),
            std::io::ErrorKind::NotFound
        );
    }
}
