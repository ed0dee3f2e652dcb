//! The whole pipeline on the shared photos: each stage's output reaches the analysis.

use facegate_core::imaging::Photo;

use super::*;
use crate::landmarks::Variant;
use crate::landmarks::asm3d::SERVICE_MIN_YAW;
use crate::recognize::Normalization;

fn pipeline_config() -> PipelineConfig {
    PipelineConfig {
        models_dir: facegate_paths::models_dir(),
        sfm_dir: Some(facegate_paths::sfm_dir()),
        recognizer: RecognizerKind::default(),
        detector: DetectorKind::default(),
    }
}

fn photo(name: &str) -> Photo {
    facegate_core::imaging::open(&facegate_paths::shared_dir().join("data/imm").join(name)).unwrap()
}

/// A full profile (UMIST photo 01) is found, landmarked by the profile model seeded by the
/// detector's five points (the C-ASM's 58 points are unreliable there), posed by the 3DMM
/// fitted to them and its far side reported hidden; a frontal face shows nearly every
/// landmark and is not seeded by the detector.
#[test]
fn a_full_profile_is_found_posed_and_its_far_side_hidden() {
    let pipeline = Pipeline::load(&PipelineConfig { detector: DetectorKind::Yunet, ..pipeline_config() }).unwrap();
    let umist = facegate_paths::shared_dir().join("data/umist");
    for person in ["s01", "s05"] {
        let profile = facegate_core::imaging::open(&umist.join(person).join("01.pgm")).unwrap();
        let reading = pipeline.read_faces(&profile, FaceChoice::Largest).unwrap();
        let face = &reading.faces[0];
        // Landmarked by the profile model from YuNet's points, posed by the 3DMM fitted to them.
        assert!(pipeline.finder.profile_seeded(&face.face), "{person}");
        let casm = pipeline.finder.landmarks(&profile.gray, &seed_box(&face.face));
        assert_ne!(face.landmarks.points, casm.points, "{person}: the profile model's points");
        assert_eq!(face.landmarks.centres, casm.centres, "{person}: the chip's centres stay the C-ASM path's");
        let yaw = face.pose.expect("posed").yaw;
        assert!(yaw.abs() > 50.0, "{person}: a full profile posed at {yaw}°");
        let visible = face.visible.as_ref().expect("visibility");
        let hidden = visible.iter().filter(|v| !**v).count();
        assert!((10..48).contains(&hidden), "{person}: {hidden} of 58 landmarks hidden at {yaw}°");
        // The probe's template is made all the same.
        assert!(pipeline.analyze(&profile).is_ok_and(|a| a.pose.is_some_and(|p| p.yaw.abs() > 50.0)), "{person}");
    }
    let frontal = pipeline.read_faces(&photo("01-1m.jpg"), FaceChoice::Largest).unwrap();
    let face = &frontal.faces[0];
    assert!(!pipeline.finder.profile_seeded(&face.face));
    assert!(face.pose.expect("posed").yaw.abs() < 20.0, "{:?}", face.pose);
    let shown = face.visible.as_ref().expect("visibility").iter().filter(|v| **v).count();
    assert!(shown >= 50, "{shown} of 58 landmarks visible on a frontal face");
}

/// Live webcam frames and frames of printed photos (NUAA; the committed model was trained on
/// these subjects, so this checks the wiring, crops and features end to end, not accuracy:
/// `facegate eval liveness` measures that on subjects left out).
#[test]
fn liveness_tells_printed_photos_from_live_faces() {
    let pipeline = Pipeline::load(&pipeline_config()).unwrap();
    let nuaa = facegate_paths::shared_dir().join("data/nuaa");
    for (path, live) in [
        ("real/0004/0004_01_00_01_109.jpg", true),
        ("real/0007/0007_00_00_01_101.jpg", true),
        ("print/0004/0004_01_01_03_211.jpg", false),
        ("print/0007/0007_01_00_01_111.jpg", false),
    ] {
        let a = pipeline.analyze(&facegate_core::imaging::open(&nuaa.join(path)).unwrap()).unwrap();
        let liveness = a.liveness.expect("models/liveness.bin is loaded");
        let threshold = pipeline.liveness.as_ref().expect("loaded").threshold;
        assert_eq!(liveness.score >= threshold, live, "{path}: score {} against {threshold}", liveness.score);
        assert!((0.0..=1.0).contains(&liveness.score));
    }
    let mut without = pipeline;
    without.liveness = None;
    assert!(without.analyze(&photo("05-1m.jpg")).unwrap().liveness.is_none());
}

/// The rendered-head check scores the features the passive model read (the two models read the
/// same blocks), and gives what it gives computing them again: on a camera's face and on a face
/// whose features were never kept.
#[test]
fn the_render_check_reuses_the_passive_models_features() {
    let pipeline = Pipeline::load(&pipeline_config()).unwrap();
    let render = pipeline.render.as_ref().expect("models/render.bin is loaded");
    assert_eq!(render.blocks, pipeline.liveness.as_ref().expect("models/liveness.bin is loaded").blocks);
    for name in ["05-1m.jpg", "15-4f.jpg"] {
        let photo = photo(name);
        let analysis = pipeline.analyze(&photo).unwrap();
        let kept = analysis.liveness_features.as_deref().expect("kept with a liveness model");
        assert_eq!(kept, render.features(&photo.rgb, &analysis.landmarks.centres).as_slice(), "{name}");
        let fresh = render.assess(&photo.rgb, &analysis.landmarks.centres);
        assert_eq!(pipeline.render_check(&photo, &analysis), Some(fresh.clone()), "{name}");
        let without = FaceAnalysis { liveness_features: None, ..analysis };
        assert_eq!(pipeline.render_check(&photo, &without), Some(fresh), "{name}");
    }
}

#[test]
fn full_pipeline_reports_every_stage() {
    let pipeline = Pipeline::load(&pipeline_config()).unwrap();
    assert!(pipeline.face_model.is_some());
    let a = pipeline.analyze(&photo("05-1m.jpg")).unwrap();
    assert_eq!(a.faces_found, 1);
    assert_eq!(a.landmarks.points.len(), 58);
    assert!(a.face.rect.contains(a.landmarks.centres.left_eye) && a.face.rect.contains(a.landmarks.centres.mouth));
    assert!(a.pose.is_some());
    assert_eq!(a.template.model_version, pipeline.recognizer.model_version());
    let norm: f32 = a.template.vector.iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!((norm - 1.0).abs() < 1e-3, "templates are unit vectors, got norm {norm}");
    assert!(a.timings.detect_ms > 0.0 && a.timings.landmarks_ms > 0.0);
}

#[test]
fn deep_and_classical_templates_carry_their_own_versions() {
    let deep = Pipeline::load(&PipelineConfig { recognizer: RecognizerKind::Dlib, ..pipeline_config() }).unwrap();
    let classical = Pipeline::load(&PipelineConfig { recognizer: RecognizerKind::Classical, ..pipeline_config() }).unwrap();
    let p = photo("05-1m.jpg");
    let (a, b) = (deep.analyze(&p).unwrap(), classical.analyze(&p).unwrap());
    assert!(a.template.model_version.starts_with("deep-") && b.template.model_version.starts_with("dlda-"));
    assert_eq!(a.template.vector.len(), facegate_nn::EMBEDDING_DIMS);
    assert_eq!((a.face, &a.landmarks), (b.face, &b.landmarks), "one front end for both");
    // The mirror agreement exists where the chip is embedded (deep), not on the classical path,
    // whose other components are the same (one chip for both).
    let (qa, qb) = (a.quality.components, b.quality.components);
    assert!(qa.mirror_agreement.is_some_and(|m| m > 0.5 && m <= 1.0) && qa.embedding_norm.is_some_and(|n| n > 0.0), "{qa:?}");
    assert_eq!((qb.mirror_agreement, qb.embedding_norm), (None, None));
    assert_eq!((qa.sharpness, qa.fit_residual), (qb.sharpness, qb.fit_residual));
    // Without the 3DMM the deep recognizer is unchanged (it never needed the rendering); the
    // pose is then unknown.
    let flat = Pipeline::load(&PipelineConfig { sfm_dir: None, recognizer: RecognizerKind::Dlib, ..pipeline_config() }).unwrap();
    let c = flat.analyze(&p).unwrap();
    assert_eq!((c.template.clone(), c.pose), (a.template, None));
}

#[test]
fn the_default_fusion_joins_both_networks_and_keeps_the_mirror_agreement() {
    let fusion = Pipeline::load(&pipeline_config()).unwrap();
    assert_eq!(fusion.recognizer.kind(), RecognizerKind::Fusion);
    let a = fusion.analyze(&photo("05-1m.jpg")).unwrap();
    assert!(a.template.model_version.starts_with("emb-"), "{}", a.template.model_version);
    assert_eq!(a.template.vector.len(), 2 * facegate_nn::EMBEDDING_DIMS, "dlib's 128 values and SFace's 128");
    // dlib's half carries √0.8 of the unit vector, SFace's √0.2.
    let (dlib, sface) = a.template.vector.split_at(facegate_nn::EMBEDDING_DIMS);
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>();
    assert!((norm(dlib) - 0.8).abs() < 1e-3 && (norm(sface) - 0.2).abs() < 1e-3, "{} {}", norm(dlib), norm(sface));
    assert!(a.quality.components.mirror_agreement.is_some_and(|m| m > 0.5), "dlib's mirror pair feeds the quality score");
}

#[test]
fn without_the_3dmm_the_classical_pipeline_uses_a_2d_model() {
    let config = PipelineConfig { sfm_dir: None, recognizer: RecognizerKind::Classical, ..pipeline_config() };
    let pipeline = Pipeline::load(&config).unwrap();
    assert!(pipeline.face_model.is_none());
    assert_eq!(pipeline.recognizer.classical().map(|r| r.normalization()), Some(Normalization::TwoD));
    let a = pipeline.analyze(&photo("05-1m.jpg")).unwrap();
    assert!(a.pose.is_none());
    assert_eq!(a.template.model_version, pipeline.recognizer.model_version());
}

#[test]
fn turned_faces_take_the_3d_asm_points_frontal_ones_the_c_asm() {
    let pipeline = Pipeline::load(&pipeline_config()).unwrap();
    let asm3d = pipeline.finder.asm3d.as_ref().expect("models/asm3d.bin");
    for (name, turned) in [("01-1m.jpg", false), ("02-3m.jpg", true)] {
        let p = photo(name);
        let a = pipeline.analyze(&p).unwrap();
        let casm = pipeline.finder.landmarker.fit(&p.gray, &seed_box(&a.face), Variant::Casm);
        let yaw = asm3d.yaw_of(&casm.points).unwrap();
        assert_eq!(yaw.abs() >= SERVICE_MIN_YAW, turned, "{name}: C-ASM yaw {yaw}");
        if turned {
            let three = asm3d.fit_seeded(&p.gray, &seed_box(&a.face), &casm.points, &pipeline.finder.landmarker.model);
            assert_eq!(a.landmarks.points, three.points, "{name}");
            assert_ne!(a.landmarks.points, casm.points, "{name}: the 3D-ASM's points, not the C-ASM's");
        } else {
            assert_eq!(a.landmarks, casm, "{name}");
        }
    }
}

#[test]
fn a_photo_without_a_face_is_no_face() {
    let pipeline = Pipeline::load(&pipeline_config()).unwrap();
    let blank = Photo::from_dynamic(image::DynamicImage::ImageLuma8(image::GrayImage::from_pixel(320, 240, image::Luma([128]))));
    assert!(matches!(pipeline.analyze(&blank), Err(PipelineError::NoFace)));
}
