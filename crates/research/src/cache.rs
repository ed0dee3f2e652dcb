//! The research front ends' one cache, and their one per-sample loop ([`map_samples`]).
//!
//! A research front end (the deep embeddings of [`crate::train_deep`], the quality measurements of
//! [`crate::eval::quality`], the crops and re-posed crops of [`crate::train_dlda`], the centres of
//! `eval deep-align`) computes one result per sample, which takes minutes; the cache keeps those
//! results between runs. A cache file holds the results of one computation, in sample order,
//! under its [`CacheKey`]: the SHA-256 of
//! - the kind of results (`deep-embeddings`, `quality-measurements`, `crops`, …);
//! - [`FRONT_END_VERSION`], this crate's version of the front ends' code;
//! - the networks' arithmetic on this CPU (`Arithmetic::detect`: 8-bit and float convolutions
//!   differ in the last digits);
//! - the bytes of every model file the front end reads ([`ModelFiles`]: the detector's cascades,
//!   `asm.bin`, `asm3d.bin`, `embedding.bin` of the models folder, the Surrey Face Model's files
//!   and the compiled-in IMM → SFM correspondence, as the front end loads them);
//! - the caller's own settings (serialised: normalisation path and parameters, offsets, …);
//! - the list of samples (each photo's path, and what else of it the front end reads).
//!
//! Where: `<dir>/<kind>-<16 hex digits of the key>.bin` (postcard), `<dir>` being the folder the
//! command is given: `target/research-cache` ([`DEFAULT_DIR`]) for `train deep`, `eval deep`,
//! `eval deep-align`, `eval verify --recognizer deep`, `train quality` and `eval quality(-cv)`
//! (their `--cache`), and `train dlda --crop-cache <dir>` for the crops (no cache without it).
//! Every change of an input makes another key, hence another file: files of old keys are never read
//! again and may be deleted at any time. A file whose stored key differs from the one asked for
//! (or which does not decode, or holds another number of results) is refused and computed again.

use std::path::{Path, PathBuf};

use serde::Serialize;
use serde::de::DeserializeOwned;
use sha2::{Digest, Sha256};

use crate::Progress;

/// The version of the front ends' code. Bump it whenever a change to the code they run (this
/// crate's front ends, or facegate-vision's detector, landmarks, 3DMM fit and rendering, chip,
/// network or quality components) changes what they compute: every cache file is then made again.
pub const FRONT_END_VERSION: u32 = 5;

/// The cache folder of the research commands, relative to the working directory.
pub const DEFAULT_DIR: &str = "target/research-cache";

/// One model file a front end reads: its name in the key, where it is read from, and the copy
/// compiled into the binary that is used when the file is absent (or that is the only one).
#[derive(Debug, Clone)]
struct ModelInput {
    name: String,
    path: Option<PathBuf>,
    embedded: Option<&'static [u8]>,
}

impl ModelInput {
    /// The bytes the front end loads, `None` when it loads none (the file is absent).
    fn bytes(&self) -> Option<Vec<u8>> {
        self.path.as_ref().and_then(|p| std::fs::read(p).ok()).or_else(|| self.embedded.map(<[u8]>::to_vec))
    }
}

/// The model files a front end reads, in a fixed order: their bytes are part of its [`CacheKey`]
/// (by name and content, not by folder: a moved copy of the same files keeps the key).
#[derive(Debug, Clone, Default)]
pub struct ModelFiles {
    inputs: Vec<ModelInput>,
}

impl ModelFiles {
    /// No model files (a front end of annotations only).
    pub fn new() -> ModelFiles {
        ModelFiles::default()
    }

    fn with(mut self, name: String, path: Option<PathBuf>, embedded: Option<&'static [u8]>) -> ModelFiles {
        self.inputs.push(ModelInput { name, path, embedded });
        self
    }

    /// The service's face finder as [`facegate_vision::pipeline::FaceFinder::load`] reads
    /// `models_dir`: the detectors' files (the cascades under `cascades/`, `yunet.onnx`; their
    /// compiled-in copies where absent, as the detector falls back to them), `asm.bin`,
    /// `asm3d.bin` and `asm3d-profile.bin` (when present).
    pub fn finder(self, models_dir: &Path) -> ModelFiles {
        use facegate_detect::{
            EMBEDDED_FRONTAL, EMBEDDED_PROFILE, EMBEDDED_SEETA, EMBEDDED_YUNET, FRONTAL_CASCADE, PROFILE_CASCADE, SEETA_MODEL, YUNET_MODEL,
        };
        let cascades =
            [(FRONTAL_CASCADE, EMBEDDED_FRONTAL.as_bytes()), (PROFILE_CASCADE, EMBEDDED_PROFILE.as_bytes()), (SEETA_MODEL, EMBEDDED_SEETA)];
        let with_cascades = cascades.into_iter().fold(self, |files, (name, embedded)| {
            files.with(format!("cascades/{name}"), Some(models_dir.join("cascades").join(name)), Some(embedded))
        });
        with_cascades
            .with(YUNET_MODEL.to_string(), Some(models_dir.join(YUNET_MODEL)), Some(EMBEDDED_YUNET))
            .model(models_dir, "asm.bin")
            .model(models_dir, "asm3d.bin")
            .model(models_dir, "asm3d-profile.bin")
    }

    /// The file `name` of `models_dir` (`embedding.bin`, …).
    pub fn model(self, models_dir: &Path, name: &str) -> ModelFiles {
        self.with(name.to_string(), Some(models_dir.join(name)), None)
    }

    /// The Surrey Face Model as [`facegate_morph::FaceModel::load`] reads `sfm_dir` (shape,
    /// expression blendshapes, contours, reference symmetry), and the compiled-in IMM → SFM
    /// correspondence (`models/imm_to_sfm.txt`) its fit uses.
    pub fn sfm(self, sfm_dir: &Path) -> ModelFiles {
        use facegate_morph::{BLENDSHAPES_FILE, CONTOURS_FILE, SHAPE_FILE, SYMMETRY_FILE};
        let files = [SHAPE_FILE, BLENDSHAPES_FILE, CONTOURS_FILE, SYMMETRY_FILE]
            .into_iter()
            .fold(self, |files, name| files.with(format!("sfm/{name}"), Some(sfm_dir.join(name)), None));
        let table = facegate_morph::correspondence::DERIVED_TABLE.as_bytes();
        files.with("imm_to_sfm.txt".to_string(), None, Some(table))
    }
}

/// What a cache file is made under: see the [module documentation](self).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CacheKey {
    kind: String,
    hex: String,
}

/// Feeds `bytes` to `hasher` with their length first, so that fields cannot run into each other.
fn field(hasher: &mut Sha256, bytes: &[u8]) {
    hasher.update((bytes.len() as u64).to_le_bytes());
    hasher.update(bytes);
}

impl CacheKey {
    /// The key of `kind` results of `samples` (each a string naming the sample: its photo's path,
    /// and what else of it the front end reads), computed by a front end that reads `models`,
    /// under the caller's `settings`.
    pub fn new<S: AsRef<str>>(kind: &str, models: &ModelFiles, settings: &[u8], samples: impl IntoIterator<Item = S>) -> CacheKey {
        let mut hasher = Sha256::new();
        field(&mut hasher, b"facegate research cache");
        hasher.update(FRONT_END_VERSION.to_le_bytes());
        field(&mut hasher, format!("{:?}", facegate_nn::Arithmetic::detect()).as_bytes());
        field(&mut hasher, kind.as_bytes());
        hasher.update((models.inputs.len() as u64).to_le_bytes());
        for input in &models.inputs {
            field(&mut hasher, input.name.as_bytes());
            match input.bytes() {
                Some(bytes) => {
                    hasher.update([1]);
                    field(&mut hasher, &bytes);
                }
                None => hasher.update([0]),
            }
        }
        field(&mut hasher, settings);
        let mut count = 0u64;
        for sample in samples {
            field(&mut hasher, sample.as_ref().as_bytes());
            count += 1;
        }
        hasher.update(count.to_le_bytes());
        CacheKey { kind: kind.to_string(), hex: hasher.finalize().iter().map(|b| format!("{b:02x}")).collect() }
    }

    /// The key's 64 hex digits.
    pub fn hex(&self) -> &str {
        &self.hex
    }

    /// The file this key's results are kept in, in `dir`.
    pub fn file_in(&self, dir: &Path) -> PathBuf {
        dir.join(format!("{}-{}.bin", self.kind, &self.hex[..16]))
    }
}

/// Why a cache file was not used.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Miss {
    /// There is no file: nothing to say.
    Absent,
    /// The file is there but not for this key: said, then computed again.
    Refused(String),
}

/// The results cached under `key` in `dir`, `samples` of them.
pub fn read<R: DeserializeOwned>(dir: &Path, key: &CacheKey, samples: usize) -> Option<Vec<R>> {
    load(dir, key, samples).ok()
}

fn load<R: DeserializeOwned>(dir: &Path, key: &CacheKey, samples: usize) -> Result<Vec<R>, Miss> {
    let bytes = std::fs::read(key.file_in(dir)).map_err(|_| Miss::Absent)?;
    let refused = |why: &str| Miss::Refused(why.to_string());
    let (stored, rest) = postcard::take_from_bytes::<String>(&bytes).map_err(|_| refused("not a cache file"))?;
    if stored != key.hex {
        return Err(refused("made under another key"));
    }
    let results: Vec<R> = postcard::from_bytes(rest).map_err(|_| refused("does not decode"))?;
    if results.len() != samples {
        return Err(refused("holds another number of results"));
    }
    Ok(results)
}

/// Writes `results` under `key` in `dir` (created if need be), through a temporary file renamed
/// into place, so that a reader never sees half a file.
pub fn write<R: Serialize>(dir: &Path, key: &CacheKey, results: &[R]) -> anyhow::Result<PathBuf> {
    let path = key.file_in(dir);
    let mut bytes = postcard::to_stdvec(&key.hex)?;
    bytes.extend(postcard::to_stdvec(results)?);
    std::fs::create_dir_all(dir)?;
    let partial = path.with_extension(format!("partial-{}", std::process::id()));
    std::fs::write(&partial, bytes)?;
    std::fs::rename(&partial, &path)?;
    Ok(path)
}

/// The `samples` results cached under `key` in `dir`, or, when there are none, those of `compute`,
/// then written there. `progress` is told where cached results came from, and why a file was refused.
pub fn get_or_compute<R: Serialize + DeserializeOwned>(
    dir: &Path,
    key: &CacheKey,
    samples: usize,
    progress: &dyn Progress,
    compute: impl FnOnce() -> anyhow::Result<Vec<R>>,
) -> anyhow::Result<Vec<R>> {
    let path = key.file_in(dir);
    match load(dir, key, samples) {
        Ok(results) => {
            progress.note(&format!("{} from the cache {}", key.kind, path.display()));
            return Ok(results);
        }
        Err(Miss::Refused(why)) => progress.note(&format!("{}: {why}; computing again", path.display())),
        Err(Miss::Absent) => {}
    }
    let results = compute()?;
    anyhow::ensure!(results.len() == samples, "{} results for {samples} samples", results.len());
    write(dir, key, &results)?;
    Ok(results)
}

/// `f` over `samples` on `threads` threads, results in input order; `progress` is told of a loop
/// called `what` and of each sample done. The one per-sample loop of the research front ends.
pub fn map_samples<T: Sync, R: Send + Clone + Default>(
    samples: &[T],
    threads: usize,
    what: &str,
    progress: &dyn Progress,
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    progress.begin(samples.len() as u64, what);
    let out = crate::par_map(samples, threads, |s| {
        let r = f(s);
        progress.step();
        r
    });
    progress.end();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Quiet;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("facegate-cache-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Every model file the front end reads is in the key: the finder's, an extra model's, the SFM's.
    #[test]
    fn the_key_covers_every_model_file() {
        let dir = temp_dir("models");
        let (models, sfm) = (dir.join("models"), dir.join("sfm"));
        std::fs::create_dir_all(models.join("cascades")).unwrap();
        std::fs::create_dir_all(&sfm).unwrap();
        let files = || ModelFiles::new().finder(&models).model(&models, "embedding.bin").sfm(&sfm);
        let key = || CacheKey::new("test", &files(), b"settings", ["a.jpg"]);
        let mut seen = vec![key()];
        let changes = [
            models.join("asm.bin"),
            models.join("asm3d.bin"),
            models.join("asm3d-profile.bin"),
            models.join(facegate_detect::YUNET_MODEL),
            models.join("embedding.bin"),
            models.join("cascades").join(facegate_detect::FRONTAL_CASCADE),
            sfm.join(facegate_morph::SHAPE_FILE),
        ];
        for file in changes {
            std::fs::write(&file, b"weights").unwrap();
            let k = key();
            assert!(!seen.contains(&k), "{} is not in the key", file.display());
            seen.push(k);
        }
        // The same files elsewhere: the same key.
        let moved = dir.join("moved");
        std::fs::rename(dir.join("models"), &moved).unwrap();
        std::fs::rename(dir.join("sfm"), dir.join("moved-sfm")).unwrap();
        let again = CacheKey::new(
            "test",
            &ModelFiles::new().finder(&moved).model(&moved, "embedding.bin").sfm(&dir.join("moved-sfm")),
            b"settings",
            ["a.jpg"],
        );
        assert_eq!(&again, seen.last().unwrap());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_file_of_another_key_is_refused() {
        let dir = temp_dir("refuse");
        let models = ModelFiles::new();
        let (a, b) = (CacheKey::new("k", &models, b"1", ["x"]), CacheKey::new("k", &models, b"2", ["x"]));
        write(&dir, &a, &[7u32]).unwrap();
        assert_eq!(read::<u32>(&dir, &a, 1), Some(vec![7]));
        assert_eq!(read::<u32>(&dir, &a, 2), None);
        // `a`'s file where `b`'s belongs: refused, computed again and replaced.
        std::fs::copy(a.file_in(&dir), b.file_in(&dir)).unwrap();
        assert_eq!(read::<u32>(&dir, &b, 1), None);
        assert_eq!(get_or_compute(&dir, &b, 1, &Quiet, || Ok(vec![9u32])).unwrap(), vec![9]);
        assert_eq!(get_or_compute::<u32>(&dir, &b, 1, &Quiet, || anyhow::bail!("not computed again")).unwrap(), vec![9]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn map_samples_keeps_the_order_and_counts_the_steps() {
        struct Count(std::sync::atomic::AtomicUsize);
        impl Progress for Count {
            fn step(&self) {
                self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
        let count = Count(Default::default());
        let items: Vec<u32> = (0..101).collect();
        assert_eq!(map_samples(&items, 3, "square", &count, |x| x * x), items.iter().map(|x| x * x).collect::<Vec<_>>());
        assert_eq!(count.0.into_inner(), 101);
    }
}
