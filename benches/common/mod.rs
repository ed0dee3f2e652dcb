//! What the benchmarks share: a criterion measurement of the benchmark thread's CPU time.
//!
//! On a machine shared with other work, wall time measures the neighbours too; the pipeline's work
//! is single-threaded, so the thread's CPU time is what one free core takes. Linux only
//! (`/proc/thread-self/schedstat`, through `facegate::research::eval::thread_cpu_ns`).

use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};

pub struct ThreadCpuTime;

fn now() -> Duration {
    Duration::from_nanos(
        facegate::research::eval::thread_cpu_ns().expect("/proc/thread-self/schedstat (Linux) gives the thread's CPU time"),
    )
}

impl Measurement for ThreadCpuTime {
    type Intermediate = Duration;
    type Value = Duration;
    fn start(&self) -> Duration {
        now()
    }
    fn end(&self, start: Duration) -> Duration {
        now().saturating_sub(start)
    }
    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }
    fn zero(&self) -> Duration {
        Duration::ZERO
    }
    fn to_f64(&self, v: &Duration) -> f64 {
        v.as_nanos() as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        WallTime.formatter()
    }
}
