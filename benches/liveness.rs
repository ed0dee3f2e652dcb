//! The liveness check's cost: `LivenessModel::assess` on one face (crops, colour planes, LBP,
//! the logistic model) beside the service's whole photo → template path (`Pipeline::analyze`,
//! decoding included, deep recognizer, 3DMM loaded) with the liveness model dropped and loaded,
//! in one run, on a NUAA webcam frame (640×480) and an LFW photo (250×250). Thread CPU time
//! (`benches/common`); the ratios to `analyze` without liveness are what hold across machines.

mod common;

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::imaging::{self, DecodeLimits};
use facegate_detect::DetectorKind;
use facegate_paths::shared_dir;

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let with = common::deep_pipeline(DetectorKind::default());
    assert!(with.liveness.is_some(), "models/liveness.bin");
    let mut without = common::deep_pipeline(DetectorKind::default());
    without.liveness = None;
    let photos = [
        ("nuaa_640x480_live", "data/nuaa/real/0004/0004_01_00_01_109.jpg"),
        ("lfw_250x250", "data/lfw/Aaron_Peirsol/Aaron_Peirsol_0001.jpg"),
    ];
    let mut group = c.benchmark_group("liveness");
    group.sample_size(20);
    for (name, path) in photos {
        let bytes = std::fs::read(shared_dir().join(path)).expect("photo");
        let photo = imaging::decode(&bytes, &DecodeLimits::default()).expect("decodes");
        let centres = with.analyze(&photo).expect("a face").landmarks.centres;
        let model = with.liveness.as_ref().expect("loaded");
        group.bench_function(format!("assess/{name}"), |b| b.iter(|| black_box(model.assess(black_box(&photo.rgb), &centres))));
        for (label, pipeline) in [("without_liveness", &without), ("with_liveness", &with)] {
            group.bench_function(format!("decode_analyze/{name}/{label}"), |b| common::decode_analyze(b, pipeline, &bytes));
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
