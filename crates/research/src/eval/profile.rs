//! Landmarks from frontal to full profile, on renders of held-out IMM faces: the error of the
//! points each view shows, for the C-ASM path and the profile model seeded by the detector's five
//! points, and the head pose from the five points or from the 3DMM fitted to the profile model's
//! points (`facegate eval landmarks`, beside the thesis's tables).

use std::io::Write;

use serde::Serialize;

use crate::dataset::ImmSample;

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, distance};
use facegate_core::imaging::GrayF32;
use facegate_detect::{Detector, Face};
use facegate_vision::landmarks::Landmarker;

/// A landmark search from a detected face (box and, from YuNet, five points) to 58 points.
pub type PointSearch<'a> = &'a dyn Fn(&GrayF32, &Face) -> Vec<Point>;

/// Yaws (degrees) of the profile renders.
pub const PROFILE_YAWS: [f32; 13] = [-90.0, -75.0, -60.0, -45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0];

/// One |yaw| of the profile renders: a search's error on the points the view shows.
#[derive(Debug, Clone, Serialize)]
pub struct ProfileRow {
    pub yaw: f32,
    pub renders: usize,
    /// Renders where the detector found no face (failures).
    pub detector_misses: usize,
    /// Mean over renders of the mean error of the points the view shows, over the distance from
    /// the eyes' midpoint to the mouth (a size that does not shrink as the head turns).
    pub mean_error: f64,
    /// Renders with that error below 0.1 and 0.2.
    pub error_01: f64,
    pub error_02: f64,
}

/// Landmark searches on renders of held-out faces from frontal to full profile: every
/// near-frontal photo (|yaw| < 10°, 3DMM fitted to its manual landmarks) of `test` is fitted,
/// textured and rendered at each of [`PROFILE_YAWS`] (as [`crossover`](super::landmarks::crossover)); the detector runs on each
/// render once and every one of `searches` gets its largest face. The error counts only the points
/// the view shows (the profile model `asm3d`'s view of that yaw), since a hidden point has no
/// position to find in the photo. Rows per search, in the order given.
pub fn profile_renders(
    fm: &facegate_morph::FaceModel,
    test: &[ImmSample],
    detector: &Detector,
    asm3d: &facegate_vision::landmarks::asm3d::Asm3dLandmarker,
    searches: &[(&'static str, PointSearch)],
) -> anyhow::Result<Vec<(&'static str, Vec<ProfileRow>)>> {
    use facegate_vision::landmarks::asm3d::nearest_view;
    let view_yaws: Vec<f32> = asm3d.model.views.iter().map(|v| v.yaw).collect();
    let bands = bands(&PROFILE_YAWS);
    // [search][band]: the error per render, infinite for a detector miss.
    let mut errors: Vec<Vec<Vec<f64>>> = vec![vec![Vec::new(); bands.len()]; searches.len()];
    let mut misses = vec![0usize; bands.len()];
    for_each_render(fm, test, &PROFILE_YAWS, &mut |yaw, view| {
        let band = bands.iter().position(|&b| b == yaw.abs()).expect("a band per yaw");
        let Some(face) = detector.detect(&view.gray).first().copied() else {
            misses[band] += 1;
            errors.iter_mut().for_each(|e| e[band].push(f64::INFINITY));
            return;
        };
        let visible = &asm3d.visible[nearest_view(&view_yaws, yaw)];
        let k = EyeMouthCentres::from_imm(&view.points);
        let mid = [0.5 * (k.left_eye[0] + k.right_eye[0]), 0.5 * (k.left_eye[1] + k.right_eye[1])];
        let size = distance(mid, k.mouth).max(1e-6) as f64;
        for ((_, search), e) in searches.iter().zip(errors.iter_mut()) {
            let found = search(&view.gray, &face);
            let shown: Vec<f64> = (0..view.points.len())
                .filter(|&i| visible.get(i).copied().unwrap_or(true))
                .map(|i| distance(found[i], view.points[i]) as f64)
                .collect();
            e[band].push(shown.iter().sum::<f64>() / shown.len().max(1) as f64 / size);
        }
    })?;
    Ok(searches
        .iter()
        .zip(errors)
        .map(|(&(name, _), by_band)| {
            let rows = bands
                .iter()
                .zip(by_band)
                .zip(&misses)
                .map(|((&yaw, e), &detector_misses)| {
                    let share = |t: f64| e.iter().filter(|&&x| x < t).count() as f64 / e.len().max(1) as f64;
                    let finite: Vec<f64> = e.iter().copied().filter(|x| x.is_finite()).collect();
                    ProfileRow {
                        yaw,
                        renders: e.len(),
                        detector_misses,
                        mean_error: finite.iter().sum::<f64>() / finite.len().max(1) as f64,
                        error_01: share(0.1),
                        error_02: share(0.2),
                    }
                })
                .collect();
            (name, rows)
        })
        .collect())
}

/// The |yaw| bands of `yaws`, ascending.
pub(super) fn bands(yaws: &[f32]) -> Vec<f32> {
    let mut bands: Vec<f32> = yaws.iter().map(|y| y.abs()).collect();
    bands.sort_by(f32::total_cmp);
    bands.dedup();
    bands
}

/// Every near-frontal photo (|yaw| < 10°, 3DMM fitted to its manual landmarks) of `test`,
/// fitted, textured and rendered at each of `yaws` (its pitch, no roll, no lighting change) by the
/// 3D-ASM training's renderer (landmarks: the projected model points moved by the photo's
/// annotation residual), handed to `each` with its yaw.
pub(super) fn for_each_render(
    fm: &facegate_morph::FaceModel,
    test: &[ImmSample],
    yaws: &[f32],
    each: &mut dyn FnMut(f32, &crate::asm3d_synth::SyntheticView),
) -> anyhow::Result<()> {
    use crate::asm3d_synth::{annotation_offsets, background_colour, contour_jaw_vertices, photo_jaw_vertices, synthesise_view};
    for sample in test {
        let photo = facegate_core::imaging::open(&sample.image)?;
        let truth = sample.landmarks()?;
        let Ok(fit) = fm.fit(&truth, photo.width(), photo.height()) else { continue };
        if fit.pose.yaw.abs() >= 10.0 {
            continue;
        }
        let texture = fm.extract_texture(&photo.rgb, &fit, 512);
        let offsets = annotation_offsets(fm, &fit, &truth);
        let jaw = photo_jaw_vertices(fm, &fit, &contour_jaw_vertices(fm));
        let background = background_colour(&photo.rgb);
        for &yaw in yaws {
            let pose = facegate_morph::Pose { yaw, pitch: fit.pose.pitch, roll: 0.0 };
            each(yaw, &synthesise_view(fm, &fit, &texture, pose, background, 0.0, &jaw, &offsets));
        }
    }
    Ok(())
}

/// One |yaw| of the profile renders' pose: the mean |yaw error| (degrees) of each way of posing
/// the head, over the renders the detector found.
#[derive(Debug, Clone, Serialize)]
pub struct ProfilePoseRow {
    pub yaw: f32,
    pub found: usize,
    /// The mean face fitted to the detector's five points (`FaceModel::fit_key_points`).
    pub five_points: f64,
    /// The 3DMM fitted to the profile model's 58 points, every point counted.
    pub landmarks: f64,
    /// The same, the points the five-point pose hides weighted by `HIDDEN_POINT_WEIGHT`.
    pub visible_landmarks: f64,
}

/// The head's yaw on the profile renders (truth: the render's yaw) from the detector's five
/// points, and from the 3DMM fitted to the profile model's points seeded by them (all points, or
/// the shown ones weighted up).
pub fn profile_poses(
    fm: &facegate_morph::FaceModel,
    test: &[ImmSample],
    detector: &Detector,
    profile: &facegate_vision::landmarks::asm3d::Asm3dLandmarker,
    casm: &Landmarker,
) -> anyhow::Result<Vec<ProfilePoseRow>> {
    let bands = bands(&PROFILE_YAWS);
    let mut errors: Vec<Vec<[f64; 3]>> = vec![Vec::new(); bands.len()];
    for_each_render(fm, test, &PROFILE_YAWS, &mut |yaw, view| {
        let band = bands.iter().position(|&b| b == yaw.abs()).expect("a band per yaw");
        let Some(points) = detector.detect(&view.gray).first().and_then(|f| f.points) else { return };
        let (w, h) = (view.gray.width as u32, view.gray.height as u32);
        let Ok(five) = fm.fit_key_points(&points, w, h) else { return };
        let Some(found) = profile.fit_from_detector(&view.gray, &points, &casm.model) else { return };
        let mut weights = [1.0; facegate_core::face::IMM_POINTS];
        for (w, shown) in weights.iter_mut().zip(fm.landmark_visibility(&five)) {
            if !shown {
                *w = facegate_vision::landmarks::asm3d::HIDDEN_POINT_WEIGHT;
            }
        }
        let fit = |point_weights| fm.fit_with(&found.points, w, h, &facegate_morph::FitOptions { point_weights, ..Default::default() });
        let (Ok(all), Ok(shown)) = (fit(None), fit(Some(weights))) else { return };
        let error = |p: facegate_morph::Pose| (p.yaw - yaw).abs() as f64;
        errors[band].push([error(five.pose), error(all.pose), error(shown.pose)]);
    })?;
    Ok(bands
        .iter()
        .zip(errors)
        .map(|(&yaw, e)| {
            let mean = |k: usize| e.iter().map(|x| x[k]).sum::<f64>() / e.len().max(1) as f64;
            ProfilePoseRow { yaw, found: e.len(), five_points: mean(0), landmarks: mean(1), visible_landmarks: mean(2) }
        })
        .collect())
}

/// Prints [`profile_renders`] rows.
pub fn print_profiles(rows: &[ProfileRow], report: &mut dyn Write) -> std::io::Result<()> {
    writeln!(report, "{:>6} {:>8} {:>7} {:>11} {:>8} {:>8}", "|yaw|", "renders", "misses", "mean error", "< 0.1", "< 0.2")?;
    for r in rows {
        writeln!(
            report,
            "{:>6.0} {:>8} {:>7} {:>11.4} {:>7.1}% {:>7.1}%",
            r.yaw,
            r.renders,
            r.detector_misses,
            r.mean_error,
            100.0 * r.error_01,
            100.0 * r.error_02
        )?;
    }
    Ok(())
}
