//! Evaluation: accuracy measures of each stage on held-out people, and their plots.

pub mod calibration;
pub mod deep;
pub mod detection;
pub mod identification;
pub mod landmarks;
pub mod pairs;
pub mod plot;
pub mod pose;
pub mod profile;
pub mod protection;
pub mod protocol;
pub mod quality;
pub mod verification;

/// Nanoseconds the calling thread has run on a CPU (Linux `schedstat`), so that timings taken on a
/// machine shared with other work count only our own; `None` where the file does not exist.
pub fn thread_cpu_ns() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    text.split_whitespace().next()?.parse().ok()
}
