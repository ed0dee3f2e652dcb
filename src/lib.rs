//! facegate: face verification after D. Zhou's thesis (2011). This package is the binary: its
//! settings ([`config`], the one place that reads the environment), the composition root that
//! builds the service from them ([`startup`]) and its command line ([`cli`]).
//!
//! The work lives in the workspace's crates, whose dependency graph is the architecture
//! (docs/architecture.md): `facegate-core` ← `facegate-detect`, `facegate-morph` (and
//! `facegate-nn`, the networks) ← `facegate-vision` (the stages and the pipeline) ←
//! `facegate-store` ← `facegate-service` (the use cases) ← `facegate-http`; `facegate-research`
//! (data sets, training, evaluation) depends on vision and is never depended on by the runtime.
//! The command line, the integration tests and the benches import each crate by its own name.

pub mod choices;
pub mod cli;
pub mod config;
pub mod database_url;
pub mod startup;
pub mod telemetry;
