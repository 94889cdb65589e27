//! Whole files or none: every output is written under a temporary name beside its final
//! one, synced, then renamed into place, so that a crash, a kill or a full disk leaves no
//! half-written file under the final name (and an earlier file of that name intact).

use crate::IoError;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A temporary name beside `path`, unique to this process and call, keeping its extension
/// (image encoders choose the format by it): `dir/.NAME.PID-N.tmp.EXT`.
pub fn temp_beside(path: &Path) -> PathBuf {
    static SERIAL: AtomicU64 = AtomicU64::new(0);
    let n = SERIAL.fetch_add(1, Ordering::Relaxed);
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "output".into());
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{}-{n}.tmp{ext}", std::process::id()))
}

/// Moves the finished file `tmp` to `path` after syncing it to disk. With `replace` false
/// an existing `path` is left alone and the move fails (`AlreadyExists`), also when it
/// appeared after the caller looked. `tmp` stays where it is when the move fails.
pub fn commit(tmp: &Path, path: &Path, replace: bool) -> std::io::Result<()> {
    std::fs::File::open(tmp)?.sync_all()?;
    if replace {
        return std::fs::rename(tmp, path);
    }
    // A hard link refuses an existing name atomically; where the file system has no links,
    // an existence check and a rename come close.
    match std::fs::hard_link(tmp, path) {
        Ok(()) => std::fs::remove_file(tmp),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(e),
        Err(_) if path.exists() => Err(std::io::ErrorKind::AlreadyExists.into()),
        Err(_) => std::fs::rename(tmp, path),
    }
}

/// Writes `path` whole or not at all: `write` gets a temporary path beside it to write,
/// which then replaces `path`. When `write` fails the temporary file is removed and `path`
/// is as it was.
pub fn write_atomically<T>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<T, IoError>,
) -> Result<T, IoError> {
    let tmp = temp_beside(path);
    let out = match write(&tmp) {
        Ok(v) => v,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    commit(&tmp, path, true).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        IoError::Write {
            path: path.into(),
            reason: e.to_string(),
        }
    })?;
    Ok(out)
}

/// [`write_atomically`] for bytes already in memory.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    write_atomically(path, |tmp| {
        std::fs::write(tmp, bytes).map_err(|e| IoError::Write {
            path: path.into(),
            reason: e.to_string(),
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_failed_write_leaves_the_old_file_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.json");
        std::fs::write(&p, "old").unwrap();
        let r: Result<(), IoError> = write_atomically(&p, |tmp| {
            std::fs::write(tmp, "half").unwrap();
            Err(IoError::Write {
                path: p.clone(),
                reason: "disk full".into(),
            })
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "old");
        assert_eq!(names(dir.path()), ["out.json"]);
        write_bytes(&p, b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new");
        assert_eq!(names(dir.path()), ["out.json"]);
    }

    #[test]
    fn the_temporary_name_keeps_the_extension_and_is_unique() {
        let p = Path::new("/x/y/overlay.png");
        let (a, b) = (temp_beside(p), temp_beside(p));
        assert_ne!(a, b);
        assert_eq!(a.parent(), p.parent());
        assert_eq!(a.extension().unwrap(), "png");
        assert!(
            a.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with(".overlay.png.")
        );
    }

    #[test]
    fn commit_without_replace_keeps_an_existing_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rec.mcap");
        std::fs::write(&p, "earlier").unwrap();
        let tmp = temp_beside(&p);
        std::fs::write(&tmp, "later").unwrap();
        let e = commit(&tmp, &p, false).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "earlier");
        // The refused file is still there for the caller to keep or remove.
        assert_eq!(std::fs::read_to_string(&tmp).unwrap(), "later");
        commit(&tmp, &p, true).unwrap();
        assert_eq!(names(dir.path()), ["rec.mcap"]);
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "later");
    }
}
