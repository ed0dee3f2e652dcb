//! facegate: face verification after D. Zhou's thesis (2011). This package is the binary: its
//! settings ([`config`], the one place that reads the environment), the composition root that
//! builds the service from them ([`startup`]) and its command line ([`cli`]).
//!
//! The work lives in the workspace's crates, whose dependency graph is the architecture
//! (docs/architecture.md): `facegate-core` ← `facegate-detect`, `facegate-morph` (and
//! `facegate-nn`, the networks) ← `facegate-vision` (the stages and the pipeline) ←
//! `facegate-store` ← `facegate-service` (the use cases) ← `facegate-http`; `facegate-research`
//! (data sets, training, evaluation) depends on vision and is never depended on by the runtime.
//! They are re-exported here under their module names for the command line, the integration tests
//! and the benches.

pub use facegate_core as core;
pub use facegate_detect as detect;
pub use facegate_http as http;
pub use facegate_morph as morph;
pub use facegate_nn as nn;
pub use facegate_research as research;
pub use facegate_service as service;
pub use facegate_store as store;
pub use facegate_vision::{embed, landmarks, liveness, pipeline, quality, recognize};

pub mod choices;
pub mod cli;
pub mod config;
pub mod database_url;
pub mod startup;
pub mod telemetry;
