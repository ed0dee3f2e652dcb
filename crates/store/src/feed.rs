//! The change feed: how processes sharing a PostgreSQL database (replicas) follow each other's
//! enrolments and deletions. Every writing transaction bumps a one-row change counter and
//! notifies its new value with the subject ([`Notice`] on [`CHANGE_CHANNEL`]); both take effect
//! at commit, so the versions are in commit order. A [`ChangeFeed`] listens on a connection of its
//! own and reports a lost connection as [`StoreChange::Resync`]. On SQLite one process owns the
//! file: there is no counter and no feed.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use sqlx::AnyConnection;
use sqlx::postgres::{PgListener, PgPoolOptions};

use crate::{Backend, Store, StoreError};

/// The PostgreSQL channel every enrolment and deletion notifies (payload: [`Notice`]).
const CHANGE_CHANNEL: &str = "facegate_changes";

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

impl Store {
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
    pub(crate) async fn record_change(&self, tx: &mut AnyConnection, subject: &str) -> Result<(), StoreError> {
        if self.backend == Backend::Postgres {
            let version: i64 = sqlx::query_scalar("UPDATE change_counter SET n = n + 1 RETURNING n").fetch_one(&mut *tx).await?;
            let notice = serde_json::to_string(&Notice { subject: subject.to_string(), version }).expect("a notice serialises");
            sqlx::query("SELECT pg_notify($1, $2)").bind(CHANGE_CHANNEL).bind(notice).execute(&mut *tx).await?;
        }
        Ok(())
    }
}

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
