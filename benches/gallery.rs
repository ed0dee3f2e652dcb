//! `/identify`'s search over the in-memory gallery (`service::gallery::Gallery::search`) in the
//! same run: the quantised gallery the service holds for best-cosine matchers (one scan of 4-bit
//! codes to a shortlist, which the service then re-scores from the store), the exact float
//! gallery (one pass of dot products over a contiguous matrix), and the per-subject
//! `score_each_subject` the gallery replaced, on synthetic 256-value templates (the default fusion
//! recognizer's size; one per subject) at 10k, 100k and 1M. The matcher scores by the best
//! cosine, as the deep recognizers do. Times are the benchmark thread's CPU time
//! (`benches/common`): the search is single-threaded. The per-subject path is timed up to 100k
//! (at 1M its input alone would take gigabytes).
//!
//! `cargo bench --bench gallery`; memory, recall and ten million templates:
//! `cargo run --release --example gallery_scale`.

use criterion::{BatchSize, BenchmarkId, Criterion, black_box};
use facegate_core::template::{OperatingPoint, Template};
use facegate_service::Matcher;
use facegate_service::gallery::{Found, Gallery, Precision};
use rand::{Rng, SeedableRng};

mod common;

const DIMS: usize = 256;

/// The deep recognizer's scoring (the best cosine), with a fixed threshold.
struct MaxCosine;

impl Matcher for MaxCosine {
    fn model_version(&self) -> &str {
        "bench"
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| probe.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
    }
    fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
        OperatingPoint { fmr, threshold: 0.6 }
    }
    fn max_cosine_scoring(&self) -> bool {
        true
    }
}

fn template(rng: &mut impl Rng) -> Template {
    Template::new("bench", (0..DIMS).map(|_| rng.random_range(-1.0f32..1.0)).collect())
}

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(15);
    let probe = template(&mut rng);
    let mut group = c.benchmark_group("identify");
    for n in [10_000usize, 100_000, 1_000_000] {
        let subjects: Vec<(String, Vec<Template>)> = (0..n).map(|i| (format!("subject-{i:07}"), vec![template(&mut rng)])).collect();
        let mut exact = Gallery::new("bench");
        let mut quantised = Gallery::with_precision("bench", Precision::Quantised);
        for (subject, templates) in &subjects {
            exact.add(subject, templates);
            quantised.add(subject, templates);
        }
        let (Found::Decided(found), _) = exact.search(&MaxCosine, &probe, 1e-3, 5).unwrap() else { unreachable!() };
        let (Found::Shortlist(shortlist), _) = quantised.search(&MaxCosine, &probe, 1e-3, 5).unwrap() else { unreachable!() };
        assert!(found.iter().all(|c| shortlist.contains(&c.subject)), "the shortlist holds the exact top 5");
        group.bench_with_input(BenchmarkId::new("quantised", n), &n, |b, _| {
            b.iter(|| black_box(quantised.search(&MaxCosine, black_box(&probe), 1e-3, 5).unwrap()))
        });
        group.bench_with_input(BenchmarkId::new("exact", n), &n, |b, _| {
            b.iter(|| black_box(exact.search(&MaxCosine, black_box(&probe), 1e-3, 5).unwrap()))
        });
        if n <= 100_000 {
            let expected = facegate_service::gallery::score_each_subject(&MaxCosine, &probe, subjects.clone(), 1e-3, 5);
            let names = |c: &[facegate_service::Candidate]| c.iter().map(|c| c.subject.clone()).collect::<Vec<_>>();
            assert_eq!(names(&found), names(&expected), "the gallery finds what service::identify finds");
            group.bench_with_input(BenchmarkId::new("per_subject", n), &n, |b, _| {
                b.iter_batched(
                    || subjects.clone(),
                    |subjects| black_box(facegate_service::gallery::score_each_subject(&MaxCosine, &probe, subjects, 1e-3, 5)),
                    BatchSize::PerIteration,
                )
            });
        }
    }
    group.finish();
}

fn main() {
    let mut c = Criterion::default().with_measurement(common::ThreadCpuTime).sample_size(10).configure_from_args();
    bench(&mut c);
    c.final_summary();
}
