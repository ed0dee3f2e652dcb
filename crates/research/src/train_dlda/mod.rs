//! Training and measuring DLDA models on labelled folders (`facegate train dlda`, `eval verify`,
//! `eval identify`): the photos ([`faces`]), where their landmarks come from ([`front_end`]: IMM
//! annotations or the service's own stages), their crops on each normalisation path ([`crops`],
//! with 3DMM re-posed copies, through the research cache, and which of them `train dlda` trains
//! on), the scoring protocols ([`protocol`]) and, here, the
//! training itself: projections per path and part, then calibration on the held-out persons of the
//! person-disjoint split.

use std::collections::BTreeMap;

use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::dlda::DldaParams;
use crate::eval::verification::{VerificationSummary, summarize};
use crate::measures::eer;
use facegate_core::imaging::GrayF32;
use facegate_core::template::Template;
use facegate_vision::recognize::Combine;
use facegate_vision::recognize::calibration::{CALIBRATED_FMRS, Calibration, EnrolledCalibration, MAX_CALIBRATED_ENROLLMENT};
use facegate_vision::recognize::dlda::Dlda;
use facegate_vision::recognize::features::{self, FeatureKind, Region};
use facegate_vision::recognize::normalize::{self, NormalizeParams};
use facegate_vision::recognize::{ClassicalModel, ClassicalRecognizer, Cohort, LocalPart, Normalization, Provenance, SecondaryPath};

pub mod crops;
pub mod faces;
pub mod front_end;
pub mod protocol;

pub use crops::*;
pub use faces::*;
pub use front_end::*;
pub use protocol::*;

/// What a training run is made of.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainConfig {
    pub normalization: Normalization,
    pub normalize: NormalizeParams,
    pub features: FeatureKind,
    pub dlda: DldaParams,
    /// Add mirrored copies of the training crops.
    pub mirror: bool,
    /// Randomly perturbed copies of each training crop (shift ±1 px, scale ±4 %, rotation ±3°),
    /// standing in for centre noise.
    pub jitter: usize,
    /// Cohort score normalisation with the training photos' templates as the cohort: `Some(0)`
    /// S-norm over the whole cohort, `Some(k)` AS-norm over each face's k closest; `None`: raw cosines.
    pub cohort_top_k: Option<usize>,
    /// Fuse a second projection trained on this path's crops (`AlignedFace::secondary_crop`).
    pub secondary: Option<Normalization>,
    /// The second path's weight in the fused score.
    pub secondary_weight: f32,
    /// Regions of the crop with a projection of their own, ensembled with the whole face.
    pub local_parts: Vec<Region>,
    /// Total weight of the local parts' cosines (shared equally), the whole face keeping the rest.
    pub local_weight: f32,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            normalization: Normalization::TwoD,
            normalize: NormalizeParams::default(),
            features: FeatureKind::Pixels,
            dlda: DldaParams::default(),
            mirror: true,
            jitter: 0,
            cohort_top_k: None,
            secondary: None,
            secondary_weight: 0.3,
            local_parts: Vec::new(),
            local_weight: 0.5,
        }
    }
}

impl TrainConfig {
    /// The normalisation paths the model is trained on: the primary, then the fused second path.
    pub fn paths(&self) -> Vec<Normalization> {
        std::iter::once(self.normalization).chain(self.secondary).collect()
    }
}

/// Held-out measurements made while training.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutReport {
    /// One template against one template, all pairs of held-out photos.
    pub pairs: VerificationSummary,
    /// Probe against the other photos of each held-out person, combined by max, and by mean.
    pub eer_combine_max: f64,
    pub eer_combine_mean: f64,
    pub combine: Combine,
}

/// A copy of `crop` under a small random similarity about its centre.
fn jittered(crop: &GrayF32, rng: &mut impl Rng) -> GrayF32 {
    let angle = rng.random_range(-3.0f32..3.0).to_radians();
    let scale = rng.random_range(0.96f32..1.04);
    let (dx, dy) = (rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0));
    let (cx, cy) = (0.5 * (crop.width - 1) as f32, 0.5 * (crop.height - 1) as f32);
    let (a, b) = (scale * angle.cos(), scale * angle.sin());
    GrayF32::from_fn(crop.width, crop.height, |x, y| {
        let (u, v) = (x as f32 - cx, y as f32 - cy);
        crop.sample(a * u - b * v + cx + dx, b * u + a * v + cy + dy)
    })
}

/// Train the projection on the training persons of `aligned`, then calibrate thresholds and choose
/// the combination rule on the held-out persons.
pub fn train_model(aligned: &[AlignedFace], config: &TrainConfig, data: &[String]) -> anyhow::Result<(ClassicalModel, HeldOutReport)> {
    let train: Vec<&AlignedFace> = aligned.iter().filter(|a| !a.face.held_out).collect();
    let held: Vec<&AlignedFace> = aligned.iter().filter(|a| a.face.held_out).collect();
    let mut labels: Vec<String> = train.iter().map(|a| a.face.label.clone()).collect();
    labels.sort();
    labels.dedup();
    anyhow::ensure!(
        config.local_parts.is_empty() || (0.0..1.0).contains(&config.local_weight),
        "the local parts' weight must be in [0, 1)"
    );
    let mask = config.normalize.mask();
    let part_indices: Vec<Vec<usize>> =
        config.local_parts.iter().map(|r| config.features.indices_in(config.normalize.width, config.normalize.height, &mask, r)).collect();
    anyhow::ensure!(part_indices.iter().all(|i| !i.is_empty()), "a local region holds no features");
    let (dlda, primary_parts) = project_path(&train, &labels, config, &part_indices, false)?;
    let (secondary, secondary_parts) = match config.secondary {
        Some(normalization) => {
            anyhow::ensure!(normalization != config.normalization, "the second path must differ from the first");
            anyhow::ensure!(held.iter().all(|a| a.secondary_crop.is_some()), "held-out photos without a crop on the second path");
            let (dlda, parts) = project_path(&train, &labels, config, &part_indices, true)?;
            (Some(SecondaryPath { normalization, dlda, weight: config.secondary_weight }), parts)
        }
        None => (None, Vec::new()),
    };
    let part_weight = config.local_weight / config.local_parts.len().max(1) as f32;
    let mut secondary_parts = secondary_parts.into_iter();
    let parts: Vec<LocalPart> = config
        .local_parts
        .iter()
        .zip(primary_parts)
        .map(|(&region, primary)| LocalPart {
            region,
            weight: part_weight,
            projections: std::iter::once(primary).chain(secondary_parts.next()).collect(),
        })
        .collect();
    let provenance = provenance(aligned, &train, &held, labels, config, data);
    let mut model = ClassicalModel::new(config.normalization, config.normalize.clone(), config.features, dlda, provenance);
    model.secondary = secondary;
    model.parts = parts;
    if let Some(top_k) = config.cohort_top_k {
        // The cohort: one template per training photo (not the mirrored copies), never a held-out person.
        let raw = ClassicalRecognizer::from_model(model.clone());
        let vectors: Vec<Vec<f32>> = train.iter().map(|a| template_of(&raw, a).map(|t| t.vector)).collect::<Result<_, _>>()?;
        model.cohort = Some(Cohort::new(model.template_dims(), &vectors, top_k));
    }
    let report = calibrate(&mut model, &held)?;
    Ok((model, report))
}

/// One path's projections, the whole face's then each local part's (on the same samples), trained
/// on the training faces' crops on that path (`second`: the second path's, else the primary's),
/// their re-posed copies, mirrored copies and jittered copies, each labelled by its person.
fn project_path(
    train: &[&AlignedFace],
    labels: &[String],
    config: &TrainConfig,
    part_indices: &[Vec<usize>],
    second: bool,
) -> anyhow::Result<(Dlda, Vec<Dlda>)> {
    let mask = config.normalize.mask();
    let features_of = |crop: &GrayF32| {
        let mut c = crop.clone();
        normalize::photometric(&mut c, config.normalize.photometric, &mask);
        config.features.extract(&c, &mask)
    };
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2011);
    for a in train {
        let y = labels.binary_search(&a.face.label).expect("label listed");
        let crop = if second { a.secondary_crop.as_ref() } else { Some(&a.crop) };
        let crop = crop.ok_or_else(|| anyhow::anyhow!("{}: no crop on the second path", a.face.image.display()))?;
        let copies = a.reposed.iter().filter_map(|(first, other)| if second { other.as_ref() } else { Some(first) });
        let mut crops: Vec<GrayF32> = std::iter::once(crop).chain(copies).cloned().collect();
        if config.mirror {
            crops.extend(crops.iter().map(normalize::mirror).collect::<Vec<_>>());
        }
        for base in crops {
            for _ in 0..config.jitter {
                xs.push(features_of(&jittered(&base, &mut rng)));
                ys.push(y);
            }
            xs.push(features_of(&base));
            ys.push(y);
        }
    }
    let whole = crate::dlda::train(&xs, &ys, &config.dlda)?;
    let parts = part_indices
        .iter()
        .map(|indices| {
            let local: Vec<Vec<f32>> = xs.iter().map(|x| features::gather(x, indices)).collect();
            crate::dlda::train(&local, &ys, &config.dlda)
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((whole, parts))
}

/// Where the model's training and calibration photos came from.
fn provenance(
    aligned: &[AlignedFace],
    train: &[&AlignedFace],
    held: &[&AlignedFace],
    labels: Vec<String>,
    config: &TrainConfig,
    data: &[String],
) -> Provenance {
    let mut held_persons: Vec<String> = held.iter().map(|a| a.face.label.clone()).collect();
    held_persons.sort();
    held_persons.dedup();
    let mut sources: BTreeMap<&str, usize> = BTreeMap::new();
    for a in aligned {
        *sources.entry(a.centre_source).or_default() += 1;
    }
    let centre_source = sources.iter().map(|(s, n)| format!("{s} ({n} photos)")).collect::<Vec<_>>().join(", ");
    Provenance {
        centre_source,
        data: data.to_vec(),
        train_persons: labels,
        train_images: train.len(),
        calibration_persons: held_persons,
        calibration_images: held.len(),
        mirrored: config.mirror,
    }
}

/// Calibrates `model` on the held-out faces: the one-photo threshold table from all their pairs,
/// the template rule (max or mean, whichever has the lower EER), and a table per enrolment size
/// (a subject enrolled with k photos scores the best, or mean, of k comparisons).
fn calibrate(model: &mut ClassicalModel, held: &[&AlignedFace]) -> anyhow::Result<HeldOutReport> {
    let recognizer = ClassicalRecognizer::from_model(model.clone());
    let templates: Vec<(String, Template)> = held
        .iter()
        .map(|a| Ok((a.face.label.clone(), template_of(&recognizer, a)?)))
        .collect::<Result<_, facegate_vision::recognize::RecognizeError>>()?;
    let (genuine, impostor) = pair_scores(&recognizer, &templates);
    anyhow::ensure!(
        !genuine.is_empty() && !impostor.is_empty(),
        "the held-out persons give no genuine or no impostor pairs to calibrate on"
    );
    let centre_source = model.provenance.centre_source.clone();
    let held_persons = model.provenance.calibration_persons.len();
    model.calibration = Calibration::from_scores(
        &genuine,
        &impostor,
        &CALIBRATED_FMRS,
        &format!("all pairs of {} photos of {held_persons} held-out persons; keypoints: {centre_source}", held.len()),
    );
    let (gm, im) = combined_scores(&recognizer, &templates, Combine::Max);
    let (ga, ia) = combined_scores(&recognizer, &templates, Combine::Mean);
    let (eer_max, eer_mean) = (eer(&gm, &im), eer(&ga, &ia));
    model.combine = if eer_mean < eer_max { Combine::Mean } else { Combine::Max };
    let combine = model.combine;
    model.enrolled_calibration = (2..=MAX_CALIBRATED_ENROLLMENT)
        .filter_map(|k| {
            let (genuine, impostor) = enrollment_scores(&recognizer, &templates, k, combine);
            (!genuine.is_empty() && !impostor.is_empty()).then(|| EnrolledCalibration {
                enrolled: k,
                calibration: Calibration::from_scores(
                    &genuine,
                    &impostor,
                    &CALIBRATED_FMRS,
                    &format!(
                        "probes against {k} enrolled photos ({combine:?}), every rotation of each held-out person's photos; keypoints: {centre_source}"
                    ),
                ),
            })
        })
        .collect();
    Ok(HeldOutReport { pairs: summarize(&genuine, &impostor), eer_combine_max: eer_max, eer_combine_mean: eer_mean, combine })
}

/// Cross-validation on the training persons only, for choosing parameters without looking at the
/// held-out persons: the training persons are dealt into `folds` groups (by sorted label), each group
/// in turn plays the held-out role. Returns the all-pairs summary of each fold.
pub fn cross_validate(aligned: &[AlignedFace], config: &TrainConfig, folds: usize) -> anyhow::Result<Vec<VerificationSummary>> {
    let train: Vec<&AlignedFace> = aligned.iter().filter(|a| !a.face.held_out).collect();
    let mut labels: Vec<&str> = train.iter().map(|a| a.face.label.as_str()).collect();
    labels.sort();
    labels.dedup();
    let folds = folds.clamp(2, labels.len().max(2));
    let mut eers = Vec::with_capacity(folds);
    for k in 0..folds {
        let fold: Vec<AlignedFace> = train
            .iter()
            .map(|a| {
                let index = labels.binary_search(&a.face.label.as_str()).expect("label listed");
                let mut a = (*a).clone();
                a.face.held_out = index % folds == k;
                a
            })
            .collect();
        let (_, report) = train_model(&fold, config, &[])?;
        eers.push(report.pairs);
    }
    Ok(eers)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Quiet;
    use facegate_core::face::EyeMouthCentres;
    use facegate_core::imaging;
    use facegate_morph::FaceModel;
    use facegate_vision::recognize::Views;

    #[test]
    fn person_numbers_and_split_follow_the_labels() {
        assert_eq!(person_number("imm-07"), Some(7));
        assert_eq!(person_number("orl-s12"), Some(12));
        assert_eq!(person_number("folder"), None);
        let faces = list_faces(&[facegate_paths::shared_dir().join("data/imm")]).unwrap();
        assert_eq!(faces.len(), 180);
        assert_eq!(faces.iter().filter(|f| f.held_out).count(), 9 * 6);
        assert!(faces.iter().all(|f| f.asf.is_some() && f.view.is_some()));
    }

    /// A re-posed copy is the same face turned by the offset: the 3DMM fitted to the copy's own
    /// landmarks finds the photo's yaw plus the offset, and its crops exist on both paths.
    #[test]
    fn reposed_copies_turn_the_face_by_the_offset() {
        let faces = list_faces(&[facegate_paths::shared_dir().join("data/imm")]).unwrap();
        let face = faces.iter().find(|f| !f.held_out && f.view == Some(1)).unwrap().clone();
        let front = FrontEnd { face_model: Some(FaceModel::load(&facegate_paths::sfm_dir()).unwrap()), ..FrontEnd::annotations_only() };
        let model = front.face_model.as_ref().unwrap();
        let photo = imaging::open(&face.image).unwrap();
        let (landmarks, _) = front.landmarks(&face, &photo).unwrap();
        let yaw0 = model.fit(&landmarks.points, photo.width(), photo.height()).unwrap().pose.yaw;
        let views = front.reposed_views(&face, &[(20.0, 0.0), (-20.0, 0.0)]).unwrap();
        assert_eq!(views.len(), 2);
        for ((view, marks), offset) in views.iter().zip([20.0f32, -20.0]) {
            assert_eq!((view.width(), view.height()), (photo.width(), photo.height()));
            let yaw = model.fit(&marks.points, view.width(), view.height()).unwrap().pose.yaw;
            assert!((yaw - (yaw0 + offset)).abs() < 6.0, "fitted yaw {yaw}, photo {yaw0}, offset {offset}");
        }
        let params = NormalizeParams::default();
        let mut aligned = align_all(&front, &[face], Normalization::TwoD, &params, &Quiet);
        let paths = [Normalization::TwoD, Normalization::Morph];
        attach_reposed_crops(None, &front, &mut aligned, &paths, &params, &[(20.0, 0.0)], &Quiet).unwrap();
        assert_eq!(aligned[0].reposed.len(), 1);
        let (first, second) = &aligned[0].reposed[0];
        assert_eq!((first.width, second.as_ref().map(|c| c.width)), (params.width, Some(params.width)));
        // The turned face is not the photo's crop, but close to it.
        let correlation = {
            let (a, b) = (&aligned[0].crop.data, &first.data);
            let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
            let (ma, mb) = (mean(a), mean(b));
            let cov: f32 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
            let var = |v: &[f32], m: f32| v.iter().map(|x| (x - m).powi(2)).sum::<f32>();
            cov / (var(a, ma) * var(b, mb)).sqrt()
        };
        assert!((0.5..0.995).contains(&correlation), "correlation with the photo's crop {correlation}");
    }

    /// The enrolment protocol: k = 1 is every all-pairs score twice; with k = 2 each probe gets
    /// the best of its person's two enrolled photos, and a person with no more photos than k
    /// enrols no set (but still probes the others' sets as an impostor).
    #[test]
    fn enrollment_sets_score_the_best_enrolled_photo() {
        let dlda = Dlda { input_dims: 1, dims: 1, mean: vec![0.0], projection: vec![1.0], within_eigenvalues: vec![1.0] };
        let recognizer = ClassicalRecognizer::from_model(ClassicalModel::new(
            Normalization::TwoD,
            NormalizeParams::default(),
            facegate_vision::recognize::FeatureKind::Pixels,
            dlda,
            Default::default(),
        ));
        let at = |label: &str, degrees: f32| {
            let r = degrees.to_radians();
            (label.to_string(), Template::new(recognizer.model_version(), vec![r.cos(), r.sin()]))
        };
        let templates = [at("a", 0.0), at("a", 10.0), at("a", 80.0), at("b", 40.0), at("b", 45.0)];
        let sorted = |mut v: Vec<f32>| {
            v.sort_by(f32::total_cmp);
            v
        };
        let (g1, i1) = enrollment_scores(&recognizer, &templates, 1, Combine::Max);
        let (g, i) = pair_scores(&recognizer, &templates);
        let twice = |v: Vec<f32>| sorted(v.iter().chain(&v).copied().collect());
        assert_eq!((sorted(g1), sorted(i1)), (twice(g), twice(i)));
        let (g2, i2) = enrollment_scores(&recognizer, &templates, 2, Combine::Max);
        let cos = |d: f32| d.to_radians().cos();
        let expected = [cos(70.0), cos(10.0), cos(10.0)];
        assert_eq!(g2.len(), 3);
        for (got, want) in sorted(g2).iter().zip(expected) {
            assert!((got - want).abs() < 1e-6, "{got} against {want}");
        }
        // b's two photos against a's three sets {0°, 10°}, {10°, 80°}, {80°, 0°}.
        let want = sorted(vec![cos(30.0), cos(35.0), cos(30.0), cos(35.0), cos(40.0), cos(35.0)]);
        assert_eq!(i2.len(), 6);
        for (got, want) in sorted(i2).iter().zip(want) {
            assert!((got - want).abs() < 1e-6, "{got} against {want}");
        }
    }

    /// Train on IMM frontal views of the training persons with annotated centres: the projection
    /// of a training photo must be stable (same template twice, and close to its mirrored copy's
    /// class), and held-out genuine pairs must score above impostor pairs on average.
    #[test]
    fn imm_training_gives_a_stable_projection() {
        let faces: Vec<FaceImage> =
            list_faces(&[facegate_paths::shared_dir().join("data/imm")]).unwrap().into_iter().filter(|f| !f.is_rotated_view()).collect();
        let front = FrontEnd::annotations_only();
        let config = TrainConfig::default();
        let aligned = align_all(&front, &faces, Normalization::TwoD, &config.normalize, &Quiet);
        assert_eq!(aligned.len(), faces.len());
        let (model, report) = train_model(&aligned, &config, &["imm".into()]).unwrap();
        let recognizer = ClassicalRecognizer::from_model(model.clone());
        let a = aligned.iter().find(|a| !a.face.held_out).unwrap();
        let t1 = template_of(&recognizer, a).unwrap();
        let prepared = front.prepare(&a.face, Normalization::TwoD).unwrap();
        let t2 = recognizer.template(Views::Single(&recognizer.normalized_crop(&prepared.gray, &prepared.centres))).unwrap();
        assert!(t1.cosine(&t2) > 0.9999, "same photo, same template");
        // A small shift of the centres (half a crop pixel) barely moves the template.
        let k = prepared.centres;
        let shift = |p: facegate_core::geometry::Point| [p[0] + 1.5, p[1] + 1.0];
        let shifted = EyeMouthCentres { left_eye: shift(k.left_eye), right_eye: shift(k.right_eye), mouth: shift(k.mouth) };
        let t3 = recognizer.template(Views::Single(&recognizer.normalized_crop(&prepared.gray, &shifted))).unwrap();
        assert!(t1.cosine(&t3) > 0.8, "shifted keypoints: cosine {}", t1.cosine(&t3));
        // Round trip through the model file keeps the version and the templates.
        let dir = std::env::temp_dir().join(format!("facegate-dlda-test-{}", std::process::id()));
        model.save(&dir.join("dlda.bin")).unwrap();
        let loaded = ClassicalRecognizer::load(&dir).unwrap();
        assert_eq!(loaded.model_version(), recognizer.model_version());
        assert_eq!(template_of(&loaded, a).unwrap(), t1);
        std::fs::remove_dir_all(&dir).ok();
        // Versions are enforced.
        let mut foreign = t1.clone();
        foreign.model_version = "dlda-000000000000".into();
        assert!(recognizer.try_score(&t1, &[foreign.clone()]).is_err());
        assert_eq!(recognizer.score(&t1, &[foreign]), -1.0);
        assert!(recognizer.try_score(&t1, &[t2]).unwrap() > 0.99);
        assert!(report.pairs.eer < 0.25, "held-out EER {}", report.pairs.eer);
        assert_eq!(model.calibration.points.len(), CALIBRATED_FMRS.len());
    }
}
