//! Fill a store with synthetic subjects for the identification load test
//! (scripts/loadtest-replicas.sh): each gets one random template of the model version and
//! dimension of an enrolled subject (`LIKE`, enrolled through the API with a real photo), ids
//! `synthetic-0000000`…, through `Store::enroll` (the service's own transaction), `CONCURRENCY`
//! at a time.
//!
//!   cargo run --release --example fill_gallery -- DATABASE_URL LIKE SUBJECTS [CONCURRENCY]

use std::time::Instant;

use facegate::recognize::Template;
use facegate::service::SubjectId;
use facegate::store::Store;
use rand::{Rng, SeedableRng};

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
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
