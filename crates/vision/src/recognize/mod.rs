//! Normalisation, Direct LDA templates, scores and calibrated thresholds (thesis 2.6).
//!
//! A face comes in as a grey image and its eye and mouth centres ([`KeyPoints`]); [`normalize`]
//! aligns and relights it into a small crop, [`features`] turns the crop into a vector, [`dlda`]
//! projects it, and the unit projection is the [`Template`]. Templates compare by cosine
//! similarity; a decision uses a threshold calibrated at a false match rate ([`calibration`]).
//! Everything a template depends on is in one model file, `models/dlda.bin` (postcard), whose
//! content hash is the model version carried by every template.

pub mod calibration;
pub mod deep;
pub mod dlda;
pub mod embedding;
pub mod features;
pub mod normalize;
mod recognizer;
pub mod score_norm;
pub mod template;

use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use facegate_core::face::KeyPoints;
use facegate_core::imaging::GrayF32;

pub use calibration::{Calibration, DEFAULT_FMR, EnrolledCalibration, MAX_CALIBRATED_ENROLLMENT};
pub use dlda::{Dlda, DldaParams};
pub use facegate_core::template::OperatingPoint;
pub use features::{FeatureKind, Region};
pub use normalize::{NormalizeParams, Photometric};
pub use score_norm::{Cohort, CohortStats};
pub use template::{Combine, Template};

pub use deep::DeepRecognizer;
pub use embedding::EmbeddingRecognizer;
pub use recognizer::{Recognizer, RecognizerKind};

/// Which normalisation a recognition model was trained for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Normalization {
    /// Similarity alignment of eye and mouth centres in the photo.
    #[serde(rename = "2d")]
    TwoD,
    /// The 3DMM's frontal rendering, then the same alignment.
    #[serde(rename = "3dmm")]
    Morph,
}

impl std::fmt::Display for Normalization {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Normalization::TwoD => "2d",
            Normalization::Morph => "3dmm",
        })
    }
}

/// A face as each normalisation path of a model sees it. A fused model has two paths (its
/// primary, the 3DMM frontal rendering, and its second, the 2D-aligned photo) and needs both
/// views; a single-path model needs one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Views<T> {
    Single(T),
    Fused { primary: T, secondary: T },
}

impl<T> Views<T> {
    /// The same views through `f`, path by path.
    pub fn map<U>(self, mut f: impl FnMut(T) -> U) -> Views<U> {
        match self {
            Views::Single(v) => Views::Single(f(v)),
            Views::Fused { primary, secondary } => Views::Fused { primary: f(primary), secondary: f(secondary) },
        }
    }

    pub fn as_ref(&self) -> Views<&T> {
        match self {
            Views::Single(v) => Views::Single(v),
            Views::Fused { primary, secondary } => Views::Fused { primary, secondary },
        }
    }

    /// How many paths: 1 or 2.
    pub fn count(&self) -> usize {
        match self {
            Views::Single(_) => 1,
            Views::Fused { .. } => 2,
        }
    }

    /// The views, primary first.
    pub fn into_vec(self) -> Vec<T> {
        match self {
            Views::Single(v) => vec![v],
            Views::Fused { primary, secondary } => vec![primary, secondary],
        }
    }
}

/// A model version: `prefix`, a dash and the first 12 hex digits of the SHA-256 of `shape` (the
/// serialised parts of a model that shape its templates). Templates of different versions are
/// never compared, so a version must not change while the model's templates do not.
pub(crate) fn model_version(prefix: &str, shape: &[u8]) -> String {
    let hex: String = Sha256::digest(shape).iter().take(6).map(|b| format!("{b:02x}")).collect();
    format!("{prefix}-{hex}")
}

#[derive(Debug, thiserror::Error)]
pub enum RecognizeError {
    #[error("cannot write {path}: {message}")]
    Save { path: String, message: String },
    #[error("cannot load the recognition model {path}: {message}")]
    Model { path: String, message: String },
    #[error("template from model {found} cannot be compared with model {expected}: re-enrol with the current model")]
    ModelVersionMismatch { expected: String, found: String },
    #[error("template has {found} dimensions, the model makes {expected}")]
    TemplateDimension { expected: usize, found: usize },
    #[error("the model makes templates from {expected} normalised views (one per path), got {found}")]
    Views { expected: usize, found: usize },
    #[error("no templates to compare against")]
    NoTemplates,
}

/// Where a model's training and calibration data came from.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// `imm-annotations` (eye/mouth centres from the `.asf` files) or `pipeline` (detector + ASM).
    pub keypoint_source: String,
    pub data: Vec<String>,
    pub train_persons: Vec<String>,
    pub train_images: usize,
    pub calibration_persons: Vec<String>,
    pub calibration_images: usize,
    /// Mirrored copies of the training crops were added.
    pub mirrored: bool,
}

/// The second path of a fused model: its normalisation (the features and crop layout are the
/// primary's) and its projection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SecondaryPath {
    pub normalization: Normalization,
    pub dlda: Dlda,
    /// Weight w of this path's cosine in the fused score (1 − w for the primary): the halves of
    /// the template are scaled by √(1 − w) and √w.
    pub weight: f32,
}

/// A projection of one face region (a subset of each path's features, [`FeatureKind::indices_in`]):
/// a local model, which a change confined to another region (glasses, an open mouth) leaves
/// alone. Its unit projection joins the template scaled by √weight, like a path's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocalPart {
    pub region: Region,
    /// Weight of this region's cosine within each path's score; the whole face keeps 1 − Σ weights.
    pub weight: f32,
    /// One projection per path, primary first.
    pub projections: Vec<Dlda>,
}

/// Everything a template depends on, saved as `models/dlda.bin`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassicalModel {
    pub format: u32,
    pub normalization: Normalization,
    pub normalize: NormalizeParams,
    pub features: FeatureKind,
    pub dlda: Dlda,
    /// A second projection trained on the other normalisation path's crops (score-level fusion of
    /// the 2D and 3DMM paths): the template is both unit projections concatenated, scaled by
    /// √(1 − w) and √w, so that the cosine of two templates is the weighted mean of the two
    /// paths' cosines.
    pub secondary: Option<SecondaryPath>,
    pub combine: Combine,
    /// Cohort score normalisation (S-norm / AS-norm): scores are then normalised cosines, and the
    /// calibration is made on them. `None`: scores are raw cosines.
    pub cohort: Option<Cohort>,
    pub calibration: Calibration,
    pub provenance: Provenance,
    /// Local region projections ensembled with the whole face (empty: the whole face only).
    pub parts: Vec<LocalPart>,
    /// Threshold tables for subjects enrolled with 2 … [`MAX_CALIBRATED_ENROLMENT`] photos, by
    /// size (`calibration` is the one-photo table). Empty in files before format 4.
    pub enrolled_calibration: Vec<EnrolledCalibration>,
}

/// A format-2 model file: [`ClassicalModel`] before the local parts (read, then given no parts).
#[derive(Deserialize)]
struct ModelFormat2 {
    /// Read for the field order only (postcard is positional); it is 2 (3 when read inside a [`ModelFormat3`]).
    _format: u32,
    normalization: Normalization,
    normalize: NormalizeParams,
    features: FeatureKind,
    dlda: Dlda,
    secondary: Option<SecondaryPath>,
    combine: Combine,
    cohort: Option<Cohort>,
    calibration: Calibration,
    provenance: Provenance,
}

/// A format-3 model file: [`ClassicalModel`] before the enrolment-size calibration. Postcard has no struct
/// framing, so the format-2 fields followed by the parts read a format-3 file.
#[derive(Deserialize)]
struct ModelFormat3 {
    v2: ModelFormat2,
    parts: Vec<LocalPart>,
}

impl From<ModelFormat3> for ClassicalModel {
    fn from(m: ModelFormat3) -> ClassicalModel {
        ClassicalModel { parts: m.parts, ..m.v2.into() }
    }
}

impl From<ModelFormat2> for ClassicalModel {
    fn from(m: ModelFormat2) -> ClassicalModel {
        let ModelFormat2 { _format: _, normalization, normalize, features, dlda, secondary, combine, cohort, calibration, provenance } = m;
        ClassicalModel {
            format: MODEL_FORMAT,
            normalization,
            normalize,
            features,
            dlda,
            secondary,
            combine,
            cohort,
            calibration,
            provenance,
            parts: Vec::new(),
            enrolled_calibration: Vec::new(),
        }
    }
}

/// 2: the fused second path and the cohort for score normalisation; 3: the local parts; 4: the
/// threshold tables per enrolment-set size.
const MODEL_FORMAT: u32 = 4;
pub const MODEL_FILE: &str = "dlda.bin";

impl ClassicalModel {
    pub fn new(
        normalization: Normalization,
        normalize: NormalizeParams,
        features: FeatureKind,
        dlda: Dlda,
        provenance: Provenance,
    ) -> ClassicalModel {
        ClassicalModel {
            format: MODEL_FORMAT,
            normalization,
            normalize,
            features,
            dlda,
            secondary: None,
            combine: Combine::Max,
            cohort: None,
            calibration: Calibration { points: Vec::new(), genuine_count: 0, impostor_count: 0, source: String::new() },
            provenance,
            parts: Vec::new(),
            enrolled_calibration: Vec::new(),
        }
    }

    /// The threshold table for a subject enrolled with `enrolled` photos: the largest calibrated
    /// set size not above it (one photo: `calibration`). Beyond the largest calibrated size the
    /// impostor rate keeps growing with each photo enrolled, above the table's FMR: the held-out
    /// persons have too few photos to calibrate larger sets (docs/recognition.md).
    pub fn calibration_for(&self, enrolled: usize) -> &Calibration {
        self.enrolled_calibration.iter().rev().find(|t| t.enrolled <= enrolled).map_or(&self.calibration, |t| &t.calibration)
    }

    /// `dlda-` and 12 hex digits of the SHA-256 of everything that shapes a template (normalisation,
    /// features, projections); calibration and provenance do not change templates, so not the
    /// version. The local parts are hashed only when there are some, so that a model without parts
    /// keeps the version it had in format 2 (and its enrolled templates stay valid).
    pub fn version(&self) -> String {
        let shape = (&self.normalization, &self.normalize, &self.features, &self.dlda, &self.secondary);
        let bytes = if self.parts.is_empty() { postcard::to_stdvec(&shape) } else { postcard::to_stdvec(&(shape, &self.parts)) }
            .expect("model serialises");
        model_version("dlda", &bytes)
    }

    /// The normalisation paths a template is made of, primary first.
    pub fn paths(&self) -> Vec<Normalization> {
        std::iter::once(self.normalization).chain(self.secondary.as_ref().map(|s| s.normalization)).collect()
    }

    /// Dimension of the templates (both paths for a fused model, each with its local parts).
    pub fn template_dims(&self) -> usize {
        self.dlda.dims
            + self.secondary.as_ref().map_or(0, |s| s.dlda.dims)
            + self.parts.iter().flat_map(|p| &p.projections).map(|d| d.dims).sum::<usize>()
    }

    /// Weight of each path's cosine in the score, primary first.
    fn path_weights(&self) -> Vec<f32> {
        match &self.secondary {
            Some(s) => {
                let w = s.weight.clamp(0.0, 1.0);
                vec![1.0 - w, w]
            }
            None => vec![1.0],
        }
    }

    /// Weight of the whole face's cosine within a path (1 without local parts).
    fn whole_face_weight(&self) -> f32 {
        1.0 - self.parts.iter().map(|p| p.weight).sum::<f32>()
    }

    pub fn save(&self, path: &Path) -> Result<(), RecognizeError> {
        facegate_core::model_file::write_model(path, self)
            .map_err(|e| RecognizeError::Save { path: path.display().to_string(), message: e })
    }

    pub fn load(path: &Path) -> Result<ClassicalModel, RecognizeError> {
        let err = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
        let file = facegate_core::model_file::ModelFile::read(path, "facegate DLDA model").map_err(err)?;
        let model: ClassicalModel = match file.format {
            2 => file.decode::<ModelFormat2>().map_err(err)?.into(),
            3 => file.decode::<ModelFormat3>().map_err(err)?.into(),
            MODEL_FORMAT => file.decode().map_err(err)?,
            format => return Err(err(format!("model format {format} (this build reads 2 to {MODEL_FORMAT})"))),
        };
        let mask = model.normalize.mask();
        let dims = model.features.dims(model.normalize.width, model.normalize.height, &mask);
        if let Some(second) = &model.secondary {
            if !second.dlda.accepts(dims) || second.normalization == model.normalization {
                return Err(err("the second path's projection does not match the feature layout".into()));
            }
        }
        if model.cohort.as_ref().is_some_and(|c| c.dims != model.template_dims()) {
            return Err(err("the score-normalisation cohort does not match the template dimension".into()));
        }
        if !model.dlda.accepts(dims) {
            return Err(err("projection does not match the feature layout".into()));
        }
        let paths = model.paths().len();
        for part in &model.parts {
            let indices = model.features.indices_in(model.normalize.width, model.normalize.height, &mask, &part.region);
            if !part.region.is_valid() || part.projections.len() != paths || !part.projections.iter().all(|d| d.accepts(indices.len())) {
                return Err(err("a local part's projections do not match its region's features".into()));
            }
        }
        if !(0.0..=1.0).contains(&model.whole_face_weight()) || model.parts.iter().any(|p| p.weight.is_nan() || p.weight < 0.0) {
            return Err(err("the local parts' weights are not between 0 and 1 in sum".into()));
        }
        if !model.enrolled_calibration.windows(2).all(|w| w[0].enrolled < w[1].enrolled)
            || model.enrolled_calibration.first().is_some_and(|t| t.enrolled < 2)
        {
            return Err(err("the enrolment-size threshold tables are not in increasing size from 2".into()));
        }
        Ok(model)
    }
}

/// The DLDA projection with its calibration table, shareable across threads.
pub struct ClassicalRecognizer {
    model: ClassicalModel,
    version: String,
    mask: Vec<bool>,
    /// `P · mean` of the primary and the second projection (see [`Dlda::offsets`]).
    offsets: Vec<Vec<f32>>,
    /// Per local part, its features' indices and per path its projection's `P · mean`.
    parts: Vec<(Vec<usize>, Vec<Vec<f32>>)>,
}

impl ClassicalRecognizer {
    /// Load `dlda.bin` from the models folder.
    pub fn load(models_dir: &Path) -> Result<ClassicalRecognizer, RecognizeError> {
        ClassicalRecognizer::load_file(&models_dir.join(MODEL_FILE))
    }

    pub fn load_file(path: &Path) -> Result<ClassicalRecognizer, RecognizeError> {
        Ok(ClassicalRecognizer::from_model(ClassicalModel::load(path)?))
    }

    pub fn from_model(model: ClassicalModel) -> ClassicalRecognizer {
        let version = model.version();
        let mask = model.normalize.mask();
        let offsets = std::iter::once(&model.dlda).chain(model.secondary.as_ref().map(|s| &s.dlda)).map(Dlda::offsets).collect();
        let (w, h) = (model.normalize.width, model.normalize.height);
        let parts = model
            .parts
            .iter()
            .map(|p| (model.features.indices_in(w, h, &mask, &p.region), p.projections.iter().map(Dlda::offsets).collect()))
            .collect();
        ClassicalRecognizer { model, version, mask, offsets, parts }
    }

    pub fn model(&self) -> &ClassicalModel {
        &self.model
    }

    pub fn model_version(&self) -> &str {
        &self.version
    }

    pub fn normalization(&self) -> Normalization {
        self.model.normalization
    }

    /// The normalisation paths a template is made of, primary first (two for a fused model).
    pub fn paths(&self) -> Vec<Normalization> {
        self.model.paths()
    }

    /// The normalised crop of a face (geometric and photometric), as the model sees it.
    pub fn normalized_crop(&self, gray: &GrayF32, keypoints: &KeyPoints) -> GrayF32 {
        normalize::normalize(gray, keypoints, &self.model.normalize)
    }

    /// The template of a face: its normalised crops (see [`ClassicalRecognizer::normalized_crop`]) as each
    /// path of the model sees it, [`Views::Single`] for a single-path model and [`Views::Fused`]
    /// for a fused one. Any other shape is [`RecognizeError::Views`]: one view never stands in for
    /// both paths. The one way to make a template.
    pub fn template(&self, crops: Views<&GrayF32>) -> Result<Template, RecognizeError> {
        let expected = 1 + self.model.secondary.is_some() as usize;
        if crops.count() != expected {
            return Err(RecognizeError::Views { expected, found: crops.count() });
        }
        // Each block (per path: the whole face, then each local part) is a unit projection scaled
        // by the square root of its weight, so that the cosine of two templates is the weighted
        // sum of the blocks' cosines.
        let mut vector = Vec::with_capacity(self.model.template_dims());
        let mut push =
            |block: Vec<f32>, weight: f32| vector.extend(facegate_core::vector::unit(block).into_iter().map(|v| v * weight.sqrt()));
        let whole_weight = self.model.whole_face_weight();
        let wholes = std::iter::once(&self.model.dlda).chain(self.model.secondary.as_ref().map(|s| &s.dlda));
        for (p, ((crop, whole), path_weight)) in crops.into_vec().into_iter().zip(wholes).zip(self.model.path_weights()).enumerate() {
            let features = self.model.features.extract(crop, &self.mask);
            push(whole.project_with_offsets(&features, &self.offsets[p]), path_weight * whole_weight);
            for (part, (indices, offsets)) in self.model.parts.iter().zip(&self.parts) {
                let local = features::gather(&features, indices);
                push(part.projections[p].project_with_offsets(&local, &offsets[p]), path_weight * part.weight);
            }
        }
        Ok(Template::new(&self.version, vector))
    }

    /// Score of a probe against one subject's templates (higher is more alike), combining
    /// several templates by the model's measured rule (max or mean). With a cohort in the model
    /// each cosine is S-normalised first ([`score_norm`]); the thresholds are calibrated on the
    /// same scores.
    ///
    /// Templates made by another model version (or of another length) cannot be compared: they
    /// are left out, and when nothing comparable is left the score is [`ClassicalRecognizer::no_match`],
    /// far below every threshold. Use [`ClassicalRecognizer::try_score`] to get that as an error.
    pub fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        if !self.comparable(probe) {
            return self.no_match();
        }
        let probe_stats = self.cohort_stats(probe);
        self.model
            .combine
            .apply(enrolled.iter().filter(|t| self.comparable(t)).map(|t| self.pair_score(probe, probe_stats, t, self.cohort_stats(t))))
            .unwrap_or(self.no_match())
    }

    /// The score given when nothing is comparable: −1 without a cohort (the lowest cosine), and
    /// far below any normalised score with one (finite, so that it serialises as JSON).
    pub fn no_match(&self) -> f32 {
        if self.model.cohort.is_some() { -1000.0 } else { -1.0 }
    }

    /// A template's cosine statistics against the model's cohort (neutral without a cohort), to
    /// be passed to [`ClassicalRecognizer::pair_score`] when one template is scored many times.
    pub fn cohort_stats(&self, t: &Template) -> CohortStats {
        match &self.model.cohort {
            Some(c) => c.stats(&t.vector),
            None => CohortStats { mean: 0.0, inv_std: 1.0 },
        }
    }

    /// The score of one pair of templates with their [`ClassicalRecognizer::cohort_stats`]: the cosine,
    /// S-normalised when the model has a cohort.
    pub fn pair_score(&self, a: &Template, a_stats: CohortStats, b: &Template, b_stats: CohortStats) -> f32 {
        let cosine = a.cosine(b);
        if self.model.cohort.is_some() { score_norm::s_norm(cosine, a_stats, b_stats) } else { cosine }
    }

    /// [`ClassicalRecognizer::score`] with a typed error for templates of another model version.
    pub fn try_score(&self, probe: &Template, enrolled: &[Template]) -> Result<f32, RecognizeError> {
        if enrolled.is_empty() {
            return Err(RecognizeError::NoTemplates);
        }
        for t in std::iter::once(probe).chain(enrolled) {
            self.check(t)?;
        }
        Ok(self.score(probe, enrolled))
    }

    /// Whether `template` was made by this model.
    pub fn check(&self, template: &Template) -> Result<(), RecognizeError> {
        if template.model_version != self.version {
            return Err(RecognizeError::ModelVersionMismatch { expected: self.version.clone(), found: template.model_version.clone() });
        }
        if template.vector.len() != self.model.template_dims() {
            return Err(RecognizeError::TemplateDimension { expected: self.model.template_dims(), found: template.vector.len() });
        }
        Ok(())
    }

    fn comparable(&self, t: &Template) -> bool {
        self.check(t).is_ok()
    }

    /// The calibrated operating point closest to `fmr` (the default is 1e-3) for a subject
    /// enrolled with `enrolled` templates (1 for a one-to-one comparison).
    pub fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.model.calibration_for(enrolled).operating_point(fmr)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn projection(input_dims: usize, dims: usize, seed: u32) -> Dlda {
        // A fixed pseudo-random projection (what is tested is the fusion, not the training).
        let value =
            |i: usize| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed.wrapping_mul(40503)) >> 8) % 1000) as f32 / 500.0 - 1.0;
        Dlda {
            input_dims,
            dims,
            mean: vec![0.0; input_dims],
            projection: (0..input_dims * dims).map(value).collect(),
            within_eigenvalues: vec![1.0; dims],
        }
    }

    /// Saves `model` as the `dlda.bin` of the models folder `dir` and loads the folder back, as the
    /// service does.
    fn save_and_load(model: &ClassicalModel, dir: &Path) -> Result<ClassicalRecognizer, RecognizeError> {
        model.save(&dir.join(MODEL_FILE)).unwrap();
        ClassicalRecognizer::load(dir)
    }

    /// Local parts: each region's projection reads its own features, and the cosine of two
    /// templates is the weighted sum of the whole face's and the regions' cosines per path; the
    /// version changes with the parts, the file round-trips, and inconsistent parts are refused.
    #[test]
    fn local_parts_score_the_weighted_sum_of_the_regions() {
        let params = NormalizeParams::default();
        let mask = params.mask();
        let kind = FeatureKind::PixelsLbp { grid: 4 };
        let dims = kind.dims(params.width, params.height, &mask);
        let provenance = Provenance::default();
        let plain = ClassicalModel::new(Normalization::TwoD, params.clone(), kind, projection(dims, 6, 1), provenance);
        let (upper, lower) = (Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 }, Region { x0: 0.1, y0: 0.5, x1: 0.9, y1: 1.0 });
        let local_dims = |r: &Region| kind.indices_in(params.width, params.height, &mask, r).len();
        let mut with_parts = plain.clone();
        with_parts.parts = vec![
            LocalPart { region: upper, weight: 0.2, projections: vec![projection(local_dims(&upper), 3, 2)] },
            LocalPart { region: lower, weight: 0.3, projections: vec![projection(local_dims(&lower), 4, 3)] },
        ];
        assert_ne!(plain.version(), with_parts.version());
        assert_eq!(with_parts.template_dims(), 13);
        let crop = |k: usize| GrayF32::from_fn(params.width, params.height, |x, y| ((x * (3 + k) + y * (7 + 2 * k)) % 13) as f32);
        let (a, b) = (crop(0), crop(1));
        let recognizer = ClassicalRecognizer::from_model(with_parts.clone());
        let (ta, tb) = (recognizer.template(Views::Single(&a)).unwrap(), recognizer.template(Views::Single(&b)).unwrap());
        let cos = |dlda: &Dlda, indices: Option<Vec<usize>>| {
            let pick = |c: &GrayF32| {
                let f = kind.extract(c, &mask);
                indices.as_ref().map_or(f.clone(), |i| features::gather(&f, i))
            };
            Template::new("v", dlda.project(&pick(&a))).cosine(&Template::new("v", dlda.project(&pick(&b))))
        };
        let indices = |r: &Region| Some(kind.indices_in(params.width, params.height, &mask, r));
        let expected = 0.5 * cos(&with_parts.dlda, None)
            + 0.2 * cos(&with_parts.parts[0].projections[0], indices(&upper))
            + 0.3 * cos(&with_parts.parts[1].projections[0], indices(&lower));
        assert!((ta.cosine(&tb) - expected).abs() < 1e-5, "{} against {expected}", ta.cosine(&tb));
        let dir = std::env::temp_dir().join(format!("facegate-parts-test-{}", std::process::id()));
        let loaded = save_and_load(&with_parts, &dir).unwrap();
        assert_eq!((loaded.model_version(), loaded.template(Views::Single(&a)).unwrap()), (recognizer.model_version(), ta));
        // A part whose projection does not fit its region is refused at load.
        with_parts.parts[1].projections[0] = projection(local_dims(&upper), 4, 3);
        assert!(matches!(save_and_load(&with_parts, &dir), Err(RecognizeError::Model { .. })));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Format-2 files (before the local parts) and format-3 files (before the enrolment-size
    /// tables) still load: same version, same templates.
    #[test]
    fn format_2_and_3_models_load_with_their_version() {
        let params = NormalizeParams::default();
        let mask = params.mask();
        let dims = FeatureKind::Pixels.dims(params.width, params.height, &mask);
        let provenance = Provenance {
            keypoint_source: "imm-annotations".into(),
            train_persons: vec!["imm-04".into()],
            train_images: 1,
            mirrored: true,
            ..Provenance::default()
        };
        let mut model = ClassicalModel::new(Normalization::Morph, params.clone(), FeatureKind::Pixels, projection(dims, 5, 1), provenance);
        model.secondary = Some(SecondaryPath { normalization: Normalization::TwoD, dlda: projection(dims, 4, 2), weight: 0.3 });
        let m = &model;
        // A format-2 file: the same fields in the same order, without the parts (postcard is positional).
        let bytes = postcard::to_stdvec(&(
            2u32,
            &m.normalization,
            &m.normalize,
            &m.features,
            &m.dlda,
            &m.secondary,
            &m.combine,
            &m.cohort,
            &m.calibration,
            &m.provenance,
        ))
        .unwrap();
        let dir = std::env::temp_dir().join(format!("facegate-format2-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(MODEL_FILE), &bytes).unwrap();
        let loaded = ClassicalRecognizer::load(&dir).unwrap();
        let fresh = ClassicalRecognizer::from_model(model.clone());
        assert_eq!((loaded.model().parts.len(), loaded.model().format), (0, MODEL_FORMAT));
        assert_eq!(loaded.model_version(), fresh.model_version());
        let crop = GrayF32::from_fn(params.width, params.height, |x, y| ((x * 5 + y * 11) % 17) as f32);
        assert_eq!(
            loaded.template(Views::Fused { primary: &crop, secondary: &crop }).unwrap(),
            fresh.template(Views::Fused { primary: &crop, secondary: &crop }).unwrap()
        );
        // A format-3 file: the format-2 fields then the parts, without the enrolment-size tables.
        let mut with_part = model.clone();
        let upper = Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 };
        let local = FeatureKind::Pixels.indices_in(params.width, params.height, &mask, &upper).len();
        with_part.parts =
            vec![LocalPart { region: upper, weight: 0.3, projections: vec![projection(local, 3, 3), projection(local, 2, 4)] }];
        // The format number is one varint byte: the format-2 bytes renumbered, then the parts.
        let format3: Vec<u8> =
            std::iter::once(3u8).chain(bytes[1..].iter().copied()).chain(postcard::to_stdvec(&with_part.parts).unwrap()).collect();
        std::fs::write(dir.join(MODEL_FILE), &format3).unwrap();
        let loaded = ClassicalRecognizer::load(&dir).unwrap();
        assert_eq!((loaded.model().parts.len(), loaded.model().enrolled_calibration.len()), (1, 0));
        assert_eq!(loaded.model_version(), ClassicalRecognizer::from_model(with_part.clone()).model_version());
        // An unknown format is refused with a typed error.
        let mut future = bytes.clone();
        future[0] = 9;
        std::fs::write(dir.join(MODEL_FILE), &future).unwrap();
        assert!(matches!(ClassicalRecognizer::load(&dir), Err(RecognizeError::Model { .. })));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A subject with k templates is judged by the table of the largest calibrated size up to k;
    /// the tables survive the model file, and tables out of order are refused at load.
    #[test]
    fn thresholds_follow_the_number_of_enrolled_templates() {
        let params = NormalizeParams::default();
        let dims = FeatureKind::Pixels.dims(params.width, params.height, &params.mask());
        let mut model =
            ClassicalModel::new(Normalization::TwoD, params, FeatureKind::Pixels, projection(dims, 3, 1), Provenance::default());
        let impostor: Vec<f32> = (0..2000).map(|i| i as f32 / 4000.0).collect();
        let table = |shift: f32| Calibration::from_scores(&[0.9], &impostor.iter().map(|s| s + shift).collect::<Vec<_>>(), &[1e-3], "t");
        model.calibration = table(0.0);
        model.enrolled_calibration = vec![
            EnrolledCalibration { enrolled: 2, calibration: table(0.01) },
            EnrolledCalibration { enrolled: 5, calibration: table(0.03) },
        ];
        let recognizer = ClassicalRecognizer::from_model(model.clone());
        let threshold = |k: usize| recognizer.operating_point(1e-3, k).threshold;
        assert!(threshold(1) < threshold(2) && threshold(2) < threshold(5));
        assert_eq!((threshold(0), threshold(3), threshold(4), threshold(9)), (threshold(1), threshold(2), threshold(2), threshold(5)));
        let dir = std::env::temp_dir().join(format!("facegate-enrolled-test-{}", std::process::id()));
        assert_eq!(save_and_load(&model, &dir).unwrap().model(), &model);
        model.enrolled_calibration.swap(0, 1);
        assert!(matches!(save_and_load(&model, &dir), Err(RecognizeError::Model { .. })));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A fused model's template is both paths' unit projections, weighted so that the cosine of two
    /// templates is the weighted mean of the two paths' cosines; it needs one crop per path.
    #[test]
    fn fused_templates_score_the_weighted_mean_of_the_paths() {
        let params = NormalizeParams::default();
        let mask = params.mask();
        let dims = FeatureKind::Pixels.dims(params.width, params.height, &mask);
        let provenance = Provenance::default();
        let single =
            ClassicalModel::new(Normalization::Morph, params.clone(), FeatureKind::Pixels, projection(dims, 5, 1), provenance.clone());
        let mut fused = single.clone();
        fused.secondary = Some(SecondaryPath { normalization: Normalization::TwoD, dlda: projection(dims, 4, 2), weight: 0.3 });
        assert_ne!(single.version(), fused.version());
        assert_eq!((fused.template_dims(), fused.paths()), (9, vec![Normalization::Morph, Normalization::TwoD]));
        let crop = |k: usize| GrayF32::from_fn(params.width, params.height, |x, y| ((x * (3 + k) + y * (7 + 2 * k)) % 13) as f32);
        let (a, b, c, d) = (crop(0), crop(1), crop(2), crop(3));
        let fused = ClassicalRecognizer::from_model(fused);
        assert!(matches!(fused.template(Views::Single(&a)), Err(RecognizeError::Views { expected: 2, found: 1 })));
        let (t1, t2) = (
            fused.template(Views::Fused { primary: &a, secondary: &b }).unwrap(),
            fused.template(Views::Fused { primary: &c, secondary: &d }).unwrap(),
        );
        assert_eq!(t1.vector.len(), 9);
        // The paths' own cosines, from their unit projections.
        let cos = |dlda: &Dlda, x: &GrayF32, y: &GrayF32| {
            let (p, q) = (dlda.project(&FeatureKind::Pixels.extract(x, &mask)), dlda.project(&FeatureKind::Pixels.extract(y, &mask)));
            Template::new("v", p).cosine(&Template::new("v", q))
        };
        let m = fused.model();
        let expected = 0.7 * cos(&m.dlda, &a, &c) + 0.3 * cos(&m.secondary.as_ref().unwrap().dlda, &b, &d);
        assert!((fused.score(&t1, std::slice::from_ref(&t2)) - expected).abs() < 1e-5);
        // Templates of the single-path model are not comparable with the fused ones.
        let single = ClassicalRecognizer::from_model(single);
        let t3 = single.template(Views::Single(&a)).unwrap();
        assert!(fused.try_score(&t1, &[t3.clone()]).is_err());
        assert_eq!(fused.score(&t1, &[t3]), -1.0);
        // The model file round-trips, fusion included.
        let dir = std::env::temp_dir().join(format!("facegate-fused-test-{}", std::process::id()));
        let loaded = save_and_load(fused.model(), &dir).unwrap();
        assert_eq!(
            (loaded.model_version(), loaded.template(Views::Fused { primary: &a, secondary: &b }).unwrap()),
            (fused.model_version(), t1)
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
