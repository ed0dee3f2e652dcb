//! The gallery and the live gallery, against the exact per-subject reference and a real store.

use super::super::*;
use super::*;
use facegate_core::template::OperatingPoint;
use rand::{Rng, SeedableRng};

/// Scores by the best cosine, like the deep recognizer; `general` turns the fast path off.
struct Cosine {
    general: bool,
}

impl Matcher for Cosine {
    fn model_version(&self) -> &str {
        "v1"
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| probe.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        OperatingPoint { fmr, threshold: 0.5 + 0.01 * enrolled as f32 }
    }
    fn max_cosine_scoring(&self) -> bool {
        !self.general
    }
}

/// A matcher whose score is not a cosine (the mean of the first components).
struct Mean;

impl Matcher for Mean {
    fn model_version(&self) -> &str {
        "v1"
    }
    fn score(&self, _probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| t.vector[0]).sum::<f32>() / enrolled.len() as f32
    }
    fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
        OperatingPoint { fmr, threshold: 0.0 }
    }
}

fn random_template(rng: &mut impl Rng, version: &str, dims: usize) -> Template {
    Template::new(version, (0..dims).map(|_| rng.random_range(-1.0f32..1.0)).collect())
}

fn summary(found: &[Candidate]) -> Vec<(String, usize, bool)> {
    found.iter().map(|c| (c.subject.clone(), c.decision.templates_compared, c.decision.is_match)).collect()
}

/// The same subjects, decisions and thresholds, scores within 1e-5 (a subject's templates may be
/// summed in another order).
fn assert_same(found: &[Candidate], expected: &[Candidate], what: &str) {
    assert_eq!(summary(found), summary(expected), "{what}");
    for (a, b) in found.iter().zip(expected) {
        assert!((a.decision.score - b.decision.score).abs() < 1e-5, "{what}: {} vs {}", a.decision.score, b.decision.score);
        assert_eq!(a.decision.threshold, b.decision.threshold);
    }
}

/// The exact search's answer.
fn decided(found: (Found, usize)) -> (Vec<Candidate>, usize) {
    match found {
        (Found::Decided(candidates), searched) => (candidates, searched),
        (Found::Shortlist(_), _) => panic!("an exact gallery decides"),
    }
}

/// The quantised search's shortlist, re-scored from `reference` as the service re-scores it
/// from the store.
fn reranked(
    found: (Found, usize),
    reference: &BTreeMap<String, Vec<Template>>,
    matcher: &dyn Matcher,
    probe: &Template,
    k: usize,
) -> (Vec<Candidate>, usize) {
    match found {
        (Found::Shortlist(shortlist), searched) => {
            let mut sorted = shortlist.clone();
            sorted.sort();
            assert_eq!(shortlist, sorted, "in id order");
            let scored = shortlist.into_iter().map(|s| (s.clone(), reference[&s].clone())).collect();
            (score_each_subject(matcher, probe, scored, 1e-3, k), searched)
        }
        (Found::Decided(_), _) => panic!("a quantised gallery shortlists"),
    }
}

/// The gallery's answer is `service::identify`'s over the same subjects and templates, through
/// additions, other versions, zero vectors and removals: the exact gallery's at once, the
/// quantised one's after its shortlist is re-scored.
#[test]
fn search_equals_identify_through_adds_and_removes() {
    // Also with room reserved up front for part of the adds (as the start-up load reserves).
    for (precision, reserved) in [(Precision::Exact, 0), (Precision::Quantised, 0), (Precision::Exact, 50), (Precision::Quantised, 50)] {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut gallery = Gallery::with_precision("v1", precision);
        gallery.reserve(reserved);
        let mut reference: BTreeMap<String, Vec<Template>> = BTreeMap::new();
        for i in 0..300 {
            let subject = format!("s{:03}", i % 120);
            let mut templates = vec![random_template(&mut rng, "v1", 20)];
            if i % 7 == 0 {
                templates.push(random_template(&mut rng, "v0", 20));
            }
            if i == 11 {
                templates.push(Template::new("v1", vec![0.0; 20]));
            }
            gallery.add(&subject, &templates);
            reference.entry(subject).or_default().extend(templates.into_iter().filter(|t| t.model_version == "v1"));
        }
        for i in (0..120).step_by(3) {
            let subject = format!("s{i:03}");
            gallery.remove(&subject);
            reference.remove(&subject);
        }
        gallery.remove("nobody");
        assert_eq!(gallery.subjects(), reference.len());
        assert_eq!(gallery.templates(), reference.values().map(Vec::len).sum::<usize>());
        for trial in 0..20 {
            let probe = random_template(&mut rng, "v1", 20);
            let k = [1, 5, 100, 1000][trial % 4];
            let expected = score_each_subject(&Cosine { general: true }, &probe, reference.clone().into_iter().collect(), 1e-3, k);
            for general in [false, true] {
                let matcher = Cosine { general };
                let found = gallery.search(&matcher, &probe, 1e-3, k).unwrap();
                let (found, searched) = match precision {
                    Precision::Exact => decided(found),
                    Precision::Quantised => reranked(found, &reference, &matcher, &probe, k),
                };
                assert_eq!(searched, reference.len());
                assert_same(&found, &expected, &format!("{precision:?}, general path: {general}"));
            }
            // A matcher that is not a cosine scores through its own `score`.
            let expected = score_each_subject(&Mean, &probe, reference.clone().into_iter().collect(), 1e-3, k);
            let found = gallery.search(&Mean, &probe, 1e-3, k).unwrap();
            let (found, _) = match precision {
                Precision::Exact => decided(found),
                Precision::Quantised => reranked(found, &reference, &Mean, &probe, k),
            };
            assert_same(&found, &expected, &format!("{precision:?}, mean"));
        }
        // Everything removed: an empty gallery answers with no candidate.
        for subject in reference.keys() {
            gallery.remove(subject);
        }
        assert_eq!((gallery.subjects(), gallery.templates(), gallery.vectors.len(), gallery.codes.len()), (0, 0, 0, 0));
        let found = gallery.search(&Cosine { general: false }, &random_template(&mut rng, "v1", 20), 1e-3, 5).unwrap();
        let empty = match found {
            (Found::Decided(c), 0) => c.is_empty(),
            (Found::Shortlist(s), 0) => s.is_empty(),
            _ => false,
        };
        assert!(empty, "{precision:?}");
    }
}

/// The quantised shortlist holds the exact search's best subject on a gallery of 20,000
/// 256-value templates, for probes that are noisy copies of an enrolled template (a genuine
/// search) and for random ones (an impostor's, where the best scores lie close together).
#[test]
fn the_shortlist_holds_the_exact_best() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut gallery = Gallery::with_precision("v1", Precision::Quantised);
    let exact = {
        let mut exact = Gallery::new("v1");
        for i in 0..20_000 {
            let t = random_template(&mut rng, "v1", 256);
            gallery.add(&format!("s{i:05}"), std::slice::from_ref(&t));
            exact.add(&format!("s{i:05}"), &[t]);
        }
        exact
    };
    let matcher = Cosine { general: false };
    for trial in 0..40 {
        let probe = if trial % 2 == 0 {
            let enrolled = &exact.vectors[(trial * 97) * 256..(trial * 97 + 1) * 256];
            Template::new("v1", enrolled.iter().map(|v| v + rng.random_range(-1.0f32..1.0)).collect())
        } else {
            random_template(&mut rng, "v1", 256)
        };
        let (best, _) = decided(exact.search(&matcher, &probe, 1e-3, 1).unwrap());
        let (Found::Shortlist(shortlist), _) = gallery.search(&matcher, &probe, 1e-3, 1).unwrap() else { panic!("a shortlist") };
        assert_eq!(shortlist.len(), 1 + SHORTLIST_MARGIN);
        assert!(shortlist.contains(&best[0].subject), "trial {trial}: {} not shortlisted", best[0].subject);
    }
}

#[test]
fn unreadable_subjects_refuse_the_search_until_erased() {
    let mut gallery = Gallery::new("v1");
    gallery.add("alice", &[Template::new("v1", vec![1.0, 0.0])]);
    gallery.mark_unreadable("bob", "authentication failed".into());
    let probe = Template::new("v1", vec![1.0, 0.0]);
    let err = gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).unwrap_err();
    assert_eq!(err, UnreadableTemplates { count: 1, first: "bob".into() });
    // A template of another dimension is not comparable: the subject is unreadable too.
    gallery.add("carol", &[Template::new("v1", vec![1.0, 0.0, 0.0])]);
    gallery.remove("bob");
    assert!(gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).is_err());
    gallery.remove("carol");
    let (found, searched) = decided(gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).unwrap());
    assert_eq!((found[0].subject.as_str(), searched), ("alice", 1));
}

/// Concurrent enrolments and deletions of the same subjects, some of them cancelled by their
/// caller: afterwards the live gallery answers as one loaded afresh from the store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_gallery_stays_in_step_with_the_store() {
    let dir = std::env::temp_dir().join(format!("facegate-gallery-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let url = format!("sqlite://{}", dir.join("g.db").display());
    let store = Store::connect(&url, None).await.unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    store.enroll(&SubjectId::parse("before").unwrap(), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
    let live = LiveGallery::new(store.clone(), "v1", Precision::Quantised);
    let mut tasks = Vec::new();
    for i in 0..120 {
        let live = live.clone();
        let subject = SubjectId::parse(&format!("s{}", i % 9)).unwrap();
        let templates = vec![random_template(&mut rng, "v1", 16), random_template(&mut rng, "v0", 16)];
        tasks.push(tokio::spawn(async move {
            let work = async {
                if i % 4 == 3 { live.delete(&subject).await.map(|_| ()) } else { live.enroll(&subject, templates).await.map(|_| ()) }
            };
            if i % 5 == 0 {
                // The caller gives up at once; what it started still completes or never starts.
                let _ = tokio::time::timeout(std::time::Duration::from_micros(50), work).await;
            } else {
                work.await.unwrap();
            }
        }));
    }
    for task in tasks {
        task.await.unwrap();
    }
    // Wait for any enrolment or deletion a cancelled caller left running (spawned: they get
    // to the writes lock, which is fair, soon after).
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    drop(live.0.writes.lock().await);
    let fresh = LiveGallery::new(store.clone(), "v1", Precision::Quantised);
    assert!(fresh.load().await.unwrap().is_empty());
    assert_eq!(live.size(), fresh.size());
    let (subjects, templates) = store.counts().await.unwrap();
    // Each enrolment stored one template of each version; `before` has one of v1 only.
    assert_eq!((live.size().0 as u64, live.size().1 as u64 * 2 - 1), (subjects, templates));
    for _ in 0..10 {
        let probe = random_template(&mut rng, "v1", 16);
        let matcher = Cosine { general: false };
        let answer = live.identify(&matcher, &probe, 1e-3, 20).await.unwrap().unwrap();
        assert_eq!(answer, fresh.identify(&matcher, &probe, 1e-3, 20).await.unwrap().unwrap());
        assert_eq!(answer.0.len(), answer.1, "k = 20 is more than the subjects: all are answered");
    }
    store.close().await;
    std::fs::remove_dir_all(dir).unwrap();
}

/// The store version the gallery has applied, when it follows a feed.
fn applied(live: &LiveGallery) -> Option<i64> {
    live.0.applied.get().map(|applied| *applied.borrow())
}

/// Another writer changes the store and a hand-made feed tells of it: each subject is re-read
/// (replaced, not appended; removed when gone; unreadable noted until erased), a resync reads
/// everything, the highest version is tracked, and the end of the feed ends the waits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_gallery_follows_a_change_feed() {
    let dir = std::env::temp_dir().join(format!("facegate-gallery-feed-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let url = format!("sqlite://{}", dir.join("g.db").display());
    let keys = facegate_store::KeyRing::parse(&"5a".repeat(32)).unwrap();
    // The other replica has the template key; this one's store is opened without it, so a
    // subject the other seals is unreadable here.
    let other = Store::connect(&url, Some(keys)).await.unwrap();
    let store = Store::connect(&url, None).await.unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let id = |s: &str| SubjectId::parse(s).unwrap();
    let live = LiveGallery::new(store.clone(), "v1", Precision::Quantised);
    assert!(live.load().await.unwrap().is_empty());
    assert_eq!((applied(&live), live.change_version().await.unwrap()), (None, None), "SQLite: no feed, nothing to wait for");
    let (changes, script) = tokio::sync::mpsc::unbounded_channel();
    live.follow(Changes::Script(script), 0);
    let notify = |subject: &str, version: i64| changes.send(StoreChange::Subject { subject: subject.into(), version }).unwrap();
    let matcher = Cosine { general: false };

    let alice = random_template(&mut rng, "v1", 16);
    store.enroll(&id("alice"), &[alice.clone(), random_template(&mut rng, "v0", 16)]).await.unwrap();
    notify("alice", 1);
    live.wait_until_applied(Some(1)).await;
    assert_eq!((applied(&live), live.size()), (Some(1), (1, 1)), "only the gallery's model version");
    assert_eq!(live.identify(&matcher, &alice, 1e-3, 1).await.unwrap().unwrap().0[0].subject, "alice");
    store.enroll(&id("alice"), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
    notify("alice", 2);
    // The notification of a write already applied (this replica's own) changes nothing.
    notify("alice", 2);
    notify("alice", 1);
    live.wait_until_applied(Some(2)).await;
    assert_eq!((applied(&live), live.size()), (Some(2), (1, 2)), "re-read, not appended");
    store.delete_subject(&id("alice")).await.unwrap();
    notify("alice", 3);
    live.wait_until_applied(Some(3)).await;
    assert_eq!(live.size(), (0, 0));

    other.enroll(&id("dave"), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
    notify("dave", 4);
    live.wait_until_applied(Some(4)).await;
    let err = live.search(&matcher, &alice, 1e-3, 1).unwrap_err();
    assert_eq!(err, UnreadableTemplates { count: 1, first: "dave".into() });
    other.delete_subject(&id("dave")).await.unwrap();
    notify("dave", 5);
    live.wait_until_applied(Some(5)).await;
    assert!(live.identify(&matcher, &alice, 1e-3, 1).await.unwrap().unwrap().0.is_empty());

    // Changes whose notifications were lost: a resync reads them all.
    for name in ["bob", "carol"] {
        store.enroll(&id(name), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
    }
    changes.send(StoreChange::Resync).unwrap();
    notify("nobody", 6);
    live.wait_until_applied(Some(6)).await;
    assert_eq!((applied(&live), live.size()), (Some(6), (2, 2)));
    let fresh = LiveGallery::new(store.clone(), "v1", Precision::Quantised);
    fresh.load().await.unwrap();
    let probe = random_template(&mut rng, "v1", 16);
    assert_eq!(
        live.identify(&matcher, &probe, 1e-3, 5).await.unwrap().unwrap(),
        fresh.identify(&matcher, &probe, 1e-3, 5).await.unwrap().unwrap()
    );

    // The feed ends: waiting for a version never applied returns at once.
    drop(changes);
    tokio::time::sleep(Duration::from_millis(50)).await;
    let start = std::time::Instant::now();
    live.wait_until_applied(Some(100)).await;
    assert!(start.elapsed() < Duration::from_secs(1), "{:?}", start.elapsed());
    live.stop_following();
    other.close().await;
    store.close().await;
    std::fs::remove_dir_all(dir).unwrap();
}

/// A version the gallery never applies is waited for at most [`CATCH_UP_WAIT`].
#[tokio::test]
async fn waiting_for_the_gallery_is_bounded() {
    let dir = std::env::temp_dir().join(format!("facegate-gallery-wait-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let store = Store::connect(&format!("sqlite://{}", dir.join("g.db").display()), None).await.unwrap();
    let live = LiveGallery::new(store.clone(), "v1", Precision::Quantised);
    let (_changes, script) = tokio::sync::mpsc::unbounded_channel();
    live.follow(Changes::Script(script), 7);
    let start = std::time::Instant::now();
    live.wait_until_applied(Some(7)).await;
    assert!(start.elapsed() < Duration::from_millis(100));
    live.wait_until_applied(Some(8)).await;
    let waited = start.elapsed();
    assert!(waited >= CATCH_UP_WAIT && waited < CATCH_UP_WAIT + Duration::from_secs(1), "{waited:?}");
    live.stop_following();
    store.close().await;
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn the_dot_product_sums_every_value() {
    for n in [1, 15, 16, 17, 128, 130] {
        let a: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let b = vec![2.0f32; n];
        assert_eq!(dot(&a, &b), (n * (n - 1)) as f32, "{n}");
    }
}
