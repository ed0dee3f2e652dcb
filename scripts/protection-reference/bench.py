"""Rough comparison cost: one probe against a gallery of N templates (numpy, 1 thread),
per scheme's stored form; relative to the plain f32 dot product."""
import os
os.environ["OPENBLAS_NUM_THREADS"] = "1"
import time, numpy as np
N = 200_000
r = np.random.default_rng(0)

def t(f, reps=5):
    f(); best = 1e9
    for _ in range(reps):
        a = time.perf_counter(); f(); best = min(best, time.perf_counter() - a)
    return best / N * 1e9  # ns per comparison

G = r.standard_normal((N, 256)).astype(np.float32); p = G[0].copy()
base = t(lambda: G @ p)
print(f"plain f32 dot (256 f32, 1024 B): {base:.1f} ns/cmp (1.00x)")
for m in (128, 256, 512, 1024, 2048, 4096):  # BioHash: 2 members x m bits
    w = 2 * m // 64
    B = r.integers(0, 2**63, (N, w), dtype=np.uint64); q = B[0].copy()
    ns = t(lambda: np.bitwise_count(B ^ q).reshape(N, 2, -1).sum(2, dtype=np.int32))
    print(f"BioHash m={m}/member ({2*m//8} B) xor+popcount: {ns:.1f} ns/cmp ({ns/base:.2f}x)")
for m in (256, 512, 1024):  # IoM: 2 members x m indices (one byte each in numpy; packed 4 bits for q<=16)
    C = r.integers(0, 16, (N, 2 * m), dtype=np.uint8); q = C[0].copy()
    ns = t(lambda: (C == q).reshape(N, 2, m).sum(2, dtype=np.int32), reps=3)
    print(f"IoM m={m}/member (numpy u8 codes, {2*m} B) equality count: {ns:.1f} ns/cmp ({ns/base:.2f}x)")
# top-k: ternary as two bit planes (nonzero, sign) of n bits per member: overlap = popcount(nz_a&nz_b) - 2*popcount(nz_a&nz_b&(s_a^s_b))
for n in (128, 512):
    w = 2 * n // 64
    NZ = r.integers(0, 2**63, (N, w), dtype=np.uint64); S = r.integers(0, 2**63, (N, w), dtype=np.uint64)
    a, s = NZ[0].copy(), S[0].copy()
    def f():
        both = NZ & a
        return np.bitwise_count(both).sum(1, dtype=np.int32) - 2 * np.bitwise_count(both & (S ^ s)).sum(1, dtype=np.int32)
    ns = t(f)
    print(f"top-k n={n}/member as 2 bit planes ({2*2*n//8} B) : {ns:.1f} ns/cmp ({ns/base:.2f}x)")
Q = r.integers(-8, 8, (N, 256), dtype=np.int8).astype(np.float32); q = Q[0].copy()
ns = t(lambda: Q @ q)
print(f"rot+quant as f32 dot after dequantisation (same as plain): {ns:.1f} ns/cmp ({ns/base:.2f}x)")
