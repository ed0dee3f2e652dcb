//! Receiving a request body as it arrives, before the request takes its place in the work queue
//! (`admission::admit`), so that what a slow client holds is what it has sent:
//!
//! - the body-memory budget ([`BodyBudget`]) is charged for the buffer the arrived bytes fill, not
//!   for the length the head declares;
//! - and per client address: one address holds at most its share of the budget
//!   ([`BodyBudget::new`]'s `per_address_bytes`), so that a few fast-then-stalled bodies from one
//!   client cannot hold the memory every other client's bodies need;
//! - the body keeps a pace ([`Pace`]): after a grace period it must keep a minimum rate over a
//!   window that moves with time (the last grace period's length), and it must be complete within
//!   the body timeout, else 408 — so a trickle is cut after the grace period, a body sent fast and
//!   then stalled a window after it stalled, while a slow steady upload goes on;
//! - at most so many bodies wait for their first byte or arrive at once from one client address
//!   ([`ArrivalSlot`]; IPv6 by its /64), so a few slow clients cannot take the server's
//!   connections and budget from the others;
//! - under connection pressure the slowest body is cut first ([`crate::shedding`]).
//!
//! The bytes are copied into one buffer of the request's own as they arrive: the connection's read
//! buffers are not held by the many small pieces a trickle sends.

use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, Ipv6Addr};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use axum::body::{Body, Bytes};
use http_body_util::BodyExt as _;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;

/// The least room a body's buffer is given at once (less when the declared length is smaller).
const MIN_ROOM: usize = 8 << 10;

/// How fast a body must arrive: all of it within `timeout`; and from `grace` after it began, at
/// least `min_rate` bytes a second over the last `grace` (a moving window: what a body sent before
/// does not pay for a stall now), the amount owed growing from 0 over the first window after the
/// grace period (0: no rate).
#[derive(Debug, Clone, Copy)]
pub struct Pace {
    pub timeout: Duration,
    pub grace: Duration,
    pub min_rate: u64,
}

/// How often a body's rate is checked once it is owed one.
const RATE_CHECK: Duration = Duration::from_millis(250);

/// The bytes a body has received over time: the running total, with a mark per piece kept as long
/// as it is inside the longest window asked about (and the last one before it).
#[derive(Debug)]
pub struct Progress {
    start: Instant,
    received: usize,
    marks: VecDeque<(Instant, usize)>,
    window: Duration,
}

impl Progress {
    /// A body that began at `start`, asked about over windows up to `window`.
    pub fn new(start: Instant, window: Duration) -> Progress {
        Progress { start, received: 0, marks: VecDeque::new(), window }
    }

    /// The body's first byte is here at `at`: the pace counts from it (a request may have been a
    /// holder for a while before, waiting for it), over windows up to `window` at least.
    fn begin(&mut self, at: Instant, window: Duration) {
        (self.start, self.received, self.window) = (at, 0, self.window.max(window));
        self.marks.clear();
    }

    /// `total` bytes received by `at`.
    pub fn arrived(&mut self, at: Instant, total: usize) {
        self.received = total;
        self.marks.push_back((at, total));
        // Keep the last mark at or before the window's start: it says what had arrived by then.
        while self.marks.len() > 1 && self.marks[1].0 + self.window <= at {
            self.marks.pop_front();
        }
    }

    /// Bytes received after `since` (everything when `since` is before the start).
    fn received_after(&self, since: Instant) -> usize {
        let before = self.marks.iter().rev().find(|(at, _)| *at <= since).map_or(0, |&(_, total)| total);
        self.received - before
    }

    /// Whether the body is behind `pace` at `now`: from the end of the grace period, fewer bytes
    /// over the last `grace` than `min_rate` owes (over the time since the grace period ended,
    /// when that is shorter).
    fn behind(&self, pace: &Pace, now: Instant) -> bool {
        let Some(owed_for) = now.checked_duration_since(self.start + pace.grace) else { return false };
        let owed = pace.min_rate as f64 * owed_for.min(pace.grace).as_secs_f64();
        let window_start = now.checked_sub(pace.grace).unwrap_or(self.start);
        (self.received_after(window_start) as f64) < owed
    }

    /// Bytes a second over the last `window` (since the start, when younger): how fast the body
    /// arrives now, which the shedding compares.
    pub fn recent_rate(&self, now: Instant, window: Duration) -> f64 {
        let since = now.checked_sub(window).unwrap_or(self.start).max(self.start);
        let span = now.saturating_duration_since(since).as_secs_f64().max(1e-3);
        self.received_after(since) as f64 / span
    }

    /// How long ago the body began.
    pub fn age(&self, now: Instant) -> Duration {
        now.saturating_duration_since(self.start)
    }
}

/// Why a body was not received.
#[derive(Debug)]
pub enum Cut {
    /// More bytes than the body limit.
    TooLarge,
    /// Not complete within the body timeout.
    TimedOut,
    /// Slower than the minimum rate after the grace period.
    TooSlow,
    /// The body-memory budget cannot hold the bytes that arrived.
    BudgetSpent,
    /// The client address's share of the budget cannot.
    AddressBudgetSpent,
    /// Cut to free a connection: the server is at its connection cap and this body arrived the
    /// slowest ([`crate::shedding`]).
    Shed,
    /// The connection failed (reset, or closed before the declared length).
    Broken(String),
}

/// A body received whole, and its share of the budget (held until the request is answered).
#[derive(Debug)]
pub struct Received {
    pub bytes: Bytes,
    /// Given back to the budget when dropped.
    pub share: Share,
}

/// Bytes of request bodies held in memory at once, in KiB permits (a semaphore counts `u32`s),
/// overall and per client address, and the bodies arriving at once per client address.
#[derive(Debug, Clone)]
pub struct BodyBudget {
    kib: Arc<Semaphore>,
    max_body_bytes: usize,
    per_address_kib: usize,
    held: AddressTally,
    arriving: Arc<Mutex<HashMap<IpAddr, Arc<Semaphore>>>>,
}

impl BodyBudget {
    /// `max_buffered_bytes` in all, of which one client address holds at most `per_address_bytes`.
    pub fn new(max_buffered_bytes: usize, per_address_bytes: usize, max_body_bytes: usize) -> BodyBudget {
        let per_address_kib = kib(per_address_bytes);
        let kib = Arc::new(Semaphore::new(kib(max_buffered_bytes).min(Semaphore::MAX_PERMITS)));
        BodyBudget { kib, max_body_bytes, per_address_kib, held: AddressTally::default(), arriving: Arc::default() }
    }

    /// Grow `share` to cover `bytes`; the cut when the budget or the address's share cannot (the
    /// share is left as it was).
    fn charge(&self, share: &mut Share, bytes: usize) -> Result<(), Cut> {
        let wanted = u32::try_from(kib(bytes)).unwrap_or(u32::MAX);
        let held = share.permit.as_ref().map_or(0, |p| p.num_permits() as u32);
        if wanted <= held {
            return Ok(());
        }
        let more = (wanted - held) as usize;
        if let Some(address) = share.address
            && !self.held.try_add(address, more, self.per_address_kib)
        {
            return Err(Cut::AddressBudgetSpent);
        }
        let Ok(permit) = self.kib.clone().try_acquire_many_owned(more as u32) else {
            if let Some(address) = share.address {
                self.held.sub(address, more);
            }
            return Err(Cut::BudgetSpent);
        };
        share.of_address += more;
        match &mut share.permit {
            Some(held) => held.merge(permit),
            None => share.permit = Some(permit),
        }
        Ok(())
    }

    /// A share of this budget charged to `address` (`None`: to no address).
    pub fn share(&self, address: Option<IpAddr>) -> Share {
        Share { permit: None, address: address.map(client_key), of_address: 0, held: self.held.clone() }
    }

    /// A place among the bodies arriving from `address` (at most `cap` at once), waiting up to
    /// `wait` for one in arrival order; `None` when none came free.
    pub async fn arrival_slot(&self, address: IpAddr, cap: usize, wait: Duration) -> Option<ArrivalSlot> {
        let key = client_key(address);
        let semaphore = {
            let mut arriving = self.arriving.lock().unwrap_or_else(PoisonError::into_inner);
            arriving.entry(key).or_insert_with(|| Arc::new(Semaphore::new(cap.max(1)))).clone()
        };
        // Made before the wait, so that a refused or cancelled request also forgets the address.
        let mut slot = ArrivalSlot { arriving: self.arriving.clone(), key, semaphore, permit: None };
        let acquired = match slot.semaphore.clone().try_acquire_owned() {
            Ok(permit) => Some(permit),
            Err(_) if wait.is_zero() => None,
            Err(_) => tokio::time::timeout(wait, slot.semaphore.clone().acquire_owned()).await.ok().and_then(Result::ok),
        };
        slot.permit = Some(acquired?);
        Some(slot)
    }

    /// Client addresses with a body arriving or waiting for a place (for the tests).
    pub fn addresses_arriving(&self) -> usize {
        self.arriving.lock().unwrap_or_else(PoisonError::into_inner).len()
    }
}

/// A request's place among the bodies arriving from its client address, given back when dropped
/// (the address is forgotten with its last place).
#[derive(Debug)]
pub struct ArrivalSlot {
    arriving: Arc<Mutex<HashMap<IpAddr, Arc<Semaphore>>>>,
    key: IpAddr,
    semaphore: Arc<Semaphore>,
    permit: Option<OwnedSemaphorePermit>,
}

impl Drop for ArrivalSlot {
    fn drop(&mut self) {
        drop(self.permit.take());
        let mut arriving = self.arriving.lock().unwrap_or_else(PoisonError::into_inner);
        // The map's and this slot's: nobody else holds or waits for a place of this address.
        if Arc::strong_count(&self.semaphore) == 2 {
            arriving.remove(&self.key);
        }
    }
}

/// A count per client address (connections, KiB of body budget), each held under a cap; an
/// address counting nothing is forgotten.
#[derive(Debug, Clone, Default)]
pub struct AddressTally(Arc<Mutex<HashMap<IpAddr, usize>>>);

impl AddressTally {
    /// Add `n` to `key`'s count unless that would pass `cap`; whether it was added.
    pub fn try_add(&self, key: IpAddr, n: usize, cap: usize) -> bool {
        let mut counts = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        let count = counts.get(&key).copied().unwrap_or(0);
        if count + n > cap {
            return false;
        }
        counts.insert(key, count + n);
        true
    }

    /// Take `n` back from `key`'s count.
    pub fn sub(&self, key: IpAddr, n: usize) {
        let mut counts = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(count) = counts.get_mut(&key) {
            *count = count.saturating_sub(n);
            if *count == 0 {
                counts.remove(&key);
            }
        }
    }

    /// `key`'s count.
    #[cfg(test)]
    fn count(&self, key: IpAddr) -> usize {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).get(&key).copied().unwrap_or(0)
    }

    /// Whether no address counts anything.
    #[cfg(test)]
    fn is_empty(&self) -> bool {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).is_empty()
    }
}

/// The address a client is counted by: an IPv4 address (also when mapped into IPv6), or the /64
/// of an IPv6 address (a host is usually given a whole /64).
pub fn client_key(address: IpAddr) -> IpAddr {
    match address {
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => IpAddr::V6(Ipv6Addr::from(u128::from(v6) & !u128::from(u64::MAX))),
        },
        v4 => v4,
    }
}

/// A share of the body budget, in KiB permits, and its charge to its client address; both given
/// back when dropped.
#[derive(Debug)]
pub struct Share {
    permit: Option<OwnedSemaphorePermit>,
    address: Option<IpAddr>,
    /// KiB charged to `address`.
    of_address: usize,
    held: AddressTally,
}

impl Drop for Share {
    fn drop(&mut self) {
        if let Some(address) = self.address {
            self.held.sub(address, self.of_address);
        }
    }
}

fn kib(bytes: usize) -> usize {
    bytes.div_ceil(1024)
}

/// Read `body` to its end at `pace`: at most `limit` bytes (the declared length, when the head
/// gave one, sizes the buffer), each piece charged to `share` of `budget` as it is kept, its
/// arrival recorded in `progress`; cut at once when `shed` is notified.
pub async fn receive(
    body: &mut Body,
    declared: Option<u64>,
    limit: usize,
    pace: Pace,
    budget: &BodyBudget,
    mut share: Share,
    progress: &Mutex<Progress>,
    shed: &tokio::sync::Notify,
) -> Result<Received, Cut> {
    let start = Instant::now();
    progress.lock().unwrap_or_else(PoisonError::into_inner).begin(start, pace.grace);
    let end = start + pace.timeout;
    let bound = declared.map_or(limit, |n| usize::try_from(n).unwrap_or(usize::MAX)).min(limit).min(budget.max_body_bytes);
    let mut buffer: Vec<u8> = Vec::new();
    loop {
        let now = Instant::now();
        if pace.min_rate > 0 && progress.lock().unwrap_or_else(PoisonError::into_inner).behind(&pace, now) {
            return Err(Cut::TooSlow);
        }
        let check = if pace.min_rate > 0 { now.max(start + pace.grace) + RATE_CHECK } else { end };
        let frame = tokio::select! {
            frame = tokio::time::timeout_at(check.min(end), body.frame()) => frame,
            () = shed.notified() => return Err(Cut::Shed),
        };
        let frame = match frame {
            Err(_) if check >= end => return Err(Cut::TimedOut),
            Err(_) => continue,
            Ok(None) => break,
            Ok(Some(Err(e))) => return Err(Cut::Broken(e.to_string())),
            Ok(Some(Ok(frame))) => frame,
        };
        let Ok(data) = frame.into_data() else { continue };
        let len = buffer.len() + data.len();
        if len > limit {
            return Err(Cut::TooLarge);
        }
        if len > buffer.capacity() {
            let room = len.max(bound.min(MIN_ROOM.max(2 * buffer.capacity())));
            budget.charge(&mut share, room)?;
            buffer.reserve_exact(room - buffer.len());
        }
        buffer.extend_from_slice(&data);
        progress.lock().unwrap_or_else(PoisonError::into_inner).arrived(Instant::now(), buffer.len());
    }
    Ok(Received { bytes: Bytes::from(buffer), share })
}

#[cfg(test)]
mod tests {
    use futures_util::StreamExt as _;

    use super::*;

    fn pace() -> Pace {
        Pace { timeout: Duration::from_secs(15), grace: Duration::from_secs(5), min_rate: 8192 }
    }

    /// `body` received from 192.0.2.1 at `pace` (never shed).
    async fn receive_at(mut body: Body, declared: Option<u64>, limit: usize, pace: Pace, budget: &BodyBudget) -> Result<Received, Cut> {
        let progress = Mutex::new(Progress::new(Instant::now(), pace.grace));
        let share = budget.share(Some("192.0.2.1".parse().unwrap()));
        receive(&mut body, declared, limit, pace, budget, share, &progress, &tokio::sync::Notify::new()).await
    }

    #[test]
    fn the_rate_is_owed_over_a_moving_window_from_the_end_of_the_grace_period() {
        let start = Instant::now();
        let s = |secs: f64| start + Duration::from_secs_f64(secs);
        let mut progress = Progress::new(start, pace().grace);
        // Within the grace period nothing is owed.
        assert!(!progress.behind(&pace(), s(4.9)));
        // 1 s after it, 8 KiB are owed over the last 5 s.
        progress.arrived(s(1.5), 8000);
        assert!(progress.behind(&pace(), s(6.0)), "8,000 bytes are less than 8 KiB");
        progress.arrived(s(5.5), 9000);
        assert!(!progress.behind(&pace(), s(6.0)));
        // 16 MiB sent at once, then nothing: behind once the window no longer holds them.
        let mut burst = Progress::new(start, pace().grace);
        burst.arrived(s(0.1), 16 << 20);
        assert!(!burst.behind(&pace(), s(5.0)));
        assert!(burst.behind(&pace(), s(5.2)), "what was sent before does not pay for the stall");
        // A steady 10 KiB/s is never behind.
        let mut steady = Progress::new(start, pace().grace);
        for tenth in 1..=150 {
            steady.arrived(s(tenth as f64 / 10.0), tenth * 1024);
            assert!(!steady.behind(&pace(), s(tenth as f64 / 10.0 + 0.05)), "at {tenth}");
        }
        assert!(steady.marks.len() <= 52, "marks older than the window are dropped: {}", steady.marks.len());
        assert!((steady.recent_rate(s(15.0), Duration::from_secs(5)) - 10240.0).abs() < 300.0);
    }

    #[test]
    fn clients_are_counted_by_ipv4_address_or_ipv6_64() {
        let key = |s: &str| client_key(s.parse().unwrap()).to_string();
        assert_eq!(key("192.0.2.7"), "192.0.2.7");
        assert_eq!(key("::ffff:192.0.2.7"), "192.0.2.7");
        assert_eq!(key("2001:db8:1:2:aaaa:bbbb:cccc:dddd"), "2001:db8:1:2::");
        assert_eq!(key("2001:db8:1:2::1"), key("2001:db8:1:2:ffff::9"));
        assert_ne!(key("2001:db8:1:2::1"), key("2001:db8:1:3::1"));
    }

    fn chunks() -> Body {
        Body::from_stream(futures_util::stream::iter((0..3).map(|_| Ok::<_, std::io::Error>(Bytes::from(vec![7u8; 20_000])))))
    }

    #[tokio::test]
    async fn the_budget_is_charged_for_what_arrives() {
        let budget = BodyBudget::new(64 << 10, 64 << 10, 1 << 20);
        let received = receive_at(chunks(), Some(60_000), 1 << 20, pace(), &budget).await.unwrap();
        assert_eq!(received.bytes.len(), 60_000);
        // The buffer grew to the declared length and no further: 59 KiB of the 64 held.
        assert_eq!(budget.kib.available_permits(), 64 - 59);
        // A second body cannot be held beside it; the first gives its share back when dropped.
        let second = receive_at(chunks(), Some(60_000), 1 << 20, pace(), &budget).await;
        assert!(matches!(second, Err(Cut::AddressBudgetSpent)), "{second:?}");
        drop(received);
        assert_eq!(budget.kib.available_permits(), 64);
        assert!(budget.held.is_empty(), "an address holding nothing is forgotten");
        // Without a declared length the buffer doubles, bounded by the limit.
        let over = receive_at(chunks(), None, 50_000, pace(), &budget).await;
        assert!(matches!(over, Err(Cut::TooLarge)), "{over:?}");
        assert_eq!(budget.kib.available_permits(), 64);
    }

    #[tokio::test]
    async fn one_address_holds_at_most_its_share_and_the_others_the_rest() {
        // 160 KiB in all, 64 KiB per address.
        let budget = BodyBudget::new(160 << 10, 64 << 10, 1 << 20);
        let (a, b, c): (IpAddr, IpAddr, IpAddr) =
            ("192.0.2.1".parse().unwrap(), "192.0.2.2".parse().unwrap(), "192.0.2.3".parse().unwrap());
        let mut shares: Vec<Share> = [a, a, b, c].iter().map(|&x| budget.share(Some(x))).collect();
        assert!(budget.charge(&mut shares[0], 60_000).is_ok());
        assert!(matches!(budget.charge(&mut shares[1], 10_000), Err(Cut::AddressBudgetSpent)), "a's share is spent");
        assert!(budget.charge(&mut shares[2], 60_000).is_ok(), "b has its own");
        assert!(matches!(budget.charge(&mut shares[3], 60_000), Err(Cut::BudgetSpent)), "the whole budget is spent");
        assert_eq!(budget.held.count(c), 0, "a refused charge leaves nothing behind");
        shares.remove(0);
        assert!(budget.charge(&mut shares[0], 10_000).is_ok(), "a's share came back");
        drop(shares);
        assert_eq!(budget.kib.available_permits(), 160);
        assert!(budget.held.is_empty());
    }

    #[tokio::test]
    async fn a_trickle_is_cut_after_the_grace_period_and_a_steady_upload_is_not() {
        // The defaults' rule, scaled in time: 8 KiB/s after 0.3 s, all of it within 1.5 s.
        let quick = Pace { timeout: Duration::from_millis(1500), grace: Duration::from_millis(300), min_rate: 8192 };
        let budget = BodyBudget::new(16 << 20, 16 << 20, 16 << 20);
        // A byte every 50 ms: cut by the rate soon after the grace period, not by the timeout.
        let trickle = futures_util::stream::unfold((), |()| async {
            tokio::time::sleep(Duration::from_millis(50)).await;
            Some((Ok::<_, std::io::Error>(Bytes::from_static(b"x")), ()))
        });
        let start = Instant::now();
        let cut = receive_at(Body::from_stream(trickle), Some(16 << 20), 16 << 20, quick, &budget).await;
        assert!(matches!(cut, Err(Cut::TooSlow)), "{cut:?}");
        assert!((300..900).contains(&start.elapsed().as_millis()), "{:?}", start.elapsed());
        // 80 kB/s after a 0.2 s pause: received whole; the same pace for longer than the body
        // timeout is cut by it.
        let steady = |pieces: usize| {
            futures_util::stream::unfold(0, move |n| async move {
                tokio::time::sleep(Duration::from_millis(if n == 0 { 200 } else { 50 })).await;
                (n < pieces).then(|| (Ok::<_, std::io::Error>(Bytes::from(vec![1u8; 4000])), n + 1))
            })
        };
        let received = receive_at(Body::from_stream(steady(10)), None, 16 << 20, quick, &budget).await.unwrap();
        assert_eq!(received.bytes.len(), 40_000);
        let late = receive_at(Body::from_stream(steady(40)), None, 16 << 20, quick, &budget).await;
        assert!(matches!(late, Err(Cut::TimedOut)), "{late:?}");
        // 1 MiB at once, then a stall: cut about a window after the stall, not at the timeout.
        let stalled = futures_util::stream::once(async { Ok::<_, std::io::Error>(Bytes::from(vec![2u8; 1 << 20])) })
            .chain(futures_util::stream::pending());
        let start = Instant::now();
        let cut = receive_at(Body::from_stream(stalled), Some(2 << 20), 16 << 20, quick, &budget).await;
        assert!(matches!(cut, Err(Cut::TooSlow)), "{cut:?}");
        assert!((300..900).contains(&start.elapsed().as_millis()), "{:?}", start.elapsed());
    }

    #[tokio::test]
    async fn a_shed_body_is_cut_at_once() {
        let budget = BodyBudget::new(1 << 20, 1 << 20, 1 << 20);
        let progress = Mutex::new(Progress::new(Instant::now(), pace().grace));
        let shed = tokio::sync::Notify::new();
        shed.notify_one();
        let mut pending = Body::from_stream(futures_util::stream::pending::<Result<Bytes, std::io::Error>>());
        let cut = receive(&mut pending, Some(1000), 1 << 20, pace(), &budget, budget.share(None), &progress, &shed).await;
        assert!(matches!(cut, Err(Cut::Shed)), "{cut:?}");
    }

    #[tokio::test]
    async fn each_address_has_its_cap_of_arriving_bodies() {
        let budget = BodyBudget::new(1 << 20, 1 << 20, 1 << 20);
        let (a, b): (IpAddr, IpAddr) = ("192.0.2.1".parse().unwrap(), "192.0.2.2".parse().unwrap());
        let held = [budget.arrival_slot(a, 2, Duration::ZERO).await.unwrap(), budget.arrival_slot(a, 2, Duration::ZERO).await.unwrap()];
        assert!(budget.arrival_slot(a, 2, Duration::from_millis(20)).await.is_none());
        let other = budget.arrival_slot(b, 2, Duration::ZERO).await.unwrap();
        assert_eq!(budget.addresses_arriving(), 2);
        // A waiting request gets the place given back.
        let waiting = tokio::spawn({
            let budget = budget.clone();
            async move { budget.arrival_slot(a, 2, Duration::from_secs(5)).await.is_some() }
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        let [first, second] = held;
        drop(first);
        assert!(waiting.await.unwrap());
        drop((second, other));
        assert_eq!(budget.addresses_arriving(), 0, "addresses are forgotten with their last place");
    }
}
