//! facegate's own kernels for ONNX embedding networks that are a plain chain of layers (each layer
//! reads the one before): convolutions, depthwise convolutions, batch normalisation, PReLU, a
//! flatten and a fully connected layer. SFace (a MobileNet-style network of 27 convolutions) is
//! one; there tract measured 3.4× slower than these kernels (docs/recognition.md).
//!
//! The graph is read from the ONNX file itself when the network is loaded: batch normalisation is
//! folded into the convolution or dense layer before it (or, after a PReLU, into the dense layer
//! after the flatten), the input's scalar Sub/Mul into the input conversion, and the flatten's
//! channel-first order into the dense layer's rows. Activations are channels-last; a convolution is
//! one matrix product ([`crate::conv::conv`], shared with dlib's network), a depthwise convolution a
//! loop over taps whose inner loop runs along the channels. A graph with anything else is not
//! taken ([`ChainNet::from_onnx`] answers `None`) and runs in tract.

use std::collections::HashMap;
use std::sync::Mutex;

use tract_onnx::pb::{GraphProto, NodeProto, TensorProto};

use crate::conv::{Act, Arithmetic, Cols, FoldedConv, conv};
use crate::layers::{Dense, Depthwise, dense, depthwise, prelu};
use crate::weights::Conv;

/// A convolution as the ONNX file gives it (filters × channels/group × k × k), before folding.
struct RawConv {
    filters: usize,
    channels: usize,
    size: usize,
    stride: usize,
    padding: usize,
    depthwise: bool,
    weights: Vec<f32>,
    bias: Vec<f32>,
}

/// A per-channel (or, after the flatten, per-value) scale and shift.
struct Affine {
    scale: Vec<f32>,
    shift: Vec<f32>,
}

enum RawOp {
    Conv(RawConv),
    PRelu(Vec<f32>),
    Affine(Affine),
    Dense(Dense),
}

enum Op {
    Conv(FoldedConv),
    Depthwise(Depthwise),
    PRelu(Vec<f32>),
    Affine(Affine),
    Dense(Dense),
}

/// Scratch buffers for one forward pass.
#[derive(Default)]
struct ChainWorkspace {
    x: Act,
    y: Act,
    cols: Cols,
}

/// The network, folded and laid out for the kernels. `Send + Sync`.
pub struct ChainNet {
    side: usize,
    /// The graph's own input arithmetic: `(value − sub) · mul`.
    sub: f32,
    mul: f32,
    ops: Vec<Op>,
    outputs: usize,
    workspaces: Mutex<Vec<ChainWorkspace>>,
}

fn floats(t: &TensorProto) -> Option<Vec<f32>> {
    const FLOAT: i32 = 1;
    if t.data_type != FLOAT {
        return None;
    }
    if !t.float_data.is_empty() {
        return Some(t.float_data.clone());
    }
    Some(t.raw_data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
}

fn ints(node: &NodeProto, name: &str) -> Vec<i64> {
    node.attribute.iter().find(|a| a.name == name).map_or_else(Vec::new, |a| a.ints.clone())
}

fn int(node: &NodeProto, name: &str, default: i64) -> i64 {
    node.attribute.iter().find(|a| a.name == name).map_or(default, |a| a.i)
}

fn float(node: &NodeProto, name: &str, default: f32) -> f32 {
    node.attribute.iter().find(|a| a.name == name).map_or(default, |a| a.f)
}

/// All equal, and the one value.
fn same(values: &[i64], default: i64) -> Option<usize> {
    match values.first() {
        None => Some(default as usize),
        Some(&v) => values.iter().all(|&x| x == v).then_some(v as usize),
    }
}

/// Reads the graph into layers; `None` at the first thing the kernels do not do.
struct Reader<'a> {
    /// The initializers, decoded only when a layer takes them (a network's weights are read once).
    init: HashMap<&'a str, &'a TensorProto>,
    ops: Vec<RawOp>,
    /// Current activation shape: channels, height, width; `flat` once flattened.
    shape: (usize, usize, usize),
    flat: Option<(usize, usize, usize)>,
    sub: f32,
    mul: f32,
}

impl<'a> Reader<'a> {
    fn tensor(&self, name: &str) -> Option<(&'a [i64], Vec<f32>)> {
        let t = self.init.get(name)?;
        Some((t.dims.as_slice(), floats(t)?))
    }

    fn scalar(&self, node: &NodeProto) -> Option<f32> {
        let (_, v) = self.tensor(node.input.get(1)?)?;
        (v.len() == 1).then(|| v[0])
    }

    fn node(&mut self, node: &NodeProto) -> Option<()> {
        match node.op_type.as_str() {
            "Sub" if self.ops.is_empty() && self.mul == 1.0 => self.sub += self.scalar(node)?,
            "Mul" if self.ops.is_empty() => self.mul *= self.scalar(node)?,
            "Conv" if self.flat.is_none() => self.conv(node)?,
            "BatchNormalization" => self.batch_norm(node)?,
            "PRelu" => {
                let (_, slope) = self.tensor(node.input.get(1)?)?;
                let n = if self.flat.is_some() { self.shape.0 * self.shape.1 * self.shape.2 } else { self.shape.0 };
                let slope = if slope.len() == 1 { vec![slope[0]; n] } else { slope };
                (slope.len() == n && self.flat.is_none()).then_some(())?;
                self.ops.push(RawOp::PRelu(slope));
            }
            "Dropout" | "Identity" => {}
            "Flatten" if self.flat.is_none() && int(node, "axis", 1) == 1 => self.flat = Some(self.shape),
            "Gemm" => self.gemm(node)?,
            _ => return None,
        }
        Some(())
    }

    fn conv(&mut self, node: &NodeProto) -> Option<()> {
        let (dims, w) = self.tensor(node.input.get(1)?)?;
        let [f, cg, kh, kw] = <[i64; 4]>::try_from(dims).ok()?;
        let (f, cg, k) = (f as usize, cg as usize, kh as usize);
        let group = int(node, "group", 1) as usize;
        let stride = same(&ints(node, "strides"), 1)?;
        let padding = same(&ints(node, "pads"), 0)?;
        let channels = self.shape.0;
        let depthwise = group == channels && group == f && cg == 1 && group > 1;
        let plain = group == 1 && cg == channels;
        let ok = kh == kw
            && same(&ints(node, "dilations"), 1)? == 1
            && (depthwise || plain)
            && node.attribute.iter().all(|a| a.name != "auto_pad" || a.s == b"NOTSET");
        ok.then_some(())?;
        let bias = match node.input.get(2).filter(|n| !n.is_empty()) {
            Some(name) => self.tensor(name)?.1,
            None => vec![0.0; f],
        };
        (bias.len() == f && w.len() == f * cg * k * k).then_some(())?;
        let out = |n: usize| (n + 2 * padding).checked_sub(k).map(|v| v / stride + 1);
        self.shape = (f, out(self.shape.1)?, out(self.shape.2)?);
        self.ops.push(RawOp::Conv(RawConv { filters: f, channels, size: k, stride, padding, depthwise, weights: w, bias }));
        Some(())
    }

    fn batch_norm(&mut self, node: &NodeProto) -> Option<()> {
        let get = |i: usize| node.input.get(i).and_then(|n| self.tensor(n)).map(|(_, v)| v);
        let (gamma, beta, mean, var) = (get(1)?, get(2)?, get(3)?, get(4)?);
        let eps = float(node, "epsilon", 1e-5);
        let scale: Vec<f32> = gamma.iter().zip(&var).map(|(g, v)| g / (v + eps).sqrt()).collect();
        let shift: Vec<f32> = beta.iter().zip(&mean).zip(&scale).map(|((b, m), s)| b - m * s).collect();
        let n = scale.len();
        match self.ops.last_mut() {
            Some(RawOp::Conv(c)) if c.filters == n => {
                let per = c.weights.len() / n;
                for (o, (w, b)) in c.weights.chunks_exact_mut(per).zip(c.bias.iter_mut()).enumerate() {
                    w.iter_mut().for_each(|v| *v *= scale[o]);
                    *b = *b * scale[o] + shift[o];
                }
            }
            Some(RawOp::Dense(d)) if d.outputs == n => {
                for row in d.rhs.chunks_exact_mut(n) {
                    row.iter_mut().zip(&scale).for_each(|(v, s)| *v *= s);
                }
                d.bias.iter_mut().zip(&scale).zip(&shift).for_each(|((b, s), t)| *b = *b * s + t);
            }
            _ if self.flat.is_none() && n == self.shape.0 => self.ops.push(RawOp::Affine(Affine { scale, shift })),
            _ => return None,
        }
        Some(())
    }

    fn gemm(&mut self, node: &NodeProto) -> Option<()> {
        let (c, h, w) = self.flat?;
        let inputs = c * h * w;
        let ok = int(node, "transA", 0) == 0 && float(node, "alpha", 1.0) == 1.0 && float(node, "beta", 1.0) == 1.0;
        ok.then_some(())?;
        let (dims, b) = self.tensor(node.input.get(1)?)?;
        let trans_b = int(node, "transB", 0) == 1;
        let outputs = if trans_b { dims.first()? } else { dims.get(1)? };
        let outputs = *outputs as usize;
        (b.len() == inputs * outputs).then_some(())?;
        let bias = match node.input.get(2).filter(|n| !n.is_empty()) {
            Some(name) => self.tensor(name)?.1,
            None => vec![0.0; outputs],
        };
        (bias.len() == outputs).then_some(())?;
        // Rows in channels-last order: ONNX flattens channel-first (index ch·h·w + y·w + x).
        let mut rhs = vec![0.0f32; inputs * outputs];
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let (chw, hwc) = (ch * h * w + y * w + x, (y * w + x) * c + ch);
                    for o in 0..outputs {
                        rhs[hwc * outputs + o] = if trans_b { b[o * inputs + chw] } else { b[chw * outputs + o] };
                    }
                }
            }
        }
        let mut dense = Dense { inputs, outputs, rhs, bias, int8: None };
        // A channel affine just before the flatten (batch normalisation after a PReLU) folds in.
        if let Some(RawOp::Affine(a)) = self.ops.last() {
            for (i, row) in dense.rhs.chunks_exact_mut(outputs).enumerate() {
                let ch = i % c;
                for (o, v) in row.iter_mut().enumerate() {
                    dense.bias[o] += *v * a.shift[ch];
                    *v *= a.scale[ch];
                }
            }
            self.ops.pop();
        }
        self.ops.push(RawOp::Dense(dense));
        Some(())
    }
}

impl ChainNet {
    /// The network of an ONNX file for a `side`-pixel square input, when it is a chain the kernels
    /// run; `None` otherwise (and when the file does not parse: tract then reports why).
    pub fn from_onnx(bytes: &[u8], side: usize) -> Option<ChainNet> {
        use tract_onnx::prelude::Framework;
        let proto = tract_onnx::onnx().proto_model_for_read(&mut &bytes[..]).ok()?;
        let graph: &GraphProto = proto.graph.as_ref()?;
        let init: HashMap<&str, &TensorProto> = graph.initializer.iter().map(|t| (t.name.as_str(), t)).collect();
        let inputs: Vec<&str> = graph.input.iter().map(|i| i.name.as_str()).filter(|n| !init.contains_key(n)).collect();
        let [input] = inputs.as_slice() else { return None };
        let mut reader = Reader { init, ops: Vec::new(), shape: (3, side, side), flat: None, sub: 0.0, mul: 1.0 };
        let mut current = input.to_string();
        for node in &graph.node {
            (node.input.first() == Some(&current)).then_some(())?;
            reader.node(node)?;
            current = node.output.first()?.clone();
        }
        (graph.output.len() == 1 && graph.output[0].name == current).then_some(())?;
        let outputs = match reader.ops.last()? {
            RawOp::Dense(d) => d.outputs,
            _ => return None,
        };
        let (raw, sub, mul) = (reader.ops, reader.sub, reader.mul);
        // The parsed file is let go before the kernels' copies are made: loading peaks lower.
        drop(proto);
        let ops = raw.into_iter().map(Op::from).collect();
        Some(ChainNet { side, sub, mul, ops, outputs, workspaces: Mutex::default() }.with_arithmetic(Arithmetic::detect()))
    }

    /// The same network computing in `arithmetic` (evaluations compare the two). Layers whose
    /// float weights were released ([`ChainNet::release_float_weights`]) stay in integers.
    pub fn with_arithmetic(mut self, arithmetic: Arithmetic) -> ChainNet {
        for op in &mut self.ops {
            match op {
                Op::Conv(conv) => conv.set_arithmetic(arithmetic),
                Op::Dense(d) => d.set_arithmetic(arithmetic),
                _ => {}
            }
        }
        self
    }

    /// Lets go of the float weights of the layers that compute in integers (not read again).
    pub fn release_float_weights(&mut self) {
        for op in &mut self.ops {
            match op {
                Op::Conv(conv) => conv.release_floats(),
                Op::Dense(d) => d.release_floats(),
                _ => {}
            }
        }
    }

    pub fn outputs(&self) -> usize {
        self.outputs
    }

    /// The raw output for an input given as three planes (channel-first, the network's channel
    /// order), already normalised as the manifest says.
    pub fn forward(&self, planes: &[f32]) -> Vec<f32> {
        let mut ws = self.workspaces.lock().ok().and_then(|mut v| v.pop()).unwrap_or_default();
        let side = self.side;
        ws.x.reshape(side, side, 3);
        let plane = side * side;
        for (i, px) in ws.x.data.chunks_exact_mut(3).enumerate() {
            for (c, v) in px.iter_mut().enumerate() {
                *v = (planes[c * plane + i] - self.sub) * self.mul;
            }
        }
        let mut out = Vec::new();
        for op in &self.ops {
            let ChainWorkspace { x, y, cols } = &mut ws;
            match op {
                Op::Conv(layer) => {
                    conv(layer, x, y, cols, false);
                    std::mem::swap(x, y);
                }
                Op::Depthwise(layer) => {
                    depthwise(layer, x, y);
                    std::mem::swap(x, y);
                }
                Op::PRelu(slope) => prelu(&mut x.data, slope),
                Op::Affine(a) => {
                    for px in x.data.chunks_exact_mut(a.scale.len()) {
                        px.iter_mut().zip(&a.scale).zip(&a.shift).for_each(|((v, s), t)| *v = *v * s + t);
                    }
                }
                Op::Dense(d) => dense(d, &x.data[..d.inputs], cols, &mut out),
            }
        }
        if let Ok(mut pool) = self.workspaces.lock() {
            pool.push(ws);
        }
        out
    }
}

impl Op {
    fn from(raw: RawOp) -> Op {
        match raw {
            RawOp::Conv(c) if c.depthwise => Op::Depthwise(Depthwise::new(c.channels, c.size, c.stride, c.padding, &c.weights, c.bias)),
            RawOp::Conv(c) => {
                let raw = Conv {
                    filters: c.filters,
                    channels: c.channels,
                    size: c.size,
                    stride: c.stride,
                    padding: c.padding,
                    weights: c.weights,
                    bias: c.bias,
                };
                Op::Conv(FoldedConv::prefolded(&raw))
            }
            RawOp::PRelu(s) => Op::PRelu(s),
            RawOp::Affine(a) => Op::Affine(a),
            RawOp::Dense(d) => Op::Dense(d),
        }
    }
}
