//! A SQLite database file that is no longer where it was opened. The pool keeps the opened file
//! (its inode) whatever happens to the path: a file unlinked (or replaced by another) under the
//! running service would take writes that no restart sees. So the path's device and inode are
//! compared with those opened at start, before each write and on the readiness probe's read (one
//! `stat`, a microsecond beside a transaction), and a file gone or replaced makes the store
//! unavailable ([`StoreError::Vanished`], 503 `store-unavailable`) until it is back. A file
//! emptied in place (truncated to nothing, the same inode) counts as gone too. Each check looks
//! afresh: when checks reused an earlier outcome for up to 500 ms, an enrolment was once
//! acknowledged into the unlinked file after `/health` had already answered 503 (in CI).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use crate::StoreError;

/// The opened file's identity and whether the last check found it gone (to log the change once).
#[derive(Debug)]
pub(crate) struct FileWatch {
    path: PathBuf,
    identity: (u64, u64),
    /// The file kept open: while it is, its inode is not reused, so a file later made at the path
    /// can never have the opened one's identity.
    _held: std::fs::File,
    gone_before: AtomicBool,
}

/// The device and inode of the file at `path`, and whether it is empty.
fn identity(path: &Path) -> std::io::Result<((u64, u64), bool)> {
    use std::os::unix::fs::MetadataExt;
    let metadata = std::fs::metadata(path)?;
    Ok(((metadata.dev(), metadata.ino()), metadata.len() == 0))
}

impl FileWatch {
    /// Watch the database file at `path`, as it is now (just opened).
    pub(crate) fn new(path: &Path) -> Result<FileWatch, StoreError> {
        let io = |source| StoreError::Io { path: path.to_path_buf(), source };
        let held = std::fs::File::open(path).map_err(io)?;
        let (identity, _) = identity(path).map_err(io)?;
        Ok(FileWatch { path: path.to_path_buf(), identity, _held: held, gone_before: AtomicBool::new(false) })
    }

    /// `Err` when the path no longer holds the file opened at start.
    pub(crate) fn check(&self) -> Result<(), StoreError> {
        let gone = match identity(&self.path) {
            // Opened, the file holds at least the schema: emptied (truncated to nothing), SQLite
            // would take it for a new database with no tables.
            Ok((found, true)) if found == self.identity => Some(format!("{} was emptied", self.path.display())),
            Ok((found, false)) if found == self.identity => None,
            Ok(_) => Some(format!("{} was replaced by another file", self.path.display())),
            Err(e) => Some(format!("{} is gone ({e})", self.path.display())),
        };
        let gone_before = self.gone_before.swap(gone.is_some(), Ordering::Relaxed);
        if let Some(why) = gone.as_ref().filter(|_| !gone_before) {
            tracing::error!(
                "the SQLite database file opened at start is no longer at its path: {why}; every write and /health are refused \
                 (503) until it is back or the service restarts on the right file"
            );
        }
        gone.map_or(Ok(()), |why| Err(StoreError::Vanished(why)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unlinked_or_replaced_file_is_noticed_at_the_next_check() {
        let dir = std::env::temp_dir().join(format!("facegate-vanish-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("db");
        std::fs::write(&path, "one").unwrap();
        let watch = FileWatch::new(&path).unwrap();
        assert!(watch.check().is_ok());
        std::fs::remove_file(&path).unwrap();
        let error = watch.check().unwrap_err();
        assert!(error.is_unavailable() && error.to_string().contains("is gone"), "{error}");
        // Another file at the path is not the database opened.
        std::fs::write(dir.join("other"), "two").unwrap();
        std::fs::rename(dir.join("other"), &path).unwrap();
        assert!(watch.check().unwrap_err().to_string().contains("replaced"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
