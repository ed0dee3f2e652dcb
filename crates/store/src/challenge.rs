//! Open liveness challenges: the steps the service drew for each (its JSON text, which the store
//! keeps as is), until one verification takes the row or it expires. Taking is a single
//! `DELETE … RETURNING`, so of two replicas answering the same challenge at once exactly one gets
//! it: a challenge is used once, on whichever replica.

use crate::{Store, StoreError};

/// A challenge taken from the store: its steps (the service's JSON text) and when it expired or
/// expires, in milliseconds since the Unix epoch.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TakenChallenge {
    pub steps: String,
    pub expires_at_ms: i64,
}

impl Store {
    /// Keep the challenge `id` with its `steps` until `expires_at_ms`. Challenges that expired
    /// before `now_ms` are removed on the way, so the table holds only open ones and their number
    /// stays bounded by the issue rate times their lifetime.
    pub async fn insert_challenge(&self, id: &str, steps: &str, expires_at_ms: i64, now_ms: i64) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM liveness_challenges WHERE expires_at < $1").bind(now_ms).execute(&self.pool).await?;
        sqlx::query("INSERT INTO liveness_challenges (id, steps, expires_at) VALUES ($1, $2, $3)")
            .bind(id)
            .bind(steps)
            .bind(expires_at_ms)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Take the challenge `id` out of the store: its row is deleted and returned, whether or not it
    /// has expired (the caller judges that). `None` when there is no such challenge: never issued,
    /// already taken, or swept after it expired.
    pub async fn take_challenge(&self, id: &str) -> Result<Option<TakenChallenge>, StoreError> {
        let row: Option<(String, i64)> = sqlx::query_as("DELETE FROM liveness_challenges WHERE id = $1 RETURNING steps, expires_at")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.map(|(steps, expires_at_ms)| TakenChallenge { steps, expires_at_ms }))
    }

    /// Open challenges in the store (expired ones not yet swept included).
    pub async fn challenges_open(&self) -> Result<u64, StoreError> {
        let count: i64 = sqlx::query_scalar("SELECT count(*) FROM liveness_challenges").fetch_one(&self.pool).await?;
        Ok(count as u64)
    }
}
