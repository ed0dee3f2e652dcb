//! Liveness research, in one wing: the NUAA, IMM, ORL, LFW and UMIST photos with their features
//! ([`train`]'s data), the simulated prints and screens ([`attacks`]), the LBP model's training
//! ([`train`]) and the rendered-head detector's ([`render`]), the CNN trained in Rust ([`cnn`]) and
//! the MiniFASNet peer ([`minifasnet`]); their evaluations ([`eval`], per subject [`subjects`],
//! against the peers [`peers`], the CNN against the LBP model [`cnn_eval`], real video's clips
//! [`video`] by how much of each a recipe refuses [`video_refusals`]) over one set of measures
//! ([`measures`]); and the head-turn challenge's evaluation ([`challenge`]).

pub mod attacks;
pub mod challenge;
pub mod cnn;
pub mod cnn_eval;
pub mod eval;
pub mod measures;
pub mod minifasnet;
pub mod peers;
pub mod render;
pub mod subjects;
pub mod train;
pub mod video;
pub mod video_refusals;
