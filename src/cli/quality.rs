//! `facegate train quality` and `facegate eval quality`: the unified quality score's model and the
//! error-versus-discard characteristic.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::config::Settings;
use facegate_research::eval::plot::{Chart, Scale, Series, line_chart};
use facegate_research::eval::quality::{
    self as research, EdcPoint, Measured, edc, genuine_pairs, is_held_out, lowest_first, measures, partial_area, random_edc, scored,
};
use facegate_research::train_deep::{self, Sample, Set};
use facegate_research::train_quality::{
    UNIFIED, VARIANTS, genuine_cosine_stats, genuine_match_rates, is_training, out_of_fold_logits, person_folds, train_model,
};
use facegate_vision::quality::{FEATURE_NAMES, QualityModel};
use facegate_vision::recognize::dlib::DlibModel;

/// Options both quality commands share.
#[derive(clap::Args, Debug)]
pub struct QualityDataArgs {
    /// The research cache folder, where every photo's embedding and quality components are kept
    /// (under a key of the front end's model files, its code version and the photos: made again
    /// when any changes).
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    /// Threads measuring photos.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

#[derive(clap::Args, Debug)]
pub struct TrainQualityArgs {
    /// Where to write the model.
    #[arg(long, default_value = "models/quality.bin")]
    pub out: PathBuf,
    #[command(flatten)]
    pub data: QualityDataArgs,
}

#[derive(clap::Args, Debug)]
pub struct EvalQualityCvArgs {
    /// Person-disjoint folds of the training persons.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    /// Repetitions with differently shuffled folds (the table is their mean).
    #[arg(long, default_value_t = 20)]
    pub repeats: usize,
    #[command(flatten)]
    pub data: QualityDataArgs,
}

#[derive(clap::Args, Debug)]
pub struct EvalQualityArgs {
    /// The unified score's model (default: `quality.bin` of the models folder).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Folder for the plots (`quality-edc-{imm,orl,lfw}.svg`).
    #[arg(long, default_value = "docs/img")]
    pub plots: PathBuf,
    /// The curves' numbers: set, measure, share discarded, FNMR, genuine pairs left.
    #[arg(long, default_value = "docs/quality-edc.csv")]
    pub csv: PathBuf,
    #[command(flatten)]
    pub data: QualityDataArgs,
    /// The enrolment policy whose refusals are counted (the service's flags, same defaults).
    #[command(flatten)]
    pub policy: PolicyArgs,
}

/// The service's quality policy flags, read as `facegate serve` reads them.
#[derive(clap::Args, Debug)]
pub struct PolicyArgs {
    #[arg(long, default_value_t = Settings::default().min_quality)]
    pub min_quality: f32,
    #[arg(long, default_value_t = Settings::default().min_inter_eye_px)]
    pub min_inter_eye_px: f32,
    #[arg(long, default_value_t = Settings::default().min_sharpness)]
    pub min_sharpness: f32,
    #[arg(long, default_value_t = Settings::default().min_brightness)]
    pub min_brightness: f32,
    #[arg(long, default_value_t = Settings::default().max_brightness)]
    pub max_brightness: f32,
    #[arg(long, default_value_t = Settings::default().max_yaw_deg)]
    pub max_yaw_deg: f32,
    #[arg(long, default_value_t = Settings::default().max_pitch_deg)]
    pub max_pitch_deg: f32,
}

impl PolicyArgs {
    fn settings(&self) -> Settings {
        Settings {
            min_quality: self.min_quality,
            min_inter_eye_px: self.min_inter_eye_px,
            min_sharpness: self.min_sharpness,
            min_brightness: self.min_brightness,
            max_brightness: self.max_brightness,
            max_yaw_deg: self.max_yaw_deg,
            max_pitch_deg: self.max_pitch_deg,
            ..Settings::default()
        }
    }
}

/// IMM, ORL and LFW with every photo measured (cached).
fn samples_and_measurements(data: &QualityDataArgs) -> anyhow::Result<(Vec<Sample>, Vec<Option<Measured>>)> {
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let (models, sfm) = (facegate_paths::models_dir(), facegate_paths::sfm_dir());
    let m = research::measurements(&data.cache, &models, &sfm, &samples, data.threads, &crate::cli::Bar::default())?;
    Ok((samples, m))
}

/// The deep model's threshold at FMR 1e-3, one photo enrolled: the service's decision threshold.
fn threshold(model: &DlibModel) -> f32 {
    model.operating_point(1e-3, 1).threshold
}

pub fn run_train(args: TrainQualityArgs) -> anyhow::Result<ExitCode> {
    let (samples, measured) = samples_and_measurements(&args.data)?;
    let deep = DlibModel::load(&facegate_paths::models_dir().join(facegate_vision::recognize::dlib::FILE))?;
    let photos = scored(&samples, &measured, &deep, &is_training);
    let t = threshold(&deep);
    let trained_on = format!(
        "{} photos of the training persons (IMM, ORL, LFW training split) with a face; target: each photo's share of genuine \
         comparisons clearing {} ({}'s FMR 1e-3 threshold); `facegate train quality`",
        photos.len(),
        t,
        deep.version
    );
    let model = train_model(&photos, t, trained_on);
    facegate_core::model_file::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    println!("{}: {}", args.out.display(), model.trained_on);
    println!("  bias {:+.3}", model.bias);
    for (k, name) in FEATURE_NAMES.iter().enumerate() {
        println!("  {name:<26} weight {:+.3}  (mean {:.3}, scale {:.3})", model.weights[k], model.mean[k], model.scale[k]);
    }
    Ok(ExitCode::SUCCESS)
}

/// The shares of photos discarded the characteristic is drawn at: 0 to 30 % by 1 %.
fn discard_shares() -> Vec<f64> {
    (0..=30).map(|k| k as f64 / 100.0).collect()
}

pub fn run_eval(args: EvalQualityArgs) -> anyhow::Result<ExitCode> {
    let (samples, measured) = samples_and_measurements(&args.data)?;
    let models = facegate_paths::models_dir();
    let deep = DlibModel::load(&models.join(facegate_vision::recognize::dlib::FILE))?;
    let model = QualityModel::load(&args.model.clone().unwrap_or_else(|| models.join(facegate_vision::quality::FILE)))?;
    let t = threshold(&deep);
    println!("{} at its FMR 1e-3 threshold {t}; unified score: {}", deep.version, model.trained_on);
    std::fs::create_dir_all(&args.plots)?;
    let mut csv = std::fs::File::create(&args.csv)?;
    writeln!(csv, "set,measure,discarded,fnmr,genuine_pairs")?;
    let shares = discard_shares();
    for (set, name) in [(Set::Imm, "imm"), (Set::Orl, "orl"), (Set::Lfw, "lfw")] {
        let photos = scored(&samples, &measured, &deep, &|s| is_held_out(s, set));
        let faceless = samples.iter().zip(&measured).filter(|(s, m)| is_held_out(s, set) && m.is_none()).count();
        let pairs = genuine_pairs(&photos, t);
        let mut curves: Vec<(String, Vec<EdcPoint>)> =
            measures(&photos, &model).into_iter().map(|m| (m.name, edc(&pairs, &lowest_first(&m.values), &shares))).collect();
        curves.push(("random (mean of 100)".into(), random_edc(&pairs, photos.len(), &shares, 100)));
        println!(
            "\n{name}: {} held-out photos with a face ({faceless} without), {} genuine pairs; FNMR at the threshold, discarding",
            photos.len(),
            pairs.len()
        );
        println!("  {:<34} {:>7} {:>7} {:>7} {:>7} {:>7}", "measure", "0%", "5%", "10%", "20%", "30%");
        for (measure, curve) in &curves {
            let at = |share: usize| 100.0 * curve[share].fnmr;
            println!("  {measure:<34} {:>6.2}% {:>6.2}% {:>6.2}% {:>6.2}% {:>6.2}%", at(0), at(5), at(10), at(20), at(30));
            for p in curve {
                writeln!(csv, "{name},{measure},{:.2},{:.5},{}", p.discarded, p.fnmr, p.genuine_pairs)?;
            }
        }
        let top = curves.iter().flat_map(|(_, c)| c.iter().map(|p| p.fnmr)).fold(0.0, f64::max);
        let series: Vec<Series> =
            curves.iter().map(|(m, c)| Series { name: m, points: c.iter().map(|p| (p.discarded, p.fnmr)).collect() }).collect();
        let title = format!("Error versus discard, {} held-out persons (FNMR at FMR 1e-3)", name.to_uppercase());
        let chart = Chart {
            title: &title,
            x_label: "share of lowest-quality photos discarded",
            y_label: "FNMR",
            x_range: (0.0, 0.3),
            y_range: (0.0, (top * 1.1).max(0.01)),
            x_scale: Scale::Linear,
            y_scale: Scale::Linear,
        };
        let path = args.plots.join(format!("quality-edc-{name}.svg"));
        line_chart(&path, &chart, &series)?;
        println!("  plot: {}", path.display());
    }
    component_percentiles(&samples, &measured, &model);
    policy_report(&samples, &measured, &model, &args.policy.settings());
    Ok(ExitCode::SUCCESS)
}

/// Model selection for the unified score on the training persons only: each candidate of
/// [`VARIANTS`] scored by person-disjoint k-fold cross-validation (every training photo scored by
/// the model fitted on the other folds), then the error-versus-discard characteristic of those
/// out-of-fold scores on LFW's training persons, beside each single component's on the same photos.
pub fn run_eval_cv(args: EvalQualityCvArgs) -> anyhow::Result<ExitCode> {
    let (samples, measured) = samples_and_measurements(&args.data)?;
    let deep = DlibModel::load(&facegate_paths::models_dir().join(facegate_vision::recognize::dlib::FILE))?;
    let t = threshold(&deep);
    // IMM's and ORL's training persons first, then LFW's: the characteristic is read on LFW's.
    let mut photos = scored(&samples, &measured, &deep, &|s| is_training(s) && s.set != Set::Lfw);
    let lfw_start = photos.len();
    photos.extend(scored(&samples, &measured, &deep, &|s| is_training(s) && s.set == Set::Lfw));
    let lfw = &photos[lfw_start..];
    let pairs = genuine_pairs(lfw, t);
    let rates = genuine_match_rates(&photos, t);
    let cosines = genuine_cosine_stats(&photos);
    let shares = discard_shares();
    println!(
        "{} training photos ({} of LFW's training persons, {} genuine pairs there); {}-fold person-disjoint cross-validation, {} \
         repeats; FNMR at {t} ({}'s FMR 1e-3 threshold) of LFW's training persons, discarding",
        photos.len(),
        lfw.len(),
        pairs.len(),
        args.folds,
        args.repeats,
        deep.version
    );
    // Per measure: partial areas over 0–10 % and 0–30 %, FNMR at 0, 5, 10, 20 and 30 %.
    let summary = |curve: &[EdcPoint]| {
        [partial_area(curve, 0.1), partial_area(curve, 0.3), curve[0].fnmr, curve[5].fnmr, curve[10].fnmr, curve[20].fnmr, curve[30].fnmr]
    };
    let mut rows: Vec<(String, [f64; 7])> = Vec::new();
    for variant in VARIANTS {
        let mut mean = [0.0; 7];
        for repeat in 0..args.repeats {
            let fold = person_folds(&photos, args.folds, repeat as u64);
            let logits = out_of_fold_logits(variant, &photos, &fold, args.folds, &rates, &cosines);
            let curve = edc(&pairs, &lowest_first(&logits[lfw_start..]), &shares);
            summary(&curve).iter().zip(&mut mean).for_each(|(v, m)| *m += v / args.repeats as f64);
        }
        let adopted = if *variant == UNIFIED { " (models/quality.bin)" } else { "" };
        rows.push((format!("unified: {}{adopted}", variant.name), mean));
    }
    let committed = facegate_vision::quality::QualityModel {
        format: facegate_vision::quality::FORMAT,
        mean: vec![0.0; facegate_vision::quality::FEATURES],
        scale: vec![1.0; facegate_vision::quality::FEATURES],
        weights: vec![0.0; facegate_vision::quality::FEATURES],
        bias: 0.0,
        trained_on: String::new(),
    };
    // The components need no training: one characteristic each, on the same photos.
    for m in measures(lfw, &committed).into_iter().skip(1) {
        rows.push((m.name, summary(&edc(&pairs, &lowest_first(&m.values), &shares))));
    }
    rows.push(("random (mean of 100)".into(), summary(&random_edc(&pairs, lfw.len(), &shares, 100))));
    println!("  {:<72} {:>8} {:>8} {:>7} {:>7} {:>7} {:>7} {:>7}", "measure", "pA 0-10", "pA 0-30", "0%", "5%", "10%", "20%", "30%");
    for (name, v) in &rows {
        let pct = v.map(|x| 100.0 * x);
        println!(
            "  {name:<72} {:>7.2}% {:>7.2}% {:>6.2}% {:>6.2}% {:>6.2}% {:>6.2}% {:>6.2}%",
            pct[0], pct[1], pct[2], pct[3], pct[4], pct[5], pct[6]
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Each component's 1st, 5th, 50th and 95th percentile per set (all persons): the scales in
/// practice, from which the policy's limits are chosen.
fn component_percentiles(samples: &[Sample], measured: &[Option<Measured>], model: &QualityModel) {
    type Pick = fn(&facegate_vision::quality::Quality) -> Option<f32>;
    let columns: [(&str, Pick); 11] = [
        ("score", |q| Some(q.score)),
        ("inter_eye_px", |q| Some(q.components.inter_eye_px)),
        ("sharpness", |q| Some(q.components.sharpness)),
        ("brightness", |q| Some(q.components.brightness)),
        ("contrast", |q| Some(q.components.contrast)),
        ("illumination_uniformity", |q| Some(q.components.illumination_uniformity)),
        ("yaw_abs_deg", |q| q.components.yaw_abs_deg),
        ("pitch_abs_deg", |q| q.components.pitch_abs_deg),
        ("fit_residual", |q| q.components.fit_residual),
        ("mirror_agreement", |q| q.components.mirror_agreement),
        ("embedding_norm", |q| q.components.embedding_norm),
    ];
    println!(
        "
components, all persons: 1st / 5th / 50th / 95th percentile"
    );
    for (set, name) in [(Set::Imm, "IMM"), (Set::Orl, "ORL"), (Set::Lfw, "LFW")] {
        let assessed: Vec<_> = samples
            .iter()
            .zip(measured)
            .filter(|(s, _)| s.set == set)
            .filter_map(|(_, m)| m.as_ref().map(|m| model.assess(m.components)))
            .collect();
        println!("  {name} ({} photos with a face)", assessed.len());
        for (column, pick) in columns {
            let mut v: Vec<f32> = assessed.iter().filter_map(pick).collect();
            v.sort_by(f32::total_cmp);
            let at = |p: f64| v.get(((v.len().max(1) - 1) as f64 * p).round() as usize).copied().unwrap_or(f32::NAN);
            println!("    {column:<24} {:>8.3} {:>8.3} {:>8.3} {:>8.3}", at(0.01), at(0.05), at(0.5), at(0.95));
        }
    }
}

/// How many IMM, ORL and LFW photos (all persons, and the held-out ones) the policy refuses, by limit.
fn policy_report(samples: &[Sample], measured: &[Option<Measured>], model: &QualityModel, settings: &Settings) {
    let policy = settings.quality_policy();
    println!("\nenrolment policy {policy:?}");
    for (set, name) in [(Set::Imm, "IMM"), (Set::Orl, "ORL"), (Set::Lfw, "LFW")] {
        for (scope, held_out_only) in [("all persons", false), ("held-out persons", true)] {
            let assessed: Vec<_> = samples
                .iter()
                .zip(measured)
                .filter(|(s, _)| s.set == set && (!held_out_only || is_held_out(s, set)))
                .filter_map(|(_, m)| m.as_ref().map(|m| model.assess(m.components)))
                .collect();
            let failures: Vec<Vec<&str>> = assessed.iter().map(|q| policy.failures(q).iter().map(|f| f.component).collect()).collect();
            let refused = failures.iter().filter(|f| !f.is_empty()).count();
            let mut by_limit: std::collections::BTreeMap<&str, usize> = Default::default();
            failures.iter().flatten().for_each(|c| *by_limit.entry(c).or_default() += 1);
            println!(
                "  {name} {scope}: refuses {refused} of {} photos with a face ({:.1}%); by limit {by_limit:?}",
                assessed.len(),
                100.0 * refused as f64 / assessed.len().max(1) as f64
            );
        }
    }
}
