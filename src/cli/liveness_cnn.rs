//! `facegate eval liveness-cnn`: the liveness CNN trained in Rust against the LBP model, each with
//! and without the simulated attacks, under NUAA subject folds and on other people and cameras.

use std::process::ExitCode;

use super::liveness::{LivenessDataArgs, shipped};
use facegate_research::liveness::cnn::TrainingConfig;
use facegate_research::liveness::cnn_eval::{self as research, CnnInputs, CnnReport, Data, Learner};
use facegate_research::liveness::eval::CameraThreshold;
use facegate_research::liveness::train::{LivenessData, Recipe};

#[derive(clap::Args, Debug)]
pub struct EvalLivenessCnnArgs {
    /// Print each model's measures as one JSON line on stdout.
    #[arg(long)]
    pub json: bool,
    /// Only the models whose name contains this.
    #[arg(long)]
    pub only: Option<String>,
    /// Only each camera's own threshold (3 fits per model): per data set, the model fitted without
    /// that set's persons, its threshold set on the set's non-test persons' live photos as
    /// `facegate calibrate-liveness` sets it, measured on its test persons.
    #[arg(long)]
    pub camera_thresholds: bool,
    /// The CNN's training epochs.
    #[arg(long, default_value_t = TrainingConfig::default().epochs)]
    pub epochs: usize,
    /// The CNN's samples drawn per epoch.
    #[arg(long, default_value_t = TrainingConfig::default().per_epoch)]
    pub per_epoch: usize,
    /// Seeds the CNN's weights and draws.
    #[arg(long, default_value_t = TrainingConfig::default().seed)]
    pub seed: u64,
    #[command(flatten)]
    pub data: LivenessDataArgs,
}

/// The models compared, by name.
fn learners(args: &EvalLivenessCnnArgs) -> Vec<(String, Learner)> {
    let config = TrainingConfig { epochs: args.epochs, per_epoch: args.per_epoch, seed: args.seed, ..TrainingConfig::default() };
    let lbp = shipped().0;
    vec![
        ("LBP (shipped recipe)".into(), Learner::Lbp(lbp.clone())),
        ("LBP + simulated attacks".into(), Learner::Lbp(Recipe { simulated_attacks: true, ..lbp })),
        ("CNN".into(), Learner::Cnn { simulated_attacks: false, config }),
        ("CNN + simulated attacks".into(), Learner::Cnn { simulated_attacks: true, config }),
        (
            "CNN + simulated attacks, jittered".into(),
            Learner::Cnn { simulated_attacks: true, config: TrainingConfig { jitter: true, ..config } },
        ),
    ]
}

pub fn run_eval(args: EvalLivenessCnnArgs) -> anyhow::Result<ExitCode> {
    let progress = super::Bar::default();
    let (shared, models) = (facegate_paths::shared_dir(), facegate_paths::models_dir());
    let features = LivenessData::load(&shared, &models, &args.data.cache, args.data.threads, &progress)?;
    let inputs = CnnInputs::load(&features, &models, &args.data.cache, args.data.threads, &progress)?;
    let data = Data { features: &features, inputs: &inputs };
    for (name, learner) in learners(&args).into_iter().filter(|(n, _)| args.only.as_ref().is_none_or(|o| n.contains(o.as_str()))) {
        if args.camera_thresholds {
            for camera in research::camera_thresholds(&data, &name, &learner, &progress)? {
                if args.json {
                    super::print_json_line(&serde_json::to_value(&camera)?);
                } else {
                    print_camera_threshold(&camera);
                }
            }
            continue;
        }
        let report = research::evaluate(&data, &name, &learner, &progress)?;
        if args.json {
            super::print_json_line(&serde_json::to_value(&report)?);
        } else {
            print_report(&report);
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn print_report(r: &CnnReport) {
    let pct = |v: f64| format!("{:.2}%", 100.0 * v);
    eprintln!(
        "{}: NUAA subjects never given ({} folds, logit 0): APCER {}, BPCER {}, ACER {}; worst subject APCER {}, BPCER {}; EER {}, BPCER@APCER1% {}",
        r.name,
        research::FOLDS,
        pct(r.pooled.apcer),
        pct(r.pooled.bpcer),
        pct(r.pooled.acer),
        pct(r.worst_apcer),
        pct(r.worst_bpcer),
        pct(r.eer),
        pct(r.bpcer_at_apcer_1)
    );
    for s in &r.subjects {
        eprintln!("    {}: APCER {} of {} prints, BPCER {} of {} live", s.subject, pct(s.apcer), s.attacks, pct(s.bpcer), s.live);
    }
    for s in &r.other_cameras {
        eprintln!("    {}: {} of {}", s.what, pct(s.share), s.photos);
    }
    if let Some(v) = &r.reverse {
        eprintln!(
            "    without NUAA, on NUAA: EER {}, BPCER@APCER1% {}, at logit 0 APCER {}, BPCER {}",
            pct(v.eer),
            pct(v.bpcer_at_apcer_1),
            pct(v.at_zero.apcer),
            pct(v.at_zero.bpcer)
        );
    }
    eprint!("    {:.0} s per fit", r.fit_seconds);
    match r.score_ms_per_face {
        Some(ms) => eprintln!(", {ms:.2} ms per face scored alone"),
        None => eprintln!(),
    }
}

/// One camera's own threshold against the model's even-odds point (`nuaa_threshold` is logit 0 here).
fn print_camera_threshold(c: &CameraThreshold) {
    eprintln!(
        "{} on {}: its own threshold {:.4} from {} live faces: test persons' live refused {:.2}% of {}, simulated prints taken for live {:.2}%, screens {:.2}%; at logit 0: {:.2}%, {:.2}%, {:.2}%",
        c.model,
        c.set,
        c.threshold,
        c.calibration_faces,
        100.0 * c.live_refused,
        c.test_live,
        100.0 * c.print_accepted,
        100.0 * c.screen_accepted,
        100.0 * c.nuaa_live_refused,
        100.0 * c.nuaa_print_accepted,
        100.0 * c.nuaa_screen_accepted
    );
}
