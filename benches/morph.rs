//! Speed of the 3DMM path on one core: fit (58 IMM points), texture extraction, frontal rendering,
//! and the mean face fitted to the detector's five key points (`key_point_pose`, which every
//! analysis now makes for the head-turn challenge). Target: fit + texture + frontal rendering
//! ≤ 10 ms per face.
//! Run: `cargo bench --bench morph` (needs the Surrey Face Model at FACEGATE_SFM or ../shared/models/sfm).
//!
//! Times are the benchmark thread's CPU time (`benches/common`), not wall time: on a
//! shared, loaded machine wall time measures the neighbours too. The work is single-threaded.

use criterion::{Criterion, criterion_group, criterion_main};
use facegate_morph::{FaceModel, TEXTURE_SIZE};
use facegate_research::dataset::list_imm;

mod common;
use common::ThreadCpuTime;

fn bench(c: &mut Criterion<ThreadCpuTime>) {
    let model = FaceModel::load(&facegate_paths::sfm_dir()).expect("Surrey Face Model");
    let sample = list_imm(&facegate_paths::shared_dir().join("data/imm"))
        .expect("IMM data")
        .into_iter()
        .find(|s| s.person == 2 && s.view == 3)
        .expect("IMM 02-3");
    let photo = facegate_core::imaging::open(&sample.image).expect("photo");
    let points = sample.landmarks().expect("landmarks");
    let (w, h) = (photo.width(), photo.height());
    let fitted = model.fit(&points, w, h).expect("fit");

    // YuNet's five points on this photo, as `/analyze` reports them (`face.points`).
    let key_points = [[255.0, 267.9], [327.8, 266.8], [275.5, 312.2], [267.6, 344.6], [327.3, 343.0]];

    c.bench_function("morph/fit", |b| b.iter(|| model.fit(std::hint::black_box(&points), w, h).unwrap()));
    // A hundred fits per iteration: one takes tens of microseconds, under the thread CPU clock's
    // step, and criterion refuses samples that measure zero.
    c.bench_function("morph/fit_key_points_x100", |b| {
        b.iter(|| {
            for _ in 0..100 {
                std::hint::black_box(model.fit_key_points(std::hint::black_box(&key_points), w, h).unwrap());
            }
        })
    });
    c.bench_function("morph/texture", |b| b.iter(|| model.extract_texture(&photo.rgb, &fitted, TEXTURE_SIZE)));
    c.bench_function("morph/frontal_render", |b| b.iter(|| model.frontalize(&photo, &fitted).unwrap()));
    c.bench_function("morph/fit_texture_frontal", |b| {
        b.iter(|| {
            let f = model.fit(std::hint::black_box(&points), w, h).unwrap();
            model.frontalize(&photo, &f).unwrap()
        })
    });
}

fn config() -> Criterion<ThreadCpuTime> {
    Criterion::default().with_measurement(ThreadCpuTime)
}

criterion_group! { name = benches; config = config(); targets = bench }
criterion_main!(benches);
