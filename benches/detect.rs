//! Detection time on one 640×480 IMM photo (frontal, and rotated about 30°), one thread, for the
//! default Haar detector and the SeetaFace alternative; plus a face-free image, where every
//! fallback runs.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use facegate::config::{models_dir, shared_dir};
use facegate::detect::{Detector, DetectorKind};
use facegate::imaging::{GrayF32, open};

fn bench_detect(c: &mut Criterion) {
    let frontal = open(&shared_dir().join("data/imm/01-1m.jpg")).expect("IMM photo").gray;
    let rotated = open(&shared_dir().join("data/imm/01-3m.jpg")).expect("IMM photo").gray;
    let orl = open(&shared_dir().join("data/orl/s1/1.pgm")).expect("ORL photo").gray;
    let blank = GrayF32::from_fn(640, 480, |x, y| ((x / 40 + y / 40) % 2) as f32 * 60.0 + 90.0);
    let mut group = c.benchmark_group("detect");
    group.sample_size(30);
    for kind in [DetectorKind::Haar, DetectorKind::Seeta] {
        let detector = Detector::load_kind(&models_dir(), kind).expect("detector loads");
        let name = format!("{kind:?}").to_lowercase();
        group.bench_function(format!("{name}/imm_640x480_frontal"), |b| b.iter(|| black_box(detector.detect(black_box(&frontal)))));
        group.bench_function(format!("{name}/imm_640x480_rotated"), |b| b.iter(|| black_box(detector.detect(black_box(&rotated)))));
        group.bench_function(format!("{name}/orl_92x112"), |b| b.iter(|| black_box(detector.detect(black_box(&orl)))));
        group.bench_function(format!("{name}/checkerboard_640x480_no_face"), |b| b.iter(|| black_box(detector.detect(black_box(&blank)))));
    }
    group.finish();
}

criterion_group!(benches, bench_detect);
criterion_main!(benches);
