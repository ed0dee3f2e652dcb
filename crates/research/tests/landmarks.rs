use facegate_core::geometry::{Point, Rect, Similarity, distance};
use facegate_core::imaging::GrayF32;
use facegate_research::dataset::{ImmSample, list_imm};
use facegate_vision::landmarks::*;
use std::sync::OnceLock;

fn samples() -> Vec<ImmSample> {
    list_imm(&facegate_paths::shared_dir().join("data/imm")).unwrap()
}

/// One model trained on the training persons, shared by the tests.
fn model() -> &'static Landmarker {
    static MODEL: OnceLock<Landmarker> = OnceLock::new();
    MODEL.get_or_init(|| {
        let training: Vec<ImmSample> =
            samples().into_iter().filter(|s| !facegate_research::dataset::imm_is_test_person(s.person)).collect();
        Landmarker {
            model: facegate_research::train_asm::train(&training, None, &facegate_research::train_asm::TrainOptions::default(), &|| {})
                .unwrap(),
        }
    })
}

fn rms(a: &[Point], b: &[Point]) -> f32 {
    (a.iter().zip(b).map(|(p, q)| distance(*p, *q).powi(2)).sum::<f32>() / a.len() as f32).sqrt()
}

#[test]
fn shape_models_reproduce_training_shapes_within_constraints() {
    let m = &model().model;
    for (pdm, range) in [(&m.full, 0..58), (&m.internal, 13..58), (&m.contour, 0..13)] {
        let (mut checked, mut clamped) = (0, 0);
        for s in samples().iter().filter(|s| !facegate_research::dataset::imm_is_test_person(s.person)).step_by(3) {
            let truth = s.landmarks().unwrap();
            let target = &truth[range.clone()];
            let (fit, pose, b) = pdm.fit(target);
            let mut at_limit = false;
            for (k, bk) in b.iter().enumerate() {
                let lim = pdm.constrain * pdm.eigenvalues[k].sqrt();
                assert!(bk.abs() <= lim + 1e-3);
                at_limit |= bk.abs() >= lim - 1e-3;
            }
            if at_limit {
                // An unusual shape, pulled back into the ±3σ box: not reproduced exactly.
                clamped += 1;
                continue;
            }
            checked += 1;
            // 98% of the variance: a shape inside the box is reproduced to a small residual.
            let size = pose.scale() * rms(&pdm.mean, &vec![[0.0, 0.0]; pdm.points()]);
            let mean_placed: Vec<Point> = pdm.mean.iter().map(|&p| Similarity::fit(&pdm.mean, target, None).apply(p)).collect();
            let (err, dev) = (rms(&fit, target), rms(&mean_placed, target));
            assert!(
                err < 0.5 * dev && err < 0.05 * size,
                "{}: residual {err:.2} px, deviation {dev:.2} px, size {size:.1} px",
                s.image.display()
            );
        }
        assert!(clamped * 3 < checked, "{clamped} clamped training shapes of {}", clamped + checked);
    }
}

#[test]
fn search_returns_to_the_annotation_from_a_perturbed_start() {
    let lm = model();
    let s = samples().into_iter().find(|s| s.person == 7 && s.view == 1).unwrap();
    let truth = s.landmarks().unwrap();
    let photo = facegate_core::imaging::open(&s.image).unwrap();
    let truth_k = facegate_core::face::EyeMouthCentres::from_imm(&truth);
    let eyes = distance(truth_k.left_eye, truth_k.right_eye);
    // The box the model expects, shifted by 10% of its width and scaled by 8%.
    let b = facegate_research::train_asm::annotation_box(&truth);
    let moved = Rect::new(b.x + 0.1 * b.width, b.y - 0.06 * b.width, 1.08 * b.width, 1.08 * b.height);
    for variant in Variant::ALL {
        let start = lm.initial_shape(&moved);
        let found = lm.fit(&photo.gray, &moved, variant);
        let (before, after) = (rms(&start, &truth), rms(&found.points, &truth));
        let d_eye = facegate_research::eval::landmarks::d_eye(&found.centres, &truth_k);
        // Plain ASM is the weakest; SIFT-ASM and C-ASM should get much closer.
        let gain = if variant == Variant::Asm { 0.7 } else { 0.4 };
        assert!(after < gain * before, "{variant:?}: rms {before:.1} -> {after:.1} px");
        if variant != Variant::Asm {
            assert!(d_eye < 0.05, "{variant:?}: d_eye {d_eye:.3} (eye distance {eyes:.0} px)");
        } else {
            assert!(d_eye < 0.1, "{variant:?}: d_eye {d_eye:.3}");
        }
    }
}

#[test]
fn fit_survives_degenerate_images_and_boxes() {
    let lm = model();
    let img = GrayF32::from_fn(92, 112, |x, y| ((x * 3 + y * 5) % 17) as f32 * 10.0);
    let boxes = [
        Rect::new(10.0, 20.0, 60.0, 60.0),
        Rect::new(-500.0, -500.0, 40.0, 40.0),
        Rect::new(80.0, 100.0, 400.0, 400.0),
        Rect::new(0.0, 0.0, 0.0, 0.0),
        Rect::new(f32::NAN, 3.0, f32::INFINITY, -2.0),
        Rect::new(1.0, 1.0, 1e9, 1e9),
    ];
    for b in &boxes {
        for v in Variant::ALL {
            let out = lm.fit(&img, b, v);
            assert_eq!(out.points.len(), 58);
        }
    }
    for (w, h) in [(1, 1), (2, 2), (3, 200), (0, 0)] {
        let tiny = GrayF32::new(w, h);
        assert_eq!(lm.fit(&tiny, &Rect::new(0.0, 0.0, 2.0, 2.0), Variant::Casm).points.len(), 58);
    }
}

#[test]
fn model_round_trips_through_a_file_and_refuses_garbage() {
    let lm = model();
    let dir = std::env::temp_dir().join(format!("facegate-asm-{}", std::process::id()));
    let path = dir.join("asm.bin");
    lm.save(&path).unwrap();
    let back = Landmarker::load(&path).unwrap();
    assert_eq!(back.model.full.mean, lm.model.full.mean);
    std::fs::write(&path, b"not a model").unwrap();
    assert!(matches!(Landmarker::load(&path), Err(LandmarkError::Model { .. })));
    std::fs::remove_dir_all(&dir).unwrap();
}
