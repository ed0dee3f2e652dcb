//! Convolutions in 8-bit integers: the activations quantised per tensor to `u8` (with a zero
//! point, so PReLU's negative values fit as well as ReLU's), the weights per filter to `i8`
//! (symmetric), the products summed exactly in `i32` and turned back into floats with the bias
//! and the ReLU in the same pass. On a CPU with AVX-512 VNNI one `vpdpbusd` does 64 of these
//! multiply-adds, four times the 16 of an AVX-512 float FMA; the embedding networks' matrix
//! products are about three quarters of their time (docs/speed.md).
//!
//! The integer sums are exact, so the VNNI kernel and the portable one ([`matmul_portable`], the
//! tests' reference) give the same bits. A CPU without VNNI keeps the float path
//! ([`crate::Arithmetic::detect`]); the two differ by the quantisation only (measured in
//! docs/speed.md: same EER, cosine to the float embedding above 0.99).

/// Filters per block: one 512-bit register of `i32` sums.
const LANES: usize = 16;

/// A convolution's `(k·k·c) × filters` weights in `i8`, laid out for the kernel.
pub(crate) struct Int8Weights {
    filters: usize,
    /// The product's depth, `k·k·c` rounded up to a multiple of 4 (the padding is zero).
    pub(crate) depth: usize,
    /// `[block][depth / 4][LANES][4]`: for one block of 16 filters, four consecutive depths of
    /// each filter are one `i32` lane, as `vpdpbusd` takes them.
    packed: Vec<i8>,
    /// Per filter (padded to whole blocks): the float value of one `i8` step.
    scale: Vec<f32>,
    /// Per filter: the sum of its `i8` weights, to take the activations' zero point out.
    sums: Vec<i32>,
}

impl Int8Weights {
    /// Quantises `rhs` (`depth × filters`, row-major, as the float product takes it).
    pub(crate) fn new(rhs: &[f32], depth: usize, filters: usize) -> Int8Weights {
        assert_eq!(rhs.len(), depth * filters);
        let blocks = filters.div_ceil(LANES);
        let padded_depth = depth.div_ceil(4) * 4;
        let mut packed = vec![0i8; blocks * padded_depth * LANES];
        let mut scale = vec![0.0f32; blocks * LANES];
        let mut sums = vec![0i32; blocks * LANES];
        for o in 0..filters {
            let largest = (0..depth).map(|d| rhs[d * filters + o].abs()).fold(0.0f32, f32::max);
            let step = if largest > 0.0 { largest / 127.0 } else { 1.0 };
            scale[o] = step;
            let (block, lane) = (o / LANES, o % LANES);
            for d in 0..depth {
                let q = (rhs[d * filters + o] / step).round().clamp(-127.0, 127.0) as i8;
                packed[(block * padded_depth + d / 4 * 4) * LANES + lane * 4 + d % 4] = q;
                sums[o] += q as i32;
            }
        }
        Int8Weights { filters, depth: padded_depth, packed, scale, sums }
    }

    fn blocks(&self) -> usize {
        self.scale.len() / LANES
    }

    /// The `i8` weight of depth `d`, filter `o`.
    fn at(&self, d: usize, o: usize) -> i8 {
        self.packed[((o / LANES) * self.depth + d / 4 * 4) * LANES + (o % LANES) * 4 + d % 4]
    }
}

/// How a tensor's floats became bytes: `value ≈ (byte − zero) · step`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Quantisation {
    pub(crate) step: f32,
    pub(crate) zero: u8,
}

impl Quantisation {
    /// The quantisation of values in `data`: their range, widened to hold 0 (zero padding is then
    /// exactly the zero point), over the 256 byte values.
    #[inline(always)]
    pub(crate) fn of(data: &[f32]) -> Quantisation {
        let (lo, hi) = range(data);
        let (lo, hi) = (lo.min(0.0), hi.max(0.0));
        let step = if hi > lo { (hi - lo) / 255.0 } else { 1.0 };
        Quantisation { step, zero: (-lo / step).round().clamp(0.0, 255.0) as u8 }
    }

    /// The quantisation of `data` and its bytes in `out`, resized to `len` (at least the data's
    /// length; the rest zero: the padding a product's depth may need).
    #[inline(always)]
    pub(crate) fn into_bytes(data: &[f32], out: &mut Vec<u8>, len: usize) -> Quantisation {
        let quantisation = Quantisation::of(data);
        out.resize(len, 0);
        out[data.len()..].fill(0);
        quantisation.apply(data, out);
        quantisation
    }

    /// Writes the bytes of `data` into `out`.
    pub(crate) fn apply(&self, data: &[f32], out: &mut [u8]) {
        let (inv, zero) = (1.0 / self.step, self.zero as f32 + 0.5);
        #[cfg(target_arch = "x86_64")]
        if vnni() {
            // SAFETY: the CPU has AVX-512 F and BW (checked at run time).
            return unsafe { x86::quantise_avx512(data, out, inv, zero) };
        }
        quantise(data, out, inv, zero)
    }
}

/// `x · inv + zero` (`zero` holding the ½ that makes truncation round: the sum is at least ½
/// for every value in the range) clamped to a byte, with one rounding as the vector kernel.
fn quantise(data: &[f32], out: &mut [u8], inv: f32, zero: f32) {
    for (o, x) in out.iter_mut().zip(data) {
        *o = x.mul_add(inv, zero).clamp(0.0, 255.0) as u8;
    }
}

#[inline(always)]
fn range(data: &[f32]) -> (f32, f32) {
    // Eight running minima and maxima: the loop vectorises.
    let mut lo = [f32::INFINITY; 8];
    let mut hi = [f32::NEG_INFINITY; 8];
    let chunks = data.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            lo[i] = lo[i].min(c[i]);
            hi[i] = hi[i].max(c[i]);
        }
    }
    let (mut l, mut h) = (lo.iter().copied().fold(f32::INFINITY, f32::min), hi.iter().copied().fold(f32::NEG_INFINITY, f32::max));
    for &x in rest {
        l = l.min(x);
        h = h.max(x);
    }
    (l, h)
}

/// What turns a row's `i32` sums into the layer's output floats.
pub(crate) struct Epilogue<'a> {
    pub(crate) input: Quantisation,
    pub(crate) bias: &'a [f32],
    pub(crate) relu: bool,
}

/// `out[r][o] = epilogue(Σ_d rows[r][d] · w[d][o])` for `rows` (`m × w.depth` bytes, row-major)
/// and `out` (`m × filters` floats), on this CPU's fastest kernel.
pub(crate) fn matmul(rows: &[u8], m: usize, w: &Int8Weights, e: &Epilogue, out: &mut [f32]) {
    assert!(rows.len() >= m * w.depth && out.len() >= m * w.filters && e.bias.len() >= w.filters);
    #[cfg(target_arch = "x86_64")]
    if vnni() {
        // SAFETY: the CPU has AVX-512 F, BW and VNNI (checked at run time); the sizes are checked above.
        return unsafe { x86::matmul_vnni(rows, m, w, e, out) };
    }
    matmul_portable(rows, m, w, e, out)
}

/// The same product, one multiply-add at a time.
pub(crate) fn matmul_portable(rows: &[u8], m: usize, w: &Int8Weights, e: &Epilogue, out: &mut [f32]) {
    for r in 0..m {
        let row = &rows[r * w.depth..(r + 1) * w.depth];
        for o in 0..w.filters {
            let sum: i32 = row.iter().enumerate().map(|(d, &a)| a as i32 * w.at(d, o) as i32).sum();
            out[r * w.filters + o] = finish(sum, o, w, e);
        }
    }
}

#[inline(always)]
fn finish(sum: i32, o: usize, w: &Int8Weights, e: &Epilogue) -> f32 {
    // One rounding, as the vector kernel's fused multiply-add: the two give the same bits.
    let v = ((sum - e.input.zero as i32 * w.sums[o]) as f32).mul_add(e.input.step * w.scale[o], e.bias[o]);
    if e.relu { v.max(0.0) } else { v }
}

/// Whether this CPU runs the VNNI kernel.
pub fn vnni() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::{Epilogue, Int8Weights, LANES};

    /// [`super::quantise`], sixteen values at a time (the float-to-byte cast does not vectorise).
    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub(crate) unsafe fn quantise_avx512(data: &[f32], out: &mut [u8], inv: f32, zero: f32) {
        let n = data.len().min(out.len());
        let (vi, vz, lo, hi) = (_mm512_set1_ps(inv), _mm512_set1_ps(zero), _mm512_setzero_ps(), _mm512_set1_ps(255.0));
        let mut i = 0;
        while i + 16 <= n {
            // SAFETY: i + 16 ≤ n, the length of both.
            unsafe {
                let v = _mm512_fmadd_ps(_mm512_loadu_ps(data.as_ptr().add(i)), vi, vz);
                let v = _mm512_min_ps(_mm512_max_ps(v, lo), hi);
                _mm_storeu_si128(out.as_mut_ptr().add(i) as *mut __m128i, _mm512_cvtepi32_epi8(_mm512_cvttps_epi32(v)));
            }
            i += 16;
        }
        super::quantise(&data[i..n], &mut out[i..n], inv, zero);
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    pub(crate) unsafe fn matmul_vnni(rows: &[u8], m: usize, w: &Int8Weights, e: &Epilogue, out: &mut [f32]) {
        // Tiles of six rows × blocks of 16 filters (at most 24 sums held in registers), then the
        // rows left one at a time.
        let mut r = 0;
        while r + 6 <= m {
            // SAFETY: rows r..r + 6 exist.
            unsafe { row_tiles::<6>(rows, r, w, e, out) };
            r += 6;
        }
        while r < m {
            // SAFETY: row r exists.
            unsafe { row_tiles::<1>(rows, r, w, e, out) };
            r += 1;
        }
    }

    /// Rows `r..r + MR` against every block of filters.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn row_tiles<const MR: usize>(rows: &[u8], r: usize, w: &Int8Weights, e: &Epilogue, out: &mut [f32]) {
        let blocks = w.blocks();
        let mut b = 0;
        while b < blocks {
            let left = blocks - b;
            // SAFETY (all three): blocks b..b + NB exist; the caller gives rows that exist.
            unsafe {
                if left >= 4 {
                    tile::<MR, 4>(rows, r, b, w, e, out);
                    b += 4;
                } else if left >= 2 {
                    tile::<MR, 2>(rows, r, b, w, e, out);
                    b += 2;
                } else {
                    tile::<MR, 1>(rows, r, b, w, e, out);
                    b += 1;
                }
            }
        }
    }

    /// Rows `r0..r0 + MR` (all of them rows of the product) against blocks `b0..b0 + NB`.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    #[inline]
    unsafe fn tile<const MR: usize, const NB: usize>(rows: &[u8], r0: usize, b0: usize, w: &Int8Weights, e: &Epilogue, out: &mut [f32]) {
        let depth = w.depth;
        let mut acc = [[_mm512_setzero_si512(); NB]; MR];
        let row_at: [*const u8; MR] = std::array::from_fn(|i| rows[(r0 + i) * depth..].as_ptr());
        let block_at: [*const i8; NB] = std::array::from_fn(|j| w.packed[(b0 + j) * depth * LANES..].as_ptr());
        for step in 0..depth / 4 {
            // SAFETY: each block holds depth / 4 steps of 64 bytes; each row holds depth bytes.
            unsafe {
                let ws: [__m512i; NB] = std::array::from_fn(|j| _mm512_loadu_si512(block_at[j].add(step * 64) as *const _));
                for i in 0..MR {
                    let a = _mm512_set1_epi32((row_at[i].add(step * 4) as *const i32).read_unaligned());
                    for j in 0..NB {
                        acc[i][j] = _mm512_dpbusd_epi32(acc[i][j], a, ws[j]);
                    }
                }
            }
        }
        let zero = _mm512_set1_epi32(e.input.zero as i32);
        for j in 0..NB {
            let first = (b0 + j) * LANES;
            let valid = w.filters.saturating_sub(first).min(LANES);
            let mask: __mmask16 = if valid == LANES { 0xffff } else { (1u16 << valid) - 1 };
            // SAFETY: the per-filter arrays are padded to whole blocks; the bias is read masked.
            unsafe {
                let sums = _mm512_loadu_si512(w.sums[first..].as_ptr() as *const _);
                let scale = _mm512_mul_ps(_mm512_loadu_ps(w.scale[first..].as_ptr()), _mm512_set1_ps(e.input.step));
                let bias = _mm512_maskz_loadu_ps(mask, e.bias[first..].as_ptr());
                let offset = _mm512_mullo_epi32(zero, sums);
                for i in 0..MR {
                    let v = _mm512_cvtepi32_ps(_mm512_sub_epi32(acc[i][j], offset));
                    let mut v = _mm512_fmadd_ps(v, scale, bias);
                    if e.relu {
                        v = _mm512_max_ps(v, _mm512_setzero_ps());
                    }
                    _mm512_mask_storeu_ps(out[(r0 + i) * w.filters + first..].as_mut_ptr(), mask, v);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 33) as f32 / (1u64 << 31) as f32) - 0.5
            })
            .collect()
    }

    #[test]
    fn quantisation_keeps_zero_exact_and_rounds_to_the_nearest_step() {
        for (data, zero) in [(noise(1000, 5).iter().map(|v| v.abs()).collect::<Vec<_>>(), Some(0)), (noise(1000, 6), None)] {
            let q = Quantisation::of(&data);
            if let Some(z) = zero {
                assert_eq!(q.zero, z, "ReLU outputs use all 256 bytes above zero");
            }
            let mut bytes = vec![0u8; data.len() + 1];
            q.apply(&[&data[..], &[0.0]].concat(), &mut bytes);
            assert_eq!(bytes[data.len()], q.zero, "zero is exact (the padding)");
            for (x, b) in data.iter().zip(&bytes) {
                let back = (*b as f32 - q.zero as f32) * q.step;
                assert!((back - x).abs() <= 0.5001 * q.step + 1e-6, "{x} → {b} → {back}");
            }
        }
    }

    /// The vector quantisation (where the CPU has it) gives the portable loop's bytes, tail and
    /// out-of-range values included.
    #[test]
    fn quantisation_kernels_agree() {
        let data: Vec<f32> = noise(1007, 9).iter().map(|v| v * 3.0).collect();
        let q = Quantisation::of(&data[..500]);
        let (mut fast, mut slow) = (vec![0u8; data.len()], vec![0u8; data.len()]);
        q.apply(&data, &mut fast);
        quantise(&data, &mut slow, 1.0 / q.step, q.zero as f32 + 0.5);
        assert_eq!(fast, slow);
        assert!(fast.contains(&0) && fast.contains(&255), "values outside the first half's range clamp");
    }

    /// The fast kernel (where the CPU has it) gives the reference's bits, on sizes that leave
    /// partial row tiles, partial filter blocks and a padded depth.
    #[test]
    fn kernels_agree_exactly_and_approximate_the_float_product() {
        for (m, depth, filters) in [(1, 3, 1), (7, 9, 17), (13, 36, 64), (25, 290, 96), (6, 64, 130)] {
            let rhs = noise(depth * filters, 1 + m as u64);
            let lhs: Vec<f32> = noise(m * depth, 7 + depth as u64).iter().map(|v| v.max(-0.2)).collect();
            let bias = noise(filters, 3);
            let w = Int8Weights::new(&rhs, depth, filters);
            let input = Quantisation::of(&lhs);
            let mut rows = vec![0u8; m * w.depth];
            for r in 0..m {
                input.apply(&lhs[r * depth..(r + 1) * depth], &mut rows[r * w.depth..r * w.depth + depth]);
            }
            for relu in [false, true] {
                let e = Epilogue { input, bias: &bias, relu };
                let (mut fast, mut slow) = (vec![0.0; m * filters], vec![0.0; m * filters]);
                matmul(&rows, m, &w, &e, &mut fast);
                matmul_portable(&rows, m, &w, &e, &mut slow);
                assert_eq!(fast, slow, "{m}×{depth}×{filters}");
                for r in 0..m {
                    for o in 0..filters {
                        let exact: f32 = (0..depth).map(|d| lhs[r * depth + d] * rhs[d * filters + o]).sum::<f32>() + bias[o];
                        let exact = if relu { exact.max(0.0) } else { exact };
                        // Two roundings of half a step each, summed over the depth.
                        let bound = 0.01 * (depth as f32).sqrt() + 1e-3;
                        assert!((slow[r * filters + o] - exact).abs() < bound, "{m}×{depth}×{filters} ({r},{o})");
                    }
                }
            }
        }
    }
}
