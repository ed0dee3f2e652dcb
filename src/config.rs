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
