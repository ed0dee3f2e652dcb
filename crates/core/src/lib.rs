//! What every facegate crate shares: geometry, the grey image (one blur, one resample), the face
//! types, subject ids, templates and operating points, and the model-file reader. Plain data and
//! pure functions: no I/O beyond reading a model file.

pub mod face;
pub mod geometry;
pub mod imaging;
pub mod model_file;
pub mod subject;
pub mod template;
pub mod vector;

pub use subject::{InvalidSubjectId, MAX_SUBJECT_LEN, SubjectId};
pub use template::{OperatingPoint, Template};

use std::time::Instant;

/// The middle element of `v` after sorting it (the upper one of an even count); `None` when empty.
pub fn median(v: &mut [f32]) -> Option<f32> {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() { None } else { Some(v[v.len() / 2]) }
}

/// Milliseconds since `since`, for per-stage timings.
pub fn elapsed_ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}
