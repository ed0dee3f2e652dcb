//! How a template's vector is stored: plain (little-endian f32s) or sealed under its subject's
//! data key ([`crate::cipher`]), as the subject's row says ([`Sealing`]). Reading checks what was
//! stored: a sealed vector must authenticate, a plain one must have its dimension's length.
//!
//! Before a service takes requests it asks [`Store::check_template_keys`] whether the configured
//! keys open what the database holds, so that a sealed database started without its key (or with
//! another one) is refused at start-up instead of answering 500 for every sealed subject and
//! storing new enrolments plain.

use serde::Serialize;
use sqlx::any::AnyRow;
use sqlx::{AnyConnection, Row};

use facegate_core::template::Template;

use crate::cipher::{CipherError, DataKey, KeyRing};
use crate::{Store, StoreError};

/// What the configured template keys can do with the subjects sealed in the database
/// ([`Store::check_template_keys`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeyCheck {
    /// No subject is sealed: there is nothing a key must open.
    NothingSealed,
    /// `sealed_subjects` are sealed, and for every master key id they name, a sampled wrapped data
    /// key opens with the configured keys.
    Opens { sealed_subjects: u64 },
    /// `sealed_subjects` are sealed, and no template key is configured.
    NoKey { sealed_subjects: u64 },
    /// `subjects` subjects are sealed under the master key `key_id`, and the configured keys open
    /// none of their sampled data keys (`reason`: the key is not in the key file, or the
    /// wrapped keys do not authenticate under it).
    CannotOpen { key_id: String, subjects: u64, reason: CipherError },
}

/// How the subjects' templates are stored, counted by subject ([`Store::sealing_counts`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct SealingCounts {
    /// Subjects whose template vectors are stored plain (enrolled without a key and not yet
    /// sealed by `facegate rekey`).
    pub plain: u64,
    /// Subjects whose data key is wrapped by the current template key.
    pub current_key: u64,
    /// Subjects whose data key is wrapped by another master key (an older key of the key file
    /// that `facegate rekey` has not yet replaced): that key must stay in the file, and copies
    /// of the database made before keep opening with it.
    pub other_keys: u64,
}

/// Wrapped data keys tried per master key id by [`Store::check_template_keys`]: one that opens
/// proves the key; several, so that one damaged row (refused on its own when read) does not read
/// as a wrong key.
const KEY_CHECK_SAMPLES: i64 = 3;

impl Store {
    /// The id of the current template key (16 hex digits of a SHA-256 of it), if one is
    /// configured. It names the key without revealing it.
    pub fn template_key_id(&self) -> Option<&str> {
        self.keys.as_deref().map(KeyRing::current_id)
    }

    /// Does the database hold sealed templates: any subject with a wrapped data key (or a master
    /// key id), whose vectors then open only with that master key?
    pub async fn holds_sealed_templates(&self) -> Result<bool, StoreError> {
        let sealed: Option<String> = sqlx::query_scalar("SELECT id FROM subjects WHERE key_id IS NOT NULL OR data_key IS NOT NULL LIMIT 1")
            .fetch_optional(&self.pool)
            .await?;
        Ok(sealed.is_some())
    }

    /// Can the configured template keys open what the database holds? For each master key id the
    /// sealed subjects name, up to three wrapped data keys (the first subjects by id) are
    /// unwrapped with the key ring; one that opens proves the key. Nothing is decrypted beyond
    /// the data keys, and nothing is written. A service runs this before it takes requests and
    /// refuses to start on anything but [`KeyCheck::NothingSealed`] and [`KeyCheck::Opens`].
    pub async fn check_template_keys(&self) -> Result<KeyCheck, StoreError> {
        let sealed: i64 = sqlx::query_scalar("SELECT count(*) FROM subjects WHERE key_id IS NOT NULL OR data_key IS NOT NULL")
            .fetch_one(&self.pool)
            .await?;
        let sealed_subjects = sealed as u64;
        if sealed_subjects == 0 {
            return Ok(KeyCheck::NothingSealed);
        }
        let Some(keys) = &self.keys else { return Ok(KeyCheck::NoKey { sealed_subjects }) };
        let groups = sqlx::query("SELECT key_id, count(*) AS n FROM subjects WHERE key_id IS NOT NULL GROUP BY key_id ORDER BY key_id")
            .fetch_all(&self.pool)
            .await?;
        for group in &groups {
            let key_id: String = group.try_get("key_id")?;
            let subjects = group.try_get::<i64, _>("n")? as u64;
            let samples = sqlx::query("SELECT id, data_key FROM subjects WHERE key_id = $1 AND data_key IS NOT NULL ORDER BY id LIMIT $2")
                .bind(&key_id)
                .bind(KEY_CHECK_SAMPLES)
                .fetch_all(&self.pool)
                .await?;
            let mut reason = CipherError::Authentication;
            let mut opened = false;
            for sample in &samples {
                let (subject, wrapped): (String, Vec<u8>) = (sample.try_get("id")?, sample.try_get("data_key")?);
                match keys.unwrap(&subject, &key_id, &wrapped) {
                    Ok(_) => {
                        opened = true;
                        break;
                    }
                    Err(e) => reason = e,
                }
            }
            if !opened {
                return Ok(KeyCheck::CannotOpen { key_id, subjects, reason });
            }
        }
        Ok(KeyCheck::Opens { sealed_subjects })
    }

    /// Subjects by how their templates are stored: plain, under the current key, under another.
    pub async fn sealing_counts(&self) -> Result<SealingCounts, StoreError> {
        let current = self.template_key_id().unwrap_or("");
        let row = sqlx::query(
            "SELECT count(CASE WHEN key_id IS NULL THEN 1 END) AS plain,
                    count(CASE WHEN key_id = $1 THEN 1 END) AS current_key,
                    count(CASE WHEN key_id <> $1 THEN 1 END) AS other_keys
             FROM subjects",
        )
        .bind(current)
        .fetch_one(&self.pool)
        .await?;
        let count = |name: &str| row.try_get::<i64, _>(name).map(|n| n as u64);
        Ok(SealingCounts { plain: count("plain")?, current_key: count("current_key")?, other_keys: count("other_keys")? })
    }
}

/// How one subject's vectors are stored.
pub(crate) enum Sealing {
    Plain,
    Sealed(DataKey),
}

impl Store {
    /// How `subject`'s vectors are stored, from its row's key id and wrapped data key.
    pub(crate) fn sealing(&self, subject: &str, key_id: Option<&str>, wrapped: Option<&[u8]>) -> Result<Sealing, StoreError> {
        let (Some(key_id), Some(wrapped)) = (key_id, wrapped) else {
            return Ok(Sealing::Plain);
        };
        let keys = self.keys.as_ref().ok_or_else(|| StoreError::NoKey { subject: subject.to_string() })?;
        keys.unwrap(subject, key_id, wrapped)
            .map(Sealing::Sealed)
            .map_err(|source| StoreError::DataKey { subject: subject.to_string(), source })
    }
}

/// Give `subject` a new data key (wrapped by the current key) and seal its plain templates under
/// it, inside `tx`. Returns the key and how many templates were sealed.
pub(crate) async fn seal_subject(tx: &mut AnyConnection, keys: &KeyRing, subject: &str) -> Result<(DataKey, u64), StoreError> {
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

/// The stored bytes of `template`'s vector, as `sealing` says.
pub(crate) fn encode_vector(sealing: &Sealing, subject: &str, template: &Template) -> Vec<u8> {
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
    if !blob.len().is_multiple_of(4) {
        return None;
    }
    // Filled in place rather than collected: the loop compiles to a copy (the gallery's start-up
    // decodes ten million of these).
    let mut vector = vec![0.0f32; blob.len() / 4];
    for (v, c) in vector.iter_mut().zip(blob.chunks_exact(4)) {
        *v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    Some(vector)
}

/// A template row of `subject` read as its `sealing` says: a sealed vector must authenticate, a
/// plain one must have exactly its dimension's length (a sealed vector on a plain subject, or the
/// reverse, is refused: rows were moved or altered).
pub(crate) fn template_from_row(sealing: &Sealing, subject: &str, row: &AnyRow) -> Result<Template, StoreError> {
    let blob: Vec<u8> = row.try_get("vector")?;
    open_vector(sealing, subject, row.try_get("id")?, row.try_get("dimension")?, row.try_get("model_version")?, &blob)
}

/// [`template_from_row`] on the row's values.
pub(crate) fn open_vector(
    sealing: &Sealing,
    subject: &str,
    id: i64,
    dimension: i64,
    model_version: String,
    blob: &[u8],
) -> Result<Template, StoreError> {
    let corrupt = |message: String| StoreError::CorruptTemplate { id, message };
    let vector = match sealing {
        Sealing::Plain => {
            let vector = blob_to_vector(blob).ok_or_else(|| corrupt(format!("{} bytes", blob.len())))?;
            if vector.len() as i64 != dimension {
                return Err(corrupt(format!("{} values, {dimension} expected", vector.len())));
            }
            vector
        }
        Sealing::Sealed(key) => {
            key.open_template(subject, &model_version, dimension as usize, blob).map_err(|e| corrupt(format!("subject {subject}: {e}")))?
        }
    };
    Ok(Template { model_version, vector })
}

/// A gallery row as stored (a template with its subject's key columns), before its vector is
/// opened, borrowed from the row it was read from: what both the sqlx reads and SQLite's bulk scan
/// ([`crate::sqlite_scan`]) hand to [`Store::group_by_subject`](crate::Store), which copies only
/// what it keeps.
pub(crate) struct StoredRow<'r> {
    pub id: i64,
    pub subject: &'r str,
    pub model_version: &'r str,
    pub dimension: i64,
    pub vector: &'r [u8],
    pub key_id: Option<&'r str>,
    pub data_key: Option<&'r [u8]>,
}

impl<'r> StoredRow<'r> {
    /// The columns `id, subject_id, model_version, dimension, vector, key_id, data_key`, in that
    /// order (by position: a lookup by name per column and row showed in the start-up load's profile).
    pub fn of(row: &'r AnyRow) -> Result<StoredRow<'r>, sqlx::Error> {
        Ok(StoredRow {
            id: row.try_get(0)?,
            subject: row.try_get(1)?,
            model_version: row.try_get(2)?,
            dimension: row.try_get(3)?,
            vector: row.try_get(4)?,
            key_id: row.try_get(5)?,
            data_key: row.try_get(6)?,
        })
    }
}
