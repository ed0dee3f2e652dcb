//! Under connection pressure, the slowest body first. Every request that waits for its body or
//! receives it is a holder ([`Holders::hold`]): its [`Progress`] and a way to cut it. While the
//! server has fewer than a reserve of connections free ([`shed_under_pressure`]), it cuts the
//! holder whose body arrives slowest now (bytes over the last [`RATE_WINDOW`]; a head still
//! waiting for its first byte arrives at 0), one at a time, so that connections held by stalled
//! or crawling bodies turn over and a new client's connection is accepted, while a body arriving
//! at a usual speed is left to finish. A holder younger than [`MIN_AGE`] is never cut: it has not
//! had the time to show its pace. Cut requests are answered 503 `overloaded`, whose detail says
//! why; without pressure nothing is cut (the pace rules of [`crate::intake`] still apply).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use tokio::sync::{Notify, Semaphore};
use tokio::time::Instant;

use crate::intake::Progress;

/// The window over which holders' rates are compared.
pub const RATE_WINDOW: Duration = Duration::from_secs(5);
/// Holders younger than this are never cut.
pub const MIN_AGE: Duration = Duration::from_secs(1);
/// How often the pressure is looked at; one holder is cut per look at most (100 a second): enough
/// for the new clients of a busy server to be accepted, few enough that bodies reopened as soon as
/// they are cut do not turn a slow flood into a flood of connections, each a head to parse.
const CHECK_EVERY: Duration = Duration::from_millis(10);

#[derive(Debug)]
struct Holder {
    progress: Arc<Mutex<Progress>>,
    cut: Arc<Notify>,
}

/// The requests waiting for or receiving their bodies.
#[derive(Debug, Clone, Default)]
pub struct Holders {
    table: Arc<Mutex<HashMap<u64, Holder>>>,
    next: Arc<AtomicU64>,
}

/// A request's place among the holders (left when dropped): its progress, to record what
/// arrives, and the notice it is cut by.
#[derive(Debug)]
pub struct Holding {
    holders: Holders,
    id: u64,
    pub progress: Arc<Mutex<Progress>>,
    pub cut: Arc<Notify>,
}

impl Drop for Holding {
    fn drop(&mut self) {
        self.holders.table.lock().unwrap_or_else(PoisonError::into_inner).remove(&self.id);
    }
}

impl Holders {
    /// A new holder, whose body began (or is awaited) from now.
    pub fn hold(&self) -> Holding {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let progress = Arc::new(Mutex::new(Progress::new(Instant::now(), RATE_WINDOW)));
        let cut = Arc::new(Notify::new());
        let holder = Holder { progress: progress.clone(), cut: cut.clone() };
        self.table.lock().unwrap_or_else(PoisonError::into_inner).insert(id, holder);
        Holding { holders: self.clone(), id, progress, cut }
    }

    /// Cut the slowest holder at least [`MIN_AGE`] old, if any; whether one was cut. It leaves the
    /// table at once, so that the next cut takes the next slowest.
    pub fn cut_slowest(&self, now: Instant) -> bool {
        let mut table = self.table.lock().unwrap_or_else(PoisonError::into_inner);
        let slowest = table
            .iter()
            .filter_map(|(&id, h)| {
                let progress = h.progress.lock().unwrap_or_else(PoisonError::into_inner);
                (progress.age(now) >= MIN_AGE).then(|| (id, progress.recent_rate(now, RATE_WINDOW)))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let Some((id, _)) = slowest else { return false };
        if let Some(holder) = table.remove(&id) {
            holder.cut.notify_one();
        }
        true
    }

    /// Requests holding now (for the tests).
    pub fn len(&self) -> usize {
        self.table.lock().unwrap_or_else(PoisonError::into_inner).len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The free connections below which holders are cut: a sixteenth of the cap (at least one).
pub fn reserve(max_connections: usize) -> usize {
    (max_connections / 16).max(1)
}

/// Forever: while fewer than `reserve` of `connections`' permits are free, cut the slowest
/// holder, one per look.
pub async fn shed_under_pressure(connections: Arc<Semaphore>, holders: Holders, reserve: usize) {
    let mut tick = tokio::time::interval(CHECK_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let free = connections.available_permits();
        if free >= reserve || holders.is_empty() {
            continue;
        }
        holders.cut_slowest(Instant::now());
    }
}

#[cfg(test)]
mod tests {
    use futures_util::FutureExt as _;

    use super::*;

    #[tokio::test(start_paused = true)]
    async fn the_slowest_holder_old_enough_is_cut_first() {
        let holders = Holders::default();
        let (stalled, crawling, fast) = (holders.hold(), holders.hold(), holders.hold());
        tokio::time::advance(Duration::from_millis(500)).await;
        let young = holders.hold();
        tokio::time::advance(Duration::from_millis(700)).await;
        let now = Instant::now();
        crawling.progress.lock().unwrap().arrived(now, 10_000);
        fast.progress.lock().unwrap().arrived(now, 10_000_000);
        // The stalled head goes first, then the crawl; the young one and the fast one stay.
        assert!(holders.cut_slowest(now));
        assert!(stalled.cut.notified().now_or_never().is_some(), "the stalled head was cut");
        assert!(holders.cut_slowest(now));
        assert!(crawling.cut.notified().now_or_never().is_some(), "then the crawl");
        assert!(holders.cut_slowest(now));
        assert!(fast.cut.notified().now_or_never().is_some(), "then the fast body, the last one old enough");
        assert!(!holders.cut_slowest(now), "the young holder is never cut");
        assert!(young.cut.notified().now_or_never().is_none());
        drop((stalled, crawling, fast));
        assert_eq!(holders.len(), 1);
        drop(young);
        assert!(holders.is_empty());
    }

    #[tokio::test(start_paused = true)]
    async fn holders_are_cut_only_while_the_free_connections_are_below_the_reserve() {
        let connections = Arc::new(Semaphore::new(32));
        let holders = Holders::default();
        let held: Vec<Holding> = (0..4).map(|_| holders.hold()).collect();
        tokio::spawn(shed_under_pressure(connections.clone(), holders.clone(), reserve(32)));
        tokio::time::sleep(Duration::from_secs(2)).await;
        assert_eq!(holders.len(), 4, "no pressure, no cut");
        let taken = connections.clone().acquire_many_owned(31).await.unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert!(holders.is_empty(), "one free of 32, below the reserve of 2: every holder old enough is cut");
        assert!(held.iter().all(|h| h.cut.notified().now_or_never().is_some()));
        drop(taken);
        let late = holders.hold();
        tokio::time::sleep(Duration::from_secs(2)).await;
        assert_eq!(holders.len(), 1, "none once connections are free again");
        drop((held, late));
    }
}
