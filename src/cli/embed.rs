//! The deep recognizer's commands: `convert embedding` (package weights → `models/embedding.bin`),
//! `embed` (embeddings of photos or chips, one JSON line each), `train deep`, and the research
//! measurements `eval deep` (scoring variants), `eval deep-align` (chip placement) and the deep
//! branch of `eval verify` / `eval identify`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use sha2::Digest;

use facegate_nn::FaceChip;
use facegate_nn::weights::{self, Provenance};
use facegate_research::dataset::Split;
use facegate_research::eval::deep::{self as deep_eval, ChipVariant, Scoring};
use facegate_research::eval::verification::VerificationSummary;
use facegate_research::train_deep::{self, PhotoEmbeddings, Sample, Set};
use facegate_vision::embed::{self, CHIP_SIZE};
use facegate_vision::pipeline::{FaceFinder, Pipeline};
use facegate_vision::recognize::dlib::{DeepProvenance, DlibModel};

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
    let file = facegate_research::convert::convert_dlib(&bytes, provenance).with_context(|| args.dlib.display().to_string())?;
    // Build it once: a file that does not make a network is refused before it is written.
    facegate_nn::Embedder::new(&file)?;
    facegate_core::model_file::write_model(&args.out, &file).map_err(anyhow::Error::msg)?;
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

/// The embedding of each image as the deep recognizer computes it (largest face, the service's
/// landmarks, chip, mirror-averaged network output), with the CPU time of the photo's whole path.
pub fn run_embed(args: EmbedArgs) -> anyhow::Result<ExitCode> {
    let models = facegate_paths::models_dir();
    let network = embed::load(&models)?;
    let finder = if args.chip { None } else { Some(FaceFinder::load(&models)?) };
    if let Some(dir) = &args.save_chips {
        std::fs::create_dir_all(dir)?;
    }
    let mut ws = network.take_workspace();
    for path in &args.images {
        let cpu_start = facegate_research::eval::thread_cpu_ns();
        let chip = match &finder {
            None => {
                let img = image::open(path).with_context(|| path.display().to_string())?.into_rgb8();
                FaceChip::from_image(&img)
                    .filter(|c| c.size == CHIP_SIZE)
                    .with_context(|| format!("{}: a chip must be {CHIP_SIZE}×{CHIP_SIZE}", path.display()))?
            }
            Some(finder) => {
                let photo = facegate_core::imaging::open(path).with_context(|| path.display().to_string())?;
                let Ok(located) = finder.locate(&photo.gray) else {
                    crate::cli::print_json_line(&serde_json::json!({"image": path.display().to_string(), "embedding": null}));
                    continue;
                };
                embed::face_chip(&photo.rgb, &located.landmarks.centres)
            }
        };
        let e = if args.single { network.forward(&chip, &mut ws) } else { network.embed_mirrored(&chip, &mut ws) };
        let cpu_ms = cpu_start.zip(facegate_research::eval::thread_cpu_ns()).map(|(a, b)| (b - a) as f64 / 1e6);
        if let Some(dir) = &args.save_chips {
            let stem = path.file_stem().unwrap_or_default().to_string_lossy();
            chip.to_image().save(dir.join(format!("{stem}.png")))?;
        }
        crate::cli::print_json_line(&serde_json::json!({"image": path.display().to_string(), "embedding": e.0.to_vec(), "cpu_ms": cpu_ms}));
    }
    Ok(ExitCode::SUCCESS)
}

/// Options every deep research command shares.
#[derive(clap::Args, Debug)]
pub struct DeepDataArgs {
    /// The research cache folder, where the embeddings are kept (under a key of the front end's
    /// model files, its code version and the photos: made again when any changes).
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    /// Threads the front end runs on (embedding photos; aligning them for `eval verify`).
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// IMM, ORL and LFW from the shared data, with the embeddings of every photo (cached).
fn samples_and_embeddings(data: &DeepDataArgs) -> anyhow::Result<(Vec<Sample>, Vec<PhotoEmbeddings>)> {
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let (models, sfm) = (facegate_paths::models_dir(), facegate_paths::sfm_dir());
    let e = train_deep::embeddings(&data.cache, &models, &sfm, &samples, data.threads, &crate::cli::Bar::default())?;
    Ok((samples, e))
}

/// (label, embedding) of the samples `f` keeps, from the photo's chip or the frontal rendering's.
fn pick<'a>(
    samples: &'a [Sample],
    embeddings: &'a [PhotoEmbeddings],
    frontal: bool,
    f: &dyn Fn(&Sample) -> bool,
) -> Vec<(&'a str, &'a [f32])> {
    samples
        .iter()
        .zip(embeddings)
        .filter(|(s, _)| f(s))
        .filter_map(|(s, e)| if frontal { e.frontal.as_deref() } else { e.photo.as_deref() }.map(|v| (s.label.as_str(), v)))
        .collect()
}

fn summary_line(name: &str, s: &VerificationSummary) {
    println!(
        "  {name:<46} EER {:>6.2}%  FNMR@1e-2 {:>6.2}%  FNMR@1e-3 {:>6.2}%  ({} genuine, {} impostor)",
        100.0 * s.eer,
        100.0 * s.fnmr_at_fmr_1e2,
        100.0 * s.fnmr_at_fmr_1e3,
        s.genuine,
        s.impostor
    );
}

#[derive(clap::Args, Debug)]
pub struct EvalDeepArgs {
    #[command(flatten)]
    pub data: DeepDataArgs,
    /// Cross-validation folds over the training persons.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    /// Stop after the cross-validation.
    #[arg(long)]
    pub cv_only: bool,
    /// Also measure rank-1 on IMM held-out faces re-posed by the 3DMM to ±30° and ±45°, the photo's
    /// chip against the 3DMM frontal rendering's.
    #[arg(long)]
    pub renders: bool,
    /// Also fuse with the classical recognizer's score (its templates of LFW's training and test
    /// persons and the IMM/ORL held-out persons; the weight chosen on LFW's training persons, which
    /// the classical model never saw).
    #[arg(long)]
    pub fusion: bool,
}

/// The deep embedding's scoring variants: cross-validation over the training persons, then the
/// held-out persons of each set, for the photo's chip and the 3DMM frontal rendering's chip.
pub fn run_eval_deep(args: EvalDeepArgs) -> anyhow::Result<ExitCode> {
    use facegate_research::dlda::DldaParams;
    let (samples, embeddings) = samples_and_embeddings(&args.data)?;
    for set in [Set::Imm, Set::Orl, Set::Lfw] {
        let all = samples.iter().zip(&embeddings).filter(|(s, _)| s.set == set);
        let (n, found, frontal) =
            all.fold((0, 0, 0), |(n, f, fr), (_, e)| (n + 1, f + e.photo.is_some() as usize, fr + e.frontal.is_some() as usize));
        println!("{set:?}: {n} photos, face found in {found}, frontal rendering for {frontal}");
    }
    if args.renders {
        use facegate_research::train_dlda::{CentreOrigin, FrontEnd, list_faces};
        let models = facegate_paths::models_dir();
        let front = FrontEnd::load(CentreOrigin::Pipeline, &models, Some(&facegate_paths::sfm_dir()));
        let imm = list_faces(&[facegate_paths::shared_dir().join("data/imm")])?;
        let table = deep_eval::turned_render_rank1(&front, &embed::load(&models)?, &imm, &[-45.0, -30.0, 30.0, 45.0])?;
        println!("rank-1 of 3DMM renders of the IMM held-out view 1 (gallery: view 2 of {} persons):", table.gallery);
        for (yaw, direct, frontal) in &table.rows {
            for (input, r) in [("photo chip", direct), ("3DMM frontal rendering chip", frontal)] {
                println!(
                    "  yaw {yaw:+.0}°, {input:<28} rank-1 {}/{}, mean genuine cosine {:.4}, smallest margin over the best impostor {:+.4}",
                    r.rank1,
                    r.probes,
                    r.mean_genuine(),
                    r.min_margin
                );
            }
        }
    }
    if args.fusion {
        fusion_report(&samples, &embeddings, args.data.threads)?;
    }
    let variants: Vec<(String, DldaParams)> = [(127, 0.01), (64, 0.01), (127, 0.1), (127, 1.0)]
        .iter()
        .map(|&(max_dims, regularization)| {
            (format!("DLDA dims {max_dims} eps {regularization}"), DldaParams { max_dims, regularization, pca_dims: 0 })
        })
        .collect();
    let train = pick(&samples, &embeddings, false, &|s| s.split == Split::Train);
    println!("{}-fold CV over the training persons ({} photos), photo chips:", args.folds, train.len());
    summary_line("cosine", &deep_eval::cross_validate(&train, args.folds, None, 0.0));
    for (name, p) in &variants {
        summary_line(name, &deep_eval::cross_validate(&train, args.folds, Some(p), 0.0));
    }
    for w in [0.5f32, 0.85] {
        for (name, p) in &variants[2..] {
            summary_line(&format!("{w} cosine + {:.2} {name}", 1.0 - w), &deep_eval::cross_validate(&train, args.folds, Some(p), w));
        }
    }
    if args.cv_only {
        return Ok(ExitCode::SUCCESS);
    }
    let held_out_sets: [(&str, Box<dyn Fn(&Sample) -> bool>); 5] = [
        ("LFW test persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Test)),
        ("IMM held-out, all views", Box::new(|s| s.set == Set::Imm && s.split == Split::Test)),
        (
            "IMM held-out, views 1 + 3-4 (turned)",
            Box::new(|s| s.set == Set::Imm && s.split == Split::Test && matches!(s.view, Some(1 | 3 | 4))),
        ),
        ("ORL held-out", Box::new(|s| s.set == Set::Orl && s.split == Split::Test)),
        ("LFW calibration persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Calibration)),
    ];
    for frontal in [false, true] {
        let train = pick(&samples, &embeddings, frontal, &|s| s.split == Split::Train);
        let scorings: Vec<(String, Scoring)> = [("euclidean".to_string(), Scoring::Euclidean), ("cosine".to_string(), Scoring::Cosine)]
            .into_iter()
            .chain(variants.iter().filter_map(|(n, p)| deep_eval::train_dlda(&train, p).ok().map(|d| (n.clone(), Scoring::Dlda(d)))))
            .collect();
        let source = if frontal { "3DMM frontal rendering" } else { "photo" };
        println!("held out, {source} chips (projections trained on {} training photos):", train.len());
        for (set_name, filter) in &held_out_sets {
            let items = pick(&samples, &embeddings, frontal, filter.as_ref());
            println!(" {set_name} ({} photos)", items.len());
            for (name, scoring) in &scorings {
                summary_line(name, &deep_eval::pair_summary(&items, scoring));
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Score-level fusion of the deep and the classical recognizers: z-normalised by each one's
/// impostor scores, the weight of the deep score chosen on LFW's training persons, then measured
/// on the held-out sets.
fn fusion_report(samples: &[Sample], embeddings: &[PhotoEmbeddings], threads: usize) -> anyhow::Result<()> {
    use facegate_vision::recognize::RecognizerKind;
    let config = facegate_vision::pipeline::PipelineConfig { recognizer: RecognizerKind::Classical, ..crate::config::pipeline_config() };
    let classical = Pipeline::load(&config)?;
    let wanted = |s: &Sample| s.split == Split::Test || (s.set == Set::Lfw && s.split == Split::Train);
    let templates = deep_eval::classical_templates(&classical, samples, &wanted, threads, &crate::cli::Bar::default());
    let items = |f: &dyn Fn(&Sample) -> bool| -> Vec<deep_eval::FusionItem> {
        samples
            .iter()
            .zip(embeddings)
            .zip(&templates)
            .filter(|((s, _), _)| f(s))
            .filter_map(|((s, e), c)| {
                let d = e.photo.as_ref()?;
                let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
                Some((s.label.as_str(), d.iter().map(|v| v / n).collect(), c.as_deref()?))
            })
            .collect()
    };
    let train = items(&|s| s.set == Set::Lfw && s.split == Split::Train);
    let stats = deep_eval::impostor_stats(&train);
    println!("fusion with the classical score (z-normalised on LFW's {} training photos):", train.len());
    let weights = [1.0, 0.95, 0.9, 0.8, 0.7, 0.5, 0.0];
    let mut best = (f64::INFINITY, 1.0);
    for w in weights {
        let s = deep_eval::fused_summary(&train, stats, w);
        summary_line(&format!("LFW training persons, deep weight {w}"), &s);
        if s.eer + s.fnmr_at_fmr_1e3 < best.0 {
            best = (s.eer + s.fnmr_at_fmr_1e3, w);
        }
    }
    println!(" chosen deep weight {}; held out:", best.1);
    for (name, f) in [
        ("LFW test persons", Box::new(|s: &Sample| s.set == Set::Lfw && s.split == Split::Test) as Box<dyn Fn(&Sample) -> bool>),
        ("IMM + ORL held-out", Box::new(|s: &Sample| s.set != Set::Lfw && s.split == Split::Test)),
        ("ORL held-out", Box::new(|s: &Sample| s.set == Set::Orl && s.split == Split::Test)),
    ] {
        let held = items(f.as_ref());
        for w in [1.0, best.1, 0.0] {
            summary_line(&format!("{name}, deep weight {w}"), &deep_eval::fused_summary(&held, stats, w));
        }
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct EvalDeepAlignArgs {
    /// The research cache folder, where the centres are kept.
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// Chip placement variants (zoom, vertical shift, mirror averaging) by cross-validation over the
/// training persons, raw cosine; the standard and the best placements then on the LFW test persons.
pub fn run_eval_deep_align(args: EvalDeepAlignArgs) -> anyhow::Result<ExitCode> {
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let models = facegate_paths::models_dir();
    let points = deep_eval::cached_centres(&args.cache, &models, &samples, args.threads, &crate::cli::Bar::default())?;
    let network = embed::load(&models)?;
    type Loaded = Vec<(usize, image::RgbImage, [[f32; 2]; 3])>;
    let load = |f: &dyn Fn(&Sample) -> bool| -> anyhow::Result<Loaded> {
        let mut v = Vec::new();
        for (i, (s, k)) in samples.iter().zip(&points).enumerate() {
            if let (true, Some(k)) = (f(s), k) {
                v.push((i, facegate_core::imaging::open(&s.image)?.rgb, *k));
            }
        }
        Ok(v)
    };
    let run = |photos: &Loaded, v: ChipVariant, cv: bool| {
        let refs: Vec<(&image::RgbImage, [[f32; 2]; 3])> = photos.iter().map(|(_, img, k)| (img, *k)).collect();
        let e = deep_eval::embed_variant(&network, &refs, v, args.threads);
        let items: Vec<(&str, &[f32])> = photos.iter().zip(&e).map(|((i, _, _), e)| (samples[*i].label.as_str(), e.as_slice())).collect();
        if cv { deep_eval::cross_validate(&items, args.folds, None, 0.0) } else { deep_eval::pair_summary(&items, &Scoring::Cosine) }
    };
    let train = load(&|s| s.split == Split::Train)?;
    println!("{}-fold CV over the training persons ({} photos), cosine:", args.folds, train.len());
    let standard = ChipVariant { scale: 1.0, dy: 0.0, flip: false };
    let mut best = (f64::INFINITY, standard);
    for flip in [false, true] {
        for scale in [0.92f32, 1.0, 1.08] {
            for dy in [-4.0f32, 0.0, 4.0] {
                let v = ChipVariant { scale, dy, flip };
                let s = run(&train, v, true);
                summary_line(&format!("scale {scale} dy {dy} mirror-averaged {flip}"), &s);
                if s.eer + s.fnmr_at_fmr_1e3 < best.0 {
                    best = (s.eer + s.fnmr_at_fmr_1e3, v);
                }
            }
        }
    }
    drop(train);
    let test = load(&|s| s.set == Set::Lfw && s.split == Split::Test)?;
    println!("LFW test persons ({} photos):", test.len());
    for v in [standard, best.1] {
        summary_line(&format!("scale {} dy {} mirror-averaged {}", v.scale, v.dy, v.flip), &run(&test, v, false));
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
    #[command(flatten)]
    pub data: DeepDataArgs,
}

/// The deep recognizer's model: projection (none by default), thresholds calibrated per enrolment
/// size on the calibration persons (LFW's calibration split and the IMM/ORL held-out persons).
pub fn run_train_deep(args: TrainDeepArgs) -> anyhow::Result<ExitCode> {
    let (samples, embeddings) = samples_and_embeddings(&args.data)?;
    let network = embed::read_file(&facegate_paths::models_dir().join(weights::FILE))?;
    let train = pick(&samples, &embeddings, false, &|s| s.split == Split::Train);
    let (projection, trained_on) = match args.projection {
        ProjectionArg::None => (None, "no projection (the embedding's cosine)".to_string()),
        ProjectionArg::Dlda => {
            let params = facegate_research::dlda::DldaParams { max_dims: 127, regularization: 0.1, pca_dims: 0 };
            let what = format!("DLDA on {} photos of the training persons (IMM, ORL, LFW training split)", train.len());
            (Some(deep_eval::train_dlda(&train, &params)?), what)
        }
    };
    let command = format!("facegate train deep --projection {}", format!("{:?}", args.projection).to_lowercase());
    let model = train_deep::train(&samples, &embeddings, projection, &network.provenance.sha256, DeepProvenance { trained_on, command });
    facegate_core::model_file::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    println!("{}: {} ({})", args.out.display(), model.version, model.provenance.trained_on);
    print_calibration(&model);
    Ok(ExitCode::SUCCESS)
}

fn print_calibration(model: &DlibModel) {
    for (k, cal) in std::iter::once((1, &model.calibration)).chain(model.enrolled_calibration.iter().map(|t| (t.enrolled, &t.calibration)))
    {
        let points: Vec<String> = cal
            .points
            .iter()
            .map(|p| {
                let flag = if p.under_sampled { ", under-sampled" } else { "" };
                format!("FMR {:e}: {:.4} (FNMR {:.2}%{flag})", p.fmr, p.threshold, 100.0 * p.observed_fnmr)
            })
            .collect();
        println!("  {k} enrolled: {} ({} genuine, {} impostor)", points.join("; "), cal.genuine_count, cal.impostor_count);
    }
}

/// `eval verify --recognizer deep`: the deep model on the held-out persons (LFW test split, IMM
/// and ORL held-out): EER and FNMR at FMR 1e-2 / 1e-3, and FNMR / FMR at the model's own
/// calibrated FMR-1e-3 threshold, one photo enrolled and three.
pub fn run_eval_verify_deep(model_path: &Path, data: &DeepDataArgs, json: bool) -> anyhow::Result<ExitCode> {
    let model = DlibModel::load(model_path)?;
    let (samples, embeddings) = samples_and_embeddings(data)?;
    if !json {
        println!("{} ({}; calibrated on {})", model.version, model.provenance.trained_on, model.calibration.source);
    }
    print_held_out(&deep_eval::held_out_report(&model, &samples, &embeddings), json)?;
    Ok(ExitCode::SUCCESS)
}

/// The held-out report as a table, or one JSON object a line.
pub fn print_held_out(lines: &[deep_eval::HeldOutLine], json: bool) -> anyhow::Result<()> {
    for l in lines {
        if json {
            crate::cli::print_json_line(&serde_json::to_value(l)?);
            continue;
        }
        let observed: Vec<String> =
            l.observed.iter().map(|o| format!("{:.0e}→{:.1e} ({}/{})", o.stated, o.observed, o.false_matches, o.impostors)).collect();
        println!(
            "  {:<38} {} enrolled, {:>4} photos: EER {:>5.2}%  FNMR@1e-2 {:>5.2}%  FNMR@1e-3 {:>5.2}%  | at the calibrated 1e-3 threshold: FNMR {:>5.2}%  | stated→observed FMR: {}",
            l.set,
            l.enrolled,
            l.photos,
            100.0 * l.summary.eer,
            100.0 * l.summary.fnmr_at_fmr_1e2,
            100.0 * l.summary.fnmr_at_fmr_1e3,
            100.0 * l.fnmr_at_threshold,
            observed.join(", ")
        );
    }
    Ok(())
}

/// `eval identify --recognizer deep`: rank-1 identification of the IMM held-out persons' views
/// 2–6 against a gallery of view 1 (plus, with `distractors`, the training persons' view 1), by
/// view group, through the service's pipeline.
pub fn run_eval_identify_deep(distractors: bool) -> anyhow::Result<ExitCode> {
    let config = crate::config::pipeline_config();
    let pipeline = Pipeline::load(&config)?;
    let samples: Vec<Sample> = train_deep::list_samples(&facegate_paths::shared_dir())?.into_iter().filter(|s| s.set == Set::Imm).collect();
    let table = deep_eval::rank1_by_view(&pipeline, &samples, distractors, &crate::cli::Bar::default())?;
    println!("{} (gallery: view 1 of {} persons)", pipeline.recognizer.model_version(), table.gallery);
    for (group, (probes, hits)) in &table.groups {
        println!("  {group:<22} rank-1 {:>6.1}% ({hits}/{probes})", 100.0 * *hits as f64 / (*probes).max(1) as f64);
    }
    Ok(ExitCode::SUCCESS)
}
