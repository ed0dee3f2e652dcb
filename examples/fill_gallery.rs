//! Fill a store with synthetic subjects for the identification load test
//! (scripts/loadtest-replicas.sh): each gets one random template of the model version and
//! dimension of an enrolled subject (`LIKE`, enrolled through the API with a real photo), ids
//! `synthetic-0000000`…, through `Store::enroll` (the service's own transaction), `CONCURRENCY`
//! at a time.
//!
//!   cargo run --release --example fill_gallery -- DATABASE_URL LIKE SUBJECTS [CONCURRENCY]
//!
//! `--bulk` fills a SQLite database at disk speed instead, for the ten-million gallery
//! (`examples/gallery_scale.rs --database`): the store's schema and on-disk form (plain
//! little-endian vectors, as a store without a template key writes them), written by plain
//! INSERTs in transactions of 100,000 subjects with `synchronous = OFF`; the store is opened
//! first so its migrations create the schema.
//!
//!   cargo run --release --example fill_gallery -- --bulk sqlite://PATH MODEL_VERSION DIMENSION SUBJECTS

use std::time::Instant;

use facegate_core::SubjectId;
use facegate_core::template::Template;
use facegate_store::Store;
use rand::{Rng, SeedableRng};

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--bulk") {
        return bulk(&args[1..]).await;
    }
    let [database, like, subjects, rest @ ..] = &args[..] else {
        eprintln!("usage: fill_gallery DATABASE_URL LIKE SUBJECTS [CONCURRENCY]");
        std::process::exit(2);
    };
    let subjects: usize = subjects.parse().expect("SUBJECTS is a number");
    let concurrency: usize = rest.first().map_or(16, |c| c.parse().expect("CONCURRENCY is a number"));
    let store = Store::connect(database, None).await.expect("the database opens");
    let like = SubjectId::parse(like).expect("LIKE is a subject id");
    let example = store.templates(&like).await.expect("reads").expect("LIKE is enrolled").remove(0);
    let (version, dimension) = (example.model_version.clone(), example.vector.len());
    let started = Instant::now();
    let mut tasks = tokio::task::JoinSet::new();
    for worker in 0..concurrency {
        let (store, version) = (store.clone(), version.clone());
        tasks.spawn(async move {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(worker as u64);
            for i in (worker..subjects).step_by(concurrency) {
                let vector: Vec<f32> = (0..dimension).map(|_| rng.random_range(-1.0f32..1.0)).collect();
                let subject = SubjectId::parse(&format!("synthetic-{i:07}")).expect("a valid id");
                store.enroll(&subject, &[Template::new(&version, vector)]).await.expect("enrols");
            }
        });
    }
    while let Some(done) = tasks.join_next().await {
        done.expect("a filling task does not panic");
    }
    let seconds = started.elapsed().as_secs_f64();
    println!("{subjects} subjects of {version} ({dimension} values) in {seconds:.1} s ({:.0} enrolments/s)", subjects as f64 / seconds);
    store.close().await;
}

async fn bulk(args: &[String]) {
    use sqlx::{Connection, Executor};
    let [database, version, dimension, subjects] = args else {
        eprintln!("usage: fill_gallery --bulk sqlite://PATH MODEL_VERSION DIMENSION SUBJECTS");
        std::process::exit(2);
    };
    let (dimension, subjects): (usize, usize) =
        (dimension.parse().expect("DIMENSION is a number"), subjects.parse().expect("SUBJECTS is a number"));
    Store::connect(database, None).await.expect("the database opens").close().await;
    let mut db = sqlx::SqliteConnection::connect(database).await.expect("the database opens");
    db.execute("PRAGMA synchronous = OFF").await.expect("pragma");
    let started = Instant::now();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(15);
    const BATCH: usize = 100_000;
    for first in (0..subjects).step_by(BATCH) {
        let mut tx = db.begin().await.expect("begins");
        for i in first..(first + BATCH).min(subjects) {
            let subject = format!("synthetic-{i:08}");
            let vector: Vec<f32> = (0..dimension).map(|_| rng.random_range(-1.0f32..1.0)).collect();
            sqlx::query("INSERT INTO subjects (id) VALUES (?)").bind(&subject).execute(&mut *tx).await.expect("inserts");
            sqlx::query("INSERT INTO templates (subject_id, model_version, dimension, vector) VALUES (?, ?, ?, ?)")
                .bind(&subject)
                .bind(version)
                .bind(dimension as i64)
                .bind(facegate_store::vector_to_blob(&vector))
                .execute(&mut *tx)
                .await
                .expect("inserts");
        }
        tx.commit().await.expect("commits");
        eprintln!("{} subjects, {:.0} s", (first + BATCH).min(subjects), started.elapsed().as_secs_f64());
    }
    println!("{subjects} subjects of {version} ({dimension} values) in {:.1} s", started.elapsed().as_secs_f64());
}
