//! `facegate rekey`, `facegate backup` and `facegate restore`: the template database offline
//! (or, for `rekey` and `backup`, beside the running service).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use crate::config::{DEFAULT_DATABASE, TemplateKeyArgs};
use crate::store::{self, Store};

/// The database the command works on.
#[derive(clap::Args, Debug)]
pub struct DatabaseArgs {
    /// Database URL (`sqlite://...` or `postgres://...`), as `facegate serve --database`.
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = DEFAULT_DATABASE)]
    pub database: String,
}

#[derive(clap::Args, Debug)]
pub struct RekeyArgs {
    #[command(flatten)]
    pub database: DatabaseArgs,
    #[command(flatten)]
    pub key: TemplateKeyArgs,
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
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread().enable_all().build().context("cannot start the async runtime")
}

/// Re-wrap every subject's data key under the current (first) key of the key file, and seal the
/// subjects still stored plain. Safe beside the running service, and resumable.
pub fn run_rekey(args: RekeyArgs) -> anyhow::Result<ExitCode> {
    let keys = args.key.key_ring()?.context("rekey needs the template key file (--template-key-file or FACEGATE_TEMPLATE_KEY_FILE)")?;
    let current = keys.current_id().to_string();
    runtime()?.block_on(async {
        let store =
            Store::connect(&args.database.database, Some(keys)).await.with_context(|| format!("cannot open {}", args.database.database))?;
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

/// The site calibration (facegate_vision::recognize::site) of each model version in the store:
/// measured from the enrolled subjects' impostor pairs and stored (or removed with `--clear`).
/// One JSON line per model version. The service reads it at start-up.
pub fn run_calibrate(args: CalibrateArgs) -> anyhow::Result<ExitCode> {
    let keys = args.key.key_ring()?;
    runtime()?.block_on(async {
        let store =
            Store::connect(&args.database.database, keys).await.with_context(|| format!("cannot open {}", args.database.database))?;
        let result = calibrate(&store, &args).await;
        store.close().await;
        result
    })
}

async fn calibrate(store: &Store, args: &CalibrateArgs) -> anyhow::Result<ExitCode> {
    let versions = match &args.model_version {
        Some(v) => vec![v.clone()],
        None => store.model_versions().await?,
    };
    if versions.is_empty() {
        anyhow::bail!("the database holds no templates: enrol the deployment's subjects first");
    }
    for version in versions {
        if args.clear {
            let removed = store.clear_site_calibration(&version).await?;
            super::print_json_line(&serde_json::json!({ "model_version": version, "removed": removed }));
            continue;
        }
        let site = store.measure_site_calibration(&version).await?;
        if !args.dry_run {
            store.set_site_calibration(&site).await?;
        }
        let mut line = serde_json::to_value(&site)?;
        line["stored"] = serde_json::Value::Bool(!args.dry_run);
        super::print_json_line(&line);
    }
    Ok(ExitCode::SUCCESS)
}

/// A consistent copy of the database while the service keeps running (SQLite; PostgreSQL has pg_dump).
pub fn run_backup(args: BackupArgs) -> anyhow::Result<ExitCode> {
    runtime()?.block_on(async {
        let store =
            Store::connect(&args.database.database, None).await.with_context(|| format!("cannot open {}", args.database.database))?;
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
        let (subjects, templates) = store::restore(&args.backup, &args.database.database, args.force).await?;
        super::print_json_line(&serde_json::json!({"restored": args.database.database, "subjects": subjects, "templates": templates}));
        Ok(ExitCode::SUCCESS)
    })
}
