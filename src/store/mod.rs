//! Subjects and their face templates in SQLite (the embedded default) or PostgreSQL, through
//! sqlx.
//!
//! One implementation serves both backends: the queries are written once in the SQL both accept
//! (`$n` parameters, `ON CONFLICT`, text timestamps) and run on an [`sqlx::AnyPool`]; only what
//! has no common form is per backend: the connection settings, the migrations (`migrations/` for
//! SQLite, `migrations/postgres/`), the change counter and its notifications (PostgreSQL), and
//! the WAL checkpoint, backup and restore (SQLite files).
//!
//! Deleting a subject erases its templates (foreign keys cascade). An enrolment is one
//! transaction: either all of its templates are stored or none. No photo is ever stored, only
//! templates: each is a little-endian f32 vector with the recognition model version that made it.
//!
//! At rest (docs/service.md): with a [`KeyRing`] each subject's vectors are sealed under its own
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
//! docs/service.md for what that means for erasure.
//!
//! Queries are checked at run time (`sqlx::query`), not by the `query!` macros, so a clean clone
//! builds without a database.

pub mod cipher;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::TryStreamExt;
use serde::{Deserialize, Serialize};
use sqlx::any::{AnyPoolOptions, AnyRow};
use sqlx::migrate::Migrator;
use sqlx::postgres::{PgConnectOptions, PgListener, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteConnection, SqliteLockingMode};
use sqlx::{AnyConnection, AnyPool, Connection, Executor, Row};

use crate::recognize::Template;
use crate::service::SubjectId;

use cipher::DataKey;
pub use cipher::{CipherError, KeyRing};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
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
                url: url.to_string(),
                source: sqlx::Error::Configuration("the scheme must be sqlite:, postgres: or postgresql:".into()),
            }),
        }
    }
}

/// SQLite's schema; it does not descend into `migrations/postgres/` (sqlx reads the files of the
/// folder only), whose files are PostgreSQL's.
static SQLITE_MIGRATIONS: Migrator = sqlx::migrate!("./migrations");
static POSTGRES_MIGRATIONS: Migrator = sqlx::migrate!("./migrations/postgres");

/// The PostgreSQL channel every enrolment and deletion notifies (payload: [`Notice`]).
const CHANGE_CHANNEL: &str = "facegate_changes";

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

/// What [`Store::rekey`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct RekeyReport {
    /// Subjects whose data key was re-wrapped by the current key.
    pub rewrapped: u64,
    /// Subjects whose plain templates were sealed (with a new data key).
    pub sealed: u64,
    /// Templates sealed along with them.
    pub templates_sealed: u64,
}

/// A change seen on the database, from [`ChangeFeed::next`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StoreChange {
    /// `subject` was enrolled into or deleted in the transaction that set the change counter to
    /// `version`: re-read it ([`Store::templates`]).
    Subject { subject: String, version: i64 },
    /// Notifications may have been missed (the listening connection was lost and re-made):
    /// re-read everything.
    Resync,
}

/// A notification's payload.
#[derive(Serialize, Deserialize)]
struct Notice {
    subject: String,
    version: i64,
}

/// How one subject's vectors are stored.
enum Sealing {
    Plain,
    Sealed(DataKey),
}

/// A subject being read by [`Store::gallery`]: its id, how its vectors are stored (none when its
/// data key cannot be opened), and its templates so far or why they cannot be read.
type SubjectReading = (String, Option<Sealing>, Result<Vec<Template>, StoreError>);

/// The template database. Cheap to clone (a connection pool).
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
    /// Where a [`ChangeFeed`] connects (PostgreSQL only).
    listen: Option<PgConnectOptions>,
    keys: Option<Arc<KeyRing>>,
}

impl std::fmt::Debug for Store {
    /// Not the connection options: they may hold a password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("backend", &self.backend).field("keys", &self.keys).finish_non_exhaustive()
    }
}

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
    let options = SqliteConnectOptions::from_str(url).map_err(|source| StoreError::Url { url: url.to_string(), source })?;
    Ok(SQLITE_PRAGMAS.iter().fold(options, |options, &(key, value)| options.pragma(key, value)))
}

/// [`SQLITE_PRAGMAS`] as one batch of statements.
fn sqlite_session() -> String {
    SQLITE_PRAGMAS.iter().map(|(key, value)| format!("PRAGMA {key} = {value};")).collect::<Vec<_>>().join(" ")
}

impl Store {
    /// Open the database at `url` and apply the migrations: `sqlite://...` (created if missing)
    /// or `postgres://...` / `postgresql://...` (the database must exist). With `keys`, new
    /// templates are sealed and sealed ones can be read; without, templates are stored plain and a
    /// subject sealed earlier cannot be read ([`StoreError::NoKey`]).
    pub async fn connect(url: &str, keys: Option<KeyRing>) -> Result<Store, StoreError> {
        sqlx::any::install_default_drivers();
        let bad_url = |source| StoreError::Url { url: url.to_string(), source };
        let backend = Backend::of(url)?;
        let (pool, listen) = match backend {
            Backend::Sqlite => {
                // The file is created (and put in WAL mode) through SQLite's own options; the
                // pool then opens the URL as given, parsed by the same code, so the same file.
                SqliteConnection::connect_with(&sqlite_options(url)?.create_if_missing(true)).await?.close().await?;
                let pool = AnyPoolOptions::new()
                    .max_connections(8)
                    .after_connect(|connection, _| Box::pin(async move { connection.execute(sqlite_session().as_str()).await.map(drop) }))
                    .connect(url)
                    .await?;
                SQLITE_MIGRATIONS.run(&pool).await?;
                (pool, None)
            }
            Backend::Postgres => {
                let listen = PgConnectOptions::from_str(url).map_err(bad_url)?;
                let pool = AnyPoolOptions::new().max_connections(8).connect(url).await?;
                POSTGRES_MIGRATIONS.run(&pool).await?;
                (pool, Some(listen))
            }
        };
        Ok(Store { pool, backend, listen, keys: keys.map(Arc::new) })
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
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// The change counter: bumped in the same transaction as every enrolment and deletion, so its
    /// order is the commit order. `None` on SQLite (one process owns the file).
    pub async fn change_version(&self) -> Result<Option<i64>, StoreError> {
        match self.backend {
            Backend::Sqlite => Ok(None),
            Backend::Postgres => Ok(Some(sqlx::query_scalar("SELECT n FROM change_counter").fetch_one(&self.pool).await?)),
        }
    }

    /// A feed of the changes committed by any process on this database, from now on. `None` on
    /// SQLite.
    pub async fn watch(&self) -> Result<Option<ChangeFeed>, StoreError> {
        let Some(options) = &self.listen else { return Ok(None) };
        // A pool of one, for PgListener to reconnect through; no lifetime or idle limit, since the
        // connection idles between notifications by design.
        let pool = PgPoolOptions::new()
            .max_connections(1)
            .max_lifetime(None)
            .idle_timeout(None)
            .acquire_timeout(Duration::from_secs(5))
            .connect_with(options.clone())
            .await?;
        let mut listener = PgListener::connect_with(&pool).await?;
        listener.listen(CHANGE_CHANNEL).await?;
        Ok(Some(ChangeFeed { listener, pending: None, give_up_after: RECONNECT_FOR }))
    }

    /// Bump the change counter inside `tx` (PostgreSQL) and notify its new value with `subject`;
    /// both take effect at commit. The counter row is locked last in every writing transaction,
    /// after the subject's row, so two writers never wait on each other in opposite orders.
    async fn record_change(&self, tx: &mut AnyConnection, subject: &str) -> Result<(), StoreError> {
        if self.backend == Backend::Postgres {
            let version: i64 = sqlx::query_scalar("UPDATE change_counter SET n = n + 1 RETURNING n").fetch_one(&mut *tx).await?;
            let notice = serde_json::to_string(&Notice { subject: subject.to_string(), version }).expect("a notice serialises");
            sqlx::query("SELECT pg_notify($1, $2)").bind(CHANGE_CHANNEL).bind(notice).execute(&mut *tx).await?;
        }
        Ok(())
    }

    /// How `subject`'s vectors are stored, from its row's key id and wrapped data key.
    fn sealing(&self, subject: &str, key_id: Option<String>, wrapped: Option<Vec<u8>>) -> Result<Sealing, StoreError> {
        let (Some(key_id), Some(wrapped)) = (key_id, wrapped) else {
            return Ok(Sealing::Plain);
        };
        let keys = self.keys.as_ref().ok_or_else(|| StoreError::NoKey { subject: subject.to_string() })?;
        keys.unwrap(subject, &key_id, &wrapped)
            .map(Sealing::Sealed)
            .map_err(|source| StoreError::DataKey { subject: subject.to_string(), source })
    }

    /// Add `templates` to `subject` (created if new), all in one transaction.
    /// Returns the subject's template count afterwards. With a key, a subject whose templates are
    /// still plain (enrolled before the key was set) is sealed in the same transaction.
    pub async fn enroll(&self, subject: &SubjectId, templates: &[Template]) -> Result<u32, StoreError> {
        let mut tx = self.pool.begin().await?;
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
        tx.commit().await?;
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

    /// Every subject's templates made by `model_version`, handed to `each` one subject at a time
    /// in subject id order (rows are streamed, so the whole gallery is never held twice). A
    /// subject whose templates cannot be read is handed its error; the scan goes on.
    pub async fn gallery(
        &self,
        model_version: &str,
        mut each: impl FnMut(&str, Result<Vec<Template>, StoreError>),
    ) -> Result<(), StoreError> {
        let mut rows = sqlx::query(
            "SELECT t.id, t.subject_id, t.model_version, t.dimension, t.vector, s.key_id, s.data_key
             FROM templates t JOIN subjects s ON s.id = t.subject_id
             WHERE t.model_version = $1 ORDER BY t.subject_id, t.id",
        )
        .bind(model_version)
        .fetch(&self.pool);
        let mut current: Option<SubjectReading> = None;
        while let Some(row) = rows.try_next().await? {
            let subject: String = row.try_get("subject_id")?;
            if current.as_ref().is_none_or(|(s, _, _)| *s != subject) {
                if let Some((done, _, templates)) = current.take() {
                    each(&done, templates);
                }
                current = Some(match self.sealing(&subject, row.try_get("key_id")?, row.try_get("data_key")?) {
                    Ok(sealing) => (subject, Some(sealing), Ok(Vec::new())),
                    Err(e) => (subject, None, Err(e)),
                });
            }
            if let Some((subject, Some(sealing), templates @ Ok(_))) = current.as_mut() {
                match template_from_row(sealing, subject, &row) {
                    Ok(template) => templates.as_mut().expect("matched Ok").push(template),
                    Err(e) => *templates = Err(e),
                }
            }
        }
        if let Some((done, _, templates)) = current.take() {
            each(&done, templates);
        }
        Ok(())
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
        let mut tx = self.pool.begin().await?;
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
        tx.commit().await?;
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

    /// Number of subjects and of templates (for metrics and health).
    pub async fn counts(&self) -> Result<(u64, u64), StoreError> {
        let row =
            sqlx::query("SELECT (SELECT count(*) FROM subjects) AS s, (SELECT count(*) FROM templates) AS t").fetch_one(&self.pool).await?;
        Ok((row.try_get::<i64, _>("s")? as u64, row.try_get::<i64, _>("t")? as u64))
    }

    /// Bring every subject under the current key: data keys wrapped by an older key of the ring
    /// are re-wrapped (the sealed templates stay as they are), and plain subjects are sealed with
    /// a new data key. One transaction per subject, so the service may keep running and an
    /// interrupted run resumes where it stopped (subjects already under the current key are
    /// skipped). `progress` is called after each subject. The templates read back the same, so
    /// no change is recorded.
    pub async fn rekey(&self, mut progress: impl FnMut(&RekeyReport)) -> Result<RekeyReport, StoreError> {
        let keys = self.keys.clone().ok_or_else(|| StoreError::Refused("rekey needs a template key".into()))?;
        let current = keys.current_id().to_string();
        let mut report = RekeyReport::default();
        let mut after = String::new();
        loop {
            let batch: Vec<String> =
                sqlx::query_scalar("SELECT id FROM subjects WHERE id > $1 AND (key_id IS NULL OR key_id <> $2) ORDER BY id LIMIT 256")
                    .bind(&after)
                    .bind(&current)
                    .fetch_all(&self.pool)
                    .await?;
            let Some(last) = batch.last() else { break };
            after = last.clone();
            for subject in &batch {
                let mut tx = self.pool.begin().await?;
                // A write first, so the transaction holds the write lock from its start.
                sqlx::query("UPDATE subjects SET key_id = key_id WHERE id = $1").bind(subject).execute(&mut *tx).await?;
                let Some(row) =
                    sqlx::query("SELECT key_id, data_key FROM subjects WHERE id = $1").bind(subject).fetch_optional(&mut *tx).await?
                else {
                    continue; // deleted meanwhile
                };
                match self.sealing(subject, row.try_get("key_id")?, row.try_get("data_key")?)? {
                    Sealing::Plain => {
                        let (_, sealed) = seal_subject(&mut tx, &keys, subject).await?;
                        report.sealed += 1;
                        report.templates_sealed += sealed;
                    }
                    Sealing::Sealed(data_key) => {
                        sqlx::query("UPDATE subjects SET key_id = $2, data_key = $3 WHERE id = $1")
                            .bind(subject)
                            .bind(&current)
                            .bind(keys.wrap(&data_key, subject))
                            .execute(&mut *tx)
                            .await?;
                        report.rewrapped += 1;
                    }
                }
                tx.commit().await?;
                progress(&report);
            }
        }
        Ok(report)
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

/// How long a [`ChangeFeed`] keeps trying to reconnect before it reports the database gone,
/// unless told otherwise ([`ChangeFeed::give_up_after`]).
const RECONNECT_FOR: Duration = Duration::from_secs(60);

/// The changes committed on a PostgreSQL database by any process ([`Store::watch`]): a `LISTEN`ing
/// connection of its own.
pub struct ChangeFeed {
    listener: PgListener,
    /// A change received right after a reconnect, handed out after the [`StoreChange::Resync`].
    pending: Option<StoreChange>,
    give_up_after: Duration,
}

impl ChangeFeed {
    /// How long [`next`](Self::next) keeps trying to reconnect before it fails (60 s unless set).
    pub fn give_up_after(&mut self, limit: Duration) {
        self.give_up_after = limit;
    }

    /// The next change. A lost connection is re-made (with `LISTEN` again) and reported as
    /// [`StoreChange::Resync`]: what was notified meanwhile is gone. Errors only when the
    /// database cannot be reached for [`give_up_after`](Self::give_up_after).
    pub async fn next(&mut self) -> Result<StoreChange, StoreError> {
        if let Some(change) = self.pending.take() {
            return Ok(change);
        }
        let mut failing_since: Option<Instant> = None;
        loop {
            match self.listener.try_recv().await {
                Ok(Some(notification)) if failing_since.is_none() => return Ok(change_from(notification.payload())),
                Ok(Some(notification)) => {
                    self.pending = Some(change_from(notification.payload()));
                    return Ok(StoreChange::Resync);
                }
                // The connection was lost and has been re-made, listening again.
                Ok(None) => return Ok(StoreChange::Resync),
                Err(e) => {
                    let since = *failing_since.get_or_insert_with(Instant::now);
                    if since.elapsed() > self.give_up_after {
                        return Err(e.into());
                    }
                    tokio::time::sleep(Duration::from_millis(250)).await;
                    // Reconnect (PgListener re-issues LISTEN) before waiting for notifications
                    // again, so that the resync is reported as soon as it can be done.
                    if sqlx::query("SELECT 1").execute(&mut self.listener).await.is_ok() {
                        return Ok(StoreChange::Resync);
                    }
                }
            }
        }
    }
}

/// A notification read as a change; one that cannot be read (not ours) calls for a resync.
fn change_from(payload: &str) -> StoreChange {
    match serde_json::from_str::<Notice>(payload) {
        Ok(Notice { subject, version }) => StoreChange::Subject { subject, version },
        Err(_) => StoreChange::Resync,
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

/// Give `subject` a new data key (wrapped by the current key) and seal its plain templates under
/// it, inside `tx`. Returns the key and how many templates were sealed.
async fn seal_subject(tx: &mut AnyConnection, keys: &KeyRing, subject: &str) -> Result<(DataKey, u64), StoreError> {
    let (data_key, wrapped) = keys.new_data_key(subject);
    let rows = sqlx::query("SELECT id, model_version, dimension, vector FROM templates WHERE subject_id = $1")
        .bind(subject)
        .fetch_all(&mut *tx)
        .await?;
    for row in &rows {
        let template = template_from_row(&Sealing::Plain, subject, row)?;
        sqlx::query("UPDATE templates SET vector = $2 WHERE id = $1")
            .bind(row.try_get::<i64, _>("id")?)
            .bind(data_key.seal_template(subject, &template.model_version, &template.vector))
            .execute(&mut *tx)
            .await?;
    }
    sqlx::query("UPDATE subjects SET key_id = $2, data_key = $3 WHERE id = $1")
        .bind(subject)
        .bind(keys.current_id())
        .bind(wrapped)
        .execute(&mut *tx)
        .await?;
    Ok((data_key, rows.len() as u64))
}

fn encode_vector(sealing: &Sealing, subject: &str, template: &Template) -> Vec<u8> {
    match sealing {
        Sealing::Plain => vector_to_blob(&template.vector),
        Sealing::Sealed(key) => key.seal_template(subject, &template.model_version, &template.vector),
    }
}

/// Little-endian f32s, the on-disk form of a plain template vector.
pub fn vector_to_blob(vector: &[f32]) -> Vec<u8> {
    vector.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Inverse of [`vector_to_blob`]; `None` when the length is not a multiple of 4.
pub fn blob_to_vector(blob: &[u8]) -> Option<Vec<f32>> {
    (blob.len() % 4 == 0).then(|| blob.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// A template row of `subject` read as its `sealing` says: a sealed vector must authenticate, a
/// plain one must have exactly its dimension's length (a sealed vector on a plain subject, or the
/// reverse, is refused: rows were moved or altered).
fn template_from_row(sealing: &Sealing, subject: &str, row: &AnyRow) -> Result<Template, StoreError> {
    let id: i64 = row.try_get("id")?;
    let dimension: i64 = row.try_get("dimension")?;
    let model_version: String = row.try_get("model_version")?;
    let blob: Vec<u8> = row.try_get("vector")?;
    let corrupt = |message: String| StoreError::CorruptTemplate { id, message };
    let vector = match sealing {
        Sealing::Plain => {
            let vector = blob_to_vector(&blob).ok_or_else(|| corrupt(format!("{} bytes", blob.len())))?;
            if vector.len() as i64 != dimension {
                return Err(corrupt(format!("{} values, {dimension} expected", vector.len())));
            }
            vector
        }
        Sealing::Sealed(key) => {
            key.open_template(subject, &model_version, dimension as usize, &blob).map_err(|e| corrupt(format!("subject {subject}: {e}")))?
        }
    };
    Ok(Template { model_version, vector })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each backend's migrator has exactly the files of its own folder: sqlx does not descend
    /// from `migrations/` into `migrations/postgres/`.
    #[test]
    fn each_backend_migrates_from_its_own_folder() {
        let versions = |migrator: &Migrator| migrator.iter().map(|m| m.version).collect::<Vec<i64>>();
        let files = |folder: &str| {
            let mut versions: Vec<i64> = std::fs::read_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(folder))
                .unwrap()
                .map(|e| e.unwrap().path())
                .filter(|p| p.is_file())
                .map(|p| p.file_name().unwrap().to_str().unwrap().split('_').next().unwrap().parse().unwrap())
                .collect();
            versions.sort();
            versions
        };
        assert_eq!(versions(&SQLITE_MIGRATIONS), files("migrations"));
        assert_eq!(versions(&POSTGRES_MIGRATIONS), files("migrations/postgres"));
    }

    #[test]
    fn blobs_round_trip_little_endian() {
        let v = [1.0f32, -0.5, 3.25e-7, f32::MAX];
        let blob = vector_to_blob(&v);
        assert_eq!(&blob[..4], &1.0f32.to_le_bytes());
        assert_eq!(blob_to_vector(&blob).unwrap(), v);
        assert!(blob_to_vector(&blob[..5]).is_none());
    }
}

#[cfg(test)]
mod at_rest {
    //! SQLite's files: sealed bytes in the file, erasure, durability settings, backup and restore.

    use super::*;

    const K1: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";

    fn ring(text: &str) -> Option<KeyRing> {
        Some(KeyRing::parse(text).unwrap())
    }

    fn id(s: &str) -> SubjectId {
        SubjectId::parse(s).unwrap()
    }

    /// A vector whose bytes are easy to find in a file, different per `seed`.
    fn marked(seed: f32) -> Template {
        Template { model_version: "m1".into(), vector: (0..32).map(|i| 1234.5678 + seed + i as f32 * 0.001).collect() }
    }

    struct Dir(PathBuf);

    impl Dir {
        fn new() -> Dir {
            static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
            let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let dir = std::env::temp_dir().join(format!("facegate-at-rest-{}-{n}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            Dir(dir)
        }
        fn url(&self, name: &str) -> String {
            format!("sqlite://{}", self.0.join(name).display())
        }
        /// The database file and its WAL, as bytes.
        fn raw(&self, name: &str) -> Vec<u8> {
            let mut bytes = std::fs::read(self.0.join(name)).unwrap();
            bytes.extend(std::fs::read(self.0.join(format!("{name}-wal"))).unwrap_or_default());
            bytes
        }
    }

    impl Drop for Dir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn contains(haystack: &[u8], needle: &[u8]) -> bool {
        haystack.windows(needle.len()).any(|w| w == needle)
    }

    /// Sealed vectors never reach the file (their round trip, wrong keys and tampered rows are
    /// tested on both backends in tests/api/store_backends.rs).
    #[tokio::test]
    async fn sealed_templates_never_show_in_the_file() {
        let dir = Dir::new();
        let store = Store::connect(&dir.url("t.db"), ring(K1)).await.unwrap();
        store.enroll(&id("alice"), &[marked(0.0), marked(1.0)]).await.unwrap();
        assert_eq!(store.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0), marked(1.0)]);
        assert!(store.checkpoint().await.unwrap());
        let raw = dir.raw("t.db");
        assert!(contains(&raw, b"alice"));
        for template in [marked(0.0), marked(1.0)] {
            assert!(!contains(&raw, &vector_to_blob(&template.vector)[..16]), "a plain vector in the file");
        }
        store.close().await;
    }

    #[tokio::test]
    async fn a_deleted_subject_leaves_nothing_in_the_files() {
        let dir = Dir::new();
        let store = Store::connect(&dir.url("t.db"), None).await.unwrap();
        let (secure, synchronous): (i64, i64) = (
            sqlx::query_scalar("PRAGMA secure_delete").fetch_one(&store.pool).await.unwrap(),
            sqlx::query_scalar("PRAGMA synchronous").fetch_one(&store.pool).await.unwrap(),
        );
        assert_eq!((secure, synchronous), (1, 2), "secure_delete on, synchronous FULL");
        let mode: String = sqlx::query_scalar("PRAGMA journal_mode").fetch_one(&store.pool).await.unwrap();
        assert_eq!(mode, "wal");
        let erased = "erasure-subject-7f3a";
        let erased_vectors = [marked(10.0), marked(20.0)];
        store.enroll(&id("keeper"), &[marked(30.0)]).await.unwrap();
        store.enroll(&id(erased), &erased_vectors).await.unwrap();
        store.enroll(&id("later"), &[marked(40.0)]).await.unwrap();
        let needles: Vec<Vec<u8>> = std::iter::once(erased.as_bytes().to_vec())
            .chain(erased_vectors.iter().flat_map(|t| vector_to_blob(&t.vector).chunks(16).map(<[u8]>::to_vec).collect::<Vec<_>>()))
            .collect();
        store.checkpoint().await.unwrap();
        let before = dir.raw("t.db");
        assert!(needles.iter().all(|n| contains(&before, n)), "the test must see the plain bytes before the deletion");

        assert_eq!(store.delete_subject(&id(erased)).await.unwrap(), Some(2));
        let after = dir.raw("t.db");
        for needle in &needles {
            assert!(!contains(&after, needle), "{needle:?} is still in the database files");
        }
        assert!(contains(&after, &vector_to_blob(&marked(30.0).vector)[..16]), "the others stay");
        store.close().await;
        let after_close = dir.raw("t.db");
        assert!(!needles.iter().any(|n| contains(&after_close, n)));
    }

    /// The pool opens the file the URL names, also with characters a URL escapes (`%25` is `%`),
    /// and after `close` that file holds everything (no WAL content is left beside it).
    #[tokio::test]
    async fn the_file_named_is_the_file_opened() {
        let dir = Dir::new();
        for (name, file) in [("with space.db", "with space.db"), ("per%25cent #1.db", "per%cent #1.db"), ("ünï.db", "ünï.db")] {
            let store = Store::connect(&dir.url(name), None).await.unwrap();
            store.enroll(&id("alice"), &[marked(0.0)]).await.unwrap();
            store.close().await;
            let mut files: Vec<String> =
                std::fs::read_dir(&dir.0).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
            files.sort();
            assert_eq!(files[0], file, "{files:?}");
            assert!(files[1..].iter().all(|f| *f == format!("{file}-shm") || *f == format!("{file}-wal")), "{files:?}");
            assert_eq!(std::fs::metadata(dir.0.join(format!("{file}-wal"))).map_or(0, |m| m.len()), 0, "the WAL is empty");
            let reopened = Store::connect(&dir.url(name), None).await.unwrap();
            assert_eq!(reopened.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0)]);
            reopened.close().await;
            // SQLite removes the -wal and -shm files when its last connection closes, on the
            // connection's worker thread, which may still be running: one may vanish meanwhile.
            for entry in std::fs::read_dir(&dir.0).unwrap() {
                match std::fs::remove_file(entry.unwrap().path()) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => panic!("{e}"),
                    _ => {}
                }
            }
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn backup_while_in_use_then_restore() {
        let dir = Dir::new();
        let store = Store::connect(&dir.url("live.db"), ring(K1)).await.unwrap();
        for i in 0..40 {
            store.enroll(&id(&format!("s{i:02}")), &[marked(i as f32), marked(i as f32 + 0.5)]).await.unwrap();
        }
        // Enrolments keep coming while the backup runs.
        let writer = {
            let store = store.clone();
            tokio::spawn(async move {
                for i in 0..200 {
                    store.enroll(&id(&format!("w{i:03}")), &[marked(100.0 + i as f32)]).await.unwrap();
                }
            })
        };
        let backup = dir.0.join("backup.db");
        store.backup(&backup).await.unwrap();
        assert!(matches!(store.backup(&backup).await, Err(StoreError::Refused(_))), "never overwrites");
        writer.await.unwrap();
        let (live_subjects, _) = store.counts().await.unwrap();
        assert_eq!(live_subjects, 240);

        // Restore to a new place: every subject of the backup reads back the same.
        let (subjects, templates) = restore(&backup, &dir.url("restored.db"), false).await.unwrap();
        assert!((40..=240).contains(&subjects) && templates == 80 + (subjects - 40), "{subjects} {templates}");
        let restored = Store::connect(&dir.url("restored.db"), ring(K1)).await.unwrap();
        for i in 0..40 {
            let s = id(&format!("s{i:02}"));
            assert_eq!(restored.templates(&s).await.unwrap(), store.templates(&s).await.unwrap());
        }
        assert_eq!(restored.counts().await.unwrap(), (subjects, templates));

        // Not over an existing database unless told, and never over one in use.
        assert!(matches!(restore(&backup, &dir.url("live.db"), false).await, Err(StoreError::Refused(_))));
        let refused = restore(&backup, &dir.url("restored.db"), true).await;
        assert!(matches!(refused, Err(StoreError::Refused(ref m)) if m.contains("in use")), "{refused:?}");
        restored.close().await;
        store.close().await;
        assert_eq!(restore(&backup, &dir.url("live.db"), true).await.unwrap(), (subjects, templates));
        let back = Store::connect(&dir.url("live.db"), ring(K1)).await.unwrap();
        assert_eq!(back.counts().await.unwrap(), (subjects, templates));
        assert_eq!(back.templates(&id("s07")).await.unwrap().unwrap(), [marked(7.0), marked(7.5)]);
        back.close().await;
        // Not a database at all.
        std::fs::write(dir.0.join("junk.db"), b"not sqlite").unwrap();
        assert!(restore(&dir.0.join("junk.db"), &dir.url("other.db"), false).await.is_err());
    }
}
