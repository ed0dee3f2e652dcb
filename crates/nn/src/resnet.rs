//! dlib's face-recognition ResNet (v1: 29 convolutions, 128 outputs) on one chip: the stem, the
//! residual units and the final pool and fully connected layer, each convolution one
//! [`crate::conv::conv`] with its batch normalisation folded in when the network is built. Buffers
//! live in a [`Workspace`] that is reused across calls, so a warm call allocates nothing.

use std::sync::Mutex;

use crate::chip::FaceChip;
use crate::conv::{Act, Arithmetic, Cols, FoldedConv, conv};
use crate::weights::{Layer, NetworkFile};

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

/// A residual unit: `relu(conv2(relu(conv1(x))) + shortcut(x))`; the down-sampling kind has a
/// stride-2 `conv1` and a 2×2 average pool as its shortcut.
struct Residual {
    conv1: FoldedConv,
    conv2: FoldedConv,
    down: bool,
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
        FoldedConv::new(conv, gamma, beta).map_err(NetworkError::Layout)
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

    /// Lets go of the float weights of the layers that compute in integers (they are not read
    /// again): what a service that never changes the arithmetic keeps (about 19 MB less for
    /// dlib's network). After it, [`Embedder::with_arithmetic`] leaves those layers in integers.
    pub fn release_float_weights(&mut self) {
        self.stem.release_floats();
        for unit in &mut self.units {
            unit.conv1.release_floats();
            unit.conv2.release_floats();
        }
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
