//! Open liveness challenges: the steps the service drew for each (its JSON text, which the store
//! keeps as is), until one verification takes the row or it expires. Taking is a single
//! `DELETE … RETURNING`, so of two replicas answering the same challenge at once exactly one gets
//! it: a challenge is used once, on whichever replica.

use crate::{Store, StoreError};

/// Most expired challenges one issue removes: the sweep's cost per issue stays bounded however
/// many have expired (one issue adds one row and removes up to this many, so expired rows never
/// pile up while challenges are issued).
pub const SWEEP_BATCH: i64 = 256;

/// A challenge taken from the store: its steps (the service's JSON text) and when it expired or
/// expires, in milliseconds since the Unix epoch.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TakenChallenge {
    pub steps: String,
    pub expires_at_ms: i64,
}

impl Store {
    /// Keep the challenge `id` with its `steps` until `expires_at_ms`, however many are open
    /// ([`Store::insert_challenge_within`] without a cap).
    pub async fn insert_challenge(&self, id: &str, steps: &str, expires_at_ms: i64, now_ms: i64) -> Result<(), StoreError> {
        self.insert_challenge_within(id, steps, expires_at_ms, now_ms, u64::MAX).await.map(drop)
    }

    /// Keep the challenge `id` with its `steps` until `expires_at_ms`, unless `max_open`
    /// challenges that have not expired at `now_ms` are already kept: whether it was stored. Up to
    /// [`SWEEP_BATCH`] challenges that expired before `now_ms` are removed first, so the table
    /// holds at most `max_open` open challenges and a bounded number of expired ones. The count
    /// and the insert are one statement (on SQLite one writer at a time: the cap is exact; on
    /// PostgreSQL replicas inserting at the same instant may pass it by their number).
    pub async fn insert_challenge_within(
        &self,
        id: &str,
        steps: &str,
        expires_at_ms: i64,
        now_ms: i64,
        max_open: u64,
    ) -> Result<bool, StoreError> {
        self.still_there()?;
        sqlx::query("DELETE FROM liveness_challenges WHERE id IN (SELECT id FROM liveness_challenges WHERE expires_at < $1 LIMIT $2)")
            .bind(now_ms)
            .bind(SWEEP_BATCH)
            .execute(&self.pool)
            .await?;
        let inserted = sqlx::query(
            "INSERT INTO liveness_challenges (id, steps, expires_at) SELECT $1, $2, $3
             WHERE (SELECT count(*) FROM liveness_challenges WHERE expires_at >= $4) < $5",
        )
        .bind(id)
        .bind(steps)
        .bind(expires_at_ms)
        .bind(now_ms)
        .bind(i64::try_from(max_open).unwrap_or(i64::MAX))
        .execute(&self.pool)
        .await?;
        Ok(inserted.rows_affected() == 1)
    }

    /// When the first of the challenges still open at `now_ms` expires (milliseconds since the
    /// Unix epoch), or `None` when none is open: when a full table next has room.
    pub async fn next_challenge_expiry(&self, now_ms: i64) -> Result<Option<i64>, StoreError> {
        let first: Option<i64> = sqlx::query_scalar("SELECT min(expires_at) FROM liveness_challenges WHERE expires_at >= $1")
            .bind(now_ms)
            .fetch_one(&self.pool)
            .await?;
        Ok(first)
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
