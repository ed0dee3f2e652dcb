//! Synthetic templates: the thesis's pose correction turned around. Instead of rendering a turned
//! probe from the front (which measured worse as the network's input), the enrolled face's fitted,
//! textured 3D head is rendered at other yaws, and each rendering is read by the same front end
//! as a probe photo (detector, landmarks, chip, network), so that a turned probe meets a template
//! made at its own pose and aligned the way its own chip is.

use facegate_core::face::EyeMouthCentres;
use facegate_core::imaging::{GrayF32, Photo};

use facegate_core::geometry::Point;

use facegate_core::template::Template;
use facegate_morph::{FaceModel, FittedFace, Pose, TEXTURE_SIZE};
use facegate_vision::landmarks::Landmarks;
use facegate_vision::pipeline::{FaceAnalysis, Pipeline};
use facegate_vision::recognize::Recognizer;

use crate::asm3d_synth as asm3d;

/// One synthetic template and the yaw it was rendered at.
#[derive(Debug, Clone)]
pub struct SyntheticTemplate {
    /// Degrees; the sign follows [`Pose::yaw`].
    pub yaw: f32,
    pub template: Template,
}

/// Renderings of the fitted head at each of `poses`, at the photo's size, scale and place, on a
/// flat background of the photo's mean grey, with the 58 landmarks (and their eye and mouth
/// centres) the model puts there. The synthetic templates here and the classical recognizer's
/// re-posed training views (`research::train_dlda`) are both made by it.
pub fn render_at(model: &FaceModel, photo: &Photo, fit: &FittedFace, points: &[Point], poses: &[Pose]) -> Vec<(Photo, Landmarks)> {
    let texture = model.extract_texture(&photo.rgb, fit, TEXTURE_SIZE);
    let offsets = asm3d::annotation_offsets(model, fit, points);
    let jaw = asm3d::photo_jaw_vertices(model, fit, &asm3d::contour_jaw_vertices(model));
    let grey = (photo.gray.data.iter().sum::<f32>() / photo.gray.data.len().max(1) as f32).clamp(0.0, 255.0) as u8;
    poses
        .iter()
        .map(|&pose| {
            let view = asm3d::synthesise_view(model, fit, &texture, pose, [grey; 3], 0.0, &jaw, &offsets);
            let centres = EyeMouthCentres::from_imm(&view.points);
            (photo_of(view.gray), Landmarks { points: view.points, centres })
        })
        .collect()
}

fn photo_of(gray: GrayF32) -> Photo {
    let rgb = image::RgbImage::from_fn(gray.width as u32, gray.height as u32, |x, y| {
        image::Rgb([gray.get(x as usize, y as usize).clamp(0.0, 255.0) as u8; 3])
    });
    Photo { rgb, gray }
}

/// The deep templates of the analysed face's head rendered at each of `yaws` (degrees, the
/// head's pitch and roll kept), read by `pipeline`'s own stages. Each rendering is read like a
/// photo: its largest face's landmarks give the chip, and when the detector finds no face there
/// the rendering's own model landmarks do. Empty without the 3D model, with the classical
/// recognizer, or when the fit fails.
pub fn synthetic_templates(pipeline: &Pipeline, photo: &Photo, analysis: &FaceAnalysis, yaws: &[f32]) -> Vec<SyntheticTemplate> {
    let Some(model) = pipeline.face_model.as_ref().filter(|_| !matches!(pipeline.recognizer, Recognizer::Classical(_))) else {
        return Vec::new();
    };
    let points = &analysis.landmarks.points;
    let Ok(fit) = model.fit(points, photo.width(), photo.height()) else { return Vec::new() };
    let poses: Vec<Pose> = yaws.iter().map(|&yaw| Pose { yaw, pitch: fit.pose.pitch, roll: fit.pose.roll }).collect();
    render_at(model, photo, &fit, points, &poses)
        .into_iter()
        .zip(yaws)
        .filter_map(|((view, exact), &yaw)| {
            let found = pipeline.finder.detect(&view.gray).first().copied();
            let centres = match &found {
                Some(face) => pipeline.finder.landmarks_of(&view.gray, face).centres,
                None => exact.centres,
            };
            let points = found.and_then(|f| f.points);
            let template = deep_template(pipeline, &view.rgb, &centres, points.as_ref())?;
            Some(SyntheticTemplate { yaw, template })
        })
        .collect()
}

/// The deep template of the analysed face's 3DMM frontal rendering (the thesis's pose correction,
/// as the network's input): the 3DMM fitted to the face's landmarks, its texture rendered from the
/// front, embedded at the rendering's eye and mouth centres by `pipeline`'s recognizer. `None`
/// without the 3D model, with the classical recognizer, or when the fit fails.
pub fn frontal_template(pipeline: &Pipeline, photo: &Photo, analysis: &FaceAnalysis) -> Option<Template> {
    let model = pipeline.face_model.as_ref()?;
    let fit = model.fit(&analysis.landmarks.points, photo.width(), photo.height()).ok()?;
    let frontal = model.frontalize(photo, &fit).ok()?;
    deep_template(pipeline, &frontal.image, &frontal.centres, None)
}

/// The deep recognizer's template of `rgb` with its eye and mouth centres at `centres` (and the
/// detector's five points, for a network aligned by them); `None` for the classical recognizer.
fn deep_template(pipeline: &Pipeline, rgb: &image::RgbImage, centres: &EyeMouthCentres, points: Option<&[Point; 5]>) -> Option<Template> {
    match &pipeline.recognizer {
        Recognizer::Dlib(deep) => Some(deep.template_of_chip(&facegate_vision::embed::face_chip(rgb, centres))),
        Recognizer::Embedding(recognizer, _) => Some(recognizer.embed(rgb, centres, points, None).template),
        Recognizer::Classical(_) => None,
    }
}
