//! Face image quality per face against the whole analysis, in one run: the components from the
//! chip the deep recognizer already cut, then with the mirror agreement of the two embeddings it
//! already made and the score (its path in the service), the chip cut and measured (the
//! classical path, and `/analyze`), the unified score, and `Pipeline::analyze` of the same photo
//! (decoding included), on a large photo (IMM 640×480) and a small one (ORL 92×112). Thread CPU
//! time (`benches/common`).

mod common;

use std::path::PathBuf;

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::imaging::{self, DecodeLimits};
use facegate_paths::{models_dir, shared_dir};
use facegate_vision::pipeline::quality_components;

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let pipeline = common::deep_pipeline(Default::default());
    let photos: [(&str, PathBuf); 2] =
        [("imm_01-1m_640x480", shared_dir().join("data/imm/01-1m.jpg")), ("orl_s1-1_92x112", shared_dir().join("data/orl/s1/1.pgm"))];
    let mut group = c.benchmark_group("quality");
    group.sample_size(20);
    for (name, path) in photos {
        let bytes = std::fs::read(&path).expect("photo");
        let photo = imaging::decode(&bytes, &DecodeLimits::default()).expect("decodes");
        let analysis = pipeline.analyze(&photo).expect("a face");
        let (landmarks, pose) = (&analysis.landmarks, analysis.pose);
        let residual = analysis.quality.components.fit_residual.map(|r| r * analysis.quality.components.inter_eye_px);
        let chip = facegate_vision::embed::face_chip(&photo.rgb, &landmarks.centres);
        group.bench_function(format!("components_of_chip/{name}"), |b| {
            b.iter(|| black_box(facegate_vision::quality::components(black_box(&chip), &landmarks.centres, pose, residual)))
        });
        // The deep path's whole quality stage: the components, the agreement of the two
        // embeddings the recognizer made anyway, the score.
        let network = facegate_vision::embed::load(&models_dir()).expect("models/embedding.bin");
        let mirror = facegate_vision::embed::chip_mirror_pair(&network, &chip);
        group.bench_function(format!("chip_components_mirror_score/{name}"), |b| {
            b.iter(|| {
                let components = facegate_vision::quality::components(black_box(&chip), &landmarks.centres, pose, residual);
                black_box(pipeline.quality.assess(components.with_mirror(black_box(&mirror))))
            })
        });
        group.bench_function(format!("chip_components_score/{name}"), |b| {
            b.iter(|| black_box(pipeline.quality.assess(quality_components(black_box(&photo), landmarks, pose, residual).1)))
        });
        group.bench_function(format!("decode_analyze/{name}"), |b| common::decode_analyze(b, &pipeline, &bytes));
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(common::ThreadCpuTime);
    targets = bench
}
criterion_main!(benches);
