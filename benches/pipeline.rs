//! The whole photo → template pipeline of the service (`Pipeline::analyze`, deep recognizer,
//! 3DMM loaded), decoding included, one photo per call: a large photo (IMM 640×480, frontal and
//! turned) against small ones (ORL 92×112, one the C-ASM keeps and one turned enough for the
//! 3D-ASM switch), in one run, and the small-image detection scanned at step 1 on every level (its
//! setting before the coarse small-window levels), so their ratio holds across machines. Thread CPU time
//! (`benches/common`).

mod common;

use std::path::PathBuf;

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::imaging::{self, DecodeLimits};
use facegate_paths::{models_dir, shared_dir};
use facegate_vision::landmarks::asm3d::SERVICE_MIN_YAW;

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let pipeline = common::deep_pipeline(Default::default());
    let photos: [(&str, PathBuf); 4] = [
        ("imm_01-1m_640x480_frontal", shared_dir().join("data/imm/01-1m.jpg")),
        ("imm_01-3m_640x480_turned", shared_dir().join("data/imm/01-3m.jpg")),
        ("orl_s1-1_92x112", shared_dir().join("data/orl/s1/1.pgm")),
        ("orl_s1-2_92x112", shared_dir().join("data/orl/s1/2.pgm")),
    ];
    // The small-image scan before its coarse small-window levels: step 1 on every level.
    let mut step1_everywhere = facegate_detect::Detector::load_kind(&models_dir(), facegate_detect::DetectorKind::Haar).expect("cascades");
    step1_everywhere.options.small_image_fine_above_scale = 0.0;
    let asm3d = pipeline.finder.asm3d.as_ref().expect("models/asm3d.bin");
    let mut group = c.benchmark_group("pipeline");
    group.sample_size(20);
    for (name, path) in photos {
        let bytes = std::fs::read(&path).expect("photo");
        let photo = imaging::decode(&bytes, &DecodeLimits::default()).expect("decodes");
        let located = pipeline.finder.locate(&photo.gray).expect("a face");
        let casm = pipeline.finder.landmarker.fit(&photo.gray, &located.face.rect, facegate_vision::landmarks::Variant::Casm);
        let switched = asm3d.yaw_of(&casm.points).is_some_and(|yaw| yaw.abs() >= SERVICE_MIN_YAW);
        eprintln!("{name}: 3D-ASM switch {}", if switched { "on" } else { "off" });
        group.bench_function(format!("decode_analyze/{name}"), |b| common::decode_analyze(b, &pipeline, &bytes));
        group.bench_function(format!("detect/{name}"), |b| b.iter(|| black_box(pipeline.finder.detect(black_box(&photo.gray)))));
        if name.starts_with("orl") {
            group.bench_function(format!("detect_step1_everywhere/{name}"), |b| {
                b.iter(|| black_box(step1_everywhere.detect(black_box(&photo.gray))))
            });
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(common::ThreadCpuTime);
    targets = bench
}
criterion_main!(benches);
