//! MiniFASNet's cost on one face: `MiniFasNet::assess` (both crops cut and resized, both
//! networks) and each network's forward pass alone, beside the LBP liveness model's
//! `LivenessModel::assess` on the same face (the ratio between the two is measured in one run), on
//! a NUAA webcam frame (640×480) and an LFW photo (250×250). Thread CPU time (`benches/common`).

mod common;

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::imaging::{self, DecodeLimits};
use facegate_detect::DetectorKind;
use facegate_paths::shared_dir;
use facegate_vision::liveness::minifasnet::{MiniFasNet, PixelBox, crop_box, network_input};

fn bench(c: &mut Criterion<common::ThreadCpuTime>) {
    let pipeline = common::deep_pipeline(DetectorKind::default());
    let lbp = pipeline.liveness.as_ref().expect("models/liveness.bin");
    let networks = MiniFasNet::load(&facegate_paths::models_dir()).expect("models/minifasnet-v2.bin and minifasnet-v1se.bin");
    let photos = [
        ("nuaa_640x480_live", "data/nuaa/real/0004/0004_01_00_01_109.jpg"),
        ("lfw_250x250", "data/lfw/Aaron_Peirsol/Aaron_Peirsol_0001.jpg"),
    ];
    let mut group = c.benchmark_group("minifasnet");
    group.sample_size(20);
    for (name, path) in photos {
        let bytes = std::fs::read(shared_dir().join(path)).expect("photo");
        let photo = imaging::decode(&bytes, &DecodeLimits::default()).expect("decodes");
        let analysis = pipeline.analyze(&photo).expect("a face");
        let face = analysis.face.rect;
        group.bench_function(format!("assess_both/{name}"), |b| b.iter(|| black_box(networks.assess(black_box(&photo.rgb), &face))));
        for net in [&networks.v2, &networks.v1se] {
            let crop = crop_box(photo.rgb.width(), photo.rgb.height(), PixelBox::from_rect(&face), net.crop_scale());
            let planes = network_input(&photo.rgb, crop, net.input_size());
            group.bench_function(format!("forward/{}/{name}", net.name()), |b| b.iter(|| black_box(net.forward(black_box(&planes)))));
        }
        let centres = analysis.landmarks.centres;
        group.bench_function(format!("lbp_assess/{name}"), |b| b.iter(|| black_box(lbp.assess(black_box(&photo.rgb), &centres))));
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(common::ThreadCpuTime);
    targets = bench
}
criterion_main!(benches);
