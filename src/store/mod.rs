//! Subjects and their face templates in SQLite, through sqlx.
//!
//! The schema lives in `migrations/` and is applied on connect. The database runs in WAL mode
//! with foreign keys on, so deleting a subject erases its templates. An enrolment is one
//! transaction: either all of its templates are stored or none. No photo is ever stored, only
//! templates: each is a little-endian f32 vector with the recognition model version that made it.
//!
//! Queries are checked at run time (`sqlx::query`), not by the `query!` macros, so a clean clone
//! builds without a database.

use std::str::FromStr;
use std::time::Duration;

use serde::Serialize;
use sqlx::Row;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous};

use crate::recognize::Template;
use crate::service::SubjectId;

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
}

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
#[derive(Debug, Clone)]
pub struct Store {
    pool: SqlitePool,
}

impl Store {
    /// Open (creating if missing) the SQLite database at `url` and apply the migrations.
    pub async fn connect(url: &str) -> Result<Store, StoreError> {
        let options = SqliteConnectOptions::from_str(url)
            .map_err(|source| StoreError::Url { url: url.to_string(), source })?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // WAL makes NORMAL durable against application crashes; only a power loss may lose
            // the last transactions, never corrupt the file.
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(5));
        let pool = SqlitePoolOptions::new().max_connections(8).connect_with(options).await?;
        sqlx::migrate!("./migrations").run(&pool).await?;
        Ok(Store { pool })
    }

    /// Is the database answering?
    pub async fn ping(&self) -> Result<(), StoreError> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// Add `templates` to `subject` (created if new), all in one transaction.
    /// Returns the subject's template count afterwards.
    pub async fn enroll(&self, subject: &SubjectId, templates: &[Template]) -> Result<u32, StoreError> {
        let mut tx = self.pool.begin().await?;
        sqlx::query(
            "INSERT INTO subjects (id) VALUES (?1)
             ON CONFLICT (id) DO UPDATE SET updated_at = strftime('%Y-%m-%dT%H:%M:%fZ', 'now')",
        )
        .bind(subject.as_str())
        .execute(&mut *tx)
        .await?;
        for template in templates {
            sqlx::query("INSERT INTO templates (subject_id, model_version, dimension, vector) VALUES (?1, ?2, ?3, ?4)")
                .bind(subject.as_str())
                .bind(&template.model_version)
                .bind(template.vector.len() as i64)
                .bind(vector_to_blob(&template.vector))
                .execute(&mut *tx)
                .await?;
        }
        let count: i64 =
            sqlx::query_scalar("SELECT count(*) FROM templates WHERE subject_id = ?1").bind(subject.as_str()).fetch_one(&mut *tx).await?;
        tx.commit().await?;
        Ok(count as u32)
    }

    /// All templates of `subject`, or `None` when the subject is unknown.
    pub async fn templates(&self, subject: &SubjectId) -> Result<Option<Vec<Template>>, StoreError> {
        let mut tx = self.pool.begin().await?;
        let exists: Option<i64> =
            sqlx::query_scalar("SELECT 1 FROM subjects WHERE id = ?1").bind(subject.as_str()).fetch_optional(&mut *tx).await?;
        if exists.is_none() {
            return Ok(None);
        }
        let rows = sqlx::query("SELECT id, model_version, dimension, vector FROM templates WHERE subject_id = ?1 ORDER BY id")
            .bind(subject.as_str())
            .fetch_all(&mut *tx)
            .await?;
        tx.commit().await?;
        rows.iter().map(template_from_row).collect::<Result<Vec<_>, _>>().map(Some)
    }

    /// Every subject's templates made by `model_version`, grouped by subject (ordered by id).
    /// Subjects without such templates are left out.
    pub async fn gallery(&self, model_version: &str) -> Result<Vec<(String, Vec<Template>)>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, subject_id, model_version, dimension, vector FROM templates
             WHERE model_version = ?1 ORDER BY subject_id, id",
        )
        .bind(model_version)
        .fetch_all(&self.pool)
        .await?;
        let mut gallery: Vec<(String, Vec<Template>)> = Vec::new();
        for row in &rows {
            let subject: String = row.try_get("subject_id")?;
            let template = template_from_row(row)?;
            match gallery.last_mut() {
                Some((last, templates)) if *last == subject => templates.push(template),
                _ => gallery.push((subject, vec![template])),
            }
        }
        Ok(gallery)
    }

    /// Subjects ordered by id, at most `limit` of them, starting after the id `after`.
    pub async fn list_subjects(&self, after: Option<&SubjectId>, limit: u32) -> Result<Vec<SubjectSummary>, StoreError> {
        let rows = sqlx::query(
            "SELECT s.id, s.created_at, s.updated_at, count(t.id) AS templates
             FROM subjects s LEFT JOIN templates t ON t.subject_id = s.id
             WHERE s.id > ?1 GROUP BY s.id ORDER BY s.id LIMIT ?2",
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
            sqlx::query("SELECT id, created_at, updated_at FROM subjects WHERE id = ?1").bind(id.as_str()).fetch_optional(&mut *tx).await?
        else {
            return Ok(None);
        };
        let versions = sqlx::query(
            "SELECT model_version, count(*) AS n FROM templates WHERE subject_id = ?1 GROUP BY model_version ORDER BY model_version",
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

    /// Erase a subject and all its templates. Returns how many templates were erased, or `None`
    /// when the subject is unknown.
    pub async fn delete_subject(&self, id: &SubjectId) -> Result<Option<u32>, StoreError> {
        let mut tx = self.pool.begin().await?;
        let templates: i64 =
            sqlx::query_scalar("SELECT count(*) FROM templates WHERE subject_id = ?1").bind(id.as_str()).fetch_one(&mut *tx).await?;
        let deleted = sqlx::query("DELETE FROM subjects WHERE id = ?1").bind(id.as_str()).execute(&mut *tx).await?.rows_affected();
        tx.commit().await?;
        Ok((deleted > 0).then_some(templates as u32))
    }

    /// Number of subjects and of templates (for metrics and health).
    pub async fn counts(&self) -> Result<(u64, u64), StoreError> {
        let row =
            sqlx::query("SELECT (SELECT count(*) FROM subjects) AS s, (SELECT count(*) FROM templates) AS t").fetch_one(&self.pool).await?;
        Ok((row.try_get::<i64, _>("s")? as u64, row.try_get::<i64, _>("t")? as u64))
    }

    /// Close the pool, checkpointing the WAL.
    pub async fn close(&self) {
        self.pool.close().await;
    }
}

/// Little-endian f32s, the on-disk form of a template vector.
pub fn vector_to_blob(vector: &[f32]) -> Vec<u8> {
    vector.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Inverse of [`vector_to_blob`]; `None` when the length is not a multiple of 4.
pub fn blob_to_vector(blob: &[u8]) -> Option<Vec<f32>> {
    (blob.len() % 4 == 0).then(|| blob.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

fn template_from_row(row: &sqlx::sqlite::SqliteRow) -> Result<Template, StoreError> {
    let id: i64 = row.try_get("id")?;
    let dimension: i64 = row.try_get("dimension")?;
    let blob: Vec<u8> = row.try_get("vector")?;
    let vector = blob_to_vector(&blob).ok_or_else(|| StoreError::CorruptTemplate { id, message: format!("{} bytes", blob.len()) })?;
    if vector.len() as i64 != dimension {
        return Err(StoreError::CorruptTemplate { id, message: format!("{} values, {dimension} expected", vector.len()) });
    }
    Ok(Template { model_version: row.try_get("model_version")?, vector })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(s: &str) -> SubjectId {
        SubjectId::parse(s).unwrap()
    }

    fn template(version: &str, v: &[f32]) -> Template {
        Template { model_version: version.into(), vector: v.to_vec() }
    }

    async fn temp_store() -> (Store, std::path::PathBuf) {
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!(
            "facegate-store-{}-{}",
            std::process::id(),
            N.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let url = format!("sqlite://{}", dir.join("t.db").display());
        (Store::connect(&url).await.unwrap(), dir)
    }

    #[test]
    fn blobs_round_trip_little_endian() {
        let v = [1.0f32, -0.5, 3.25e-7, f32::MAX];
        let blob = vector_to_blob(&v);
        assert_eq!(&blob[..4], &1.0f32.to_le_bytes());
        assert_eq!(blob_to_vector(&blob).unwrap(), v);
        assert!(blob_to_vector(&blob[..5]).is_none());
    }

    #[tokio::test]
    async fn enrol_list_read_and_delete() {
        let (store, dir) = temp_store().await;
        assert_eq!(store.enroll(&id("alice"), &[template("m1", &[1.0, 0.0]), template("m1", &[0.0, 1.0])]).await.unwrap(), 2);
        assert_eq!(store.enroll(&id("alice"), &[template("m2", &[0.5, 0.5, 0.0])]).await.unwrap(), 3);
        assert_eq!(store.enroll(&id("bob"), &[template("m1", &[0.6, 0.8])]).await.unwrap(), 1);

        let alice = store.templates(&id("alice")).await.unwrap().unwrap();
        assert_eq!(alice.len(), 3);
        assert_eq!(alice[2], template("m2", &[0.5, 0.5, 0.0]));
        assert!(store.templates(&id("carol")).await.unwrap().is_none());

        let gallery = store.gallery("m1").await.unwrap();
        assert_eq!(gallery.iter().map(|(s, t)| (s.as_str(), t.len())).collect::<Vec<_>>(), [("alice", 2), ("bob", 1)]);

        let list = store.list_subjects(None, 10).await.unwrap();
        assert_eq!(list.iter().map(|s| (s.id.as_str(), s.templates)).collect::<Vec<_>>(), [("alice", 3), ("bob", 1)]);
        assert_eq!(store.list_subjects(Some(&id("alice")), 10).await.unwrap().len(), 1);
        assert_eq!(store.list_subjects(None, 1).await.unwrap().len(), 1);

        let detail = store.subject(&id("alice")).await.unwrap().unwrap();
        assert_eq!(detail.templates, 3);
        assert_eq!(
            detail.model_versions,
            [VersionCount { model_version: "m1".into(), templates: 2 }, VersionCount { model_version: "m2".into(), templates: 1 }]
        );

        assert_eq!(store.delete_subject(&id("alice")).await.unwrap(), Some(3));
        assert_eq!(store.delete_subject(&id("alice")).await.unwrap(), None);
        // Foreign keys cascade: no orphan template is left.
        assert_eq!(store.counts().await.unwrap(), (1, 1));
        store.close().await;
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[tokio::test]
    async fn a_failed_enrolment_stores_nothing() {
        let (store, dir) = temp_store().await;
        // The second template violates the schema (empty vector): the whole enrolment rolls back.
        let err = store.enroll(&id("alice"), &[template("m1", &[1.0]), template("m1", &[])]).await;
        assert!(err.is_err());
        assert!(store.templates(&id("alice")).await.unwrap().is_none());
        assert_eq!(store.counts().await.unwrap(), (0, 0));
        let mode: String = sqlx::query_scalar("PRAGMA journal_mode").fetch_one(&store.pool).await.unwrap();
        assert_eq!(mode, "wal");
        store.close().await;
        std::fs::remove_dir_all(dir).unwrap();
    }
}
