//! Face-embedding speed: one forward pass of the ResNet on a 150×150 chip (target ≤ 12 ms on one
//! core), and the mirror-averaged embedding the deep recognizer uses (two passes); thread CPU time. The chip is cut from an IMM photo with its annotated centres.

mod common;

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::face::EyeMouthCentres;
use facegate_nn::Workspace;
use facegate_research::dataset::list_imm;
use facegate_vision::embed;

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let embedder = embed::load(&facegate_paths::models_dir()).expect("models/embedding.bin (facegate convert embedding)");
    let sample = &list_imm(&facegate_paths::shared_dir().join("data/imm")).expect("IMM data")[0];
    let photo = facegate_core::imaging::open(&sample.image).expect("IMM photo");
    let k = EyeMouthCentres::from_imm(&sample.landmarks().expect("IMM landmarks"));
    let chip = embed::face_chip(&photo.rgb, &k);
    let mut ws = Workspace::default();

    c.bench_function("embed_chip_150", |b| b.iter(|| black_box(embedder.forward(black_box(&chip), &mut ws))));
    c.bench_function("embed_chip_150_mirror_averaged", |b| b.iter(|| black_box(embedder.embed_mirrored(black_box(&chip), &mut ws))));
    c.bench_function("cut_chip_640x480", |b| b.iter(|| black_box(embed::face_chip(black_box(&photo.rgb), &k))));
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(common::ThreadCpuTime).sample_size(30);
    targets = bench
}
criterion_main!(benches);
