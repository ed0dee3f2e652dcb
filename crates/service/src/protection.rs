//! Protected templates: a per-deployment secret turns every template into another unit vector by
//! a keyed random rotation, before anything stores or compares it ([`ProtectedEngine`]).
//!
//! A rotation keeps every cosine, so scores, thresholds, the site calibration and the
//! identification gallery work on protected templates unchanged, and the accuracy is the plain
//! templates' exactly. What it changes is what a stolen database gives without the secret:
//! - **unlinkable:** the same face under two deployments' secrets gives vectors as unrelated as
//!   two random ones, so templates of two databases cannot be matched to each other (or to the
//!   networks' plain embeddings) by cosine;
//! - **renewable:** a new secret makes new templates that do not link to the old ones.
//!
//! It does *not* make a template irreversible for whoever also holds the secret: the rotation is
//! inverted exactly. The families that lose information on purpose (BioHashing's sign
//! quantisation, Index-of-Max hashing, quantised rotations) were measured before this was chosen
//! (docs/template-protection.md): every one accurate enough to use was inverted to an
//! embedding that matches the person's other photos in 97–100 % of attempts by an attacker with the
//! secret, at a cost of 0.15 to 1.6 points of FNMR. So the secret lives in a key file, never in the
//! database, as the template keys do; sealing (`--template-key-file`) still encrypts the stored
//! vectors on top.
//!
//! The rotation of a dimension `d` is drawn from a ChaCha20 generator seeded with SHA-256 of a
//! domain label, the secret and `d`: Gaussian `d × d`, orthonormalised row by row (Gram–Schmidt in
//! f64), which is a uniformly random rotation. The templates' model version is the recognizer's
//! with `+rot-` and the secret's id (8 hex digits of another SHA-256), so plain templates, and
//! templates of another secret, are never compared with these.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};

use rand::SeedableRng as _;
use rand_distr::Distribution as _;
use sha2::{Digest, Sha256};

use facegate_core::imaging::Photo;
use facegate_core::template::{OperatingPoint, Template};
use facegate_morph::AvatarFormat;
use facegate_vision::liveness::Liveness;
use facegate_vision::pipeline::{FaceAnalysis, FaceChoice, FollowedFace, PhotoReading, PipelineError};

use crate::{FaceEngine, LivenessPoint, Matcher};

/// The scheme's name in a protected model version.
pub const SCHEME: &str = "rot";

/// A deployment's protection secret: 32 bytes.
#[derive(Clone)]
pub struct ProtectionKey {
    secret: [u8; 32],
}

impl std::fmt::Debug for ProtectionKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ProtectionKey({})", self.id())
    }
}

impl ProtectionKey {
    /// The key file's text: one line of 64 hex digits (`openssl rand -hex 32`); blank and `#`
    /// lines are skipped.
    pub fn parse(text: &str) -> Result<ProtectionKey, String> {
        let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')).collect();
        let [line] = lines[..] else {
            return Err(format!("the protection key file must hold one key (64 hex digits), it holds {}", lines.len()));
        };
        let mut secret = [0u8; 32];
        hex::decode_to_slice(line, &mut secret).map_err(|_| "the protection key is not 64 hex digits (32 bytes)".to_string())?;
        Ok(ProtectionKey { secret })
    }

    /// The secret's id: 8 hex digits of a SHA-256 of it (naming it, never revealing it).
    pub fn id(&self) -> String {
        let digest = Sha256::new().chain_update(b"facegate template protection: key id\0").chain_update(self.secret).finalize();
        hex::encode(&digest[..4])
    }

    /// The rotation of `dimension`-value templates under this secret, rows of a `d × d` matrix.
    pub fn rotation(&self, dimension: usize) -> Rotation {
        let seed: [u8; 32] = Sha256::new()
            .chain_update(b"facegate template protection: keyed rotation v1\0")
            .chain_update(self.secret)
            .chain_update((dimension as u64).to_le_bytes())
            .finalize()
            .into();
        let mut rng = rand_chacha::ChaCha20Rng::from_seed(seed);
        let mut rows: Vec<Vec<f64>> = Vec::with_capacity(dimension);
        while rows.len() < dimension {
            let mut v: Vec<f64> = (0..dimension).map(|_| rand_distr::StandardNormal.sample(&mut rng)).collect();
            // Modified Gram–Schmidt, twice for accuracy in f64.
            for _ in 0..2 {
                for r in &rows {
                    let along: f64 = v.iter().zip(r).map(|(a, b)| a * b).sum();
                    v.iter_mut().zip(r).for_each(|(a, b)| *a -= along * b);
                }
            }
            let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
            // A draw in the span of the rows before it (probability zero) is drawn again.
            if norm > 1e-6 {
                rows.push(v.into_iter().map(|a| a / norm).collect());
            }
        }
        Rotation { dimension, values: rows.into_iter().flatten().map(|a| a as f32).collect() }
    }

    /// The model version of `plain`'s templates protected under this secret.
    pub fn model_version(&self, plain: &str) -> String {
        format!("{plain}+{SCHEME}-{}", self.id())
    }
}

/// An orthogonal `dimension × dimension` matrix, row-major.
#[derive(Debug, Clone)]
pub struct Rotation {
    dimension: usize,
    values: Vec<f32>,
}

impl Rotation {
    /// `x` rotated (a vector of another length is returned as zeros: it matches nothing).
    pub fn apply(&self, x: &[f32]) -> Vec<f32> {
        if x.len() != self.dimension {
            return vec![0.0; x.len()];
        }
        self.values.chunks_exact(self.dimension).map(|row| facegate_core::vector::dot(row, x)).collect()
    }

    /// `x` rotated back (the transpose): what an operator's renewal, or an attacker with the
    /// secret, computes.
    pub fn invert(&self, y: &[f32]) -> Vec<f32> {
        let mut x = vec![0.0f32; self.dimension];
        for (row, &yi) in self.values.chunks_exact(self.dimension).zip(y) {
            x.iter_mut().zip(row).for_each(|(a, r)| *a += r * yi);
        }
        x
    }
}

/// Renewal (`facegate renew-protection`): templates protected under one secret (or plain ones)
/// turned into templates protected under another without the photos, since a rotation is undone by
/// its transpose: `t_new = R_new · R_oldᵀ · t_old` (`t_new = R_new · t` from plain). The scores
/// between renewed templates are the old ones (to float rounding), so the site calibration holds.
pub struct Renewal {
    old: Option<ProtectionKey>,
    /// From plain templates: the recognizer's (plain) model version, the only one taken.
    plain: Option<String>,
    new: ProtectionKey,
    rotations: HashMap<usize, (Option<Rotation>, Rotation)>,
}

impl Renewal {
    /// From templates protected under `old` to `new`; refused when both are the same secret.
    pub fn between(old: ProtectionKey, new: ProtectionKey) -> Result<Renewal, String> {
        if old.secret == new.secret {
            return Err(format!("the old and the new protection secret are the same ({}): nothing to renew", new.id()));
        }
        Ok(Renewal { old: Some(old), plain: None, new, rotations: HashMap::new() })
    }

    /// From the plain templates of the recognizer whose model version is `plain` to `new`.
    pub fn from_plain(plain: &str, new: ProtectionKey) -> Renewal {
        Renewal { old: None, plain: Some(plain.to_string()), new, rotations: HashMap::new() }
    }

    /// The new secret's id.
    pub fn new_key_id(&self) -> String {
        self.new.id()
    }

    /// The model version a stored template of `version` gets, or `None` when it is not one this
    /// renewal takes: `<plain>+rot-<old id>` becomes `<plain>+rot-<new id>` (whatever the
    /// recognizer: the rotation depends on the secret and the dimension only); from plain
    /// templates, only the recognizer's own version becomes `<plain>+rot-<new id>`.
    pub fn renewed_version(&self, version: &str) -> Option<String> {
        match (&self.old, &self.plain) {
            (Some(old), _) => {
                let suffix = format!("+{SCHEME}-{}", old.id());
                version.strip_suffix(&suffix).filter(|p| !p.is_empty()).map(|p| self.new.model_version(p))
            }
            (None, plain) => plain.as_deref().filter(|p| *p == version).map(|p| self.new.model_version(p)),
        }
    }

    /// `vector` (protected under the old secret, or plain) protected under the new one.
    pub fn vector(&mut self, vector: &[f32]) -> Vec<f32> {
        let dimension = vector.len();
        let (old, new) = (&self.old, &self.new);
        let (from, to) =
            self.rotations.entry(dimension).or_insert_with(|| (old.as_ref().map(|k| k.rotation(dimension)), new.rotation(dimension)));
        renew(from.as_ref(), to, vector)
    }
}

/// The store's side of a renewal: versions and vectors as above, and the site calibration of a
/// renewed version kept for the new one (the scores, hence its thresholds, are the same).
impl facegate_store::Renewing for Renewal {
    fn version(&self, stored: &str) -> Option<String> {
        self.renewed_version(stored)
    }
    fn vector(&mut self, stored: &[f32]) -> Vec<f32> {
        Renewal::vector(self, stored)
    }
    fn calibration(&self, json: &str, to: &str) -> Result<String, String> {
        let mut site: crate::site::SiteCalibration = serde_json::from_str(json).map_err(|e| format!("unreadable: {e}"))?;
        site.model_version = to.to_string();
        serde_json::to_string(&site.as_stored()).map_err(|e| e.to_string())
    }
}

/// `t` protected by `from` (`None`: plain) protected by `to` instead: `to · fromᵀ · t`.
pub fn renew(from: Option<&Rotation>, to: &Rotation, t: &[f32]) -> Vec<f32> {
    match from {
        Some(from) => to.apply(&from.invert(t)),
        None => to.apply(t),
    }
}

/// What protected templates are made and compared with: a recognizer scored by the best cosine.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("template protection needs a recognizer scored by cosine (dlib, SFace, the fusion or your own network); {0} is not")]
pub struct NotCosineScored(pub String);

/// A face engine whose templates are protected under a [`ProtectionKey`]: every analysis's
/// template is rotated before it leaves, so the store, the gallery and every comparison see
/// protected templates only. Scores and thresholds are the inner engine's (a rotation keeps
/// cosines).
pub struct ProtectedEngine {
    inner: Arc<dyn FaceEngine>,
    key: ProtectionKey,
    version: String,
    rotations: Mutex<HashMap<usize, Arc<Rotation>>>,
}

impl ProtectedEngine {
    pub fn new(inner: Arc<dyn FaceEngine>, key: ProtectionKey) -> Result<ProtectedEngine, NotCosineScored> {
        if !inner.max_cosine_scoring() {
            return Err(NotCosineScored(inner.model_version().to_string()));
        }
        let version = key.model_version(inner.model_version());
        Ok(ProtectedEngine { inner, key, version, rotations: Mutex::default() })
    }

    /// The secret's id.
    pub fn key_id(&self) -> String {
        self.key.id()
    }

    /// The inner engine's (plain) model version.
    pub fn plain_version(&self) -> &str {
        self.inner.model_version()
    }

    /// `template` protected: rotated, and stamped with the protected model version.
    pub fn protect(&self, template: &Template) -> Template {
        let dimension = template.vector.len();
        let rotation = {
            let mut rotations = self.rotations.lock().unwrap_or_else(PoisonError::into_inner);
            rotations.entry(dimension).or_insert_with(|| Arc::new(self.key.rotation(dimension))).clone()
        };
        Template::new(&self.version, rotation.apply(&template.vector))
    }
}

impl Matcher for ProtectedEngine {
    fn model_version(&self) -> &str {
        &self.version
    }
    /// The inner engine's best cosine ([`ProtectedEngine::new`] takes no other), of protected
    /// templates.
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        self.inner.score(probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.inner.operating_point(fmr, enrolled)
    }
    fn max_cosine_scoring(&self) -> bool {
        true
    }
}

impl FaceEngine for ProtectedEngine {
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        let mut analysis = self.inner.analyze(photo)?;
        analysis.template = self.protect(&analysis.template);
        Ok(analysis)
    }
    fn analyze_following(&self, photo: &Photo, last: &FollowedFace) -> Result<FaceAnalysis, PipelineError> {
        let mut analysis = self.inner.analyze_following(photo, last)?;
        analysis.template = self.protect(&analysis.template);
        Ok(analysis)
    }
    fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError> {
        self.inner.read_faces(photo, choice)
    }
    fn avatar(&self, photo: &Photo, format: AvatarFormat) -> Result<Vec<u8>, PipelineError> {
        self.inner.avatar(photo, format)
    }
    fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError> {
        self.inner.frontal_png(photo)
    }
    fn liveness_model_point(&self) -> Option<LivenessPoint> {
        self.inner.liveness_model_point()
    }
    fn render_check(&self, photo: &Photo, analysis: &FaceAnalysis) -> Option<Liveness> {
        self.inner.render_check(photo, analysis)
    }
}

/// Whether the model versions stored in a database fit an engine: with protection, no template
/// of the plain version or of another secret; without, none protected over the plain version.
/// The refusal names what was found and what to do.
pub fn check_stored_versions(stored: &[String], plain: &str, protected: Option<&str>) -> Result<(), String> {
    let prefix = format!("{plain}+{SCHEME}-");
    for version in stored {
        match protected {
            Some(ours) if version == plain => {
                return Err(format!(
                    "the database holds plain templates of {plain}, and --template-protection-key-file asks for protected ones \
                     ({ours}): a database holds one or the other. Start without the key file, protect the stored templates with \
                     `facegate renew-protection --from-plain --new-key-file` (the service stopped), or enrol the subjects again into \
                     a new database with it (docs/template-protection.md)"
                ));
            }
            Some(ours) if version.starts_with(&prefix) && version != ours => {
                return Err(format!(
                    "the database holds templates protected under another secret ({version}; this key makes {ours}): give the \
                     key file they were made with, renew them to this one with `facegate renew-protection --old-key-file \
                     --new-key-file` (the service stopped), or enrol the subjects again under this one"
                ));
            }
            None if version.starts_with(&prefix) => {
                return Err(format!(
                    "the database holds protected templates ({version}): start with the --template-protection-key-file they were \
                     made with"
                ));
            }
            _ => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEX_A: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";
    const HEX_B: &str = "ffeeddccbbaa99887766554433221100ffeeddccbbaa99887766554433221100";

    fn unit(seed: u64, dimension: usize) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let v: Vec<f32> = (0..dimension).map(|_| rand_distr::StandardNormal.sample(&mut rng)).collect();
        Template::new("v", v).vector
    }

    fn dot(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    #[test]
    fn the_key_file_holds_one_key_of_64_hex_digits() {
        let key = ProtectionKey::parse(&format!("# made with openssl rand -hex 32\n{HEX_A}\n")).unwrap();
        assert_eq!(key.id().len(), 8);
        assert_ne!(key.id(), ProtectionKey::parse(HEX_B).unwrap().id());
        assert!(!format!("{key:?}").contains("0011"), "the secret is never printed");
        for bad in ["", "abc", &HEX_A[..62], &format!("{HEX_A}\n{HEX_B}")] {
            assert!(ProtectionKey::parse(bad).is_err(), "{bad:?}");
        }
        assert_eq!(key.model_version("emb-1234"), format!("emb-1234+rot-{}", key.id()));
    }

    #[test]
    fn a_rotation_keeps_every_cosine_and_is_inverted_by_its_transpose() {
        let rotation = ProtectionKey::parse(HEX_A).unwrap().rotation(64);
        let (a, b) = (unit(1, 64), unit(2, 64));
        let (ra, rb) = (rotation.apply(&a), rotation.apply(&b));
        assert!((dot(&ra, &rb) - dot(&a, &b)).abs() < 1e-5);
        assert!((dot(&ra, &ra) - 1.0).abs() < 1e-5);
        assert!(rotation.invert(&ra).iter().zip(&a).all(|(x, y)| (x - y).abs() < 1e-5));
        // Not the identity, and the same key always makes the same rotation.
        assert!(dot(&ra, &a) < 0.5);
        assert_eq!(ProtectionKey::parse(HEX_A).unwrap().rotation(64).apply(&a), ra);
        // Another length is no template of this rotation: it matches nothing.
        assert!(rotation.apply(&a[..10]).iter().all(|v| *v == 0.0));
    }

    #[test]
    fn the_same_face_under_two_secrets_links_no_better_than_two_faces() {
        let (ka, kb) = (ProtectionKey::parse(HEX_A).unwrap(), ProtectionKey::parse(HEX_B).unwrap());
        let (ra, rb) = (ka.rotation(256), kb.rotation(256));
        // 200 faces: each one's protected templates under A and B, against two different faces'.
        let faces: Vec<Vec<f32>> = (0..200).map(|i| unit(100 + i, 256)).collect();
        let same: Vec<f32> = faces.iter().map(|f| dot(&ra.apply(f), &rb.apply(f))).collect();
        let plain_same: Vec<f32> = faces.iter().map(|f| dot(f, f)).collect();
        let mean_abs = |v: &[f32]| v.iter().map(|x| x.abs()).sum::<f32>() / v.len() as f32;
        // Random unit vectors in 256 dimensions: |cosine| about 0.05.
        assert!(mean_abs(&same) < 0.1, "{}", mean_abs(&same));
        assert!(same.iter().all(|c| c.abs() < 0.3), "{same:?}");
        assert!(plain_same.iter().all(|c| (c - 1.0).abs() < 1e-5));
    }

    #[test]
    fn renewal_makes_the_new_secrets_templates_from_the_old_ones_without_the_photos() {
        let (ka, kb) = (ProtectionKey::parse(HEX_A).unwrap(), ProtectionKey::parse(HEX_B).unwrap());
        let (ra, rb) = (ka.rotation(256), kb.rotation(256));
        let face = unit(7, 256);
        let other = unit(8, 256);
        let mut renewal = Renewal::between(ka.clone(), kb.clone()).unwrap();
        let renewed = renewal.vector(&ra.apply(&face));
        // What protecting the photo's embedding under B makes, to float rounding.
        assert!(renewed.iter().zip(rb.apply(&face)).all(|(x, y)| (x - y).abs() < 1e-5), "renewed ≠ R_B t");
        // Scores between renewed templates are the old ones; nothing links to the old template.
        let renewed_other = renewal.vector(&ra.apply(&other));
        assert!((dot(&renewed, &renewed_other) - dot(&face, &other)).abs() < 1e-5);
        assert!(dot(&renewed, &ra.apply(&face)).abs() < 0.3);
        // From plain: R_B t.
        let mut from_plain = Renewal::from_plain("emb-1", kb.clone());
        assert!(from_plain.vector(&face).iter().zip(rb.apply(&face)).all(|(x, y)| (x - y).abs() < 1e-5));
        // Versions: the old secret's become the new secret's; from plain only the recognizer's.
        let (a, b) = (ka.model_version("emb-1"), kb.model_version("emb-1"));
        assert_eq!(renewal.renewed_version(&a).as_deref(), Some(b.as_str()));
        assert_eq!(renewal.renewed_version("emb-1"), None);
        assert_eq!(renewal.renewed_version(&b), None);
        assert_eq!(from_plain.renewed_version("emb-1").as_deref(), Some(b.as_str()));
        assert_eq!(from_plain.renewed_version("deep-9"), None);
        assert_eq!(from_plain.renewed_version(&a), None);
        assert!(Renewal::between(kb.clone(), kb).is_err(), "the same secret renews nothing");
    }

    #[test]
    fn a_database_holds_plain_or_protected_templates_of_one_secret() {
        let ours = "emb-1+rot-aaaa0000";
        let stored = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert!(check_stored_versions(&stored(&["emb-1+rot-aaaa0000", "deep-9"]), "emb-1", Some(ours)).is_ok());
        assert!(check_stored_versions(&stored(&["emb-1"]), "emb-1", Some(ours)).unwrap_err().contains("plain templates"));
        assert!(check_stored_versions(&stored(&["emb-1+rot-bbbb1111"]), "emb-1", Some(ours)).unwrap_err().contains("another secret"));
        assert!(check_stored_versions(&stored(&["emb-1+rot-aaaa0000"]), "emb-1", None).unwrap_err().contains("protected templates"));
        assert!(check_stored_versions(&stored(&["emb-1", "deep-9"]), "emb-1", None).is_ok());
    }
}
