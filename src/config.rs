//! Where the project finds its files. Research data and the 3DMM are never part of the
//! repository: they are read from configured paths.
//!
//! - `FACEGATE_SHARED`: the shared data folder (default `../shared` beside the crate).
//! - `FACEGATE_SFM`: the Surrey Face Model folder (default `<shared>/models/sfm`).
//! - `FACEGATE_MODELS`: the project's trained models (default `models` in the working directory,
//!   or the crate's own `models/` when that does not exist).

use std::path::PathBuf;

fn env_path(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from)
}

/// The shared research data (IMM, ORL, cascades, SFM), read-only.
pub fn shared_dir() -> PathBuf {
    env_path("FACEGATE_SHARED").unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

/// The Surrey Face Model folder (`sfm_shape_3448.bin` and companions).
pub fn sfm_dir() -> PathBuf {
    env_path("FACEGATE_SFM").unwrap_or_else(|| shared_dir().join("models/sfm"))
}

/// The project's own trained models (`asm.bin`, `dlda.bin`, cascades, calibration).
pub fn models_dir() -> PathBuf {
    if let Some(p) = env_path("FACEGATE_MODELS") {
        return p;
    }
    let local = PathBuf::from("models");
    if local.is_dir() { local } else { PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models") }
}

/// Write a model file: `value` serialised with postcard, its folder created when missing.
pub fn write_model<T: serde::Serialize>(path: &std::path::Path, value: &T) -> Result<(), String> {
    let bytes = postcard::to_stdvec(value).map_err(|e| e.to_string())?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    }
    std::fs::write(path, bytes).map_err(|e| e.to_string())
}
