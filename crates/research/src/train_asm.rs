//! Training all three variants from annotated IMM photos: the full, internal and contour shape
//! models, the grey-level profile and SIFT models of every point at every pyramid level, and the
//! placement of the mean shape relative to the face boxes. Deterministic: the same photos give the
//! same model, byte for byte.

use crate::dataset::{self, ImmSample};

use crate::landmark_models::{train_full_gaussian, train_pca_gaussian, train_shape_model};
use facegate_core::face::{INTERNAL, JAW};
use facegate_core::geometry::{Point, Rect, Similarity};
use facegate_core::imaging::{self, GrayF32};
use facegate_detect::Detector;

use facegate_vision::landmarks::pdm::ShapeModel;
use facegate_vision::landmarks::search::{Frame, normals, pyramid, to_level};
use facegate_vision::landmarks::{
    AsmModel, BoxSource, LandmarkError, MODEL_FORMAT, Placement, SearchParams, Start, TrainInfo, profile, sift,
};

/// Training settings (thesis defaults).
#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub params: SearchParams,
    /// Share of the shape variance the PDMs keep (thesis: 98%).
    pub shape_variance: f64,
    /// S_constrain (thesis: 3).
    pub constrain: f32,
    /// Principal components of each SIFT model.
    pub sift_modes: usize,
    /// Ridge added to the profile covariances, as a share of their mean variance.
    pub profile_ridge: f64,
}

impl Default for TrainOptions {
    fn default() -> Self {
        Self { params: SearchParams::default(), shape_variance: 0.98, constrain: 3.0, sift_modes: 24, profile_ridge: 0.05 }
    }
}

/// A box for a training photo from the detector: the detection holding both annotated eye
/// centres and the mouth centre (`None` when the detector missed the face).
pub fn detector_box(detector: &Detector, gray: &GrayF32, shape: &[Point]) -> Option<Rect> {
    let k = facegate_core::face::EyeMouthCentres::from_imm(shape);
    detector
        .detect(gray)
        .iter()
        .map(facegate_vision::pipeline::seed_box)
        .find(|r| r.contains(k.left_eye) && r.contains(k.right_eye) && r.contains(k.mouth))
}

/// The fallback box: the bounding box of the annotated points.
pub fn annotation_box(shape: &[Point]) -> Rect {
    Rect::bounding(shape).unwrap_or(Rect::new(0.0, 0.0, 1.0, 1.0))
}

/// The median, 0 for no values.
fn median(v: &mut [f32]) -> f32 {
    facegate_core::median(v).unwrap_or(0.0)
}

/// Group the training shapes by their first coefficient (turned one way, frontal, turned the other
/// way, at ±`threshold` σ) and learn each group's mean shape and its placement relative to the
/// boxes. The frontal group (all photos when `threshold` is 0) comes first.
fn learn_starts(full: &ShapeModel, shapes: &[Vec<Point>], boxes: &[Option<Rect>], threshold: f32) -> Vec<Start> {
    let coefs: Vec<Vec<f32>> = shapes.iter().map(|s| full.fit(s).2).collect();
    let sigma0 = full.eigenvalues.first().map_or(1.0, |l| l.sqrt().max(1e-6));
    let group_of = |b: &[f32]| -> usize {
        let z = b.first().copied().unwrap_or(0.0) / sigma0;
        if threshold <= 0.0 || z.abs() <= threshold {
            0
        } else if z > 0.0 {
            1
        } else {
            2
        }
    };
    let mut out = Vec::new();
    for g in 0..3 {
        let members: Vec<usize> = (0..shapes.len()).filter(|&i| group_of(&coefs[i]) == g).collect();
        let placed: Vec<usize> = members.iter().copied().filter(|&i| boxes[i].is_some()).collect();
        if placed.len() < 3 {
            continue;
        }
        let mut b = vec![0.0f32; full.modes()];
        for &i in &members {
            for (a, c) in b.iter_mut().zip(&coefs[i]) {
                *a += c / members.len() as f32;
            }
        }
        let start_shape = full.shape(&b);
        let (mut sc, mut dx, mut dy) = (Vec::new(), Vec::new(), Vec::new());
        for &i in &placed {
            let bx = boxes[i].expect("filtered");
            let pose = Similarity::fit(&start_shape, &shapes[i], None);
            let c = bx.center();
            sc.push(pose.scale() / bx.width);
            dx.push((pose.tx - c[0]) / bx.width);
            dy.push((pose.ty - c[1]) / bx.width);
        }
        let placement = Placement { scale_per_width: median(&mut sc), dx: median(&mut dx), dy: median(&mut dy) };
        out.push(Start { b, placement, photos: members.len() });
    }
    out
}

/// Neighbours of each point on its contour from the `.asf` connectivity (`from`, `to`).
fn neighbours(sample: &ImmSample) -> Result<Vec<[u16; 2]>, LandmarkError> {
    let shape = dataset::read_asf(&sample.asf, 1.0, 1.0).map_err(|e| LandmarkError::Training(e.to_string()))?;
    Ok(shape.points.iter().map(|p| [p.from.min(57) as u16, p.to.min(57) as u16]).collect())
}

/// Train on `samples`. `detector` (optional) provides the boxes the placement is learnt from;
/// without it, or when it misses every photo, the annotation boxes are used. `tick` is called
/// once per photo processed.
pub fn train(
    samples: &[ImmSample],
    detector: Option<&Detector>,
    options: &TrainOptions,
    tick: &dyn Fn(),
) -> Result<AsmModel, LandmarkError> {
    if samples.len() < 3 {
        return Err(LandmarkError::Training(format!("{} annotated photos; at least 3 are needed", samples.len())));
    }
    let p = &options.params;
    let shapes: Vec<Vec<Point>> =
        samples.iter().map(|s| s.landmarks()).collect::<Result<_, _>>().map_err(|e| LandmarkError::Training(e.to_string()))?;
    let full = train_shape_model(&shapes, p.ref_width, options.shape_variance, options.constrain);
    // The group models are aligned in their own right, at the scale the full model gives them.
    let group = |range: std::ops::Range<usize>| {
        let sub: Vec<Vec<Point>> = shapes.iter().map(|s| s[range.clone()].to_vec()).collect();
        let (x0, x1) = full.mean[range].iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
        train_shape_model(&sub, x1 - x0, options.shape_variance, options.constrain)
    };
    let contour = group(JAW);
    let internal = group(INTERNAL);
    let neighbours = neighbours(&samples[0])?;

    let n = full.points();
    let mut profile_samples: Vec<Vec<Vec<Vec<f32>>>> = vec![vec![Vec::new(); n]; p.levels];
    let mut sift_samples: Vec<Vec<Vec<Vec<f32>>>> = vec![vec![Vec::new(); n]; p.levels];
    let (mut misses, mut detected) = (0usize, 0usize);
    let mut boxes: Vec<Option<Rect>> = Vec::with_capacity(samples.len());
    let mut nrm = Vec::new();
    for (sample, shape) in samples.iter().zip(&shapes) {
        let photo = imaging::open(&sample.image).map_err(|e| LandmarkError::Training(e.to_string()))?;
        let pose = Similarity::fit(&full.mean, shape, None);
        boxes.push(match detector {
            Some(det) => {
                let b = detector_box(det, &photo.gray, shape);
                if b.is_some() {
                    detected += 1
                } else {
                    misses += 1
                }
                b
            }
            None => None,
        });
        // Texture statistics at the annotated points, in the same crop the search uses.
        let frame = Frame::from_pose(&Similarity { a: pose.scale(), b: 0.0, tx: pose.tx, ty: pose.ty }, p.crop_size);
        let levels = pyramid(frame.crop(&photo.gray, p.crop_size), p.levels);
        let in_crop: Vec<Point> = shape.iter().map(|&q| frame.to_crop(q)).collect();
        for (l, lvl) in levels.iter().enumerate() {
            let pts: Vec<Point> = in_crop.iter().map(|&q| to_level(q, l)).collect();
            normals(&pts, &neighbours, &mut nrm);
            for i in 0..n {
                profile_samples[l][i].push(profile::profile(&lvl.image, pts[i], nrm[i]).to_vec());
                sift_samples[l][i].push(sift::descriptor(&lvl.gradients, pts[i], nrm[i]).to_vec());
            }
        }
        tick();
    }
    // Placement from detector boxes when the detector found enough of the training faces; photos
    // it missed are left out. Otherwise from the annotation boxes.
    let box_source = if detected >= 3 { BoxSource::Detector } else { BoxSource::Annotation };
    let boxes: Vec<Option<Rect>> = match box_source {
        BoxSource::Detector => boxes,
        BoxSource::Annotation => shapes.iter().map(|s| Some(annotation_box(s))).collect(),
    };
    let starts = learn_starts(&full, &shapes, &boxes, p.yaw_start);
    if starts.is_empty() {
        return Err(LandmarkError::Training("fewer than 3 photos with a face box".into()));
    }
    let profiles = profile_samples.iter().map(|lv| lv.iter().map(|s| train_full_gaussian(s, options.profile_ridge)).collect()).collect();
    let sifts = sift_samples.iter().map(|lv| lv.iter().map(|s| train_pca_gaussian(s, options.sift_modes)).collect()).collect();
    let mut persons: Vec<u32> = samples.iter().map(|s| s.person).collect();
    persons.dedup();
    Ok(AsmModel {
        format: MODEL_FORMAT,
        params: p.clone(),
        neighbours,
        full,
        internal,
        contour,
        profiles,
        sifts,
        starts,
        info: TrainInfo { images: samples.len(), persons, box_source, detector_misses: misses },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_imm_asf_file_reads_with_the_same_contours() {
        let samples = dataset::list_imm(&facegate_paths::shared_dir().join("data/imm")).unwrap();
        assert_eq!(samples.len(), 180);
        let first = neighbours(&samples[0]).unwrap();
        assert_eq!(first.len(), facegate_core::face::IMM_POINTS);
        // The jaw is an open contour (its ends are their own neighbours), the eyes are closed.
        assert_eq!(first[0], [0, 1]);
        assert_eq!(first[12], [11, 12]);
        assert_eq!(first[13], [20, 14]);
        for s in &samples {
            assert_eq!(neighbours(s).unwrap(), first, "{}", s.asf.display());
            let pts = s.landmarks().unwrap();
            assert!(pts.iter().all(|p| p[0] > 0.0 && p[0] < 640.0 && p[1] > 0.0 && p[1] < 480.0));
        }
    }
}
