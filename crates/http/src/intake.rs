//! Receiving a request body as it arrives, before the request takes its place in the work queue
//! (`admission::admit`), so that what a slow client holds is what it has sent:
//!
//! - the body-memory budget ([`BodyBudget`]) is charged for the buffer the arrived bytes fill, not
//!   for the length the head declares;
//! - the body keeps a pace ([`Pace`]): after a grace period it must average a minimum rate, and it
//!   must be complete within the body timeout, else 408 — the deadline moves with the bytes
//!   received, so a trickle is cut after the grace period while a slow steady upload goes on;
//! - at most so many bodies arrive at once from one client address ([`ArrivalSlot`]; IPv6 by its
//!   /64), so a few slow clients cannot take the server's connections and budget from the others.
//!
//! The bytes are copied into one buffer of the request's own as they arrive: the connection's read
//! buffers are not held by the many small pieces a trickle sends.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use axum::body::{Body, Bytes};
use http_body_util::BodyExt as _;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;

/// The least room a body's buffer is given at once (less when the declared length is smaller).
const MIN_ROOM: usize = 8 << 10;

/// How fast a body must arrive: all of it within `timeout`, and after `grace` at least
/// `min_rate` bytes per second on average since it began (0: no rate).
#[derive(Debug, Clone, Copy)]
pub struct Pace {
    pub timeout: Duration,
    pub grace: Duration,
    pub min_rate: u64,
}

impl Pace {
    /// The instant by which more than `received` bytes must have arrived, for a body that began
    /// at `start`; and whether that is the body timeout (rather than the rate).
    fn deadline(&self, start: Instant, received: usize) -> (Instant, bool) {
        let end = start + self.timeout;
        if self.min_rate == 0 {
            return (end, true);
        }
        let earned = Duration::try_from_secs_f64(received as f64 / self.min_rate as f64).unwrap_or(Duration::MAX);
        match start.checked_add(self.grace.saturating_add(earned)) {
            Some(by_rate) if by_rate < end => (by_rate, false),
            _ => (end, true),
        }
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
/// and the bodies arriving at once per client address.
#[derive(Debug, Clone)]
pub struct BodyBudget {
    kib: Arc<Semaphore>,
    max_body_bytes: usize,
    arriving: Arc<Mutex<HashMap<IpAddr, Arc<Semaphore>>>>,
}

impl BodyBudget {
    pub fn new(max_buffered_bytes: usize, max_body_bytes: usize) -> BodyBudget {
        let kib = Arc::new(Semaphore::new(kib(max_buffered_bytes).min(Semaphore::MAX_PERMITS)));
        BodyBudget { kib, max_body_bytes, arriving: Arc::default() }
    }

    /// Grow `share` to cover `bytes`; false when the budget cannot (the share is left as it was).
    fn charge(&self, share: &mut Share, bytes: usize) -> bool {
        let wanted = u32::try_from(kib(bytes)).unwrap_or(u32::MAX);
        let held = share.0.as_ref().map_or(0, |p| p.num_permits() as u32);
        if wanted <= held {
            return true;
        }
        let Ok(more) = self.kib.clone().try_acquire_many_owned(wanted - held) else { return false };
        match &mut share.0 {
            Some(permit) => permit.merge(more),
            None => share.0 = Some(more),
        }
        true
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

/// A share of the body budget, in KiB permits, given back when dropped.
#[derive(Debug, Default)]
pub struct Share(Option<OwnedSemaphorePermit>);

fn kib(bytes: usize) -> usize {
    bytes.div_ceil(1024)
}

/// Read `body` to its end at `pace`: at most `limit` bytes (the declared length, when the head
/// gave one, sizes the buffer), each piece charged to `budget` as it is kept.
pub async fn receive(body: &mut Body, declared: Option<u64>, limit: usize, pace: Pace, budget: &BodyBudget) -> Result<Received, Cut> {
    let start = Instant::now();
    let bound = declared.map_or(limit, |n| usize::try_from(n).unwrap_or(usize::MAX)).min(limit).min(budget.max_body_bytes);
    let mut buffer: Vec<u8> = Vec::new();
    let mut share = Share::default();
    loop {
        let (deadline, is_timeout) = pace.deadline(start, buffer.len());
        let frame = match tokio::time::timeout_at(deadline, body.frame()).await {
            Err(_) if is_timeout => return Err(Cut::TimedOut),
            Err(_) => return Err(Cut::TooSlow),
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
            if !budget.charge(&mut share, room) {
                return Err(Cut::BudgetSpent);
            }
            buffer.reserve_exact(room - buffer.len());
        }
        buffer.extend_from_slice(&data);
    }
    Ok(Received { bytes: Bytes::from(buffer), share })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pace() -> Pace {
        Pace { timeout: Duration::from_secs(15), grace: Duration::from_secs(5), min_rate: 8192 }
    }

    #[test]
    fn the_deadline_moves_with_the_bytes_received() {
        let start = Instant::now();
        let at = |received| {
            let (deadline, is_timeout) = pace().deadline(start, received);
            ((deadline - start).as_secs_f64(), is_timeout)
        };
        assert_eq!(at(0), (5.0, false));
        assert_eq!(at(8192), (6.0, false));
        assert_eq!(at(64 * 1000), (5.0 + 64_000.0 / 8192.0, false));
        // Past the body timeout the timeout is the deadline.
        assert_eq!(at(1 << 20), (15.0, true));
        let no_rate = Pace { min_rate: 0, ..pace() };
        assert_eq!(no_rate.deadline(start, 0), (start + Duration::from_secs(15), true));
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

    #[tokio::test]
    async fn the_budget_is_charged_for_what_arrives() {
        let budget = BodyBudget::new(64 << 10, 1 << 20);
        let chunks = || futures_util::stream::iter((0..3).map(|_| Ok::<_, std::io::Error>(Bytes::from(vec![7u8; 20_000]))));
        let received = receive(&mut Body::from_stream(chunks()), Some(60_000), 1 << 20, pace(), &budget).await.unwrap();
        assert_eq!(received.bytes.len(), 60_000);
        // The buffer grew to the declared length and no further: 59 KiB of the 64 held.
        assert_eq!(budget.kib.available_permits(), 64 - 59);
        // A second body cannot be held beside it; the first gives its share back when dropped.
        let second = receive(&mut Body::from_stream(chunks()), Some(60_000), 1 << 20, pace(), &budget).await;
        assert!(matches!(second, Err(Cut::BudgetSpent)), "{second:?}");
        drop(received);
        assert_eq!(budget.kib.available_permits(), 64);
        // Without a declared length the buffer doubles, bounded by the limit.
        let over = receive(&mut Body::from_stream(chunks()), None, 50_000, pace(), &budget).await;
        assert!(matches!(over, Err(Cut::TooLarge)), "{over:?}");
        assert_eq!(budget.kib.available_permits(), 64);
    }

    #[tokio::test]
    async fn a_trickle_is_cut_after_the_grace_period_and_a_steady_upload_is_not() {
        // The defaults' rule, scaled in time: 8 KiB/s after 0.3 s, all of it within 1.5 s.
        let quick = Pace { timeout: Duration::from_millis(1500), grace: Duration::from_millis(300), min_rate: 8192 };
        let budget = BodyBudget::new(16 << 20, 16 << 20);
        // A byte every 50 ms: cut by the rate at the end of the grace period, not by the timeout.
        let trickle = futures_util::stream::unfold((), |()| async {
            tokio::time::sleep(Duration::from_millis(50)).await;
            Some((Ok::<_, std::io::Error>(Bytes::from_static(b"x")), ()))
        });
        let start = Instant::now();
        let cut = receive(&mut Body::from_stream(trickle), Some(16 << 20), 16 << 20, quick, &budget).await;
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
        let received = receive(&mut Body::from_stream(steady(10)), None, 16 << 20, quick, &budget).await.unwrap();
        assert_eq!(received.bytes.len(), 40_000);
        let late = receive(&mut Body::from_stream(steady(40)), None, 16 << 20, quick, &budget).await;
        assert!(matches!(late, Err(Cut::TimedOut)), "{late:?}");
    }

    #[tokio::test]
    async fn each_address_has_its_cap_of_arriving_bodies() {
        let budget = BodyBudget::new(1 << 20, 1 << 20);
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
