//! `facegate rekey`, `facegate renew-protection`, `facegate backup`, `facegate restore`, `facegate
//! calibrate` and `facegate calibrate-liveness`: the template database offline (or, for `rekey` and
//! `backup`, beside the running service), and the deployment's calibrations kept in it.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;

use crate::config::{DEFAULT_DATABASE, TemplateKeyArgs, TemplateProtectionArgs};
use facegate_service::liveness_camera::{self, DEFAULT_BPCER, LivenessCalibration};
use facegate_service::protection::{ProtectedEngine, Renewal};
use facegate_service::site::{self, SiteCalibration};
use facegate_service::{FaceEngine, Matcher};
use facegate_store::Store;
use facegate_vision::liveness::LivenessModel;
use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::RecognizerKind;

use crate::choices::{Detector, Recognizer};
use facegate_detect::DetectorKind;

/// The database the command works on.
#[derive(clap::Args, Debug)]
pub struct DatabaseArgs {
    /// Database URL (`sqlite://...` or `postgres://...`), as `facegate serve --database`.
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = DEFAULT_DATABASE)]
    pub database: String,
    /// A file whose first line is the PostgreSQL password, as `facegate serve --database-password-file`.
    #[arg(long, env = "FACEGATE_DATABASE_PASSWORD_FILE")]
    pub database_password_file: Option<PathBuf>,
}

impl DatabaseArgs {
    /// The URL to connect to (the password file's password merged in) and the URL as printed
    /// (its password redacted).
    fn url(&self) -> anyhow::Result<(String, String)> {
        crate::database_url::connect_and_shown(&self.database, self.database_password_file.as_deref())
    }
}

#[derive(clap::Args, Debug)]
pub struct RekeyArgs {
    #[command(flatten)]
    pub database: DatabaseArgs,
    #[command(flatten)]
    pub key: TemplateKeyArgs,
}

#[derive(clap::Args, Debug)]
pub struct RenewProtectionArgs {
    #[command(flatten)]
    pub database: DatabaseArgs,
    /// The template key file, as `facegate serve`, when the database is sealed: renewed vectors are
    /// sealed again under each subject's own data key.
    #[command(flatten)]
    pub key: TemplateKeyArgs,
    /// The protection secret the stored templates are protected under now (the key file
    /// `serve --template-protection-key-file` was given).
    #[arg(long, required_unless_present = "from_plain")]
    pub old_key_file: Option<PathBuf>,
    /// The new protection secret (64 hex digits, `openssl rand -hex 32`): every template is
    /// protected under it afterwards; start the service with it.
    #[arg(long)]
    pub new_key_file: PathBuf,
    /// The stored templates are plain (enrolled without a protection secret): protect the
    /// recognizer's templates under the new secret.
    #[arg(long, conflicts_with = "old_key_file")]
    pub from_plain: bool,
    /// With --from-plain: the recognizer whose plain templates are protected, as `facegate serve
    /// --recognizer`.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = Recognizer::from(RecognizerKind::default()))]
    pub recognizer: Recognizer,
    /// With --from-plain: the trained models, as `facegate serve --models`.
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct BackupArgs {
    /// The backup file to write (must not exist).
    pub out: PathBuf,
    #[command(flatten)]
    pub database: DatabaseArgs,
}

#[derive(clap::Args, Debug)]
pub struct RestoreArgs {
    /// A backup file made by `facegate backup`.
    pub backup: PathBuf,
    #[command(flatten)]
    pub database: DatabaseArgs,
    /// Replace an existing database (never one another process has open).
    #[arg(long)]
    pub force: bool,
}

#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    #[command(flatten)]
    pub database: DatabaseArgs,
    #[command(flatten)]
    pub key: TemplateKeyArgs,
    /// Only this model version (default: every version the stored templates were made by).
    #[arg(long)]
    pub model_version: Option<String>,
    /// Measure and print; store nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Remove the stored site calibration instead (the service then uses the model's thresholds).
    #[arg(long, conflicts_with = "dry_run")]
    pub clear: bool,
    /// The trained models, as `facegate serve --models`: the recognizer's thresholds tell which
    /// pairs of ids score like one person (suspected duplicates, left out of the calibration).
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
    /// The recognizer, as `facegate serve --recognizer`: its model version is the one calibrated.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = Recognizer::from(RecognizerKind::default()))]
    pub recognizer: Recognizer,
    /// Largest rise of a threshold (site minus model, in score) stored without --accept-raise: a
    /// calibration that would raise one further is printed with the ids carrying its tail, and not
    /// stored (exit status 3). Lab photos of one camera raised 1e-3 by about 0.013; ids poisoned
    /// with look-alikes by 0.03–0.04 (docs/recognition.md).
    #[arg(long, default_value_t = DEFAULT_MAX_RAISE)]
    pub max_raise: f32,
    /// Store the calibration even when it raises a threshold by more than --max-raise (after
    /// checking the ids its warning names).
    #[arg(long, conflicts_with = "clear")]
    pub accept_raise: bool,
    /// Write every suspected duplicate pair of ids to this CSV file (`subject_a,subject_b,score`,
    /// highest first; the JSON line lists the first 100).
    #[arg(long, conflicts_with = "clear")]
    pub duplicates_csv: Option<PathBuf>,
    #[command(flatten)]
    pub protection: TemplateProtectionArgs,
}

/// `calibrate --max-raise`'s default.
pub const DEFAULT_MAX_RAISE: f32 = 0.02;

/// The exit status of a calibration refused for its raise.
const RAISE_REFUSED: u8 = 3;

#[derive(clap::Args, Debug)]
pub struct CalibrateLivenessArgs {
    /// Live captures of the deployment's camera (people in front of it, never prints or screens):
    /// image files, or folders searched for them. At least 1 / --bpcer faces.
    #[arg(required_unless_present = "clear")]
    pub live: Vec<PathBuf>,
    /// The share of those live faces the threshold may refuse, strictly between 0 and 0.5.
    #[arg(long, default_value_t = DEFAULT_BPCER)]
    pub bpcer: f64,
    #[command(flatten)]
    pub database: DatabaseArgs,
    /// Measure and print; store nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Remove the stored liveness calibration instead (the service then uses the model's threshold).
    #[arg(long, conflicts_with_all = ["dry_run", "live"])]
    pub clear: bool,
    /// The trained models, as `facegate serve --models`: the liveness model calibrated is theirs.
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
    /// The face detector, as `facegate serve --detector`: it places the crops the liveness model reads.
    #[arg(long, env = "FACEGATE_DETECTOR", value_enum, default_value_t = Detector::from(DetectorKind::default()))]
    pub detector: Detector,
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread().enable_all().build().context("cannot start the async runtime")
}

/// Re-wrap every subject's data key under the current (first) key of the key file, and seal the
/// subjects still stored plain. Safe beside the running service, and resumable.
pub fn run_rekey(args: RekeyArgs) -> anyhow::Result<ExitCode> {
    let keys = args.key.key_ring()?.context("rekey needs the template key file (--template-key-file or FACEGATE_TEMPLATE_KEY_FILE)")?;
    let current = keys.current_id().to_string();
    let (url, shown) = args.database.url()?;
    runtime()?.block_on(async {
        let store = Store::connect(&url, Some(keys)).await.with_context(|| format!("cannot open {shown}"))?;
        let bar = super::progress(0, "rekey");
        let report = store
            .rekey(|r| {
                bar.set_position(r.rewrapped + r.sealed);
            })
            .await;
        bar.finish_and_clear();
        store.close().await;
        let report = report?;
        super::print_json_line(&serde_json::json!({
            "key_id": current,
            "rewrapped": report.rewrapped,
            "sealed": report.sealed,
            "templates_sealed": report.templates_sealed,
        }));
        Ok(ExitCode::SUCCESS)
    })
}

/// A protection key file's secret.
fn protection_key(path: &Path) -> anyhow::Result<facegate_service::protection::ProtectionKey> {
    let args = TemplateProtectionArgs { template_protection_key_file: Some(path.to_path_buf()) };
    Ok(args.key()?.expect("a key file is given"))
}

/// Every template protected under the old secret (or, `--from-plain`, every plain template of the
/// recognizer) rewritten under the new one without the photos, and the site calibrations of those
/// versions carried over: one transaction (`Store::renew_templates`), so a failure leaves the
/// database as it was, and a second run after a finished one changes nothing. The service must be
/// stopped (every replica): one still running under the old secret would enrol old templates,
/// which the new key's start-up refuses until this is run again.
pub fn run_renew_protection(args: RenewProtectionArgs) -> anyhow::Result<ExitCode> {
    let new = protection_key(&args.new_key_file)?;
    let mut renewal = match &args.old_key_file {
        Some(old) => Renewal::between(protection_key(old)?, new).map_err(anyhow::Error::msg)?,
        None => {
            let config = PipelineConfig { recognizer: args.recognizer.into(), ..crate::config::pipeline_config() };
            let config = PipelineConfig { models_dir: args.models.clone().unwrap_or(config.models_dir), ..config };
            let pipeline = Pipeline::load(&config).context("cannot load the recognizer")?;
            let engine = ProtectedEngine::new(Arc::new(pipeline), new.clone())?;
            Renewal::from_plain(engine.plain_version(), new)
        }
    };
    let keys = args.key.key_ring()?;
    let (url, shown) = args.database.url()?;
    runtime()?.block_on(async {
        let store = Store::connect_existing(&url, keys).await.with_context(|| format!("cannot open {shown}"))?;
        let report = store.renew_templates(&mut renewal).await;
        let stored = store.model_versions().await;
        store.close().await;
        let report = report.with_context(|| format!("nothing was changed in {shown}"))?;
        let stored = stored?;
        let new_suffix = format!("+{}-{}", facegate_service::protection::SCHEME, renewal.new_key_id());
        if report.versions.is_empty() && !stored.iter().any(|v| v.ends_with(&new_suffix)) {
            anyhow::bail!(
                "{shown} holds no template {} (its model versions: {}): nothing renewed",
                if args.from_plain { "of the recognizer, plain" } else { "protected under the old secret" },
                if stored.is_empty() { "none".to_string() } else { stored.join(", ") }
            );
        }
        super::print_json_line(&serde_json::json!({
            "new_key_id": renewal.new_key_id(),
            "subjects": report.subjects,
            "templates": report.templates,
            "versions": report.versions,
            "already_renewed": report.versions.is_empty(),
        }));
        Ok(ExitCode::SUCCESS)
    })
}

/// The site calibration (`facegate_service::site`) of the recognizer's model version: measured from
/// the enrolled subjects' impostor pairs, suspected duplicate identities left out and named, and
/// stored (or removed with `--clear`). One JSON line per model version. The service reads it at
/// start-up. The database must exist: a mistyped path is refused, never created.
pub fn run_calibrate(args: CalibrateArgs) -> anyhow::Result<ExitCode> {
    let keys = args.key.key_ring()?;
    let (url, shown) = args.database.url()?;
    runtime()?.block_on(async {
        let store = Store::connect_existing(&url, keys).await.with_context(|| format!("cannot open {shown}"))?;
        let result = if args.clear { clear(&store, &args).await } else { calibrate(&store, &args).await };
        store.close().await;
        result
    })
}

/// `--clear`: the named version, or every version with a stored calibration.
async fn clear(store: &Store, args: &CalibrateArgs) -> anyhow::Result<ExitCode> {
    let versions = match &args.model_version {
        Some(v) => vec![v.clone()],
        None => store.calibrated_versions().await?,
    };
    for version in versions {
        let removed = store.clear_site_calibration(&version).await?;
        super::print_json_line(&serde_json::json!({ "model_version": version, "removed": removed }));
    }
    Ok(ExitCode::SUCCESS)
}

async fn calibrate(store: &Store, args: &CalibrateArgs) -> anyhow::Result<ExitCode> {
    let stored = store.model_versions().await?;
    if stored.is_empty() {
        anyhow::bail!("the database holds no templates: enrol the deployment's subjects first");
    }
    let config = PipelineConfig { recognizer: args.recognizer.into(), ..crate::config::pipeline_config() };
    let config = PipelineConfig { models_dir: args.models.clone().unwrap_or(config.models_dir), ..config };
    let pipeline = tokio::task::spawn_blocking(move || Pipeline::load(&config)).await?.context("cannot load the recognizer")?;
    anyhow::ensure!(
        Matcher::max_cosine_scoring(&pipeline),
        "the site calibration is for cosine-scored recognizers; {} keeps its own thresholds",
        pipeline.recognizer.model_version()
    );
    // With the protection secret, the templates calibrated are the protected ones.
    let matcher: Arc<dyn FaceEngine> = match args.protection.key()? {
        Some(key) => Arc::new(ProtectedEngine::new(Arc::new(pipeline), key)?),
        None => Arc::new(pipeline),
    };
    let version = matcher.model_version().to_string();
    if let Some(asked) = args.model_version.as_ref().filter(|asked| **asked != version) {
        anyhow::bail!("--model-version {asked} is not the recognizer's ({version}): pass the --recognizer (and --models) that make it");
    }
    for other in stored.iter().filter(|v| **v != version) {
        let why = "no template of the current recognizer; its subjects must enrol again";
        super::print_json_line(&serde_json::json!({ "model_version": other, "stored": false, "skipped": why }));
    }
    anyhow::ensure!(args.max_raise.is_finite() && args.max_raise >= 0.0, "--max-raise must be 0 or more");
    let site = site::measure(store, matcher.as_ref()).await?;
    warn_of_duplicates(&site);
    if let Some(path) = &args.duplicates_csv {
        write_duplicates_csv(path, &site)?;
    }
    report_pull(&site);
    let too_far = site.largest_raise().filter(|p| p.raise > args.max_raise && !args.accept_raise);
    if let Some(p) = too_far {
        eprintln!(
            "{}: the calibration would raise the threshold at FMR {:e} by {:.4} ({:.4} → {:.4}), more than --max-raise {}: \
             check the ids above (one person under several ids, or look-alikes enrolled on purpose); erase or merge them and \
             calibrate again, or store it with --accept-raise",
            if args.dry_run { "warning" } else { "error" },
            p.fmr,
            p.raise,
            p.model_threshold,
            p.site_threshold,
            args.max_raise
        );
    }
    let stored = !args.dry_run && too_far.is_none();
    if stored {
        site::save(store, &site).await?;
    }
    let mut line = serde_json::to_value(&site)?;
    line["stored"] = serde_json::Value::Bool(stored);
    super::print_json_line(&line);
    // A dry run stores nothing either way: the warning says what a real run would refuse.
    Ok(if too_far.is_some() && !args.dry_run { ExitCode::from(RAISE_REFUSED) } else { ExitCode::SUCCESS })
}

/// Each calibrated FMR's threshold against the model's on standard error, with the ids most in
/// the impostor pairs above the model's threshold where the site raises it.
fn report_pull(site: &SiteCalibration) {
    for p in &site.pull {
        eprintln!(
            "FMR {:e}: model threshold {:.4}, site {:.4} ({:+.4}{}); {} impostor pair(s) at or above the model's threshold, {:.1} expected",
            p.fmr,
            p.model_threshold,
            p.site_threshold,
            p.raise,
            if p.raise > 0.0 { ", raised" } else { ", the model's kept" },
            p.tail_pairs,
            p.expected_tail_pairs
        );
        if p.raise > 0.0 && !p.tail_ids.is_empty() {
            let ids: Vec<String> = p.tail_ids.iter().map(|t| format!("{} ({})", t.subject, t.pairs)).collect();
            eprintln!("  ids in most of those pairs: {}", ids.join(", "));
        }
    }
}

/// Every suspected duplicate pair as CSV (subject ids are CSV-safe: `A-Z a-z 0-9 . _ -`).
fn write_duplicates_csv(path: &std::path::Path, site: &SiteCalibration) -> anyhow::Result<()> {
    let mut text = String::from("subject_a,subject_b,score\n");
    for d in &site.every_suspected_duplicate {
        text.push_str(&format!("{},{},{:.6}\n", d.subjects[0], d.subjects[1], d.score));
    }
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
    eprintln!("{} suspected pair(s) of ids written to {}", site.every_suspected_duplicate.len(), path.display());
    Ok(())
}

/// The liveness threshold of the deployment's camera (`facegate_service::liveness_camera`): the
/// liveness model scores every live capture given, the threshold that refuses at most `--bpcer` of
/// them is stored (or the stored one removed with `--clear`), and the service uses it from its next
/// start. One JSON line. The database must exist, as for `facegate calibrate`; it is opened before
/// any photo is scored, so a mistyped one is refused at once.
pub fn run_calibrate_liveness(args: CalibrateLivenessArgs) -> anyhow::Result<ExitCode> {
    let config = PipelineConfig { detector: args.detector.into(), ..crate::config::pipeline_config() };
    let config = PipelineConfig { models_dir: args.models.clone().unwrap_or(config.models_dir), ..config };
    let pipeline = Pipeline::load(&config).context("cannot load the face pipeline")?;
    let model = pipeline.liveness.as_ref().with_context(|| {
        format!("no liveness model ({}) in {}: nothing to calibrate", facegate_vision::liveness::FILE, config.models_dir.display())
    })?;
    let photos = if args.clear { Vec::new() } else { image_files(&args.live)? };
    anyhow::ensure!(args.clear || !photos.is_empty(), "no image files (.jpg, .jpeg, .png, .pgm, .ppm, .bmp, .webp) in {:?}", args.live);
    let (url, shown) = args.database.url()?;
    runtime()?.block_on(async {
        let store = match args.dry_run {
            true => None,
            false => Some(Store::connect_existing(&url, None).await.with_context(|| format!("cannot open {shown}"))?),
        };
        let done = match &store {
            Some(store) if args.clear => {
                let removed = store.clear_liveness_calibration(&model.name).await?;
                super::print_json_line(&serde_json::json!({ "model": model.name, "removed": removed }));
                Ok(())
            }
            _ => calibrate_liveness(&pipeline, model, &photos, args.bpcer, store.as_ref()).await,
        };
        if let Some(store) = store {
            store.close().await;
        }
        done.map(|()| ExitCode::SUCCESS)
    })
}

/// Score `photos` with `model` (through `pipeline`), make the calibration and store it in `store`
/// (none: a dry run); its JSON line on stdout.
async fn calibrate_liveness(
    pipeline: &Pipeline,
    model: &LivenessModel,
    photos: &[PathBuf],
    bpcer: f64,
    store: Option<&Store>,
) -> anyhow::Result<()> {
    let bar = super::progress(photos.len() as u64, "live captures");
    let (mut scores, mut not_read) = (Vec::with_capacity(photos.len()), 0usize);
    for path in photos {
        let photo = facegate_core::imaging::open(path).with_context(|| format!("cannot read {}", path.display()))?;
        match pipeline.analyze(&photo).map(|a| a.liveness) {
            Ok(Some(liveness)) => scores.push(liveness.score),
            Ok(None) => anyhow::bail!("the liveness model gave {} no score", path.display()),
            Err(e) => {
                bar.suspend(|| eprintln!("warning: {}: {e}: not counted", path.display()));
                not_read += 1;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let calibration = LivenessCalibration::from_scores(model, &scores, bpcer)?;
    if let Some(store) = store {
        liveness_camera::save(store, &calibration).await?;
    }
    let mut line = serde_json::to_value(&calibration)?;
    line["photos"] = photos.len().into();
    line["without_face"] = not_read.into();
    line["stored"] = store.is_some().into();
    super::print_json_line(&line);
    Ok(())
}

/// The image files among `paths`, folders searched through, in name order.
fn image_files(paths: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    fn walk(path: &Path, out: &mut Vec<PathBuf>) -> anyhow::Result<()> {
        if path.is_dir() {
            let mut entries: Vec<PathBuf> = std::fs::read_dir(path)
                .with_context(|| format!("cannot list {}", path.display()))?
                .map(|e| e.map(|e| e.path()))
                .collect::<Result<_, _>>()?;
            entries.sort();
            for entry in entries {
                walk(&entry, out)?;
            }
        } else {
            let image = ["jpg", "jpeg", "png", "pgm", "ppm", "bmp", "webp"];
            let extension = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
            anyhow::ensure!(path.exists(), "{} does not exist", path.display());
            if extension.is_some_and(|e| image.contains(&e.as_str())) {
                out.push(path.to_path_buf());
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    for path in paths {
        walk(path, &mut out)?;
    }
    Ok(out)
}

/// Suspected duplicate identities on standard error, for the operator to merge or erase.
fn warn_of_duplicates(site: &SiteCalibration) {
    if site.suspected_duplicates.is_empty() {
        return;
    }
    const SHOWN: usize = 20;
    let pairs = site.duplicate_id_pairs;
    eprintln!(
        "warning: {pairs} pair(s) of ids score like one person (at or above {:.4}); their {} template pair(s) were left out of the calibration; {}:",
        site.duplicate_threshold.unwrap_or(f32::INFINITY),
        site.duplicate_pairs_left_out,
        if pairs > SHOWN {
            format!("the {SHOWN} highest (the JSON line lists up to {}, --duplicates-csv all)", site.suspected_duplicates.len())
        } else {
            "they are".into()
        }
    );
    for d in site.suspected_duplicates.iter().take(SHOWN) {
        eprintln!("  {} and {} ({:.4})", d.subjects[0], d.subjects[1], d.score);
    }
}

/// A consistent copy of the database while the service keeps running (SQLite; PostgreSQL has pg_dump).
pub fn run_backup(args: BackupArgs) -> anyhow::Result<ExitCode> {
    let (url, shown) = args.database.url()?;
    runtime()?.block_on(async {
        let store = Store::connect(&url, None).await.with_context(|| format!("cannot open {shown}"))?;
        let done = store.backup(&args.out).await;
        store.close().await;
        done?;
        let (subjects, templates) = {
            // The copy is read back to report what it holds.
            let copy = Store::connect(&format!("sqlite://{}", args.out.display()), None).await?;
            let counts = copy.counts().await?;
            copy.close().await;
            counts
        };
        super::print_json_line(&serde_json::json!({"backup": args.out, "subjects": subjects, "templates": templates}));
        Ok(ExitCode::SUCCESS)
    })
}

/// Replace the database with a backup (the service stopped; SQLite; PostgreSQL has pg_restore).
pub fn run_restore(args: RestoreArgs) -> anyhow::Result<ExitCode> {
    runtime()?.block_on(async {
        let (url, shown) = args.database.url()?;
        let (subjects, templates) = facegate_store::restore(&args.backup, &url, args.force).await?;
        super::print_json_line(&serde_json::json!({"restored": shown, "subjects": subjects, "templates": templates}));
        Ok(ExitCode::SUCCESS)
    })
}
