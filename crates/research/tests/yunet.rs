//! The YuNet detector on real photos: frontal (IMM), full profile (UMIST), small grey crops (ORL)
//! and face-free images.

use facegate_detect::{DetectOptions, Detector, DetectorKind, Face, YUNET_MODEL};
use facegate_paths::{models_dir, shared_dir};

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Rect, distance};
use facegate_core::imaging::{GrayF32, open};
use facegate_research::dataset::list_imm;

fn yunet() -> Detector {
    Detector::load_kind(&models_dir(), DetectorKind::Yunet).unwrap()
}

fn points(face: &Face) -> [[f32; 2]; 5] {
    face.points.expect("YuNet locates five key points")
}

fn holds_points(face: &Face) -> bool {
    points(face).iter().all(|&p| face.rect.contains(p))
}

#[test]
fn the_model_file_is_the_converted_one() {
    let bytes = std::fs::read(models_dir().join(YUNET_MODEL)).unwrap();
    assert_eq!(facegate_vision::embed::onnx::sha256_hex(&bytes), facegate_research::convert::yunet::SHA256);
    assert_eq!(bytes, facegate_detect::EMBEDDED_YUNET);
}

#[test]
fn imm_frontal_photos_give_one_face_with_eyes_nose_and_mouth_in_image_order() {
    let detector = yunet();
    assert_eq!(detector.kind(), DetectorKind::Yunet);
    let samples = list_imm(&shared_dir().join("data/imm")).unwrap();
    // Held-out persons, both frontal views and the spot-light one.
    for s in samples.iter().filter(|s| [1, 2, 5, 10].contains(&s.person) && [1, 2, 5].contains(&s.view)) {
        let name = s.image.display().to_string();
        let faces = detector.detect(&open(&s.image).unwrap().gray);
        assert_eq!(faces.len(), 1, "{name}: {faces:?}");
        let face = &faces[0];
        let keys = EyeMouthCentres::from_imm(&s.landmarks().unwrap());
        assert!(face.rect.contains(keys.left_eye) && face.rect.contains(keys.right_eye) && face.rect.contains(keys.mouth), "{name}");
        assert!(holds_points(face), "{name}: {face:?}");
        let [left_eye, right_eye, nose, mouth_left, mouth_right] = points(face);
        let eyes = distance(keys.left_eye, keys.right_eye);
        assert!(distance(left_eye, keys.left_eye) < 0.25 * eyes, "{name}: {left_eye:?} vs {:?}", keys.left_eye);
        assert!(distance(right_eye, keys.right_eye) < 0.25 * eyes, "{name}: {right_eye:?} vs {:?}", keys.right_eye);
        let mouth = [(mouth_left[0] + mouth_right[0]) / 2.0, (mouth_left[1] + mouth_right[1]) / 2.0];
        assert!(distance(mouth, keys.mouth) < 0.25 * eyes, "{name}: {mouth:?} vs {:?}", keys.mouth);
        assert!(mouth_left[0] < mouth_right[0], "{name}");
        assert!(nose[1] > left_eye[1].max(right_eye[1]) && nose[1] < mouth[1], "{name}: nose {nose:?}");
        assert!(face.score >= detector.options.yunet_score && face.score <= 1.0);
    }
}

#[test]
fn a_mirrored_photo_keeps_the_image_left_eye_first() {
    let detector = yunet();
    let gray = open(&shared_dir().join("data/imm/03-1m.jpg")).unwrap().gray;
    let mirrored = GrayF32::from_fn(gray.width, gray.height, |x, y| gray.get(gray.width - 1 - x, y));
    let (direct, flipped) = (detector.detect(&gray), detector.detect(&mirrored));
    assert_eq!((direct.len(), flipped.len()), (1, 1));
    let (a, b) = (points(&direct[0]), points(&flipped[0]));
    let w = gray.width as f32 - 1.0;
    assert!(a[0][0] < a[1][0] && b[0][0] < b[1][0], "{a:?} / {b:?}");
    // The mirror's image-left eye is the original's image-right one, moved across.
    assert!((w - b[0][0] - a[1][0]).abs() < 6.0 && (b[0][1] - a[1][1]).abs() < 6.0, "{a:?} / {b:?}");
    let back = Rect::new(w - flipped[0].rect.x - flipped[0].rect.width, flipped[0].rect.y, flipped[0].rect.width, flipped[0].rect.height);
    assert!(direct[0].rect.iou(&back) > 0.8, "{:?} vs {back:?}", direct[0].rect);
}

#[test]
fn a_umist_full_profile_gives_one_central_face() {
    let detector = yunet();
    for subject in ["s01", "s05"] {
        let gray = open(&shared_dir().join(format!("data/umist/{subject}/01.pgm"))).unwrap().gray;
        assert_eq!((gray.width, gray.height), (92, 112));
        let faces = detector.detect(&gray);
        assert_eq!(faces.len(), 1, "{subject}: {faces:?}");
        let r = faces[0].rect;
        // The head fills the crop: a box over half its width whose centre lies in the middle half.
        let c = r.center();
        assert!(r.width > 46.0 && (23.0..69.0).contains(&c[0]) && (28.0..84.0).contains(&c[1]), "{subject}: {r:?}");
        assert!(holds_points(&faces[0]), "{subject}: {:?}", faces[0]);
    }
}

#[test]
fn an_orl_crop_gives_one_face_holding_its_key_points() {
    let detector = yunet();
    let gray = open(&shared_dir().join("data/orl/s1/1.pgm")).unwrap().gray;
    let faces = detector.detect(&gray);
    assert_eq!(faces.len(), 1, "{faces:?}");
    let face = &faces[0];
    assert!(face.rect.contains([46.0, 56.0]) && face.rect.width > 40.0, "{face:?}");
    assert!(holds_points(face), "{face:?}");
    let [left_eye, right_eye, _, mouth_left, _] = points(face);
    assert!(left_eye[0] < 46.0 && right_eye[0] > 46.0 && mouth_left[1] > left_eye[1], "{face:?}");
}

#[test]
fn face_free_images_give_no_face() {
    let detector = yunet();
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let noise = GrayF32::from_fn(640, 480, |_, _| rng.random_range(0.0..255.0));
    let mut images =
        vec![GrayF32::from_fn(640, 480, |_, _| 128.0), noise.gaussian_blur(3.0), noise, GrayF32::new(5, 3), GrayF32::new(0, 0)];
    // The background left of an IMM sitter (as eval detect's face-free strips).
    let photo = open(&shared_dir().join("data/imm/01-1m.jpg")).unwrap().gray;
    let keys = EyeMouthCentres::from_imm(&list_imm(&shared_dir().join("data/imm")).unwrap()[0].landmarks().unwrap());
    let strip = (keys.left_eye[0] - 1.5 * distance(keys.left_eye, keys.right_eye)).max(0.0) as usize;
    assert!(strip >= 100, "strip of {strip} pixels");
    images.push(GrayF32::from_fn(strip, photo.height, |x, y| photo.get(x, y)));
    for (i, g) in images.iter().enumerate() {
        assert!(detector.detect(g).is_empty(), "image {i}: {:?}", detector.detect(g));
    }
}

/// The input shrunk to the smallest face searched (the default) finds the faces the full square
/// finds, in about the same boxes: frontal, turned and spot-lit IMM photos, LFW photos (small
/// images keep the square).
#[test]
fn the_shrunk_input_finds_what_the_full_square_finds() {
    let shrunk = yunet();
    assert!(shrunk.options.yunet_min_face_px > 0.0, "the default shrinks the input");
    let options = DetectOptions { yunet_min_face_px: 0.0, ..shrunk.options };
    let full = Detector::load_with(&models_dir(), DetectorKind::Yunet, options).unwrap();
    let data = shared_dir().join("data");
    for path in ["imm/01-1m.jpg", "imm/05-3m.jpg", "imm/10-5m.jpg", "lfw/Hal_Sutton/Hal_Sutton_0001.jpg", "lfw/Al_Gore/Al_Gore_0002.jpg"] {
        let gray = open(&data.join(path)).unwrap().gray;
        let (a, b) = (shrunk.detect(&gray), full.detect(&gray));
        assert_eq!(a.len(), b.len(), "{path}");
        let iou = a[0].rect.iou(&b[0].rect);
        assert!(iou > 0.7, "{path}: IoU {iou}");
    }
}

#[test]
fn two_photos_side_by_side_give_two_faces_largest_first() {
    let detector = yunet();
    let a = open(&shared_dir().join("data/imm/02-1m.jpg")).unwrap().gray;
    let b = open(&shared_dir().join("data/imm/05-2m.jpg")).unwrap().gray.resize(480, 360);
    let both = GrayF32::from_fn(a.width + b.width, a.height, |x, y| {
        if x < a.width {
            a.get(x, y)
        } else if y < b.height {
            b.get(x - a.width, y)
        } else {
            0.0
        }
    });
    let faces = detector.detect(&both);
    assert_eq!(faces.len(), 2, "{faces:?}");
    assert!(faces[0].rect.area() > faces[1].rect.area());
    assert!(faces[0].rect.center()[0] < a.width as f32 && faces[1].rect.center()[0] > a.width as f32, "{faces:?}");
}

#[test]
fn a_higher_threshold_or_a_larger_minimum_drops_faces() {
    let gray = open(&shared_dir().join("data/orl/s1/1.pgm")).unwrap().gray;
    let strict = Detector::load_with(&models_dir(), DetectorKind::Yunet, DetectOptions { yunet_score: 1.01, ..DetectOptions::default() });
    assert!(strict.unwrap().detect(&gray).is_empty());
    let big = DetectOptions { min_face: 200, ..DetectOptions::default() };
    assert!(Detector::load_with(&models_dir(), DetectorKind::Yunet, big).unwrap().detect(&gray).is_empty());
}

#[test]
fn threads_share_one_loaded_detector() {
    let detector = yunet();
    let gray = open(&shared_dir().join("data/orl/s2/1.pgm")).unwrap().gray;
    let alone = detector.detect(&gray);
    assert_eq!(alone.len(), 1);
    std::thread::scope(|scope| {
        let runs: Vec<_> = (0..4).map(|_| scope.spawn(|| detector.detect(&gray))).collect();
        for run in runs {
            assert_eq!(run.join().unwrap(), alone);
        }
    });
}

#[test]
fn the_embedded_copy_serves_when_the_models_folder_lacks_the_file() {
    let empty = std::env::temp_dir().join(format!("facegate-yunet-empty-{}", std::process::id()));
    std::fs::create_dir_all(&empty).unwrap();
    let detector = Detector::load_kind(&empty, DetectorKind::Yunet).unwrap();
    let gray = open(&shared_dir().join("data/orl/s1/1.pgm")).unwrap().gray;
    assert_eq!(detector.detect(&gray), yunet().detect(&gray));
    std::fs::remove_dir(&empty).unwrap();
}
