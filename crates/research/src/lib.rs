//! The offline side: data sets, training and evaluation. Research code may read data folders,
//! write files and report progress (through a [`Progress`] the caller hands down); the runtime
//! (stages, pipeline, service, store, http) never imports it.

pub mod asm3d_synth;
pub mod cache;
pub mod convert;
pub mod dataset;
pub mod dlda;
pub mod eval;
pub mod landmark_models;
pub mod liveness;
pub mod logistic;
pub mod measures;
pub mod synthetic;
pub mod train_asm;
pub mod train_asm3d;
pub mod train_deep;
pub mod train_dlda;
pub mod train_embedding;
pub mod train_imm_sfm;
pub mod train_quality;

/// Progress of a long loop, handed down by the caller (the CLI draws a bar; tests stay quiet).
pub trait Progress: Sync {
    /// A loop of `len` steps called `what` begins.
    fn begin(&self, _len: u64, _what: &str) {}
    /// One step done.
    fn step(&self) {}
    /// A message for the user (a skipped photo, a cache hit), shown beside the bar.
    fn note(&self, _message: &str) {}
    /// The loop ended.
    fn end(&self) {}
}

/// No progress shown, notes dropped.
pub struct Quiet;

impl Progress for Quiet {}

/// `f` over `items` on `threads` scoped threads (contiguous chunks), results in input order.
pub fn par_map<T: Sync, R: Send + Clone + Default>(items: &[T], threads: usize, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let mut out = vec![R::default(); items.len()];
    let per = items.len().div_ceil(threads.max(1)).max(1);
    let f = &f;
    std::thread::scope(|scope| {
        for (chunk, dst) in items.chunks(per).zip(out.chunks_mut(per)) {
            scope.spawn(move || {
                for (item, d) in chunk.iter().zip(dst) {
                    *d = f(item);
                }
            });
        }
    });
    out
}
