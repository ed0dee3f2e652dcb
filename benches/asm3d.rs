//! 3D-ASM search time per face, one thread, with the committed `models/asm3d.bin`: a frontal and a
//! turned IMM photo (640×480) from the detector's box; C-ASM (`models/asm.bin`) on the same boxes
//! for comparison. The 3D-ASM is refined by that C-ASM, as in the service. Times are the benchmark thread's CPU time (`benches/common`), not wall time: on a
//! shared machine wall time measures the neighbours too.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use facegate_core::imaging::open;
use facegate_detect::Detector;
use facegate_paths::{models_dir, shared_dir};
use facegate_vision::landmarks::asm3d::{Asm3dLandmarker, Refinement, SERVICE_MIN_YAW};
use facegate_vision::landmarks::{Landmarker, Variant};

mod common;
use common::ThreadCpuTime;

fn bench_asm3d(c: &mut Criterion<ThreadCpuTime>) {
    let landmarker = Asm3dLandmarker::load(&models_dir().join("asm3d.bin")).expect("models/asm3d.bin");
    let casm = Landmarker::load(&models_dir().join("asm.bin")).expect("models/asm.bin");
    let detector = Detector::load(&models_dir()).expect("detector");
    let mut group = c.benchmark_group("asm3d");
    group.sample_size(20);
    for (name, file) in [("frontal_01-1", "01-1m.jpg"), ("turned_02-3", "02-3m.jpg")] {
        let gray = open(&shared_dir().join("data/imm").join(file)).expect("IMM photo").gray;
        let face = detector.detect(&gray).first().map(|f| f.rect).expect("a face");
        // As the service and `facegate landmarks --variant asm3d` run it: refined by the C-ASM.
        let refinement = Refinement::Casm(&casm.model);
        group.bench_function(name, |b| b.iter(|| black_box(landmarker.fit_with(black_box(&gray), &face, refinement))));
        group.bench_function(format!("casm_{name}"), |b| b.iter(|| black_box(casm.fit(black_box(&gray), &face, Variant::Casm))));
    }
    // The service's switched path on a turned photo: C-ASM, its yaw, then the 3D-ASM seeded by
    // its points (`switch`), against the C-ASM and the blind 3D-ASM (`fit_with`) above/below.
    let gray = open(&shared_dir().join("data/imm/01-3m.jpg")).expect("IMM photo").gray;
    let face = detector.detect(&gray).first().map(|f| f.rect).expect("a face");
    let refinement = Refinement::Casm(&casm.model);
    assert!(landmarker.switch(&gray, &face, &casm, casm.fit(&gray, &face, Variant::Casm), SERVICE_MIN_YAW).1, "01-3 switches");
    group.bench_function("switch_turned_01-3", |b| {
        b.iter(|| black_box(landmarker.switch(black_box(&gray), &face, &casm, casm.fit(&gray, &face, Variant::Casm), SERVICE_MIN_YAW)))
    });
    group.bench_function("casm_then_blind_3d_turned_01-3", |b| {
        b.iter(|| {
            black_box(casm.fit(black_box(&gray), &face, Variant::Casm));
            black_box(landmarker.fit_with(black_box(&gray), &face, refinement))
        })
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(ThreadCpuTime);
    targets = bench_asm3d
}
criterion_main!(benches);
