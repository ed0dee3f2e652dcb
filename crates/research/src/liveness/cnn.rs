//! A small convolutional network for passive liveness, trained in Rust (candle's CPU tensors and
//! their reverse-mode gradients) on the crops the LBP model reads
//! ([`facegate_vision::liveness::features::crops`]: the face and a crop three times as wide, each
//! 64×64 RGB, at the recognizer's eye and mouth centres). Research only: `facegate eval
//! liveness-cnn` compares it with the LBP model under the same subject folds
//! ([`crate::liveness::cnn_eval`]); nothing at run time reads it.
//!
//! Why this shape: the LBP features see micro-texture and colour, learnt by a linear model from
//! nine NUAA subjects; a network learns its own filters, and with the simulated prints and
//! screens of many people ([`crate::liveness::attacks`]) in the attack class it has more than NUAA's
//! printer to learn "print" from. Four 3×3 convolutions (three of stride 2: 64 → 8 pixels), ReLU,
//! the mean over the last map and one linear layer to two classes: about 66 thousand weights, a
//! size nine subjects and a few thousand simulated attacks can train without a pretrained start.

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, Linear, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use facegate_core::face::EyeMouthCentres;
use facegate_vision::liveness::features::{CONTEXT_SIZE, FACE_SIZE, crops};
use image::RgbImage;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::Progress;

/// The crops' side (the face and the wide crop are the same size).
pub const SIDE: usize = FACE_SIZE;
const _: () = assert!(CONTEXT_SIZE == FACE_SIZE, "the network stacks both crops as channels");
/// The face crop's RGB planes, then the wide crop's.
pub const CHANNELS: usize = 6;
const PLANE: usize = SIDE * SIDE;

/// (input channels, output channels, stride) of each 3×3 convolution.
const CONVOLUTIONS: [(usize, usize, usize); 4] = [(CHANNELS, 16, 2), (16, 32, 2), (32, 64, 2), (64, 64, 1)];

/// One face's input: both crops' RGB planes, channel-major, as bytes (a data set's inputs are
/// kept in memory between fits).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Input(pub Vec<u8>);

/// The network's input for the face at `centres` in `photo`.
pub fn input(photo: &RgbImage, centres: &EyeMouthCentres) -> Input {
    let c = crops(photo, centres);
    let mut out = vec![0u8; CHANNELS * PLANE];
    for (k, crop) in [&c.face, &c.context].into_iter().enumerate() {
        for (i, px) in crop.pixels().enumerate() {
            for ch in 0..3 {
                out[(3 * k + ch) * PLANE + i] = px[ch];
            }
        }
    }
    Input(out)
}

/// Training settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrainingConfig {
    pub epochs: usize,
    /// Samples drawn per epoch: half live, half attack, each half split evenly between its groups.
    pub per_epoch: usize,
    pub batch: usize,
    pub learning_rate: f64,
    pub weight_decay: f64,
    /// Seeds the initial weights, the draws and the variations.
    pub seed: u64,
    /// Besides mirror images, vary each training sample's contrast, brightness and position.
    pub jitter: bool,
}

impl Default for TrainingConfig {
    fn default() -> TrainingConfig {
        TrainingConfig { epochs: 10, per_epoch: 4096, batch: 64, learning_rate: 2e-3, weight_decay: 1e-4, seed: 1, jitter: false }
    }
}

/// Faces of one source (NUAA's live frames, its prints, other cameras' live photos, simulated
/// attacks), all of one class. Each group gets an equal share of its class's draws, so that a
/// large source (LFW) does not drown a small one (NUAA's live frames).
pub struct Group<'a> {
    pub inputs: Vec<&'a Input>,
    pub live: bool,
}

/// The trained network.
pub struct LivenessNet {
    convolutions: Vec<Conv2d>,
    classes: Linear,
}

impl LivenessNet {
    fn new(varmap: &VarMap, seed: u64) -> candle_core::Result<LivenessNet> {
        let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
        let convolutions = CONVOLUTIONS
            .iter()
            .enumerate()
            .map(|(k, &(i, o, stride))| {
                candle_nn::conv2d(i, o, 3, Conv2dConfig { padding: 1, stride, ..Default::default() }, vb.pp(format!("conv{k}")))
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let classes = candle_nn::linear(CONVOLUTIONS[3].1, 2, vb.pp("classes"))?;
        seed_weights(varmap, seed)?;
        Ok(LivenessNet { convolutions, classes })
    }

    /// Class logits `[n, 2]` (0: attack, 1: live) of a batch `[n, 6, 64, 64]`.
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        let mut h = x.clone();
        for c in &self.convolutions {
            h = c.forward(&h)?.relu()?;
        }
        self.classes.forward(&h.mean((2, 3))?)
    }

    /// Each input's live-against-attack logit (the live class's minus the attack class's): above
    /// 0, the network finds a live face likelier at even prior odds.
    pub fn logits(&self, inputs: &[&Input]) -> anyhow::Result<Vec<f32>> {
        let mut out = Vec::with_capacity(inputs.len());
        for chunk in inputs.chunks(256) {
            let items: Vec<(&Input, Variation)> = chunk.iter().map(|&i| (i, Variation::NONE)).collect();
            let pairs = self.forward(&batch(&items)?)?.to_vec2::<f32>()?;
            out.extend(pairs.iter().map(|p| p[1] - p[0]));
        }
        Ok(out)
    }
}

/// He-normal weights and zero biases from `seed` (candle's own initialiser draws from an unseeded
/// generator on the CPU), in the order of the variables' names.
fn seed_weights(varmap: &VarMap, seed: u64) -> candle_core::Result<()> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let data = varmap.data().lock().expect("the variable map's lock is never poisoned");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        let dims = var.dims().to_vec();
        let values: Vec<f32> = if dims.len() >= 2 {
            let fan_in: usize = dims[1..].iter().product();
            let normal = Normal::new(0.0, (2.0 / fan_in as f64).sqrt()).expect("a positive deviation");
            (0..var.elem_count()).map(|_| normal.sample(&mut rng) as f32).collect()
        } else {
            vec![0.0; var.elem_count()]
        };
        var.set(&Tensor::from_vec(values, dims, &Device::Cpu)?)?;
    }
    Ok(())
}

/// How a training sample is varied before the network sees it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Variation {
    mirror: bool,
    /// Contrast and brightness on the scaled values (the same for every channel, so that the
    /// colour relations a print shifts are kept).
    gain: f32,
    offset: f32,
    /// Shift in pixels (the edge pixels repeated): the centres' jitter.
    dx: i32,
    dy: i32,
}

impl Variation {
    const NONE: Variation = Variation { mirror: false, gain: 1.0, offset: 0.0, dx: 0, dy: 0 };

    fn draw(jitter: bool, rng: &mut ChaCha8Rng) -> Variation {
        let mirror = rng.random_bool(0.5);
        if !jitter {
            return Variation { mirror, ..Variation::NONE };
        }
        Variation {
            mirror,
            gain: rng.random_range(0.75..1.25),
            offset: rng.random_range(-0.15..0.15),
            dx: rng.random_range(-3..=3),
            dy: rng.random_range(-3..=3),
        }
    }
}

/// A batch tensor of `items` (each input, and how to vary it), scaled to about [−1, 1].
fn batch(items: &[(&Input, Variation)]) -> candle_core::Result<Tensor> {
    let mut values = Vec::with_capacity(items.len() * CHANNELS * PLANE);
    let last = SIDE as i32 - 1;
    for (input, v) in items {
        for plane in input.0.chunks(PLANE) {
            for y in 0..SIDE as i32 {
                let row = &plane[(y + v.dy).clamp(0, last) as usize * SIDE..][..SIDE];
                for x in 0..SIDE as i32 {
                    let from = if v.mirror { last - x } else { x } + v.dx;
                    values.push((f32::from(row[from.clamp(0, last) as usize]) / 127.5 - 1.0) * v.gain + v.offset);
                }
            }
        }
    }
    Tensor::from_vec(values, (items.len(), CHANNELS, SIDE, SIDE), &Device::Cpu)
}

/// Each epoch's draws: `(group, index in it)`, half from the live groups and half from the attack
/// groups, shuffled.
fn draws(groups: &[Group], per_epoch: usize, rng: &mut ChaCha8Rng) -> Vec<(usize, usize)> {
    let mut out = Vec::with_capacity(per_epoch);
    for live in [true, false] {
        let members: Vec<usize> = (0..groups.len()).filter(|&g| groups[g].live == live && !groups[g].inputs.is_empty()).collect();
        for &g in &members {
            for _ in 0..per_epoch / 2 / members.len() {
                out.push((g, rng.random_range(0..groups[g].inputs.len())));
            }
        }
    }
    out.shuffle(rng);
    out
}

/// The network trained on `groups` (cross-entropy, AdamW, mirror images and, with `jitter`,
/// varied contrast, brightness and position at random).
pub fn train(groups: &[Group], config: &TrainingConfig, progress: &dyn Progress) -> anyhow::Result<LivenessNet> {
    for live in [true, false] {
        anyhow::ensure!(
            groups.iter().any(|g| g.live == live && !g.inputs.is_empty()),
            "no {} faces to train on",
            if live { "live" } else { "attack" }
        );
    }
    let varmap = VarMap::new();
    let net = LivenessNet::new(&varmap, config.seed)?;
    let params = ParamsAdamW { lr: config.learning_rate, weight_decay: config.weight_decay, ..Default::default() };
    let mut optimizer = candle_nn::AdamW::new(varmap.all_vars(), params)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed.wrapping_add(1));
    let steps_per_epoch = config.per_epoch.div_ceil(config.batch);
    progress.begin((config.epochs * steps_per_epoch) as u64, "train the liveness CNN");
    for epoch in 0..config.epochs {
        // The last quarter of the epochs at a tenth of the rate: the weights settle.
        if epoch == config.epochs - config.epochs / 4 {
            optimizer.set_learning_rate(config.learning_rate / 10.0);
        }
        for chunk in draws(groups, config.per_epoch, &mut rng).chunks(config.batch) {
            let items: Vec<(&Input, Variation)> =
                chunk.iter().map(|&(g, i)| (groups[g].inputs[i], Variation::draw(config.jitter, &mut rng))).collect();
            let labels: Vec<u32> = chunk.iter().map(|&(g, _)| u32::from(groups[g].live)).collect();
            let labels = Tensor::from_vec(labels, chunk.len(), &Device::Cpu)?;
            let loss = candle_nn::loss::cross_entropy(&net.forward(&batch(&items)?)?, &labels)?;
            optimizer.backward_step(&loss)?;
            progress.step();
        }
    }
    progress.end();
    Ok(net)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Faces that differ only in a texture the network must find: live inputs smooth, attacks
    /// with a fine stripe, as a halftone or a pixel grid would add.
    fn toy(live: bool, seed: u64) -> Input {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let base: u8 = rng.random_range(60..190);
        Input((0..CHANNELS * PLANE).map(|i| if !live && (i % SIDE) % 2 == 0 { base.saturating_add(40) } else { base }).collect())
    }

    #[test]
    fn learns_a_texture_that_separates_the_classes() {
        let live: Vec<Input> = (0..40).map(|s| toy(true, s)).collect();
        let attacks: Vec<Input> = (0..40).map(|s| toy(false, 100 + s)).collect();
        let groups = [Group { inputs: live.iter().collect(), live: true }, Group { inputs: attacks.iter().collect(), live: false }];
        // Eight steps of 16 learn the stripes (logits about +0.4 and -3); candle runs at opt-level 0 in
        // the test profile, where the 32 steps of 32 this took before cost 90 s.
        let config = TrainingConfig { epochs: 1, per_epoch: 128, batch: 16, ..Default::default() };
        let net = train(&groups, &config, &crate::Quiet).unwrap();
        let (fresh_live, fresh_attack) = (toy(true, 999), toy(false, 998));
        let logits = net.logits(&[&fresh_live, &fresh_attack]).unwrap();
        assert!(logits[0] > 0.0 && logits[1] < 0.0, "{logits:?}");
    }

    #[test]
    fn mirrors_each_row_of_each_plane() {
        let mut bytes = vec![0u8; CHANNELS * PLANE];
        bytes[PLANE + SIDE] = 255; // plane 1, row 1, column 0
        let mirrored = Variation { mirror: true, ..Variation::NONE };
        let flat = batch(&[(&Input(bytes.clone()), mirrored)]).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(flat[PLANE + SIDE + SIDE - 1], 1.0);
        assert_eq!(flat.iter().filter(|&&v| v > 0.0).count(), 1);
        let unmirrored = batch(&[(&Input(bytes.clone()), Variation::NONE)]).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(unmirrored[PLANE + SIDE], 1.0);
    }

    #[test]
    fn shifts_repeat_the_edge_and_gain_scales_about_zero() {
        let mut bytes = vec![0u8; CHANNELS * PLANE];
        bytes[0] = 255; // plane 0, row 0, column 0
        let shifted = Variation { dx: -2, dy: -1, gain: 0.5, offset: 0.25, ..Variation::NONE };
        let flat = batch(&[(&Input(bytes), shifted)]).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        // Output (x, y) reads (x − 2, y − 1), clamped: rows 0–1, columns 0–2 read the corner.
        let bright: Vec<usize> = (0..PLANE).filter(|&i| flat[i] > 0.5).collect();
        assert_eq!(bright, vec![0, 1, 2, SIDE, SIDE + 1, SIDE + 2]);
        assert_eq!(flat[0], 0.5 + 0.25);
        assert_eq!(flat[3], -0.5 + 0.25);
    }

    #[test]
    fn draws_half_of_each_class_evenly_between_groups() {
        let (a, b, c) = (vec![Input::default(); 3], vec![Input::default(); 100], vec![Input::default(); 7]);
        let groups = [
            Group { inputs: a.iter().collect(), live: true },
            Group { inputs: b.iter().collect(), live: true },
            Group { inputs: c.iter().collect(), live: false },
        ];
        let d = draws(&groups, 400, &mut ChaCha8Rng::seed_from_u64(3));
        let count = |g: usize| d.iter().filter(|x| x.0 == g).count();
        assert_eq!((count(0), count(1), count(2)), (100, 100, 200));
        assert!(d.iter().all(|&(g, i)| i < groups[g].inputs.len()));
    }
}
