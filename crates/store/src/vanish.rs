//! A SQLite database file that is no longer where it was opened. The pool keeps the opened file
//! (its inode) whatever happens to the path: a file unlinked (or replaced by another) under the
//! running service would take writes that no restart sees. So the path's device and inode are
//! compared with those opened at start, before each write and on the readiness probe's read, at
//! most once per [`CHECK_EVERY`] (one `stat`), and a file gone or replaced makes the store
//! unavailable ([`StoreError::Vanished`], 503 `store-unavailable`) until it is back. A file
//! emptied in place (truncated to nothing, the same inode) counts as gone too.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use crate::StoreError;

/// Longest a vanished file goes unnoticed (between two checks).
pub const CHECK_EVERY: Duration = Duration::from_millis(500);

/// The opened file's identity and the last check's outcome.
#[derive(Debug)]
pub(crate) struct FileWatch {
    path: PathBuf,
    identity: (u64, u64),
    /// The file kept open: while it is, its inode is not reused, so a file later made at the path
    /// can never have the opened one's identity.
    _held: std::fs::File,
    last: Mutex<Option<(Instant, Option<String>)>>,
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
        Ok(FileWatch { path: path.to_path_buf(), identity, _held: held, last: Mutex::new(None) })
    }

    /// `Err` when the path no longer holds the file opened at start (checked at most once per
    /// [`CHECK_EVERY`]; meanwhile the last check's outcome stands).
    pub(crate) fn check(&self) -> Result<(), StoreError> {
        let now = Instant::now();
        let mut last = self.last.lock().expect("file watch lock");
        let fresh = last.as_ref().filter(|(at, _)| now.duration_since(*at) < CHECK_EVERY).map(|(_, gone)| gone.clone());
        let gone = match fresh {
            Some(gone) => gone,
            None => {
                let gone = match identity(&self.path) {
                    // Opened, the file holds at least the schema: emptied (truncated to nothing),
                    // SQLite would take it for a new database with no tables.
                    Ok((found, true)) if found == self.identity => Some(format!("{} was emptied", self.path.display())),
                    Ok((found, false)) if found == self.identity => None,
                    Ok(_) => Some(format!("{} was replaced by another file", self.path.display())),
                    Err(e) => Some(format!("{} is gone ({e})", self.path.display())),
                };
                if let Some(why) = gone.as_ref().filter(|_| last.as_ref().is_none_or(|(_, before)| before.is_none())) {
                    tracing::error!(
                        "the SQLite database file opened at start is no longer at its path: {why}; every write and /health are \
                         refused (503) until it is back or the service restarts on the right file"
                    );
                }
                *last = Some((now, gone.clone()));
                gone
            }
        };
        gone.map_or(Ok(()), |why| Err(StoreError::Vanished(why)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unlinked_or_replaced_file_is_noticed_within_the_check_interval() {
        let dir = std::env::temp_dir().join(format!("facegate-vanish-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("db");
        std::fs::write(&path, "one").unwrap();
        let watch = FileWatch::new(&path).unwrap();
        assert!(watch.check().is_ok());
        std::fs::remove_file(&path).unwrap();
        // The last outcome stands until the interval has passed.
        assert!(watch.check().is_ok());
        std::thread::sleep(CHECK_EVERY);
        let error = watch.check().unwrap_err();
        assert!(error.is_unavailable() && error.to_string().contains("is gone"), "{error}");
        // Another file at the path is not the database opened.
        std::fs::write(dir.join("other"), "two").unwrap();
        std::fs::rename(dir.join("other"), &path).unwrap();
        std::thread::sleep(CHECK_EVERY);
        assert!(watch.check().unwrap_err().to_string().contains("replaced"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
