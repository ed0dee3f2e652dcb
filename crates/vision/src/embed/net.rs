//! The ResNet forward pass on one chip: channels-last activations, each convolution an im2col
//! copy and one matrix product (faer, SIMD kernels chosen at run time), batch normalisation folded
//! into the convolutions when the network is built. Buffers live in a [`Workspace`] that is reused
//! across calls, so a warm call allocates nothing.

use std::sync::Mutex;

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

use super::chip::FaceChip;
use super::int8::{self, Epilogue, Int8Weights, Quantisation};
use super::weights::{Conv, Layer, NetworkFile};

/// Products per output below which a layer stays in floats ([`int8_weights`]).
const MIN_INT8_DEPTH: usize = 64;

/// The `i8` weights of a layer (`rhs`: `depth × outputs`, as the float product takes it) that
/// computes in `arithmetic`, or `None` for floats. A layer of few products per output (a first
/// convolution over the photo's three channels under a 3×3 kernel: 27) stays in floats whatever is
/// asked: in 8 bits SFace's lost a point of EER on UMIST's grey profiles, while dlib's 7×7 stem
/// (147 products) lost nothing measurable (docs/speed.md).
pub(super) fn int8_weights(arithmetic: Arithmetic, rhs: &[f32], depth: usize, outputs: usize) -> Option<Int8Weights> {
    (arithmetic == Arithmetic::Int8 && depth >= MIN_INT8_DEPTH).then(|| Int8Weights::new(rhs, depth, outputs))
}

/// How the networks' convolutions compute.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arithmetic {
    /// 32-bit floats throughout.
    Float,
    /// The convolutions in 8-bit integers ([`super::int8`]) but a first one of few products
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

/// Length of an embedding.
pub const EMBEDDING_DIMS: usize = 128;

/// A face embedding: the network's output as it is (dlib compares these by Euclidean distance,
/// same person below 0.6).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Embedding(pub [f32; EMBEDDING_DIMS]);

impl Embedding {
    pub fn distance(&self, other: &Embedding) -> f32 {
        self.0.iter().zip(&other.0).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt()
    }

    pub fn cosine(&self, other: &Embedding) -> f32 {
        let dot: f32 = self.0.iter().zip(&other.0).map(|(a, b)| a * b).sum();
        let na: f32 = self.0.iter().map(|a| a * a).sum::<f32>().sqrt();
        let nb: f32 = other.0.iter().map(|b| b * b).sum::<f32>().sqrt();
        dot / (na * nb).max(f32::MIN_POSITIVE)
    }
}

/// The embeddings of a chip and of its mirror image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MirrorPair {
    pub direct: Embedding,
    pub mirrored: Embedding,
}

impl MirrorPair {
    /// Their mean: the embedding the deep recognizer uses.
    pub fn mean(&self) -> Embedding {
        let mut out = [0.0f32; EMBEDDING_DIMS];
        for ((o, x), y) in out.iter_mut().zip(self.direct.0).zip(self.mirrored.0) {
            *o = 0.5 * (x + y);
        }
        Embedding(out)
    }

    /// Cosine between the two (−1 to 1): a face and its mirror are the same person, so a
    /// well-aligned, sharp, frontal, unoccluded face gives nearly the same embedding both ways;
    /// a badly fitted, turned, blurred or occluded one does not (a two-sample form of SER-FIQ's
    /// embedding robustness, Terhörst et al. 2020).
    pub fn agreement(&self) -> f32 {
        self.direct.cosine(&self.mirrored)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum NetworkError {
    #[error("the network file does not have the expected ResNet layout: {0}")]
    Layout(String),
}

/// A convolution with its batch normalisation folded in, weights as the `(k·k·c) × filters`
/// right-hand side of the im2col product (rows ordered ky, kx, channel).
pub(super) struct FoldedConv {
    pub(super) filters: usize,
    pub(super) channels: usize,
    size: usize,
    stride: usize,
    padding: usize,
    rhs: Vec<f32>,
    bias: Vec<f32>,
    /// The weights in `i8`, when the layer computes in integers.
    int8: Option<Int8Weights>,
}

impl FoldedConv {
    pub(super) fn new(conv: &Conv, gamma: &[f32], beta: &[f32]) -> Result<FoldedConv, NetworkError> {
        let (f, c, k) = (conv.filters, conv.channels, conv.size);
        if gamma.len() != f || beta.len() != f {
            return Err(NetworkError::Layout(format!("affine of {} channels after {f} filters", gamma.len())));
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

    /// Sets the layer to compute in `arithmetic` ([`int8_weights`]).
    pub(super) fn set_arithmetic(&mut self, arithmetic: Arithmetic) {
        self.int8 = int8_weights(arithmetic, &self.rhs, self.size * self.size * self.channels, self.filters);
    }

    /// A 1×1 convolution of stride 1: its input is the product's left-hand side, no im2col copy.
    fn pointwise(&self) -> bool {
        self.size == 1 && self.stride == 1 && self.padding == 0
    }

    pub(super) fn out_side(&self, side: usize) -> usize {
        (side + 2 * self.padding - self.size) / self.stride + 1
    }
}

/// A residual unit: `relu(conv2(relu(conv1(x))) + shortcut(x))`; the down-sampling kind has a
/// stride-2 `conv1` and a 2×2 average pool as its shortcut.
struct Residual {
    conv1: FoldedConv,
    conv2: FoldedConv,
    down: bool,
}

/// Activations: `h × w × c`, channels fastest.
#[derive(Default)]
pub(super) struct Act {
    pub(super) h: usize,
    pub(super) w: usize,
    pub(super) c: usize,
    pub(super) data: Vec<f32>,
}

impl Act {
    pub(super) fn reshape(&mut self, h: usize, w: usize, c: usize) {
        self.h = h;
        self.w = w;
        self.c = c;
        self.data.resize(h * w * c, 0.0);
    }
}

/// The im2col copies of a convolution's input: floats, or bytes for an integer layer (whose
/// input is quantised first, since the copy reads each value up to k·k times).
#[derive(Default)]
pub(super) struct Cols {
    floats: Vec<f32>,
    input: Vec<u8>,
    rows: Vec<u8>,
}

impl Cols {
    /// A byte buffer for a layer that is not a convolution (its contents are not kept).
    pub(super) fn bytes(&mut self) -> &mut Vec<u8> {
        &mut self.rows
    }
}

/// Scratch buffers for one forward pass at a time.
#[derive(Default)]
pub struct Workspace {
    x: Act,
    t: Act,
    u: Act,
    s: Act,
    cols: Cols,
}

/// The loaded network.
pub struct Embedder {
    input_size: usize,
    input_mean: [f32; 3],
    stem: FoldedConv,
    stem_pool: (usize, usize, usize),
    units: Vec<Residual>,
    fc: Vec<f32>,
    fc_inputs: usize,
    workspaces: Mutex<Vec<Workspace>>,
}

/// Consumes layers in order, checking each is what the ResNet layout puts there.
struct Layers<'a> {
    rest: std::slice::Iter<'a, Layer>,
}

impl<'a> Layers<'a> {
    fn next(&mut self, what: &str) -> Result<&'a Layer, NetworkError> {
        self.rest.next().ok_or_else(|| NetworkError::Layout(format!("ends where a {what} was expected")))
    }

    fn conv_affine(&mut self) -> Result<FoldedConv, NetworkError> {
        let Layer::Conv(conv) = self.next("convolution")? else {
            return Err(NetworkError::Layout("expected a convolution".into()));
        };
        let Layer::Affine { gamma, beta } = self.next("affine layer")? else {
            return Err(NetworkError::Layout("expected an affine layer after a convolution".into()));
        };
        FoldedConv::new(conv, gamma, beta)
    }

    fn relu(&mut self) -> Result<(), NetworkError> {
        match self.next("relu")? {
            Layer::Relu => Ok(()),
            other => Err(NetworkError::Layout(format!("expected relu, found {other:?}").chars().take(80).collect())),
        }
    }
}

impl Embedder {
    /// Builds the network from the project's weight file: stem (conv, affine, relu, max pool),
    /// residual units, global average pool, fully connected layer to 128 values; in this CPU's
    /// arithmetic ([`Arithmetic::detect`]).
    pub fn new(file: &NetworkFile) -> Result<Embedder, NetworkError> {
        let mut layers = Layers { rest: file.layers.iter() };
        let stem = layers.conv_affine()?;
        layers.relu()?;
        let stem_pool = match layers.next("max pool")? {
            Layer::MaxPool { size, stride, padding } => (*size, *stride, *padding),
            _ => return Err(NetworkError::Layout("expected the stem's max pool".into())),
        };
        let mut units = Vec::new();
        let (fc, fc_inputs) = loop {
            match layers.rest.as_slice().first() {
                Some(Layer::AvgPool { size: 0, .. }) => {
                    layers.next("pool")?;
                    match layers.next("fc layer")? {
                        Layer::Fc { inputs, outputs, weights } if *outputs == EMBEDDING_DIMS => break (weights.clone(), *inputs),
                        _ => return Err(NetworkError::Layout("expected a 128-output fc layer".into())),
                    }
                }
                Some(Layer::Conv(_)) => {
                    let conv1 = layers.conv_affine()?;
                    layers.relu()?;
                    let conv2 = layers.conv_affine()?;
                    let down = match layers.next("add or pool")? {
                        Layer::AddPrev => false,
                        Layer::AvgPool { size: 2, stride: 2, padding: 0 } => {
                            if !matches!(layers.next("add")?, Layer::AddPrev) {
                                return Err(NetworkError::Layout("expected add after the shortcut pool".into()));
                            }
                            true
                        }
                        _ => return Err(NetworkError::Layout("expected a residual add".into())),
                    };
                    layers.relu()?;
                    if conv1.channels != units.last().map_or(stem.filters, |u: &Residual| u.conv2.filters)
                        || conv2.channels != conv1.filters
                        || (!down && conv2.filters != conv1.channels)
                    {
                        return Err(NetworkError::Layout("residual unit channels do not chain".into()));
                    }
                    units.push(Residual { conv1, conv2, down });
                }
                _ => return Err(NetworkError::Layout("expected a residual unit or the final pool".into())),
            }
        };
        if layers.rest.next().is_some() {
            return Err(NetworkError::Layout("layers after the fc layer".into()));
        }
        // `forward` pools into a fixed 512-value buffer.
        if stem.channels != 3 || fc_inputs != units.last().map_or(0, |u| u.conv2.filters) || fc_inputs > 512 {
            return Err(NetworkError::Layout("input or fc sizes do not chain".into()));
        }
        Ok(Embedder {
            input_size: file.input_size,
            input_mean: file.input_mean,
            stem,
            stem_pool,
            units,
            fc,
            fc_inputs,
            workspaces: Mutex::new(Vec::new()),
        }
        .with_arithmetic(Arithmetic::detect()))
    }

    /// The same network computing in `arithmetic` (evaluations compare the two).
    pub fn with_arithmetic(mut self, arithmetic: Arithmetic) -> Embedder {
        self.stem.set_arithmetic(arithmetic);
        for unit in &mut self.units {
            unit.conv1.set_arithmetic(arithmetic);
            unit.conv2.set_arithmetic(arithmetic);
        }
        self
    }

    /// Side of the square chip the network takes.
    pub fn input_size(&self) -> usize {
        self.input_size
    }

    /// The embedding of one chip (one thread; a reused workspace).
    pub fn embed(&self, chip: &FaceChip) -> Embedding {
        let mut ws = self.take_workspace();
        let e = self.forward(chip, &mut ws);
        self.give_back(ws);
        e
    }

    /// The mean of the embeddings of the chip and of its mirror image: a face and its mirror are
    /// the same person, and averaging the two halves the noise of what the network sees on one
    /// side only (held-out LFW EER 2.38% → 2.00%, docs/recognition.md), for twice the work.
    pub fn embed_mirrored(&self, chip: &FaceChip, ws: &mut Workspace) -> Embedding {
        self.embed_mirror_pair(chip, ws).mean()
    }

    /// The embeddings of the chip and of its mirror image, kept apart: their mean is
    /// [`Embedder::embed_mirrored`], their agreement a quality signal ([`MirrorPair::agreement`]).
    pub fn embed_mirror_pair(&self, chip: &FaceChip, ws: &mut Workspace) -> MirrorPair {
        MirrorPair { direct: self.forward(chip, ws), mirrored: self.forward(&chip.mirrored(), ws) }
    }

    /// A workspace from the pool (or a new one), to hand back with [`Embedder::give_back`].
    pub fn take_workspace(&self) -> Workspace {
        self.workspaces.lock().map(|mut p| p.pop()).unwrap_or(None).unwrap_or_default()
    }

    pub fn give_back(&self, ws: Workspace) {
        if let Ok(mut pool) = self.workspaces.lock() {
            pool.push(ws);
        }
    }

    /// Embeddings of many chips, spread over `threads` threads (training and evaluation).
    pub fn embed_batch(&self, chips: &[FaceChip], threads: usize) -> Vec<Embedding> {
        let threads = threads.clamp(1, chips.len().max(1));
        let per = chips.len().div_ceil(threads).max(1);
        let mut out = vec![Embedding([0.0; EMBEDDING_DIMS]); chips.len()];
        std::thread::scope(|scope| {
            for (chunk_in, chunk_out) in chips.chunks(per).zip(out.chunks_mut(per)) {
                scope.spawn(move || {
                    let mut ws = Workspace::default();
                    for (c, o) in chunk_in.iter().zip(chunk_out) {
                        *o = self.forward(c, &mut ws);
                    }
                });
            }
        });
        out
    }

    /// The forward pass with explicit scratch space.
    pub fn forward(&self, chip: &FaceChip, ws: &mut Workspace) -> Embedding {
        assert_eq!(chip.size, self.input_size, "chip side must match the network input");
        let n = self.input_size;
        ws.t.reshape(n, n, 3);
        for (dst, src) in ws.t.data.chunks_exact_mut(3).zip(chip.rgb.chunks_exact(3)) {
            for ch in 0..3 {
                dst[ch] = (src[ch] as f32 - self.input_mean[ch]) / 256.0;
            }
        }
        conv(&self.stem, &ws.t, &mut ws.u, &mut ws.cols, true);
        let (size, stride, padding) = self.stem_pool;
        max_pool(&ws.u, &mut ws.x, size, stride, padding);
        for unit in &self.units {
            conv(&unit.conv1, &ws.x, &mut ws.t, &mut ws.cols, true);
            conv(&unit.conv2, &ws.t, &mut ws.u, &mut ws.cols, false);
            if unit.down {
                avg_pool_2x2(&ws.x, &mut ws.s);
                add_padded_relu(&ws.u, &ws.s, &mut ws.x);
            } else {
                for (u, x) in ws.u.data.iter_mut().zip(&ws.x.data) {
                    *u = (*u + x).max(0.0);
                }
                std::mem::swap(&mut ws.x, &mut ws.u);
            }
        }
        let x = &ws.x;
        let mut pooled = [0.0f32; 512];
        let pooled = &mut pooled[..self.fc_inputs];
        for px in x.data.chunks_exact(x.c) {
            for (p, v) in pooled.iter_mut().zip(px) {
                *p += v;
            }
        }
        let area = (x.h * x.w) as f32;
        let mut out = [0.0f32; EMBEDDING_DIMS];
        for (i, p) in pooled.iter().enumerate() {
            let v = p / area;
            let row = &self.fc[i * EMBEDDING_DIMS..(i + 1) * EMBEDDING_DIMS];
            for (o, w) in out.iter_mut().zip(row) {
                *o += v * w;
            }
        }
        Embedding(out)
    }
}

/// `out = conv(input)` (+ relu): im2col into `cols`, then one matrix product, in floats or (for a
/// layer with `i8` weights) in integers.
pub(super) fn conv(layer: &FoldedConv, input: &Act, out: &mut Act, cols: &mut Cols, relu: bool) {
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

fn max_pool(input: &Act, out: &mut Act, size: usize, stride: usize, padding: usize) {
    let side = |n: usize| (n + 2 * padding - size) / stride + 1;
    let (ho, wo, c) = (side(input.h), side(input.w), input.c);
    out.reshape(ho, wo, c);
    for oy in 0..ho {
        for ox in 0..wo {
            let dst = &mut out.data[(oy * wo + ox) * c..(oy * wo + ox + 1) * c];
            dst.fill(f32::NEG_INFINITY);
            for ky in 0..size {
                for kx in 0..size {
                    let (iy, ix) = ((oy * stride + ky) as isize - padding as isize, (ox * stride + kx) as isize - padding as isize);
                    if iy < 0 || ix < 0 || iy >= input.h as isize || ix >= input.w as isize {
                        continue;
                    }
                    let at = (iy as usize * input.w + ix as usize) * c;
                    for (d, v) in dst.iter_mut().zip(&input.data[at..at + c]) {
                        *d = d.max(*v);
                    }
                }
            }
        }
    }
}

/// The down-sampling shortcut: 2×2 windows, stride 2, no padding.
fn avg_pool_2x2(input: &Act, out: &mut Act) {
    let (ho, wo, c) = ((input.h - 2) / 2 + 1, (input.w - 2) / 2 + 1, input.c);
    out.reshape(ho, wo, c);
    for oy in 0..ho {
        for ox in 0..wo {
            let dst = &mut out.data[(oy * wo + ox) * c..(oy * wo + ox + 1) * c];
            dst.fill(0.0);
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let at = ((oy * 2 + dy) * input.w + ox * 2 + dx) * c;
                for (d, v) in dst.iter_mut().zip(&input.data[at..at + c]) {
                    *d += v;
                }
            }
            for d in dst.iter_mut() {
                *d *= 0.25;
            }
        }
    }
}

/// `relu(a + b)` where the two may differ in size: the result takes the larger of each
/// dimension and a missing value counts as zero (dlib's `add_prev` on a down-sampling unit,
/// where the strided convolution and the pooled shortcut can disagree by a pixel).
fn add_padded_relu(a: &Act, b: &Act, out: &mut Act) {
    let (h, w, c) = (a.h.max(b.h), a.w.max(b.w), a.c.max(b.c));
    out.reshape(h, w, c);
    let at = |t: &Act, y: usize, x: usize, ch: usize| {
        if y < t.h && x < t.w && ch < t.c { t.data[(y * t.w + x) * t.c + ch] } else { 0.0 }
    };
    for y in 0..h {
        for x in 0..w {
            for ch in 0..c {
                out.data[(y * w + x) * c + ch] = (at(a, y, x, ch) + at(b, y, x, ch)).max(0.0);
            }
        }
    }
}
