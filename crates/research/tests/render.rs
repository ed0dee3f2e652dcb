//! The committed rendered-head detector (`models/render.bin`) on persons it never saw: UMIST's
//! test persons (s06–s10; s01–s05 trained it), whose small grey camera is the one no other
//! training set shows. Their turned photos are a camera's faces, and their probe photo's head
//! rendered across a turned step's range (the attack `facegate eval challenge` makes) is not.

use facegate_paths::{models_dir, sfm_dir, shared_dir};
use facegate_research::dataset::umist_is_test_person;
use facegate_research::liveness::challenge::{Source, render_source};
use facegate_service::challenge::RENDER_MIN;
use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::RecognizerKind;

fn render_score(pipeline: &Pipeline, source: &Source) -> f32 {
    let photo = render_source(pipeline, source).unwrap_or_else(|| panic!("{source:?} made no photo"));
    let analysis = pipeline.analyze(&photo).unwrap_or_else(|e| panic!("{source:?}: {e}"));
    pipeline.render_check(&photo, &analysis).expect("render.bin is loaded").score
}

#[test]
fn umist_test_persons_turned_photos_are_a_cameras_and_their_rendered_heads_are_not() {
    let config = PipelineConfig {
        models_dir: models_dir(),
        sfm_dir: Some(sfm_dir()),
        recognizer: RecognizerKind::default(),
        detector: Default::default(),
    };
    let pipeline = Pipeline::load(&config).unwrap();
    let umist = shared_dir().join("data/umist");
    let persons = ["s06", "s07", "s08", "s09", "s10"];
    assert!(persons.iter().all(|p| umist_is_test_person(p)), "never trained on");
    for person in persons {
        // The probe photo and the turned photos a live challenge takes, as they are and mirrored.
        for number in [12, 15, 19] {
            let path = umist.join(person).join(format!("{number:02}.pgm"));
            for source in [Source::File(path.clone()), Source::Mirror(path)] {
                let score = render_score(&pipeline, &source);
                assert!(score >= RENDER_MIN, "{person}: {source:?} read as a rendered head ({score:.3})");
            }
        }
        let probe = umist.join(person).join("19.pgm");
        for yaw in [-35, 25] {
            let source = Source::Avatar { path: probe.clone(), yaw };
            let score = render_score(&pipeline, &source);
            assert!(score < RENDER_MIN, "{person}: the head rendered at {yaw}° passed as a camera's face ({score:.3})");
        }
    }
}
