//! MiniFASNet, the passive face anti-spoofing networks of Minivision's Silent-Face-Anti-Spoofing
//! (Apache-2.0): an 80×80 crop around the face in, the softmax of three classes out (class 1 is a
//! live face). Two of its networks are converted (`facegate convert minifasnet`): V2 and V1SE,
//! which adds squeeze-and-excitation to the last block of each residual stage.
//!
//! The layers, in the order of `MiniFASNet.forward`: a 3×3 stride-2 convolution and a 3×3
//! depthwise one, each with PReLU; then bottleneck blocks (a 1×1 expansion with PReLU, a 3×3
//! depthwise convolution with PReLU, a 1×1 projection; the residual ones add their input back,
//! after the squeeze-and-excitation where there is one); a 1×1 convolution with PReLU, a depthwise
//! convolution over the whole 5×5 map, then two fully connected layers (512 → 128 → 3). Every
//! batch normalisation is folded into the layer before it by the converter, so the file
//! ([`MiniFasNetFile`], postcard) holds only weights, biases and PReLU slopes, in PyTorch's own
//! layouts.
//!
//! The kernels are the crate's: a convolution is one [`conv`] (im2col and one product; the 1×1
//! ones need no copy), the depthwise convolutions, PReLU and the fully connected layers those the
//! ONNX chain ([`crate::chain`]) runs on. Everything computes in floats: the networks are small
//! (about 41 M multiply-adds), and the tests hold them to PyTorch's outputs.

use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use crate::conv::{Act, Cols, FoldedConv, conv};
use crate::layers::{Dense, Depthwise, dense, depthwise, prelu};
use crate::weights::Conv;

/// The layout of [`MiniFasNetFile`] this build writes and reads.
pub const FORMAT: u32 = 1;

/// The networks' classes: 0 and 2 are the two kinds of attack their training data had, 1 is a
/// live face.
pub const CLASSES: usize = 3;
pub const LIVE_CLASS: usize = 1;

/// Where a converted network came from: enough to fetch the same file again and check it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Source {
    /// The public repository, `owner/name`.
    pub repository: String,
    pub commit: String,
    /// The weight file's path in the repository.
    pub file: String,
    /// SHA-256 of that file, lower-case hex.
    pub sha256: String,
    pub licence: String,
}

/// A convolution with its batch normalisation folded in: `weights[o][c][ky][kx]` as PyTorch
/// stores them (`c` runs over one channel for a depthwise convolution), one bias per filter,
/// then PReLU with one slope per filter when there is one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConvLayer {
    pub filters: usize,
    pub channels: usize,
    /// Square kernels only.
    pub size: usize,
    pub stride: usize,
    pub padding: usize,
    /// One filter per channel (`groups == channels == filters`).
    pub depthwise: bool,
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
    pub prelu: Option<Vec<f32>>,
}

/// A fully connected layer as PyTorch's `Linear` stores it: `weights[output][input]`, with the
/// batch normalisation after it (if any) folded into weights and bias.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Linear {
    pub inputs: usize,
    pub outputs: usize,
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Squeeze-and-excitation: each channel's mean over the map → a 1×1 convolution (`reduce`) and
/// ReLU → a 1×1 convolution (`expand`) and a sigmoid → each channel scaled by its gate. Both
/// convolutions work on one pixel, so they are stored as [`Linear`] layers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SqueezeExcite {
    pub reduce: Linear,
    pub expand: Linear,
}

/// `Depth_Wise` (and `Depth_Wise_SE`) of `MiniFASNet.py`: expansion, depthwise, projection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bottleneck {
    pub expand: ConvLayer,
    pub depthwise: ConvLayer,
    /// No PReLU (`Linear_block`).
    pub project: ConvLayer,
    pub squeeze_excite: Option<SqueezeExcite>,
    /// The block's input is added to its output.
    pub residual: bool,
}

/// One step of the forward pass.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Layer {
    Conv(ConvLayer),
    Bottleneck(Box<Bottleneck>),
    /// A fully connected layer; the map must be down to one pixel by then, so the flatten is a
    /// no-op in both channel orders.
    Linear(Linear),
}

/// The project's weight file of one network (`models/minifasnet-v2.bin`, `minifasnet-v1se.bin`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MiniFasNetFile {
    pub format: u32,
    /// The architecture's name in the original code (`MiniFASNetV2`, `MiniFASNetV1SE`).
    pub name: String,
    pub source: Source,
    /// Side of the square input, in pixels.
    pub input_size: usize,
    /// The crop the network was trained on: the face box scaled by this about its centre
    /// (`generate_patches.py`); `f64` as Python computes the crop.
    pub crop_scale: f64,
    pub layers: Vec<Layer>,
}

impl MiniFasNetFile {
    /// Number of learnt values (weights, biases, slopes).
    pub fn parameter_count(&self) -> usize {
        let conv = |c: &ConvLayer| c.weights.len() + c.bias.len() + c.prelu.as_ref().map_or(0, Vec::len);
        let linear = |l: &Linear| l.weights.len() + l.bias.len();
        self.layers
            .iter()
            .map(|layer| match layer {
                Layer::Conv(c) => conv(c),
                Layer::Bottleneck(b) => {
                    conv(&b.expand)
                        + conv(&b.depthwise)
                        + conv(&b.project)
                        + b.squeeze_excite.as_ref().map_or(0, |se| linear(&se.reduce) + linear(&se.expand))
                }
                Layer::Linear(l) => linear(l),
            })
            .sum()
    }
}

/// Why a weight file cannot be run.
#[derive(Debug, thiserror::Error)]
#[error("the MiniFASNet weights do not fit together: {0}")]
pub struct LayoutError(pub String);

/// A convolution laid out for its kernel.
enum Kernel {
    Full(FoldedConv),
    Depthwise(Depthwise),
}

/// A convolution and the PReLU after it.
struct ConvStep {
    kernel: Kernel,
    prelu: Option<Vec<f32>>,
}

struct SqueezeExciteStep {
    reduce: Dense,
    expand: Dense,
}

struct BottleneckStep {
    expand: ConvStep,
    depthwise: ConvStep,
    project: ConvStep,
    squeeze_excite: Option<SqueezeExciteStep>,
    residual: bool,
}

enum Step {
    Conv(ConvStep),
    Bottleneck(Box<BottleneckStep>),
    Linear(Dense),
}

/// Scratch buffers for one forward pass, reused across calls.
#[derive(Default)]
struct Workspace {
    x: Act,
    a: Act,
    b: Act,
    cols: Cols,
    /// Squeeze-and-excitation's channel means, hidden values and gates.
    pooled: Vec<f32>,
    hidden: Vec<f32>,
    gates: Vec<f32>,
    /// The fully connected layers' input and output.
    flat: Vec<f32>,
    dense_out: Vec<f32>,
}

/// One MiniFASNet, laid out for the kernels. `Send + Sync`; concurrent calls each take a
/// workspace from the pool (a new one only when all are in use).
pub struct MiniFasNetwork {
    name: String,
    input_size: usize,
    crop_scale: f64,
    steps: Vec<Step>,
    workspaces: Mutex<Vec<Workspace>>,
}

impl std::fmt::Debug for MiniFasNetwork {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MiniFasNetwork")
            .field("name", &self.name)
            .field("input_size", &self.input_size)
            .field("crop_scale", &self.crop_scale)
            .field("steps", &self.steps.len())
            .finish()
    }
}

/// Activation shape while the layers are checked: channels, height, width.
type Shape = (usize, usize, usize);

fn check(ok: bool, what: impl FnOnce() -> String) -> Result<(), LayoutError> {
    if ok { Ok(()) } else { Err(LayoutError(what())) }
}

fn conv_step(layer: &ConvLayer, shape: Shape, what: &str) -> Result<(ConvStep, Shape), LayoutError> {
    let (c, h, w) = shape;
    let ConvLayer { filters: f, channels, size: k, stride, padding, depthwise, .. } = *layer;
    check(channels == c, || format!("{what}: {channels} input channels after {c}"))?;
    check(!depthwise || f == c, || format!("{what}: a depthwise convolution of {f} filters over {c} channels"))?;
    check(k > 0 && stride > 0 && h + 2 * padding >= k && w + 2 * padding >= k, || format!("{what}: a {k}×{k} kernel over {h}×{w}"))?;
    let per_filter = if depthwise { k * k } else { c * k * k };
    check(layer.weights.len() == f * per_filter && layer.bias.len() == f, || format!("{what}: weights or bias of the wrong length"))?;
    check(layer.prelu.as_ref().is_none_or(|s| s.len() == f), || format!("{what}: {f} filters but another number of PReLU slopes"))?;
    let kernel = if depthwise {
        Kernel::Depthwise(Depthwise::new(c, k, stride, padding, &layer.weights, layer.bias.clone()))
    } else {
        let raw = Conv { filters: f, channels: c, size: k, stride, padding, weights: layer.weights.clone(), bias: layer.bias.clone() };
        Kernel::Full(FoldedConv::prefolded(&raw))
    };
    let side = |n: usize| (n + 2 * padding - k) / stride + 1;
    Ok((ConvStep { kernel, prelu: layer.prelu.clone() }, (f, side(h), side(w))))
}

fn dense_step(layer: &Linear, inputs: usize, what: &str) -> Result<Dense, LayoutError> {
    check(layer.inputs == inputs, || format!("{what}: {} inputs for {inputs} values", layer.inputs))?;
    check(layer.weights.len() == layer.inputs * layer.outputs && layer.bias.len() == layer.outputs, || {
        format!("{what}: weights or bias of the wrong length")
    })?;
    Ok(Dense::from_rows(layer.inputs, layer.outputs, &layer.weights, layer.bias.clone()))
}

fn bottleneck_step(block: &Bottleneck, shape: Shape, what: &str) -> Result<(BottleneckStep, Shape), LayoutError> {
    let (expand, expanded) = conv_step(&block.expand, shape, &format!("{what} expansion"))?;
    let (depthwise, filtered) = conv_step(&block.depthwise, expanded, &format!("{what} depthwise"))?;
    check(block.depthwise.depthwise, || format!("{what}: the middle convolution is not depthwise"))?;
    let (project, out) = conv_step(&block.project, filtered, &format!("{what} projection"))?;
    check(!block.residual || out == shape, || format!("{what}: a residual block from {shape:?} to {out:?}"))?;
    let squeeze_excite = match &block.squeeze_excite {
        Some(se) => {
            let reduce = dense_step(&se.reduce, out.0, &format!("{what} squeeze"))?;
            let expand = dense_step(&se.expand, reduce.outputs, &format!("{what} excitation"))?;
            check(expand.outputs == out.0, || format!("{what}: {} gates for {} channels", expand.outputs, out.0))?;
            Some(SqueezeExciteStep { reduce, expand })
        }
        None => None,
    };
    Ok((BottleneckStep { expand, depthwise, project, squeeze_excite, residual: block.residual }, out))
}

impl MiniFasNetwork {
    /// The network of a weight file, its layers checked to fit together from a 3-channel input
    /// of the file's side down to the [`CLASSES`] outputs.
    pub fn new(file: &MiniFasNetFile) -> Result<MiniFasNetwork, LayoutError> {
        check(file.input_size > 0, || "an input of no pixels".into())?;
        let mut shape: Shape = (3, file.input_size, file.input_size);
        let mut flat: Option<usize> = None;
        let mut steps = Vec::with_capacity(file.layers.len());
        for (i, layer) in file.layers.iter().enumerate() {
            let what = format!("layer {i}");
            let spatial = flat.is_none();
            match layer {
                Layer::Conv(c) if spatial => {
                    let (step, out) = conv_step(c, shape, &what)?;
                    steps.push(Step::Conv(step));
                    shape = out;
                }
                Layer::Bottleneck(b) if spatial => {
                    let (step, out) = bottleneck_step(b, shape, &what)?;
                    steps.push(Step::Bottleneck(Box::new(step)));
                    shape = out;
                }
                Layer::Linear(l) => {
                    let inputs = match flat {
                        Some(n) => n,
                        None => {
                            check(shape.1 == 1 && shape.2 == 1, || {
                                format!("{what}: a fully connected layer on a {}×{} map", shape.1, shape.2)
                            })?;
                            shape.0
                        }
                    };
                    let dense = dense_step(l, inputs, &what)?;
                    flat = Some(dense.outputs);
                    steps.push(Step::Linear(dense));
                }
                _ => return Err(LayoutError(format!("{what}: a convolution after the fully connected layers"))),
            }
        }
        check(flat == Some(CLASSES), || format!("the network ends in {flat:?} outputs, not {CLASSES} classes"))?;
        Ok(MiniFasNetwork {
            name: file.name.clone(),
            input_size: file.input_size,
            crop_scale: file.crop_scale,
            steps,
            workspaces: Mutex::default(),
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn input_size(&self) -> usize {
        self.input_size
    }

    /// The face box's scale about its centre that gives the network's crop.
    pub fn crop_scale(&self) -> f64 {
        self.crop_scale
    }

    /// The softmax of the three classes for an input given as the original code gives it: three
    /// channel-first planes of `input_size²` values in OpenCV's channel order (blue, green, red),
    /// 0–255 as the pixels are (its `ToTensor` does not divide by 255).
    ///
    /// # Panics
    /// When `planes` is not `3 · input_size²` values long.
    pub fn forward(&self, planes: &[f32]) -> [f32; CLASSES] {
        let side = self.input_size;
        let plane = side * side;
        assert_eq!(planes.len(), 3 * plane, "three {side}×{side} planes");
        let mut ws = self.workspaces.lock().ok().and_then(|mut pool| pool.pop()).unwrap_or_default();
        ws.x.reshape(side, side, 3);
        for (i, px) in ws.x.data.chunks_exact_mut(3).enumerate() {
            for (c, v) in px.iter_mut().enumerate() {
                *v = planes[c * plane + i];
            }
        }
        let mut flattened = false;
        for step in &self.steps {
            match step {
                Step::Conv(layer) => {
                    run_conv(layer, &ws.x, &mut ws.a, &mut ws.cols);
                    std::mem::swap(&mut ws.x, &mut ws.a);
                }
                Step::Bottleneck(block) => run_bottleneck(block, &mut ws),
                Step::Linear(d) => {
                    // The map is one pixel (checked at load): its channels are the flat values.
                    if !flattened {
                        ws.flat.clear();
                        ws.flat.extend_from_slice(&ws.x.data);
                        flattened = true;
                    }
                    dense(d, &ws.flat, &mut ws.cols, &mut ws.dense_out);
                    std::mem::swap(&mut ws.flat, &mut ws.dense_out);
                }
            }
        }
        let mut logits = [0.0f32; CLASSES];
        logits.copy_from_slice(&ws.flat[..CLASSES]);
        if let Ok(mut pool) = self.workspaces.lock() {
            pool.push(ws);
        }
        softmax(logits)
    }
}

fn run_conv(layer: &ConvStep, input: &Act, out: &mut Act, cols: &mut Cols) {
    match &layer.kernel {
        Kernel::Full(folded) => conv(folded, input, out, cols, false),
        Kernel::Depthwise(dw) => depthwise(dw, input, out),
    }
    if let Some(slope) = &layer.prelu {
        prelu(&mut out.data, slope);
    }
}

/// `x ← block(x)`: expansion into `a`, depthwise into `b`, projection into `a`, then the
/// squeeze-and-excitation and the residual sum in place, and `a` becomes `x`.
fn run_bottleneck(block: &BottleneckStep, ws: &mut Workspace) {
    run_conv(&block.expand, &ws.x, &mut ws.a, &mut ws.cols);
    run_conv(&block.depthwise, &ws.a, &mut ws.b, &mut ws.cols);
    run_conv(&block.project, &ws.b, &mut ws.a, &mut ws.cols);
    if let Some(se) = &block.squeeze_excite {
        squeeze_excite(se, ws);
    }
    if block.residual {
        for (v, s) in ws.a.data.iter_mut().zip(&ws.x.data) {
            *v += s;
        }
    }
    std::mem::swap(&mut ws.x, &mut ws.a);
}

/// Scales each channel of `ws.a` by its gate: σ(expand(relu(reduce(mean over the map)))).
fn squeeze_excite(se: &SqueezeExciteStep, ws: &mut Workspace) {
    let c = ws.a.c;
    let pixels = (ws.a.h * ws.a.w) as f32;
    ws.pooled.clear();
    ws.pooled.resize(c, 0.0);
    for px in ws.a.data.chunks_exact(c) {
        for (sum, v) in ws.pooled.iter_mut().zip(px) {
            *sum += v;
        }
    }
    ws.pooled.iter_mut().for_each(|v| *v /= pixels);
    dense(&se.reduce, &ws.pooled, &mut ws.cols, &mut ws.hidden);
    ws.hidden.iter_mut().for_each(|v| *v = v.max(0.0));
    dense(&se.expand, &ws.hidden, &mut ws.cols, &mut ws.gates);
    ws.gates.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));
    for px in ws.a.data.chunks_exact_mut(c) {
        for (v, g) in px.iter_mut().zip(&ws.gates) {
            *v *= g;
        }
    }
}

/// Probabilities from logits (the largest subtracted first, so that `exp` cannot overflow).
pub fn softmax(logits: [f32; CLASSES]) -> [f32; CLASSES] {
    let top = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let exp = logits.map(|l| (l - top).exp());
    let sum: f32 = exp.iter().sum();
    exp.map(|e| e / sum)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn source() -> Source {
        Source { repository: "r".into(), commit: "c".into(), file: "f".into(), sha256: "0".into(), licence: "l".into() }
    }

    fn conv_layer(filters: usize, channels: usize, size: usize, stride: usize, depthwise: bool, prelu: bool) -> ConvLayer {
        let per = if depthwise { size * size } else { channels * size * size };
        ConvLayer {
            filters,
            channels,
            size,
            stride,
            padding: size / 2,
            depthwise,
            weights: (0..filters * per).map(|i| ((i * 7 % 11) as f32 - 5.0) / 20.0).collect(),
            bias: (0..filters).map(|i| i as f32 * 0.01).collect(),
            prelu: prelu.then(|| vec![0.25; filters]),
        }
    }

    fn linear(inputs: usize, outputs: usize) -> Linear {
        Linear {
            inputs,
            outputs,
            weights: (0..inputs * outputs).map(|i| ((i * 5 % 13) as f32 - 6.0) / 30.0).collect(),
            bias: vec![0.1; outputs],
        }
    }

    /// A network of every kind of layer on a 4×4 input: stem, a residual block with
    /// squeeze-and-excitation, a whole-map depthwise convolution, two fully connected layers.
    fn small_file() -> MiniFasNetFile {
        let block = Bottleneck {
            expand: conv_layer(6, 4, 1, 1, false, true),
            depthwise: conv_layer(6, 6, 3, 1, true, true),
            project: conv_layer(4, 6, 1, 1, false, false),
            squeeze_excite: Some(SqueezeExcite { reduce: linear(4, 2), expand: linear(2, 4) }),
            residual: true,
        };
        let mut whole_map = conv_layer(4, 4, 2, 1, true, false);
        whole_map.padding = 0;
        MiniFasNetFile {
            format: FORMAT,
            name: "test".into(),
            source: source(),
            input_size: 4,
            crop_scale: 2.7,
            layers: vec![
                Layer::Conv(conv_layer(4, 3, 3, 2, false, true)),
                Layer::Bottleneck(Box::new(block)),
                Layer::Conv(whole_map),
                Layer::Linear(linear(4, 5)),
                Layer::Linear(linear(5, 3)),
            ],
        }
    }

    /// The same network computed directly on channel-first arrays, as PyTorch would.
    fn reference(file: &MiniFasNetFile, planes: &[f32]) -> [f32; CLASSES] {
        fn conv(l: &ConvLayer, x: &[f32], (c, h, w): Shape) -> (Vec<f32>, Shape) {
            let (k, s, p) = (l.size, l.stride, l.padding);
            let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
            let mut out = vec![0.0; l.filters * ho * wo];
            for o in 0..l.filters {
                let inputs: Vec<usize> = if l.depthwise { vec![o] } else { (0..c).collect() };
                for oy in 0..ho {
                    for ox in 0..wo {
                        let mut acc = l.bias[o];
                        for (j, &ch) in inputs.iter().enumerate() {
                            for ky in 0..k {
                                for kx in 0..k {
                                    let (iy, ix) = ((oy * s + ky) as isize - p as isize, (ox * s + kx) as isize - p as isize);
                                    if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w {
                                        let wi = ((o * inputs.len() + j) * k + ky) * k + kx;
                                        acc += x[(ch * h + iy as usize) * w + ix as usize] * l.weights[wi];
                                    }
                                }
                            }
                        }
                        let v = match &l.prelu {
                            Some(slope) if acc < 0.0 => acc * slope[o],
                            _ => acc,
                        };
                        out[(o * ho + oy) * wo + ox] = v;
                    }
                }
            }
            (out, (l.filters, ho, wo))
        }
        fn fc(l: &Linear, x: &[f32]) -> Vec<f32> {
            (0..l.outputs).map(|o| l.bias[o] + (0..l.inputs).map(|i| l.weights[o * l.inputs + i] * x[i]).sum::<f32>()).collect()
        }
        let mut x = planes.to_vec();
        let mut shape = (3, file.input_size, file.input_size);
        for layer in &file.layers {
            match layer {
                Layer::Conv(l) => (x, shape) = conv(l, &x, shape),
                Layer::Bottleneck(b) => {
                    let (e, s1) = conv(&b.expand, &x, shape);
                    let (d, s2) = conv(&b.depthwise, &e, s1);
                    let (mut p, s3) = conv(&b.project, &d, s2);
                    if let Some(se) = &b.squeeze_excite {
                        let hw = s3.1 * s3.2;
                        let mean: Vec<f32> = (0..s3.0).map(|c| p[c * hw..(c + 1) * hw].iter().sum::<f32>() / hw as f32).collect();
                        let hidden: Vec<f32> = fc(&se.reduce, &mean).into_iter().map(|v| v.max(0.0)).collect();
                        let gates: Vec<f32> = fc(&se.expand, &hidden).into_iter().map(|v| 1.0 / (1.0 + (-v).exp())).collect();
                        for c in 0..s3.0 {
                            p[c * hw..(c + 1) * hw].iter_mut().for_each(|v| *v *= gates[c]);
                        }
                    }
                    if b.residual {
                        p.iter_mut().zip(&x).for_each(|(v, s)| *v += s);
                    }
                    (x, shape) = (p, s3);
                }
                Layer::Linear(l) => x = fc(l, &x),
            }
        }
        softmax([x[0], x[1], x[2]])
    }

    #[test]
    fn the_forward_pass_matches_a_direct_computation_of_every_layer_kind() {
        let file = small_file();
        let net = MiniFasNetwork::new(&file).unwrap();
        let planes: Vec<f32> = (0..48).map(|i| ((i * 29 % 31) as f32) * 8.0).collect();
        let expected = reference(&file, &planes);
        // Twice: the second call runs on the pooled workspace.
        for _ in 0..2 {
            let got = net.forward(&planes);
            for (a, b) in got.iter().zip(&expected) {
                assert!((a - b).abs() < 1e-5, "{got:?} against {expected:?}");
            }
        }
        assert!((expected.iter().sum::<f32>() - 1.0).abs() < 1e-5);
    }

    #[test]
    fn layers_that_do_not_fit_together_are_refused() {
        let mut wrong_channels = small_file();
        if let Layer::Conv(c) = &mut wrong_channels.layers[0] {
            c.channels = 1;
        }
        assert!(MiniFasNetwork::new(&wrong_channels).unwrap_err().0.contains("input channels"));
        let mut not_one_pixel = small_file();
        not_one_pixel.layers.remove(2);
        assert!(MiniFasNetwork::new(&not_one_pixel).unwrap_err().0.contains("fully connected layer on a 2×2 map"));
        let mut two_classes = small_file();
        two_classes.layers[4] = Layer::Linear(linear(5, 2));
        assert!(MiniFasNetwork::new(&two_classes).unwrap_err().0.contains("not 3 classes"));
        let mut short_bias = small_file();
        if let Layer::Bottleneck(b) = &mut short_bias.layers[1] {
            b.project.bias.pop();
        }
        assert!(MiniFasNetwork::new(&short_bias).unwrap_err().0.contains("wrong length"));
    }

    #[test]
    fn softmax_of_large_logits_stays_finite() {
        let p = softmax([1000.0, 1001.0, 0.0]);
        assert!(p.iter().all(|v| v.is_finite()));
        assert!((p[1] - 1.0 / (1.0 + (-1.0f32).exp())).abs() < 1e-6);
    }
}
