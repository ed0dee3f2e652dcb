//! MiniFASNet (the pretrained passive networks, [`facegate_vision::liveness::minifasnet`]) as a
//! peer of the LBP model under the same measures: the nested subject-wise protocol on NUAA (the
//! networks never trained on NUAA, so only the threshold is chosen without the held-out subject),
//! and the IMM, ORL and LFW test persons' live photos and their simulated prints and screens
//! ([`crate::liveness::attacks`], the same seeds as [`LivenessData`]'s).

use std::path::{Path, PathBuf};

use facegate_vision::liveness::minifasnet::{MiniFasNet, MiniFasScores};
use serde::Serialize;

use crate::Progress;
use crate::cache::map_samples;
use crate::dataset::Split;
use crate::liveness::attacks::{AttackKind, simulate};
use crate::liveness::eval::{CameraThreshold, camera_threshold, unseen_camera_fits};
use crate::liveness::measures::eer_threshold;
use crate::liveness::subjects::{FitAndScore, Fold, folds, recipe_scores};
use crate::liveness::train::{LivenessData, Recipe, columns, out_of_fold_logits};
use crate::train_deep::Set;

/// Which of MiniFASNet's scores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Network {
    V2,
    V1se,
    Fused,
}

impl Network {
    pub const ALL: [Network; 3] = [Network::V2, Network::V1se, Network::Fused];

    pub fn name(self) -> &'static str {
        match self {
            Network::V2 => "MiniFASNet V2 (as shipped)",
            Network::V1se => "MiniFASNet V1SE (as shipped)",
            Network::Fused => "MiniFASNet V2 + V1SE (as shipped)",
        }
    }

    pub fn of(self, s: &MiniFasScores) -> f32 {
        match self {
            Network::V2 => s.v2,
            Network::V1se => s.v1se,
            Network::Fused => s.fused,
        }
    }
}

/// The networks' scores of every photo the liveness evaluation reads: NUAA's frames, the other
/// cameras' test persons' live photos and each simulated attack of them (`None`: no face, or a
/// training person), and the other persons' live photos (what a camera's threshold is set on).
pub struct PeerScores {
    pub nuaa: Vec<Option<MiniFasScores>>,
    pub others_live: Vec<Option<MiniFasScores>>,
    /// The persons outside the test split (`None`: no face, or a test person).
    pub others_live_development: Vec<Option<MiniFasScores>>,
    /// Per [`AttackKind::ALL`].
    pub others_simulated: Vec<Vec<Option<MiniFasScores>>>,
}

impl PeerScores {
    pub fn compute(
        data: &LivenessData,
        cache_dir: &Path,
        models_dir: &Path,
        threads: usize,
        progress: &dyn Progress,
    ) -> anyhow::Result<PeerScores> {
        let nuaa_images: Vec<PathBuf> = data.nuaa.iter().map(|s| s.image.clone()).collect();
        let nuaa = crate::liveness::minifasnet::scores(cache_dir, models_dir, &nuaa_images, threads, progress)?;
        let other_images: Vec<PathBuf> = data.others.iter().map(|s| s.image.clone()).collect();
        let boxes = crate::liveness::minifasnet::face_boxes(cache_dir, models_dir, &other_images, threads, progress)?;
        let networks = MiniFasNet::load(models_dir)?;
        let split =
            |test: bool| -> Vec<usize> { (0..data.others.len()).filter(|&i| (data.others[i].split == Split::Test) == test).collect() };
        let score = |kind: Option<AttackKind>, test: bool| -> Vec<Option<MiniFasScores>> {
            let persons = split(test);
            let scored = map_samples(&persons, threads, "MiniFASNet on the other cameras' persons", progress, |&i| {
                let face = boxes[i].as_ref()?;
                let photo = image::open(&other_images[i]).ok()?.to_rgb8();
                let photo = match kind {
                    Some(kind) => simulate(&photo, kind, i as u64),
                    None => photo,
                };
                Some(networks.assess(&photo, face))
            });
            let mut all = vec![None; data.others.len()];
            for (&i, s) in persons.iter().zip(scored) {
                all[i] = s;
            }
            all
        };
        Ok(PeerScores {
            nuaa,
            others_live: score(None, true),
            others_live_development: score(None, false),
            others_simulated: AttackKind::ALL.iter().map(|&k| score(Some(k), true)).collect(),
        })
    }

    /// `network`'s NUAA scores as a [`FitAndScore`] that learns nothing.
    pub fn fixed(&self, network: Network) -> impl Fn(&[usize], &[usize]) -> Vec<Option<f32>> + Sync + '_ {
        move |_train, frames| frames.iter().map(|&i| self.nuaa[i].as_ref().map(|s| network.of(s))).collect()
    }

    /// The nested folds of `network` (the threshold rules choose on the other subjects' scores).
    pub fn folds(&self, data: &LivenessData, network: Network, threads: usize, progress: &dyn Progress) -> Vec<Fold> {
        let fixed = self.fixed(network);
        let fit: &FitAndScore = &fixed;
        folds(data, fit, threads, progress)
    }
}

/// Other cameras' live photos refused and simulated attacks taken for live at one threshold.
#[derive(Debug, Clone, Serialize)]
pub struct OtherCameras {
    pub network: Network,
    /// `0.5` (the networks' own arg-max point) or NUAA's equal rates.
    pub threshold_from: String,
    pub threshold: f32,
    pub live_refused: f64,
    pub live_photos: usize,
    pub print_accepted: f64,
    pub screen_accepted: f64,
}

/// The threshold where `network`'s APCER and BPCER are equal on every NUAA frame.
fn nuaa_eer_threshold(data: &LivenessData, scores: &PeerScores, network: Network) -> f32 {
    let nuaa = |live: bool| -> Vec<f32> {
        data.nuaa.iter().zip(&scores.nuaa).filter(|(s, _)| s.live == live).filter_map(|(_, x)| x.as_ref().map(|x| network.of(x))).collect()
    };
    eer_threshold(&nuaa(true), &nuaa(false))
}

/// `network` at its own 0.5 and at NUAA's equal-rates threshold.
pub fn other_cameras(data: &LivenessData, scores: &PeerScores, network: Network) -> Vec<OtherCameras> {
    let flat = |v: &[Option<MiniFasScores>]| -> Vec<f32> { v.iter().flatten().map(|s| network.of(s)).collect() };
    let live = flat(&scores.others_live);
    let sims: Vec<Vec<f32>> = scores.others_simulated.iter().map(|v| flat(v)).collect();
    let share = |v: &[f32], f: &dyn Fn(f32) -> bool| v.iter().filter(|&&s| f(s)).count() as f64 / v.len().max(1) as f64;
    [("0.5 (the networks' own)".to_string(), 0.5), ("NUAA's equal rates".to_string(), nuaa_eer_threshold(data, scores, network))]
        .into_iter()
        .map(|(from, t)| OtherCameras {
            network,
            threshold_from: from,
            threshold: t,
            live_refused: share(&live, &|s| s < t),
            live_photos: live.len(),
            print_accepted: share(&sims[0], &|s| s >= t),
            screen_accepted: share(&sims[1], &|s| s >= t),
        })
        .collect()
}

/// `network` with each camera's own threshold ([`CameraThreshold`]): set on the live photos of
/// the data set's persons outside the test split (the networks never saw any), measured on its
/// test persons, beside NUAA's equal-rates threshold.
pub fn camera_thresholds(data: &LivenessData, scores: &PeerScores, network: Network) -> Vec<CameraThreshold> {
    let nuaa_threshold = nuaa_eer_threshold(data, scores, network);
    Set::ALL
        .into_iter()
        .filter_map(|set| {
            let of = |v: &[Option<MiniFasScores>]| -> Vec<f32> {
                v.iter().zip(&data.others).filter(|(_, o)| o.set == set).filter_map(|(x, _)| x.as_ref().map(|x| network.of(x))).collect()
            };
            let (prints, screens) = (of(&scores.others_simulated[0]), of(&scores.others_simulated[1]));
            camera_threshold(
                (network.name(), set.name()),
                &of(&scores.others_live_development),
                [&of(&scores.others_live), &prints, &screens],
                nuaa_threshold,
            )
        })
        .collect()
}

/// The name of the shipped LBP recipe fused with MiniFASNet V2 + V1SE.
pub const FUSED_WITH_LBP: &str = "shipped LBP + MiniFASNet V2 + V1SE (as shipped)";

/// A probability as log-odds, kept finite.
fn logit(p: f32) -> f32 {
    let p = p.clamp(1e-6, 1.0 - 1e-6);
    (p / (1.0 - p)).ln()
}

/// The LBP `recipe`'s logit plus MiniFASNet V2 + V1SE's (the log-odds of its fused live
/// probability): two looks at one face added as independent evidence, as the frames of one
/// capture are. Under the nested protocol the LBP part is fitted without the held-out subject.
pub fn fused_folds(data: &LivenessData, recipe: &Recipe, scores: &PeerScores, threads: usize, progress: &dyn Progress) -> Vec<Fold> {
    let lbp = recipe_scores(data, recipe);
    let fused = move |train: &[usize], frames: &[usize]| -> Vec<Option<f32>> {
        let lbp = lbp(train, frames);
        lbp.into_iter().zip(frames).map(|(l, &i)| Some(l? + logit(scores.nuaa[i].as_ref()?.fused))).collect()
    };
    let fit: &FitAndScore = &fused;
    folds(data, fit, threads, progress)
}

/// [`camera_thresholds`] of the fusion: per data set, the LBP recipe fitted without that set's
/// live photos ([`unseen_camera_fits`]: none for a recipe without other cameras' live photos);
/// NUAA's threshold the equal rates of its out-of-fold fused scores.
pub fn fused_camera_thresholds(data: &LivenessData, recipe: &Recipe, scores: &PeerScores, progress: &dyn Progress) -> Vec<CameraThreshold> {
    let cols = columns(&recipe.blocks);
    let out_of_fold = out_of_fold_logits(data, recipe, progress);
    let nuaa = |live: bool| -> Vec<f32> {
        let frames = data.nuaa.iter().zip(&out_of_fold).zip(&scores.nuaa).filter(|((s, _), _)| s.live == live);
        frames.filter_map(|((_, l), m)| Some(l.as_ref()? + logit(m.as_ref()?.fused))).collect()
    };
    let nuaa_threshold = eer_threshold(&nuaa(true), &nuaa(false));
    unseen_camera_fits(data, recipe)
        .into_iter()
        .filter_map(|(set, fit)| {
            let of = |features: &[Option<Vec<f32>>], minifas: &[Option<MiniFasScores>]| -> Vec<f32> {
                let photos = features.iter().zip(minifas).zip(&data.others).filter(|(_, o)| o.set == set);
                photos.filter_map(|((x, m), _)| Some(fit.logit_at(&cols, x.as_ref()?) + logit(m.as_ref()?.fused))).collect()
            };
            let live = of(&data.other_features, &scores.others_live);
            let development = of(&data.other_features, &scores.others_live_development);
            let prints = of(&data.simulated_features[0], &scores.others_simulated[0]);
            let screens = of(&data.simulated_features[1], &scores.others_simulated[1]);
            camera_threshold((FUSED_WITH_LBP, set.name()), &development, [&live, &prints, &screens], nuaa_threshold)
        })
        .collect()
}
