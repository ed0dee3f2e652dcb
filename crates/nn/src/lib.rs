//! The neural networks facegate runs in-process, and the kernels they run on: plain arrays in and
//! out, nothing of faces, photos or landmarks (the face stages in `facegate-vision` cut the chips
//! and read the embeddings).
//!
//! [`int8`]: the AVX-512 VNNI integer product (and its portable reference); [`conv`]: a convolution
//! with its batch normalisation folded in, as im2col and one product (8-bit or float);
//! [`resnet`]: dlib's face-recognition ResNet on a [`FaceChip`], whose weights are the project's
//! own file ([`weights`]); [`chain`]: facegate's kernels for ONNX networks that are a chain of
//! layers (depthwise convolutions and PReLU compiled for AVX2 at run time); [`onnx`]: an ONNX
//! network run by those kernels or by tract; [`minifasnet`]: the MiniFASNet anti-spoofing
//! networks on the same kernels, from the project's own weight files.
//!
//! Runtime code: it never prints or reads the environment (the workspace's clippy lints).

pub mod chain;
pub mod chip;
pub mod conv;
pub mod int8;
mod layers;
pub mod minifasnet;
pub mod onnx;
pub mod resnet;
pub mod weights;

pub use chip::FaceChip;
pub use conv::Arithmetic;
pub use resnet::{EMBEDDING_DIMS, Embedder, Embedding, MirrorPair, NetworkError, Workspace};
pub use weights::NetworkFile;
