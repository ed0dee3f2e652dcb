//! The composition root: the one place the application is put together from the [`Settings`] —
//! the store (its template keys checked), the face pipeline (loaded, its liveness settings and the
//! site calibration applied), the service and the HTTP state over them, the identification
//! gallery, the listener and the router. `facegate serve` runs what [`Application::build`] makes;
//! the HTTP integration tests build theirs through [`Application::builder`], with a stand-in face
//! engine or a pipeline loaded once for many apps, so they test the application `serve` runs.
//!
//! The runtime crates never see the settings: this module hands them plain values
//! (`ApiConfig`, `ServerLimits`, a `KeyRing`, a `PipelineConfig`).

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::Context;
use tokio::net::TcpListener;

use crate::config::Settings;
use facegate_http::server::{self, ServerLimits, Stopped};
use facegate_http::{ApiConfig, AppState};
use facegate_service::liveness::ThresholdSource;
use facegate_service::protection::{ProtectedEngine, check_stored_versions};
use facegate_service::site::SiteStatus;
use facegate_service::{FaceEngine, Facegate, LivenessPolicy, Matcher};
use facegate_store::{KeyCheck, KeyRing, Store};
use facegate_vision::pipeline::Pipeline;

/// The target of the start-up and shutdown log lines: `facegate serve`'s module, where they were
/// first written, which operators and the scripts filter on (`RUST_LOG=facegate::cli::serve=info`
/// shows the address a `--bind …:0` listens on).
const SERVE_LOG: &str = "facegate::cli::serve";

/// `tracing`'s event macros with the target [`SERVE_LOG`].
macro_rules! info {
    ($($event:tt)*) => { tracing::info!(target: SERVE_LOG, $($event)*) };
}
macro_rules! warn {
    ($($event:tt)*) => { tracing::warn!(target: SERVE_LOG, $($event)*) };
}
macro_rules! error {
    ($($event:tt)*) => { tracing::error!(target: SERVE_LOG, $($event)*) };
}

/// The application, built and listening (its gallery loaded); [`Application::run_until_stopped`]
/// serves it.
pub struct Application {
    listener: TcpListener,
    address: SocketAddr,
    state: AppState,
    limits: ServerLimits,
}

/// What [`Application::builder`] takes in place of what the settings would make: each part given
/// here is used as it is, every other one is made from the settings as `facegate serve` makes it.
pub struct ApplicationBuilder {
    settings: Settings,
    config: Option<ApiConfig>,
    limits: Option<ServerLimits>,
    engine: Option<Arc<dyn FaceEngine>>,
    store: Option<Store>,
    /// `Some` replaces the key ring of `--template-key-file` (`Some(None)`: no key).
    template_keys: Option<Option<KeyRing>>,
}

impl Application {
    /// `facegate serve`'s application, everything made from `settings`.
    pub async fn build(settings: Settings) -> anyhow::Result<Application> {
        Application::builder(settings).build().await
    }

    /// An application from `settings`, some of whose parts may be given instead.
    pub fn builder(settings: Settings) -> ApplicationBuilder {
        ApplicationBuilder { settings, config: None, limits: None, engine: None, store: None, template_keys: None }
    }

    /// The address it listens on (the port chosen when the settings bind port 0).
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// The service and the HTTP layer's settings the router is built over.
    pub fn state(&self) -> &AppState {
        &self.state
    }

    /// Serve until `shutdown` completes, let the connections drain within the grace period, then
    /// stop following the other replicas' changes and close the store.
    pub async fn run_until_stopped(self, shutdown: impl Future<Output = ()>) {
        let Application { listener, state, limits, .. } = self;
        match server::serve(listener, facegate_http::router(state.clone()), limits, shutdown).await {
            Stopped::Drained => info!("every connection finished"),
            Stopped::GraceExpired => {
                warn!(grace_s = limits.shutdown_grace.as_secs_f64(), "connections still open after the grace period were dropped")
            }
        }
        state.facegate().stop_following();
        state.store().close().await;
        info!("stopped");
    }
}

impl ApplicationBuilder {
    /// This API configuration instead of `Settings::api_config`'s.
    pub fn api_config(mut self, config: ApiConfig) -> ApplicationBuilder {
        self.config = Some(config);
        self
    }

    /// These connection limits instead of `Settings::server_limits`'s.
    pub fn server_limits(mut self, limits: ServerLimits) -> ApplicationBuilder {
        self.limits = Some(limits);
        self
    }

    /// This face engine instead of the pipeline the settings load (the tests' stand-in, or a
    /// pipeline loaded once and shared): used as it is (its liveness model is not dropped under
    /// `--liveness off`); the service's liveness threshold and site calibration are made for it
    /// as for a loaded one.
    pub fn engine(mut self, engine: Arc<dyn FaceEngine>) -> ApplicationBuilder {
        self.engine = Some(engine);
        self
    }

    /// This open store instead of connecting to the settings' database (its template keys are
    /// still checked). From here it is the application's: closed when it stops.
    pub fn store(mut self, store: Store) -> ApplicationBuilder {
        self.store = Some(store);
        self
    }

    /// These template keys instead of the key file the settings name.
    pub fn template_keys(mut self, keys: Option<KeyRing>) -> ApplicationBuilder {
        self.template_keys = Some(keys);
        self
    }

    /// Build the application: the settings checked, the store opened and its keys checked, the
    /// pipeline loaded, the gallery loaded, the listener bound. A start-up that fails after the
    /// store was opened closes it where `facegate serve` always has (a refused key, a pipeline
    /// that cannot be loaded or its site calibration read).
    pub async fn build(self) -> anyhow::Result<Application> {
        let settings = self.settings;
        let config = match self.config {
            Some(config) => config,
            None => settings.api_config()?,
        };
        let limits = match self.limits {
            Some(limits) => limits,
            None => settings.server_limits()?,
        };
        // The store and its keys first: a database the keys cannot read stops the start-up before
        // the models are loaded.
        let store = match self.store {
            Some(store) => store,
            None => connect(&settings, self.template_keys).await?,
        };
        if let Err(refused) = template_keys_open_the_store(&store, &settings).await {
            store.close().await;
            return Err(refused);
        }
        log_api_keys(&config, &settings.bind);
        let engine: Arc<dyn FaceEngine> = match self.engine {
            Some(engine) => engine,
            None => match load_pipeline(&settings).await {
                Ok(pipeline) => Arc::new(pipeline),
                Err(e) => {
                    store.close().await;
                    return Err(e);
                }
            },
        };
        let engine = match protect(engine, &settings, &store).await {
            Ok(engine) => engine,
            Err(e) => {
                store.close().await;
                return Err(e);
            }
        };
        info!(workers = config.workers, queue = config.queue_depth, enroll_queue = config.enroll_queue_depth, "bounded work pool");
        let state = AppState::new(engine, store, config);
        load_site_calibration(state.facegate()).await?;
        load_liveness_calibration(state.facegate()).await?;
        load_gallery(&state).await?;
        let listener = TcpListener::bind(&settings.bind).await.with_context(|| format!("cannot listen on {}", settings.bind))?;
        let address = listener.local_addr()?;
        info!(
            max_connections = limits.max_connections,
            header_timeout_s = limits.header_timeout.as_secs_f64(),
            "listening on http://{}",
            address
        );
        Ok(Application { listener, address, state, limits })
    }
}

/// `engine` with its templates protected under the settings' protection secret, if any; refused
/// when the database holds templates of the other kind, or of another secret.
async fn protect(engine: Arc<dyn FaceEngine>, settings: &Settings, store: &Store) -> anyhow::Result<Arc<dyn FaceEngine>> {
    let stored = store.model_versions().await.context("cannot read the stored model versions")?;
    let plain = engine.model_version().to_string();
    let Some(key) = settings.template_protection.key()? else {
        check_stored_versions(&stored, &plain, None).map_err(anyhow::Error::msg)?;
        return Ok(engine);
    };
    let protected = ProtectedEngine::new(engine, key)?;
    check_stored_versions(&stored, &plain, Some(protected.model_version())).map_err(anyhow::Error::msg)?;
    info!(key_id = protected.key_id(), model_version = protected.model_version(), "templates are protected (keyed rotation)");
    Ok(Arc::new(protected))
}

/// The settings' database, its templates sealed under `template_keys` when given, else under the
/// key file the settings name.
async fn connect(settings: &Settings, template_keys: Option<Option<KeyRing>>) -> anyhow::Result<Store> {
    let keys = match template_keys {
        Some(keys) => keys,
        None => settings.template_key.key_ring()?,
    };
    match &keys {
        Some(keys) => info!(key_id = keys.current_id(), "templates are encrypted at rest"),
        None => warn!("no template key (FACEGATE_TEMPLATE_KEY_FILE): templates are stored UNENCRYPTED"),
    }
    let (url, shown) = crate::database_url::connect_and_shown(&settings.database, settings.database_password_file.as_deref())?;
    Store::connect(&url, keys).await.with_context(|| format!("cannot open the database {shown}"))
}

fn log_api_keys(config: &ApiConfig, bind: &str) {
    if config.api_keys.is_empty() {
        warn!("no API keys configured (FACEGATE_API_KEYS_FILE, FACEGATE_API_KEYS): the API is OPEN to anyone who can reach {}", bind);
    } else {
        info!("{} API key(s) configured", config.api_keys.len());
    }
}

/// The face pipeline the settings name, its liveness model dropped under `--liveness off`.
async fn load_pipeline(settings: &Settings) -> anyhow::Result<Pipeline> {
    let pipeline_config = settings.pipeline_config();
    info!(models = %pipeline_config.models_dir.display(), "loading the face pipeline");
    let loaded = tokio::task::spawn_blocking(move || Pipeline::load(&pipeline_config)).await?;
    let mut pipeline = loaded.context("cannot load the face pipeline models")?;
    settings.configure_liveness(&mut pipeline)?;
    info!(model_version = pipeline.recognizer.model_version(), with_3dmm = pipeline.face_model.is_some(), "pipeline loaded");
    Ok(pipeline)
}

/// Read the camera's liveness calibration (`facegate calibrate-liveness`) into the service and log
/// the one liveness threshold it decides by: the operator's `--liveness-threshold`, else the
/// camera's, else the liveness model's own operating point.
async fn load_liveness_calibration(facegate: &Facegate) -> anyhow::Result<()> {
    let (stored, point) = facegate.load_liveness_calibration().await.context("cannot read the liveness calibration")?;
    let Some(point) = point else {
        match facegate.config().liveness {
            LivenessPolicy::Off => info!("liveness off: no face is checked for a presentation attack"),
            _ => warn!("no liveness model ({}): faces report no liveness", facegate_vision::liveness::FILE),
        }
        return Ok(());
    };
    match (stored, point.source) {
        (Some(calibration), ThresholdSource::Operator) => warn!(
            calibrated = calibration.threshold,
            "--liveness-threshold (FACEGATE_LIVENESS_THRESHOLD) is set: the camera's stored liveness calibration is not used"
        ),
        (Some(calibration), ThresholdSource::Camera) => info!(
            model_threshold = calibration.model_threshold,
            live_faces = calibration.live_faces,
            refused = calibration.refused,
            "liveness threshold of this camera (facegate calibrate-liveness) in place of the model's"
        ),
        (None, ThresholdSource::Model) => info!("no liveness calibration (facegate calibrate-liveness): the model's threshold"),
        _ => {}
    }
    info!(
        policy = ?facegate.config().liveness,
        model = point.model,
        threshold = point.threshold,
        source = point.source.name(),
        operating_point = point.operating_point,
        "liveness (presentation-attack detection)"
    );
    Ok(())
}

/// Read the site calibration of the engine's model version (`facegate calibrate`) into the service
/// and log the default operating point it gives against the model's.
async fn load_site_calibration(facegate: &Facegate) -> anyhow::Result<()> {
    let status = facegate.load_site_calibration().await.context("cannot read the site calibration")?;
    let fmr = facegate_vision::recognize::DEFAULT_FMR;
    let matcher = facegate.matcher();
    let model = matcher.inner.operating_point(fmr, 1).threshold;
    match status {
        SiteStatus::InUse(site) => info!(
            subjects = site.subjects,
            impostor_pairs = site.impostor_pairs,
            duplicate_pairs_left_out = site.duplicate_pairs_left_out,
            model_threshold = model,
            threshold = matcher.operating_point(fmr, 1).threshold,
            "site calibration (facegate calibrate): thresholds at FMR {fmr:e} raised to the deployment's own impostors where they are higher"
        ),
        SiteStatus::NotForThisMatcher => {
            warn!("the site calibration is for cosine-scored recognizers; the classical one keeps its own thresholds")
        }
        SiteStatus::None => info!(threshold = model, "no site calibration (facegate calibrate): the model's thresholds"),
    }
    Ok(())
}

/// Load the identification gallery before the first request, logging the subjects whose
/// templates cannot be read and the time it took.
async fn load_gallery(state: &AppState) -> anyhow::Result<()> {
    let loading = std::time::Instant::now();
    for (subject, why) in state.facegate().load_gallery().await? {
        error!(subject, "templates cannot be read; /identify refuses until the subject is erased: {why}");
    }
    let (subjects, templates) = state.facegate().gallery_size();
    let backend = state.store().backend();
    info!(subjects, templates, load_ms = loading.elapsed().as_millis() as u64, backend = ?backend, "identify gallery loaded");
    let (enrolled, _) = state.store().counts().await.context("cannot count the enrolled subjects")?;
    if (subjects as u64) < enrolled {
        warn!(
            subjects_current_model = subjects,
            subjects = enrolled,
            model_version = state.facegate().model_version(),
            "{} subject(s) have no template of the current model version: verify answers model-mismatch and identify does not search them until they enrol again",
            enrolled - subjects as u64
        );
    }
    Ok(())
}

/// Refuse to serve a database whose sealed templates the configured template keys cannot open: with
/// no key, every sealed subject would answer 500 and new enrolments would be stored unencrypted
/// beside them; with the wrong key, every sealed subject would answer 500. Logs what the keys
/// leave to do (plain subjects to seal, subjects under an older key to re-wrap).
async fn template_keys_open_the_store(store: &Store, args: &Settings) -> anyhow::Result<()> {
    let key_file = || args.template_key.template_key_file.as_ref().map_or_else(String::new, |p| format!(" {}", p.display()));
    match store.check_template_keys().await.context("cannot check the database's sealed templates")? {
        KeyCheck::NothingSealed => {}
        KeyCheck::Opens { sealed_subjects } => {
            info!(sealed_subjects, "the template key opens the sealed subjects")
        }
        KeyCheck::NoKey { sealed_subjects } => anyhow::bail!(
            "the database holds {sealed_subjects} subject(s) whose templates are sealed with a template key, but no template key \
             is configured: start with --template-key-file (FACEGATE_TEMPLATE_KEY_FILE) naming the key file that sealed them \
             (without it every sealed subject would answer 500 and new enrolments would be stored unencrypted)"
        ),
        KeyCheck::CannotOpen { key_id, subjects, reason } => anyhow::bail!(
            "the template key file{} (--template-key-file, FACEGATE_TEMPLATE_KEY_FILE) cannot open the {subjects} subject(s) sealed \
             under template key {key_id}: {reason}; give the key file that holds that key (an older key stays below the current \
             one until `facegate rekey` has re-wrapped every subject)",
            key_file()
        ),
    }
    if store.encrypts() {
        let counts = store.sealing_counts().await?;
        if counts.plain > 0 {
            warn!(subjects = counts.plain, "subjects enrolled before the template key are still stored plain: run `facegate rekey`");
        }
        if counts.other_keys > 0 {
            warn!(
                subjects = counts.other_keys,
                "subjects are sealed under an older template key: run `facegate rekey` before removing it from the key file"
            );
        }
    }
    Ok(())
}
