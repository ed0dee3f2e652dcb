//! The two MiniFASNet anti-spoofing networks of minivision-ai/Silent-Face-Anti-Spoofing
//! (Apache-2.0) converted into the project's own weight files ([`MiniFasNetFile`]): each `.pth`
//! is checked against the SHA-256 of the file that was measured, its `state_dict` read
//! ([`super::torch_legacy`]), every batch normalisation folded into the convolution or fully
//! connected layer before it (in `f64`, then stored as `f32`), and the layers laid out in the
//! order of `MiniFASNet.forward`. Every tensor of the checkpoint must be used (but the batch
//! normalisations' `num_batches_tracked`), so a checkpoint of another architecture is refused.

use std::collections::BTreeMap;

use facegate_nn::minifasnet::{self, Bottleneck, ConvLayer, Layer, Linear, MiniFasNetFile, Source, SqueezeExcite};
use facegate_vision::liveness::minifasnet::{V1SE_FILE, V2_FILE};

use super::torch_legacy::{self, Tensor, TorchError};
use facegate_vision::embed::onnx::sha256_hex;

pub const REPOSITORY: &str = "minivision-ai/Silent-Face-Anti-Spoofing";
pub const COMMIT: &str = "b6d5f04ad78778917853b25c778acef6d5626d15";
pub const LICENCE: &str = "Apache-2.0";
/// `BatchNorm1d`/`BatchNorm2d`'s default, which `MiniFASNet.py` keeps.
const BATCH_NORM_EPS: f64 = 1e-5;

/// One network of the repository and the file it is converted into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Original {
    /// The architecture's name in `MiniFASNet.py`.
    pub name: &'static str,
    /// The weight file, under `resources/anti_spoof_models/` in the repository.
    pub file: &'static str,
    pub sha256: &'static str,
    /// The crop the file name states (`utility.parse_model_name`).
    pub crop_scale: f64,
    pub input_size: usize,
    /// The converted file's name under the models folder.
    pub output: &'static str,
}

/// The two networks the repository's predictor runs, both on 80×80 crops.
pub const ORIGINALS: [Original; 2] = [
    Original {
        name: "MiniFASNetV2",
        file: "2.7_80x80_MiniFASNetV2.pth",
        sha256: "a5eb02e1843f19b5386b953cc4c9f011c3f985d0ee2bb9819eea9a142099bec0",
        crop_scale: 2.7,
        input_size: 80,
        output: V2_FILE,
    },
    Original {
        name: "MiniFASNetV1SE",
        file: "4_0_0_80x80_MiniFASNetV1SE.pth",
        sha256: "84ee1d37d96894d5e82de5a57df044ef80a58be2b218b5ed7cdfd875ec2f5990",
        crop_scale: 4.0,
        input_size: 80,
        output: V1SE_FILE,
    },
];

#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    #[error("{file} has SHA-256 {found}, not the expected {expected}")]
    Hash { file: String, expected: String, found: String },
    #[error(transparent)]
    Torch(#[from] TorchError),
    #[error("the checkpoint is not a {name}: {message}")]
    Layout { name: String, message: String },
}

/// The checkpoint's tensors, taken one by one so that what is left over can be reported.
struct StateDict {
    name: &'static str,
    /// `module.` when the network was saved from `DataParallel`.
    prefix: String,
    tensors: BTreeMap<String, Tensor>,
}

/// A batch normalisation as a per-channel scale and shift, in `f64`.
struct Affine {
    scale: Vec<f64>,
    shift: Vec<f64>,
}

impl StateDict {
    fn fail<T>(&self, message: String) -> Result<T, ConvertError> {
        Err(ConvertError::Layout { name: self.name.to_string(), message })
    }

    fn has(&self, name: &str) -> bool {
        self.tensors.contains_key(&format!("{}{name}", self.prefix))
    }

    /// The float tensor `name`, of the given shape (`None` for any length along an axis).
    fn take(&mut self, name: &str, shape: &[Option<usize>]) -> Result<(Vec<usize>, Vec<f32>), ConvertError> {
        let Some(tensor) = self.tensors.remove(&format!("{}{name}", self.prefix)) else { return self.fail(format!("no tensor {name}")) };
        let fits = tensor.shape.len() == shape.len() && tensor.shape.iter().zip(shape).all(|(n, want)| want.is_none_or(|w| w == *n));
        if !fits {
            return self.fail(format!("{name} has shape {:?}", tensor.shape));
        }
        match tensor.f32() {
            Some(values) => Ok((tensor.shape, values)),
            None => self.fail(format!("{name} is a {}, not floats", tensor.storage)),
        }
    }

    fn batch_norm(&mut self, prefix: &str, channels: usize) -> Result<Affine, ConvertError> {
        let mut get = |what: &str| self.take(&format!("{prefix}.{what}"), &[Some(channels)]).map(|(_, v)| v);
        let (gamma, beta, mean, var) = (get("weight")?, get("bias")?, get("running_mean")?, get("running_var")?);
        // A counter of training steps, not read at inference.
        self.tensors.remove(&format!("{}{prefix}.num_batches_tracked", self.prefix));
        let scale: Vec<f64> = gamma.iter().zip(&var).map(|(&g, &v)| g as f64 / (v as f64 + BATCH_NORM_EPS).sqrt()).collect();
        let shift = beta.iter().zip(&mean).zip(&scale).map(|((&b, &m), s)| b as f64 - m as f64 * s).collect();
        Ok(Affine { scale, shift })
    }

    /// `Conv_block` (with PReLU) or `Linear_block` (without) at `prefix`: a convolution without
    /// bias, then `bn` folded in.
    fn conv_block(&mut self, prefix: &str, geometry: (usize, usize), depthwise: bool, prelu: bool) -> Result<ConvLayer, ConvertError> {
        let (stride, padding) = geometry;
        let (shape, weights) = self.take(&format!("{prefix}.conv.weight"), &[None, None, None, None])?;
        let [filters, per_group, size, width] = shape[..] else { unreachable!("four axes checked") };
        if size != width || (depthwise && per_group != 1) {
            return self.fail(format!("{prefix}.conv.weight has shape {shape:?}"));
        }
        let bn = self.batch_norm(&format!("{prefix}.bn"), filters)?;
        let per_filter = per_group * size * size;
        let folded =
            weights.chunks_exact(per_filter).zip(&bn.scale).flat_map(|(w, &s)| w.iter().map(move |&v| (v as f64 * s) as f32)).collect();
        let prelu = match prelu {
            true => Some(self.take(&format!("{prefix}.prelu.weight"), &[Some(filters)])?.1),
            false => None,
        };
        Ok(ConvLayer {
            filters,
            channels: if depthwise { filters } else { per_group },
            size,
            stride,
            padding,
            depthwise,
            weights: folded,
            bias: bn.shift.iter().map(|&b| b as f32).collect(),
            prelu,
        })
    }

    /// A 1×1 convolution (or `Linear`) without bias at `weight`, then the batch normalisation at
    /// `bn` (if any) folded in, as a fully connected layer.
    fn linear(&mut self, weight: &str, one_by_one: bool, bn: Option<&str>) -> Result<Linear, ConvertError> {
        let axes: &[Option<usize>] = if one_by_one { &[None, None, Some(1), Some(1)] } else { &[None, None] };
        let (shape, weights) = self.take(weight, axes)?;
        let (outputs, inputs) = (shape[0], shape[1]);
        let affine = match bn {
            Some(prefix) => self.batch_norm(prefix, outputs)?,
            None => Affine { scale: vec![1.0; outputs], shift: vec![0.0; outputs] },
        };
        let weights =
            weights.chunks_exact(inputs).zip(&affine.scale).flat_map(|(w, &s)| w.iter().map(move |&v| (v as f64 * s) as f32)).collect();
        Ok(Linear { inputs, outputs, weights, bias: affine.shift.iter().map(|&b| b as f32).collect() })
    }

    /// `Depth_Wise` / `Depth_Wise_SE` at `prefix`.
    fn bottleneck(&mut self, prefix: &str, stride: usize, residual: bool) -> Result<Bottleneck, ConvertError> {
        let expand = self.conv_block(&format!("{prefix}.conv"), (1, 0), false, true)?;
        let depthwise = self.conv_block(&format!("{prefix}.conv_dw"), (stride, 1), true, true)?;
        let project = self.conv_block(&format!("{prefix}.project"), (1, 0), false, false)?;
        let se = format!("{prefix}.se_module");
        let squeeze_excite = if self.has(&format!("{se}.fc1.weight")) {
            let reduce = self.linear(&format!("{se}.fc1.weight"), true, Some(&format!("{se}.bn1")))?;
            let expand = self.linear(&format!("{se}.fc2.weight"), true, Some(&format!("{se}.bn2")))?;
            Some(SqueezeExcite { reduce, expand })
        } else {
            None
        };
        Ok(Bottleneck { expand, depthwise, project, squeeze_excite, residual })
    }

    /// `Residual` / `ResidualSE` at `prefix`: its blocks `model.0`, `model.1`, … as many as there are.
    fn residual_stage(&mut self, prefix: &str, layers: &mut Vec<Layer>) -> Result<(), ConvertError> {
        let count = (0..).take_while(|i| self.has(&format!("{prefix}.model.{i}.conv.conv.weight"))).count();
        if count == 0 {
            return self.fail(format!("no blocks under {prefix}"));
        }
        for i in 0..count {
            layers.push(Layer::Bottleneck(Box::new(self.bottleneck(&format!("{prefix}.model.{i}"), 1, true)?)));
        }
        Ok(())
    }
}

/// Converts one checkpoint, refused unless its SHA-256 is `original`'s.
pub fn convert(bytes: &[u8], original: &Original) -> Result<MiniFasNetFile, ConvertError> {
    let found = sha256_hex(bytes);
    if found != original.sha256 {
        return Err(ConvertError::Hash { file: original.file.to_string(), expected: original.sha256.to_string(), found });
    }
    convert_state_dict(torch_legacy::read_state_dict(bytes)?, original)
}

/// The layers of a checkpoint's tensors (the part of [`convert`] after the hash).
fn convert_state_dict(tensors: BTreeMap<String, Tensor>, original: &Original) -> Result<MiniFasNetFile, ConvertError> {
    let prefix = if !tensors.is_empty() && tensors.keys().all(|k| k.starts_with("module.")) { "module." } else { "" };
    let mut sd = StateDict { name: original.name, prefix: prefix.to_string(), tensors };
    let mut layers = vec![
        Layer::Conv(sd.conv_block("conv1", (2, 1), false, true)?),
        Layer::Conv(sd.conv_block("conv2_dw", (1, 1), true, true)?),
        Layer::Bottleneck(Box::new(sd.bottleneck("conv_23", 2, false)?)),
    ];
    sd.residual_stage("conv_3", &mut layers)?;
    layers.push(Layer::Bottleneck(Box::new(sd.bottleneck("conv_34", 2, false)?)));
    sd.residual_stage("conv_4", &mut layers)?;
    layers.push(Layer::Bottleneck(Box::new(sd.bottleneck("conv_45", 2, false)?)));
    sd.residual_stage("conv_5", &mut layers)?;
    layers.push(Layer::Conv(sd.conv_block("conv_6_sep", (1, 0), false, true)?));
    layers.push(Layer::Conv(sd.conv_block("conv_6_dw", (1, 0), true, false)?));
    layers.push(Layer::Linear(sd.linear("linear.weight", false, Some("bn"))?));
    layers.push(Layer::Linear(sd.linear("prob.weight", false, None)?));
    if let Some(left) = sd.tensors.keys().find(|k| !k.ends_with("num_batches_tracked")) {
        return sd.fail(format!("{left} is not part of the network"));
    }
    let file = MiniFasNetFile {
        format: minifasnet::FORMAT,
        name: original.name.to_string(),
        source: Source {
            repository: REPOSITORY.to_string(),
            commit: COMMIT.to_string(),
            file: format!("resources/anti_spoof_models/{}", original.file),
            sha256: original.sha256.to_string(),
            licence: LICENCE.to_string(),
        },
        input_size: original.input_size,
        crop_scale: original.crop_scale,
        layers,
    };
    // The layers must fit together from the input to the three classes.
    facegate_nn::minifasnet::MiniFasNetwork::new(&file)
        .map_err(|e| ConvertError::Layout { name: original.name.to_string(), message: e.to_string() })?;
    Ok(file)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::convert::torch_legacy::tests::Writer;

    /// The tensors of a `Conv_block` (or `Linear_block` without `prelu`) at `prefix`.
    fn conv_block(out: &mut Vec<(String, Vec<usize>, Vec<f32>)>, prefix: &str, shape: [usize; 4], prelu: bool) {
        let n: usize = shape.iter().product();
        out.push((format!("module.{prefix}.conv.weight"), shape.to_vec(), (0..n).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect()));
        batch_norm(out, &format!("{prefix}.bn"), shape[0]);
        if prelu {
            out.push((format!("module.{prefix}.prelu.weight"), vec![shape[0]], vec![0.25; shape[0]]));
        }
    }

    fn batch_norm(out: &mut Vec<(String, Vec<usize>, Vec<f32>)>, prefix: &str, c: usize) {
        for (what, v) in [("weight", 2.0), ("bias", 0.5), ("running_mean", 1.0), ("running_var", 4.0 - 1e-5)] {
            out.push((format!("module.{prefix}.{what}"), vec![c], vec![v; c]));
        }
    }

    fn bottleneck(out: &mut Vec<(String, Vec<usize>, Vec<f32>)>, prefix: &str, c: usize, inner: usize, se: bool) {
        conv_block(out, &format!("{prefix}.conv"), [inner, c, 1, 1], true);
        conv_block(out, &format!("{prefix}.conv_dw"), [inner, 1, 3, 3], true);
        conv_block(out, &format!("{prefix}.project"), [c, inner, 1, 1], false);
        if se {
            out.push((format!("module.{prefix}.se_module.fc1.weight"), vec![c / 2, c, 1, 1], vec![0.1; c * c / 2]));
            batch_norm(out, &format!("{prefix}.se_module.bn1"), c / 2);
            out.push((format!("module.{prefix}.se_module.fc2.weight"), vec![c, c / 2, 1, 1], vec![0.1; c * c / 2]));
            batch_norm(out, &format!("{prefix}.se_module.bn2"), c);
        }
    }

    /// A MiniFASNet's tensors with small channel counts, for a 16×16 input (a 1×1 map after
    /// `conv_6_dw`'s 1×1 kernel).
    fn small_network(se: bool) -> Vec<(String, Vec<usize>, Vec<f32>)> {
        let mut t = Vec::new();
        conv_block(&mut t, "conv1", [4, 3, 3, 3], true);
        conv_block(&mut t, "conv2_dw", [4, 1, 3, 3], true);
        bottleneck(&mut t, "conv_23", 4, 6, false);
        for (stage, down) in [("conv_3", "conv_34"), ("conv_4", "conv_45"), ("conv_5", "")] {
            bottleneck(&mut t, &format!("{stage}.model.0"), 4, 2, se);
            if !down.is_empty() {
                bottleneck(&mut t, down, 4, 6, false);
            }
        }
        conv_block(&mut t, "conv_6_sep", [8, 4, 1, 1], true);
        conv_block(&mut t, "conv_6_dw", [8, 1, 1, 1], false);
        t.push(("module.linear.weight".into(), vec![5, 8], vec![0.2; 40]));
        batch_norm(&mut t, "bn", 5);
        t.push((
            "module.prob.weight".into(),
            vec![3, 5],
            vec![0.1, 0.2, 0.3, 0.4, 0.5, -0.1, -0.2, -0.3, -0.4, -0.5, 1.0, 0.0, 0.0, 0.0, 0.0],
        ));
        t
    }

    fn original() -> Original {
        Original { input_size: 16, ..ORIGINALS[0] }
    }

    fn checkpoint(tensors: &[(String, Vec<usize>, Vec<f32>)]) -> Vec<u8> {
        let borrowed: Vec<(&str, Vec<usize>, Vec<f32>)> = tensors.iter().map(|(n, s, v)| (n.as_str(), s.clone(), v.clone())).collect();
        Writer::checkpoint(&borrowed)
    }

    #[test]
    fn folds_batch_normalisation_and_lays_out_the_blocks() {
        let bytes = checkpoint(&small_network(true));
        let file = convert_state_dict(torch_legacy::read_state_dict(&bytes).unwrap(), &original()).unwrap();
        // conv1, conv2_dw, conv_23, 1 + down + 1 + down + 1 blocks, conv_6_sep, conv_6_dw, linear, prob.
        assert_eq!(file.layers.len(), 12);
        let Layer::Conv(conv1) = &file.layers[0] else { panic!("conv1") };
        // γ / √(var + ε) = 2 / 2 = 1 per filter: the weights as stored (the second is
        // 1 · 0.1 − 0.3); the bias β − mean · 1.
        assert_eq!((conv1.stride, conv1.padding, conv1.channels, conv1.size), (2, 1, 3, 3));
        assert!((conv1.weights[1] + 0.2).abs() < 1e-6);
        assert!(conv1.bias.iter().all(|b| (b + 0.5).abs() < 1e-6));
        let Layer::Bottleneck(block) = &file.layers[3] else { panic!("conv_3.model.0") };
        assert!(block.residual && block.squeeze_excite.is_some() && block.depthwise.depthwise);
        let Layer::Bottleneck(down) = &file.layers[2] else { panic!("conv_23") };
        assert!(!down.residual && down.squeeze_excite.is_none() && down.depthwise.stride == 2);
        let Layer::Linear(prob) = &file.layers[11] else { panic!("prob") };
        assert_eq!((prob.inputs, prob.outputs), (5, 3));
        assert!(prob.bias.iter().all(|&b| b == 0.0));
        let net = facegate_nn::minifasnet::MiniFasNetwork::new(&file).unwrap();
        let p = net.forward(&vec![100.0; 3 * 16 * 16]);
        assert!((p.iter().sum::<f32>() - 1.0).abs() < 1e-5);
    }

    #[test]
    fn refuses_a_wrong_hash_and_a_checkpoint_of_another_architecture() {
        let bytes = checkpoint(&small_network(false));
        match convert(&bytes, &original()) {
            Err(ConvertError::Hash { expected, found, .. }) => {
                assert_eq!(expected, ORIGINALS[0].sha256);
                assert_eq!(found, sha256_hex(&bytes));
            }
            other => panic!("{other:?}"),
        }
        let mut extra = small_network(false);
        extra.push(("module.head.weight".into(), vec![2], vec![0.0, 1.0]));
        let e = convert_state_dict(torch_legacy::read_state_dict(&checkpoint(&extra)).unwrap(), &original()).unwrap_err();
        assert!(e.to_string().contains("module.head.weight is not part of the network"), "{e}");
        let mut missing = small_network(false);
        missing.retain(|(n, _, _)| n != "module.conv_6_sep.prelu.weight");
        let e = convert_state_dict(torch_legacy::read_state_dict(&checkpoint(&missing)).unwrap(), &original()).unwrap_err();
        assert!(e.to_string().contains("no tensor conv_6_sep.prelu.weight"), "{e}");
    }

    #[test]
    fn a_malformed_checkpoint_is_an_error() {
        let mut bytes = checkpoint(&small_network(false));
        bytes.truncate(bytes.len() / 2);
        assert!(matches!(convert_state_dict_bytes(&bytes), Err(ConvertError::Torch(_))));
    }

    fn convert_state_dict_bytes(bytes: &[u8]) -> Result<MiniFasNetFile, ConvertError> {
        convert_state_dict(torch_legacy::read_state_dict(bytes)?, &original())
    }
}
