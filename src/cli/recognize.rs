//! `facegate compare`, `train dlda`, `eval pairs`, `eval verify`, `eval identify`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;

use crate::choices;
use facegate_core::template::Template;
use facegate_research::dlda::DldaParams;
use facegate_research::eval::identification;
use facegate_research::eval::pairs::{read_pairs, score_pairs};
use facegate_research::eval::verification::{self, summarize};
use facegate_research::train_dlda::{self as train, AlignedFace, FaceRegion, FrontEnd, HeldOutReport, TrainConfig};
use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::calibration::DEFAULT_FMR;
use facegate_vision::recognize::{
    ClassicalModel, ClassicalRecognizer, FeatureKind, Normalization, NormalizeParams, Photometric, RecognizerKind,
};

#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    pub a: PathBuf,
    pub b: PathBuf,
    #[arg(long)]
    pub json: bool,
    /// Which recognizer compares the photos.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = choices::Recognizer::from(RecognizerKind::default()))]
    pub recognizer: choices::Recognizer,
    /// Operating point: the calibrated false match rate closest to this (1e-2, 1e-3, 1e-4, and 1e-5 where the model has it).
    #[arg(long, default_value_t = DEFAULT_FMR)]
    pub fmr: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum NormalizationArg {
    #[value(name = "2d")]
    TwoD,
    #[value(name = "3dmm")]
    Morph,
    /// Both paths, one projection each, scores fused (the mean of the two cosines).
    #[value(name = "3dmm+2d")]
    Fused,
}

impl NormalizationArg {
    /// The primary path and the fused second path, if any.
    fn paths(self) -> (Normalization, Option<Normalization>) {
        match self {
            NormalizationArg::TwoD => (Normalization::TwoD, None),
            NormalizationArg::Morph => (Normalization::Morph, None),
            NormalizationArg::Fused => (Normalization::Morph, Some(Normalization::TwoD)),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PhotometricArg {
    None,
    Histeq,
    TanTriggs,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FeaturesArg {
    Pixels,
    Lbp,
    /// Pixels and LBP histograms concatenated.
    PixelsLbp,
    /// Pixels, LBP(8,1) and LBP(8,2) histograms concatenated.
    PixelsLbpMulti,
    /// Pixels, LBP(8,1), LBP(8,2) and Gabor magnitudes (3 wavelengths × 8 orientations).
    PixelsLbpGabor,
}

/// The choices that make a model, with the measured defaults.
#[derive(clap::Args, Debug, Clone)]
pub struct ModelOptions {
    /// Both paths fused by default: lower EER and lower FNMR at FMR 1e-3 in cross-validation over
    /// the training persons than either path alone (docs/recognition.md).
    #[arg(long, value_enum, default_value = "3dmm+2d")]
    pub normalization: NormalizationArg,
    #[arg(long, value_enum, default_value = "histeq")]
    pub photometric: PhotometricArg,
    /// Pixels + LBP(8,1) + LBP(8,2) histograms by default: cross-validated over the training persons
    /// (docs/recognition.md), with --pca-dims 300 and --regularization 1.
    #[arg(long, value_enum, default_value = "pixels-lbp-multi")]
    pub features: FeaturesArg,
    /// Cells per side of the LBP grid.
    #[arg(long, default_value_t = 8)]
    pub lbp_grid: usize,
    /// Do not add mirrored copies of the training photos.
    #[arg(long)]
    pub no_mirror: bool,
    /// Leave the IMM rotated views (3, 4) out of training.
    #[arg(long)]
    pub train_frontal_only: bool,
    #[arg(long, default_value_t = 100)]
    pub dims: usize,
    /// ε of the regularised S_w^{-1/2}, as a fraction of the mean within-class eigenvalue.
    #[arg(long, default_value_t = 1.0)]
    pub regularization: f64,
    /// Principal components (whitened) kept before DLDA; 0 runs DLDA on the raw features (the
    /// thesis's DLDA, measured with --regularization 0.01).
    #[arg(long, default_value_t = 300)]
    pub pca_dims: usize,
    /// Disable the elliptical mask.
    #[arg(long)]
    pub no_mask: bool,
    /// Randomly perturbed copies of each training photo (centre noise).
    #[arg(long, default_value_t = 0)]
    pub jitter: usize,
    /// Side of the square normalised crop in pixels (the canonical positions scale with it).
    #[arg(long, default_value_t = 48)]
    pub crop: usize,
    /// Scale of the centre layout about the crop centre (below 1 shows more of the head).
    #[arg(long, default_value_t = 1.0)]
    pub zoom: f32,
    /// Weight of the mouth centre in the alignment (the eyes weigh 1; 0 aligns the eyes only).
    #[arg(long, default_value_t = 1.0)]
    pub mouth_weight: f32,
    /// Cohort score normalisation against the training photos' templates (shipped in the model):
    /// `none` (raw cosines), `s-norm` (whole cohort) or `as-norm` (each face's --cohort-top-k closest).
    #[arg(long, value_enum, default_value = "none")]
    pub score_norm: ScoreNormArg,
    #[arg(long, default_value_t = 50)]
    pub cohort_top_k: usize,
    /// With `--normalization 3dmm+2d`: weight of the 2D path's cosine in the fused score (0.3: the
    /// lowest cross-validated FNMR at FMR 1e-3, the service's operating point; docs/recognition.md).
    #[arg(long, default_value_t = 0.3)]
    pub fuse_weight: f32,
    /// Face regions with a projection of their own, ensembled with the whole face on each path
    /// (comma-separated). Eyes, nose and mouth by default: lower EER and FNMR at FMR 1e-3 in
    /// cross-validation over the training persons than the whole face alone (docs/recognition.md).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "eyes,nose,mouth")]
    pub local_parts: Vec<choices::Region>,
    /// The whole face only (no local parts).
    #[arg(long, conflicts_with = "local_parts")]
    pub no_local_parts: bool,
    /// Total weight of the local parts' cosines in each path's score (shared equally).
    #[arg(long, default_value_t = 0.5)]
    pub local_weight: f32,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ScoreNormArg {
    None,
    SNorm,
    AsNorm,
}

impl ModelOptions {
    fn config(&self) -> TrainConfig {
        let mut config = TrainConfig {
            normalization: self.normalization.paths().0,
            secondary: self.normalization.paths().1,
            secondary_weight: self.fuse_weight,
            features: match self.features {
                FeaturesArg::Pixels => FeatureKind::Pixels,
                FeaturesArg::Lbp => FeatureKind::Lbp { grid: self.lbp_grid },
                FeaturesArg::PixelsLbp => FeatureKind::PixelsLbp { grid: self.lbp_grid },
                FeaturesArg::PixelsLbpMulti => FeatureKind::PixelsLbpMulti { grid: self.lbp_grid },
                FeaturesArg::PixelsLbpGabor => FeatureKind::PixelsLbpGabor { grid: self.lbp_grid },
            },
            dlda: DldaParams { max_dims: self.dims, regularization: self.regularization, pca_dims: self.pca_dims },
            mirror: !self.no_mirror,
            local_parts: if self.no_local_parts {
                Vec::new()
            } else {
                self.local_parts.iter().map(|&r| FaceRegion::from(r).region()).collect()
            },
            local_weight: self.local_weight,
            cohort_top_k: match self.score_norm {
                ScoreNormArg::None => None,
                ScoreNormArg::SNorm => Some(0),
                ScoreNormArg::AsNorm => Some(self.cohort_top_k.max(1)),
            },
            ..TrainConfig::default()
        };
        config.normalize.photometric = match self.photometric {
            PhotometricArg::None => Photometric::None,
            PhotometricArg::Histeq => Photometric::HistogramEqualization,
            PhotometricArg::TanTriggs => Photometric::TanTriggs,
        };
        config.normalize.elliptical_mask = !self.no_mask;
        config.jitter = self.jitter;
        config.normalize = NormalizeParams {
            photometric: config.normalize.photometric,
            elliptical_mask: config.normalize.elliptical_mask,
            ..NormalizeParams::layout64().scaled(self.crop).zoomed(self.zoom)
        };
        config.normalize.mouth_weight = self.mouth_weight;
        config
    }
}

#[derive(clap::Args, Debug)]
pub struct TrainDldaArgs {
    /// Labelled folders: a folder per person, or IMM names `NN-V*.jpg`.
    #[arg(long, num_args = 1.., required = true)]
    pub data: Vec<PathBuf>,
    #[arg(long, default_value = "models/dlda.bin")]
    pub out: PathBuf,
    /// Where the eye and mouth centres come from.
    #[arg(long = "keypoints", value_enum, default_value = "annotated")]
    pub centre_origin: choices::CentreOrigin,
    /// Before training, report the EER of K-fold cross-validation over the training persons only
    /// (how parameters are chosen without looking at the held-out persons).
    #[arg(long)]
    pub cv_folds: Option<usize>,
    /// Keep the aligned crops in this research cache folder between runs (e.g. `target/research-cache`;
    /// keyed by everything that shapes them: the photos, the settings, every model file the front
    /// end reads and its code version), so that parameter searches skip the front end.
    #[arg(long)]
    pub crop_cache: Option<PathBuf>,
    /// Threads the front end runs on (aligning and re-posing photos).
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Only cross-validate (with --cv-folds); do not train or write the model.
    #[arg(long)]
    pub cv_only: bool,
    /// Add 3DMM re-posed copies of the training photos: the fitted, textured face rendered at its
    /// pose plus each of these yaw offsets (degrees, comma-separated), pitch unchanged. ±20° by
    /// default: lower cross-validated EER and FNMR than none, ±12° or ±30° (docs/recognition.md).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_value = "-20,20")]
    pub repose_yaw: Vec<f32>,
    /// No re-posed copies.
    #[arg(long)]
    pub no_repose: bool,
    /// … and at each of these pitch offsets (degrees), yaw unchanged.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub repose_pitch: Vec<f32>,

    #[command(flatten)]
    pub model: ModelOptions,
}

#[derive(clap::Args, Debug)]
pub struct EvalPairsArgs {
    /// CSV whose first two columns are image paths relative to --images (header `file_x,file_y,...`).
    #[arg(long)]
    pub pairs: PathBuf,
    #[arg(long)]
    pub images: PathBuf,
    /// Which recognizer scores the pairs.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = choices::Recognizer::from(RecognizerKind::default()))]
    pub recognizer: choices::Recognizer,
}

#[derive(clap::Args, Debug)]
pub struct EvalVerifyArgs {
    /// Labelled folders (the classical recognizer; the deep one measures IMM, ORL and LFW under
    /// the shared data folder).
    #[arg(required_if_eq("recognizer", "classical"))]
    pub dirs: Vec<PathBuf>,
    /// Which recognizer to measure.
    #[arg(long, value_enum, default_value_t = choices::Recognizer::from(RecognizerKind::Classical))]
    pub recognizer: choices::Recognizer,
    /// The model to measure (default: `dlda.bin`, or `deep.bin` with `--recognizer deep`, in the
    /// models folder).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub deep: crate::cli::embed::DeepDataArgs,
    /// With `--recognizer deep`: one JSON object per line.
    #[arg(long)]
    pub json: bool,
    #[arg(long = "keypoints", value_enum, default_value = "annotated")]
    pub centre_origin: choices::CentreOrigin,
    /// Measure on every person, including those the projection was trained on (optimistic).
    #[arg(long)]
    pub all_persons: bool,
    /// Where the ROC and DET plots go.
    #[arg(long, default_value = "docs/img")]
    pub plots: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct EvalIdentifyArgs {
    /// IMM folder (its rotated views 3 and 4 are the posed probes).
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[arg(long = "keypoints", value_enum, default_value = "annotated")]
    pub centre_origin: choices::CentreOrigin,
    /// Add the view-1 photos of the training persons to the gallery as distractors (the probes
    /// stay held-out persons only).
    #[arg(long)]
    pub distractors: bool,
    /// `classical`: a 2D and a 3DMM model trained here and compared; `deep`: the deep recognizer
    /// through the service's pipeline (the IMM data under the shared folder).
    #[arg(long, value_enum, default_value_t = choices::Recognizer::from(RecognizerKind::Classical))]
    pub recognizer: choices::Recognizer,
    #[command(flatten)]
    pub model: ModelOptions,
}

pub fn run_compare(args: CompareArgs) -> anyhow::Result<ExitCode> {
    let pipeline = Pipeline::load(&PipelineConfig { recognizer: args.recognizer.into(), ..crate::config::pipeline_config() })?;
    let (a, b) = (facegate_core::imaging::open(&args.a)?, facegate_core::imaging::open(&args.b)?);
    // `b` plays a subject enrolled with one photo; both templates come from the loaded model.
    let d = facegate_service::compare(&pipeline, &a, &b, args.fmr)
        .map_err(|e| anyhow::Error::new(e.source).context([&args.a, &args.b][e.photo].display().to_string()))?;
    if args.json {
        crate::cli::print_json_line(&serde_json::json!({"score": d.score, "threshold": d.threshold, "fmr": d.fmr, "match": d.is_match}));
    } else {
        let outcome = if d.is_match { "match" } else { "no match" };
        println!("score {:.4}  threshold {:.4} (FMR {:e})  {outcome}", d.score, d.threshold, d.fmr);
    }
    Ok(ExitCode::SUCCESS)
}

pub fn run_train(args: TrainDldaArgs) -> anyhow::Result<ExitCode> {
    let config = args.model.config();
    let aligned = training_crops(&args, &config)?;
    let data: Vec<String> = args.data.iter().map(|d| d.display().to_string()).collect();
    if let Some(folds) = args.cv_folds {
        report_cross_validation(&train::cross_validate(&aligned, &config, folds)?);
        if args.cv_only {
            return Ok(ExitCode::SUCCESS);
        }
    }
    eprintln!("training DLDA on {} photos ({} of training persons)…", aligned.len(), aligned.iter().filter(|a| !a.face.held_out).count());
    let (model, report) = train::train_model(&aligned, &config, &data)?;
    model.save(&args.out)?;
    report_model(&args.out, &model, &report);
    Ok(ExitCode::SUCCESS)
}

/// The crops `train dlda` trains on: every path's, with the re-posed copies unless `--no-repose`.
fn training_crops(args: &TrainDldaArgs, config: &TrainConfig) -> anyhow::Result<Vec<AlignedFace>> {
    let photos = train::TrainingPhotos {
        data: args.data.clone(),
        centre_origin: args.centre_origin.into(),
        frontal_only: args.model.train_frontal_only,
        repose: if args.no_repose { Vec::new() } else { train::repose_offsets(&args.repose_yaw, &args.repose_pitch) },
        cache: args.crop_cache.clone(),
        threads: args.threads,
    };
    let (models, sfm) = (facegate_paths::models_dir(), facegate_paths::sfm_dir());
    train::training_crops(&photos, config, &models, &sfm, &crate::cli::Bar::default())
}

/// Prints the cross-validation folds (stderr) and their JSON line (stdout).
fn report_cross_validation(folds: &[verification::VerificationSummary]) {
    let mean = |f: &dyn Fn(&verification::VerificationSummary) -> f64| folds.iter().map(f).sum::<f64>() / folds.len() as f64;
    let (eer, f2, f3) = (mean(&|s| s.eer), mean(&|s| s.fnmr_at_fmr_1e2), mean(&|s| s.fnmr_at_fmr_1e3));
    let per: Vec<String> = folds.iter().map(|s| format!("{:.2}%", 100.0 * s.eer)).collect();
    eprintln!(
        "cross-validation over training persons: mean EER {:.2}% (folds {}), FNMR@FMR1e-2 {:.2}%, FNMR@FMR1e-3 {:.2}%",
        100.0 * eer,
        per.join(", "),
        100.0 * f2,
        100.0 * f3
    );
    crate::cli::print_json_line(
        &serde_json::json!({"cv_folds": folds, "cv_eer_mean": eer, "cv_fnmr_at_fmr_1e2_mean": f2, "cv_fnmr_at_fmr_1e3_mean": f3}),
    );
}

/// Prints what was trained (stderr: version, held-out measures, threshold tables) and its JSON line.
fn report_model(out: &Path, model: &ClassicalModel, report: &HeldOutReport) {
    let version = model.version();
    eprintln!(
        "{}: {version}, {} → {} dims, trained on {} photos of {} persons (+mirrored: {}), keypoints {}",
        out.display(),
        model.dlda.input_dims,
        model.template_dims(),
        model.provenance.train_images,
        model.provenance.train_persons.len(),
        model.provenance.mirrored,
        model.provenance.centre_source
    );
    eprintln!(
        "held-out ({} photos of {} persons): EER {:.2}%, FNMR@FMR1e-2 {:.2}%, FNMR@FMR1e-3 {:.2}%; combine max EER {:.2}%, mean EER {:.2}% → {:?}",
        model.provenance.calibration_images,
        model.provenance.calibration_persons.len(),
        100.0 * report.pairs.eer,
        100.0 * report.pairs.fnmr_at_fmr_1e2,
        100.0 * report.pairs.fnmr_at_fmr_1e3,
        100.0 * report.eer_combine_max,
        100.0 * report.eer_combine_mean,
        report.combine
    );
    let tables = std::iter::once((1, &model.calibration)).chain(model.enrolled_calibration.iter().map(|t| (t.enrolled, &t.calibration)));
    for (enrolled, calibration) in tables {
        eprintln!(
            "  {enrolled} photo(s) enrolled ({} genuine, {} impostor scores):",
            calibration.genuine_count, calibration.impostor_count
        );
        for p in &calibration.points {
            eprintln!(
                "    FMR {:e}: threshold {:.4} (observed FMR {:.5}, FNMR {:.4}{})",
                p.fmr,
                p.threshold,
                p.observed_fmr,
                p.observed_fnmr,
                if p.under_sampled { ", under-sampled: fewer than 1/FMR impostor scores" } else { "" }
            );
        }
    }
    crate::cli::print_json_line(&serde_json::json!({
        "model": out, "version": version, "normalization": model.normalization, "features": model.features,
        "photometric": model.normalize.photometric, "dims": model.template_dims(), "paths": model.paths(), "keypoints": model.provenance.centre_source,
        "held_out": report, "calibration": model.calibration.points, "enrolled_calibration": model.enrolled_calibration,
    }));
}

pub fn run_eval_pairs(args: EvalPairsArgs) -> anyhow::Result<ExitCode> {
    let file = std::fs::File::open(&args.pairs).with_context(|| args.pairs.display().to_string())?;
    let pairs = read_pairs(std::io::BufReader::new(file))?;
    let pipeline = Pipeline::load(&PipelineConfig { recognizer: args.recognizer.into(), ..crate::config::pipeline_config() })?;
    let bar = crate::cli::progress(pairs.len() as u64, "pairs");
    let template_of = |path: &Path| -> anyhow::Result<Template> {
        let photo = facegate_core::imaging::open(path)?;
        Ok(pipeline.analyze(&photo)?.template)
    };
    let stdout = std::io::stdout().lock();
    score_pairs(
        &pairs,
        &args.images,
        template_of,
        |a, b| pipeline.recognizer.score(a, std::slice::from_ref(b)),
        stdout,
        |w| {
            // A hidden bar (stderr not a terminal) drops `println`: warn directly then.
            if bar.is_hidden() { eprintln!("warning: {w}") } else { bar.println(format!("warning: {w}")) }
        },
    )?;
    bar.finish_and_clear();
    Ok(ExitCode::SUCCESS)
}

/// Enrolment set sizes measured by `eval verify` (k = 1 is the all-pairs figure again).
const ENROLLED_PHOTOS: [usize; 4] = [1, 2, 3, 5];

pub fn run_eval_verify(args: EvalVerifyArgs) -> anyhow::Result<ExitCode> {
    if RecognizerKind::from(args.recognizer) == RecognizerKind::Dlib {
        let path = args.model.clone().unwrap_or_else(|| facegate_paths::models_dir().join(facegate_vision::recognize::dlib::FILE));
        return crate::cli::embed::run_eval_verify_deep(&path, &args.deep, args.json);
    }
    if let Some(file) = RecognizerKind::from(args.recognizer).embedding_model_file() {
        let path = args.model.clone().unwrap_or_else(|| facegate_paths::models_dir().join(file));
        return crate::cli::networks::run_eval_verify_embedding(&path, &args.deep, args.json);
    }
    let model_path = args.model.clone().unwrap_or_else(|| facegate_paths::models_dir().join(facegate_vision::recognize::MODEL_FILE));
    let recognizer = ClassicalRecognizer::load_file(&model_path)?;
    let model = recognizer.model();
    let mut faces = train::list_faces(&args.dirs)?;
    if !args.all_persons {
        faces.retain(|f| f.held_out);
    }
    anyhow::ensure!(!faces.is_empty(), "no photos of held-out persons under {:?}", args.dirs);
    let paths = model.paths();
    let sfm = paths.contains(&Normalization::Morph).then(facegate_paths::sfm_dir);
    let front = FrontEnd::load(args.centre_origin.into(), &facegate_paths::models_dir(), sfm.as_deref()).with_threads(args.deep.threads);
    let aligned = train::align_paths(None, &front, &faces, &paths, &model.normalize, &crate::cli::Bar::default())?;
    let templates: Vec<(String, Template, bool)> = aligned
        .iter()
        .map(|a| Ok((a.face.label.clone(), train::template_of(&recognizer, a)?, a.face.is_rotated_view())))
        .collect::<anyhow::Result<_>>()?;
    let sources = identification::centre_sources(&aligned);
    println!(
        "model {} ({}, {:?}, {} dims, keypoints of the model: {}); measured on {} photos of {} persons, keypoints: {sources}",
        recognizer.model_version(),
        model.normalization,
        model.features,
        model.template_dims(),
        model.provenance.centre_source,
        aligned.len(),
        {
            let mut l: Vec<&str> = aligned.iter().map(|a| a.face.label.as_str()).collect();
            l.dedup();
            l.len()
        },
    );
    let all: Vec<(String, Template)> = templates.iter().map(|(l, t, _)| (l.clone(), t.clone())).collect();
    let frontal: Vec<(String, Template)> = templates.iter().filter(|(_, _, r)| !r).map(|(l, t, _)| (l.clone(), t.clone())).collect();
    let (ga, ia) = train::pair_scores(&recognizer, &all);
    let (gf, iff) = train::pair_scores(&recognizer, &frontal);
    let who = if args.all_persons { "all persons" } else { "held-out persons" };
    for (name, g, i) in [("frontal/near-frontal", &gf, &iff), ("all views", &ga, &ia)] {
        if g.is_empty() || i.is_empty() {
            println!("{name}: no genuine or no impostor pairs");
            continue;
        }
        let s = summarize(g, i);
        println!(
            "{name} ({who}): {} genuine, {} impostor pairs: EER {:.2}%, FNMR@FMR=1e-2 {:.2}%, FNMR@FMR=1e-3 {:.2}%",
            s.genuine,
            s.impostor,
            100.0 * s.eer,
            100.0 * s.fnmr_at_fmr_1e2,
            100.0 * s.fnmr_at_fmr_1e3
        );
    }
    print_enrollment_protocol(&recognizer, [("frontal/near-frontal", &frontal), ("all views", &all)], who);
    std::fs::create_dir_all(&args.plots)?;
    let (roc, det) = (args.plots.join("roc.svg"), args.plots.join("det.svg"));
    verification::write_roc_det(&roc, &det, &[("frontal/near-frontal", &gf, &iff), ("all views (incl. IMM ±30°)", &ga, &ia)])?;
    println!("wrote {} and {}", roc.display(), det.display());
    Ok(ExitCode::SUCCESS)
}

/// The service's protocol: k photos enrolled per person, the probe scored against all of them, at
/// the threshold the service uses for a subject with k templates.
fn print_enrollment_protocol(recognizer: &ClassicalRecognizer, sets: [(&str, &Vec<(String, Template)>); 2], who: &str) {
    let model = recognizer.model();
    for (name, set) in sets {
        for k in ENROLLED_PHOTOS {
            let (g, i) = train::enrollment_scores(recognizer, set, k, model.combine);
            if g.is_empty() || i.is_empty() {
                continue;
            }
            let s = summarize(&g, &i);
            // The threshold the service uses for a subject with k templates (its own table: the
            // best of k comparisons raises impostor scores too), and what it does here.
            let op = recognizer.operating_point(DEFAULT_FMR, k);
            let rate = |v: &[f32], hit: &dyn Fn(f32) -> bool| v.iter().filter(|&&x| hit(x)).count() as f64 / v.len() as f64;
            println!(
                "{name} ({who}), {k} photo(s) enrolled per person ({:?}): {} genuine, {} impostor probes: EER {:.2}%, FNMR@FMR=1e-2 {:.2}%, FNMR@FMR=1e-3 {:.2}%; at the shipped threshold {:.4} (FMR {:e}): FMR {:.3}%, FNMR {:.2}%",
                model.combine,
                s.genuine,
                s.impostor,
                100.0 * s.eer,
                100.0 * s.fnmr_at_fmr_1e2,
                100.0 * s.fnmr_at_fmr_1e3,
                op.threshold,
                op.fmr,
                100.0 * rate(&i, &|x| x >= op.threshold),
                100.0 * rate(&g, &|x| x < op.threshold)
            );
        }
    }
}

pub fn run_eval_identify(args: EvalIdentifyArgs) -> anyhow::Result<ExitCode> {
    if RecognizerKind::from(args.recognizer) == RecognizerKind::Dlib {
        return crate::cli::embed::run_eval_identify_deep(args.distractors);
    }
    let data = args.data.clone().unwrap_or_else(|| facegate_paths::shared_dir().join("data/imm"));
    let faces = train::list_faces(std::slice::from_ref(&data))?;
    let front = FrontEnd::load(args.centre_origin.into(), &facegate_paths::models_dir(), Some(&facegate_paths::sfm_dir()));
    let mut normalizations = vec![Normalization::TwoD];
    if front.face_model.is_some() {
        normalizations.push(Normalization::Morph);
    } else {
        eprintln!("3DMM unavailable: measuring 2D alignment only");
    }
    let table = identification::rank1_by_pose(
        &front,
        &faces,
        &normalizations,
        |normalization| TrainConfig { normalization, secondary: None, ..args.model.config() },
        &[data.display().to_string()],
        args.distractors,
        &crate::cli::Bar::default(),
    )?;
    let sources = &table.centre_sources;
    let gallery =
        if args.distractors { "view 1 of all persons (training persons as distractors)" } else { "view 1 of the held-out persons" };
    println!("rank-1 identification of held-out IMM persons (gallery: {gallery}; keypoints: {sources})");
    let names: Vec<String> = normalizations.iter().map(|n| format!("rank1_{n}")).collect();
    println!("pose_bin,probes,{}", names.join(","));
    for (bin, (n, hits)) in &table.bins {
        let rates: Vec<String> = hits.iter().map(|&h| format!("{:.1}%", 100.0 * h as f64 / (*n).max(1) as f64)).collect();
        println!("{bin},{n},{}", rates.join(","));
    }
    Ok(ExitCode::SUCCESS)
}
