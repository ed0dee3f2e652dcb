//! Speed of the 3DMM path on one core: fit (58 IMM points), texture extraction, frontal rendering.
//! Target: fit + texture + frontal rendering ≤ 10 ms per face.
//! Run: `cargo bench --bench morph` (needs the Surrey Face Model at FACEGATE_SFM or ../shared/models/sfm).
//!
//! Times are the benchmark thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), not wall time: on a
//! shared, loaded machine wall time measures the neighbours too. The work is single-threaded.

use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{Criterion, criterion_group, criterion_main};
use facegate::dataset::list_imm;
use facegate::morph::{FaceModel, TEXTURE_SIZE};

/// Criterion measurement: CPU time of the calling thread.
struct ThreadCpuTime {
    wall: WallTime,
}

fn thread_cpu_now() -> Duration {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; the clock id is a Linux/POSIX constant.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

impl Measurement for ThreadCpuTime {
    type Intermediate = Duration;
    type Value = Duration;
    fn start(&self) -> Duration {
        thread_cpu_now()
    }
    fn end(&self, start: Duration) -> Duration {
        thread_cpu_now().saturating_sub(start)
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
        self.wall.formatter()
    }
}

fn bench(c: &mut Criterion<ThreadCpuTime>) {
    let model = FaceModel::load(&facegate::config::sfm_dir()).expect("Surrey Face Model");
    let sample = list_imm(&facegate::config::shared_dir().join("data/imm"))
        .expect("IMM data")
        .into_iter()
        .find(|s| s.person == 2 && s.view == 3)
        .expect("IMM 02-3");
    let photo = facegate::imaging::open(&sample.image).expect("photo");
    let points = sample.landmarks().expect("landmarks");
    let (w, h) = (photo.width(), photo.height());
    let fitted = model.fit(&points, w, h).expect("fit");

    c.bench_function("morph/fit", |b| b.iter(|| model.fit(std::hint::black_box(&points), w, h).unwrap()));
    c.bench_function("morph/texture", |b| b.iter(|| model.extract_texture(&photo.rgb, &fitted, TEXTURE_SIZE)));
    c.bench_function("morph/frontal_render", |b| b.iter(|| model.frontalize(&photo, &fitted).unwrap()));
    c.bench_function("morph/fit_texture_frontal", |b| {
        b.iter(|| {
            let f = model.fit(std::hint::black_box(&points), w, h).unwrap();
            model.frontalize(&photo, &f).unwrap()
        })
    });
}

fn config() -> Criterion<ThreadCpuTime> {
    Criterion::default().with_measurement(ThreadCpuTime { wall: WallTime })
}

criterion_group! { name = benches; config = config(); targets = bench }
criterion_main!(benches);
