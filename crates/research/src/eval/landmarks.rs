//! Landmark accuracy on held-out IMM persons (the analogue of the thesis's table 2.1): the three
//! variants side by side, from the detector's box to the searched points, with the Jesorsky
//! d_eye measure and the mouth error (thesis eq. 2.4–2.5), and their cumulative curves.

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::dataset::{self, ImmSample};

use crate::train_asm as train;
use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Rect, distance};
use facegate_core::imaging::GrayF32;
use facegate_detect::Detector;
use facegate_detect::Face;
use facegate_vision::landmarks::{BoxSource, Landmarker, Variant};

use super::plot::{Chart, Scale, Series, cumulative, line_chart};
use super::thread_cpu_ns;
use crate::Progress;

mod crossover;
pub use crossover::{CROSSOVER_YAWS, CrossoverRow, crossover, crossover_yaw, print_crossover};

/// d_eye = max(d_left, d_right) / ||C_l − C_r|| (Jesorsky et al.).
pub fn d_eye(found: &EyeMouthCentres, truth: &EyeMouthCentres) -> f64 {
    let d = distance(found.left_eye, truth.left_eye).max(distance(found.right_eye, truth.right_eye));
    (d / distance(truth.left_eye, truth.right_eye).max(1e-6)) as f64
}

/// Mouth error normalised by the distance from the eyes' midpoint to the mouth (thesis eq. 2.5).
pub fn d_mouth(found: &EyeMouthCentres, truth: &EyeMouthCentres) -> f64 {
    let mid = [0.5 * (truth.left_eye[0] + truth.right_eye[0]), 0.5 * (truth.left_eye[1] + truth.right_eye[1])];
    (distance(found.mouth, truth.mouth) / distance(mid, truth.mouth).max(1e-6)) as f64
}

#[derive(Debug, Clone, Serialize)]
pub struct PhotoError {
    pub person: u32,
    pub view: u32,
    /// `None` when the detector found no face (a failure at every threshold).
    pub d_eye: Option<f64>,
    pub d_mouth: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct VariantSummary {
    pub variant: &'static str,
    pub photos: usize,
    pub detector_misses: usize,
    pub d_eye_005: f64,
    pub d_eye_01: f64,
    pub mouth_01: f64,
    pub mean_d_eye: f64,
    pub ms_per_face: f64,
    pub errors: Vec<PhotoError>,
}

fn share(errors: &[PhotoError], f: impl Fn(&PhotoError) -> Option<f64>, t: f64) -> f64 {
    errors.iter().filter(|e| f(e).is_some_and(|v| v < t)).count() as f64 / errors.len().max(1) as f64
}

/// A face box for a test photo: the detector's largest face (as the pipeline uses it), or the
/// annotation's bounding box when no detector is given.
fn test_box(detector: Option<&Detector>, gray: &facegate_core::imaging::GrayF32, truth: &[facegate_core::geometry::Point]) -> Option<Rect> {
    match detector {
        Some(d) => d.detect(gray).first().map(facegate_vision::pipeline::seed_box),
        None => Some(train::annotation_box(truth)),
    }
}

/// Measure one variant on `test` photos (boxes precomputed).
pub fn measure(
    landmarker: &Landmarker,
    photos: &[(ImmSample, facegate_core::imaging::GrayF32, Vec<facegate_core::geometry::Point>, Option<Rect>)],
    variant: Variant,
) -> VariantSummary {
    measure_fn(photos, variant.name(), &|gray, rect| landmarker.fit(gray, rect, variant).centres)
}

type TestPhoto = (ImmSample, facegate_core::imaging::GrayF32, Vec<facegate_core::geometry::Point>, Option<Rect>);

/// Load test photos, halved `halvings` times (2×2 means, the pyramid's convention: a point `p` goes
/// to `(p − ½)/2`), with the annotation moved alike and the box of the smaller photo.
fn load_test_photos(test: &[ImmSample], detector: Option<&Detector>, halvings: usize) -> anyhow::Result<Vec<TestPhoto>> {
    let mut photos = Vec::new();
    for s in test {
        let mut gray = facegate_core::imaging::open(&s.image)?.gray;
        let mut truth = s.landmarks()?;
        for _ in 0..halvings {
            gray = gray.downsample_half();
            truth.iter_mut().for_each(|p| *p = [(p[0] - 0.5) * 0.5, (p[1] - 0.5) * 0.5]);
        }
        let rect = test_box(detector, &gray, &truth);
        photos.push((s.clone(), gray, truth, rect));
    }
    Ok(photos)
}

/// Person-disjoint k-fold cross-validation: the IMM persons (in order) are dealt into `folds`
/// folds; each fold is measured by a model trained on the others, so every photo is measured by a
/// model that never saw its person. Prints the table over all photos and writes
/// `summary-folds{folds}[-halvings{h}].json` into `out`.
pub fn run_folds(
    imm: &Path,
    detector: Option<&Detector>,
    out: &Path,
    folds: usize,
    halvings: usize,
    progress: &dyn Progress,
    report: &mut dyn Write,
) -> anyhow::Result<Vec<VariantSummary>> {
    let all = dataset::list_imm(imm)?;
    let mut persons: Vec<u32> = all.iter().map(|s| s.person).collect();
    persons.sort_unstable();
    persons.dedup();
    anyhow::ensure!(persons.len() >= folds, "{} persons cannot fill {folds} folds", persons.len());
    let fold_of = |person: u32| persons.iter().position(|&p| p == person).unwrap_or(0) % folds;
    let mut errors: Vec<Vec<PhotoError>> = vec![Vec::new(); Variant::ALL.len()];
    let mut cpu_ms = vec![0.0f64; Variant::ALL.len()];
    for fold in 0..folds {
        let (test, training): (Vec<ImmSample>, Vec<ImmSample>) = all.iter().cloned().partition(|s| fold_of(s.person) == fold);
        progress.begin(training.len() as u64, "train asm");
        let model = train::train(&training, detector, &train::TrainOptions::default(), &|| progress.step())?;
        progress.end();
        let landmarker = Landmarker { model };
        let photos = load_test_photos(&test, detector, halvings)?;
        for (k, &v) in Variant::ALL.iter().enumerate() {
            let s = measure(&landmarker, &photos, v);
            cpu_ms[k] += s.ms_per_face * (s.photos - s.detector_misses) as f64;
            errors[k].extend(s.errors);
        }
    }
    let summaries: Vec<VariantSummary> = Variant::ALL
        .iter()
        .zip(errors)
        .zip(cpu_ms)
        .map(|((v, errors), ms)| {
            let fitted = errors.iter().filter(|e| e.d_eye.is_some()).count();
            summarise(v.name(), errors, ms / fitted.max(1) as f64)
        })
        .collect();
    writeln!(
        report,
        "IMM person-disjoint {folds}-fold cross-validation over {} persons: {} photos, each measured by a model not trained on its person{}",
        persons.len(),
        all.len(),
        if halvings > 0 { format!(", test photos halved {halvings}×") } else { String::new() }
    )?;
    print_table(&summaries, report)?;
    std::fs::create_dir_all(out)?;
    let name = if halvings > 0 { format!("summary-folds{folds}-halvings{halvings}.json") } else { format!("summary-folds{folds}.json") };
    let summary = serde_json::json!({ "folds": folds, "halvings": halvings, "photos": all.len(), "variants": summaries });
    std::fs::write(out.join(&name), serde_json::to_string_pretty(&summary)?)?;
    writeln!(report, "wrote {}", out.join(name).display())?;
    Ok(summaries)
}

fn print_table(summaries: &[VariantSummary], report: &mut dyn Write) -> std::io::Result<()> {
    writeln!(
        report,
        "{:<8} {:>12} {:>12} {:>14} {:>12} {:>9} {:>12}",
        "variant", "d_eye<0.05", "d_eye<0.1", "mouth<0.1", "mean d_eye", "misses", "cpu ms/face"
    )?;
    for s in summaries {
        writeln!(
            report,
            "{:<8} {:>11.1}% {:>11.1}% {:>13.1}% {:>12.4} {:>9} {:>12.2}",
            s.variant,
            100.0 * s.d_eye_005,
            100.0 * s.d_eye_01,
            100.0 * s.mouth_01,
            s.mean_d_eye,
            s.detector_misses,
            s.ms_per_face
        )?;
    }
    Ok(())
}

/// Train on the training persons, measure the three variants (and the 3D-ASM with the Surrey Face
/// Model in `sfm`) on the held-out persons, their test photos halved `halvings` times, print the
/// table, write `summary.json`, `landmarks-d_eye.svg` and `landmarks-mouth.svg` into `out`.
pub fn run_scaled(
    imm: &Path,
    sfm: &Path,
    detector: Option<&Detector>,
    out: &Path,
    halvings: usize,
    progress: &dyn Progress,
    report: &mut dyn Write,
) -> anyhow::Result<Vec<VariantSummary>> {
    let all = dataset::list_imm(imm)?;
    let (test, training): (Vec<ImmSample>, Vec<ImmSample>) = all.into_iter().partition(|s| dataset::imm_is_test_person(s.person));
    anyhow::ensure!(!test.is_empty() && !training.is_empty(), "need both training and held-out persons in {}", imm.display());
    progress.begin(training.len() as u64, "train asm");
    let model = train::train(&training, detector, &train::TrainOptions::default(), &|| progress.step())?;
    progress.end();
    let box_source = model.info.box_source;
    let landmarker = Landmarker { model };
    let photos = load_test_photos(&test, detector, halvings)?;
    if halvings > 0 {
        writeln!(report, "test photos halved {halvings}× before detection and search")?;
    }
    let mut summaries: Vec<VariantSummary> = Variant::ALL.iter().map(|&v| measure(&landmarker, &photos, v)).collect();
    // The 3D-ASM beside them, and the head yaw of each photo for the per-view table.
    let (yaws, crossover_rows, profile_rows, pose_rows) =
        match measure_asm3d(sfm, &training, if halvings == 0 { &test } else { &[] }, detector, &photos, &landmarker, progress) {
            Some(m) => {
                summaries.push(m.asm3d);
                summaries.push(m.switch);
                (m.yaws, m.crossover, m.profiles, m.poses)
            }
            None => (vec![f32::NAN; photos.len()], Vec::new(), Vec::new(), Vec::new()),
        };

    let boxes = match (detector, box_source) {
        (Some(_), BoxSource::Detector) => "detector boxes",
        (Some(_), BoxSource::Annotation) => "detector boxes (placement learnt from annotation boxes)",
        (None, _) => "ANNOTATION boxes (no detector available)",
    };
    writeln!(
        report,
        "IMM held-out persons {:?}: {} photos, {} training photos, {boxes}",
        {
            let mut p: Vec<u32> = test.iter().map(|s| s.person).collect();
            p.dedup();
            p
        },
        test.len(),
        training.len()
    )?;
    print_table(&summaries, report)?;

    let per_view = per_view_tables(&summaries, &yaws, report)?;
    print_render_tables(&crossover_rows, &profile_rows, &pose_rows, report)?;

    std::fs::create_dir_all(out)?;
    write_charts(&summaries, out)?;
    let summary = serde_json::json!({ "boxes": boxes, "test_photos": test.len(), "training_photos": training.len(), "variants": summaries, "per_view": per_view, "yaw_of_annotation": yaws, "crossover": crossover_rows.iter().map(|(name, rows)| serde_json::json!({ "search": name, "rows": rows, "crossover_yaw": crossover_yaw(rows) })).collect::<Vec<_>>(), "profile_renders": profile_rows.iter().map(|(name, rows)| serde_json::json!({ "search": name, "rows": rows })).collect::<Vec<_>>(), "profile_poses": pose_rows });
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    writeln!(report, "wrote {}", out.display())?;
    Ok(summaries)
}

/// The tables of the renders of held-out faces: the crossover per search, the searches to full
/// profile and the pose on the same renders.
fn print_render_tables(
    crossover_rows: &[(&'static str, Vec<CrossoverRow>)],
    profile_rows: &[(&'static str, Vec<super::profile::ProfileRow>)],
    pose_rows: &[super::profile::ProfilePoseRow],
    report: &mut dyn Write,
) -> std::io::Result<()> {
    for (name, rows) in crossover_rows {
        writeln!(report, "{name}:")?;
        print_crossover(rows, report)?;
    }
    writeln!(report, "renders of held-out faces to full profile, error of the shown points / eyes-to-mouth distance:")?;
    for (name, rows) in profile_rows {
        writeln!(report, "{name}:")?;
        super::profile::print_profiles(rows, report)?;
    }
    if !pose_rows.is_empty() {
        writeln!(report, "pose on the same renders, mean |yaw error| (degrees):")?;
        writeln!(report, "{:>6} {:>6} {:>12} {:>14} {:>22}", "|yaw|", "found", "five points", "3DMM to all 58", "3DMM, hidden weighted")?;
        for r in pose_rows {
            writeln!(report, "{:>6.0} {:>6} {:>12.1} {:>14.1} {:>22.1}", r.yaw, r.found, r.five_points, r.landmarks, r.visible_landmarks)?;
        }
    }
    Ok(())
}

/// The cumulative curves of every variant's eye and mouth errors: `landmarks-d_eye.svg` and
/// `landmarks-mouth.svg` in `out`.
fn write_charts(summaries: &[VariantSummary], out: &Path) -> anyhow::Result<()> {
    let curves = |f: &dyn Fn(&PhotoError) -> Option<f64>| -> Vec<Series> {
        summaries
            .iter()
            .map(|s| {
                // Misses count as failures: an error beyond the plotted range.
                let errs: Vec<f64> = s.errors.iter().map(|e| f(e).unwrap_or(f64::INFINITY)).collect();
                Series {
                    name: match s.variant {
                        "asm" => "ASM (profiles)",
                        "sift" => "SIFT-ASM",
                        "asm3d" => "3D-ASM",
                        "switch" => "service: C-ASM or 3D-ASM by yaw",
                        _ => "C-ASM",
                    },
                    points: cumulative(&errs, 0.25, 100),
                }
            })
            .collect()
    };
    let chart = |title, x_label| Chart {
        title,
        x_label,
        y_label: "share of photos",
        x_range: (0.0, 0.25),
        y_range: (0.0, 1.0),
        x_scale: Scale::Linear,
        y_scale: Scale::Linear,
    };
    line_chart(
        &out.join("landmarks-d_eye.svg"),
        &chart("IMM held-out persons: eye error", "d_eye (max eye error / eye distance)"),
        &curves(&|e| e.d_eye),
    )?;
    line_chart(
        &out.join("landmarks-mouth.svg"),
        &chart("IMM held-out persons: mouth error", "mouth error / eyes-to-mouth distance"),
        &curves(&|e| e.d_mouth),
    )?;
    Ok(())
}

/// Measure any landmark search (as [`measure`]) under the name `variant`.
pub fn measure_fn(
    photos: &[(ImmSample, facegate_core::imaging::GrayF32, Vec<facegate_core::geometry::Point>, Option<Rect>)],
    variant: &'static str,
    fit: &dyn Fn(&facegate_core::imaging::GrayF32, &Rect) -> EyeMouthCentres,
) -> VariantSummary {
    let mut errors = Vec::new();
    let (mut total_ms, mut fitted) = (0.0, 0usize);
    for (sample, gray, truth, rect) in photos {
        let truth_k = EyeMouthCentres::from_imm(truth);
        let (de, dm) = match rect {
            Some(r) => {
                let (t, c) = (Instant::now(), thread_cpu_ns());
                let found = fit(gray, r);
                total_ms += match (c, thread_cpu_ns()) {
                    (Some(a), Some(b)) => (b - a) as f64 * 1e-6,
                    _ => t.elapsed().as_secs_f64() * 1e3,
                };
                fitted += 1;
                (Some(d_eye(&found, &truth_k)), Some(d_mouth(&found, &truth_k)))
            }
            None => (None, None),
        };
        errors.push(PhotoError { person: sample.person, view: sample.view, d_eye: de, d_mouth: dm });
    }
    summarise(variant, errors, total_ms / fitted.max(1) as f64)
}

fn summarise(variant: &'static str, errors: Vec<PhotoError>, ms_per_face: f64) -> VariantSummary {
    let found: Vec<f64> = errors.iter().filter_map(|e| e.d_eye).collect();
    VariantSummary {
        variant,
        photos: errors.len(),
        detector_misses: errors.iter().filter(|e| e.d_eye.is_none()).count(),
        d_eye_005: share(&errors, |e| e.d_eye, 0.05),
        d_eye_01: share(&errors, |e| e.d_eye, 0.1),
        mouth_01: share(&errors, |e| e.d_mouth, 0.1),
        mean_d_eye: found.iter().sum::<f64>() / found.len().max(1) as f64,
        ms_per_face,
        errors,
    }
}

/// A landmark search under measurement: photo and face box in, eye and mouth centres out.
pub type CentreSearch<'a> = &'a dyn Fn(&facegate_core::imaging::GrayF32, &Rect) -> EyeMouthCentres;

/// What [`measure_asm3d`] measured.
struct Asm3dMeasurements {
    /// The 3D-ASM refined by the C-ASM.
    asm3d: VariantSummary,
    /// The service's switch between C-ASM and 3D-ASM.
    switch: VariantSummary,
    /// Head yaw of each test photo (3DMM fitted to its manual landmarks).
    yaws: Vec<f32>,
    /// Crossover rows per search.
    crossover: Vec<(&'static str, Vec<CrossoverRow>)>,
    /// Profile-render rows per search.
    profiles: Vec<(&'static str, Vec<super::profile::ProfileRow>)>,
    /// The pose on the profile renders.
    poses: Vec<super::profile::ProfilePoseRow>,
}

/// The 3D-ASM beside the 2D variants: trained on the same training persons (needs the Surrey Face
/// Model; skipped with a message without it), refined by `casm`, measured on the same photos and
/// boxes, alone and as the service switches to it (`asm3d::Asm3dLandmarker::switch` at
/// `asm3d::SERVICE_MIN_YAW`); with a detector, both also against C-ASM on turned renders of the
/// `test` persons ([`crossover`]).
fn measure_asm3d(
    sfm: &Path,
    training: &[ImmSample],
    test: &[ImmSample],
    detector: Option<&Detector>,
    photos: &[(ImmSample, facegate_core::imaging::GrayF32, Vec<facegate_core::geometry::Point>, Option<Rect>)],
    casm: &Landmarker,
    progress: &dyn Progress,
) -> Option<Asm3dMeasurements> {
    use facegate_vision::landmarks::asm3d;
    let fm = match facegate_morph::FaceModel::load(sfm) {
        Ok(m) => m,
        Err(e) => {
            progress.note(&format!("facegate: 3D-ASM not measured: {e}"));
            return None;
        }
    };
    progress.begin(training.len() as u64, "train asm3d");
    let model =
        match crate::train_asm3d::train(training, &fm, detector, &crate::train_asm3d::Asm3dTrainOptions::default(), &|| progress.step()) {
            Ok(m) => m,
            Err(e) => {
                progress.note(&format!("facegate: 3D-ASM not measured: {e}"));
                return None;
            }
        };
    progress.end();
    let lm = asm3d::Asm3dLandmarker::new(model);
    let fit = |g: &facegate_core::imaging::GrayF32, r: &Rect| lm.fit_with(g, r, asm3d::Refinement::Casm(&casm.model)).centres;
    let summary = measure_fn(photos, "asm3d", &fit);
    let switch_points = |g: &facegate_core::imaging::GrayF32, r: &Rect| {
        lm.switch(g, r, casm, casm.fit(g, r, Variant::Casm), asm3d::SERVICE_MIN_YAW).0.points
    };
    let switch = |g: &facegate_core::imaging::GrayF32, r: &Rect| EyeMouthCentres::from_imm(&switch_points(g, r));
    let switch_summary = measure_fn(photos, "switch", &switch);
    // The head yaw of every test photo, from the 3DMM fitted to its manual landmarks.
    let yaws =
        photos.iter().map(|(_, g, truth, _)| fm.fit(truth, g.width as u32, g.height as u32).map_or(f32::NAN, |f| f.pose.yaw)).collect();
    let mut rows = Vec::new();
    let mut profiles = Vec::new();
    let mut poses = Vec::new();
    if let Some(det) = detector.filter(|_| !test.is_empty()) {
        let searches: [(&'static str, CentreSearch); 2] = [("3D-ASM (refined by C-ASM)", &fit), ("service switch", &switch)];
        for (name, search) in searches {
            match crossover(&fm, test, det, casm, search) {
                Ok(r) => rows.push((name, r)),
                Err(e) => progress.note(&format!("facegate: crossover not measured: {e}")),
            }
        }
        // Up to full profile: the C-ASM switched by its own points (the service up to the
        // detector seed) against the 3D-ASM seeded by the detector's five points, and the
        // service's choice between them.
        // The profile model, trained on the same persons.
        progress.begin(training.len() as u64, "train asm3d --profile");
        let options = crate::train_asm3d::Asm3dTrainOptions::profile();
        let profile = match crate::train_asm3d::train_profile(training, &fm, detector, &options, &|| progress.step()) {
            Ok(p) => asm3d::Asm3dLandmarker::from_profile(p),
            Err(e) => {
                progress.note(&format!("facegate: profile renders not measured: {e}"));
                return Some(Asm3dMeasurements { asm3d: summary, switch: switch_summary, yaws, crossover: rows, profiles, poses });
            }
        };
        progress.end();
        let switched = |g: &GrayF32, f: &Face| switch_points(g, &facegate_vision::pipeline::seed_box(f));
        let seeded = |g: &GrayF32, f: &Face| match &f.points {
            Some(p) => profile.fit_from_detector(g, p, &casm.model).map_or_else(|| switched(g, f), |r| r.points),
            None => switched(g, f),
        };
        let service = |g: &GrayF32, f: &Face| match &f.points {
            Some(p) if profile.detector_yaw(p).is_some_and(|y| y.abs() >= asm3d::DETECTOR_SEED_MIN_YAW) => seeded(g, f),
            _ => switched(g, f),
        };
        let searches: [(&'static str, super::profile::PointSearch); 3] = [
            ("C-ASM switched to the 3D-ASM by its points", &switched),
            ("3D-ASM seeded by the detector's points", &seeded),
            ("service: the detector seed from DETECTOR_SEED_MIN_YAW", &service),
        ];
        match super::profile::profile_renders(&fm, test, det, &profile, &searches) {
            Ok(r) => profiles = r,
            Err(e) => progress.note(&format!("facegate: profile renders not measured: {e}")),
        }
        match super::profile::profile_poses(&fm, test, det, &profile, casm) {
            Ok(r) => poses = r,
            Err(e) => progress.note(&format!("facegate: profile poses not measured: {e}")),
        }
    }
    Some(Asm3dMeasurements { asm3d: summary, switch: switch_summary, yaws, crossover: rows, profiles, poses })
}

/// Per IMM view group (frontal 1–2, turned 3–4, spot light and free 5–6) and per |yaw| band of the
/// 3DMM fitted to the manual landmarks: share with d_eye < 0.1 and mean d_eye of every variant.
fn per_view_tables(summaries: &[VariantSummary], yaws: &[f32], report: &mut dyn Write) -> std::io::Result<serde_json::Value> {
    let groups: [(&str, &dyn Fn(&PhotoError, f32) -> bool); 7] = [
        ("views 1-2 (frontal)", &|e, _| matches!(e.view, 1 | 2)),
        ("views 3-4 (turned)", &|e, _| matches!(e.view, 3 | 4)),
        ("views 5-6 (light, free)", &|e, _| matches!(e.view, 5 | 6)),
        ("|yaw| < 10", &|_, y| y.abs() < 10.0),
        ("|yaw| 10-20", &|_, y| (10.0..20.0).contains(&y.abs())),
        ("|yaw| 20-30", &|_, y| (20.0..30.0).contains(&y.abs())),
        ("|yaw| >= 30", &|_, y| y.abs() >= 30.0),
    ];
    writeln!(
        report,
        "{:<26} {}",
        "group (photos)",
        summaries.iter().map(|s| format!("{:>22}", format!("{} <0.1 / mean", s.variant))).collect::<String>()
    )?;
    let mut rows = Vec::new();
    for (name, member) in groups {
        let mut line = String::new();
        let mut count = 0;
        let mut cells = Vec::new();
        for s in summaries {
            let d: Vec<f64> =
                s.errors.iter().zip(yaws).filter(|(e, y)| member(e, **y)).map(|(e, _)| e.d_eye.unwrap_or(f64::INFINITY)).collect();
            count = d.len();
            let ok = d.iter().filter(|&&v| v < 0.1).count() as f64 / d.len().max(1) as f64;
            let finite: Vec<f64> = d.iter().copied().filter(|v| v.is_finite()).collect();
            let mean = finite.iter().sum::<f64>() / finite.len().max(1) as f64;
            line += &format!("{:>22}", format!("{:.1}% / {:.3}", 100.0 * ok, mean));
            cells.push(serde_json::json!({ "variant": s.variant, "d_eye_01": ok, "mean_d_eye": mean }));
        }
        writeln!(report, "{:<26}{line}", format!("{name} ({count})"))?;
        rows.push(serde_json::json!({ "group": name, "photos": count, "variants": cells }));
    }
    Ok(serde_json::Value::Array(rows))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_measures_follow_the_thesis_definitions() {
        let truth = EyeMouthCentres { left_eye: [0.0, 0.0], right_eye: [100.0, 0.0], mouth: [50.0, 80.0] };
        let found = EyeMouthCentres { left_eye: [3.0, 4.0], right_eye: [100.0, 2.0], mouth: [50.0, 88.0] };
        assert!((d_eye(&found, &truth) - 0.05).abs() < 1e-6);
        assert!((d_mouth(&found, &truth) - 0.1).abs() < 1e-6);
    }
}
