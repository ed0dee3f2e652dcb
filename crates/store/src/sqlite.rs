//! What is only about SQLite's files: the settings every connection gets (WAL, `synchronous =
//! FULL`, `secure_delete`), the pool that opens the file, and the file operations PostgreSQL has
//! its own tools for: the WAL checkpoint, [`Store::backup`] and [`restore`].

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use sqlx::any::AnyPoolOptions;
use sqlx::sqlite::{SqliteConnectOptions, SqliteConnection, SqliteLockingMode};
use sqlx::{AnyPool, Connection, Executor, Row};

use crate::{ACQUIRE_TIMEOUT, Backend, Store, StoreError};

/// SQLite's settings, for every connection: given to SQLite's own options ([`sqlite_options`])
/// and run on each connection of the generic pool ([`sqlite_session`]), which opens the URL and
/// so carries none of them.
const SQLITE_PRAGMAS: [(&str, &str); 5] = [
    ("journal_mode", "WAL"),
    // FULL: every commit (an enrolment, a deletion) is fsynced to the WAL before it is
    // acknowledged, so it survives a power loss too. NORMAL in WAL mode survives application
    // crashes but may lose the last commits on power loss; an acknowledged enrolment must not.
    ("synchronous", "FULL"),
    // Deleted content is overwritten with zeros, so it cannot be read back from free pages.
    ("secure_delete", "ON"),
    ("foreign_keys", "ON"),
    ("busy_timeout", "5000"),
];

fn sqlite_options(url: &str) -> Result<SqliteConnectOptions, StoreError> {
    let options = SqliteConnectOptions::from_str(url).map_err(|source| StoreError::Url { url: crate::redact_url(url), source })?;
    Ok(SQLITE_PRAGMAS.iter().fold(options, |options, &(key, value)| options.pragma(key, value)))
}

/// [`SQLITE_PRAGMAS`] as one batch of statements.
fn sqlite_session() -> String {
    SQLITE_PRAGMAS.iter().map(|(key, value)| format!("PRAGMA {key} = {value};")).collect::<Vec<_>>().join(" ")
}

/// Open a pool on the SQLite database at `url`, creating the file if missing; every connection
/// of the pool runs [`SQLITE_PRAGMAS`]. The migrations are [`Store::connect`]'s.
pub(crate) async fn open(url: &str) -> Result<AnyPool, StoreError> {
    // The file is created (and put in WAL mode) through SQLite's own options; the
    // pool then opens the URL as given, parsed by the same code, so the same file.
    let new = file_of(url)?.filter(|file| !file.exists());
    SqliteConnection::connect_with(&sqlite_options(url)?.create_if_missing(true)).await?.close().await?;
    if let Some(file) = new {
        // Said loudly: a database lost (deleted, or a volume not mounted) is otherwise replaced
        // by an empty one without a word, and every enrolled subject is unknown from then on.
        tracing::warn!(
            path = %file.display(),
            "NO DATABASE at {}: created a new, EMPTY one; if a database was expected there (a deleted file, a volume not \
             mounted), stop the service and restore it (facegate restore)",
            file.display()
        );
    }
    let pool = AnyPoolOptions::new()
        .max_connections(8)
        .acquire_timeout(ACQUIRE_TIMEOUT)
        .after_connect(|connection, _| Box::pin(async move { connection.execute(sqlite_session().as_str()).await.map(drop) }))
        .connect(url)
        .await?;
    Ok(pool)
}

/// The database file of the SQLite `url`, or `None` for an in-memory database.
pub(crate) fn file_of(url: &str) -> Result<Option<PathBuf>, StoreError> {
    let options = sqlite_options(url)?;
    let file = options.get_filename();
    let in_memory = file.as_os_str().is_empty() || file.to_string_lossy().starts_with(":memory:") || url.contains("mode=memory");
    Ok((!in_memory).then(|| file.to_path_buf()))
}

impl Store {
    /// `Err` ([`StoreError::Vanished`]) when the SQLite file opened at start is no longer at its
    /// path (one `stat`); always `Ok` on PostgreSQL.
    pub(crate) fn still_there(&self) -> Result<(), StoreError> {
        self.file_watch.as_ref().map_or(Ok(()), |watch| watch.check())
    }

    /// Copy the WAL into the database and truncate it (waits for readers, up to the busy
    /// timeout). Whether it completed. SQLite only.
    pub async fn checkpoint(&self) -> Result<bool, StoreError> {
        self.sqlite_only("a WAL checkpoint")?;
        let busy: i64 = sqlx::query_scalar("PRAGMA wal_checkpoint(TRUNCATE)").fetch_one(&self.pool).await?;
        Ok(busy == 0)
    }

    fn sqlite_only(&self, what: &str) -> Result<(), StoreError> {
        match self.backend {
            Backend::Sqlite => Ok(()),
            Backend::Postgres => Err(StoreError::Refused(format!(
                "{what} is a SQLite file operation; back up and restore a PostgreSQL database with pg_dump and pg_restore"
            ))),
        }
    }

    /// Write a consistent copy of the database to `path` (which must not exist) while it stays in
    /// use: `VACUUM INTO`, one read transaction, so writers go on meanwhile. The copy holds no free
    /// pages (nothing deleted), and is synced to disk before this returns. SQLite only (refused on
    /// PostgreSQL, which has pg_dump).
    pub async fn backup(&self, path: &Path) -> Result<(), StoreError> {
        self.sqlite_only("facegate backup")?;
        if path.exists() {
            return Err(StoreError::Refused(format!("{} exists; a backup never overwrites a file", path.display())));
        }
        let target = path.to_str().ok_or_else(|| StoreError::Refused(format!("{} is not UTF-8", path.display())))?;
        sqlx::query("VACUUM INTO $1").bind(target).execute(&self.pool).await?;
        let io = |source| StoreError::Io { path: path.to_path_buf(), source };
        std::fs::File::open(path).and_then(|f| f.sync_all()).map_err(io)?;
        Ok(())
    }
}

/// Replace the SQLite database at `url` with the backup file `backup` (made by
/// [`Store::backup`]). The backup is checked first (SQLite's integrity check, a facegate schema).
/// An existing database is overwritten only with `overwrite`, and never while another process
/// has it open. Returns the backup's subject and template counts. Refused for a PostgreSQL URL
/// (pg_restore restores what pg_dump made).
pub async fn restore(backup: &Path, url: &str, overwrite: bool) -> Result<(u64, u64), StoreError> {
    if Backend::of(url)? == Backend::Postgres {
        return Err(StoreError::Refused(
            "facegate restore writes SQLite files; restore a PostgreSQL database from pg_dump's output with pg_restore (or psql)".into(),
        ));
    }
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| StoreError::Io { path, source }
    };
    let mut source = SqliteConnection::connect_with(&SqliteConnectOptions::new().filename(backup).read_only(true)).await?;
    let check: String = sqlx::query_scalar("PRAGMA integrity_check").fetch_one(&mut source).await?;
    if check != "ok" {
        return Err(StoreError::Refused(format!("{} fails SQLite's integrity check: {check}", backup.display())));
    }
    let counts = sqlx::query("SELECT (SELECT count(*) FROM subjects) AS s, (SELECT count(*) FROM templates) AS t")
        .fetch_one(&mut source)
        .await
        .map_err(|e| StoreError::Refused(format!("{} is not a facegate database: {e}", backup.display())))?;
    let counts = (counts.try_get::<i64, _>("s")? as u64, counts.try_get::<i64, _>("t")? as u64);
    source.close().await?;

    let options = sqlite_options(url)?;
    let target = options.get_filename().to_path_buf();
    let sidecar = |suffix: &str| {
        let mut name = target.clone().into_os_string();
        name.push(suffix);
        PathBuf::from(name)
    };
    if target.exists() {
        if !overwrite {
            return Err(StoreError::Refused(format!("{} exists; restore over it only when told to (--force)", target.display())));
        }
        // Exclusive locking fails while any other connection has the database open (after a
        // short wait: a connection being closed lets go within it, a running service does not).
        let exclusive = options.clone().locking_mode(SqliteLockingMode::Exclusive).busy_timeout(Duration::from_secs(5));
        let mut live = SqliteConnection::connect_with(&exclusive)
            .await
            .map_err(|e| StoreError::Refused(format!("{} is in use ({e}); stop the service first", target.display())))?;
        let in_use = sqlx::query("PRAGMA wal_checkpoint(TRUNCATE)").fetch_all(&mut live).await;
        live.close().await?;
        in_use.map_err(|e| StoreError::Refused(format!("{} is in use ({e}); stop the service first", target.display())))?;
    }
    // Copied beside the target, synced, then renamed over it: the target is either the old
    // database or the whole backup. A WAL left by the old database must not be applied to it.
    let staged = sidecar(".restoring");
    std::fs::copy(backup, &staged).map_err(io(&staged))?;
    std::fs::File::open(&staged).and_then(|f| f.sync_all()).map_err(io(&staged))?;
    for stale in [sidecar("-wal"), sidecar("-shm")] {
        match std::fs::remove_file(&stale) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&stale)(e)),
            _ => {}
        }
    }
    std::fs::rename(&staged, &target).map_err(io(&target))?;
    if let Some(dir) = target.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))?;
    }
    Ok(counts)
}
