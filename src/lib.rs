//! facegate: face verification after D. Zhou's thesis (2011).
//!
//! The runtime, a request's path: bytes → [`core::imaging`] (decode with limits) → [`detect`]
//! (face boxes) → [`landmarks`] (58 IMM points) → [`morph`] (3DMM fit, frontal rendering) →
//! [`recognize`] (normalise, DLDA, templates), [`quality`] (face image quality), assembled once in [`pipeline`]; [`service`] decides
//! (verify, identify) and runs the work pool, [`store`] keeps templates (SQLite), [`http`] serves it.
//!
//! Offline: [`research`] (data sets, training, evaluation) and [`cli`] (arguments, printing,
//! progress bars); [`config`] reads the environment and holds the service's settings. The runtime
//! never prints, reads the environment or imports the offline side (`runtime_rule` checks it).

pub mod config;
pub mod core;

pub mod detect;
pub mod embed;
pub mod landmarks;
pub mod morph;
pub mod quality;
pub mod recognize;

pub mod pipeline;

pub mod http;
pub mod service;
pub mod store;

pub mod research;

pub mod cli;

#[cfg(test)]
mod runtime_rule;
