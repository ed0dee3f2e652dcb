//! Recognition speed: projection and scoring of one face (target ≤ 1 ms), and the normalisation of a
//! 640×480 photo before it. Uses the committed `models/dlda.bin` and an IMM photo with its annotated
//! centres. A fused model (3DMM + 2D) gets one crop per path (here the same crop, which costs the
//! same as two different ones).

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use facegate_core::face::EyeMouthCentres;
use facegate_research::dataset::list_imm;
use facegate_vision::recognize::{ClassicalRecognizer, Views};

/// The one crop on every path of the model (what is measured is the time, not the template).
fn views<T: Copy>(fused: bool, crop: T) -> Views<T> {
    if fused { Views::Fused { primary: crop, secondary: crop } } else { Views::Single(crop) }
}

fn bench(c: &mut Criterion) {
    let recognizer = ClassicalRecognizer::load(&facegate_paths::models_dir()).expect("models/dlda.bin (facegate train dlda)");
    let sample = &list_imm(&facegate_paths::shared_dir().join("data/imm")).expect("IMM data")[0];
    let photo = facegate_core::imaging::open(&sample.image).expect("IMM photo");
    let centres = EyeMouthCentres::from_imm(&sample.landmarks().expect("IMM landmarks"));
    let crop = recognizer.normalized_crop(&photo.gray, &centres);
    let fused = recognizer.paths().len() == 2;
    let enrolled = vec![recognizer.template(views(fused, &crop)).expect("one crop per path")];

    c.bench_function("project_and_score", |b| {
        b.iter(|| {
            let t = recognizer.template(black_box(views(fused, &crop))).expect("one crop per path");
            black_box(recognizer.score(&t, &enrolled))
        })
    });
    c.bench_function("normalize_project_score_640x480", |b| {
        b.iter(|| {
            let crop = recognizer.normalized_crop(black_box(&photo.gray), &centres);
            let t = recognizer.template(views(fused, &crop)).expect("one crop per path");
            black_box(recognizer.score(&t, &enrolled))
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
