use facegate_core::face::{EyeMouthCentres, IMM_POINTS, JAW};
use facegate_core::geometry::{Point, Rect, centroid};
use facegate_core::imaging::{self, GrayF32};
use facegate_morph::{Camera, FaceModel, Pose};
use facegate_research::asm3d_synth::*;
use facegate_research::dataset::list_imm;
use facegate_research::dataset::{self, ImmSample};
use facegate_research::train_asm3d::*;
use facegate_vision::landmarks::asm3d::*;
use facegate_vision::landmarks::{BoxSource, LandmarkError, Variant};
use std::sync::OnceLock;

fn face_model() -> &'static FaceModel {
    static M: OnceLock<FaceModel> = OnceLock::new();
    M.get_or_init(|| FaceModel::load(&facegate_paths::sfm_dir()).expect("the Surrey Face Model"))
}

#[test]
fn pdm3d_recovers_a_projected_model_shape_and_pose() {
    let fm = face_model();
    let pdms = train_pdms(fm, &[0.0, 30.0], &contour_jaw_vertices(fm), 120, 0.98, 3.0, 3);
    let pdm = &pdms[1];
    assert!(pdm.modes() >= 5 && pdm.modes() < 100, "{} modes", pdm.modes());
    // A shape inside the model at a known pose is fitted back: pose within 2°, points within 1.5 px (the prior shrinks the coefficients a little).
    let b: Vec<f32> = pdm
        .eigenvalues
        .iter()
        .enumerate()
        .map(|(k, l)| if k < 4 { 0.8 * l.sqrt() * if k % 2 == 0 { 1.0 } else { -1.0 } } else { 0.0 })
        .collect();
    let cam = Camera::from_pose(Pose { yaw: 28.0, pitch: 4.0, roll: -6.0 }, 2.0, 200.0, 180.0);
    let target = pdm.project(&b, &cam);
    let fit = pdm.fit(&target, 0.5, 10).unwrap();
    let pose = fit.camera.pose();
    assert!((pose.yaw - 28.0).abs() < 2.0 && (pose.pitch - 4.0).abs() < 2.0 && (pose.roll + 6.0).abs() < 2.0, "{pose:?}");
    let worst = fit.points.iter().zip(&target).map(|(a, b)| facegate_core::geometry::distance(*a, *b)).fold(0.0, f32::max);
    assert!(worst < 1.5, "worst point error {worst} px (face about 280 px wide)");
    // Degenerate targets give None, not a panic.
    assert!(pdm.fit(&vec![[1.0, 1.0]; IMM_POINTS], 1.0, 3).is_none());
    assert!(pdm.fit(&vec![[f32::NAN, 1.0]; IMM_POINTS], 1.0, 3).is_none());
    assert!(pdm.fit(&target[..10], 1.0, 3).is_none());
}

#[test]
fn jaw_follows_the_outline_as_the_head_turns() {
    // At yaw +40° (nose to the image right) the image-right jaw points leave the frontal contour
    // for the occluding outline, which projects further out than the frontal contour vertex.
    let fm = face_model();
    let at = |v: u32| fm.vertex(v as usize, &[], &[]);
    let jaw = contour_jaw_vertices(fm);
    let frontal = view_correspondence(fm, &at, &Camera::from_pose(Pose::default(), 1.0, 0.0, 0.0), &jaw);
    let cam = Camera::from_pose(Pose { yaw: 40.0, pitch: 0.0, roll: 0.0 }, 1.0, 0.0, 0.0);
    let turned = view_correspondence(fm, &at, &cam, &jaw);
    assert_eq!(frontal[13..], turned[13..]);
    let moved: Vec<usize> = (7..13).filter(|&j| turned[j] != frontal[j]).collect();
    assert!(!moved.is_empty(), "no image-right jaw point moved");
    for j in moved {
        let (a, b) = (cam.project(at(frontal[j])), cam.project(at(turned[j])));
        assert!(b[0] > a[0] - 1.0, "jaw {j}: outline at x {} inside the contour vertex at {}", b[0], a[0]);
    }
}

#[test]
fn learnt_jaw_vertices_follow_the_annotation() {
    // Frontal photos of training persons: the jaw at the learnt vertices of each photo's fitted
    // shape is near the annotated jaw; the contour rule (`contour_jaw_vertices`) is far above it.
    let fm = face_model();
    let samples: Vec<ImmSample> = list_imm(&facegate_paths::shared_dir().join("data/imm"))
        .unwrap()
        .into_iter()
        .filter(|s| s.view == 1 && !dataset::imm_is_test_person(s.person))
        .take(8)
        .collect();
    let shapes: Vec<Vec<Point>> = samples.iter().map(|s| s.landmarks().unwrap()).collect();
    let fits: Vec<facegate_morph::FittedFace> = shapes.iter().map(|p| fm.fit(p, 640, 480).unwrap()).collect();
    let learnt = annotated_jaw_vertices(fm, &fits.iter().collect::<Vec<_>>());
    let contour = contour_jaw_vertices(fm);
    let error = |jaw: &JawVertices| {
        let mut total = 0.0;
        for (fit, truth) in fits.iter().zip(&shapes) {
            let k = EyeMouthCentres::from_imm(truth);
            let eyes = facegate_core::geometry::distance(k.left_eye, k.right_eye);
            for j in JAW {
                let p = fit.vertices[jaw[j] as usize];
                let q = fit.camera.project([p[0] as f64, p[1] as f64, p[2] as f64]);
                total += facegate_core::geometry::distance([q[0] as f32, q[1] as f32], truth[j]) / eyes;
            }
        }
        total / (fits.len() * JAW.len()) as f32
    };
    let (e_learnt, e_contour) = (error(&learnt), error(&contour));
    eprintln!("jaw error / eye distance: learnt {e_learnt:.3}, contour rule {e_contour:.3}");
    assert!(e_learnt < 0.1 && e_learnt < 0.5 * e_contour, "learnt {e_learnt:.3}, contour rule {e_contour:.3}");
    assert_eq!(learnt[6], fm.imm_vertices[6]);
}

#[test]
fn synthetic_views_put_the_landmarks_on_the_rendered_face() {
    // The rendered eye region is darker than the cheeks in a grey render; simpler and stronger:
    // the landmark positions move the right way with yaw, and the face is drawn where they are.
    let fm = face_model();
    let s = list_imm(&facegate_paths::shared_dir().join("data/imm")).unwrap().into_iter().find(|s| s.person == 7 && s.view == 1).unwrap();
    let photo = imaging::open(&s.image).unwrap();
    let shape = s.landmarks().unwrap();
    let fit = fm.fit(&shape, photo.width(), photo.height()).unwrap();
    let texture = fm.extract_texture(&photo.rgb, &fit, 128);
    let bg = [0u8, 0, 0];
    let jaw = photo_jaw_vertices(fm, &fit, &contour_jaw_vertices(fm));
    let left = synthesise_view(fm, &fit, &texture, Pose { yaw: -30.0, pitch: 0.0, roll: 0.0 }, bg, 0.0, &jaw, &[]);
    let right = synthesise_view(fm, &fit, &texture, Pose { yaw: 30.0, pitch: 0.0, roll: 0.0 }, bg, 0.0, &jaw, &[]);
    // With the annotation offsets, the frontal re-render at the photo's own pose puts every
    // point, the jaw included (a frontal photo keeps its fitted jaw vertices), back on the
    // annotation.
    let offsets = annotation_offsets(fm, &fit, &shape);
    let same = synthesise_view(fm, &fit, &texture, fit.pose, bg, 0.0, &jaw, &offsets);
    for i in 0..58 {
        assert!(facegate_core::geometry::distance(same.points[i], shape[i]) < 0.5, "point {i}: {:?} vs {:?}", same.points[i], shape[i]);
    }
    // Nose tip (IMM 52 lies on the nose ridge/tip region) moves to the image right with positive yaw.
    let nose = |v: &SyntheticView| centroid(&v.points[facegate_core::face::NOSE]);
    assert!(nose(&right)[0] > nose(&left)[0] + 10.0);
    for v in [&left, &right] {
        // Every internal landmark is on the rendered face (not the black background).
        for p in &v.points[13..] {
            assert!(v.gray.sample(p[0], p[1]) > 5.0, "landmark {p:?} off the render");
        }
        // The fit of the 3DMM to the synthetic landmarks gives back the rendered yaw.
        let back = fm.fit(&v.points, photo.width(), photo.height()).unwrap();
        let want = v.camera.pose().yaw;
        assert!((back.pose.yaw - want).abs() < 5.0, "rendered at {want}, fitted {}", back.pose.yaw);
    }
}

#[test]
fn small_model_round_trips_and_survives_degenerate_input() {
    let fm = face_model();
    let samples: Vec<ImmSample> =
        list_imm(&facegate_paths::shared_dir().join("data/imm")).unwrap().into_iter().filter(|s| s.person == 4 || s.person == 6).collect();
    let options = Asm3dTrainOptions { pdm_shapes: 40, texture_size: 128, ..Default::default() };
    let model = train(&samples, fm, None, &options, &|| {}).unwrap();
    assert_eq!(model.views.len(), 7);
    assert_eq!(model.info.box_source, BoxSource::Annotation);
    let lm = Asm3dLandmarker::new(model);
    let dir = std::env::temp_dir().join(format!("facegate-asm3d-{}", std::process::id()));
    let path = dir.join("asm3d.bin");
    lm.save(&path).unwrap();
    let back = Asm3dLandmarker::load(&path).unwrap();
    assert_eq!(back.model.views[3].pdm.mean, lm.model.views[3].pdm.mean);
    std::fs::write(&path, b"not a model").unwrap();
    assert!(matches!(Asm3dLandmarker::load(&path), Err(LandmarkError::Model { .. })));
    std::fs::remove_dir_all(&dir).unwrap();
    // A training photo searched from its annotation box comes back near its annotation.
    let s = &samples[0];
    let photo = imaging::open(&s.image).unwrap();
    let truth = s.landmarks().unwrap();
    let found = lm.fit(&photo.gray, &facegate_research::train_asm::annotation_box(&truth));
    let de = facegate_research::eval::landmarks::d_eye(&found.centres, &EyeMouthCentres::from_imm(&truth));
    assert!(de < 0.1, "d_eye {de}");
    // The yaw of a projected model shape comes back, at any image scale.
    let view = &lm.model.views[3];
    for (yaw, scale) in [(0.0f32, 2.0), (30.0, 1.2), (-25.0, 3.0)] {
        let cam = Camera::from_pose(Pose { yaw, pitch: 5.0, roll: 3.0 }, scale, 300.0, 240.0);
        let pts = view.pdm.project(&vec![0.0; view.pdm.modes()], &cam);
        let got = lm.yaw_of(&pts).unwrap();
        assert!((got - yaw).abs() < 3.0, "yaw {yaw}: estimated {got}");
    }
    assert!(lm.yaw_of(&vec![[5.0, 5.0]; IMM_POINTS]).is_none());
    // The service switch keeps the C-ASM's points below the yaw threshold and replaces them
    // beyond it.
    let casm = facegate_vision::landmarks::Landmarker {
        model: facegate_research::train_asm::train(&samples, None, &facegate_research::train_asm::TrainOptions::default(), &|| {}).unwrap(),
    };
    let face = facegate_research::train_asm::annotation_box(&truth);
    let c = casm.fit(&photo.gray, &face, Variant::Casm);
    let (kept, used) = lm.switch(&photo.gray, &face, &casm, c.clone(), 90.0);
    assert!(!used && kept == c);
    let (replaced, used) = lm.switch(&photo.gray, &face, &casm, c.clone(), 0.0);
    assert!(used && replaced.points != c.points);
    let de = facegate_research::eval::landmarks::d_eye(&replaced.centres, &EyeMouthCentres::from_imm(&truth));
    assert!(de < 0.1, "switched d_eye {de}");
    let img = GrayF32::from_fn(92, 112, |x, y| ((x * 3 + y * 5) % 17) as f32 * 10.0);
    for b in [
        Rect::new(10.0, 20.0, 60.0, 60.0),
        Rect::new(-500.0, -500.0, 40.0, 40.0),
        Rect::new(0.0, 0.0, 0.0, 0.0),
        Rect::new(f32::NAN, 3.0, f32::INFINITY, -2.0),
        Rect::new(1.0, 1.0, 1e9, 1e9),
    ] {
        let out = lm.fit(&img, &b);
        assert_eq!(out.points.len(), 58);
    }
    for (w, h) in [(1, 1), (2, 2), (0, 0)] {
        assert_eq!(lm.fit(&GrayF32::new(w, h), &Rect::new(0.0, 0.0, 2.0, 2.0)).points.len(), 58);
    }
}

/// A point the view hides, given a wrong target, barely moves a weighted fit: its weight is small,
/// where the unweighted fit drags the other points after it.
#[test]
fn pdm3d_weighted_fit_discounts_hidden_points() {
    let fm = face_model();
    let pdm = &train_pdms(fm, &[60.0], &contour_jaw_vertices(fm), 120, 0.98, 3.0, 3)[0];
    let cam = Camera::from_pose(Pose { yaw: 60.0, pitch: 0.0, roll: 0.0 }, 2.0, 200.0, 180.0);
    let truth = pdm.project(&vec![0.0; pdm.modes()], &cam);
    let mut targets = truth.clone();
    // An eye's points (as a hidden eye's guesses would be) pulled 60 px away.
    for p in &mut targets[facegate_core::face::EYE_IMAGE_LEFT] {
        p[0] -= 60.0;
    }
    let mut weights = vec![1.0; IMM_POINTS];
    facegate_core::face::EYE_IMAGE_LEFT.for_each(|i| weights[i] = HIDDEN_POINT_WEIGHT);
    let error = |fit: &Fit3d| {
        let others: Vec<f32> = (0..IMM_POINTS)
            .filter(|i| !facegate_core::face::EYE_IMAGE_LEFT.contains(i))
            .map(|i| facegate_core::geometry::distance(fit.points[i], truth[i]))
            .collect();
        others.iter().sum::<f32>() / others.len() as f32
    };
    let plain = pdm.fit(&targets, 4.0, 4).unwrap();
    let weighted = pdm.fit_weighted(&targets, &weights, 4.0, 4).unwrap();
    assert!(error(&weighted) < 0.5 * error(&plain), "weighted {} px, plain {} px", error(&weighted), error(&plain));
    // Unit weights are the plain fit.
    let ones = pdm.fit_weighted(&targets, &vec![1.0; IMM_POINTS], 4.0, 4).unwrap();
    assert_eq!(ones.points, plain.points);
}

/// A frontal view shows every internal point; a full profile hides the far eye and mouth corner
/// and keeps the near ones.
#[test]
fn views_hide_the_far_side_as_the_head_turns() {
    let fm = face_model();
    let jaw = contour_jaw_vertices(fm);
    let frontal = view_visibility(fm, &jaw, 0.0);
    assert!(frontal[13..].iter().all(|v| *v), "{frontal:?}");
    // +90°: the nose points to the image right, so the subject turned to their left and the
    // image-right eye (the subject's left) is behind the nose.
    let profile = view_visibility(fm, &jaw, 90.0);
    let hidden = |range: std::ops::Range<usize>| range.filter(|&i| !profile[i]).count();
    assert!(hidden(facegate_core::face::EYE_IMAGE_RIGHT) >= 6, "{profile:?}");
    assert!(hidden(facegate_core::face::EYE_IMAGE_LEFT) <= 2, "{profile:?}");
    assert!(profile[39] && !profile[43], "mouth corners: image-left shown, image-right hidden");
}

/// On renders of an IMM face at 75°, the profile model seeded by YuNet's five points finds the
/// points the view shows; the C-ASM (switched to the thesis's 3D-ASM by its own points) does not.
/// (The committed models saw this person; `facegate eval landmarks` measures held-out persons.)
#[test]
fn the_profile_model_finds_a_turned_render_from_the_detectors_points() {
    let fm = face_model();
    let models = facegate_paths::models_dir();
    let detector = facegate_detect::Detector::load(&models).unwrap();
    let casm = facegate_vision::landmarks::Landmarker::load(&models.join("asm.bin")).unwrap();
    let thesis = Asm3dLandmarker::load(&models.join("asm3d.bin")).unwrap();
    let profile = Asm3dLandmarker::load_profile(&models.join("asm3d-profile.bin")).unwrap();
    let sample =
        list_imm(&facegate_paths::shared_dir().join("data/imm")).unwrap().into_iter().find(|s| s.person == 3 && s.view == 1).unwrap();
    let photo = imaging::open(&sample.image).unwrap();
    let truth = sample.landmarks().unwrap();
    let fit = fm.fit(&truth, photo.width(), photo.height()).unwrap();
    let texture = fm.extract_texture(&photo.rgb, &fit, 512);
    let jaw = photo_jaw_vertices(fm, &fit, &contour_jaw_vertices(fm));
    let offsets = annotation_offsets(fm, &fit, &truth);
    for yaw in [-75.0f32, 75.0] {
        let view = synthesise_view(
            fm,
            &fit,
            &texture,
            Pose { yaw, pitch: fit.pose.pitch, roll: 0.0 },
            background_colour(&photo.rgb),
            0.0,
            &jaw,
            &offsets,
        );
        let face = detector.detect(&view.gray).first().copied().expect("YuNet finds the render");
        let points = face.points.expect("YuNet's five points");
        assert!(profile.detector_yaw(&points).unwrap().abs() >= DETECTOR_SEED_MIN_YAW, "{yaw}°");
        let shown = &profile.visible[profile.model.views.iter().position(|v| v.yaw == yaw).unwrap()];
        let k = EyeMouthCentres::from_imm(&view.points);
        let size =
            facegate_core::geometry::distance([0.5 * (k.left_eye[0] + k.right_eye[0]), 0.5 * (k.left_eye[1] + k.right_eye[1])], k.mouth);
        let error = |found: &[Point]| {
            let e: Vec<f32> =
                (0..IMM_POINTS).filter(|&i| shown[i]).map(|i| facegate_core::geometry::distance(found[i], view.points[i])).collect();
            e.iter().sum::<f32>() / e.len() as f32 / size
        };
        let seeded = profile.fit_from_detector(&view.gray, &points, &casm.model).expect("seeded");
        assert!(seeded.view_yaw.abs() >= 60.0 && seeded.view_yaw.signum() == yaw.signum(), "{yaw}°: view {}", seeded.view_yaw);
        let rect = facegate_vision::pipeline::seed_box(&face);
        let switched = thesis.switch(&view.gray, &rect, &casm, casm.fit(&view.gray, &rect, Variant::Casm), SERVICE_MIN_YAW).0;
        let (a, b) = (error(&seeded.points), error(&switched.points));
        assert!(a < 0.12 && a < 0.8 * b, "{yaw}°: seeded {a:.3}, C-ASM path {b:.3} (of the eyes-to-mouth distance)");
    }
}
