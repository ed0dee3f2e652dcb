//! What the benchmarks share: a criterion measurement of the benchmark thread's CPU time.
//!
//! On a machine shared with other work, wall time measures the neighbours too; the pipeline's work
//! is single-threaded, so the thread's CPU time is what one free core takes. Linux only
//! (`/proc/thread-self/schedstat`, through `facegate_research::eval::thread_cpu_ns`).

use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};

pub struct ThreadCpuTime;

fn now() -> Duration {
    Duration::from_nanos(facegate_research::eval::thread_cpu_ns().expect("/proc/thread-self/schedstat (Linux) gives the thread's CPU time"))
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

/// The service's pipeline as the benches measure it: deep recognizer, the Surrey Face Model of
/// `../shared`, the detector `detector`. (Not every bench that shares this module loads one.)
#[allow(dead_code)]
pub fn deep_pipeline(detector: facegate_detect::DetectorKind) -> facegate_vision::pipeline::Pipeline {
    let config = facegate_vision::pipeline::PipelineConfig {
        models_dir: facegate_paths::models_dir(),
        sfm_dir: Some(facegate_paths::shared_dir().join("models/sfm")),
        recognizer: facegate_vision::recognize::RecognizerKind::Dlib,
        detector,
    };
    facegate_vision::pipeline::Pipeline::load(&config).expect("models and ../shared/models/sfm")
}

/// The service's cost of one photo: `bytes` decoded, then `Pipeline::analyze` (the face must be found).
#[allow(dead_code)]
pub fn decode_analyze(b: &mut criterion::Bencher<'_, ThreadCpuTime>, pipeline: &facegate_vision::pipeline::Pipeline, bytes: &[u8]) {
    use facegate_core::imaging::{self, DecodeLimits};
    b.iter(|| {
        let photo = imaging::decode(criterion::black_box(bytes), &DecodeLimits::default()).unwrap();
        criterion::black_box(pipeline.analyze(&photo).unwrap())
    })
}
