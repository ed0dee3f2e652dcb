//! `facegate train liveness` and `facegate eval liveness`: the passive liveness model from NUAA,
//! and its ISO/IEC 30107-3 measures by leave-one-subject-out folds.

use std::path::PathBuf;
use std::process::ExitCode;

use facegate_research::liveness::eval as research;
use facegate_research::liveness::measures::OperatingPoint;
use facegate_research::liveness::peers::{self as peer, Network, PeerScores};
use facegate_research::liveness::subjects;
use facegate_research::liveness::train::{self, LivenessData, Recipe};
use facegate_vision::liveness::Block;

/// Options both liveness commands share.
#[derive(clap::Args, Debug, Clone)]
pub struct LivenessDataArgs {
    /// The research cache folder, where every photo's eye and mouth centres are kept.
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
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
    /// The recipes (of those evaluated) whose name contains this also run the nested subject-wise
    /// protocol: each NUAA subject scored by a model and a threshold chosen without it, every
    /// subject's APCER and BPCER, the worst (81 fits per recipe). `MiniFASNet` runs the
    /// pretrained networks (`models/minifasnet-*.bin`) as peers under it.
    #[arg(long, default_value = "shipped")]
    pub nested: String,
    #[command(flatten)]
    pub data: LivenessDataArgs,
}

/// The shipped model's recipe and operating point (chosen by `facegate eval liveness`: docs/liveness.md).
pub fn shipped() -> (Recipe, OperatingPoint) {
    (
        Recipe {
            blocks: vec![Block::FaceLbp, Block::FaceColourLbp, Block::ContextLbp],
            other_cameras: true,
            ridge: 1e-2,
            simulated_attacks: false,
            video_live: false,
        },
        OperatingPoint::Eer,
    )
}

/// The recipes compared, by name.
pub fn candidates() -> Vec<(String, Recipe)> {
    let r = |blocks: &[Block], other_cameras: bool, ridge: f64| Recipe {
        blocks: blocks.to_vec(),
        other_cameras,
        ridge,
        simulated_attacks: false,
        video_live: false,
    };
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
        ("face LBP + colour + context + other cameras' live + video live".into(), Recipe { video_live: true, ..shipped().0 }),
        (
            "face LBP + colour + context + other cameras' live + simulated prints and screens".into(),
            Recipe { simulated_attacks: true, ..shipped().0 },
        ),
    ]
}

fn load(args: &LivenessDataArgs, progress: &super::Bar) -> anyhow::Result<LivenessData> {
    LivenessData::load(&facegate_paths::shared_dir(), &facegate_paths::models_dir(), &args.cache, args.threads, progress)
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
            for a in &report.simulated_accepted {
                eprintln!(
                    "    test persons' simulated attacks taken for live at {}: prints {:.2}%, screens {:.2}% of {}",
                    a.operating_point,
                    100.0 * a.print,
                    100.0 * a.screen,
                    a.photos
                );
            }
            print_camera_thresholds(&report.camera_thresholds);
            for v in &report.video_refused {
                eprintln!(
                    "    video {} ({}): live frames refused at {:.3}: {:.1}% of {}; by the recipe without this person {:.1}% (median score {:.3})",
                    v.clip,
                    v.person,
                    v.threshold,
                    100.0 * v.refused,
                    v.frames,
                    100.0 * v.refused_person_unseen,
                    v.median_person_unseen
                );
            }
            if let Some(r) = &report.reverse {
                eprintln!(
                    "    without NUAA, on NUAA: EER {:.2}%  BPCER@APCER1% {:.2}%  at the test persons' threshold APCER {:.2}%, BPCER {:.2}%",
                    100.0 * r.eer,
                    100.0 * r.bpcer_at_apcer_1,
                    100.0 * r.at_threshold.apcer,
                    100.0 * r.at_threshold.bpcer
                );
            }
        }
        curves.push((name.clone(), logits));
        if name.contains(args.nested.as_str()) {
            let fit = subjects::recipe_scores(&data, recipe);
            let folds = subjects::folds(&data, &fit, args.data.threads, &progress);
            print_nested(name, &folds, args.json)?;
        }
    }
    run_peers(&args, &data, &progress)?;
    let sets: Vec<(&str, &[Option<f32>])> = curves.iter().map(|(n, l)| (n.as_str(), l.as_slice())).collect();
    research::write_det(&args.plot, &data, &sets)?;
    let images: Vec<PathBuf> = data.nuaa.iter().map(|s| s.image.clone()).collect();
    let landmarks = train::landmarks(&args.data.cache, &facegate_paths::models_dir(), &images, args.data.threads, &progress)?;
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

/// MiniFASNet as shipped (`models/minifasnet-*.bin`), each network whose name `--only` and
/// `--nested` select, and its fusion with the shipped LBP recipe ([`peer::FUSED_WITH_LBP`]): the
/// nested protocol, other cameras' live photos and simulated attacks.
fn run_peers(args: &EvalLivenessArgs, data: &LivenessData, progress: &super::Bar) -> anyhow::Result<()> {
    let selected: Vec<Network> = Network::ALL
        .into_iter()
        .filter(|n| args.only.as_ref().is_none_or(|o| n.name().contains(o.as_str())) && n.name().contains(args.nested.as_str()))
        .collect();
    let fused = peer::FUSED_WITH_LBP;
    let with_fusion = args.only.as_ref().is_none_or(|o| fused.contains(o.as_str())) && fused.contains(args.nested.as_str());
    if selected.is_empty() && !with_fusion {
        return Ok(());
    }
    let scores = PeerScores::compute(data, &args.data.cache, &facegate_paths::models_dir(), args.data.threads, progress)?;
    if with_fusion {
        let recipe = shipped().0;
        print_nested(fused, &peer::fused_folds(data, &recipe, &scores, args.data.threads, progress), args.json)?;
        report_peer_camera_thresholds(&peer::fused_camera_thresholds(data, &recipe, &scores, progress), args.json);
    }
    for network in selected {
        let folds = scores.folds(data, network, args.data.threads, progress);
        print_nested(network.name(), &folds, args.json)?;
        report_peer_camera_thresholds(&peer::camera_thresholds(data, &scores, network), args.json);
        for o in peer::other_cameras(data, &scores, network) {
            if args.json {
                super::print_json_line(&serde_json::json!({ "peer_other_cameras": o }));
            } else {
                eprintln!(
                    "{} at {} ({:.3}): IMM/ORL/LFW test persons' live photos refused {:.2}% of {}; their simulated prints taken for live {:.2}%, screens {:.2}%",
                    network.name(),
                    o.threshold_from,
                    o.threshold,
                    100.0 * o.live_refused,
                    o.live_photos,
                    100.0 * o.print_accepted,
                    100.0 * o.screen_accepted
                );
            }
        }
    }
    Ok(())
}

/// A peer's camera thresholds: one JSON line (`peer_camera_thresholds`), or the lines below.
fn report_peer_camera_thresholds(cameras: &[research::CameraThreshold], json: bool) {
    if json {
        super::print_json_line(&serde_json::json!({ "peer_camera_thresholds": cameras }));
    } else {
        print_camera_thresholds(cameras);
    }
}

/// Each camera's own threshold against NUAA's, on the camera's test persons.
fn print_camera_thresholds(cameras: &[research::CameraThreshold]) {
    for c in cameras {
        eprintln!(
            "    {} on {}: its own threshold {:.4} from {} live faces (BPCER {}%): test persons' live refused {:.2}% of {}, simulated prints taken for live {:.2}%, screens {:.2}%; at NUAA's {:.4}: {:.2}%, {:.2}%, {:.2}%",
            c.model,
            c.set,
            c.threshold,
            c.calibration_faces,
            100.0 * c.bpcer,
            100.0 * c.live_refused,
            c.test_live,
            100.0 * c.print_accepted,
            100.0 * c.screen_accepted,
            c.nuaa_threshold,
            100.0 * c.nuaa_live_refused,
            100.0 * c.nuaa_print_accepted,
            100.0 * c.nuaa_screen_accepted
        );
    }
}

/// The nested protocol's per-subject table and worst subject, for each threshold rule.
fn print_nested(name: &str, folds: &[subjects::Fold], json: bool) -> anyhow::Result<()> {
    for rule in subjects::RULES {
        let report = subjects::report(name, folds, rule);
        if json {
            super::print_json_line(&serde_json::json!({ "nested": report }));
            continue;
        }
        eprintln!(
            "{name}, unseen subjects, threshold at {}: APCER {:.2}%  BPCER {:.2}%  ACER {:.2}%; worst APCER {:.2}% (subject {}), worst BPCER {:.2}% (subject {}); pooled EER {:.2}%, BPCER@APCER1% {:.2}%",
            report.rule,
            100.0 * report.apcer,
            100.0 * report.bpcer,
            100.0 * report.acer,
            100.0 * report.worst_apcer,
            report.worst_apcer_subject,
            100.0 * report.worst_bpcer,
            report.worst_bpcer_subject,
            100.0 * report.pooled_eer,
            100.0 * report.pooled_bpcer_at_apcer_1
        );
        for s in &report.subjects {
            eprintln!(
                "    subject {}: threshold {:.3}  APCER {:6.2}% of {:4}  BPCER {:6.2}% of {:4}",
                s.subject,
                s.threshold,
                100.0 * s.apcer,
                s.attacks,
                100.0 * s.bpcer,
                s.live
            );
        }
    }
    Ok(())
}

pub fn run_train(args: TrainLivenessArgs) -> anyhow::Result<ExitCode> {
    let progress = super::Bar::default();
    let data = load(&args.data, &progress)?;
    let (recipe, point) = shipped();
    let (report, _) = research::evaluate(&data, "shipped", &recipe, &progress);
    let all: Vec<usize> = (0..data.nuaa.len()).collect();
    let fit = train::fit_recipe(&data, &recipe, &all);
    let refusal =
        report.other_cameras_refused.iter().find(|r| r.operating_point == point.name()).expect("every operating point is reported");
    let subjects = {
        let mut s: Vec<&str> = data.nuaa.iter().map(|s| s.subject.as_str()).collect();
        s.sort_unstable();
        s.dedup();
        s.join(", ")
    };
    let model = train::model(
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

#[derive(clap::Args, Debug)]
pub struct TrainRenderArgs {
    /// Where to write the model.
    #[arg(long, default_value = "models/render.bin")]
    pub out: PathBuf,
    /// LFW training persons taken (their first photo each; every other one also rendered).
    #[arg(long, default_value_t = 400)]
    pub lfw_persons: usize,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

/// `facegate train render`: the rendered-head detector the head-turn challenge holds its frames
/// against (docs/liveness-challenge.md, "Rendered heads").
pub fn run_train_render(args: TrainRenderArgs) -> anyhow::Result<ExitCode> {
    use facegate_research::liveness::render::{RenderTrainConfig, train};
    let shared = facegate_paths::shared_dir();
    let config = RenderTrainConfig {
        imm: shared.join("data/imm"),
        orl: shared.join("data/orl"),
        lfw: shared.join("data/lfw"),
        umist: shared.join("data/umist"),
        lfw_persons: args.lfw_persons,
        threads: args.threads.max(1),
    };
    let mut pipeline = facegate_vision::pipeline::Pipeline::load(&crate::config::pipeline_config())?;
    anyhow::ensure!(pipeline.face_model.is_some(), "renders need the 3D morphable model: the Surrey Face Model is needed");
    pipeline.render = None;
    let (model, report) = train(&pipeline, &config, &super::Bar::default())?;
    facegate_core::model_file::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    eprintln!(
        "wrote {}: {} camera faces, {} renders ({} without a face); out of fold at even odds: camera faces refused {:.2}%, renders passed {:.2}%",
        args.out.display(),
        report.camera_faces,
        report.renders,
        report.without_face,
        100.0 * report.oof_camera_refused,
        100.0 * report.oof_renders_passed
    );
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalChallengeArgs {
    /// Which IMM persons: `test` (never trained on; with UMIST, the video clips and NUAA) or `train` (where the
    /// challenge's limits were read).
    #[arg(long, value_parser = ["test", "train"], default_value = "test")]
    pub persons: String,
    /// Challenges drawn per person.
    #[arg(long, default_value_t = 10)]
    pub challenges: usize,
    /// Seed of the challenges drawn.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Threads analysing frames.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Print the report as one JSON line on stdout.
    #[arg(long)]
    pub json: bool,
}

/// `facegate eval challenge`: the head-turn challenge's BPCER and APCER per attack type.
pub fn run_eval_challenge(args: EvalChallengeArgs) -> anyhow::Result<ExitCode> {
    use facegate_research::liveness::challenge::{ChallengeEvalConfig, evaluate};
    let shared = facegate_paths::shared_dir();
    let config = ChallengeEvalConfig {
        imm: shared.join("data/imm"),
        umist: shared.join("data/umist"),
        nuaa: shared.join("data/nuaa"),
        test_persons: args.persons == "test",
        challenges_per_person: args.challenges,
        seed: args.seed,
        threads: args.threads.max(1),
        video: shared.join("data/video"),
        lfw: shared.join("data/lfw"),
    };
    let pipeline = facegate_vision::pipeline::Pipeline::load(&crate::config::pipeline_config())?;
    anyhow::ensure!(pipeline.face_model.is_some(), "the challenge is judged on the 3D fit: the Surrey Face Model is needed");
    let progress = super::Bar::default();
    let report = evaluate(&pipeline, &config, &progress)?;
    if args.json {
        super::print_json_line(&serde_json::to_value(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    print_challenge_report(&report);
    Ok(ExitCode::SUCCESS)
}

/// The challenge report as tables on stderr: the rows by kind, each person's live passes, the
/// yaw and depth quantiles, the limits and the CPU.
fn print_challenge_report(report: &facegate_research::liveness::challenge::ChallengeReport) {
    eprintln!("persons: {}; mean steps {:.2}", report.persons, report.mean_steps);
    eprintln!("{:<44} {:>8} {:>16} {:>16} {:>7} {:>6}  first reasons", "kind", "attempts", "pass challenge", "pass enforce", "shift", "z");
    for row in &report.rows {
        let rate = |n: usize| format!("{n} ({:.1}%)", 100.0 * n as f64 / row.attempts.max(1) as f64);
        let shift = row.shift_median.map_or("-".to_string(), |p| format!("{p:.3}"));
        let z = row.z_median.map_or("-".to_string(), |p| format!("{p:.1}"));
        let reasons: Vec<String> = row.reasons.iter().map(|(r, n)| format!("{r}: {n}")).collect();
        eprintln!(
            "{:<44} {:>8} {:>16} {:>16} {:>7} {:>6}  {}",
            row.kind,
            row.attempts,
            rate(row.passed_challenge),
            rate(row.passed_enforce),
            shift,
            z,
            reasons.join("; ")
        );
    }
    eprintln!("reused challenge: {} of {} given out a second time", report.reused_passed, report.reused_attempts);
    if let Some(s) = &report.stranger_steps {
        eprintln!(
            "stranger in one step, LFW test persons ({} persons, {} captures): {} of {} attempts pass ({} matched the probe alone)",
            s.persons, s.captures, s.passed, s.attempts, s.matched_probe
        );
    }
    for (person, (n, passed)) in &report.live_by_person {
        let why = report.live_refused.get(person).map_or(String::new(), |(_, r)| format!("; first refusal: {r}"));
        eprintln!("live {person}: {passed} of {n} pass{why}");
    }
    for (clip, n) in report.video_other_faces.iter().filter(|(_, n)| **n > 0) {
        eprintln!("{clip}: {n} frames whose largest face is another person's, left out");
    }
    for (kind, [min, p5, median, p95, max]) in &report.yaw_quantiles {
        eprintln!("yaw {kind}: min {min:.1}° p5 {p5:.1}° median {median:.1}° p95 {p95:.1}° max {max:.1}°");
    }
    for (kind, depth) in &report.depth_by_kind {
        print_depth_quantiles(kind, depth);
    }
    eprintln!(
        "limits: excess turn <= {:.0}°, shift >= {:.3}, z >= {:.1} (noise floor {:.3}), identity at FMR {:e}",
        facegate_service::challenge::MAX_EXCESS_TURN,
        facegate_service::challenge::SHIFT_MIN,
        facegate_service::challenge::Z_MIN,
        facegate_service::challenge::NOISE_FLOOR,
        facegate_service::challenge::CAPTURE_FMR
    );
    eprintln!(
        "CPU: {:.0} ms per photo analysis, {:.3} ms per judgement: a challenge of {:.2} steps costs {:.2} plain verifications",
        report.analysis_ms,
        report.judge_ms,
        report.mean_steps,
        report.mean_steps + 1.0 + report.judge_ms / report.analysis_ms
    );
}

/// One kind's depth test readings (shift, z, excess turn) as quantiles on stderr.
fn print_depth_quantiles(kind: &str, depth: &[(f64, f64, f64)]) {
    let q = |i: usize, p: f64| {
        let mut v: Vec<f64> = depth.iter().map(|d| [d.0, d.1, d.2][i]).collect();
        v.sort_by(f64::total_cmp);
        v.get(((v.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(f64::NAN)
    };
    eprintln!(
        "depth, poses right, {kind} (n {}): shift min {:.3} p5 {:.3} median {:.3} max {:.3}; z min {:.1} p5 {:.1} median {:.1} max {:.1}; excess turn median {:.1}° p95 {:.1}° max {:.1}°",
        depth.len(),
        q(0, 0.0),
        q(0, 0.05),
        q(0, 0.5),
        q(0, 1.0),
        q(1, 0.0),
        q(1, 0.05),
        q(1, 0.5),
        q(1, 1.0),
        q(2, 0.5),
        q(2, 0.95),
        q(2, 1.0)
    );
}
