//! The use cases: [`Facegate`] enrolls, verifies, identifies, deletes, analyzes and renders, in
//! the order each one needs (cheap checks and store look-ups before the photo work, the photo work
//! on the bounded [`WorkPool`], the store commit last). HTTP handlers and the command line call
//! these and only translate requests and results.

use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use bytes::Bytes;

use facegate_core::SubjectId;
use facegate_core::elapsed_ms;
use facegate_core::imaging::{DecodeError, DecodeLimits, Photo};
use facegate_core::template::{OperatingPoint, Template};
use facegate_morph::AvatarFormat;
use facegate_store::{Backend, Store, StoreError, SubjectDetail, SubjectSummary};
use facegate_vision::pipeline::{FaceAnalysis, FaceChoice, PipelineError};
use facegate_vision::quality::{Failure, QualityPolicy};

use crate::challenge::{ChallengeConfig, ChallengeOutcome, InvalidChallenge};
use crate::gallery::{LiveGallery, Precision, UnreadableTemplates};
use crate::inspect::{self, Analysis, InspectError};
use crate::liveness::{LivenessPoint, LivenessPolicy, LivenessVerdict, PresentationAttack};
use crate::liveness_camera::LivenessCalibration;
use crate::site::{CalibratedMatcher, SiteCalibration, SiteStatus};
use crate::{Candidate, Decision, FaceEngine, Matcher, PoolError, VerifyError, WorkPool};
use facegate_vision::liveness::Liveness;

/// The head-turn challenge's use cases (issue, verify), on the rules of [`crate::challenge`].
mod challenge;

/// The service's policies (made from the binary's settings, where the defaults are).
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Pixel-count, dimension and decode-memory limits per photo.
    pub decode_limits: DecodeLimits,
    /// Most photos in one enrolment.
    pub max_images: usize,
    /// The least quality an enrolment photo must have.
    pub quality_policy: QualityPolicy,
    /// The false match rate whose operating point decides a match unless a request asks otherwise.
    pub default_fmr: f64,
    /// What enrolment, verify and identify do with a face's liveness.
    pub liveness: LivenessPolicy,
    /// The operator's liveness threshold (`--liveness-threshold`), in place of the camera's
    /// calibration and the model's own operating point ([`crate::liveness::threshold_in_force`]).
    pub liveness_threshold: Option<f32>,
    /// The head-turn challenges' settings.
    pub challenge: ChallengeConfig,
    /// Most challenges open (issued, not yet taken or expired) at once in the store; beyond, an
    /// issue is refused ([`ServiceError::TooManyChallenges`]).
    pub max_open_challenges: u64,
    /// `/verify` only with a passed head-turn challenge (`liveness` must be `Enforce`): a
    /// verification without one is refused ([`InvalidChallenge::Required`]), so that a client app
    /// cannot forget to ask for it. Identification and enrolment are not affected.
    pub require_challenge: bool,
}

/// What is wrong with one photo.
#[derive(Debug, thiserror::Error)]
pub enum PhotoError {
    #[error(transparent)]
    Decode(#[from] DecodeError),
    #[error("no face was found in the photo")]
    NoFace,
    /// Landmarks the 3D model cannot be fitted to, where a template was asked for: no usable face,
    /// as far as the client can act on it.
    #[error("the face found could not be pose-corrected: {0}")]
    NotPoseCorrected(String),
    /// The 3D model could not be fitted where the 3D model itself was asked for.
    #[error("the 3D morphable model could not be fitted to the face: {0}")]
    FitFailed(String),
    #[error("{0}")]
    NoFaceModel(String),
    #[error("{0} faces were found; an enrolment photo must show exactly one face, since a template of the wrong person is costly")]
    SeveralFaces(usize),
    #[error("the photo is below the quality policy")]
    LowQuality(Vec<Failure>),
    /// Liveness is enforced and the face was taken for a printed photo.
    #[error("{0}")]
    PresentationAttack(PresentationAttack),
    /// Liveness is enforced and the capture answering a challenge failed it.
    #[error("the capture failed the liveness challenge: {}", .0.reason.as_deref().unwrap_or("no reason"))]
    ChallengeFailed(ChallengeOutcome),
    /// Liveness is enforced but the engine gave none (no liveness model): a fault of the server,
    /// and no face is let through unchecked.
    #[error("liveness is enforced but no liveness model is loaded")]
    LivenessUnavailable,
    /// A fault of the pipeline, not of the photo.
    #[error(transparent)]
    Internal(PipelineError),
}

/// Why a use case did not complete.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A photo cannot be used; `index` names it among several.
    #[error("{error}")]
    Photo { index: Option<usize>, error: PhotoError },
    /// A further frame of a verification's capture cannot be used; `index` is 0-based among the
    /// frames (the probe is not counted).
    #[error("{error}")]
    Frame { index: usize, error: PhotoError },
    /// The challenge a verification answers is unknown, used or expired.
    #[error(transparent)]
    InvalidChallenge(#[from] InvalidChallenge),
    /// A further frame of a verification's capture does not show the probe's person.
    #[error("{0}")]
    FramesMismatch(FramesMismatch),
    /// The request asks for something the service does not do (wrong photo count).
    #[error("{0}")]
    Invalid(String),
    /// As many challenges as the store may hold are open: none is issued until one is taken or
    /// expires, at the latest after `retry_after`.
    #[error("{open} liveness challenges are open, the most the service keeps at once; retry when one has been answered or has expired")]
    TooManyChallenges { open: u64, retry_after: std::time::Duration },
    #[error("subject {0} is not enrolled")]
    UnknownSubject(SubjectId),
    #[error(transparent)]
    ModelMismatch(#[from] VerifyError),
    #[error(transparent)]
    Pool(#[from] PoolError),
    /// The database cannot be reached: refused at once while the store circuit is open.
    #[error("the template database is unavailable; retry shortly")]
    StoreUnavailable,
    /// The database went away during a write's commit: whether it is stored is not known.
    #[error(
        "the template database went away during the commit: the change may or may not be stored; check the subject (GET /subjects/{{id}}) before retrying"
    )]
    OutcomeUnknown,
    #[error(transparent)]
    Store(StoreError),
    #[error(transparent)]
    Gallery(#[from] UnreadableTemplates),
}

impl From<StoreError> for ServiceError {
    fn from(error: StoreError) -> ServiceError {
        match error {
            StoreError::CommitUnknown(_) => ServiceError::OutcomeUnknown,
            e if e.is_unavailable() => ServiceError::StoreUnavailable,
            e => ServiceError::Store(e),
        }
    }
}

impl From<PhotoError> for ServiceError {
    fn from(error: PhotoError) -> ServiceError {
        ServiceError::Photo { index: None, error }
    }
}

/// A frame of a verification's capture whose face is not the probe's person: its score against
/// the probe's template is below the verification threshold of the operating point in use, for a
/// subject of one template. It stops a print presented as the probe from borrowing the liveness of
/// someone else's live frames.
#[derive(Debug, Clone, PartialEq)]
pub struct FramesMismatch {
    /// 0-based among the frames (the probe is not counted).
    pub frame: usize,
    pub score: f32,
    pub threshold: f32,
}

impl std::fmt::Display for FramesMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "frame {} does not show the person of the probe: its score against the probe, {:.3}, is below the verification threshold \
             {:.3}; every frame must be of the same capture of the same face",
            self.frame, self.score, self.threshold
        )
    }
}

impl PhotoError {
    fn at(self, index: usize) -> ServiceError {
        ServiceError::Photo { index: Some(index), error: self }
    }

    pub(crate) fn at_frame(self, index: usize) -> ServiceError {
        ServiceError::Frame { index, error: self }
    }

    /// A pipeline error where a template was asked for.
    fn of_analysis(error: PipelineError) -> PhotoError {
        match error {
            PipelineError::NoFace => PhotoError::NoFace,
            PipelineError::PoseCorrection(e) => PhotoError::NotPoseCorrected(e.to_string()),
            other => PhotoError::Internal(other),
        }
    }

    /// A decoding or pipeline error where the face itself (landmarks, 3D model) was asked for.
    fn of_inspection(error: InspectError) -> PhotoError {
        match error {
            InspectError::Decode(e) => PhotoError::Decode(e),
            InspectError::Pipeline(PipelineError::NoFace) => PhotoError::NoFace,
            InspectError::Pipeline(e @ PipelineError::NoFaceModel) => PhotoError::NoFaceModel(e.to_string()),
            InspectError::Pipeline(PipelineError::PoseCorrection(e)) => PhotoError::FitFailed(e.to_string()),
            InspectError::Pipeline(other) => PhotoError::Internal(other),
        }
    }
}

/// One photo decoded and analyzed: its face and template, the time decoding took, and the
/// service's verdict on its liveness.
#[derive(Debug, Clone)]
pub struct AnalyzedPhoto {
    pub analysis: FaceAnalysis,
    pub decode_ms: f64,
    /// The verdict on `analysis.liveness` (for a verification's probe with frames or a challenge,
    /// the capture's): `None` until the policy has judged it, and with liveness off or no model.
    pub liveness: Option<LivenessVerdict>,
}

/// Decode `bytes` within `limits` and analyze the largest face: the one path from a photo's bytes
/// to a template (call it on the work pool).
pub fn analyze_photo(engine: &dyn FaceEngine, bytes: &[u8], limits: &DecodeLimits) -> Result<AnalyzedPhoto, PhotoError> {
    decode_and_analyze(engine, bytes, limits).map(|(_, analyzed)| analyzed)
}

/// [`analyze_photo`], keeping the decoded photo for a further look at it (a challenge frame's
/// rendered-head check).
pub(crate) fn decode_and_analyze(
    engine: &dyn FaceEngine,
    bytes: &[u8],
    limits: &DecodeLimits,
) -> Result<(Photo, AnalyzedPhoto), PhotoError> {
    let (photo, decode_ms) = inspect::decode_photo(bytes, limits)?;
    let analysis = engine.analyze(&photo).map_err(PhotoError::of_analysis)?;
    Ok((photo, AnalyzedPhoto { analysis, decode_ms, liveness: None }))
}

/// A completed enrolment.
#[derive(Debug)]
pub struct Enrollment {
    pub subject: SubjectId,
    /// Templates the subject has now (all model versions).
    pub templates: u32,
    /// The photos in request order, one template added from each.
    pub photos: Vec<AnalyzedPhoto>,
}

/// An enrolment whose photos all passed, not stored yet.
pub struct PreparedEnrollment {
    facegate: Facegate,
    subject: SubjectId,
    photos: Vec<AnalyzedPhoto>,
}

impl PreparedEnrollment {
    /// Store the templates in one transaction, then add them to the identification gallery. The
    /// commit runs to its end even if the caller stops waiting.
    pub async fn commit(self) -> Result<Enrollment, ServiceError> {
        let templates: Vec<Template> = self.photos.iter().map(|p| p.analysis.template.clone()).collect();
        let count = self.facegate.with_store(self.facegate.0.gallery.enroll(&self.subject, templates)).await?;
        Ok(Enrollment { subject: self.subject, templates: count, photos: self.photos })
    }
}

/// A completed verification.
#[derive(Debug)]
pub struct Verification {
    pub decision: Decision,
    /// The probe, the photo the decision is about. With further frames its `liveness` verdict is
    /// the capture's, fused over the probe and the frames ([`crate::fuse_liveness`]).
    pub photo: AnalyzedPhoto,
    /// The further frames of the capture, in request order (none for a single photo).
    pub frames: Vec<AnalyzedPhoto>,
    /// Each photo's own liveness score, the probe's first, when the liveness was fused over
    /// frames; empty otherwise (a single photo, or no liveness).
    pub frame_scores: Vec<f32>,
    /// The verdict on the capture when it answered a challenge.
    pub challenge: Option<ChallengeOutcome>,
    /// Time spent deciding, after the photo's analysis.
    pub match_ms: f64,
}

impl Verification {
    /// The decision on `photo` against the subject's `comparable` templates at `fmr`, timed: the
    /// last step of every verification, with or without frames or a challenge.
    fn of_probe(matcher: &dyn Matcher, comparable: &[Template], fmr: f64, photo: AnalyzedPhoto) -> Verification {
        let start = Instant::now();
        let decision = crate::decide(matcher, &photo.analysis.template, comparable, fmr);
        Verification { decision, photo, frames: Vec::new(), frame_scores: Vec::new(), challenge: None, match_ms: elapsed_ms(start) }
    }
}

/// A completed identification.
#[derive(Debug)]
pub struct Identification {
    /// The best-scoring subjects, best first.
    pub candidates: Vec<Candidate>,
    /// The operating point for a subject with one template (each candidate carries its own).
    pub operating_point: OperatingPoint,
    /// Subjects with templates of the current model version that were searched.
    pub subjects_searched: usize,
    pub photo: AnalyzedPhoto,
    /// Time spent searching, after the photo's analysis.
    pub match_ms: f64,
}

/// The state of the service, for `/health`.
#[derive(Debug, Clone)]
pub struct Health {
    pub model_version: String,
    pub subjects: u64,
    pub templates: u64,
    /// Whether template vectors are sealed at rest.
    pub templates_encrypted: bool,
    pub store_backend: Backend,
    /// The site calibration in use (`facegate calibrate`), if any.
    pub site_calibration: Option<Arc<SiteCalibration>>,
    /// Subjects with a template of the current model version: those verify and identify can
    /// find (the others were enrolled under another model and must enrol again).
    pub subjects_current_model: u64,
    /// The liveness threshold in force and how it was set (the model's, the camera's calibration
    /// or the operator's); `None` with liveness off or no model.
    pub liveness: Option<LivenessPoint>,
}

/// How long requests that need the database are refused at once after it could not be reached,
/// before one request tries it again.
pub const STORE_RETRY: Duration = Duration::from_secs(1);

/// Longest a use case waits for a read of the database: past it the database is taken as
/// unreachable (under the 2 s in which every request is answered while it is down).
pub const STORE_READ_WAIT: Duration = Duration::from_millis(1800);

/// The store's availability as the use cases last saw it (a circuit breaker): after a failure to
/// reach the database, every request that needs it is refused at once with
/// [`ServiceError::StoreUnavailable`] for [`STORE_RETRY`]; then one request tries the database
/// again, and its success closes the circuit. While the database is down no request waits out the
/// pool's acquire timeout but that one.
#[derive(Debug, Default)]
struct StoreCircuit {
    open_until: Mutex<Option<Instant>>,
}

impl StoreCircuit {
    /// May a request use the store now? While open, no; once the wait is over, the first caller
    /// may (and the circuit stays open for the others until it reports).
    fn admit(&self) -> bool {
        let mut open_until = self.open_until.lock().unwrap_or_else(|e| e.into_inner());
        match *open_until {
            Some(until) if Instant::now() < until => false,
            Some(_) => {
                *open_until = Some(Instant::now() + STORE_RETRY);
                true
            }
            None => true,
        }
    }

    fn report<T>(&self, result: &Result<T, StoreError>) {
        let mut open_until = self.open_until.lock().unwrap_or_else(|e| e.into_inner());
        match result {
            Err(e) if e.is_unavailable() => *open_until = Some(Instant::now() + STORE_RETRY),
            _ => *open_until = None,
        }
    }
}

struct Inner {
    engine: Arc<dyn FaceEngine>,
    store: Store,
    /// The current model's templates in memory for identification; enrolments and deletions go
    /// through it so that it stays in step with the store.
    gallery: LiveGallery,
    pool: WorkPool,
    config: ServiceConfig,
    circuit: StoreCircuit,
    /// The site calibration raising the engine's thresholds (`facegate calibrate`), read from the
    /// store at start-up by [`Facegate::load_site_calibration`].
    site: RwLock<Option<Arc<SiteCalibration>>>,
    /// The liveness threshold every verdict is made at: the model's own operating point or the
    /// operator's, then the camera's calibration where one is stored and the operator set none
    /// ([`Facegate::load_liveness_calibration`]). `None` with liveness off or no liveness model
    /// (then `Enforce` refuses every face: it fails closed).
    liveness_point: RwLock<Option<Arc<LivenessPoint>>>,
}

/// The service: the face engine, the store, the identification gallery and the work pool behind
/// the use cases. Cheap to clone.
#[derive(Clone)]
pub struct Facegate(Arc<Inner>);

impl Facegate {
    pub fn new(engine: Arc<dyn FaceEngine>, store: Store, pool: WorkPool, config: ServiceConfig) -> Facegate {
        // Best-cosine matchers search 4-bit codes and re-score the shortlist from the store; any
        // other matcher scores every subject from floats held in memory.
        let precision = if engine.max_cosine_scoring() { Precision::Quantised } else { Precision::Exact };
        let gallery = LiveGallery::new(store.clone(), engine.model_version(), precision);
        let site = RwLock::new(None);
        let point = Self::liveness_model_point(engine.as_ref(), &config).map(|model| Self::liveness_point_of(model, &config, None));
        let liveness_point = RwLock::new(point.map(Arc::new));
        Facegate(Arc::new(Inner { engine, store, gallery, pool, config, circuit: StoreCircuit::default(), site, liveness_point }))
    }

    /// The operating point of `engine`'s liveness model; `None` with liveness off under `config`
    /// or no liveness model.
    fn liveness_model_point(engine: &dyn FaceEngine, config: &ServiceConfig) -> Option<LivenessPoint> {
        engine.liveness_model_point().filter(|_| config.liveness != LivenessPolicy::Off)
    }

    /// The liveness threshold in force for the liveness `model`'s point under `config`, with the
    /// `camera`'s calibration, if any.
    fn liveness_point_of(model: LivenessPoint, config: &ServiceConfig, camera: Option<&LivenessCalibration>) -> LivenessPoint {
        let camera = camera.and_then(|c| c.point(&model));
        crate::liveness::threshold_in_force(model, camera, config.liveness_threshold)
    }

    /// Read this camera's liveness calibration (`facegate calibrate-liveness`) for the engine's
    /// liveness model from the store and decide by it from now on, unless the operator set a
    /// threshold (it changes with `facegate calibrate-liveness` and takes effect at the next
    /// start). Returns the stored calibration, if any, and the threshold now in force.
    pub async fn load_liveness_calibration(&self) -> Result<(Option<LivenessCalibration>, Option<LivenessPoint>), ServiceError> {
        let Some(model) = Self::liveness_model_point(self.0.engine.as_ref(), &self.0.config) else {
            return Ok((None, None));
        };
        let stored = self.read_store(crate::liveness_camera::load(&self.0.store, &model.model)).await?;
        let point = Some(Self::liveness_point_of(model, &self.0.config, stored.as_ref()));
        *self.0.liveness_point.write().unwrap_or_else(|e| e.into_inner()) = point.clone().map(Arc::new);
        Ok((stored, point))
    }

    /// The liveness threshold in force.
    fn liveness_point(&self) -> Option<Arc<LivenessPoint>> {
        self.0.liveness_point.read().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// The engine's scores held to its operating points raised by the site calibration in use:
    /// what every decision is made with.
    pub fn matcher(&self) -> CalibratedMatcher<dyn FaceEngine> {
        let site = self.0.site.read().unwrap_or_else(|e| e.into_inner()).clone();
        CalibratedMatcher { site, inner: self.0.engine.clone() }
    }

    /// Read the site calibration of the current model version from the store and decide with it
    /// from now on (it changes with `facegate calibrate` and takes effect at the next start).
    pub async fn load_site_calibration(&self) -> Result<SiteStatus, ServiceError> {
        let status = self.read_store(crate::site::load(&self.0.store, self.0.engine.as_ref())).await?;
        *self.0.site.write().unwrap_or_else(|e| e.into_inner()) = status.calibration().cloned();
        Ok(status)
    }

    /// The version stamped on every template the current model makes.
    pub fn model_version(&self) -> &str {
        self.0.engine.model_version()
    }

    pub fn pool(&self) -> &WorkPool {
        &self.0.pool
    }

    pub fn store(&self) -> &Store {
        &self.0.store
    }

    pub fn config(&self) -> &ServiceConfig {
        &self.0.config
    }

    /// `work` on the store, through the circuit: refused at once while the database is known to be
    /// unreachable.
    pub(crate) async fn with_store<T>(&self, work: impl std::future::Future<Output = Result<T, StoreError>>) -> Result<T, ServiceError> {
        if !self.0.circuit.admit() {
            return Err(ServiceError::StoreUnavailable);
        }
        let result = tracing::Instrument::instrument(work, tracing::info_span!("store")).await;
        self.0.circuit.report(&result);
        Ok(result?)
    }

    /// [`Facegate::with_store`] for a read, bounded in time: a read cut short changes nothing,
    /// and a database that went away answers no read in time.
    pub(crate) async fn read_store<T>(&self, read: impl std::future::Future<Output = Result<T, StoreError>>) -> Result<T, ServiceError> {
        let bounded = async { tokio::time::timeout(STORE_READ_WAIT, read).await.unwrap_or_else(|_| Err(StoreError::timed_out())) };
        self.with_store(bounded).await
    }

    /// The requested false match rate, or the configured one.
    fn fmr(&self, fmr: Option<f64>) -> f64 {
        fmr.unwrap_or(self.0.config.default_fmr)
    }

    /// Enroll `subject` from `images`: every photo must show exactly one face and meet the quality
    /// policy; then all templates are stored in one transaction. One bad photo refuses the whole
    /// enrolment (its index is named) and nothing is stored. [`Facegate::prepare_enrollment`]
    /// then [`PreparedEnrollment::commit`].
    pub async fn enroll(&self, subject: &SubjectId, images: Vec<Bytes>) -> Result<Enrollment, ServiceError> {
        self.prepare_enrollment(subject, images).await?.commit().await
    }

    /// The photo work of an enrolment: every photo analyzed and checked, nothing stored yet.
    pub async fn prepare_enrollment(&self, subject: &SubjectId, images: Vec<Bytes>) -> Result<PreparedEnrollment, ServiceError> {
        let max = self.0.config.max_images;
        match images.len() {
            0 => return Err(ServiceError::Invalid("at least one photo is required (field image)".into())),
            n if n > max => return Err(ServiceError::Invalid(format!("at most {max} photos per enrolment, got {n}"))),
            _ => {}
        }
        let (engine, limits) = (self.0.engine.clone(), self.0.config.decode_limits);
        let policies = (self.0.config.quality_policy, self.0.config.liveness, self.liveness_point());
        let photos = self.0.pool.run(move || enrollment_photos(engine.as_ref(), &images, &limits, policies)).await??;
        Ok(PreparedEnrollment { facegate: self.clone(), subject: subject.clone(), photos })
    }

    /// Is the largest face of `image` the enrolled `subject`? The subject is looked up before the
    /// photo work.
    pub async fn verify(&self, subject: &SubjectId, image: Bytes, fmr: Option<f64>) -> Result<Verification, ServiceError> {
        self.verify_capture(subject, image, Vec::new(), fmr).await
    }

    /// [`Facegate::verify`] of a probe with up to [`crate::MAX_CAPTURE_FRAMES`] further `frames` of the
    /// same capture. The probe alone is matched against the subject's templates; each frame must
    /// show a face (else `Frame` with its index) of the probe's person ([`FramesMismatch`]), and
    /// the liveness the policy judges is the capture's, fused over the probe and the frames.
    /// Without frames this is the single-photo verification, unchanged.
    pub async fn verify_capture(
        &self,
        subject: &SubjectId,
        image: Bytes,
        frames: Vec<Bytes>,
        fmr: Option<f64>,
    ) -> Result<Verification, ServiceError> {
        if self.0.config.require_challenge {
            return Err(InvalidChallenge::Required.into());
        }
        if frames.len() > crate::MAX_CAPTURE_FRAMES {
            let (max, n) = (crate::MAX_CAPTURE_FRAMES, frames.len());
            return Err(ServiceError::Invalid(format!("at most {max} frames besides the probe, got {n}")));
        }
        let fmr = self.fmr(fmr);
        let (matcher, comparable) = self.comparable_of(subject).await?;
        let (photo, frames, frame_scores) = if frames.is_empty() {
            (self.analyze_probe(image).await?, Vec::new(), Vec::new())
        } else {
            self.analyze_capture(image, frames, fmr).await?
        };
        Ok(Verification { frames, frame_scores, ..Verification::of_probe(&matcher, &comparable, fmr, photo) })
    }

    /// The matcher in use and the subject's templates it can compare with, what a verification
    /// holds its probe against: an unknown subject, or one without a template of the model in
    /// use, is refused.
    async fn comparable_of(&self, subject: &SubjectId) -> Result<(CalibratedMatcher<dyn FaceEngine>, Vec<Template>), ServiceError> {
        let enrolled =
            self.read_store(self.0.store.templates(subject)).await?.ok_or_else(|| ServiceError::UnknownSubject(subject.clone()))?;
        let matcher = self.matcher();
        let comparable = crate::comparable_templates(&matcher, subject, enrolled)?;
        Ok((matcher, comparable))
    }

    /// The best `k` enrolled subjects for the largest face of `image`. What the store holds when
    /// the request comes in (other replicas' enrolments and deletions included) is what the search
    /// sees: the gallery catches up while the probe is analyzed.
    pub async fn identify(&self, image: Bytes, fmr: Option<f64>, k: usize) -> Result<Identification, ServiceError> {
        let fmr = self.fmr(fmr);
        let gallery = self.0.gallery.clone();
        let store_version = self.read_store(gallery.change_version()).await?;
        let photo = self.analyze_probe(image).await?;
        let start = Instant::now();
        self.with_store(gallery.load()).await?;
        gallery.wait_until_applied(store_version).await;
        let (matcher, probe) = (self.matcher(), photo.analysis.template.clone());
        // Scanning the whole gallery is CPU work too: it runs on the pool.
        let (searching, scoring) = (gallery.clone(), matcher.clone());
        let search = move || tracing::info_span!("gallery").in_scope(|| searching.search(&scoring, &probe, fmr, k));
        let (found, subjects_searched) = self.0.pool.run(search).await??;
        let candidates = self.read_store(gallery.rerank(&matcher, &photo.analysis.template, found, fmr, k)).await?;
        let operating_point = matcher.operating_point(fmr, 1);
        Ok(Identification { candidates, operating_point, subjects_searched, photo, match_ms: elapsed_ms(start) })
    }

    /// The probe of a verify or identify, analyzed and held against the liveness policy.
    async fn analyze_probe(&self, image: Bytes) -> Result<AnalyzedPhoto, ServiceError> {
        let (engine, limits) = (self.0.engine.clone(), self.0.config.decode_limits);
        let mut photo = self.0.pool.run(move || analyze_photo(engine.as_ref(), &image, &limits)).await??;
        photo.liveness = self.check_liveness(photo.analysis.liveness.as_ref())?;
        Ok(photo)
    }

    /// A probe and further frames of its capture, analyzed on the pool and checked to show one
    /// person at `fmr`'s operating point, then held against the liveness policy with the liveness
    /// fused over all of them. Returns the probe (with the fused liveness), the frames and each
    /// photo's own liveness score (empty when there is no liveness to fuse).
    async fn analyze_capture(
        &self,
        image: Bytes,
        frames: Vec<Bytes>,
        fmr: f64,
    ) -> Result<(AnalyzedPhoto, Vec<AnalyzedPhoto>, Vec<f32>), ServiceError> {
        let (matcher, limits) = (self.matcher(), self.0.config.decode_limits);
        let (mut probe, frames) = self.0.pool.run(move || capture_photos(&matcher, &image, &frames, &limits, fmr)).await??;
        let (fused, scores) = self.check_capture_liveness(&probe, &frames)?;
        probe.liveness = fused;
        Ok((probe, frames, scores))
    }

    /// One face's measured liveness held against the policy at the threshold in force.
    fn check_liveness(&self, measured: Option<&Liveness>) -> Result<Option<LivenessVerdict>, PhotoError> {
        crate::check_liveness(self.0.config.liveness, self.liveness_point().as_deref(), measured)
    }

    /// A capture's liveness, fused over the `probe` and its `frames`, held against the policy at
    /// the threshold in force; with each photo's own score.
    pub(crate) fn check_capture_liveness(
        &self,
        probe: &AnalyzedPhoto,
        frames: &[AnalyzedPhoto],
    ) -> Result<(Option<LivenessVerdict>, Vec<f32>), PhotoError> {
        crate::liveness::check_capture_liveness(self.0.config.liveness, self.liveness_point().as_deref(), capture_liveness(probe, frames))
    }

    /// Erase `subject` and all its templates; `None` when it was not enrolled.
    pub async fn delete(&self, subject: &SubjectId) -> Result<Option<u32>, ServiceError> {
        self.with_store(self.0.gallery.delete(subject)).await
    }

    /// One subject's templates by model version and dates.
    pub async fn subject(&self, subject: &SubjectId) -> Result<SubjectDetail, ServiceError> {
        self.read_store(self.0.store.subject(subject)).await?.ok_or_else(|| ServiceError::UnknownSubject(subject.clone()))
    }

    /// Subjects ordered by id, after `after`, at most `limit`.
    pub async fn subjects(&self, after: Option<&SubjectId>, limit: u32) -> Result<Vec<SubjectSummary>, ServiceError> {
        self.read_store(self.0.store.list_subjects(after, limit)).await
    }

    /// The database answers and the models are loaded.
    pub async fn health(&self) -> Result<Health, ServiceError> {
        let (subjects, templates) = self.read_store(self.0.store.counts()).await?;
        // The gallery holds the current model version's subjects once loaded (at start-up);
        // before that the store counts them.
        let subjects_current_model = match self.0.gallery.is_loaded() {
            true => self.0.gallery.size().0 as u64,
            false => self.read_store(self.0.store.subjects_of_version(self.model_version())).await?,
        };
        Ok(Health {
            model_version: self.model_version().to_string(),
            subjects,
            templates,
            templates_encrypted: self.0.store.encrypts(),
            store_backend: self.0.store.backend(),
            site_calibration: self.matcher().site,
            subjects_current_model,
            liveness: self.liveness_point().map(|p| LivenessPoint::clone(&p)),
        })
    }

    /// Every face of `image` (or the largest) with landmarks, pose, 3D fit and (unless liveness
    /// is off) the verdict on its liveness; nothing stored, nothing refused as an attack: an
    /// inspection.
    pub async fn analyze(&self, image: Bytes, choice: FaceChoice) -> Result<Analysis, ServiceError> {
        let (engine, limits) = (self.0.engine.clone(), self.0.config.decode_limits);
        let analysis = self.0.pool.run(move || inspect::analyze(engine.as_ref(), &image, &limits, choice)).await?;
        let mut analysis = analysis.map_err(PhotoError::of_inspection)?;
        // Reported, never refused: each measured face's verdict at the threshold in force. With
        // liveness off there is no threshold in force, so no verdict.
        let point = self.liveness_point();
        let verdict = |face: &facegate_vision::pipeline::FaceReading| Some(point.as_deref()?.judge(face.liveness.as_ref()?));
        analysis.liveness = analysis.reading.faces.iter().map(verdict).collect();
        Ok(analysis)
    }

    /// The textured 3D head of the largest face of `image`.
    pub async fn avatar(&self, image: Bytes, format: AvatarFormat) -> Result<Vec<u8>, ServiceError> {
        let (engine, limits) = (self.0.engine.clone(), self.0.config.decode_limits);
        let bytes = self.0.pool.run(move || inspect::avatar(engine.as_ref(), &image, &limits, format)).await?;
        Ok(bytes.map_err(PhotoError::of_inspection)?)
    }

    /// The largest face of `image` rendered from the front, PNG.
    pub async fn frontalize(&self, image: Bytes) -> Result<Vec<u8>, ServiceError> {
        let (engine, limits) = (self.0.engine.clone(), self.0.config.decode_limits);
        let png = self.0.pool.run(move || inspect::frontalize(engine.as_ref(), &image, &limits)).await?;
        Ok(png.map_err(PhotoError::of_inspection)?)
    }

    /// Load the identification gallery now (else on first use). Returns the subjects whose
    /// templates cannot be read, with why: identification refuses to answer while there are any.
    /// Where other replicas write to the same database, the gallery follows their changes from
    /// then on, until [`Facegate::stop_following`].
    pub async fn load_gallery(&self) -> Result<Vec<(String, String)>, StoreError> {
        self.0.gallery.load().await
    }

    /// Subjects and templates in the identification gallery.
    pub fn gallery_size(&self) -> (usize, usize) {
        self.0.gallery.size()
    }

    /// Stop following the other replicas' changes (before closing the store).
    pub fn stop_following(&self) {
        self.0.gallery.stop_following();
    }
}

/// Analyze a verification's probe, then each further frame of its capture in order, refusing at
/// the first frame with no usable face or whose face is not the probe's person at `fmr`'s
/// operating point (the recognizer's own score and threshold, for a subject of one template).
fn capture_photos(
    matcher: &CalibratedMatcher<dyn FaceEngine>,
    image: &[u8],
    frames: &[Bytes],
    limits: &DecodeLimits,
    fmr: f64,
) -> Result<(AnalyzedPhoto, Vec<AnalyzedPhoto>), ServiceError> {
    let engine = matcher.inner.as_ref();
    let probe = analyze_photo(engine, image, limits)?;
    let mut analyzed = Vec::with_capacity(frames.len());
    for (index, bytes) in frames.iter().enumerate() {
        let frame = analyze_photo(engine, bytes, limits).map_err(|e| e.at_frame(index))?;
        let same = crate::decide(matcher, &frame.analysis.template, std::slice::from_ref(&probe.analysis.template), fmr);
        if !same.is_match {
            return Err(ServiceError::FramesMismatch(FramesMismatch { frame: index, score: same.score, threshold: same.threshold }));
        }
        analyzed.push(frame);
    }
    Ok((probe, analyzed))
}

/// Each photo's own measured liveness, the probe's first: what a capture's liveness is fused from
/// (`None` when one photo has none).
pub(crate) fn capture_liveness(probe: &AnalyzedPhoto, frames: &[AnalyzedPhoto]) -> Option<Vec<facegate_vision::liveness::Liveness>> {
    std::iter::once(probe).chain(frames).map(|p| p.analysis.liveness.clone()).collect()
}

/// Analyze every enrolment photo in order, refusing at the first that shows several faces, fails
/// the quality policy or (liveness enforced) is taken for a presentation attack. Quality comes
/// before liveness, so that a genuine photo too poor to judge is told what to fix.
fn enrollment_photos(
    engine: &dyn FaceEngine,
    images: &[Bytes],
    limits: &DecodeLimits,
    (quality, liveness, point): (QualityPolicy, LivenessPolicy, Option<Arc<LivenessPoint>>),
) -> Result<Vec<AnalyzedPhoto>, ServiceError> {
    let mut photos = Vec::with_capacity(images.len());
    for (index, bytes) in images.iter().enumerate() {
        let mut photo = analyze_photo(engine, bytes, limits).map_err(|e| e.at(index))?;
        crate::check_enrollment_photo(photo.analysis.faces_found).map_err(|e| e.at(index))?;
        crate::check_enrollment_quality(&quality, &photo.analysis.quality).map_err(|f| PhotoError::LowQuality(f).at(index))?;
        photo.liveness = crate::check_liveness(liveness, point.as_deref(), photo.analysis.liveness.as_ref()).map_err(|e| e.at(index))?;
        photos.push(photo);
    }
    Ok(photos)
}
