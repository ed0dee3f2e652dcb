//! A rate per client address: a token bucket per address (an IPv4 address or the /64 of an IPv6
//! one, as the upload cap counts them, [`super::intake::client_key`]), kept in memory. It bounds
//! what one client may make the service store (`POST /liveness/challenge`); the cap on open
//! challenges in the store bounds what many addresses may.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::AppState;
use super::intake::client_key;
use super::problem::Problem;

/// Most addresses remembered at once: beyond, the addresses whose bucket has filled again are
/// forgotten (they are as new ones); if every one is still draining, all are forgotten, so the
/// map never grows past this however many addresses take part.
const MAX_ADDRESSES: usize = 65_536;

/// Tokens per address, refilled at `per_second` up to `burst`; each request takes one.
#[derive(Debug)]
pub struct RateLimiter {
    per_second: f64,
    burst: f64,
    buckets: Mutex<HashMap<IpAddr, Bucket>>,
}

#[derive(Debug, Clone, Copy)]
struct Bucket {
    tokens: f64,
    at: Instant,
}

impl RateLimiter {
    /// `per_second` requests a second per address, `burst` at once; `per_second` 0: no limit.
    pub fn new(per_second: f64, burst: u32) -> RateLimiter {
        RateLimiter { per_second, burst: f64::from(burst.max(1)), buckets: Mutex::new(HashMap::new()) }
    }

    /// Take a token of `address`'s bucket at `now`: `Ok`, or how long until it has one.
    pub fn take(&self, address: IpAddr, now: Instant) -> Result<(), Duration> {
        if self.per_second <= 0.0 {
            return Ok(());
        }
        let mut buckets = self.buckets.lock().expect("rate buckets lock");
        if buckets.len() >= MAX_ADDRESSES && !buckets.contains_key(&client_key(address)) {
            buckets.retain(|_, bucket| self.refilled(bucket, now) < self.burst);
            if buckets.len() >= MAX_ADDRESSES {
                buckets.clear();
            }
        }
        let bucket = buckets.entry(client_key(address)).or_insert(Bucket { tokens: self.burst, at: now });
        bucket.tokens = self.refilled(bucket, now);
        bucket.at = now;
        if bucket.tokens >= 1.0 {
            bucket.tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - bucket.tokens) / self.per_second))
        }
    }

    fn refilled(&self, bucket: &Bucket, now: Instant) -> f64 {
        (bucket.tokens + now.saturating_duration_since(bucket.at).as_secs_f64() * self.per_second).min(self.burst)
    }

    /// Addresses remembered (for the tests).
    pub fn addresses(&self) -> usize {
        self.buckets.lock().expect("rate buckets lock").len()
    }
}

/// The route layer of `POST /liveness/challenge`: over its address's rate, 429
/// `too-many-challenges` with `Retry-After`, before the handler (so before the store).
pub async fn limit_challenges(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let address = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|ConnectInfo(a)| a.ip());
    if let Some(address) = address
        && let Err(wait) = state.0.challenge_rate.take(address, Instant::now())
    {
        let rate = state.0.config.challenge_rate;
        let detail = format!("this client address asked for challenges faster than {rate} a second; retry after the Retry-After seconds");
        return Problem::too_many_challenges(detail, wait).into_response();
    }
    next.run(request).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_address_has_its_burst_then_its_rate() {
        let limiter = RateLimiter::new(10.0, 20);
        let (a, b): (IpAddr, IpAddr) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let start = Instant::now();
        assert!((0..20).all(|_| limiter.take(a, start).is_ok()));
        let wait = limiter.take(a, start).unwrap_err();
        assert!((wait.as_secs_f64() - 0.1).abs() < 1e-6, "{wait:?}");
        assert!(limiter.take(b, start).is_ok(), "another address has its own bucket");
        assert!(limiter.take(a, start + Duration::from_millis(100)).is_ok(), "one more after 1/rate");
        assert!(limiter.take(a, start + Duration::from_millis(100)).is_err());
        // The /64 of an IPv6 address is one client.
        let (c, d): (IpAddr, IpAddr) = ("2001:db8::1".parse().unwrap(), "2001:db8::2".parse().unwrap());
        assert!((0..20).all(|_| limiter.take(c, start).is_ok()));
        assert!(limiter.take(d, start).is_err());
        assert!(RateLimiter::new(0.0, 1).take(a, start).is_ok(), "rate 0: no limit");
    }

    #[test]
    fn the_addresses_remembered_are_bounded() {
        let limiter = RateLimiter::new(1.0, 2);
        let start = Instant::now();
        for n in 0..MAX_ADDRESSES as u32 {
            let _ = limiter.take(IpAddr::from(n.to_be_bytes()), start);
        }
        assert_eq!(limiter.addresses(), MAX_ADDRESSES);
        // Full, every bucket still draining: a new address makes room by forgetting them.
        let _ = limiter.take("192.0.2.1".parse().unwrap(), start);
        assert_eq!(limiter.addresses(), 1);
        for n in 0..MAX_ADDRESSES as u32 - 1 {
            let _ = limiter.take(IpAddr::from(n.to_be_bytes()), start);
        }
        // Once their buckets have filled again they are forgotten first.
        let _ = limiter.take("192.0.2.2".parse().unwrap(), start + Duration::from_secs(5));
        assert_eq!(limiter.addresses(), 1);
    }
}
