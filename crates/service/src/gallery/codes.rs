//! Templates held in 4 bits per value for the identification scan, and the scan itself.
//!
//! A gallery of ten million 256-value float templates is 10 GB; in 4 bits it is 1.3 GB, and a scan
//! reads an eighth of the bytes. The scan only shortlists: the shortlisted subjects are re-scored
//! exactly from the store's float templates (`Facegate::identify`), so no score or decision the
//! service gives comes from a quantised value.
//!
//! A template `x` is scaled by its largest magnitude to integers `q` in −7…7 (`step = max|x| / 7`)
//! kept as nibbles `q + 8`; its cosine with a probe `p` quantised to `p8` in −127…127
//! (`pstep = max|p| / 127`) is about `(Σ qᵢ·p8ᵢ) · step/‖x‖ · pstep/‖p‖`, and `Σ qᵢ·p8ᵢ =
//! Σ (qᵢ + 8)·p8ᵢ − 8·Σ p8ᵢ`: an unsigned-by-signed byte product, which x86 multiplies 32 (AVX2
//! `vpmaddubsw`) or 64 at a time (AVX-512 VNNI `vpdpbusd`), chosen at run time.
//!
//! Layout: values are padded with zeros to a multiple of [`BLOCK`] (128); each block of 128 values
//! is 64 bytes, byte `j` holding value `j` in its low nibble and value `64 + j` in its high one, so
//! that one 64-byte load splits into two runs of 64 consecutive values with a mask and a shift.

/// Values per block of the nibble layout.
pub const BLOCK: usize = 128;

/// Largest quantised magnitude of a template value.
const LEVELS: f32 = 7.0;

/// Bytes per template of `dimension` values.
pub fn code_len(dimension: usize) -> usize {
    dimension.div_ceil(BLOCK) * BLOCK / 2
}

/// `x` in nibbles (appended to `out`: [`code_len`] bytes) and the factor that turns its integer
/// dot product with a quantised probe into a cosine (`step / ‖x‖`; 0 for a zero vector).
pub fn encode(x: &[f32], out: &mut Vec<u8>) -> f32 {
    let (max, squares) = max_abs_and_squares(x);
    let norm = squares.sqrt();
    let start = out.len();
    out.resize(start + code_len(x.len()), 0);
    if max == 0.0 || !norm.is_finite() || norm == 0.0 {
        out[start..].fill(0x88);
        return 0.0;
    }
    let step = max / LEVELS;
    let per_step = 1.0 / step;
    let code = &mut out[start..];
    let mut nibbles = [8u8; BLOCK];
    for (block, values) in code.chunks_exact_mut(BLOCK / 2).zip(x.chunks(BLOCK)) {
        // Rounded half up by truncating a positive number (`round` is a library call); a short
        // last block keeps the zero nibble (8) past its end.
        for (n, v) in nibbles.iter_mut().zip(values) {
            *n = ((v * per_step).clamp(-LEVELS, LEVELS) + 8.5) as u8;
        }
        nibbles[values.len()..].fill(8);
        let (low, high) = nibbles.split_at(BLOCK / 2);
        for ((byte, l), h) in block.iter_mut().zip(low).zip(high) {
            *byte = l | (h << 4);
        }
    }
    step / norm
}

/// The largest magnitude of `x` and its sum of squares, in 16 lanes that the compiler vectorises
/// (a running sum is one dependent addition per value: the start-up load encodes ten million
/// templates).
fn max_abs_and_squares(x: &[f32]) -> (f32, f32) {
    const LANES: usize = 16;
    let (mut max, mut squares) = ([0.0f32; LANES], [0.0f32; LANES]);
    let chunks = x.chunks_exact(LANES);
    let rest = chunks.remainder();
    for chunk in chunks {
        for ((m, s), v) in max.iter_mut().zip(squares.iter_mut()).zip(chunk) {
            *m = m.max(v.abs());
            *s += v * v;
        }
    }
    let max = rest.iter().fold(max.iter().fold(0.0f32, |a, &b| a.max(b)), |m, v| m.max(v.abs()));
    (max, rest.iter().fold(squares.iter().sum::<f32>(), |s, v| s + v * v))
}

/// A probe quantised for the scan: its bytes in the same order as a template's values (padded),
/// their sum (the nibbles' offset of 8), and `pstep / ‖p‖`.
pub struct QuantisedProbe {
    values: Vec<i8>,
    offset: i32,
    scale: f32,
}

impl QuantisedProbe {
    pub fn new(p: &[f32]) -> QuantisedProbe {
        let padded = p.len().div_ceil(BLOCK) * BLOCK;
        let (max, squares) = max_abs_and_squares(p);
        let norm = squares.sqrt();
        if max == 0.0 || !norm.is_finite() || norm == 0.0 {
            return QuantisedProbe { values: vec![0; padded], offset: 0, scale: 0.0 };
        }
        let step = max / 127.0;
        let mut values: Vec<i8> = p.iter().map(|v| (v / step).round().clamp(-127.0, 127.0) as i8).collect();
        values.resize(padded, 0);
        let offset = 8 * values.iter().map(|&v| v as i32).sum::<i32>();
        QuantisedProbe { values, offset, scale: step / norm }
    }
}

/// The approximate cosine of the probe with each template of `codes` (rows of
/// `code_len(dimension)` bytes, with their factors `scales`), handed to `each(row, cosine)` in row
/// order, with the fastest kernel this CPU runs.
pub fn scan(codes: &[u8], scales: &[f32], probe: &QuantisedProbe, each: impl FnMut(usize, f32)) {
    scan_with(Kernel::detect(), codes, scales, probe, each)
}

/// [`scan`] with `kernel`, which the CPU must run (see [`Kernel::available`]).
pub fn scan_with(kernel: Kernel, codes: &[u8], scales: &[f32], probe: &QuantisedProbe, each: impl FnMut(usize, f32)) {
    assert!(Kernel::available().contains(&kernel), "{kernel:?} does not run on this CPU");
    if probe.values.is_empty() {
        return;
    }
    match kernel {
        Kernel::Portable => scan_rows(codes, scales, probe, each, dot_portable),
        // SAFETY: the CPU has the kernel's features (asserted above); `scan_rows` hands the dot
        // product a code of half the probe's length, a multiple of BLOCK.
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 => unsafe { x86::scan_avx2(codes, scales, probe, each) },
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx512Vnni => unsafe { x86::scan_avx512_vnni(codes, scales, probe, each) },
    }
}

/// The row loop every kernel shares; `dot` is inlined into each kernel's copy.
#[inline(always)]
fn scan_rows(codes: &[u8], scales: &[f32], probe: &QuantisedProbe, mut each: impl FnMut(usize, f32), dot: impl Fn(&[u8], &[i8]) -> i32) {
    let len = probe.values.len() / 2;
    let factor = probe.scale;
    for (row, (code, &scale)) in codes.chunks_exact(len).zip(scales).enumerate() {
        let integer = dot(code, &probe.values) - probe.offset;
        each(row, integer as f32 * scale * factor);
    }
}

/// The integer dot product of nibble codes with a probe's bytes, as the CPU can do it fastest.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512Vnni,
}

impl Kernel {
    /// The kernels this CPU runs, slowest first.
    pub fn available() -> Vec<Kernel> {
        #[allow(unused_mut)]
        let mut kernels = vec![Kernel::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                kernels.push(Kernel::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512bw") && std::arch::is_x86_feature_detected!("avx512vnni") {
                kernels.push(Kernel::Avx512Vnni);
            }
        }
        kernels
    }

    /// The fastest kernel this CPU runs.
    pub fn detect() -> Kernel {
        *Kernel::available().last().expect("the portable kernel runs everywhere")
    }
}

/// The best `n` subjects offered during a scan, one entry per subject (its best cosine): a few
/// dozen entries searched linearly, touched only when a row beats the current floor.
pub struct Best {
    n: usize,
    entries: Vec<(u32, f32)>,
    floor: f32,
}

impl Best {
    pub fn new(n: usize) -> Best {
        Best { n, entries: Vec::with_capacity(n), floor: if n == 0 { f32::INFINITY } else { f32::NEG_INFINITY } }
    }

    /// The score a row must beat to enter (−∞ until `n` subjects are held).
    #[inline]
    pub fn floor(&self) -> f32 {
        self.floor
    }

    /// Offer `slot`'s row scoring `cosine` (above the floor).
    #[cold]
    pub fn offer(&mut self, slot: u32, cosine: f32) {
        if let Some(entry) = self.entries.iter_mut().find(|(s, _)| *s == slot) {
            entry.1 = entry.1.max(cosine);
        } else if self.entries.len() < self.n {
            self.entries.push((slot, cosine));
        } else {
            let lowest = self.entries.iter().enumerate().min_by(|a, b| a.1.1.total_cmp(&b.1.1)).map(|(i, _)| i).expect("n > 0");
            self.entries[lowest] = (slot, cosine);
        }
        if self.entries.len() == self.n {
            self.floor = self.entries.iter().map(|e| e.1).fold(f32::INFINITY, f32::min);
        }
    }

    /// The subjects held.
    pub fn slots(&self) -> impl Iterator<Item = u32> + '_ {
        self.entries.iter().map(|e| e.0)
    }
}

fn dot_portable(code: &[u8], probe: &[i8]) -> i32 {
    let mut sum = 0i32;
    for (block, values) in code.chunks_exact(BLOCK / 2).zip(probe.chunks_exact(BLOCK)) {
        let (low, high) = values.split_at(BLOCK / 2);
        for ((&byte, &l), &h) in block.iter().zip(low).zip(high) {
            sum += (byte & 0x0f) as i32 * l as i32 + (byte >> 4) as i32 * h as i32;
        }
    }
    sum
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::BLOCK;

    use super::{QuantisedProbe, scan_rows};

    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn scan_avx2(codes: &[u8], scales: &[f32], probe: &QuantisedProbe, each: impl FnMut(usize, f32)) {
        // SAFETY: the caller's CPU has AVX2; scan_rows passes matching lengths.
        scan_rows(codes, scales, probe, each, |c, p| unsafe { dot_avx2(c, p) })
    }

    /// # Safety
    /// The CPU must have AVX-512 BW and VNNI.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    pub unsafe fn scan_avx512_vnni(codes: &[u8], scales: &[f32], probe: &QuantisedProbe, each: impl FnMut(usize, f32)) {
        // SAFETY: the caller's CPU has the features; scan_rows passes matching lengths.
        scan_rows(codes, scales, probe, each, |c, p| unsafe { dot_avx512_vnni(c, p) })
    }

    /// # Safety
    /// The CPU must have AVX2; `probe.len() == 2 * code.len()`, a multiple of [`BLOCK`].
    #[inline]
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot_avx2(code: &[u8], probe: &[i8]) -> i32 {
        let mask = _mm256_set1_epi8(0x0f);
        let ones = _mm256_set1_epi16(1);
        let mut acc = _mm256_setzero_si256();
        for (block, values) in code.chunks_exact(BLOCK / 2).zip(probe.chunks_exact(BLOCK)) {
            for half in 0..2 {
                // SAFETY: 32 bytes at offset 32·half of a 64-byte block, and of its 64-value runs.
                let (bytes, low, high) = unsafe {
                    (
                        _mm256_loadu_si256(block.as_ptr().add(32 * half).cast()),
                        _mm256_loadu_si256(values.as_ptr().add(32 * half).cast()),
                        _mm256_loadu_si256(values.as_ptr().add(BLOCK / 2 + 32 * half).cast()),
                    )
                };
                let lo = _mm256_and_si256(bytes, mask);
                let hi = _mm256_and_si256(_mm256_srli_epi16(bytes, 4), mask);
                // Each 16-bit sum is at most 4 · 15 · 127: no saturation.
                let pairs = _mm256_add_epi16(_mm256_maddubs_epi16(lo, low), _mm256_maddubs_epi16(hi, high));
                acc = _mm256_add_epi32(acc, _mm256_madd_epi16(pairs, ones));
            }
        }
        let sum = _mm_add_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
        let sum = _mm_add_epi32(sum, _mm_shuffle_epi32(sum, 0b01_00_11_10));
        let sum = _mm_add_epi32(sum, _mm_shuffle_epi32(sum, 0b10_11_00_01));
        _mm_cvtsi128_si32(sum)
    }

    /// # Safety
    /// The CPU must have AVX-512 BW and VNNI; `probe.len() == 2 * code.len()`, a multiple of
    /// [`BLOCK`].
    #[inline]
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    pub unsafe fn dot_avx512_vnni(code: &[u8], probe: &[i8]) -> i32 {
        let mask = _mm512_set1_epi8(0x0f);
        let mut acc = _mm512_setzero_si512();
        for (block, values) in code.chunks_exact(BLOCK / 2).zip(probe.chunks_exact(BLOCK)) {
            // SAFETY: one 64-byte block and its two 64-value runs.
            let (bytes, low, high) = unsafe {
                (
                    _mm512_loadu_si512(block.as_ptr().cast()),
                    _mm512_loadu_si512(values.as_ptr().cast()),
                    _mm512_loadu_si512(values.as_ptr().add(BLOCK / 2).cast()),
                )
            };
            let lo = _mm512_and_si512(bytes, mask);
            let hi = _mm512_and_si512(_mm512_srli_epi16(bytes, 4), mask);
            acc = _mm512_dpbusd_epi32(acc, lo, low);
            acc = _mm512_dpbusd_epi32(acc, hi, high);
        }
        _mm512_reduce_add_epi32(acc)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random(rng: &mut impl Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
    }

    fn cosine(a: &[f32], b: &[f32]) -> f32 {
        let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
        dot / (a.iter().map(|x| x * x).sum::<f32>().sqrt() * b.iter().map(|x| x * x).sum::<f32>().sqrt())
    }

    /// One template's integer dot product with `kernel`.
    fn dot_with(kernel: Kernel, code: &[u8], values: &[i8]) -> i32 {
        let probe = QuantisedProbe { values: values.to_vec(), offset: 0, scale: 1.0 };
        let mut got = 0;
        scan_with(kernel, code, &[1.0], &probe, |_, v| got = v as i32);
        got
    }

    #[test]
    fn every_kernel_gives_the_portable_sum() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for dimension in [1, 100, 128, 129, 256, 512] {
            let mut code = Vec::new();
            encode(&random(&mut rng, dimension), &mut code);
            let probe = QuantisedProbe::new(&random(&mut rng, dimension));
            // Extreme values too: every nibble 15 against bytes of ±127.
            let full = vec![0xffu8; code.len()];
            let extreme: Vec<i8> = (0..probe.values.len()).map(|i| if i % 3 == 0 { -127 } else { 127 }).collect();
            for kernel in Kernel::available() {
                assert_eq!(dot_with(kernel, &code, &probe.values), dot_portable(&code, &probe.values), "{kernel:?} {dimension}");
                assert_eq!(dot_with(kernel, &full, &extreme), dot_portable(&full, &extreme), "{kernel:?} {dimension}");
            }
        }
    }

    #[test]
    fn the_scan_approximates_the_cosine() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let dimension = 256;
        let templates: Vec<Vec<f32>> = (0..200).map(|_| random(&mut rng, dimension)).collect();
        let (mut codes, mut scales) = (Vec::new(), Vec::new());
        for t in &templates {
            scales.push(encode(t, &mut codes));
        }
        let p = random(&mut rng, dimension);
        let mut worst = 0.0f32;
        let mut rows = 0;
        scan(&codes, &scales, &QuantisedProbe::new(&p), |row, approx| {
            worst = worst.max((approx - cosine(&templates[row], &p)).abs());
            rows += 1;
        });
        assert_eq!(rows, 200);
        assert!(worst < 0.02, "largest error {worst}");
        assert!(worst > 0.0, "the values are quantised");
    }

    #[test]
    fn best_keeps_the_top_subjects_once_each() {
        let mut best = Best::new(2);
        for (slot, cosine) in [(5, 0.1), (6, 0.3), (5, 0.5), (7, 0.2), (8, 0.4), (6, 0.35)] {
            if cosine > best.floor() {
                best.offer(slot, cosine);
            }
        }
        let mut held: Vec<u32> = best.slots().collect();
        held.sort();
        assert_eq!((held, best.floor()), (vec![5, 8], 0.4));
        assert!(Best::new(0).slots().next().is_none() && Best::new(0).floor() == f32::INFINITY);
    }

    #[test]
    fn zero_vectors_score_zero() {
        let mut codes = Vec::new();
        let scale = encode(&[0.0; 10], &mut codes);
        assert_eq!((codes.len(), scale), (64, 0.0));
        let mut got = Vec::new();
        scan(&codes, &[scale], &QuantisedProbe::new(&[1.0; 10]), |_, c| got.push(c));
        assert_eq!(got, vec![0.0]);
        scan(&codes, &[scale], &QuantisedProbe::new(&[0.0; 10]), |_, c| got.push(c));
        assert_eq!(got, vec![0.0, 0.0]);
    }
}
