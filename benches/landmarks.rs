//! Landmark search time per face, one thread: each variant on an IMM photo (640×480, from the
//! detector's box) and on a small ORL face (92×112), with the committed `models/asm.bin`.
//! Run: `cargo bench --bench landmarks`. Times are the benchmark thread's CPU time
//! (`benches/common`): on the shared build machine wall time measures the neighbours too.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use facegate_core::geometry::Rect;
use facegate_core::imaging::open;
use facegate_detect::Detector;
use facegate_paths::{models_dir, shared_dir};
use facegate_vision::landmarks::{Landmarker, Variant};

mod common;
use common::ThreadCpuTime;

fn bench_landmarks(c: &mut Criterion<ThreadCpuTime>) {
    let landmarker = Landmarker::load(&models_dir().join("asm.bin")).expect("models/asm.bin");
    let detector = Detector::load(&models_dir()).expect("detector");
    let imm = open(&shared_dir().join("data/imm/01-1m.jpg")).expect("IMM photo").gray;
    let orl = open(&shared_dir().join("data/orl/s1/1.pgm")).expect("ORL photo").gray;
    let imm_box = detector.detect(&imm).first().map(|f| f.rect).expect("a face in 01-1m");
    let orl_box = detector.detect(&orl).first().map(|f| f.rect).unwrap_or(Rect::new(16.0, 25.0, 60.0, 60.0));
    let mut group = c.benchmark_group("landmarks");
    group.sample_size(30);
    for variant in Variant::ALL {
        let name = variant.name();
        group.bench_function(format!("{name}/imm_640x480"), |b| b.iter(|| black_box(landmarker.fit(black_box(&imm), &imm_box, variant))));
        group.bench_function(format!("{name}/orl_92x112"), |b| b.iter(|| black_box(landmarker.fit(black_box(&orl), &orl_box, variant))));
    }
    group.finish();
}

fn config() -> Criterion<ThreadCpuTime> {
    Criterion::default().with_measurement(ThreadCpuTime)
}

criterion_group! { name = benches; config = config(); targets = bench_landmarks }
criterion_main!(benches);
