//! `facegate reconstruct` and `facegate frontalize`: fit the Surrey Face Model to the 58 landmarks
//! of a photo, then export a textured avatar or render the face from the front.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};

use facegate_core::geometry::Point;
use facegate_core::imaging::Photo;
use facegate_morph::{AVATAR_TEXTURE_SIZE, FRONTAL_VIEW_SIZE, FaceModel, FitOptions, FittedFace, export};

/// Where the model and the landmarks come from (shared by both commands).
#[derive(clap::Args, Debug)]
pub struct MorphInput {
    /// Surrey Face Model folder (default: FACEGATE_SFM, else ../shared/models/sfm).
    #[arg(long)]
    pub sfm: Option<PathBuf>,
    /// Take the 58 landmarks from an IMM `.asf` annotation instead of the detector + C-ASM.
    #[arg(long)]
    pub landmarks: Option<PathBuf>,
    /// The project's models folder for automatic landmarks (default: FACEGATE_MODELS or models/).
    #[arg(long)]
    pub models: Option<PathBuf>,
    /// Also fit the 6 expression blendshapes.
    #[arg(long)]
    pub expressions: bool,
}

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    pub image: PathBuf,
    /// Output file: `.glb` (glTF binary) or `.obj` (OBJ + MTL + PNG).
    #[arg(long)]
    pub out: PathBuf,
    /// Side of the exported UV texture in pixels.
    #[arg(long, default_value_t = AVATAR_TEXTURE_SIZE)]
    pub texture_size: usize,
    #[command(flatten)]
    pub input: MorphInput,
}

#[derive(clap::Args, Debug)]
pub struct FrontalizeArgs {
    pub image: PathBuf,
    /// Output PNG.
    #[arg(long)]
    pub out: PathBuf,
    /// Side of the square frontal rendering in pixels.
    #[arg(long, default_value_t = FRONTAL_VIEW_SIZE)]
    pub size: usize,
    /// Render the head turned to this yaw instead of from the front (degrees, -90 to 90; > 0: the
    /// head turned to its own left, as `/analyze` reports it): the avatar of one photo, as an
    /// attack on the liveness challenge would show it.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub yaw: f32,
    #[command(flatten)]
    pub input: MorphInput,
}

fn load_model(input: &MorphInput) -> anyhow::Result<FaceModel> {
    let dir = input.sfm.clone().unwrap_or_else(facegate_paths::sfm_dir);
    FaceModel::load(&dir)
        .context("the 3D morphable model is needed for this command (the Surrey Face Model is not redistributed with facegate)")
}

fn landmarks(input: &MorphInput, photo: &Photo) -> anyhow::Result<Vec<Point>> {
    if let Some(asf) = &input.landmarks {
        let shape = facegate_research::dataset::read_asf(asf, photo.width() as f32, photo.height() as f32)?;
        if shape.points.len() != facegate_core::face::IMM_POINTS {
            bail!("{}: {} points, expected 58 (IMM template)", asf.display(), shape.points.len());
        }
        return Ok(shape.xy());
    }
    let models = input.models.clone().unwrap_or_else(facegate_paths::models_dir);
    // The service's landmarks (detector, C-ASM, 3D-ASM on turned faces): the same avatar as
    // `POST /avatar` for the same photo.
    let automatic = || -> anyhow::Result<Vec<Point>> {
        let finder = facegate_vision::pipeline::FaceFinder::load(&models)?;
        Ok(finder.locate(&photo.gray)?.landmarks.points)
    };
    automatic().context("automatic landmarks are unavailable; pass --landmarks FILE.asf (58-point IMM annotation)")
}

fn fit(input: &MorphInput, model: &FaceModel, photo: &Photo) -> anyhow::Result<FittedFace> {
    let points = landmarks(input, photo)?;
    let options = FitOptions { expressions: input.expressions, ..Default::default() };
    Ok(model.fit_with(&points, photo.width(), photo.height(), &options)?)
}

fn open(path: &Path) -> anyhow::Result<Photo> {
    facegate_core::imaging::open(path).with_context(|| format!("cannot read {}", path.display()))
}

pub fn run_reconstruct(args: ReconstructArgs) -> anyhow::Result<ExitCode> {
    let ext = args.out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if !matches!(ext.as_deref(), Some("glb") | Some("obj")) {
        bail!("--out must end in .glb or .obj");
    }
    if !(16..=4096).contains(&args.texture_size) {
        bail!("--texture-size must be between 16 and 4096");
    }
    let model = load_model(&args.input)?;
    let photo = open(&args.image)?;
    let points = landmarks(&args.input, &photo)?;
    let options = FitOptions { expressions: args.input.expressions, ..Default::default() };
    let avatar = model.avatar(&photo, &points, &options, args.texture_size)?;
    match ext.as_deref() {
        Some("glb") => {
            let bytes = model.avatar_glb(&avatar)?;
            std::fs::write(&args.out, bytes).with_context(|| format!("cannot write {}", args.out.display()))?;
        }
        _ => export::write_obj(&model.avatar_mesh(&avatar), &args.out)?,
    }
    let fitted = &avatar.fitted;
    super::print_json_line(&serde_json::json!({
        "image": args.image.display().to_string(),
        "pose": {"yaw": fitted.pose.yaw, "pitch": fitted.pose.pitch, "roll": fitted.pose.roll},
        "residual_px": fitted.residual_px,
        "vertices": fitted.vertices.len(),
        "out": args.out.display().to_string(),
    }));
    Ok(ExitCode::SUCCESS)
}

pub fn run_frontalize(args: FrontalizeArgs) -> anyhow::Result<ExitCode> {
    if !args.out.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png")) {
        bail!("--out must end in .png");
    }
    if !(16..=2048).contains(&args.size) {
        bail!("--size must be between 16 and 2048");
    }
    if !(-90.0..=90.0).contains(&args.yaw) {
        bail!("--yaw must be between -90 and 90 degrees");
    }
    let model = load_model(&args.input)?;
    let photo = open(&args.image)?;
    let fitted = fit(&args.input, &model, &photo)?;
    let pose = facegate_morph::Pose { yaw: args.yaw, ..Default::default() };
    let (frontal, png) = model.posed_png(&photo, &fitted, pose, args.size)?;
    std::fs::write(&args.out, png).with_context(|| format!("cannot write {}", args.out.display()))?;
    let k = frontal.centres;
    super::print_json_line(&serde_json::json!({
        "image": args.image.display().to_string(),
        "pose": {"yaw": fitted.pose.yaw, "pitch": fitted.pose.pitch, "roll": fitted.pose.roll},
        "residual_px": fitted.residual_px,
        "keypoints": {"left_eye": k.left_eye, "right_eye": k.right_eye, "mouth": k.mouth},
        "rendered_yaw": args.yaw,
        "out": args.out.display().to_string(),
    }));
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct TrainImmSfmArgs {
    /// Surrey Face Model folder (default: FACEGATE_SFM, else ../shared/models/sfm).
    #[arg(long)]
    pub sfm: Option<PathBuf>,
    /// IMM folder (default: <shared>/data/imm).
    #[arg(long)]
    pub imm: Option<PathBuf>,
    /// Refinement rounds.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Search radius around each point's current vertex, millimetres on the mean shape.
    #[arg(long, default_value_t = 12.0)]
    pub radius_mm: f32,
    #[arg(long, default_value = "models/imm_to_sfm.txt")]
    pub out: PathBuf,
}

/// `facegate train imm-sfm`: refine the fixed IMM correspondences on the frontal views (1, 2) of
/// the IMM training persons (never the held-out ones) and write the table.
pub fn run_train_imm_sfm(args: TrainImmSfmArgs) -> anyhow::Result<ExitCode> {
    let dir = args.sfm.clone().unwrap_or_else(facegate_paths::sfm_dir);
    let mut model = FaceModel::load(&dir).context("the 3D morphable model is needed for this command")?;
    // Start from the geometric anchors, not from a previously written table.
    model.imm_vertices = facegate_morph::correspondence::resolve(&facegate_morph::correspondence::imm_anchors(), &model.shape.mean);
    let imm = args.imm.clone().unwrap_or_else(|| facegate_paths::shared_dir().join("data/imm"));
    let mut shapes = Vec::new();
    let mut persons = std::collections::BTreeSet::new();
    for s in facegate_research::dataset::list_imm(&imm)? {
        if facegate_research::dataset::imm_is_test_person(s.person) || !(s.view == 1 || s.view == 2) {
            continue;
        }
        let (w, h) = image::image_dimensions(&s.image)?;
        shapes.push((s.landmarks()?, w, h));
        persons.insert(s.person);
    }
    if shapes.is_empty() {
        bail!("no IMM training annotations in {}", imm.display());
    }
    let (table, before, after) =
        facegate_research::train_imm_sfm::derive_from_annotations(&mut model, &shapes, args.rounds, args.radius_mm)?;
    let anchors = facegate_morph::correspondence::imm_anchors();
    let mut text = String::new();
    text.push_str("# IMM point -> Surrey Face Model (sfm_shape_3448) vertex id, for the fixed points (jaw 0-12 except\n");
    text.push_str("# the chin slide along the model contour at fit time). Written by `facegate train imm-sfm`:\n");
    text.push_str(&format!(
        "# geometric anchors (src/morph/correspondence.rs) refined in {} rounds within {} mm on the frontal views\n",
        args.rounds, args.radius_mm
    ));
    text.push_str(&format!("# (1, 2) of IMM training persons {:?}; RMS landmark residual {before:.2} px -> {after:.2} px.\n", persons));
    for (i, v) in table.iter().enumerate() {
        if !matches!(anchors[i], facegate_morph::correspondence::Anchor::Contour { .. }) {
            text.push_str(&format!("{i} {v}\n"));
        }
    }
    std::fs::write(&args.out, text).with_context(|| format!("cannot write {}", args.out.display()))?;
    super::print_json_line(&serde_json::json!({
        "shapes": shapes.len(), "persons": persons.len(), "residual_px_before": before, "residual_px_after": after,
        "out": args.out.display().to_string(),
    }));
    Ok(ExitCode::SUCCESS)
}
