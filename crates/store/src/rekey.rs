//! Every subject brought under the template key ring's current key (`facegate rekey`): data keys
//! wrapped by an older key re-wrapped, plain subjects sealed ([`Store::rekey`]).

use serde::Serialize;
use sqlx::Row;

use crate::codec::{Sealing, seal_subject};
use crate::{Store, StoreError};

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

impl Store {
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
}
