//! Training and measuring DLDA models on labelled folders, behind a front-end abstraction: the eye
//! and mouth centres come either from IMM annotations (`.asf` beside the photo) or from the
//! automatic pipeline (detector + ASM landmarks); the 3DMM path renders the face from the front
//! first. The person-disjoint split decides who trains the projection and who calibrates it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::core::imaging::{self, GrayF32};
use crate::landmarks::Landmarks;
use crate::morph::{FaceModel, Pose};
use crate::pipeline::{FaceFinder, PipelineError, load_face_model, recognition_input};
use crate::recognize::calibration::{CALIBRATED_FMRS, Calibration, EnrolledCalibration, MAX_CALIBRATED_ENROLMENT};
use crate::recognize::dlda::{Dlda, DldaParams};
use crate::recognize::features::{self, FeatureKind, Region};
use crate::recognize::normalize::{self, NormalizeParams};
use crate::recognize::template::{Combine, Template};
use crate::recognize::{Cohort, LocalPart, Model, Normalization, Provenance, Recognizer, SecondaryPath, Views};
use crate::research::Progress;
use crate::research::dataset::{self, IMM_POINTS, KeyPoints};
use crate::research::eval::verification::{VerificationSummary, eer, summarize};

/// One labelled photo with what the split needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceImage {
    pub label: String,
    /// The person is in the held-out set (`dataset::imm_is_test_person` on the label's number).
    pub held_out: bool,
    /// IMM view number (1–6) when the file has an IMM name.
    pub view: Option<u32>,
    pub image: PathBuf,
    /// The IMM annotation beside the photo, if any.
    pub asf: Option<PathBuf>,
}

impl FaceImage {
    /// IMM views 3 and 4 are the heads rotated by about 30°; every other photo counts as frontal or
    /// near-frontal (ORL's pose variation is mild).
    pub fn is_rotated_view(&self) -> bool {
        matches!(self.view, Some(3 | 4))
    }
}

/// The person number at the end of a label (`imm-07` → 7, `orl-s12` → 12).
pub fn person_number(label: &str) -> Option<u32> {
    let tail = label.rsplit('-').next()?;
    let digits: String = tail.chars().rev().take_while(|c| c.is_ascii_digit()).collect::<Vec<_>>().into_iter().rev().collect();
    digits.parse().ok()
}

/// All labelled photos of `dirs` (a folder per person, or IMM names).
pub fn list_faces(dirs: &[PathBuf]) -> Result<Vec<FaceImage>, dataset::DatasetError> {
    let mut out = Vec::new();
    for dir in dirs {
        for item in dataset::list_labelled(dir)? {
            let name = item.image.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            let view = dataset::parse_imm_name(&name).map(|(_, v)| v);
            let asf = Some(item.image.with_extension("asf")).filter(|p| p.exists());
            let held_out = person_number(&item.label).is_some_and(dataset::imm_is_test_person);
            out.push(FaceImage { label: item.label, held_out, view, image: item.image, asf });
        }
    }
    Ok(out)
}

/// Named regions of the normalised crop (eyes at 34 % of its height, 26 % and 73 % of its width,
/// the mouth at 82 % of its height).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FaceRegion {
    /// Both eyes and brows.
    Eyes,
    /// The nose, between and below the eyes.
    Nose,
    /// The mouth and chin.
    Mouth,
    /// Everything above the nose tip (eyes, brows, forehead).
    Upper,
    /// Everything below the eyes (nose, cheeks, mouth).
    Lower,
    /// The central face without the outline (eyes to mouth).
    Inner,
    /// The eye and brow on the image's left.
    LeftEye,
    /// The eye and brow on the image's right.
    RightEye,
    /// The image's left half of the face.
    LeftHalf,
    /// The image's right half of the face.
    RightHalf,
}

impl FaceRegion {
    /// The region of the crop, in fractions of its width and height.
    pub fn region(self) -> Region {
        let r = |x0, y0, x1, y1| Region { x0, y0, x1, y1 };
        match self {
            FaceRegion::Eyes => r(0.0, 0.1, 1.0, 0.52),
            FaceRegion::Nose => r(0.25, 0.3, 0.75, 0.78),
            FaceRegion::Mouth => r(0.12, 0.64, 0.88, 1.0),
            FaceRegion::Upper => r(0.0, 0.0, 1.0, 0.6),
            FaceRegion::Lower => r(0.0, 0.45, 1.0, 1.0),
            FaceRegion::Inner => r(0.15, 0.2, 0.85, 0.95),
            FaceRegion::LeftEye => r(0.0, 0.1, 0.55, 0.55),
            FaceRegion::RightEye => r(0.45, 0.1, 1.0, 0.55),
            FaceRegion::LeftHalf => r(0.0, 0.0, 0.55, 1.0),
            FaceRegion::RightHalf => r(0.45, 0.0, 1.0, 1.0),
        }
    }
}

/// Where the keypoints of a photo come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeypointSource {
    /// IMM `.asf` annotations where present, else the automatic front end (detector + ASM, or
    /// detector-box keypoints while the ASM is not available).
    Annotated,
    /// The automatic front end for every photo.
    Pipeline,
}

#[derive(Debug, thiserror::Error)]
pub enum FrontEndError {
    #[error(transparent)]
    Decode(#[from] imaging::DecodeError),
    #[error(transparent)]
    Dataset(#[from] dataset::DatasetError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("no annotation and no automatic front end loaded")]
    NoKeypoints,
    #[error("the re-posed copies need the Surrey Face Model, which is not loaded")]
    NoFaceModel,
    #[error("the 3DMM cannot be fitted to the landmarks: {0}")]
    Fit(#[from] crate::morph::MorphError),
}

/// A photo ready for normalisation: the grey image (the frontal rendering on the 3DMM path), the
/// eye and mouth centres in it, and the head pose when the 3DMM was fitted.
pub struct Prepared {
    pub gray: GrayF32,
    pub keypoints: KeyPoints,
    pub pose: Option<Pose>,
    /// `imm-annotations` or `pipeline`.
    pub keypoint_source: &'static str,
}

/// Where training and evaluation get a photo's landmarks and its view for the recognizer: the IMM
/// annotations, or the service's own stages ([`FaceFinder`]: detector, C-ASM, 3D-ASM), then the
/// service's [`recognition_input`] (3DMM fit and frontal rendering). Crops are thereby made as the
/// service makes them.
pub struct FrontEnd {
    pub source: KeypointSource,
    /// The service's face finder; `None` when its models cannot be loaded (annotations only).
    pub finder: Option<FaceFinder>,
    pub face_model: Option<FaceModel>,
    /// The folder the finder's models were loaded from (part of the crop-cache key).
    pub models_dir: Option<PathBuf>,
}

impl FrontEnd {
    /// Annotations only (no automatic front end, no 3DMM).
    pub fn annotations_only() -> FrontEnd {
        FrontEnd { source: KeypointSource::Annotated, finder: None, face_model: None, models_dir: None }
    }

    /// The service's face finder from `models_dir` and the 3DMM from `sfm_dir`, each when it loads;
    /// a missing part only matters for the photos that need it.
    pub fn load(source: KeypointSource, models_dir: &Path, sfm_dir: Option<&Path>) -> FrontEnd {
        let finder = FaceFinder::load(models_dir).map_err(|e| tracing::info!("automatic front end unavailable: {e}")).ok();
        let models_dir = finder.as_ref().map(|_| models_dir.to_path_buf());
        FrontEnd { source, finder, face_model: load_face_model(sfm_dir), models_dir }
    }

    /// The 58 landmarks of a photo from the configured source, and which source gave them.
    fn landmarks(&self, face: &FaceImage, photo: &imaging::Photo) -> Result<(Landmarks, &'static str), FrontEndError> {
        if let (KeypointSource::Annotated, Some(asf)) = (self.source, &face.asf) {
            let shape = dataset::read_asf(asf, photo.width() as f32, photo.height() as f32)?;
            if shape.points.len() == IMM_POINTS {
                let points = shape.xy();
                let keypoints = KeyPoints::from_imm(&points);
                return Ok((Landmarks { points, keypoints }, "imm-annotations"));
            }
        }
        let finder = self.finder.as_ref().ok_or(FrontEndError::NoKeypoints)?;
        Ok((finder.locate(&photo.gray)?.landmarks, "pipeline"))
    }

    /// The face of a photo re-posed by the 3DMM: fitted to its landmarks, textured from the photo
    /// and rendered at its fitted pose plus each (yaw, pitch) offset in degrees, on a flat
    /// background of the photo's mean grey, at the photo's scale and place, with the 58 landmarks
    /// of each rendering (moved by the photo's annotation offsets, as the 3D-ASM's synthetic
    /// views are, so that they follow the same convention as the photo's own landmarks).
    pub fn reposed_views(&self, face: &FaceImage, offsets: &[(f32, f32)]) -> Result<Vec<(imaging::Photo, Landmarks)>, FrontEndError> {
        use crate::landmarks::asm3d;
        let photo = imaging::open(&face.image)?;
        let (landmarks, _) = self.landmarks(face, &photo)?;
        let model = self.face_model.as_ref().ok_or(FrontEndError::NoFaceModel)?;
        let fit = model.fit(&landmarks.points, photo.width(), photo.height())?;
        let texture = model.extract_texture(&photo.rgb, &fit, crate::morph::TEXTURE_SIZE);
        let annotation_offsets = asm3d::annotation_offsets(model, &fit, &landmarks.points);
        let jaw = asm3d::photo_jaw_vertices(model, &fit, &asm3d::contour_jaw_vertices(model));
        let grey = (photo.gray.data.iter().sum::<f32>() / photo.gray.data.len().max(1) as f32).clamp(0.0, 255.0) as u8;
        Ok(offsets
            .iter()
            .map(|&(yaw, pitch)| {
                let pose = Pose { yaw: fit.pose.yaw + yaw, pitch: fit.pose.pitch + pitch, roll: fit.pose.roll };
                let view = asm3d::synthesise_view(model, &fit, &texture, pose, [grey; 3], 0.0, &jaw, &annotation_offsets);
                let rgb = image::RgbImage::from_fn(view.gray.width as u32, view.gray.height as u32, |x, y| {
                    image::Rgb([view.gray.get(x as usize, y as usize).clamp(0.0, 255.0) as u8; 3])
                });
                let keypoints = KeyPoints::from_imm(&view.points);
                (imaging::Photo { rgb, gray: view.gray }, Landmarks { points: view.points, keypoints })
            })
            .collect())
    }

    /// The image and keypoints the recognizer normalises, as the service's pipeline makes them.
    pub fn prepare(&self, face: &FaceImage, normalization: Normalization) -> Result<Prepared, FrontEndError> {
        let photo = imaging::open(&face.image)?;
        let (landmarks, keypoint_source) = self.landmarks(face, &photo)?;
        let input = recognition_input(self.face_model.as_ref(), &photo, &landmarks, normalization)?;
        Ok(Prepared { gray: input.gray.into_owned(), keypoints: input.keypoints, pose: input.pose, keypoint_source })
    }
}

/// A photo after geometric normalisation (photometric normalisation is part of the model).
#[derive(Debug, Clone)]
pub struct AlignedFace {
    pub face: FaceImage,
    pub crop: GrayF32,
    /// The crop on the second path of a fused model (see [`align_paths`]).
    pub secondary_crop: Option<GrayF32>,
    pub pose: Option<Pose>,
    pub keypoint_source: &'static str,
    /// 3DMM re-posed copies of the face ([`attach_reposed_crops`]), used as extra training samples of
    /// its person: per copy, the crop on the primary path and on the second path.
    pub reposed: Vec<(GrayF32, Option<GrayF32>)>,
}

/// Geometric crops of all `faces` (photos whose front end fails are reported and left out).
pub fn align_all(
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> Vec<AlignedFace> {
    progress.begin(faces.len() as u64, "aligning");
    let mut out = Vec::with_capacity(faces.len());
    for face in faces {
        match front_end.prepare(face, normalization) {
            Ok(p) => out.push(AlignedFace {
                face: face.clone(),
                crop: normalize::geometric(&p.gray, &p.keypoints, params),
                secondary_crop: None,
                pose: p.pose,
                keypoint_source: p.keypoint_source,
                reposed: Vec::new(),
            }),
            Err(e) => progress.note(&format!("warning: {}: skipped ({e})", face.image.display())),
        }
        progress.step();
    }
    progress.end();
    out
}

/// 16 hex digits of the SHA-256 of what shapes cached crops: `settings` (serialised parameters),
/// the keypoint source, the photos, and the bytes of the landmark models the front end loaded
/// (`asm.bin`, `asm3d.bin` of its models folder).
fn cache_key(settings: &[u8], front_end: &FrontEnd, faces: &[FaceImage]) -> String {
    let source = front_end.source;
    use sha2::{Digest, Sha256};
    let mut hasher = Sha256::new();
    hasher.update(settings);
    hasher.update(format!("{source:?}"));
    for f in faces {
        hasher.update(f.image.display().to_string());
        hasher.update([f.asf.is_some() as u8]);
    }
    for model in ["asm.bin", "asm3d.bin"] {
        if let Some(Ok(bytes)) = front_end.models_dir.as_ref().map(|dir| std::fs::read(dir.join(model))) {
            hasher.update(&bytes);
        }
    }
    hasher.finalize().iter().take(8).map(|b| format!("{b:02x}")).collect()
}

/// The entries of a crop cache file (postcard), or `None` when there is no readable file (a miss:
/// the caller computes them and writes them with [`write_cache_file`]). A file that is there but
/// does not decode is an error rather than a miss, so that a cache written by another format is
/// noticed instead of silently recomputed over.
fn read_cache_file<T: serde::de::DeserializeOwned>(file: &Path) -> anyhow::Result<Option<T>> {
    match std::fs::read(file) {
        Ok(bytes) => Ok(Some(postcard::from_bytes(&bytes)?)),
        Err(_) => Ok(None),
    }
}

/// Writes crop cache `entries` (postcard) to `file`, creating its folder.
fn write_cache_file<T: Serialize>(file: &Path, entries: &T) -> anyhow::Result<()> {
    std::fs::create_dir_all(file.parent().unwrap_or(Path::new(".")))?;
    std::fs::write(file, postcard::to_stdvec(entries)?)?;
    Ok(())
}

/// [`align_all`] through a cache file in `dir`, keyed by the SHA-256 of everything that shapes the
/// crops: the photos, the keypoint source, the normalisation path and parameters, and the bytes of
/// the landmark models (`asm.bin`, `asm3d.bin`). Photos the front end skipped stay skipped.
pub fn align_all_cached(
    dir: &Path,
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    type Entry = (String, usize, usize, Vec<f32>, String);
    let key = cache_key(&postcard::to_stdvec(&(normalization, params))?, front_end, faces);
    let path = dir.join(format!("crops-{key}.bin"));
    let source_name = |s: &str| -> &'static str {
        match s {
            "imm-annotations" => "imm-annotations",
            "pipeline" => "pipeline",
            _ => "detector-box",
        }
    };
    if let Some(entries) = read_cache_file::<Vec<Entry>>(&path)? {
        let by_path: BTreeMap<String, &Entry> = entries.iter().map(|e| (e.0.clone(), e)).collect();
        progress.note(&format!("aligned crops from cache {}", path.display()));
        return Ok(faces
            .iter()
            .filter_map(|f| by_path.get(&f.image.display().to_string()))
            .zip(faces.iter().filter(|f| by_path.contains_key(&f.image.display().to_string())))
            .map(|(e, f)| AlignedFace {
                face: f.clone(),
                crop: GrayF32 { width: e.1, height: e.2, data: e.3.clone() },
                secondary_crop: None,
                pose: None,
                keypoint_source: source_name(&e.4),
                reposed: Vec::new(),
            })
            .collect());
    }
    let aligned = align_all(front_end, faces, normalization, params, progress);
    let entries: Vec<Entry> = aligned
        .iter()
        .map(|a| (a.face.image.display().to_string(), a.crop.width, a.crop.height, a.crop.data.clone(), a.keypoint_source.to_string()))
        .collect();
    write_cache_file(&path, &entries)?;
    Ok(aligned)
}

/// Crops of `faces` on each normalisation path of `paths` (primary first): the primary crop in
/// `crop`, the second path's in `secondary_crop`; photos that fail on any path are left out. With
/// `cache`, each path's crops go through [`align_all_cached`].
pub fn align_paths(
    cache: Option<&Path>,
    front_end: &FrontEnd,
    faces: &[FaceImage],
    paths: &[Normalization],
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    let align = |normalization| match cache {
        Some(dir) => align_all_cached(dir, front_end, faces, normalization, params, progress),
        None => Ok(align_all(front_end, faces, normalization, params, progress)),
    };
    let (&primary, rest) = paths.split_first().ok_or_else(|| anyhow::anyhow!("no normalisation path"))?;
    let mut aligned = align(primary)?;
    if let Some(&second) = rest.first() {
        let mut by_path: BTreeMap<PathBuf, GrayF32> = align(second)?.into_iter().map(|a| (a.face.image, a.crop)).collect();
        aligned.retain_mut(|a| match by_path.remove(&a.face.image) {
            Some(crop) => {
                a.secondary_crop = Some(crop);
                true
            }
            None => false,
        });
    }
    Ok(aligned)
}

/// Crops of 3DMM re-posed copies ([`FrontEnd::reposed_views`]) of the training persons' photos
/// (held-out persons get none) on each path of `paths`, attached to `aligned` (see
/// [`AlignedFace::reposed`]); a copy that fails on a path is left out. With `cache`, the crops are
/// kept in a file keyed like [`align_all_cached`]'s, and the offsets.
pub fn attach_reposed_crops(
    cache: Option<&Path>,
    front_end: &FrontEnd,
    aligned: &mut [AlignedFace],
    paths: &[Normalization],
    params: &NormalizeParams,
    offsets: &[(f32, f32)],
    progress: &dyn Progress,
) -> anyhow::Result<()> {
    type Entry = (String, Vec<(usize, usize, Vec<f32>, Option<Vec<f32>>)>);
    if offsets.is_empty() {
        return Ok(());
    }
    let faces: Vec<FaceImage> = aligned.iter().filter(|a| !a.face.held_out).map(|a| a.face.clone()).collect();
    let key = cache_key(&postcard::to_stdvec(&(paths, params, offsets))?, front_end, &faces);
    let file = cache.map(|dir| dir.join(format!("reposed-{key}.bin")));
    let cached = match &file {
        Some(f) => read_cache_file::<Vec<Entry>>(f)?,
        None => None,
    };
    let entries: Vec<Entry> = match cached {
        Some(entries) => entries,
        None => {
            progress.begin(faces.len() as u64, "re-posing");
            let mut entries = Vec::with_capacity(faces.len());
            for face in &faces {
                let mut copies = Vec::new();
                match front_end.reposed_views(face, offsets) {
                    Ok(views) => {
                        for (photo, landmarks) in views {
                            let crop = |normalization| {
                                recognition_input(front_end.face_model.as_ref(), &photo, &landmarks, normalization)
                                    .ok()
                                    .map(|input| normalize::geometric(&input.gray, &input.keypoints, params))
                            };
                            let (Some(first), second) = (crop(paths[0]), paths.get(1).map(|&p| crop(p))) else { continue };
                            if second.as_ref().is_some_and(|c| c.is_none()) {
                                continue;
                            }
                            copies.push((first.width, first.height, first.data, second.flatten().map(|c| c.data)));
                        }
                    }
                    Err(e) => progress.note(&format!("{}: no re-posed copies ({e})", face.image.display())),
                }
                entries.push((face.image.display().to_string(), copies));
                progress.step();
            }
            progress.end();
            if let Some(f) = &file {
                write_cache_file(f, &entries)?;
            }
            entries
        }
    };
    let by_path: BTreeMap<String, &Entry> = entries.iter().map(|e| (e.0.clone(), e)).collect();
    for a in aligned.iter_mut().filter(|a| !a.face.held_out) {
        if let Some((_, copies)) = by_path.get(&a.face.image.display().to_string()) {
            a.reposed = copies
                .iter()
                .map(|(w, h, first, second)| {
                    let image = |data: &Vec<f32>| GrayF32 { width: *w, height: *h, data: data.clone() };
                    (image(first), second.as_ref().map(image))
                })
                .collect();
        }
    }
    Ok(())
}

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
    /// standing in for keypoint noise.
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

/// Template of an aligned face under a model (photometric normalisation, features, projection; the
/// second path's crop too for a fused model: `RecognizeError::Views` when it is missing).
pub fn template_of(recognizer: &Recognizer, aligned: &AlignedFace) -> Result<Template, crate::recognize::RecognizeError> {
    let params = &recognizer.model().normalize;
    let relit = |c: &GrayF32| {
        let mut crop = c.clone();
        normalize::photometric(&mut crop, params.photometric, &params.mask());
        crop
    };
    let primary = relit(&aligned.crop);
    let secondary = aligned.secondary_crop.as_ref().filter(|_| recognizer.model().secondary.is_some()).map(relit);
    let views = match &secondary {
        Some(secondary) => Views::Fused { primary: &primary, secondary },
        None => Views::Single(&primary),
    };
    recognizer.template(views)
}

/// Genuine and impostor scores of all pairs of templates (one template each), scored as the
/// recognizer scores (cosines, S-normalised when the model has a cohort).
pub fn pair_scores(recognizer: &Recognizer, templates: &[(String, Template)]) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for i in 0..templates.len() {
        for j in i + 1..templates.len() {
            let s = recognizer.pair_score(&templates[i].1, stats[i], &templates[j].1, stats[j]);
            if templates[i].0 == templates[j].0 { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// The indices of each person's templates, in listing order.
fn photos_by_person(templates: &[(String, Template)]) -> BTreeMap<&str, Vec<usize>> {
    let mut by_person: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, (label, _)) in templates.iter().enumerate() {
        by_person.entry(label).or_default().push(i);
    }
    by_person
}

/// Genuine and impostor scores of each template against every person's other templates, combined.
pub fn combined_scores(recognizer: &Recognizer, templates: &[(String, Template)], combine: Combine) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let by_person = photos_by_person(templates);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (p, (label, probe)) in templates.iter().enumerate() {
        for (person, idx) in &by_person {
            let Some(s) =
                combine.apply(idx.iter().filter(|&&i| i != p).map(|&i| recognizer.pair_score(probe, stats[p], &templates[i].1, stats[i])))
            else {
                continue;
            };
            if *person == label.as_str() { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// Genuine and impostor scores of the service's protocol with `k` photos enrolled per person:
/// each person's photos (in listing order) give one enrolment set per rotation (photos r … r+k−1,
/// cyclically); the person's other photos are its genuine probes, every other person's photos its
/// impostor probes, each scored against the set combined by `combine`. `k` = 1 gives each all-pairs
/// score twice. Persons with no more than `k` photos are left out.
pub fn enrolment_scores(recognizer: &Recognizer, templates: &[(String, Template)], k: usize, combine: Combine) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let by_person = photos_by_person(templates);
    let k = k.max(1);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (person, photos) in by_person.iter().filter(|(_, photos)| photos.len() > k) {
        for r in 0..photos.len() {
            let enrolled: Vec<usize> = (0..k).map(|j| photos[(r + j) % photos.len()]).collect();
            for (p, (label, probe)) in templates.iter().enumerate().filter(|(p, _)| !enrolled.contains(p)) {
                let scores = enrolled.iter().map(|&e| recognizer.pair_score(probe, stats[p], &templates[e].1, stats[e]));
                let s = combine.apply(scores).expect("an enrolment set is never empty");
                if label.as_str() == *person { genuine.push(s) } else { impostor.push(s) }
            }
        }
    }
    (genuine, impostor)
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
pub fn train_model(aligned: &[AlignedFace], config: &TrainConfig, data: &[String]) -> anyhow::Result<(Model, HeldOutReport)> {
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
    let mut model = Model::new(config.normalization, config.normalize.clone(), config.features, dlda, provenance);
    model.secondary = secondary;
    model.parts = parts;
    if let Some(top_k) = config.cohort_top_k {
        // The cohort: one template per training photo (not the mirrored copies), never a held-out person.
        let raw = Recognizer::from_model(model.clone());
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
    let whole = Dlda::train(&xs, &ys, &config.dlda)?;
    let parts = part_indices
        .iter()
        .map(|indices| {
            let local: Vec<Vec<f32>> = xs.iter().map(|x| features::gather(x, indices)).collect();
            Dlda::train(&local, &ys, &config.dlda)
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
        *sources.entry(a.keypoint_source).or_default() += 1;
    }
    let keypoint_source = sources.iter().map(|(s, n)| format!("{s} ({n} photos)")).collect::<Vec<_>>().join(", ");
    Provenance {
        keypoint_source,
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
fn calibrate(model: &mut Model, held: &[&AlignedFace]) -> anyhow::Result<HeldOutReport> {
    let recognizer = Recognizer::from_model(model.clone());
    let templates: Vec<(String, Template)> = held
        .iter()
        .map(|a| Ok((a.face.label.clone(), template_of(&recognizer, a)?)))
        .collect::<Result<_, crate::recognize::RecognizeError>>()?;
    let (genuine, impostor) = pair_scores(&recognizer, &templates);
    anyhow::ensure!(
        !genuine.is_empty() && !impostor.is_empty(),
        "the held-out persons give no genuine or no impostor pairs to calibrate on"
    );
    let keypoint_source = model.provenance.keypoint_source.clone();
    let held_persons = model.provenance.calibration_persons.len();
    model.calibration = Calibration::from_scores(
        &genuine,
        &impostor,
        &CALIBRATED_FMRS,
        &format!("all pairs of {} photos of {held_persons} held-out persons; keypoints: {keypoint_source}", held.len()),
    );
    let (gm, im) = combined_scores(&recognizer, &templates, Combine::Max);
    let (ga, ia) = combined_scores(&recognizer, &templates, Combine::Mean);
    let (eer_max, eer_mean) = (eer(&gm, &im), eer(&ga, &ia));
    model.combine = if eer_mean < eer_max { Combine::Mean } else { Combine::Max };
    let combine = model.combine;
    model.enrolled_calibration = (2..=MAX_CALIBRATED_ENROLMENT)
        .filter_map(|k| {
            let (genuine, impostor) = enrolment_scores(&recognizer, &templates, k, combine);
            (!genuine.is_empty() && !impostor.is_empty()).then(|| EnrolledCalibration {
                enrolled: k,
                calibration: Calibration::from_scores(
                    &genuine,
                    &impostor,
                    &CALIBRATED_FMRS,
                    &format!(
                        "probes against {k} enrolled photos ({combine:?}), every rotation of each held-out person's photos; keypoints: {keypoint_source}"
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
    use crate::research::Quiet;

    #[test]
    fn person_numbers_and_split_follow_the_labels() {
        assert_eq!(person_number("imm-07"), Some(7));
        assert_eq!(person_number("orl-s12"), Some(12));
        assert_eq!(person_number("folder"), None);
        let faces = list_faces(&[crate::config::shared_dir().join("data/imm")]).unwrap();
        assert_eq!(faces.len(), 180);
        assert_eq!(faces.iter().filter(|f| f.held_out).count(), 9 * 6);
        assert!(faces.iter().all(|f| f.asf.is_some() && f.view.is_some()));
    }

    /// A re-posed copy is the same face turned by the offset: the 3DMM fitted to the copy's own
    /// landmarks finds the photo's yaw plus the offset, and its crops exist on both paths.
    #[test]
    fn reposed_copies_turn_the_face_by_the_offset() {
        let faces = list_faces(&[crate::config::shared_dir().join("data/imm")]).unwrap();
        let face = faces.iter().find(|f| !f.held_out && f.view == Some(1)).unwrap().clone();
        let front = FrontEnd { face_model: Some(FaceModel::load(&crate::config::sfm_dir()).unwrap()), ..FrontEnd::annotations_only() };
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
    fn enrolment_sets_score_the_best_enrolled_photo() {
        let dlda = Dlda { input_dims: 1, dims: 1, mean: vec![0.0], projection: vec![1.0], within_eigenvalues: vec![1.0] };
        let recognizer = Recognizer::from_model(Model::new(
            Normalization::TwoD,
            NormalizeParams::default(),
            crate::recognize::FeatureKind::Pixels,
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
        let (g1, i1) = enrolment_scores(&recognizer, &templates, 1, Combine::Max);
        let (g, i) = pair_scores(&recognizer, &templates);
        let twice = |v: Vec<f32>| sorted(v.iter().chain(&v).copied().collect());
        assert_eq!((sorted(g1), sorted(i1)), (twice(g), twice(i)));
        let (g2, i2) = enrolment_scores(&recognizer, &templates, 2, Combine::Max);
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

    /// Train on IMM frontal views of the training persons with annotated keypoints: the projection
    /// of a training photo must be stable (same template twice, and close to its mirrored copy's
    /// class), and held-out genuine pairs must score above impostor pairs on average.
    #[test]
    fn imm_training_gives_a_stable_projection() {
        let faces: Vec<FaceImage> =
            list_faces(&[crate::config::shared_dir().join("data/imm")]).unwrap().into_iter().filter(|f| !f.is_rotated_view()).collect();
        let front = FrontEnd::annotations_only();
        let config = TrainConfig::default();
        let aligned = align_all(&front, &faces, Normalization::TwoD, &config.normalize, &Quiet);
        assert_eq!(aligned.len(), faces.len());
        let (model, report) = train_model(&aligned, &config, &["imm".into()]).unwrap();
        let recognizer = Recognizer::from_model(model.clone());
        let a = aligned.iter().find(|a| !a.face.held_out).unwrap();
        let t1 = template_of(&recognizer, a).unwrap();
        let prepared = front.prepare(&a.face, Normalization::TwoD).unwrap();
        let t2 = recognizer.template(Views::Single(&recognizer.normalized_crop(&prepared.gray, &prepared.keypoints))).unwrap();
        assert!(t1.cosine(&t2) > 0.9999, "same photo, same template");
        // A small shift of the keypoints (half a crop pixel) barely moves the template.
        let k = prepared.keypoints;
        let shift = |p: crate::core::geometry::Point| [p[0] + 1.5, p[1] + 1.0];
        let shifted = KeyPoints { left_eye: shift(k.left_eye), right_eye: shift(k.right_eye), mouth: shift(k.mouth) };
        let t3 = recognizer.template(Views::Single(&recognizer.normalized_crop(&prepared.gray, &shifted))).unwrap();
        assert!(t1.cosine(&t3) > 0.8, "shifted keypoints: cosine {}", t1.cosine(&t3));
        // Round trip through the model file keeps the version and the templates.
        let dir = std::env::temp_dir().join(format!("facegate-dlda-test-{}", std::process::id()));
        model.save(&dir.join("dlda.bin")).unwrap();
        let loaded = Recognizer::load(&dir).unwrap();
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
        assert_eq!(model.calibration.points.len(), 3);
    }
}
