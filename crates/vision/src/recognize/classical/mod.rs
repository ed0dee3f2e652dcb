//! The classical recognizer (thesis 2.6): the model file `models/dlda.bin` ([`ClassicalModel`]:
//! normalisation, features, Direct LDA per path and local part, cohort normalisation, calibration
//! per enrolment size) and [`ClassicalRecognizer`], which makes and scores its templates.

use std::path::Path;

use serde::{Deserialize, Serialize};

use facegate_core::face::EyeMouthCentres;
use facegate_core::imaging::GrayF32;

use super::{
    Calibration, Cohort, CohortStats, Combine, Dlda, EnrolledCalibration, FeatureKind, Normalization, NormalizeParams, OperatingPoint,
    RecognizeError, Region, Template, Views, features, model_version, normalize, score_norm,
};

/// Where a model's training and calibration data came from.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// `imm-annotations` (eye/mouth centres from the `.asf` files) or `pipeline` (detector + ASM).
    #[serde(rename = "keypoint_source")]
    pub centre_source: String,
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
    pub fn normalized_crop(&self, gray: &GrayF32, centres: &EyeMouthCentres) -> GrayF32 {
        normalize::normalize(gray, centres, &self.model.normalize)
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
mod tests;
