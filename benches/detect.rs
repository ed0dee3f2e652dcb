//! Detection time on one 640×480 IMM photo (frontal, and rotated about 30°), one thread, for the
//! default Haar detector and the SeetaFace and YuNet alternatives; plus a face-free image, where
//! every fallback runs.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use facegate_core::imaging::{GrayF32, open};
use facegate_detect::{Detector, DetectorKind};
use facegate_paths::{models_dir, shared_dir};

mod common;
use common::ThreadCpuTime;

fn bench_detect(c: &mut Criterion<ThreadCpuTime>) {
    let frontal = open(&shared_dir().join("data/imm/01-1m.jpg")).expect("IMM photo").gray;
    let rotated = open(&shared_dir().join("data/imm/01-3m.jpg")).expect("IMM photo").gray;
    let orl = open(&shared_dir().join("data/orl/s1/1.pgm")).expect("ORL photo").gray;
    let blank = GrayF32::from_fn(640, 480, |x, y| ((x / 40 + y / 40) % 2) as f32 * 60.0 + 90.0);
    let mut group = c.benchmark_group("detect");
    group.sample_size(30);
    for kind in [DetectorKind::Haar, DetectorKind::Seeta, DetectorKind::Yunet] {
        let detector = Detector::load_kind(&models_dir(), kind).expect("detector loads");
        let name = format!("{kind:?}").to_lowercase();
        group.bench_function(format!("{name}/imm_640x480_frontal"), |b| b.iter(|| black_box(detector.detect(black_box(&frontal)))));
        group.bench_function(format!("{name}/imm_640x480_rotated"), |b| b.iter(|| black_box(detector.detect(black_box(&rotated)))));
        group.bench_function(format!("{name}/orl_92x112"), |b| b.iter(|| black_box(detector.detect(black_box(&orl)))));
        group.bench_function(format!("{name}/checkerboard_640x480_no_face"), |b| b.iter(|| black_box(detector.detect(black_box(&blank)))));
    }
    // `rustface`'s detector is `&mut self` and not `Send`: `Detector` builds one per call from a
    // clone of the parsed model. This is that per-call overhead.
    let bytes = std::fs::read(models_dir().join("cascades").join(facegate_detect::SEETA_MODEL)).expect("SeetaFace model");
    let model = rustface::read_model(&bytes[..]).expect("model parses");
    group.bench_function("seeta/per_call_detector_from_model_clone", |b| {
        b.iter(|| black_box(rustface::create_detector_with_model(black_box(&model).clone())))
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(ThreadCpuTime);
    targets = bench_detect
}
criterion_main!(benches);
