//! `facegate eval protection`: the protected templates measured on held-out persons:
//! accuracy plain against protected, unlinkability across secrets (D↔sys), and inversion attacks
//! with and without the secret (`facegate_research::eval::protection`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use facegate_research::dataset::Split;
use facegate_research::eval::protection;
use facegate_research::train_deep::{self, Set};
use facegate_service::Matcher;
use facegate_vision::pipeline::Pipeline;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ProtectionSet {
    /// LFW's test persons (the person-disjoint split of every other evaluation).
    Lfw,
    /// IMM's held-out persons.
    Imm,
    /// ORL's held-out persons.
    Orl,
}

#[derive(clap::Args, Debug)]
pub struct EvalProtectionArgs {
    /// The held-out persons measured on.
    #[arg(long, value_enum, default_value_t = ProtectionSet::Lfw)]
    pub dataset: ProtectionSet,
    /// Seed of the secrets drawn (A and B of two deployments, C of a guessing attacker).
    #[arg(long, default_value_t = 55)]
    pub seed: u64,
    /// The research cache folder: the photos' plain templates are kept there (made again when a
    /// model file, the pipeline's settings or the photos change).
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    /// Threads the pipeline runs on.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// One JSON line instead of the summary.
    #[arg(long)]
    pub json: bool,
}

/// The held-out persons' photos through the service's pipeline (the default recognizer), their
/// templates protected by the service's own engine, and the measurements.
pub fn run_eval(args: EvalProtectionArgs) -> anyhow::Result<ExitCode> {
    let started = std::time::Instant::now();
    let set = match args.dataset {
        ProtectionSet::Lfw => Set::Lfw,
        ProtectionSet::Imm => Set::Imm,
        ProtectionSet::Orl => Set::Orl,
    };
    let samples: Vec<_> =
        train_deep::list_samples(&facegate_paths::shared_dir())?.into_iter().filter(|s| s.set == set && s.split == Split::Test).collect();
    anyhow::ensure!(
        !samples.is_empty(),
        "no photos of {:?}'s held-out persons under {}",
        args.dataset,
        facegate_paths::shared_dir().display()
    );
    let config = crate::config::pipeline_config();
    let pipeline = Pipeline::load(&config)?;
    anyhow::ensure!(
        Matcher::max_cosine_scoring(&pipeline),
        "template protection needs a cosine-scored recognizer; {} is not",
        Matcher::model_version(&pipeline)
    );
    let bar = crate::cli::Bar::default();
    let vectors = protection::plain_templates(&pipeline, &config, &samples, &args.cache, args.threads, &bar)?;
    let (labels, found): (Vec<&str>, Vec<Vec<f32>>) =
        samples.iter().zip(vectors).filter_map(|(s, v)| v.map(|v| (s.label.as_str(), v))).unzip();
    let name = match args.dataset {
        ProtectionSet::Lfw => "LFW test persons",
        ProtectionSet::Imm => "IMM held-out persons",
        ProtectionSet::Orl => "ORL held-out persons",
    };
    let report = protection::evaluate(name, samples.len(), Arc::new(pipeline), &labels, &found, args.seed);
    let mut line = serde_json::to_value(&report)?;
    line["seed"] = args.seed.into();
    line["seconds"] = (started.elapsed().as_secs_f64().round()).into();
    if args.json {
        crate::cli::print_json_line(&line);
        return Ok(ExitCode::SUCCESS);
    }
    let pct = |v: f64| format!("{:.3}%", 100.0 * v);
    println!(
        "{}: {} of {} photos with a face, {} persons; {} genuine and {} impostor pairs; {} → {}",
        report.set,
        report.templates,
        report.photos,
        report.persons,
        report.genuine_pairs,
        report.impostor_pairs,
        report.model_version,
        report.protected_model_version
    );
    println!("  EER plain {} protected {}", pct(report.eer_plain), pct(report.eer_protected));
    println!("  FNMR at FMR 1e-3 plain {} protected {}", pct(report.fnmr_plain), pct(report.fnmr_protected));
    println!(
        "  D↔sys across secrets {:.3}, same secret {:.3}, plain across deployments {:.3} (noise floor {:.3}; {} bins, {} mated, {} non-mated pairs)",
        report.dsys_cross_secret,
        report.dsys_same_secret,
        report.dsys_plain_cross_deployment,
        report.dsys_noise_floor,
        report.dsys_bins,
        report.mated_pairs,
        report.non_mated_pairs
    );
    println!(
        "  inversion with the secret: {} of {} attempts match ({} of templates), without it {}, from {} known pairs {}",
        pct(report.inversion_match_rate),
        report.inversion_attempts,
        pct(report.inversion_template_rate),
        pct(report.inversion_match_rate_without_secret),
        report.known_pairs,
        pct(report.inversion_match_rate_known_pairs)
    );
    Ok(ExitCode::SUCCESS)
}
