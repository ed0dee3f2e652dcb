//! Run-time choice of the instruction set for the search's hot loops. The crate is built for the
//! x86-64 baseline (SSE2: 4 lanes); the descriptor, window sampling and Mahalanobis loops are
//! written in 8 independent lanes and, on a CPU with AVX2, compiled a second time for it (one
//! 8-lane instruction instead of two). No fused multiply-add is enabled and the lane order is the
//! same, so both versions give bit-identical results.

/// Whether the CPU has AVX2 (detected once; the standard library caches the answer).
#[cfg(target_arch = "x86_64")]
#[inline]
pub fn avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}
