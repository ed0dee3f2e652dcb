//! Third-party model weights converted once into the project's own files (offline: the service
//! only reads the converted file).

pub mod dlib;
pub mod minifasnet;
pub mod onnx_embedding;
pub mod torch_legacy;
pub mod wheel;
pub mod yunet;

use facegate_nn::weights::{self, NetworkFile};

/// Converts dlib's serialised network into the project's weight file.
pub fn convert_dlib(bytes: &[u8], provenance: weights::Provenance) -> Result<NetworkFile, dlib::DlibError> {
    let net = dlib::read(bytes)?;
    Ok(NetworkFile { format: weights::FORMAT, provenance, input_size: net.input_size, input_mean: net.input_mean, layers: net.layers })
}
