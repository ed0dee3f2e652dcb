//! The convolution kernels both network runners share: a layer's batch normalisation folded into
//! its weights ([`FoldedConv`]), channels-last activations ([`Act`]), and each convolution as an
//! im2col copy and one matrix product — faer's float product (SIMD kernels chosen at run time) or,
//! for a layer with `i8` weights, [`crate::int8`]'s integer one.

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

use crate::int8::{self, Epilogue, Int8Weights, Quantisation};
use crate::weights::Conv;

/// Products per output below which a layer stays in floats ([`int8_weights`]).
const MIN_INT8_DEPTH: usize = 64;

/// The `i8` weights of a layer (`rhs`: `depth × outputs`, as the float product takes it) that
/// computes in `arithmetic`, or `None` for floats. A layer of few products per output (a first
/// convolution over the photo's three channels under a 3×3 kernel: 27) stays in floats whatever is
/// asked: in 8 bits SFace's lost a point of EER on UMIST's grey profiles, while dlib's 7×7 stem
/// (147 products) lost nothing measurable (docs/speed.md).
pub(crate) fn int8_weights(arithmetic: Arithmetic, rhs: &[f32], depth: usize, outputs: usize) -> Option<Int8Weights> {
    (arithmetic == Arithmetic::Int8 && depth >= MIN_INT8_DEPTH).then(|| Int8Weights::new(rhs, depth, outputs))
}

/// How the networks' convolutions compute.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arithmetic {
    /// 32-bit floats throughout.
    Float,
    /// The convolutions in 8-bit integers ([`crate::int8`]) but a first one of few products
    /// per output (SFace's), and an ONNX network's fully connected layer; the pools, the depthwise
    /// convolutions and dlib's final layer stay in floats.
    Int8,
}

impl Arithmetic {
    /// `Int8` where the CPU has its fast kernel (AVX-512 VNNI), `Float` elsewhere: without it
    /// the integer product is slower than the float one.
    pub fn detect() -> Arithmetic {
        if int8::vnni() { Arithmetic::Int8 } else { Arithmetic::Float }
    }
}

/// A convolution with its batch normalisation folded in, weights as the `(k·k·c) × filters`
/// right-hand side of the im2col product (rows ordered ky, kx, channel).
pub(crate) struct FoldedConv {
    pub(crate) filters: usize,
    pub(crate) channels: usize,
    size: usize,
    stride: usize,
    padding: usize,
    rhs: Vec<f32>,
    bias: Vec<f32>,
    /// The weights in `i8`, when the layer computes in integers.
    int8: Option<Int8Weights>,
}

impl FoldedConv {
    pub(crate) fn new(conv: &Conv, gamma: &[f32], beta: &[f32]) -> Result<FoldedConv, String> {
        let (f, c, k) = (conv.filters, conv.channels, conv.size);
        if gamma.len() != f || beta.len() != f {
            return Err(format!("affine of {} channels after {f} filters", gamma.len()));
        }
        let mut rhs = vec![0.0f32; k * k * c * f];
        for o in 0..f {
            for ch in 0..c {
                for ky in 0..k {
                    for kx in 0..k {
                        let w = conv.weights[((o * c + ch) * k + ky) * k + kx];
                        rhs[((ky * k + kx) * c + ch) * f + o] = w * gamma[o];
                    }
                }
            }
        }
        let bias = (0..f).map(|o| conv.bias[o] * gamma[o] + beta[o]).collect();
        Ok(FoldedConv { filters: f, channels: c, size: k, stride: conv.stride, padding: conv.padding, rhs, bias, int8: None })
    }

    /// A convolution whose batch normalisation is already in its weights and bias.
    pub(crate) fn prefolded(conv: &Conv) -> FoldedConv {
        let f = conv.filters;
        FoldedConv::new(conv, &vec![1.0; f], &vec![0.0; f]).expect("one unit scale and zero shift per filter")
    }

    /// Sets the layer to compute in `arithmetic` ([`int8_weights`]). A layer whose float weights
    /// were released ([`FoldedConv::release_floats`]) keeps computing in integers.
    pub(crate) fn set_arithmetic(&mut self, arithmetic: Arithmetic) {
        if self.rhs.is_empty() && self.int8.is_some() {
            return;
        }
        self.int8 = int8_weights(arithmetic, &self.rhs, self.size * self.size * self.channels, self.filters);
    }

    /// Lets go of the float weights of a layer that computes in integers: nothing reads them
    /// then, and they are four times the integer copy.
    pub(crate) fn release_floats(&mut self) {
        if self.int8.is_some() {
            self.rhs = Vec::new();
        }
    }

    /// A 1×1 convolution of stride 1: its input is the product's left-hand side, no im2col copy.
    fn pointwise(&self) -> bool {
        self.size == 1 && self.stride == 1 && self.padding == 0
    }

    pub(crate) fn out_side(&self, side: usize) -> usize {
        (side + 2 * self.padding - self.size) / self.stride + 1
    }
}

/// Activations: `h × w × c`, channels fastest.
#[derive(Default)]
pub(crate) struct Act {
    pub(crate) h: usize,
    pub(crate) w: usize,
    pub(crate) c: usize,
    pub(crate) data: Vec<f32>,
}

impl Act {
    pub(crate) fn reshape(&mut self, h: usize, w: usize, c: usize) {
        self.h = h;
        self.w = w;
        self.c = c;
        self.data.resize(h * w * c, 0.0);
    }
}

/// The im2col copies of a convolution's input: floats, or bytes for an integer layer (whose
/// input is quantised first, since the copy reads each value up to k·k times).
#[derive(Default)]
pub(crate) struct Cols {
    floats: Vec<f32>,
    input: Vec<u8>,
    rows: Vec<u8>,
}

impl Cols {
    /// A byte buffer for a layer that is not a convolution (its contents are not kept).
    pub(crate) fn bytes(&mut self) -> &mut Vec<u8> {
        &mut self.rows
    }
}

/// `out = conv(input)` (+ relu): im2col into `cols`, then one matrix product, in floats or (for a
/// layer with `i8` weights) in integers.
pub(crate) fn conv(layer: &FoldedConv, input: &Act, out: &mut Act, cols: &mut Cols, relu: bool) {
    debug_assert_eq!(input.c, layer.channels);
    let (ho, wo) = (layer.out_side(input.h), layer.out_side(input.w));
    out.reshape(ho, wo, layer.filters);
    match &layer.int8 {
        None => conv_float(layer, input, out, &mut cols.floats, relu),
        Some(weights) => {
            let (quantisation, rows) = input_bytes(layer, weights, input, cols);
            let epilogue = Epilogue { input: quantisation, bias: &layer.bias, relu };
            int8::matmul(rows, ho * wo, weights, &epilogue, &mut out.data);
        }
    }
}

/// An integer layer's input as bytes, and the rows of its product: the quantised input itself
/// for a 1×1 convolution of stride 1 over whole groups of four channels, else its im2col copy.
fn input_bytes<'c>(layer: &FoldedConv, weights: &Int8Weights, input: &Act, cols: &'c mut Cols) -> (Quantisation, &'c [u8]) {
    #[cfg(target_arch = "x86_64")]
    if int8::vnni() {
        // SAFETY: the CPU has AVX-512 F and BW (checked at run time).
        return unsafe { input_bytes_avx512(layer, weights, input, cols) };
    }
    input_bytes_body(layer, weights, input, cols)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,avx512f,avx512bw")]
fn input_bytes_avx512<'c>(layer: &FoldedConv, weights: &Int8Weights, input: &Act, cols: &'c mut Cols) -> (Quantisation, &'c [u8]) {
    input_bytes_body(layer, weights, input, cols)
}

#[inline(always)]
fn input_bytes_body<'c>(layer: &FoldedConv, weights: &Int8Weights, input: &Act, cols: &'c mut Cols) -> (Quantisation, &'c [u8]) {
    let quantisation = Quantisation::into_bytes(&input.data, &mut cols.input, input.data.len());
    if layer.pointwise() && weights.depth == layer.channels {
        return (quantisation, &cols.input);
    }
    im2col(layer, input, &cols.input, quantisation.zero, weights.depth, &mut cols.rows);
    (quantisation, &cols.rows)
}

/// The im2col copy of `values` (the input's `h × w × c` values, as floats or bytes): one row of
/// `row_len` per output pixel, `k·k·c` values in (ky, kx, channel) order, `pad` outside the
/// input, and `pad` again after them up to `row_len`. The taps of one kernel row that fall inside
/// the input are one run in both, so each is one copy.
#[inline(always)]
fn im2col<T: Copy>(layer: &FoldedConv, input: &Act, values: &[T], pad: T, row_len: usize, cols: &mut Vec<T>) {
    let (ho, wo) = (layer.out_side(input.h), layer.out_side(input.w));
    let (k, c, s, p) = (layer.size, layer.channels, layer.stride, layer.padding);
    cols.clear();
    cols.resize(ho * wo * row_len, pad);
    for oy in 0..ho {
        for ox in 0..wo {
            let row = &mut cols[(oy * wo + ox) * row_len..(oy * wo + ox) * row_len + k * k * c];
            // Taps kx in first..last land inside the row: 0 ≤ ox·s + kx − p < w.
            let first = p.saturating_sub(ox * s);
            let last = (input.w + p).saturating_sub(ox * s).min(k);
            if first >= last {
                continue;
            }
            let ix = ox * s + first - p;
            for ky in 0..k {
                let Some(iy) = (oy * s + ky).checked_sub(p).filter(|&iy| iy < input.h) else { continue };
                let at = (iy * input.w + ix) * c;
                row[(ky * k + first) * c..(ky * k + last) * c].copy_from_slice(&values[at..at + (last - first) * c]);
            }
        }
    }
}

/// [`conv`] in floats: faer's matrix product.
fn conv_float(layer: &FoldedConv, input: &Act, out: &mut Act, cols: &mut Vec<f32>, relu: bool) {
    let kk = layer.size * layer.size * layer.channels;
    let pointwise = layer.pointwise();
    if !pointwise {
        im2col(layer, input, &input.data, 0.0, kk, cols);
    }
    let (m, f) = (out.h * out.w, layer.filters);
    let lhs = MatRef::from_row_major_slice(if pointwise { &input.data[..] } else { &cols[..] }, m, kk);
    let rhs = MatRef::from_row_major_slice(&layer.rhs[..], kk, f);
    let dst = MatMut::from_row_major_slice_mut(&mut out.data[..], m, f);
    matmul(dst, Accum::Replace, lhs, rhs, 1.0f32, Par::Seq);
    for px in out.data.chunks_exact_mut(f) {
        for (v, b) in px.iter_mut().zip(&layer.bias) {
            *v += b;
            if relu {
                *v = v.max(0.0);
            }
        }
    }
}
