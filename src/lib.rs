//! facegate: face verification after D. Zhou's thesis (2011).
//!
//! Each pipeline stage is a module with plain data in and plain data out, usable from the CLI, the
//! HTTP API, the benchmarks and the evaluation tools alike:
//!
//! bytes → [`imaging`] (decode with limits) → [`detect`] (face boxes) → [`landmarks`] (58 IMM points)
//! → [`morph`] (3DMM fit, texture, frontal rendering) → [`recognize`] (normalise, DLDA, templates)
//! → [`store`] (SQLite) → [`api`] (HTTP).

pub mod config;
pub mod dataset;
pub mod geometry;
pub mod imaging;

pub mod detect;
pub mod embed;
pub mod eval;
pub mod landmarks;
pub mod morph;
pub mod pipeline;
pub mod recognize;

pub mod api;
pub mod store;

pub mod cli;
