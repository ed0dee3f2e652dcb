//! The template store on both backends: each behaviour runs one test body against a fresh SQLite
//! file and a fresh PostgreSQL database (`store_backends::<behaviour>::{sqlite, postgres}`), plus
//! what only PostgreSQL has: concurrent migration, the change counter and its feed.

use std::time::Duration;

use facegate_core::SubjectId;
use facegate_core::template::{OperatingPoint, Template};
use facegate_service::Matcher;
use facegate_service::liveness_camera::{self, LivenessCalibration};
use facegate_service::site::{self, SiteStatus};
use facegate_store::{Backend, CipherError, KeyRing, RekeyReport, Store, StoreChange, StoreError, VersionCount};
use sqlx::AnyPool;

const K1: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";
const K2: &str = "ff0102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1eff";

/// Each behaviour as two tests, `sqlite` and `postgres`, running the same async body on a URL.
macro_rules! on_both_backends {
    ($($behaviour:ident),* $(,)?) => {$(
        mod $behaviour {
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn sqlite() {
                let dir = super::TempDir::new();
                super::$behaviour(dir.sqlite_url()).await;
            }
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn postgres() {
                let url = $crate::postgres_or_skip!(concat!("store_backends::", stringify!($behaviour), "::postgres"));
                super::$behaviour(url).await;
            }
        }
    )*};
}

on_both_backends!(
    enroll_list_read_and_delete,
    a_failed_enrollment_stores_nothing,
    sealed_round_trip_and_tampered_rows_refused,
    rekey_seals_then_rotates,
    the_gallery_reads_in_parts_and_by_subject,
    the_site_calibration_is_measured_on_sealed_templates_and_stored_per_version,
    a_challenge_is_taken_once_and_expired_ones_are_swept,
    a_liveness_calibration_is_kept_per_model_and_replaced
);

async fn a_liveness_calibration_is_kept_per_model_and_replaced(url: String) {
    let store = Store::connect(&url, None).await.unwrap();
    let calibration = |model: &str, threshold: f32| LivenessCalibration {
        model: model.into(),
        bpcer: 0.02,
        live_faces: 120,
        refused: 2,
        threshold,
        model_threshold: 0.64,
        refused_at_model_threshold: 9,
    };
    assert_eq!(liveness_camera::load(&store, "lbp-1").await.unwrap(), None);
    liveness_camera::save(&store, &calibration("lbp-1", 0.31)).await.unwrap();
    liveness_camera::save(&store, &calibration("other", 0.9)).await.unwrap();
    liveness_camera::save(&store, &calibration("lbp-1", 0.42)).await.unwrap();
    assert_eq!(liveness_camera::load(&store, "lbp-1").await.unwrap(), Some(calibration("lbp-1", 0.42)), "the later one replaces it");
    assert!(store.clear_liveness_calibration("lbp-1").await.unwrap());
    assert!(!store.clear_liveness_calibration("lbp-1").await.unwrap());
    assert_eq!(liveness_camera::load(&store, "lbp-1").await.unwrap(), None);
    assert_eq!(liveness_camera::load(&store, "other").await.unwrap(), Some(calibration("other", 0.9)), "another model's is kept");
    store.close().await;
}

/// A matcher with a fixed threshold table (1e-2: 0.5, 1e-3: 0.7, 1e-4: 0.8, so duplicates at 0.9).
struct Table;

impl Matcher for Table {
    fn model_version(&self) -> &str {
        "v1"
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| probe.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
    }
    fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
        let threshold = if fmr >= 1e-2 {
            0.5
        } else if fmr >= 1e-3 {
            0.7
        } else {
            0.8
        };
        OperatingPoint { fmr, threshold }
    }
    fn max_cosine_scoring(&self) -> bool {
        true
    }
}

/// The site calibration scores the pairs of different subjects' templates of one model version,
/// sealed ones too, leaves out the pairs of ids that score like one person (naming them), and is
/// stored, replaced and removed per version.
/// A liveness challenge is taken once, by exactly one of several takers at the same moment (the
/// replicas answering it), and challenges past their expiry are swept when a new one is issued.
async fn a_challenge_is_taken_once_and_expired_ones_are_swept(url: String) {
    let store = Store::connect(&url, None).await.unwrap();
    store.insert_challenge("a", "[\"steps\"]", 5_000, 1_000).await.unwrap();
    store.insert_challenge("old", "[]", 1_500, 1_000).await.unwrap();
    assert_eq!(store.challenges_open().await.unwrap(), 2);
    let taken = store.take_challenge("a").await.unwrap().expect("issued");
    assert_eq!((taken.steps.as_str(), taken.expires_at_ms), ("[\"steps\"]", 5_000));
    assert_eq!(store.take_challenge("a").await.unwrap(), None, "a challenge is taken once");
    assert_eq!(store.take_challenge("never").await.unwrap(), None);
    // Issued at 2 000 ms: "old" expired at 1 500 and is swept.
    store.insert_challenge("b", "[]", 9_000, 2_000).await.unwrap();
    assert_eq!(store.challenges_open().await.unwrap(), 1);
    // Eight takers at once, as replicas answering the same challenge would: one gets it.
    let takers: Vec<_> = (0..8)
        .map(|_| {
            let store = store.clone();
            tokio::spawn(async move { store.take_challenge("b").await.unwrap().is_some() })
        })
        .collect();
    let mut got = 0;
    for taker in takers {
        got += taker.await.unwrap() as usize;
    }
    assert_eq!(got, 1, "exactly one taker gets the challenge");
    store.close().await;
}

async fn the_site_calibration_is_measured_on_sealed_templates_and_stored_per_version(url: String) {
    use rand::SeedableRng;
    use rand_distr::Distribution;
    let store = Store::connect(&url, Some(KeyRing::parse(K1).unwrap())).await.unwrap();
    assert!(store.model_versions().await.unwrap().is_empty());
    // 40 subjects of two templates under "v1" (random 32-dimensional faces: two photos of one
    // differ a little), 5 of them enrolled again as "dup{s}" with the same templates, and one
    // subject under "v2" that is no part of it.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let normal = rand_distr::StandardNormal;
    let mut faces = Vec::new();
    for s in 0..40 {
        let face: Vec<f32> = (0..32).map(|_| normal.sample(&mut rng)).collect();
        let again: Vec<f32> = face.iter().map(|v| v + 0.1 * Distribution::<f32>::sample(&normal, &mut rng)).collect();
        let templates = [Template::new("v1", face), Template::new("v1", again)];
        store.enroll(&SubjectId::parse(&format!("s{s:02}")).unwrap(), &templates).await.unwrap();
        faces.push(templates);
    }
    for (s, templates) in faces.iter().enumerate().take(5) {
        store.enroll(&SubjectId::parse(&format!("dup{s}")).unwrap(), templates).await.unwrap();
    }
    store.enroll(&SubjectId::parse("other").unwrap(), &[Template::new("v2", vec![1.0; 32])]).await.unwrap();
    assert_eq!(store.model_versions().await.unwrap(), ["v1", "v2"]);
    let site = site::measure(&store, &Table).await.unwrap();
    // 90 templates: 4,005 pairs, 45 within a subject, 5 × 4 of the duplicates left out.
    assert_eq!((site.subjects, site.templates, site.impostor_pairs), (45, 90, 90 * 89 / 2 - 45 - 20));
    assert_eq!(site.duplicate_pairs_left_out, 20);
    assert!((site.duplicate_threshold.unwrap() - 0.9).abs() < 1e-6, "0.8 + (0.8 - 0.7): {:?}", site.duplicate_threshold);
    let mut named: Vec<[String; 2]> = site.suspected_duplicates.iter().map(|d| d.subjects.clone()).collect();
    named.sort();
    assert_eq!(named, (0..5).map(|s| [format!("dup{s}"), format!("s{s:02}")]).collect::<Vec<_>>());
    assert_eq!(site.points.iter().map(|p| p.fmr).collect::<Vec<_>>(), [1e-2]);
    assert!(site.points[0].threshold < 0.9, "no pair kept reaches the duplicate threshold");
    assert_eq!(site::load(&store, &Table).await.unwrap(), SiteStatus::None);
    site::save(&store, &site).await.unwrap();
    let mut raised = site.clone();
    raised.points[0].threshold += 0.1;
    site::save(&store, &raised).await.unwrap();
    // Stored without the suspected ids and the tails' ids: a calibration names no subject.
    let stored = raised.as_stored();
    assert!(stored.suspected_duplicates.is_empty() && stored.pull.iter().all(|p| p.tail_ids.is_empty()));
    assert!(raised.pull.iter().any(|p| !p.tail_ids.is_empty()), "the measured one names them");
    assert_eq!(site::load(&store, &Table).await.unwrap(), SiteStatus::InUse(std::sync::Arc::new(stored)));
    assert_eq!(store.site_calibration("v2").await.unwrap(), None);
    assert_eq!(store.calibrated_versions().await.unwrap(), ["v1"]);
    assert!(store.clear_site_calibration("v1").await.unwrap());
    assert!(!store.clear_site_calibration("v1").await.unwrap());
    assert_eq!(site::load(&store, &Table).await.unwrap(), SiteStatus::None);
    store.close().await;
}

pub struct TempDir(std::path::PathBuf);

impl TempDir {
    pub fn new() -> TempDir {
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("facegate-backends-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }
    pub fn sqlite_url(&self) -> String {
        format!("sqlite://{}", self.0.join("t.db").display())
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn id(s: &str) -> SubjectId {
    SubjectId::parse(s).unwrap()
}

fn template(version: &str, v: &[f32]) -> Template {
    Template::new(version, v.to_vec())
}

/// A vector different per `seed`.
fn marked(seed: f32) -> Template {
    Template::new("m1", (0..32).map(|i| 1234.5678 + seed + i as f32 * 0.001).collect())
}

fn ring(text: &str) -> Option<KeyRing> {
    Some(KeyRing::parse(text).unwrap())
}

/// A connection of the test's own to the same database, to look at and alter rows.
async fn raw(url: &str) -> AnyPool {
    sqlx::any::install_default_drivers();
    AnyPool::connect(url).await.unwrap()
}

async fn scan(store: &Store, version: &str) -> Vec<(String, Result<Vec<Template>, String>)> {
    store.gallery(version, Vec::new(), |out, s, t| out.push((s.to_string(), t.map_err(|e| e.to_string())))).await.unwrap()
}

/// The identification gallery's reads: in parts (start-up, several connections) that together are
/// the whole scan, each subject in exactly one part; and the shortlist's templates in one statement.
async fn the_gallery_reads_in_parts_and_by_subject(url: String) {
    let store = Store::connect(&url, None).await.unwrap();
    for i in 0..10 {
        let mut templates = vec![marked(i as f32)];
        if i == 4 {
            templates.push(marked(40.0));
        }
        store.enroll(&id(&format!("s{i}")), &templates).await.unwrap();
    }
    store.enroll(&id("other"), &[template("m2", &[1.0])]).await.unwrap();
    let whole = scan(&store, "m1").await;
    assert_eq!(whole.len(), 10);
    for parts in [1, 3, 4, 11, 40] {
        let cut = store.gallery_parts("m1", parts).await.unwrap();
        assert!(!cut.is_empty() && cut.len() <= parts, "{parts} parts: {cut:?}");
        let mut joined = Vec::new();
        for part in &cut {
            joined =
                store.gallery_part("m1", part, joined, |out, s, t| out.push((s.to_string(), t.map_err(|e| e.to_string())))).await.unwrap();
        }
        assert_eq!(joined, whole, "{parts} parts");
    }
    assert_eq!(store.gallery_parts("m3", 4).await.unwrap().len(), 1, "an empty version is one part");

    let found = store.templates_of(&[id("s7"), id("s4"), id("nobody"), id("other")], "m1").await.unwrap();
    assert_eq!(found, [("s4".to_string(), vec![marked(4.0), marked(40.0)]), ("s7".to_string(), vec![marked(7.0)])]);
    assert!(store.templates_of(&[], "m1").await.unwrap().is_empty());
    store.close().await;
}

async fn enroll_list_read_and_delete(url: String) {
    let store = Store::connect(&url, None).await.unwrap();
    let postgres = store.backend() == Backend::Postgres;
    assert_eq!(store.backend(), if url.starts_with("sqlite:") { Backend::Sqlite } else { Backend::Postgres });
    assert_eq!(store.change_version().await.unwrap(), postgres.then_some(0));
    assert_eq!(store.enroll(&id("alice"), &[template("m1", &[1.0, 0.0]), template("m1", &[0.0, 1.0])]).await.unwrap(), 2);
    assert_eq!(store.enroll(&id("alice"), &[template("m2", &[0.5, 0.5, 0.0])]).await.unwrap(), 3);
    assert_eq!(store.enroll(&id("bob"), &[template("m1", &[0.6, 0.8])]).await.unwrap(), 1);
    // Ids sort bytewise on both (upper case before lower case).
    assert_eq!(store.enroll(&id("Zed"), &[template("m1", &[0.8, 0.6])]).await.unwrap(), 1);
    assert_eq!(store.change_version().await.unwrap(), postgres.then_some(4));

    let alice = store.templates(&id("alice")).await.unwrap().unwrap();
    assert_eq!(alice, [template("m1", &[1.0, 0.0]), template("m1", &[0.0, 1.0]), template("m2", &[0.5, 0.5, 0.0])]);
    assert!(store.templates(&id("carol")).await.unwrap().is_none());

    let gallery = scan(&store, "m1").await;
    let gallery: Vec<_> = gallery.iter().map(|(s, t)| (s.as_str(), t.as_ref().unwrap().len())).collect();
    assert_eq!(gallery, [("Zed", 1), ("alice", 2), ("bob", 1)]);

    let list = store.list_subjects(None, 10).await.unwrap();
    assert_eq!(list.iter().map(|s| (s.id.as_str(), s.templates)).collect::<Vec<_>>(), [("Zed", 1), ("alice", 3), ("bob", 1)]);
    let alice_summary = &list[1];
    // The same timestamp form on both backends: 2026-11-24T14:00:00.000Z.
    for stamp in [&alice_summary.created_at, &alice_summary.updated_at] {
        assert_eq!(stamp.len(), 24, "{stamp}");
        assert!(stamp.ends_with('Z') && stamp.as_bytes()[10] == b'T' && stamp.as_bytes()[19] == b'.', "{stamp}");
    }
    assert!(alice_summary.updated_at >= alice_summary.created_at);
    assert_eq!(store.list_subjects(Some(&id("alice")), 10).await.unwrap().len(), 1);
    assert_eq!(store.list_subjects(None, 1).await.unwrap().len(), 1);

    let detail = store.subject(&id("alice")).await.unwrap().unwrap();
    assert_eq!(detail.templates, 3);
    assert_eq!(
        detail.model_versions,
        [VersionCount { model_version: "m1".into(), templates: 2 }, VersionCount { model_version: "m2".into(), templates: 1 }]
    );

    assert_eq!(store.delete_subject(&id("alice")).await.unwrap(), Some(3));
    assert_eq!(store.delete_subject(&id("alice")).await.unwrap(), None);
    assert!(store.subject(&id("alice")).await.unwrap().is_none());
    // Foreign keys cascade: no orphan template is left. An unknown subject's deletion is no change.
    assert_eq!(store.counts().await.unwrap(), (2, 2));
    assert_eq!(store.change_version().await.unwrap(), postgres.then_some(5));
    store.ping().await.unwrap();
    store.close().await;
}

async fn a_failed_enrollment_stores_nothing(url: String) {
    let store = Store::connect(&url, None).await.unwrap();
    store.enroll(&id("bob"), &[template("m1", &[0.5])]).await.unwrap();
    let version = store.change_version().await.unwrap();
    // The second template violates the schema (empty vector): the whole enrolment rolls back.
    let err = store.enroll(&id("alice"), &[template("m1", &[1.0]), template("m1", &[])]).await;
    assert!(matches!(err, Err(StoreError::Database(_))), "{err:?}");
    assert!(store.templates(&id("alice")).await.unwrap().is_none());
    // Nor into an existing subject.
    assert!(store.enroll(&id("bob"), &[template("m1", &[1.0]), template("m1", &[])]).await.is_err());
    assert_eq!(store.templates(&id("bob")).await.unwrap().unwrap(), [template("m1", &[0.5])]);
    assert_eq!(store.counts().await.unwrap(), (1, 1));
    assert_eq!(store.change_version().await.unwrap(), version, "a rolled back enrolment is no change");
    store.close().await;
}

async fn sealed_round_trip_and_tampered_rows_refused(url: String) {
    let store = Store::connect(&url, ring(K1)).await.unwrap();
    assert!(store.encrypts());
    store.enroll(&id("alice"), &[marked(0.0), marked(1.0)]).await.unwrap();
    store.enroll(&id("alice"), &[marked(2.0)]).await.unwrap();
    assert_eq!(store.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0), marked(1.0), marked(2.0)]);
    let db = raw(&url).await;
    let lengths: Vec<i64> = sqlx::query_scalar("SELECT length(vector) FROM templates").fetch_all(&db).await.unwrap();
    assert_eq!(lengths, [4 * 32 + 28; 3]);

    // Another key, or none, cannot read them: a server fault, never a score.
    let other = Store::connect(&url, ring(K2)).await.unwrap();
    assert!(matches!(other.templates(&id("alice")).await, Err(StoreError::DataKey { .. })));
    assert!(matches!(other.enroll(&id("alice"), &[marked(3.0)]).await, Err(StoreError::DataKey { .. })));
    other.close().await;
    let plain = Store::connect(&url, None).await.unwrap();
    assert!(matches!(plain.templates(&id("alice")).await, Err(StoreError::NoKey { .. })));
    assert!(matches!(plain.enroll(&id("alice"), &[marked(3.0)]).await, Err(StoreError::NoKey { .. })));
    assert_eq!(plain.counts().await.unwrap(), (1, 3), "a refused enrolment stores nothing");
    plain.close().await;

    for (subject, seed) in [("bob", 1.0), ("carol", 2.0), ("dave", 3.0)] {
        store.enroll(&id(subject), &[marked(seed)]).await.unwrap();
    }
    let exec = |sql: &'static str| {
        let db = db.clone();
        async move { sqlx::query(sql).execute(&db).await.unwrap() }
    };
    // One bit of one of alice's vectors flipped.
    let (row, mut vector): (i64, Vec<u8>) =
        sqlx::query_as("SELECT id, vector FROM templates WHERE subject_id = 'alice' ORDER BY id LIMIT 1").fetch_one(&db).await.unwrap();
    vector[20] ^= 1;
    sqlx::query("UPDATE templates SET vector = $1 WHERE id = $2").bind(vector).bind(row).execute(&db).await.unwrap();
    // bob's template moved to carol (carol's own data key does not open it either).
    exec("UPDATE templates SET subject_id = 'carol' WHERE subject_id = 'bob'").await;
    // dave's model version relabelled.
    exec("UPDATE templates SET model_version = 'm2' WHERE subject_id = 'dave'").await;
    for subject in ["alice", "carol", "dave"] {
        let read = store.templates(&id(subject)).await;
        assert!(matches!(read, Err(StoreError::CorruptTemplate { .. })), "{subject}: {read:?}");
    }
    assert_eq!(store.templates(&id("bob")).await.unwrap().unwrap(), []);
    // A data key swapped between subjects does not open.
    store.enroll(&id("erin"), &[marked(4.0)]).await.unwrap();
    exec("UPDATE subjects SET data_key = (SELECT data_key FROM subjects WHERE id = 'alice') WHERE id = 'erin'").await;
    assert!(matches!(store.templates(&id("erin")).await, Err(StoreError::DataKey { .. })));
    // The gallery scan hands each unreadable subject its error and goes on.
    store.enroll(&id("frank"), &[marked(5.0)]).await.unwrap();
    let scanned = scan(&store, "m1").await;
    let readable: Vec<&str> = scanned.iter().filter(|(_, t)| t.is_ok()).map(|(s, _)| s.as_str()).collect();
    let refused: Vec<&str> = scanned.iter().filter(|(_, t)| t.is_err()).map(|(s, _)| s.as_str()).collect();
    assert_eq!((readable, refused), (vec!["frank"], vec!["alice", "carol", "erin"]));
    db.close().await;
    store.close().await;
}

async fn rekey_seals_then_rotates(url: String) {
    let plain = Store::connect(&url, None).await.unwrap();
    plain.enroll(&id("alice"), &[marked(0.0)]).await.unwrap();
    plain.enroll(&id("bob"), &[marked(1.0), marked(2.0)]).await.unwrap();
    plain.enroll(&id("carol"), &[marked(3.0)]).await.unwrap();
    assert!(matches!(plain.rekey(|_| {}).await, Err(StoreError::Refused(_))));
    plain.close().await;

    // A key set: plain subjects stay readable; an enrolment seals its subject; rekey the rest.
    let keyed = Store::connect(&url, ring(K1)).await.unwrap();
    assert_eq!(keyed.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0)]);
    keyed.enroll(&id("carol"), &[marked(4.0)]).await.unwrap();
    let mut steps = 0;
    let report = keyed.rekey(|_| steps += 1).await.unwrap();
    assert_eq!((report, steps), (RekeyReport { rewrapped: 0, sealed: 2, templates_sealed: 3 }, 2));
    assert_eq!(keyed.rekey(|_| {}).await.unwrap(), RekeyReport::default(), "nothing left to do");
    let db = raw(&url).await;
    let sealed: i64 =
        sqlx::query_scalar("SELECT count(*) FROM templates WHERE length(vector) = 4 * dimension + 28").fetch_one(&db).await.unwrap();
    assert_eq!(sealed, 5);
    db.close().await;
    keyed.close().await;

    // Rotation: K2 current, K1 still readable; after rekey, K2 alone reads everything.
    let rotating = Store::connect(&url, ring(&format!("{K2}\n{K1}"))).await.unwrap();
    assert_eq!(rotating.templates(&id("bob")).await.unwrap().unwrap(), [marked(1.0), marked(2.0)]);
    assert_eq!(rotating.rekey(|_| {}).await.unwrap(), RekeyReport { rewrapped: 3, sealed: 0, templates_sealed: 0 });
    rotating.close().await;
    let rotated = Store::connect(&url, ring(K2)).await.unwrap();
    assert_eq!(rotated.templates(&id("carol")).await.unwrap().unwrap(), [marked(3.0), marked(4.0)]);
    assert_eq!(rotated.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0)]);
    rotated.close().await;
    let old_only = Store::connect(&url, ring(K1)).await.unwrap();
    assert!(matches!(old_only.templates(&id("alice")).await, Err(StoreError::DataKey { source: CipherError::UnknownKey(_), .. })));
    old_only.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sqlite_has_no_change_feed() {
    let dir = TempDir::new();
    let store = Store::connect(&dir.sqlite_url(), None).await.unwrap();
    assert_eq!(store.change_version().await.unwrap(), None);
    assert!(store.watch().await.unwrap().is_none());
    store.close().await;
}

/// Six stores connecting at once to a fresh database: all succeed, and the migrations ran once
/// (sqlx's migrator holds a PostgreSQL advisory lock while it migrates).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_connects_migrate_once() {
    let url = crate::postgres_or_skip!("store_backends::concurrent_connects_migrate_once");
    let connecting: Vec<_> = (0..6)
        .map(|_| {
            tokio::spawn({
                let url = url.clone();
                async move { Store::connect(&url, None).await }
            })
        })
        .collect();
    let mut stores = Vec::new();
    for connect in connecting {
        stores.push(connect.await.unwrap().unwrap());
    }
    let db = raw(&url).await;
    let migrations: Vec<i64> = sqlx::query_scalar("SELECT version FROM _sqlx_migrations ORDER BY version").fetch_all(&db).await.unwrap();
    let files = std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/migrations/postgres")).unwrap().count();
    assert_eq!(migrations.len(), files, "each migration recorded once: {migrations:?}");
    let counters: i64 = sqlx::query_scalar("SELECT count(*) FROM change_counter").fetch_one(&db).await.unwrap();
    assert_eq!(counters, 1, "the counter row was inserted once");
    // All six work on the one schema.
    for (i, store) in stores.iter().enumerate() {
        store.enroll(&id(&format!("s{i}")), &[marked(i as f32)]).await.unwrap();
    }
    assert_eq!(stores[0].counts().await.unwrap(), (6, 6));
    assert_eq!(stores[5].change_version().await.unwrap(), Some(6));
    db.close().await;
    for store in stores {
        store.close().await;
    }
}

/// Waits for the next change, failing the test rather than hanging.
async fn next_change(feed: &mut facegate_store::ChangeFeed) -> StoreChange {
    tokio::time::timeout(Duration::from_secs(20), feed.next()).await.expect("a change within 20 s").unwrap()
}

/// Two stores on one database: what one commits, the other's feed reports, with the versions
/// the counter took, in commit order; a rolled back enrolment is not reported.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_change_feed_follows_another_store() {
    let url = crate::postgres_or_skip!("store_backends::the_change_feed_follows_another_store");
    let a = Store::connect(&url, None).await.unwrap();
    let b = Store::connect(&url, None).await.unwrap();
    let mut feed = b.watch().await.unwrap().expect("a feed on PostgreSQL");
    let subject = |s: &str, version: i64| StoreChange::Subject { subject: s.to_string(), version };

    a.enroll(&id("alice"), &[marked(0.0)]).await.unwrap();
    assert_eq!(next_change(&mut feed).await, subject("alice", 1));
    a.enroll(&id("bob"), &[marked(1.0)]).await.unwrap();
    assert!(a.enroll(&id("carol"), &[marked(2.0), template("m1", &[])]).await.is_err());
    a.enroll(&id("alice"), &[marked(3.0)]).await.unwrap();
    assert_eq!(next_change(&mut feed).await, subject("bob", 2));
    assert_eq!(next_change(&mut feed).await, subject("alice", 3));
    assert_eq!(b.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0), marked(3.0)], "read-through sees it");

    assert_eq!(a.delete_subject(&id("alice")).await.unwrap(), Some(2));
    assert_eq!(a.delete_subject(&id("alice")).await.unwrap(), None);
    assert_eq!(next_change(&mut feed).await, subject("alice", 4));
    assert!(b.templates(&id("alice")).await.unwrap().is_none());
    assert_eq!(b.change_version().await.unwrap(), Some(4));

    // Concurrent writers on both stores: every version from 5 on is reported exactly once.
    let writers: Vec<_> = [a.clone(), b.clone()]
        .into_iter()
        .enumerate()
        .map(|(w, store)| {
            tokio::spawn(async move {
                for i in 0..10 {
                    store.enroll(&id(&format!("w{w}-{i}")), &[marked(i as f32)]).await.unwrap();
                }
            })
        })
        .collect();
    for writer in writers {
        writer.await.unwrap();
    }
    let mut versions = Vec::new();
    for _ in 0..20 {
        match next_change(&mut feed).await {
            StoreChange::Subject { version, .. } => versions.push(version),
            StoreChange::Resync => panic!("no connection was lost"),
        }
    }
    assert_eq!(versions, (5..25).collect::<Vec<i64>>(), "notified in commit order");
    a.close().await;
    b.close().await;
}

/// A feed whose connection is cut reconnects by itself and says `Resync` (what was notified
/// meanwhile is lost), then goes on reporting changes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_feed_connection_reports_a_resync() {
    let url = crate::postgres_or_skip!("store_backends::a_lost_feed_connection_reports_a_resync");
    let store = Store::connect(&url, None).await.unwrap();
    let mut feed = store.watch().await.unwrap().unwrap();
    store.enroll(&id("alice"), &[marked(0.0)]).await.unwrap();
    assert!(matches!(next_change(&mut feed).await, StoreChange::Subject { version: 1, .. }));

    let db = raw(&url).await;
    let cut: Vec<bool> = sqlx::query_scalar(
        "SELECT pg_terminate_backend(pid) FROM pg_stat_activity
         WHERE datname = current_database() AND query LIKE 'LISTEN%' AND pid <> pg_backend_pid()",
    )
    .fetch_all(&db)
    .await
    .unwrap();
    assert_eq!(cut, [true], "the feed's one listening connection");
    assert_eq!(next_change(&mut feed).await, StoreChange::Resync);
    store.enroll(&id("bob"), &[marked(1.0)]).await.unwrap();
    assert_eq!(next_change(&mut feed).await, StoreChange::Subject { subject: "bob".into(), version: 2 });
    db.close().await;
    store.close().await;
}

/// `backup` and `restore` are SQLite file operations: on PostgreSQL they refuse, naming
/// pg_dump and pg_restore.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backup_and_restore_refuse_postgres() {
    let url = crate::postgres_or_skip!("store_backends::backup_and_restore_refuse_postgres");
    let store = Store::connect(&url, None).await.unwrap();
    let dir = TempDir::new();
    let refused = store.backup(&dir.0.join("b.db")).await;
    assert!(matches!(refused, Err(StoreError::Refused(ref m)) if m.contains("pg_dump")), "{refused:?}");
    assert!(!dir.0.join("b.db").exists());
    let refused = facegate_store::restore(&dir.0.join("b.db"), &url, true).await;
    assert!(matches!(refused, Err(StoreError::Refused(ref m)) if m.contains("pg_restore")), "{refused:?}");
    store.close().await;
}

/// The bytes of `relations`' files (main fork, every segment) under the server's data directory,
/// after a CHECKPOINT has written every dirty page; `None` when the files cannot be read here
/// (a server of `FACEGATE_TEST_POSTGRES` on another machine or under another user).
async fn relation_files(db: &AnyPool, relations: &[&str]) -> Option<Vec<u8>> {
    sqlx::query("CHECKPOINT").execute(db).await.unwrap();
    let data: String = sqlx::query_scalar("SELECT current_setting('data_directory')").fetch_one(db).await.unwrap();
    let mut bytes = Vec::new();
    for relation in relations {
        let path: String = sqlx::query_scalar("SELECT pg_relation_filepath($1)").bind(relation).fetch_one(db).await.unwrap();
        let main = std::path::Path::new(&data).join(path);
        bytes.extend(std::fs::read(&main).ok()?);
        for segment in 1.. {
            match std::fs::read(format!("{}.{segment}", main.display())) {
                Ok(more) => bytes.extend(more),
                Err(_) => break,
            }
        }
    }
    Some(bytes)
}

fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle)
}

const RELATIONS: [&str; 5] = ["subjects", "subjects_pkey", "templates", "templates_by_subject", "templates_by_model"];

/// The WAL segments' bytes (pg_wal under the data directory).
fn wal_files(data: &str) -> Vec<u8> {
    let mut bytes = Vec::new();
    for entry in std::fs::read_dir(std::path::Path::new(data).join("pg_wal")).unwrap().flatten() {
        if entry.file_type().unwrap().is_file() {
            bytes.extend(std::fs::read(entry.path()).unwrap());
        }
    }
    bytes
}

/// PostgreSQL does not erase in place: a deleted subject's id and plain template bytes stay
/// readable in the tables' files after DELETE, some of them after VACUUM (which frees the space
/// without zeroing it), and in the WAL; VACUUM FULL rewrites the tables into new files without
/// them. With a template key the files never hold a plain vector; what a deletion leaves is
/// sealed bytes and the subject's data key wrapped by the master key. (docs/storage.md.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_erasure_leaves_what_the_docs_say() {
    let test = "store_backends::postgres_erasure_leaves_what_the_docs_say";
    let plain_url = crate::postgres_or_skip!(test);
    let keyed_url = crate::postgres_or_skip!(test);
    let erased = "erasure-subject-7f3a";
    let erased_vectors = [marked(10.0), marked(20.0)];
    let vector_bytes = |t: &Template| t.vector.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
    let needles: Vec<Vec<u8>> = erased_vectors.iter().map(|t| vector_bytes(t)[..16].to_vec()).collect();
    let vectors_in = |files: &[u8]| needles.iter().filter(|v| contains(files, v)).count();

    // No key: plain vectors.
    let store = Store::connect(&plain_url, None).await.unwrap();
    let db = raw(&plain_url).await;
    store.enroll(&id("keeper"), &[marked(30.0)]).await.unwrap();
    store.enroll(&id(erased), &erased_vectors).await.unwrap();
    store.enroll(&id("later"), &[marked(40.0)]).await.unwrap();
    let Some(before) = relation_files(&db, &RELATIONS).await else {
        eprintln!("SKIPPED {test}: the server's files are not readable here");
        return;
    };
    assert!(contains(&before, erased.as_bytes()) && vectors_in(&before) == 2, "the test must see the plain bytes first");
    store.delete_subject(&id(erased)).await.unwrap();
    let after_delete = relation_files(&db, &RELATIONS).await.unwrap();
    assert!(contains(&after_delete, erased.as_bytes()) && vectors_in(&after_delete) == 2, "DELETE leaves the rows in the files");
    let data: String = sqlx::query_scalar("SELECT current_setting('data_directory')").fetch_one(&db).await.unwrap();
    assert_eq!(vectors_in(&wal_files(&data)), 2, "the WAL holds the inserted rows");
    sqlx::query("VACUUM subjects, templates").execute(&db).await.unwrap();
    let after_vacuum = relation_files(&db, &RELATIONS).await.unwrap();
    assert!(contains(&after_vacuum, erased.as_bytes()) || vectors_in(&after_vacuum) > 0, "VACUUM does not zero the freed space");
    sqlx::query("VACUUM FULL subjects, templates").execute(&db).await.unwrap();
    let after_full = relation_files(&db, &RELATIONS).await.unwrap();
    assert!(!contains(&after_full, erased.as_bytes()) && vectors_in(&after_full) == 0, "VACUUM FULL rewrites the tables without them");
    assert!(contains(&after_full, &vector_bytes(&marked(30.0))[..16]), "the others stay");
    db.close().await;
    store.close().await;

    // With a key: never a plain vector, in the tables or the WAL; a deletion leaves sealed bytes
    // and the wrapped data key.
    let store = Store::connect(&keyed_url, ring(K1)).await.unwrap();
    let db = raw(&keyed_url).await;
    let sealed_vectors = [marked(50.0), marked(60.0)];
    let needles: Vec<Vec<u8>> = sealed_vectors.iter().map(|t| vector_bytes(t)[..16].to_vec()).collect();
    let vectors_in = |files: &[u8]| needles.iter().filter(|v| contains(files, v)).count();
    store.enroll(&id(erased), &sealed_vectors).await.unwrap();
    let wrapped: Vec<u8> = sqlx::query_scalar("SELECT data_key FROM subjects WHERE id = $1").bind(erased).fetch_one(&db).await.unwrap();
    let sealed: Vec<Vec<u8>> = sqlx::query_scalar("SELECT vector FROM templates").fetch_all(&db).await.unwrap();
    store.delete_subject(&id(erased)).await.unwrap();
    let files = relation_files(&db, &RELATIONS).await.unwrap();
    assert_eq!(vectors_in(&files), 0);
    assert_eq!(vectors_in(&wal_files(&data)), 0);
    assert!(contains(&files, &wrapped) && sealed.iter().all(|s| contains(&files, s)), "what a deletion leaves: sealed bytes, wrapped key");
    db.close().await;
    store.close().await;
}

/// Two stores (replicas) enrolling into and deleting the same subjects at once: every
/// transaction takes the subject's row first and the change counter last, so none deadlocks (a
/// deadlock would be an error here) and each enrolment is all or nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_writing_the_same_subjects_do_not_deadlock() {
    let url = crate::postgres_or_skip!("store_backends::replicas_writing_the_same_subjects_do_not_deadlock");
    let a = Store::connect(&url, ring(K1)).await.unwrap();
    let b = Store::connect(&url, ring(K1)).await.unwrap();
    let writers: Vec<_> = [a.clone(), b.clone(), a.clone(), b.clone()]
        .into_iter()
        .enumerate()
        .map(|(w, store)| {
            tokio::spawn(async move {
                for i in 0..30 {
                    let subject = id(["shared-1", "shared-2"][i % 2]);
                    if (i + w) % 7 == 6 {
                        store.delete_subject(&subject).await.unwrap();
                    } else {
                        store.enroll(&subject, &[marked(w as f32), marked(i as f32)]).await.unwrap();
                    }
                }
            })
        })
        .collect();
    for writer in writers {
        writer.await.unwrap();
    }
    for subject in ["shared-1", "shared-2"] {
        if let Some(templates) = a.templates(&id(subject)).await.unwrap() {
            assert!(!templates.is_empty() && templates.len() % 2 == 0, "{subject}: {}", templates.len());
        }
    }
    let (_, stored) = a.counts().await.unwrap();
    assert_eq!(stored % 2, 0);
    a.close().await;
    b.close().await;
}

/// A feed whose database is gone for good (dropped, so every reconnection is refused) fails once
/// its reconnection limit has passed, rather than waiting forever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_feed_fails_when_its_database_is_gone() {
    let url = crate::postgres_or_skip!("store_backends::a_feed_fails_when_its_database_is_gone");
    let store = Store::connect(&url, None).await.unwrap();
    let mut feed = store.watch().await.unwrap().unwrap();
    feed.give_up_after(Duration::from_secs(1));
    store.close().await;
    let (server, name) = url.rsplit_once('/').unwrap();
    let admin = raw(&format!("{server}/postgres")).await;
    sqlx::query(&format!("DROP DATABASE {name} WITH (FORCE)")).execute(&admin).await.unwrap();
    admin.close().await;
    let started = std::time::Instant::now();
    let outcome = tokio::time::timeout(Duration::from_secs(30), feed.next()).await.expect("gives up within 30 s");
    assert!(outcome.is_err(), "{outcome:?}");
    assert!(started.elapsed() >= Duration::from_secs(1), "{:?}", started.elapsed());
}
