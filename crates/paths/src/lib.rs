//! Where facegate finds its files, read from the environment with defaults beside the repository:
//! - `FACEGATE_SHARED`: the shared research data folder (default `../shared` beside the repository);
//! - `FACEGATE_SFM`: the Surrey Face Model folder (default `<shared>/models/sfm`);
//! - `FACEGATE_MODELS`: the project's trained models (default `models` in the working directory,
//!   or the repository's own `models/` when that does not exist).
//!
//! The binary's settings and the research commands use it; the runtime crates (core, detect, nn,
//! morph, vision, store, service, http) depend on it only for their tests, so they are always handed paths.

use std::path::PathBuf;

/// The repository's root folder (this crate lives in `crates/paths`).
pub fn repository_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

fn env_path(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from)
}

/// The shared research data (IMM, ORL, LFW, UMIST, NUAA, cascades, SFM), read-only.
pub fn shared_dir() -> PathBuf {
    env_path("FACEGATE_SHARED").unwrap_or_else(|| repository_dir().join("../shared"))
}

/// The Surrey Face Model folder (`sfm_shape_3448.bin` and companions).
pub fn sfm_dir() -> PathBuf {
    env_path("FACEGATE_SFM").unwrap_or_else(|| shared_dir().join("models/sfm"))
}

/// The project's own trained models (`asm.bin`, `deep.bin`, cascades, calibration).
pub fn models_dir() -> PathBuf {
    if let Some(p) = env_path("FACEGATE_MODELS") {
        return p;
    }
    let local = PathBuf::from("models");
    if local.is_dir() { local } else { repository_dir().join("models") }
}
