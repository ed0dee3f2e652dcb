//! `facegate train liveness` and `facegate eval liveness`: the passive liveness model from NUAA,
//! and its ISO/IEC 30107-3 measures by leave-one-subject-out folds.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::liveness::Block;
use crate::research::eval::liveness::{self as research, OperatingPoint};
use crate::research::train_liveness::{self, LivenessData, Recipe};

/// Options both liveness commands share.
#[derive(clap::Args, Debug, Clone)]
pub struct LivenessDataArgs {
    /// The research cache folder, where every photo's face key points are kept.
    #[arg(long, default_value = crate::research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    /// Threads measuring photos.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

#[derive(clap::Args, Debug)]
pub struct TrainLivenessArgs {
    /// Where to write the model.
    #[arg(long, default_value = "models/liveness.bin")]
    pub out: PathBuf,
    #[command(flatten)]
    pub data: LivenessDataArgs,
}

#[derive(clap::Args, Debug)]
pub struct EvalLivenessArgs {
    /// The DET plot of the compared recipes.
    #[arg(long, default_value = "docs/img/liveness/det.svg")]
    pub plot: PathBuf,
    /// Print each recipe's measures as one JSON line on stdout.
    #[arg(long)]
    pub json: bool,
    /// Only the recipes whose name contains this.
    #[arg(long)]
    pub only: Option<String>,
    #[command(flatten)]
    pub data: LivenessDataArgs,
}

/// The shipped model's recipe and operating point (chosen by `facegate eval liveness`: docs/liveness.md).
pub fn shipped() -> (Recipe, OperatingPoint) {
    (
        Recipe { blocks: vec![Block::FaceLbp, Block::FaceColourLbp, Block::ContextLbp], other_cameras: true, ridge: 1e-2 },
        OperatingPoint::Eer,
    )
}

/// The recipes compared, by name.
pub fn candidates() -> Vec<(String, Recipe)> {
    let r = |blocks: &[Block], other_cameras: bool, ridge: f64| Recipe { blocks: blocks.to_vec(), other_cameras, ridge };
    vec![
        ("face LBP (Määttä)".into(), r(&[Block::FaceLbp], false, 1e-2)),
        ("face colour LBP (Boulkenafet)".into(), r(&[Block::FaceColourLbp], false, 1e-2)),
        ("face frequency (Tan)".into(), r(&[Block::FaceFrequency], false, 1e-2)),
        ("context LBP".into(), r(&[Block::ContextLbp], false, 1e-2)),
        ("face LBP + colour".into(), r(&[Block::FaceLbp, Block::FaceColourLbp], false, 1e-2)),
        ("all blocks".into(), r(&Block::ALL, false, 1e-2)),
        ("all blocks + other cameras' live".into(), r(&Block::ALL, true, 1e-2)),
        ("all blocks + other cameras' live, ridge 0.1".into(), r(&Block::ALL, true, 1e-1)),
        ("all blocks + other cameras' live, ridge 0.001".into(), r(&Block::ALL, true, 1e-3)),
        ("shipped: face LBP + colour + context + other cameras' live".into(), shipped().0),
    ]
}

fn load(args: &LivenessDataArgs, progress: &super::Bar) -> anyhow::Result<LivenessData> {
    LivenessData::load(&crate::config::shared_dir(), &crate::config::models_dir(), &args.cache, args.threads, progress)
}

pub fn run_eval(args: EvalLivenessArgs) -> anyhow::Result<ExitCode> {
    let progress = super::Bar::default();
    let data = load(&args.data, &progress)?;
    let recipes: Vec<(String, Recipe)> =
        candidates().into_iter().filter(|(name, _)| args.only.as_ref().is_none_or(|o| name.contains(o.as_str()))).collect();
    let mut curves = Vec::new();
    for (name, recipe) in &recipes {
        let (report, logits) = research::evaluate(&data, name, recipe, &progress);
        if args.json {
            super::print_json_line(&serde_json::to_value(&report)?);
        } else {
            eprintln!(
                "{name}: EER {:.2}%  BPCER@APCER1% {:.2}%  @5% {:.2}%  ACER {:.2}% (APCER {:.2}%, BPCER {:.2}%)",
                100.0 * report.eer,
                100.0 * report.bpcer_at_apcer_1,
                100.0 * report.bpcer_at_apcer_5,
                100.0 * report.at_eer_of_other_subjects.acer,
                100.0 * report.at_eer_of_other_subjects.apcer,
                100.0 * report.at_eer_of_other_subjects.bpcer
            );
        }
        curves.push((name.clone(), logits));
    }
    let sets: Vec<(&str, &[Option<f32>])> = curves.iter().map(|(n, l)| (n.as_str(), l.as_slice())).collect();
    research::write_det(&args.plot, &data, &sets)?;
    let images: Vec<PathBuf> = data.nuaa.iter().map(|s| s.image.clone()).collect();
    let landmarks = train_liveness::landmarks(&args.data.cache, &crate::config::models_dir(), &images, args.data.threads, &progress)?;
    let motion = research::motion_measures(&data, &landmarks);
    if args.json {
        super::print_json_line(&serde_json::json!({ "motion": motion }));
    } else {
        eprintln!(
            "motion test (one homography across {} frames): EER {:.2}%, BPCER@APCER1% {:.2}%; median residual live {:.4}, print {:.4}",
            research::SEQUENCE_FRAMES,
            100.0 * motion.eer,
            100.0 * motion.bpcer_at_apcer_1,
            motion.live_median,
            motion.attack_median
        );
    }
    Ok(ExitCode::SUCCESS)
}

pub fn run_train(args: TrainLivenessArgs) -> anyhow::Result<ExitCode> {
    let progress = super::Bar::default();
    let data = load(&args.data, &progress)?;
    let (recipe, point) = shipped();
    let (report, _) = research::evaluate(&data, "shipped", &recipe, &progress);
    let all: Vec<usize> = (0..data.nuaa.len()).collect();
    let fit = train_liveness::fit_recipe(&data, &recipe, &all);
    let refusal =
        report.other_cameras_refused.iter().find(|r| r.operating_point == point.name()).expect("every operating point is reported");
    let subjects = {
        let mut s: Vec<&str> = data.nuaa.iter().map(|s| s.subject.as_str()).collect();
        s.sort_unstable();
        s.dedup();
        s.join(", ")
    };
    let model = train_liveness::model(
        "lbp-colour-context-1",
        &recipe.blocks,
        fit,
        report.calibration,
        refusal.threshold,
        format!("{} of leave-one-subject-out NUAA scores", point.name()),
        format!(
            "NUAA Photograph Imposter Database subjects {subjects} (live and print frames), with the live photos of the IMM, ORL and LFW training persons; `facegate train liveness`"
        ),
    );
    facegate_core::model_file::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    eprintln!(
        "wrote {}: threshold {:.3} ({}); out-of-fold EER {:.2}%, ACER {:.2}%",
        args.out.display(),
        model.threshold,
        model.operating_point,
        100.0 * report.eer,
        100.0 * report.at_eer_of_other_subjects.acer
    );
    Ok(ExitCode::SUCCESS)
}
