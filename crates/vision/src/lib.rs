//! The face stages, each plain data in and plain data out, and the one pipeline that assembles
//! them: a decoded photo → [`detect`] (face boxes) → [`landmarks`] (58 IMM points) → [`morph`]
//! (3D morphable model fit, frontal rendering, avatar) → [`embed`] (the face-embedding network) and
//! [`recognize`] (normalization, Direct LDA, templates, scores, calibration) → [`quality`] (face
//! image quality) and [`liveness`] (a live face or a printed photo), assembled once in
//! [`pipeline`]. The detectors are `facegate-detect`, the networks run in `facegate-nn`, the 3D
//! morphable model is `facegate-morph`.
//!
//! Runtime code: it never prints, reads the environment or shows progress (the workspace's clippy
//! lints); models are loaded from paths it is handed.

pub mod embed;
pub mod landmarks;
pub mod liveness;
pub mod quality;
pub mod recognize;

pub mod pipeline;
