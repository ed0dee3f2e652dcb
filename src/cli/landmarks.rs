use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use serde_json::json;

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::GrayF32;
use facegate_detect::Detector;
use facegate_research::dataset;
use facegate_research::train_asm as train;
use facegate_vision::landmarks::asm3d::{Asm3dLandmarker, Refinement};
use facegate_vision::landmarks::{Landmarker, Variant};

#[derive(clap::Args, Debug)]
pub struct LandmarksArgs {
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    #[arg(long)]
    pub json: bool,
    /// Landmark model variant.
    #[arg(long, default_value = "casm", value_parser = ["asm", "sift", "casm", "asm3d"])]
    pub variant: String,
}

#[derive(clap::Args, Debug)]
pub struct TrainAsmArgs {
    /// IMM folder with `NN-V*.jpg` photos and `.asf` annotations.
    #[arg(long)]
    pub imm: PathBuf,
    #[arg(long, default_value = "models/asm.bin")]
    pub out: PathBuf,
    /// Train only on the persons of the person-disjoint training split (leave out
    /// `dataset::imm_is_test_person`), for measurements.
    #[arg(long)]
    pub train_split: bool,
    /// The profile model (`models/asm3d-profile.bin`): views from −90° to +90°, with each view's
    /// visibility and the mean face's five detector points.
    #[arg(long)]
    pub profile: bool,
}

#[derive(clap::Args, Debug)]
pub struct EvalLandmarksArgs {
    #[arg(long)]
    pub imm: PathBuf,
    /// Folder for the cumulative curves (SVG) and the JSON summary.
    #[arg(long, default_value = "target/eval-landmarks")]
    pub out: PathBuf,
    /// Person-disjoint k-fold cross-validation instead of the fixed held-out split: every IMM
    /// person is measured by a model trained on the other folds (all 180 photos measured).
    #[arg(long)]
    pub folds: Option<usize>,
    /// Halve the test photos this many times before detection and search (2: a quarter of the
    /// size, faces about as wide as ORL's), to measure small faces.
    #[arg(long, default_value_t = 0)]
    pub halvings: usize,
    /// Surrey Face Model folder for the 3D-ASM's rows (default: `FACEGATE_SFM` or
    /// `../shared/models/sfm`).
    #[arg(long)]
    pub sfm: Option<PathBuf>,
}

/// The detector, or `None` with a warning when it cannot be loaded.
fn load_detector() -> Option<Detector> {
    match Detector::load(&facegate_paths::models_dir()) {
        Ok(d) => Some(d),
        Err(e) => {
            eprintln!("facegate: warning: no face detector ({e}); using boxes from the annotations");
            None
        }
    }
}

pub fn run(args: LandmarksArgs) -> anyhow::Result<ExitCode> {
    let variant = Variant::parse(&args.variant).context("unknown variant")?;
    let models = facegate_paths::models_dir();
    let detector = Detector::load(&models)?;
    // One face's JSON object; the 3D-ASM adds its fitted pose to the C-ASM fields.
    let fit_face: Box<dyn Fn(&GrayF32, &Rect) -> serde_json::Value> = if variant == Variant::Asm3d {
        let landmarker = Asm3dLandmarker::load(&models.join("asm3d.bin"))?;
        // The 3D search's result is refined by the C-ASM, as in the service.
        let casm = Landmarker::load(&models.join("asm.bin"))?;
        Box::new(move |gray, rect| {
            let lm = landmarker.fit_with(gray, rect, Refinement::Casm(&casm.model));
            let mut face = face_json(rect, &lm.points, &lm.centres);
            face["pose"] = json!(lm.pose);
            face["view_yaw"] = json!(lm.view_yaw);
            face
        })
    } else {
        let landmarker = Landmarker::load(&models.join("asm.bin"))?;
        Box::new(move |gray, rect| {
            let lm = landmarker.fit(gray, rect, variant);
            face_json(rect, &lm.points, &lm.centres)
        })
    };
    let mut failed = false;
    for image in &args.images {
        let photo = match facegate_core::imaging::open(image) {
            Ok(p) => p,
            Err(e) => {
                eprintln!("facegate: {}: {e}", image.display());
                failed = true;
                continue;
            }
        };
        let faces: Vec<serde_json::Value> =
            detector.detect(&photo.gray).iter().map(|f| fit_face(&photo.gray, &facegate_vision::pipeline::seed_box(f))).collect();
        let value = json!({ "image": image.display().to_string(), "variant": variant.name(), "faces": faces });
        if args.json {
            crate::cli::print_json_line(&value);
        } else {
            println!("{}: {} face(s)", image.display(), faces.len());
            for f in &faces {
                let pose = f.get("pose").map(|p| format!("  pose {p}")).unwrap_or_default();
                println!("  box {}  left eye {}  right eye {}  mouth {}{pose}", f["box"], f["left_eye"], f["right_eye"], f["mouth"]);
            }
        }
    }
    Ok(if failed { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}

/// The landmarks JSON contract of one face: box, 58 points in IMM order, eye and mouth centres.
fn face_json(rect: &Rect, points: &[Point], centres: &EyeMouthCentres) -> serde_json::Value {
    json!({
        "box": rect,
        "points": points,
        "left_eye": centres.left_eye,
        "right_eye": centres.right_eye,
        "mouth": centres.mouth,
    })
}

pub fn run_train(args: TrainAsmArgs) -> anyhow::Result<ExitCode> {
    let mut samples = dataset::list_imm(&args.imm)?;
    if args.train_split {
        samples.retain(|s| !dataset::imm_is_test_person(s.person));
    }
    anyhow::ensure!(!samples.is_empty(), "no annotated IMM photos in {}", args.imm.display());
    let detector = load_detector();
    let bar = crate::cli::progress(samples.len() as u64, "train asm");
    let model = train::train(&samples, detector.as_ref(), &train::TrainOptions::default(), &|| bar.inc(1))?;
    bar.finish();
    let info = model.info.clone();
    let landmarker = Landmarker { model };
    landmarker.save(&args.out)?;
    let size = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    eprintln!(
        "trained on {} photos of {} persons; placement from {:?} boxes ({} detector misses); shape modes full/internal/contour {}/{}/{}; wrote {} ({} kB)",
        info.images,
        info.persons.len(),
        info.box_source,
        info.detector_misses,
        landmarker.model.full.modes(),
        landmarker.model.internal.modes(),
        landmarker.model.contour.modes(),
        args.out.display(),
        size / 1024
    );
    Ok(ExitCode::SUCCESS)
}

pub fn run_eval(args: EvalLandmarksArgs) -> anyhow::Result<ExitCode> {
    let detector = load_detector();
    match args.folds {
        Some(folds) => {
            anyhow::ensure!(folds >= 2, "--folds needs at least 2 folds");
            facegate_research::eval::landmarks::run_folds(
                &args.imm,
                detector.as_ref(),
                &args.out,
                folds,
                args.halvings,
                &crate::cli::Bar::default(),
                &mut std::io::stdout().lock(),
            )?;
        }
        None => {
            facegate_research::eval::landmarks::run_scaled(
                &args.imm,
                &args.sfm.clone().unwrap_or_else(facegate_paths::sfm_dir),
                detector.as_ref(),
                &args.out,
                args.halvings,
                &crate::cli::Bar::default(),
                &mut std::io::stdout().lock(),
            )?;
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct TrainAsm3dArgs {
    /// IMM folder with `NN-V*.jpg` photos and `.asf` annotations.
    #[arg(long)]
    pub imm: PathBuf,
    /// Where to write the model (default `models/asm3d.bin`, with `--profile`
    /// `models/asm3d-profile.bin`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Surrey Face Model folder (default: `FACEGATE_SFM` or `../shared/models/sfm`).
    #[arg(long)]
    pub sfm: Option<PathBuf>,
    /// Train only on the persons of the person-disjoint training split (leave out
    /// `dataset::imm_is_test_person`), for measurements.
    #[arg(long)]
    pub train_split: bool,
    /// The profile model (`models/asm3d-profile.bin`): views from −90° to +90°, with each view's
    /// visibility and the mean face's five detector points.
    #[arg(long)]
    pub profile: bool,
}

pub fn run_train_asm3d(args: TrainAsm3dArgs) -> anyhow::Result<ExitCode> {
    use facegate_vision::landmarks::asm3d;
    let mut samples = dataset::list_imm(&args.imm)?;
    if args.train_split {
        samples.retain(|s| !dataset::imm_is_test_person(s.person));
    }
    anyhow::ensure!(!samples.is_empty(), "no annotated IMM photos in {}", args.imm.display());
    let face_model = facegate_morph::FaceModel::load(&args.sfm.clone().unwrap_or_else(facegate_paths::sfm_dir))?;
    let detector = load_detector();
    let bar = crate::cli::progress(samples.len() as u64, "train asm3d");
    let out = args.out.clone().unwrap_or_else(|| PathBuf::from(if args.profile { "models/asm3d-profile.bin" } else { "models/asm3d.bin" }));
    let landmarker = if args.profile {
        let options = facegate_research::train_asm3d::Asm3dTrainOptions::profile();
        let profile = facegate_research::train_asm3d::train_profile(&samples, &face_model, detector.as_ref(), &options, &|| bar.inc(1))?;
        facegate_core::model_file::write_model(&out, &profile).map_err(|e| anyhow::anyhow!("{}: {e}", out.display()))?;
        asm3d::Asm3dLandmarker::from_profile(profile)
    } else {
        let options = facegate_research::train_asm3d::Asm3dTrainOptions::default();
        let model = facegate_research::train_asm3d::train(&samples, &face_model, detector.as_ref(), &options, &|| bar.inc(1))?;
        let landmarker = asm3d::Asm3dLandmarker::new(model);
        landmarker.save(&out)?;
        landmarker
    };
    bar.finish();
    let m = &landmarker.model;
    let size = std::fs::metadata(&out).map(|m| m.len()).unwrap_or(0);
    eprintln!(
        "trained on {} photos of {} persons ({} 3DMM fit failures); placement from {:?} boxes ({} detector misses); views {:?}; real photos per view {:?}; 3D PDM modes {:?}; hidden points per view {:?}; wrote {} ({} kB)",
        m.info.photos,
        m.info.persons.len(),
        m.info.fit_failures,
        m.info.box_source,
        m.info.detector_misses,
        m.views.iter().map(|v| v.yaw).collect::<Vec<_>>(),
        m.views.iter().map(|v| v.real_photos).collect::<Vec<_>>(),
        m.views.iter().map(|v| v.pdm.modes()).collect::<Vec<_>>(),
        landmarker.visible.iter().map(|v| v.iter().filter(|s| !**s).count()).collect::<Vec<_>>(),
        out.display(),
        size / 1024
    );
    Ok(ExitCode::SUCCESS)
}
