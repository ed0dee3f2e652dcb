//! Challenges are bounded: `POST /liveness/challenge` has a rate per client address (a token
//! bucket: `--challenge-rate` a second, bursts of twice as many) and the store a cap on the
//! challenges open at once (`--max-open-challenges`); both are answered 429
//! `too-many-challenges` with `Retry-After`, and another address still gets its challenge. Each
//! issue removes a bounded number of expired challenges.

use facegate::config::Settings;
use facegate_http::ApiConfig;
use facegate_store::{SWEEP_BATCH, Store};

use crate::fail_closed::Scratch;
use crate::support::*;

fn config(challenge_rate: f64, max_open_challenges: u64) -> ApiConfig {
    Settings { challenge_rate, max_open_challenges, ..Settings::default() }.api_config().unwrap()
}

/// `n` challenges asked at once from the app's client (127.0.0.1).
async fn challenges(app: &TestApp, n: usize) -> Vec<Reply> {
    futures_util::future::join_all((0..n).map(|_| app.send(app.client.post(app.url("/liveness/challenge"))))).await
}

fn retry_after(reply: &Reply) -> u64 {
    reply.headers["retry-after"].to_str().unwrap().parse().unwrap()
}

#[tokio::test]
async fn one_address_asking_too_fast_gets_429_with_retry_after() {
    // 2 a second, bursts of 4: 30 at once cannot all pass however slow the machine.
    let app = TestApp::start(StandInEngine::new("v1"), config(2.0, 2_000)).await;
    let replies = challenges(&app, 30).await;
    let issued = replies.iter().filter(|r| r.status == 201).count();
    let refused: Vec<&Reply> = replies.iter().filter(|r| r.status == 429).collect();
    assert_eq!(issued + refused.len(), 30, "only 201 and 429: {:?}", replies.iter().map(|r| r.status).collect::<Vec<_>>());
    assert!((4..=10).contains(&issued), "the burst and little more: {issued}");
    for reply in &refused {
        reply.assert_problem(429, "too-many-challenges");
        assert_eq!(retry_after(reply), 1, "a token within a second at 2 a second: {:?}", reply.headers);
    }
    assert_eq!(app.store.challenges_open().await.unwrap(), issued as u64, "a refused challenge stores nothing");
    // Another address has its own bucket.
    let other = reqwest::Client::builder().local_address("127.0.0.2".parse::<std::net::IpAddr>().unwrap()).build().unwrap();
    let response = other.post(app.url("/liveness/challenge")).send().await.unwrap();
    assert_eq!(response.status(), 201);
    // The bucket refills: after the Retry-After the first address is served again.
    tokio::time::sleep(std::time::Duration::from_secs(1)).await;
    assert_eq!(challenges(&app, 1).await[0].status, 201);
}

#[tokio::test]
async fn the_store_keeps_at_most_the_open_challenges_cap() {
    let app = TestApp::start(StandInEngine::new("v1"), config(0.0, 3)).await;
    for reply in challenges(&app, 3).await {
        assert_eq!(reply.status, 201, "{}", String::from_utf8_lossy(&reply.body));
    }
    let full = &challenges(&app, 1).await[0];
    full.assert_problem(429, "too-many-challenges");
    assert!(full.json()["detail"].as_str().unwrap().contains("3 liveness challenges are open"), "{:?}", full.json());
    // Room comes back when the first open challenge expires: within the lifetime (120 s).
    assert!((1..=120).contains(&retry_after(full)), "{:?}", full.headers);
    assert_eq!(app.store.challenges_open().await.unwrap(), 3);
}

#[tokio::test]
async fn each_issue_sweeps_a_bounded_number_of_expired_challenges() {
    let scratch = Scratch::new("sweep");
    let store = Store::connect(&scratch.url("sweep.db"), None).await.unwrap();
    let expired = SWEEP_BATCH as u64 + 44;
    for n in 0..expired {
        store.insert_challenge(&format!("old-{n}"), "[]", 1_000, 0).await.unwrap();
    }
    // At 2,000 ms every one of them has expired: the first issue removes SWEEP_BATCH, the next the rest.
    assert!(store.insert_challenge_within("new-1", "[]", 9_000, 2_000, 2).await.unwrap());
    assert_eq!(store.challenges_open().await.unwrap(), expired - SWEEP_BATCH as u64 + 1);
    assert!(store.insert_challenge_within("new-2", "[]", 8_000, 2_000, 2).await.unwrap());
    assert_eq!(store.challenges_open().await.unwrap(), 2);
    // Two open: the cap refuses a third, and says when the first expires.
    assert!(!store.insert_challenge_within("new-3", "[]", 9_000, 2_000, 2).await.unwrap());
    assert_eq!(store.next_challenge_expiry(2_000).await.unwrap(), Some(8_000));
    // Expired ones do not count against the cap.
    assert!(store.insert_challenge_within("new-4", "[]", 20_000, 8_500, 2).await.unwrap());
    store.close().await;
}
