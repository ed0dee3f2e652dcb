//! The service's photo → template cost (`Pipeline::analyze`, decoding included, deep recognizer,
//! 3DMM loaded) with the multi-view YuNet front end against the Viola–Jones one, in one run, on
//! frontal photos (IMM 640×480, LFW 250×250) and on turned ones (UMIST 92×112: near frontal,
//! 45°, full profile, which only YuNet finds). Thread CPU time (`benches/common`); the ratio of
//! the two front ends on one photo is what holds across machines.

mod common;

use criterion::{Criterion, criterion_group, criterion_main};
use facegate_core::imaging::{self, DecodeLimits};
use facegate_detect::DetectorKind;
use facegate_paths::shared_dir;

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let pipelines = [("yunet", common::deep_pipeline(DetectorKind::Yunet)), ("haar", common::deep_pipeline(DetectorKind::Haar))];
    let photos = [
        ("imm_01-1m_640x480_frontal", "data/imm/01-1m.jpg"),
        ("lfw_250x250_frontal", "data/lfw/Aaron_Peirsol/Aaron_Peirsol_0001.jpg"),
        ("umist_s01-19_near_frontal", "data/umist/s01/19.pgm"),
        ("umist_s01-08_45deg", "data/umist/s01/08.pgm"),
        ("umist_s01-01_profile", "data/umist/s01/01.pgm"),
    ];
    let mut group = c.benchmark_group("pose");
    group.sample_size(20);
    for (name, path) in photos {
        let bytes = std::fs::read(shared_dir().join(path)).expect("photo");
        for (front_end, pipeline) in &pipelines {
            let photo = imaging::decode(&bytes, &DecodeLimits::default()).expect("decodes");
            // A photo a front end cannot find a face in costs its detection only: not comparable.
            if pipeline.analyze(&photo).is_err() {
                eprintln!("{name}: {front_end} finds no face");
                continue;
            }
            group.bench_function(format!("decode_analyze/{name}/{front_end}"), |b| common::decode_analyze(b, pipeline, &bytes));
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
