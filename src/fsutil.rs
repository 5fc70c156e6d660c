//! Atomic file writes and the never-overwrite rule.
//!
//! Every file lensrig writes goes through [`write_atomic`]: the bytes land in a temporary file
//! in the destination's directory, are flushed to disk, and only then renamed over the final
//! name. A crash, a full disk or a kill leaves either the old file or the new one, never half a
//! file. Captures are written with [`Overwrite::Never`] so a user's data cannot be replaced.

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// What to do when the destination already exists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Overwrite {
    /// Replace it (derived outputs: reports, predictions, profiles the user asked for).
    Replace,
    /// Refuse with [`io::ErrorKind::AlreadyExists`] (captures, sessions).
    Never,
}

/// Writes `bytes` to `path` atomically (temporary file + fsync + rename).
///
/// # Errors
/// Any I/O error (including a full disk), or `AlreadyExists` under [`Overwrite::Never`]. On
/// error the temporary file is removed and `path` is untouched.
pub fn write_atomic(path: &Path, bytes: &[u8], overwrite: Overwrite) -> io::Result<()> {
    write_atomic_with(path, overwrite, |f| f.write_all(bytes))
}

/// Like [`write_atomic`], with a writer callback for encoders that stream.
///
/// # Errors
/// As [`write_atomic`], plus whatever `fill` returns.
pub fn write_atomic_with(
    path: &Path,
    overwrite: Overwrite,
    fill: impl FnOnce(&mut File) -> io::Result<()>,
) -> io::Result<()> {
    if overwrite == Overwrite::Never && path.exists() {
        return Err(io::Error::new(io::ErrorKind::AlreadyExists, format!("{} already exists and is never overwritten", path.display())));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "path has no file name"))?;
    let tmp = dir.join(format!(".{}.tmp-{}", name.to_string_lossy(), std::process::id()));
    let result = (|| {
        let mut f = File::create(&tmp)?;
        fill(&mut f)?;
        f.flush()?;
        f.sync_all()?;
        drop(f);
        if overwrite == Overwrite::Never {
            // hard_link fails if the destination appeared meanwhile: no race with another writer.
            fs::hard_link(&tmp, path)?;
            fs::remove_file(&tmp)?;
        } else {
            fs::rename(&tmp, path)?;
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_refuses_existing_and_keeps_content() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.bin");
        write_atomic(&p, b"first", Overwrite::Never).unwrap();
        let e = write_atomic(&p, b"second", Overwrite::Never).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        assert_eq!(fs::read(&p).unwrap(), b"first");
        write_atomic(&p, b"third", Overwrite::Replace).unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"third");
        // no temporary files left behind
        assert_eq!(fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn failing_writer_leaves_nothing() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("b.bin");
        let e = write_atomic_with(&p, Overwrite::Replace, |f| {
            f.write_all(b"partial")?;
            Err(io::Error::other("disk full"))
        });
        assert!(e.is_err());
        assert!(!p.exists());
        assert_eq!(fs::read_dir(d.path()).unwrap().count(), 0);
    }
}
