//! How a template's vector is stored: plain (little-endian f32s) or sealed under its subject's
//! data key ([`crate::cipher`]), as the subject's row says ([`Sealing`]). Reading checks what was
//! stored: a sealed vector must authenticate, a plain one must have its dimension's length.

use sqlx::any::AnyRow;
use sqlx::{AnyConnection, Row};

use facegate_vision::recognize::Template;

use crate::cipher::{DataKey, KeyRing};
use crate::{Store, StoreError};

/// How one subject's vectors are stored.
pub(crate) enum Sealing {
    Plain,
    Sealed(DataKey),
}

impl Store {
    /// How `subject`'s vectors are stored, from its row's key id and wrapped data key.
    pub(crate) fn sealing(&self, subject: &str, key_id: Option<String>, wrapped: Option<Vec<u8>>) -> Result<Sealing, StoreError> {
        let (Some(key_id), Some(wrapped)) = (key_id, wrapped) else {
            return Ok(Sealing::Plain);
        };
        let keys = self.keys.as_ref().ok_or_else(|| StoreError::NoKey { subject: subject.to_string() })?;
        keys.unwrap(subject, &key_id, &wrapped)
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
    (blob.len() % 4 == 0).then(|| blob.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
}

/// A template row of `subject` read as its `sealing` says: a sealed vector must authenticate, a
/// plain one must have exactly its dimension's length (a sealed vector on a plain subject, or the
/// reverse, is refused: rows were moved or altered).
pub(crate) fn template_from_row(sealing: &Sealing, subject: &str, row: &AnyRow) -> Result<Template, StoreError> {
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
