//! The gallery's reads, the same on both backends: every subject's templates of one model version
//! streamed in subject id order ([`Store::gallery`]), cut into parts that several connections
//! read at once ([`crate::gallery_part`], [`Store::gallery_parts`], [`Store::gallery_part`]; on a SQLite
//! file through [`crate::sqlite_scan`]), and the templates of a few subjects
//! ([`Store::templates_of`]).

use std::sync::Arc;

use futures_util::TryStreamExt;

use facegate_core::SubjectId;
use facegate_core::template::Template;

use crate::codec::{Sealing, StoredRow, open_vector};
use crate::gallery_part::{GalleryPart, gallery_statement};
use crate::{Backend, Store, StoreError, sqlite_scan};

/// A subject being read by [`Store::gallery`]: its id, how its vectors are stored (none when its
/// data key cannot be opened), and its templates so far or why they cannot be read.
type SubjectReading = (String, Option<Sealing>, Result<Vec<Template>, StoreError>);

/// Sets its flag when dropped: tells a blocking reader that its caller is gone.
struct AbandonOnDrop(Arc<std::sync::atomic::AtomicBool>);

impl Drop for AbandonOnDrop {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

impl Store {
    /// Every subject's templates made by `model_version`, handed to `each` with `state` one
    /// subject at a time in subject id order (rows are streamed, so the whole gallery is never
    /// held twice); returns `state`. A subject whose templates cannot be read is handed its error;
    /// the scan goes on.
    pub async fn gallery<S, F>(&self, model_version: &str, state: S, each: F) -> Result<S, StoreError>
    where
        S: Send + 'static,
        F: FnMut(&mut S, &str, Result<Vec<Template>, StoreError>) + Send + 'static,
    {
        self.gallery_part(model_version, &GalleryPart::default(), state, each).await
    }

    /// Subject ids that cut `model_version`'s templates into up to `parts` parts of about equal
    /// size ([`GalleryPart::between`]), so that the gallery can be read by several connections at
    /// once ([`Store::gallery_part`]). One count and `parts − 1` index lookups.
    pub async fn gallery_parts(&self, model_version: &str, parts: usize) -> Result<Vec<GalleryPart>, StoreError> {
        let count: i64 =
            sqlx::query_scalar("SELECT count(*) FROM templates WHERE model_version = $1").bind(model_version).fetch_one(&self.pool).await?;
        let mut cuts: Vec<String> = Vec::new();
        for i in 1..parts.max(1) as i64 {
            let cut: Option<String> =
                sqlx::query_scalar("SELECT subject_id FROM templates WHERE model_version = $1 ORDER BY subject_id LIMIT 1 OFFSET $2")
                    .bind(model_version)
                    .bind(count * i / parts as i64)
                    .fetch_optional(&self.pool)
                    .await?;
            // A subject's rows stay in one part: parts end at a subject, inclusive.
            if let Some(cut) = cut.filter(|c| cuts.last().is_none_or(|last| last < c)) {
                cuts.push(cut);
            }
        }
        let mut parts = GalleryPart::between(&cuts);
        let share = count.max(0) as usize / parts.len();
        parts.iter_mut().for_each(|p| p.expected_templates = share);
        Ok(parts)
    }

    /// [`Store::gallery`] for the subjects of one part only. On a SQLite file the rows are read
    /// through SQLite's C API on a blocking thread, which also runs `each` (so `state` moves there
    /// and back: no row crosses threads); else through the pool.
    pub async fn gallery_part<S, F>(&self, model_version: &str, part: &GalleryPart, mut state: S, mut each: F) -> Result<S, StoreError>
    where
        S: Send + 'static,
        F: FnMut(&mut S, &str, Result<Vec<Template>, StoreError>) + Send + 'static,
    {
        if let Some(path) = &self.sqlite_file {
            // Set when this future is dropped, so that an abandoned load stops reading.
            let abandoned = Arc::new(std::sync::atomic::AtomicBool::new(false));
            let _abandon_on_drop = AbandonOnDrop(abandoned.clone());
            let (store, file, version, part) = (self.clone(), path.clone(), model_version.to_string(), part.clone());
            let read = tokio::task::spawn_blocking(move || {
                let mut current = None;
                let mut hand = |subject: &str, templates| each(&mut state, subject, templates);
                sqlite_scan::read_gallery_part(&file, &version, &part, |row| {
                    store.group_by_subject(&mut current, row, &mut hand);
                    !abandoned.load(std::sync::atomic::Ordering::Relaxed)
                })?;
                if let Some((done, _, templates)) = current.take() {
                    hand(&done, templates);
                }
                Ok(state)
            })
            .await
            .expect("the SQLite gallery reader does not panic");
            return read.map_err(|e: String| StoreError::Refused(format!("reading the gallery from {}: {e}", path.display())));
        }
        let statement = gallery_statement(part, |n| format!("${n}"));
        let mut query = sqlx::query(&statement).bind(model_version).bind(part.after.as_deref().unwrap_or(""));
        if let Some(through) = &part.through {
            query = query.bind(through.as_str());
        }
        let mut tx = self.pool.begin().await?;
        if self.backend == Backend::Postgres {
            // Read in the index's order (model version, subject, id): PostgreSQL's planner
            // otherwise scans the whole table and sorts the part's rows, per part (docs/gallery.md,
            // start-up: 64 s against 30 s at ten million).
            sqlx::query("SET LOCAL enable_sort = off").execute(&mut *tx).await?;
        }
        self.each_subject(query.fetch(&mut *tx), |subject, templates| each(&mut state, subject, templates)).await?;
        tx.commit().await.map_err(StoreError::of_commit)?;
        Ok(state)
    }

    /// The templates of `model_version` of each of `subjects` that holds any, in subject id
    /// order (bytewise on both backends), in one statement: the identification's exact re-scoring of its shortlist. A
    /// subject whose templates cannot be read fails the read, as in [`Store::templates`].
    pub async fn templates_of(&self, subjects: &[SubjectId], model_version: &str) -> Result<Vec<(String, Vec<Template>)>, StoreError> {
        if subjects.is_empty() {
            return Ok(Vec::new());
        }
        let placeholders: Vec<String> = (2..subjects.len() + 2).map(|i| format!("${i}")).collect();
        let statement = format!(
            "SELECT t.id, t.subject_id, t.model_version, t.dimension, t.vector, s.key_id, s.data_key
             FROM templates t JOIN subjects s ON s.id = t.subject_id
             WHERE t.model_version = $1 AND t.subject_id IN ({})
             ORDER BY t.subject_id, t.id",
            placeholders.join(", ")
        );
        let query = subjects.iter().fold(sqlx::query(&statement).bind(model_version), |q, s| q.bind(s.as_str()));
        let mut found = Vec::with_capacity(subjects.len());
        let mut failed = None;
        self.each_subject(query.fetch(&self.pool), |subject, templates| match templates {
            Ok(templates) => found.push((subject.to_string(), templates)),
            Err(e) => failed = failed.take().or(Some(e)),
        })
        .await?;
        failed.map_or(Ok(found), Err)
    }

    /// Template rows (ordered by subject) handed to `each` one subject at a time, opened with the
    /// subject's sealing; a subject whose key or a template cannot be opened is handed its error.
    async fn each_subject(
        &self,
        mut rows: impl futures_util::Stream<Item = Result<sqlx::any::AnyRow, sqlx::Error>> + Unpin,
        mut each: impl FnMut(&str, Result<Vec<Template>, StoreError>),
    ) -> Result<(), StoreError> {
        let mut current: Option<SubjectReading> = None;
        while let Some(row) = rows.try_next().await? {
            self.group_by_subject(&mut current, StoredRow::of(&row)?, &mut each);
        }
        if let Some((done, _, templates)) = current.take() {
            each(&done, templates);
        }
        Ok(())
    }

    /// One row of a read ordered by subject: a new subject hands the one before to `each`.
    fn group_by_subject(
        &self,
        current: &mut Option<SubjectReading>,
        row: StoredRow<'_>,
        each: &mut impl FnMut(&str, Result<Vec<Template>, StoreError>),
    ) {
        if current.as_ref().is_none_or(|(s, _, _)| s != row.subject) {
            if let Some((done, _, templates)) = current.take() {
                each(&done, templates);
            }
            *current = Some(match self.sealing(row.subject, row.key_id, row.data_key) {
                Ok(sealing) => (row.subject.to_string(), Some(sealing), Ok(Vec::new())),
                Err(e) => (row.subject.to_string(), None, Err(e)),
            });
        }
        if let Some((subject, Some(sealing), templates @ Ok(_))) = current.as_mut() {
            match open_vector(sealing, subject, row.id, row.dimension, row.model_version.to_string(), row.vector) {
                Ok(template) => templates.as_mut().expect("matched Ok").push(template),
                Err(e) => *templates = Err(e),
            }
        }
    }
}
