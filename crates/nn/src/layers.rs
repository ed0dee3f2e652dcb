//! The layers other than plain convolutions that the ONNX chain ([`crate::chain`]) and MiniFASNet
//! ([`crate::minifasnet`]) share: the depthwise convolution, PReLU and the fully connected layer.
//! Activations are channels-last ([`Act`]), so a depthwise tap and a PReLU run along the channels
//! in their inner loop, branch-free; both are compiled a second time for AVX2 and FMA and picked
//! at run time.

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

use crate::conv::{Act, Arithmetic, Cols, int8_weights};
use crate::int8::{self, Epilogue, Int8Weights, Quantisation};

/// Depthwise convolution weights as `k × k × channels` (channels fastest).
pub(crate) struct Depthwise {
    pub(crate) channels: usize,
    pub(crate) size: usize,
    stride: usize,
    padding: usize,
    weights: Vec<f32>,
    bias: Vec<f32>,
}

impl Depthwise {
    /// From weights as ONNX and PyTorch store them (`channels × 1 × k × k`), one bias per channel.
    pub(crate) fn new(channels: usize, size: usize, stride: usize, padding: usize, weights: &[f32], bias: Vec<f32>) -> Depthwise {
        assert_eq!(weights.len(), channels * size * size, "depthwise weights of {channels} channels, {size}×{size}");
        assert_eq!(bias.len(), channels, "depthwise bias of {channels} channels");
        let mut taps_first = vec![0.0f32; weights.len()];
        for ch in 0..channels {
            for t in 0..size * size {
                taps_first[t * channels + ch] = weights[ch * size * size + t];
            }
        }
        Depthwise { channels, size, stride, padding, weights: taps_first, bias }
    }

    pub(crate) fn out_side(&self, side: usize) -> usize {
        (side + 2 * self.padding - self.size) / self.stride + 1
    }
}

/// A fully connected layer: `inputs × outputs` row-major, rows in channels-last order.
pub(crate) struct Dense {
    pub(crate) inputs: usize,
    pub(crate) outputs: usize,
    pub(crate) rhs: Vec<f32>,
    pub(crate) bias: Vec<f32>,
    /// The weights in `i8`, when the layer computes in integers.
    pub(crate) int8: Option<Int8Weights>,
}

impl Dense {
    /// From weights as PyTorch's `Linear` stores them (`outputs × inputs`).
    pub(crate) fn from_rows(inputs: usize, outputs: usize, weights: &[f32], bias: Vec<f32>) -> Dense {
        assert_eq!(weights.len(), inputs * outputs, "dense weights of {inputs} → {outputs}");
        assert_eq!(bias.len(), outputs, "dense bias of {outputs} outputs");
        let mut rhs = vec![0.0f32; inputs * outputs];
        for o in 0..outputs {
            for i in 0..inputs {
                rhs[i * outputs + o] = weights[o * inputs + i];
            }
        }
        Dense { inputs, outputs, rhs, bias, int8: None }
    }

    /// As [`crate::conv::FoldedConv`]'s: the layer computes in `arithmetic`, unless its float
    /// weights were released (then it stays in integers).
    pub(crate) fn set_arithmetic(&mut self, arithmetic: Arithmetic) {
        if self.rhs.is_empty() && self.int8.is_some() {
            return;
        }
        self.int8 = int8_weights(arithmetic, &self.rhs, self.inputs, self.outputs);
    }

    /// Lets go of the float weights when the layer computes in integers.
    pub(crate) fn release_floats(&mut self) {
        if self.int8.is_some() {
            self.rhs = Vec::new();
        }
    }
}

/// `out = d(x)`: in integers (the one row quantised into the scratch bytes, zero-padded to the
/// weights' depth) or floats. `out` is resized to the layer's outputs.
pub(crate) fn dense(d: &Dense, x: &[f32], cols: &mut Cols, out: &mut Vec<f32>) {
    out.clear();
    out.extend_from_slice(&d.bias);
    match &d.int8 {
        Some(weights) => {
            let bytes = cols.bytes();
            let input = Quantisation::into_bytes(x, bytes, weights.depth);
            int8::matmul(bytes, 1, weights, &Epilogue { input, bias: &d.bias, relu: false }, out);
        }
        None => {
            let lhs = MatRef::from_row_major_slice(x, 1, d.inputs);
            let rhs = MatRef::from_row_major_slice(&d.rhs[..], d.inputs, d.outputs);
            matmul(MatMut::from_row_major_slice_mut(&mut out[..], 1, d.outputs), Accum::Add, lhs, rhs, 1.0f32, Par::Seq);
        }
    }
}

/// The crate is built for the x86-64 baseline (SSE2, 4 lanes); on a CPU with AVX2 and FMA the
/// element-wise kernels are compiled a second time for it (8 lanes, fused multiply-add).
#[cfg(target_arch = "x86_64")]
fn avx2_fma() -> bool {
    std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
}

#[cfg(not(target_arch = "x86_64"))]
fn avx2_fma() -> bool {
    false
}

/// PReLU on channels-last values: `slope` has one value per channel.
pub(crate) fn prelu(data: &mut [f32], slope: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has AVX2 and FMA (checked at run time).
        return unsafe { prelu_avx2(data, slope) };
    }
    prelu_body(data, slope)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn prelu_avx2(data: &mut [f32], slope: &[f32]) {
    prelu_body(data, slope)
}

/// `v` where positive, `slope · v` where negative; branch-free, so the loop vectorises (a branch
/// on the sign measured three times slower than the convolutions themselves).
#[inline(always)]
fn prelu_body(data: &mut [f32], slope: &[f32]) {
    for px in data.chunks_exact_mut(slope.len()) {
        for (v, s) in px.iter_mut().zip(slope) {
            *v = v.max(0.0) + s * v.min(0.0);
        }
    }
}

/// `out = depthwise(input)`: per channel, a `k × k` filter. Taps outermost, then the output
/// pixels each tap reaches, then the channels: the inner loop is branch-free along the channels.
pub(crate) fn depthwise(layer: &Depthwise, input: &Act, out: &mut Act) {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma() {
        // SAFETY: the CPU has AVX2 and FMA (checked at run time).
        return unsafe { depthwise_avx2(layer, input, out) };
    }
    depthwise_body(layer, input, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn depthwise_avx2(layer: &Depthwise, input: &Act, out: &mut Act) {
    depthwise_body(layer, input, out)
}

#[inline(always)]
fn depthwise_body(layer: &Depthwise, input: &Act, out: &mut Act) {
    let (k, s, p, c) = (layer.size, layer.stride, layer.padding, layer.channels);
    let (ho, wo, w) = (layer.out_side(input.h), layer.out_side(input.w), input.w);
    out.reshape(ho, wo, c);
    for oy in 0..ho {
        let row = &mut out.data[oy * wo * c..(oy + 1) * wo * c];
        for px in row.chunks_exact_mut(c) {
            px.copy_from_slice(&layer.bias);
        }
        for ky in 0..k {
            let Some(iy) = (oy * s + ky).checked_sub(p).filter(|&iy| iy < input.h) else { continue };
            let in_row = &input.data[iy * w * c..(iy + 1) * w * c];
            for kx in 0..k {
                let taps = &layer.weights[(ky * k + kx) * c..(ky * k + kx + 1) * c];
                // Output columns whose input column ox·s + kx − p lies inside the row: none when
                // the tap lies right of the row's last column even for the first output (a map
                // narrower than the kernel's reach).
                let first = p.saturating_sub(kx).div_ceil(s);
                let last = (w + p).checked_sub(kx + 1).map_or(0, |reach| (reach / s + 1).min(wo));
                for ox in first..last {
                    let ix = ox * s + kx - p;
                    let acc = &mut row[ox * c..(ox + 1) * c];
                    for ((a, v), t) in acc.iter_mut().zip(&in_row[ix * c..(ix + 1) * c]).zip(taps) {
                        *a += v * t;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A direct depthwise convolution on channel-first planes, the kernel's reference.
    fn reference(input: &Act, weights: &[f32], bias: &[f32], k: usize, s: usize, p: usize) -> Vec<f32> {
        let c = input.c;
        let side = |n: usize| (n + 2 * p - k) / s + 1;
        let (ho, wo) = (side(input.h), side(input.w));
        let mut out = vec![0.0f32; ho * wo * c];
        for ch in 0..c {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut acc = bias[ch];
                    for ky in 0..k {
                        for kx in 0..k {
                            let (iy, ix) = ((oy * s + ky) as isize - p as isize, (ox * s + kx) as isize - p as isize);
                            if iy >= 0 && ix >= 0 && (iy as usize) < input.h && (ix as usize) < input.w {
                                acc += input.data[(iy as usize * input.w + ix as usize) * c + ch] * weights[(ch * k + ky) * k + kx];
                            }
                        }
                    }
                    out[(oy * wo + ox) * c + ch] = acc;
                }
            }
        }
        out
    }

    #[test]
    fn depthwise_matches_the_direct_convolution_for_strides_paddings_and_a_whole_map_kernel() {
        // (height, width, kernel, stride, padding): the last two on maps smaller than the kernel.
        let cases = [(7, 6, 3, 1, 1), (7, 6, 3, 2, 1), (5, 5, 5, 1, 0), (7, 6, 1, 1, 0), (1, 1, 3, 1, 1), (2, 1, 3, 2, 1)];
        for (h, w, k, s, p) in cases {
            let mut input = Act::default();
            input.reshape(h, w, 5);
            for (i, v) in input.data.iter_mut().enumerate() {
                *v = ((i * 37 % 23) as f32 - 11.0) / 7.0;
            }
            let weights: Vec<f32> = (0..5 * k * k).map(|i| ((i * 13 % 17) as f32 - 8.0) / 9.0).collect();
            let bias: Vec<f32> = (0..5).map(|i| i as f32 * 0.25).collect();
            let layer = Depthwise::new(5, k, s, p, &weights, bias.clone());
            let mut out = Act::default();
            depthwise(&layer, &input, &mut out);
            let expected = reference(&input, &weights, &bias, k, s, p);
            assert_eq!(out.data.len(), expected.len(), "{h}×{w} k {k} s {s} p {p}");
            for (a, b) in out.data.iter().zip(&expected) {
                assert!((a - b).abs() < 1e-5, "{h}×{w} k {k} s {s} p {p}: {a} against {b}");
            }
        }
    }

    #[test]
    fn prelu_scales_only_the_negative_values_per_channel() {
        let mut data = vec![1.0, -2.0, -4.0, 3.0];
        prelu(&mut data, &[0.5, 0.25]);
        assert_eq!(data, vec![1.0, -0.5, -2.0, 3.0]);
    }

    #[test]
    fn dense_from_pytorch_rows_computes_the_product_plus_bias() {
        // outputs × inputs = 2 × 3.
        let d = Dense::from_rows(3, 2, &[1.0, 2.0, 3.0, -1.0, 0.0, 1.0], vec![0.5, -0.5]);
        let mut out = Vec::new();
        dense(&d, &[1.0, 1.0, 2.0], &mut Cols::default(), &mut out);
        assert_eq!(out, vec![9.5, 0.5]);
    }
}
