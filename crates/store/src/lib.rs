//! Subjects and their face templates in SQLite (the embedded default) or PostgreSQL, through
//! sqlx.
//!
//! One implementation serves both backends: the queries are written once in the SQL both accept
//! (`$n` parameters, `ON CONFLICT`, text timestamps) and run on an [`sqlx::AnyPool`]; only what
//! has no common form is per backend: the connection settings, the migrations (`migrations/sqlite/`,
//! `migrations/postgres/`), the change counter and its notifications (PostgreSQL), and
//! the WAL checkpoint, backup and restore (SQLite files).
//!
//! Deleting a subject erases its templates (foreign keys cascade). An enrolment is one
//! transaction: either all of its templates are stored or none. No photo is ever stored, only
//! templates: each is a little-endian f32 vector with the recognition model version that made it.
//!
//! At rest (docs/storage.md): with a [`KeyRing`] each subject's vectors are sealed under its own
//! data key ([`cipher`], backend-neutral); a vector that fails authentication is refused
//! ([`StoreError::CorruptTemplate`]), never scored. Without a key, vectors are stored plain.
//!
//! SQLite: WAL mode; `secure_delete` zeroes what a deletion frees and the WAL is checkpointed and
//! truncated after each deletion, so a deleted subject leaves no bytes in the files;
//! `synchronous = FULL`, so an acknowledged enrolment survives a power loss, not only a crash.
//!
//! PostgreSQL: several processes (replicas) may share the database. Every enrolment and deletion
//! bumps a one-row change counter in its own transaction and notifies the new version with the
//! subject id (`LISTEN`/`NOTIFY`), so the others can follow ([`Store::watch`]). The migrator holds
//! an advisory lock while migrating, so replicas starting together migrate once. A deleted row
//! stays in the table's heap file until its page is reused (VACUUM does not zero it): see
//! docs/storage.md for what that means for erasure.
//!
//! Queries are checked at run time (`sqlx::query`), not by the `query!` macros, so a clean clone
//! builds without a database.
//!
//! The crate by concern: this file holds the errors, the row types, [`Store`] and the queries
//! both backends share for a subject (enrol, read, list, delete, count), and the migrators;
//! `gallery` the gallery's reads (whole, in parts, or a few subjects'); `sqlite` what is only
//! about SQLite's files (connection settings, checkpoint, backup, [`restore`]); `sqlite_scan`
//! the gallery read through SQLite's C API; `feed` the change counter and the change feed
//! (PostgreSQL's `LISTEN`/`NOTIFY`); `codec` how a template's vector is stored, plain or sealed;
//! [`cipher`] the sealing itself; `rekey` every subject brought under the current key
//! (`facegate rekey`); `site` the site calibration per model version; `renew` the rewrite of
//! protected templates under a new secret (`facegate renew-protection`).

mod challenge;
pub mod cipher;
mod codec;
mod feed;
mod gallery;
mod gallery_part;
mod redact;
mod rekey;
mod renew;
mod site;
mod sqlite;
mod sqlite_scan;
mod vanish;

#[cfg(test)]
mod at_rest;
#[cfg(test)]
mod tests;

use std::path::PathBuf;
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use sqlx::any::AnyPoolOptions;
use sqlx::migrate::Migrator;
use sqlx::postgres::PgConnectOptions;
use sqlx::{AnyPool, Row};

use facegate_core::SubjectId;
use facegate_core::template::Template;

use codec::{Sealing, encode_vector, seal_subject, template_from_row};

pub use challenge::{SWEEP_BATCH, TakenChallenge};
pub use cipher::{CipherError, KeyRing};
pub use codec::{KeyCheck, SealingCounts, blob_to_vector, vector_to_blob};
pub use feed::{ChangeFeed, StoreChange};
pub use gallery_part::GalleryPart;
pub use redact::redact_url;
pub use rekey::RekeyReport;
pub use renew::{RenewReport, RenewedVersion, Renewing};
pub use sqlite::restore;

/// Longest a query waits for a connection of the pool (sqlx's default is 30 s). A database that
/// cannot be reached fails each request within this bound ([`StoreError::is_unavailable`]),
/// rather than holding it for half a minute; connections refused meanwhile are retried with
/// back-off until it passes. Under 2 s, so that while the database is down no request waits
/// longer: the service's circuit refuses the others at once.
pub const ACQUIRE_TIMEOUT: Duration = Duration::from_millis(1500);

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// `url` is the URL as printed: its password redacted ([`redact_url`]).
    #[error("invalid database URL {url:?}: {source}")]
    Url { url: String, source: sqlx::Error },
    #[error("cannot migrate the database: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    #[error("stored template {id} is corrupt: {message}")]
    CorruptTemplate { id: i64, message: String },
    #[error("the data key of subject {subject} cannot be opened: {source}")]
    DataKey { subject: String, source: CipherError },
    #[error("subject {subject}'s templates are encrypted, but no template key is configured (FACEGATE_TEMPLATE_KEY_FILE)")]
    NoKey { subject: String },
    #[error("{0}")]
    Refused(String),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// The connection was lost while the commit was under way: the server may have committed it
    /// before it went away, so whether the write is stored is not known.
    #[error("the database went away during the commit, which may or may not have been stored: {0}")]
    CommitUnknown(sqlx::Error),
    /// The SQLite file opened at start is no longer at its path (unlinked or replaced).
    #[error("the database file is no longer where it was opened: {0}")]
    Vanished(String),
}

impl StoreError {
    /// Is the database unreachable (rather than refusing this one request)? No connection could be
    /// had within [`ACQUIRE_TIMEOUT`], the pool is closed, the connection failed with an I/O or
    /// TLS error, or the server says it is shutting down or not accepting connections
    /// (PostgreSQL classes 08 and 57P0x); on SQLite, the file cannot be opened or read
    /// (`SQLITE_CANTOPEN`, `SQLITE_IOERR`). A busy or locked database, a constraint, a corrupt
    /// template or a data key that does not open is not unavailability: retrying elsewhere does not
    /// help those.
    /// A failed commit: [`StoreError::CommitUnknown`] when the database went away meanwhile.
    fn of_commit(error: sqlx::Error) -> StoreError {
        if sqlx_unavailable(&error) { StoreError::CommitUnknown(error) } else { StoreError::Database(error) }
    }

    /// The database did not answer within the time a caller gives it (taken as unreachable).
    pub fn timed_out() -> StoreError {
        StoreError::Database(sqlx::Error::PoolTimedOut)
    }

    pub fn is_unavailable(&self) -> bool {
        match self {
            StoreError::Database(e) | StoreError::CommitUnknown(e) => sqlx_unavailable(e),
            StoreError::Vanished(_) => true,
            StoreError::Migrate(sqlx::migrate::MigrateError::Execute(e) | sqlx::migrate::MigrateError::ExecuteMigration(e, _)) => {
                sqlx_unavailable(e)
            }
            _ => false,
        }
    }
}

fn sqlx_unavailable(error: &sqlx::Error) -> bool {
    match error {
        sqlx::Error::PoolTimedOut | sqlx::Error::PoolClosed | sqlx::Error::Io(_) | sqlx::Error::Tls(_) => true,
        sqlx::Error::Database(e) => {
            if let Some(e) = e.try_downcast_ref::<sqlx::postgres::PgDatabaseError>() {
                // SQLSTATE class 08: connection exception; 57P01-57P03: the server is shutting
                // down, crashed, or cannot take connections now.
                let code = e.code();
                code.starts_with("08") || matches!(code, "57P01" | "57P02" | "57P03")
            } else if e.try_downcast_ref::<sqlx::sqlite::SqliteError>().is_some() {
                // The extended result code; its low byte is the primary code: 10 SQLITE_IOERR,
                // 11 SQLITE_CORRUPT, 14 SQLITE_CANTOPEN, 26 SQLITE_NOTADB (a file corrupted or
                // truncated under the service: no request can be served from it).
                e.code().and_then(|code| code.parse::<i32>().ok()).is_some_and(|code| matches!(code & 0xff, 10 | 11 | 14 | 26))
            } else {
                false
            }
        }
        sqlx::Error::Migrate(e) => matches!(
            &**e,
            sqlx::migrate::MigrateError::Execute(e) | sqlx::migrate::MigrateError::ExecuteMigration(e, _) if sqlx_unavailable(e)
        ),
        _ => false,
    }
}

/// Which database a [`Store`] is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Sqlite,
    Postgres,
}

impl Backend {
    /// The backend a database URL names by its scheme.
    pub fn of(url: &str) -> Result<Backend, StoreError> {
        let scheme = url.split_once(':').map_or("", |(scheme, _)| scheme);
        match scheme {
            "sqlite" => Ok(Backend::Sqlite),
            "postgres" | "postgresql" => Ok(Backend::Postgres),
            _ => Err(StoreError::Url {
                url: redact_url(url),
                source: sqlx::Error::Configuration("the scheme must be sqlite:, postgres: or postgresql:".into()),
            }),
        }
    }
}

/// Each backend's schema from its own folder, `migrations/sqlite/` and `migrations/postgres/`.
/// sqlx's checksum is of a file's contents and its version of the file name, so databases
/// migrated before the SQLite files moved into their folder still match.
static SQLITE_MIGRATIONS: Migrator = sqlx::migrate!("../../migrations/sqlite");
static POSTGRES_MIGRATIONS: Migrator = sqlx::migrate!("../../migrations/postgres");

/// One subject as listed: its id, how many templates it has, and when it was enrolled.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SubjectSummary {
    pub id: String,
    pub templates: u32,
    pub created_at: String,
    pub updated_at: String,
}

/// Templates of one subject made by one model version.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VersionCount {
    pub model_version: String,
    pub templates: u32,
}

/// One subject in detail.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SubjectDetail {
    pub id: String,
    pub templates: u32,
    pub model_versions: Vec<VersionCount>,
    pub created_at: String,
    pub updated_at: String,
}

/// The template database. Cheap to clone (a connection pool).
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
    /// Where a [`ChangeFeed`] connects (PostgreSQL only).
    listen: Option<PgConnectOptions>,
    keys: Option<Arc<KeyRing>>,
    /// The SQLite database file, which the gallery's start-up read scans on a connection of its
    /// own ([`sqlite_scan`]); `None` on PostgreSQL.
    sqlite_file: Option<PathBuf>,
    /// That file's identity at start, checked before writes and by [`Store::counts`].
    file_watch: Option<Arc<vanish::FileWatch>>,
}

impl std::fmt::Debug for Store {
    /// Not the connection options: they may hold a password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("backend", &self.backend).field("keys", &self.keys).finish_non_exhaustive()
    }
}

impl Store {
    /// Open the database at `url` and apply the migrations: `sqlite://...` (created if missing)
    /// or `postgres://...` / `postgresql://...` (the database must exist). With `keys`, new
    /// templates are sealed and sealed ones can be read; without, templates are stored plain and a
    /// subject sealed earlier cannot be read ([`StoreError::NoKey`]).
    pub async fn connect(url: &str, keys: Option<KeyRing>) -> Result<Store, StoreError> {
        sqlx::any::install_default_drivers();
        let bad_url = |source| StoreError::Url { url: redact_url(url), source };
        let backend = Backend::of(url)?;
        let (pool, listen) = match backend {
            Backend::Sqlite => {
                let pool = sqlite::open(url).await?;
                SQLITE_MIGRATIONS.run(&pool).await?;
                (pool, None)
            }
            Backend::Postgres => {
                let listen = PgConnectOptions::from_str(url).map_err(bad_url)?;
                let pool = AnyPoolOptions::new().max_connections(8).acquire_timeout(ACQUIRE_TIMEOUT).connect(url).await?;
                POSTGRES_MIGRATIONS.run(&pool).await?;
                (pool, Some(listen))
            }
        };
        let sqlite_file = match backend {
            Backend::Sqlite => sqlite::file_of(url)?,
            Backend::Postgres => None,
        };
        let file_watch = sqlite_file.as_deref().map(vanish::FileWatch::new).transpose()?.map(Arc::new);
        Ok(Store { pool, backend, listen, keys: keys.map(Arc::new), sqlite_file, file_watch })
    }

    /// [`Store::connect`] to a database that must already exist: an SQLite file that is not there
    /// is refused, never created (an operator command on a mistyped path must not leave an empty
    /// database behind).
    pub async fn connect_existing(url: &str, keys: Option<KeyRing>) -> Result<Store, StoreError> {
        if Backend::of(url)? == Backend::Sqlite
            && let Some(file) = sqlite::file_of(url)?.filter(|file| !file.exists())
        {
            return Err(StoreError::Refused(format!("there is no database at {}", file.display())));
        }
        Store::connect(url, keys).await
    }

    /// Which database this is.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Are new templates sealed (a template key is configured)?
    pub fn encrypts(&self) -> bool {
        self.keys.is_some()
    }

    /// Is the database answering?
    pub async fn ping(&self) -> Result<(), StoreError> {
        self.still_there()?;
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// A write transaction, begun by `begin_by` (at most [`ACQUIRE_TIMEOUT`] after the caller
    /// arrived) in all: a database that went away
    /// can make sqlx's own acquire wait more than once (a dead pooled connection, then a new one),
    /// and a write that has not begun by then is refused rather than committed after its caller
    /// was told it failed.
    async fn begin_write(&self, begin_by: tokio::time::Instant) -> Result<sqlx::Transaction<'static, sqlx::Any>, StoreError> {
        self.still_there()?;
        match tokio::time::timeout_at(begin_by, self.pool.begin()).await {
            Ok(tx) => Ok(tx?),
            Err(_) => Err(StoreError::timed_out()),
        }
    }

    /// Add `templates` to `subject` (created if new), all in one transaction.
    /// Returns the subject's template count afterwards. With a key, a subject whose templates are
    /// still plain (enrolled before the key was set) is sealed in the same transaction.
    pub async fn enroll(&self, subject: &SubjectId, templates: &[Template]) -> Result<u32, StoreError> {
        self.enroll_by(subject, templates, tokio::time::Instant::now() + ACQUIRE_TIMEOUT).await
    }

    /// [`Store::enroll`], refused unless its transaction has begun by `begin_by` (a writer that
    /// waited behind another for the database is not held past the caller's bound).
    pub async fn enroll_by(&self, subject: &SubjectId, templates: &[Template], begin_by: tokio::time::Instant) -> Result<u32, StoreError> {
        let mut tx = self.begin_write(begin_by).await?;
        // A write first, so the transaction holds the write lock (SQLite) or the subject's row
        // lock (PostgreSQL) from its start.
        sqlx::query("INSERT INTO subjects (id) VALUES ($1) ON CONFLICT (id) DO UPDATE SET updated_at = excluded.updated_at")
            .bind(subject.as_str())
            .execute(&mut *tx)
            .await?;
        let row = sqlx::query("SELECT key_id, data_key FROM subjects WHERE id = $1").bind(subject.as_str()).fetch_one(&mut *tx).await?;
        let mut sealing = self.sealing(subject.as_str(), row.try_get("key_id")?, row.try_get("data_key")?)?;
        if let (Sealing::Plain, Some(keys)) = (&sealing, &self.keys) {
            sealing = Sealing::Sealed(seal_subject(&mut tx, keys, subject.as_str()).await?.0);
        }
        for template in templates {
            sqlx::query("INSERT INTO templates (subject_id, model_version, dimension, vector) VALUES ($1, $2, $3, $4)")
                .bind(subject.as_str())
                .bind(&template.model_version)
                .bind(template.vector.len() as i64)
                .bind(encode_vector(&sealing, subject.as_str(), template))
                .execute(&mut *tx)
                .await?;
        }
        let count: i64 =
            sqlx::query_scalar("SELECT count(*) FROM templates WHERE subject_id = $1").bind(subject.as_str()).fetch_one(&mut *tx).await?;
        self.record_change(&mut tx, subject.as_str()).await?;
        tx.commit().await.map_err(StoreError::of_commit)?;
        Ok(count as u32)
    }

    /// All templates of `subject`, or `None` when the subject is unknown. A template that fails
    /// authentication fails the whole read. One statement, so one snapshot on both backends (a
    /// subject sealed by a concurrent `rekey` is read either before or after, never half).
    pub async fn templates(&self, subject: &SubjectId) -> Result<Option<Vec<Template>>, StoreError> {
        let rows = sqlx::query(
            "SELECT s.key_id, s.data_key, t.id, t.model_version, t.dimension, t.vector
             FROM subjects s LEFT JOIN templates t ON t.subject_id = s.id
             WHERE s.id = $1 ORDER BY t.id",
        )
        .bind(subject.as_str())
        .fetch_all(&self.pool)
        .await?;
        let Some(first) = rows.first() else { return Ok(None) };
        let sealing = self.sealing(subject.as_str(), first.try_get("key_id")?, first.try_get("data_key")?)?;
        let mut templates = Vec::with_capacity(rows.len());
        for row in &rows {
            // A subject without templates is one row with no template.
            if row.try_get::<Option<i64>, _>("id")?.is_some() {
                templates.push(template_from_row(&sealing, subject.as_str(), row)?);
            }
        }
        Ok(Some(templates))
    }

    /// Subjects ordered by id, at most `limit` of them, starting after the id `after`.
    pub async fn list_subjects(&self, after: Option<&SubjectId>, limit: u32) -> Result<Vec<SubjectSummary>, StoreError> {
        let rows = sqlx::query(
            "SELECT s.id, s.created_at, s.updated_at, count(t.id) AS templates
             FROM subjects s LEFT JOIN templates t ON t.subject_id = s.id
             WHERE s.id > $1 GROUP BY s.id ORDER BY s.id LIMIT $2",
        )
        .bind(after.map_or("", SubjectId::as_str))
        .bind(limit as i64)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|row| {
                Ok(SubjectSummary {
                    id: row.try_get("id")?,
                    templates: row.try_get::<i64, _>("templates")? as u32,
                    created_at: row.try_get("created_at")?,
                    updated_at: row.try_get("updated_at")?,
                })
            })
            .collect()
    }

    /// One subject with its template counts per model version, or `None` when unknown.
    pub async fn subject(&self, id: &SubjectId) -> Result<Option<SubjectDetail>, StoreError> {
        let mut tx = self.pool.begin().await?;
        let Some(row) =
            sqlx::query("SELECT id, created_at, updated_at FROM subjects WHERE id = $1").bind(id.as_str()).fetch_optional(&mut *tx).await?
        else {
            return Ok(None);
        };
        let versions = sqlx::query(
            "SELECT model_version, count(*) AS n FROM templates WHERE subject_id = $1 GROUP BY model_version ORDER BY model_version",
        )
        .bind(id.as_str())
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        let model_versions = versions
            .iter()
            .map(|r| Ok(VersionCount { model_version: r.try_get("model_version")?, templates: r.try_get::<i64, _>("n")? as u32 }))
            .collect::<Result<Vec<_>, sqlx::Error>>()?;
        Ok(Some(SubjectDetail {
            id: row.try_get("id")?,
            templates: model_versions.iter().map(|v| v.templates).sum(),
            model_versions,
            created_at: row.try_get("created_at")?,
            updated_at: row.try_get("updated_at")?,
        }))
    }

    /// Erase a subject, its templates and its data key. Returns how many templates were erased,
    /// or `None` when the subject is unknown. On SQLite the WAL is then checkpointed and
    /// truncated, so the erased rows are left neither in the WAL nor (`secure_delete`) in the
    /// database's free space.
    pub async fn delete_subject(&self, id: &SubjectId) -> Result<Option<u32>, StoreError> {
        self.delete_subject_by(id, tokio::time::Instant::now() + ACQUIRE_TIMEOUT).await
    }

    /// [`Store::delete_subject`], refused unless its transaction has begun by `begin_by`.
    pub async fn delete_subject_by(&self, id: &SubjectId, begin_by: tokio::time::Instant) -> Result<Option<u32>, StoreError> {
        let mut tx = self.begin_write(begin_by).await?;
        // The subject's row is locked first (as an enrolment does), so no enrolment adds
        // templates between the count and the deletion.
        let found =
            sqlx::query("UPDATE subjects SET key_id = key_id WHERE id = $1").bind(id.as_str()).execute(&mut *tx).await?.rows_affected();
        if found == 0 {
            tx.rollback().await?;
            return Ok(None);
        }
        let templates: i64 =
            sqlx::query_scalar("SELECT count(*) FROM templates WHERE subject_id = $1").bind(id.as_str()).fetch_one(&mut *tx).await?;
        let deleted = sqlx::query("DELETE FROM subjects WHERE id = $1").bind(id.as_str()).execute(&mut *tx).await?.rows_affected();
        self.record_change(&mut tx, id.as_str()).await?;
        tx.commit().await.map_err(StoreError::of_commit)?;
        if deleted > 0 && self.backend == Backend::Sqlite {
            // The deletion is committed whatever happens here: a checkpoint that cannot finish is
            // logged (the erased rows may then stay in the WAL until it is overwritten or the next
            // deletion's checkpoint truncates it).
            match self.checkpoint().await {
                Ok(true) => {}
                Ok(false) => {
                    tracing::warn!(subject = %id, "WAL checkpoint after a deletion blocked by readers; the WAL may hold the erased rows until the next one")
                }
                Err(e) => tracing::warn!(subject = %id, "WAL checkpoint after a deletion failed: {e}"),
            }
        }
        Ok((deleted > 0).then_some(templates as u32))
    }

    /// Number of subjects and of templates (for metrics and health).
    pub async fn counts(&self) -> Result<(u64, u64), StoreError> {
        self.still_there()?;
        let row =
            sqlx::query("SELECT (SELECT count(*) FROM subjects) AS s, (SELECT count(*) FROM templates) AS t").fetch_one(&self.pool).await?;
        Ok((row.try_get::<i64, _>("s")? as u64, row.try_get::<i64, _>("t")? as u64))
    }

    /// Close the pool. On SQLite the WAL is checkpointed and truncated first, so the database
    /// file alone holds everything (the pool's connections close side by side, and SQLite
    /// removes the WAL only when the last one finds itself alone).
    ///
    /// A connection goes back to sqlx's pool in a task of its own after its last query, and
    /// `Pool::close` can miss one still on its way: it then lands in the closed pool's idle queue
    /// and stays open for the pool's life, holding the database file (seen here: 1 close in 30
    /// left one open). So the pool is closed only once every connection is back in it.
    pub async fn close(&self) {
        if self.backend == Backend::Sqlite {
            if let Err(e) = self.checkpoint().await {
                tracing::warn!("WAL checkpoint on close failed: {e}");
            }
        }
        let started = Instant::now();
        while self.pool.num_idle() < self.pool.size() as usize && started.elapsed() < CLOSE_WAIT {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        self.pool.close().await;
        if self.pool.size() > 0 {
            tracing::warn!(open = self.pool.size(), "database connections still open after the store was closed");
        }
    }
}

/// Longest [`Store::close`] waits for connections in use to come back to the pool (queries of
/// other tasks still running) before it closes it anyway.
const CLOSE_WAIT: Duration = Duration::from_secs(5);
