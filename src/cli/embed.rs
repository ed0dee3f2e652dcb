//! `facegate convert embedding` (package weights → `models/embedding.bin`) and `facegate embed`
//! (the embedding of photos or of ready-made chips, one JSON line each).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use sha2::Digest;

use crate::embed::{self, CHIP_SIZE, FaceChip, weights::Provenance};
use crate::pipeline::{Pipeline, PipelineConfig, find_landmarks};

#[derive(clap::Args, Debug)]
pub struct ConvertEmbeddingArgs {
    /// dlib's `dlib_face_recognition_resnet_model_v1.dat`, as the package ships it.
    #[arg(long)]
    pub dlib: PathBuf,
    /// The registry package the file came from.
    #[arg(long, default_value = "face_recognition_models")]
    pub package: String,
    #[arg(long, default_value = "0.3.0")]
    pub package_version: String,
    /// Path of the file inside the package.
    #[arg(long, default_value = "face_recognition_models/models/dlib_face_recognition_resnet_model_v1.dat")]
    pub package_file: String,
    #[arg(long, default_value = "CC0-1.0")]
    pub licence: String,
    #[arg(long, default_value = "models/embedding.bin")]
    pub out: PathBuf,
}

pub fn run_convert(args: ConvertEmbeddingArgs) -> anyhow::Result<ExitCode> {
    let bytes = std::fs::read(&args.dlib).with_context(|| args.dlib.display().to_string())?;
    let sha256 = sha2::Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect::<String>();
    let provenance =
        Provenance { package: args.package, version: args.package_version, file: args.package_file, sha256, licence: args.licence };
    let file = embed::convert_dlib(&bytes, provenance).with_context(|| args.dlib.display().to_string())?;
    // Build it once: a file that does not make a network is refused before it is written.
    embed::Embedder::new(&file)?;
    crate::config::write_model(&args.out, &file).map_err(anyhow::Error::msg)?;
    eprintln!(
        "{}: {} layers, {} parameters, from {} {} (sha256 {})",
        args.out.display(),
        file.layers.len(),
        file.parameter_count(),
        file.provenance.package,
        file.provenance.version,
        file.provenance.sha256
    );
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EmbedArgs {
    /// Photos (or, with --chip, aligned 150×150 chips).
    pub images: Vec<PathBuf>,
    /// The images are already aligned chips: embed them as they are.
    #[arg(long)]
    pub chip: bool,
    /// Write each photo's chip as PNG into this folder (same file stem).
    #[arg(long)]
    pub save_chips: Option<PathBuf>,
    /// One pass on the chip alone instead of the mirror-averaged embedding.
    #[arg(long)]
    pub single: bool,
}

pub fn run_embed(args: EmbedArgs) -> anyhow::Result<ExitCode> {
    let config = PipelineConfig::default();
    let embedder = embed::load(&config.models_dir)?;
    let pipeline = if args.chip { None } else { Some(Pipeline::load(&config)?) };
    if let Some(dir) = &args.save_chips {
        std::fs::create_dir_all(dir)?;
    }
    for path in &args.images {
        let cpu_start = crate::eval::thread_cpu_ns();
        let chip = match &pipeline {
            None => {
                let img = image::open(path).with_context(|| path.display().to_string())?.into_rgb8();
                FaceChip::from_image(&img)
                    .filter(|c| c.size == CHIP_SIZE)
                    .with_context(|| format!("{}: a chip must be {CHIP_SIZE}×{CHIP_SIZE}", path.display()))?
            }
            Some(p) => {
                let photo = crate::imaging::open(path).with_context(|| path.display().to_string())?;
                let Some(face) = p.detector.detect(&photo.gray).first().copied() else {
                    crate::cli::print_json_line(&serde_json::json!({"image": path.display().to_string(), "embedding": null}));
                    continue;
                };
                let lm = find_landmarks(&p.landmarker, p.asm3d.as_ref(), &photo.gray, &face.rect);
                let k = lm.keypoints;
                let t = embed::chip::chip_to_photo(CHIP_SIZE, k.left_eye, k.right_eye, k.mouth);
                embed::chip::extract(&photo.rgb, &t, CHIP_SIZE)
            }
        };
        if let Some(dir) = &args.save_chips {
            let stem = path.file_stem().unwrap_or_default().to_string_lossy();
            chip.to_image().save(dir.join(format!("{stem}.png")))?;
        }
        // What the deep recognizer computes: the mean of the chip's and its mirror's embeddings.
        let mut ws = embedder.take_workspace();
        let e = if args.single { embedder.forward(&chip, &mut ws) } else { embedder.embed_mirrored(&chip, &mut ws) };
        embedder.give_back(ws);
        // CPU time of this photo's whole path (decode, detection, landmarks, chip, network).
        let cpu_ms = cpu_start.zip(crate::eval::thread_cpu_ns()).map(|(a, b)| (b - a) as f64 / 1e6);
        crate::cli::print_json_line(&serde_json::json!({"image": path.display().to_string(), "embedding": e.0.to_vec(), "cpu_ms": cpu_ms}));
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalDeepArgs {
    /// Embeddings cache (rebuilt when the front end's models change).
    #[arg(long, default_value = "target/deep-embeddings.bin")]
    pub cache: PathBuf,
    /// Cross-validation folds over the training persons.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Stop after the cross-validation.
    #[arg(long)]
    pub cv_only: bool,
}

/// The deep embedding's scoring variants: cross-validation over the training persons, then the
/// held-out persons of each set, for the photo's chip and the 3DMM frontal rendering's chip.
pub fn run_eval_deep(args: EvalDeepArgs) -> anyhow::Result<ExitCode> {
    use crate::eval::deep::{self, Scoring, Set, Split};
    use crate::recognize::DldaParams;
    let config = PipelineConfig::default();
    let samples = deep::list_samples(&crate::config::shared_dir())?;
    let embeddings = cached_embeddings(&config, &samples, &args.cache, args.threads)?;
    for set in [Set::Imm, Set::Orl, Set::Lfw] {
        let all = samples.iter().zip(&embeddings).filter(|(s, _)| s.set == set);
        let (n, found, frontal) =
            all.fold((0, 0, 0), |(n, f, fr), (_, e)| (n + 1, f + e.photo.is_some() as usize, fr + e.frontal.is_some() as usize));
        println!("{set:?}: {n} photos, face found in {found}, frontal rendering for {frontal}");
    }
    let pick = |frontal: bool, f: &dyn Fn(&deep::Sample) -> bool| -> Vec<(&str, &[f32])> {
        samples
            .iter()
            .zip(&embeddings)
            .filter(|(s, _)| f(s))
            .filter_map(|(s, e)| if frontal { e.frontal.as_deref() } else { e.photo.as_deref() }.map(|v| (s.label.as_str(), v)))
            .collect()
    };
    let line = |name: &str, s: &crate::eval::verification::VerificationSummary| {
        println!(
            "  {name:<44} EER {:>6.2}%  FNMR@1e-2 {:>6.2}%  FNMR@1e-3 {:>6.2}%  ({} genuine, {} impostor)",
            100.0 * s.eer,
            100.0 * s.fnmr_at_fmr_1e2,
            100.0 * s.fnmr_at_fmr_1e3,
            s.genuine,
            s.impostor
        )
    };
    let variants: Vec<(String, DldaParams)> =
        [(127, 0, 0.01), (100, 0, 0.01), (64, 0, 0.01), (127, 0, 0.1), (127, 0, 1.0), (127, 128, 0.01)]
            .iter()
            .map(|&(max_dims, pca_dims, regularization)| {
                (format!("DLDA dims {max_dims} pca {pca_dims} eps {regularization}"), DldaParams { max_dims, regularization, pca_dims })
            })
            .collect();
    let train = pick(false, &|s| s.split == Split::Train);
    println!("{}-fold CV over the training persons ({} photos), photo chips:", args.folds, train.len());
    line("cosine", &deep::cross_validate(&train, args.folds, None, 0.0));
    for (name, p) in &variants {
        line(name, &deep::cross_validate(&train, args.folds, Some(p), 0.0));
    }
    for w in [0.5f32, 0.7, 0.85] {
        for (name, p) in variants.iter().take(1).chain(variants.iter().skip(3).take(2)) {
            line(&format!("{w} cosine + {:.2} {name}", 1.0 - w), &deep::cross_validate(&train, args.folds, Some(p), w));
        }
    }
    if args.cv_only {
        return Ok(ExitCode::SUCCESS);
    }
    let held_out_sets: [(&str, Box<dyn Fn(&deep::Sample) -> bool>); 6] = [
        ("LFW test persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Test)),
        ("IMM held-out, all views", Box::new(|s| s.set == Set::Imm && s.split == Split::Test)),
        ("IMM held-out, frontal views 1-2", Box::new(|s| s.set == Set::Imm && s.split == Split::Test && matches!(s.view, Some(1 | 2)))),
        (
            "IMM held-out, views 1 + 3-4 (turned)",
            Box::new(|s| s.set == Set::Imm && s.split == Split::Test && matches!(s.view, Some(1 | 3 | 4))),
        ),
        ("ORL held-out", Box::new(|s| s.set == Set::Orl && s.split == Split::Test)),
        ("LFW calibration persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Calibration)),
    ];
    for frontal in [false, true] {
        let train = pick(frontal, &|s| s.split == Split::Train);
        let scorings: Vec<(String, Scoring)> = [("euclidean".to_string(), Scoring::Euclidean), ("cosine".to_string(), Scoring::Cosine)]
            .into_iter()
            .chain(variants.iter().filter_map(|(n, p)| deep::train_dlda(&train, p).ok().map(|d| (n.clone(), Scoring::Dlda(d)))))
            .collect();
        println!(
            "held out, {} chips (projections trained on {} training photos):",
            if frontal { "3DMM frontal" } else { "photo" },
            train.len()
        );
        for (set_name, filter) in &held_out_sets {
            let items = pick(frontal, filter.as_ref());
            println!(" {set_name} ({} photos)", items.len());
            for (name, scoring) in &scorings {
                line(name, &deep::pair_summary(&items, scoring));
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalDeepAlignArgs {
    #[arg(long, default_value = "target/deep-keypoints.json")]
    pub cache: PathBuf,
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// Chip placement variants (zoom, vertical shift, mirror averaging) by cross-validation over the
/// training persons, raw cosine; the best and the standard one then on the LFW test persons.
pub fn run_eval_deep_align(args: EvalDeepAlignArgs) -> anyhow::Result<ExitCode> {
    use crate::eval::deep::{self, ChipVariant, Scoring, Set, Split};
    let config = PipelineConfig::default();
    let samples = deep::list_samples(&crate::config::shared_dir())?;
    let key = deep::models_key(&config.models_dir);
    let cached: Option<(String, Vec<Option<[[f32; 2]; 3]>>)> =
        std::fs::read(&args.cache).ok().and_then(|b| serde_json::from_slice(&b).ok());
    let points = match cached {
        Some((k, p)) if k == key && p.len() == samples.len() => p,
        _ => {
            let pipeline = Pipeline::load(&config)?;
            let p = deep::key_points(&pipeline, &samples, args.threads, &|| {});
            std::fs::write(&args.cache, serde_json::to_vec(&(&key, &p))?)?;
            p
        }
    };
    let embedder = embed::load(&config.models_dir)?;
    let load = |f: &dyn Fn(&deep::Sample) -> bool| -> anyhow::Result<Vec<(usize, image::RgbImage, [[f32; 2]; 3])>> {
        let mut v = Vec::new();
        for (i, (s, k)) in samples.iter().zip(&points).enumerate() {
            if let (true, Some(k)) = (f(s), k) {
                v.push((i, crate::imaging::open(&s.image)?.rgb, *k));
            }
        }
        Ok(v)
    };
    let run = |photos: &[(usize, image::RgbImage, [[f32; 2]; 3])], v: ChipVariant, cv: bool| {
        let refs: Vec<(usize, &image::RgbImage, [[f32; 2]; 3])> = photos.iter().map(|(i, img, k)| (*i, img, *k)).collect();
        let e = deep::embed_variant(&embedder, &refs, v, args.threads);
        let items: Vec<(&str, &[f32])> = photos.iter().zip(&e).map(|((i, _, _), e)| (samples[*i].label.as_str(), e.as_slice())).collect();
        if cv { deep::cross_validate(&items, args.folds, None, 0.0) } else { deep::pair_summary(&items, &Scoring::Cosine) }
    };
    let show = |name: String, s: &crate::eval::verification::VerificationSummary| {
        println!(
            "  {name:<36} EER {:>5.2}%  FNMR@1e-2 {:>5.2}%  FNMR@1e-3 {:>5.2}%",
            100.0 * s.eer,
            100.0 * s.fnmr_at_fmr_1e2,
            100.0 * s.fnmr_at_fmr_1e3
        )
    };
    let train = load(&|s| s.split == Split::Train)?;
    println!("{}-fold CV over the training persons ({} photos), cosine:", args.folds, train.len());
    let mut best = (f64::INFINITY, ChipVariant { scale: 1.0, dy: 0.0, flip: false });
    for flip in [false, true] {
        for scale in [0.92f32, 1.0, 1.08] {
            for dy in [-4.0f32, 0.0, 4.0] {
                let v = ChipVariant { scale, dy, flip };
                let s = run(&train, v, true);
                show(format!("scale {scale} dy {dy} flip {flip}"), &s);
                let cost = s.eer + s.fnmr_at_fmr_1e3;
                if cost < best.0 {
                    best = (cost, v);
                }
            }
        }
    }
    drop(train);
    let test = load(&|s| s.set == Set::Lfw && s.split == Split::Test)?;
    println!("LFW test persons ({} photos):", test.len());
    for v in [ChipVariant { scale: 1.0, dy: 0.0, flip: false }, ChipVariant { flip: true, ..best.1 }, best.1] {
        show(format!("scale {} dy {} flip {}", v.scale, v.dy, v.flip), &run(&test, v, false));
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ProjectionArg {
    /// The embedding's own cosine (chosen by cross-validation: `facegate eval deep`).
    None,
    /// Direct LDA over the embeddings of the training persons.
    Dlda,
}

#[derive(clap::Args, Debug)]
pub struct TrainDeepArgs {
    #[arg(long, default_value = "models/deep.bin")]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value_t = ProjectionArg::None)]
    pub projection: ProjectionArg,
    /// Embeddings cache (rebuilt when the front end's models change).
    #[arg(long, default_value = "target/deep-embeddings.bin")]
    pub cache: PathBuf,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// The deep recognizer's model: projection (none by default), thresholds calibrated per enrolment
/// size on the calibration persons (LFW's calibration split and the IMM/ORL held-out persons).
pub fn run_train_deep(args: TrainDeepArgs) -> anyhow::Result<ExitCode> {
    use crate::eval::deep::{self, Set, Split};
    use crate::recognize::deep::{ChipSource, DeepModel, DeepProvenance, FORMAT};
    let config = PipelineConfig::default();
    let samples = deep::list_samples(&crate::config::shared_dir())?;
    let embeddings = cached_embeddings(&config, &samples, &args.cache, args.threads)?;
    let network = embed::read_file(&config.models_dir.join(embed::weights::FILE))?;
    let items = |f: &dyn Fn(&deep::Sample) -> bool| -> Vec<(&str, &[f32])> {
        samples
            .iter()
            .zip(&embeddings)
            .filter(|(s, _)| f(s))
            .filter_map(|(s, e)| e.photo.as_deref().map(|v| (s.label.as_str(), v)))
            .collect()
    };
    let train = items(&|s| s.split == Split::Train);
    let projection = match args.projection {
        ProjectionArg::None => None,
        ProjectionArg::Dlda => {
            let params = crate::recognize::DldaParams { max_dims: 127, regularization: 0.1, pca_dims: 0 };
            Some(deep::train_dlda(&train, &params)?)
        }
    };
    let is_calibration = |s: &deep::Sample| match s.set {
        Set::Lfw => s.split == Split::Calibration,
        _ => s.split == Split::Test,
    };
    let version = DeepModel::version_of(projection.as_ref(), ChipSource::Photo, &network.provenance.sha256);
    let mut model = DeepModel {
        format: FORMAT,
        version,
        network_sha256: network.provenance.sha256.clone(),
        chip_source: ChipSource::Photo,
        projection,
        calibration: crate::recognize::Calibration::from_scores(&[], &[], &[], ""),
        enrolled_calibration: Vec::new(),
        provenance: DeepProvenance {
            trained_on: match args.projection {
                ProjectionArg::None => "no projection (the embedding's cosine)".to_string(),
                ProjectionArg::Dlda => format!("DLDA on {} photos of the training persons (IMM, ORL, LFW train split)", train.len()),
            },
            command: format!("facegate train deep --projection {:?}", args.projection).to_lowercase(),
        },
    };
    let calibration: Vec<(&str, Vec<f32>)> = items(&is_calibration)
        .into_iter()
        .map(|(l, e)| (l, model.template(&embed::Embedding(e.try_into().expect("128 values"))).vector))
        .collect();
    let source =
        format!("{} photos: LFW calibration persons, IMM and ORL held-out persons (1, 2, 3, 5, 10, 15, 20, 25, 30)", calibration.len());
    (model.calibration, model.enrolled_calibration) = deep::calibrate(&calibration, &source);
    crate::config::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    println!("{}: {} ({})", args.out.display(), model.version, model.provenance.trained_on);
    for (k, cal) in std::iter::once((1, &model.calibration)).chain(model.enrolled_calibration.iter().map(|t| (t.enrolled, &t.calibration)))
    {
        let points: Vec<String> = cal
            .points
            .iter()
            .map(|p| {
                format!(
                    "FMR {:e}: {:.4} (FNMR {:.2}%{})",
                    p.fmr,
                    p.threshold,
                    100.0 * p.observed_fnmr,
                    if p.under_sampled { ", under-sampled" } else { "" }
                )
            })
            .collect();
        println!("  {k} enrolled: {} ({} genuine, {} impostor)", points.join("; "), cal.genuine_count, cal.impostor_count);
    }
    Ok(ExitCode::SUCCESS)
}

/// The mirror-averaged embeddings of `samples` through the service's front end, from the cache
/// when it holds them for the current models.
fn cached_embeddings(
    config: &PipelineConfig,
    samples: &[crate::eval::deep::Sample],
    cache: &std::path::Path,
    threads: usize,
) -> anyhow::Result<Vec<crate::eval::deep::PhotoEmbeddings>> {
    use crate::eval::deep;
    let key = deep::models_key(&config.models_dir);
    if let Some(e) = deep::read_cache(cache, &key, samples) {
        return Ok(e);
    }
    let pipeline = Pipeline::load(config)?;
    let embedder = embed::load(&config.models_dir)?;
    let bar = crate::cli::progress(samples.len() as u64, "embed");
    let e = deep::embed_samples(&pipeline, &embedder, samples, threads, &|| bar.inc(1));
    bar.finish();
    deep::write_cache(cache, &key, samples, &e)?;
    Ok(e)
}

#[derive(clap::Args, Debug)]
pub struct EvalVerifyDeepArgs {
    /// The deep model to measure.
    #[arg(long, default_value = "models/deep.bin")]
    pub model: PathBuf,
    #[arg(long, default_value = "target/deep-embeddings.bin")]
    pub cache: PathBuf,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    #[arg(long)]
    pub json: bool,
}

/// The deep recognizer on the held-out persons: EER and FNMR at FMR 1e-2 / 1e-3 (threshold-free),
/// and FNMR / FMR at the model's own calibrated FMR-1e-3 threshold.
pub fn run_eval_verify_deep(args: EvalVerifyDeepArgs) -> anyhow::Result<ExitCode> {
    let config = PipelineConfig::default();
    let model = crate::recognize::deep::DeepModel::load(&args.model)?;
    let samples = crate::eval::deep::list_samples(&crate::config::shared_dir())?;
    let embeddings = cached_embeddings(&config, &samples, &args.cache, args.threads)?;
    println!("{} ({})", model.version, model.provenance.trained_on);
    for l in crate::eval::deep::held_out_report(&model, &samples, &embeddings) {
        if args.json {
            crate::cli::print_json_line(&serde_json::to_value(&l)?);
            continue;
        }
        println!(
            "  {:<32} {} enrolled, {:>4} photos: EER {:>5.2}%  FNMR@1e-2 {:>5.2}%  FNMR@1e-3 {:>5.2}%  | at the calibrated 1e-3 threshold: FNMR {:>5.2}%, FMR {:.2e}  ({} genuine, {} impostor)",
            l.set,
            l.enrolled,
            l.photos,
            100.0 * l.summary.eer,
            100.0 * l.summary.fnmr_at_fmr_1e2,
            100.0 * l.summary.fnmr_at_fmr_1e3,
            100.0 * l.fnmr_at_threshold,
            l.fmr_at_threshold,
            l.summary.genuine,
            l.summary.impostor
        );
    }
    Ok(ExitCode::SUCCESS)
}
