//! Evaluation: accuracy measures of each stage on held-out people, and their plots.

pub mod detection;
pub mod plot;
pub mod landmarks;
pub mod verification;
