//! The liveness CNN trained in Rust ([`crate::liveness::cnn`]) against the LBP model, under one
//! protocol both can afford (a CNN fit takes minutes, so not the 81 fits of the nested protocol):
//!
//! - **NUAA subjects never given:** three folds of three subjects (subject `k` in fold `k mod 3`);
//!   each fold's subjects are scored by a model fitted on the other six, at logit 0. Both models
//!   are trained with the classes weighted to equal totals, so logit 0 is each one's own even-odds
//!   point: no threshold is read on any scores, the held-out subject's least of all. Every
//!   subject's APCER and BPCER, the worst, and the pooled ranking (EER, BPCER at APCER 1%).
//! - **Other people and cameras:** the model fitted on all nine subjects, on the IMM, ORL and LFW
//!   test persons' live photos (refused), their simulated prints and screens (taken for live) and
//!   UMIST's live photos (refused), at logit 0.
//! - **The reverse**, for a recipe with simulated attacks: fitted without any NUAA frame, on
//!   NUAA's real frames (does what it learnt of simulated prints find real ones?).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::Progress;
use crate::cache::map_samples;
use crate::dataset::Split;
use crate::liveness::attacks::{AttackKind, simulate};
use crate::liveness::cnn::{Group, Input, LivenessNet, TrainingConfig, input, train};
use crate::liveness::eval::{CameraThreshold, camera_threshold};
use crate::liveness::measures::Rates;
use crate::liveness::subjects::SubjectRates;
use crate::liveness::train::{LivenessData, Recipe, centres, columns, fit_recipe_without};
use crate::logistic::LogisticFit;
use crate::measures::{eer, fnmr_at_fmr};
use crate::train_deep::Set;

/// NUAA's subjects fall into this many folds.
pub const FOLDS: usize = 3;

/// The CNN's inputs of every photo [`LivenessData`] has features of, in the same order (`None`:
/// no face found).
pub struct CnnInputs {
    pub nuaa: Vec<Option<Input>>,
    pub others: Vec<Option<Input>>,
    /// Per [`AttackKind::ALL`], the other cameras' photos as that attack (the
    /// same seeds as the LBP model's simulated features).
    pub simulated: Vec<Vec<Option<Input>>>,
    pub unseen: Vec<Option<Input>>,
}

impl CnnInputs {
    pub fn load(
        data: &LivenessData,
        models_dir: &Path,
        cache_dir: &Path,
        threads: usize,
        progress: &dyn Progress,
    ) -> anyhow::Result<CnnInputs> {
        // Each photo is opened once, its centres read once: as it is, and (the other cameras')
        // as each simulated attack.
        let of = |images: &[PathBuf], attacks: &[AttackKind]| -> anyhow::Result<Vec<Vec<Option<Input>>>> {
            let centres = centres(cache_dir, models_dir, images, threads, progress)?;
            let items: Vec<(usize, &PathBuf, &Option<_>)> = images.iter().zip(&centres).enumerate().map(|(i, (p, k))| (i, p, k)).collect();
            let per_photo = map_samples(&items, threads, "liveness CNN inputs", progress, |(i, path, centres)| {
                let (Some(centres), Ok(photo)) = (centres, image::open(path)) else { return vec![None; 1 + attacks.len()] };
                let photo = photo.to_rgb8();
                let attacked = attacks.iter().map(|&kind| Some(input(&simulate(&photo, kind, *i as u64), centres)));
                std::iter::once(Some(input(&photo, centres))).chain(attacked).collect()
            });
            let mut variants: Vec<Vec<Option<Input>>> = vec![Vec::with_capacity(images.len()); 1 + attacks.len()];
            for photo in per_photo {
                variants.iter_mut().zip(photo).for_each(|(v, x)| v.push(x));
            }
            Ok(variants)
        };
        let nuaa: Vec<PathBuf> = data.nuaa.iter().map(|s| s.image.clone()).collect();
        let others: Vec<PathBuf> = data.others.iter().map(|s| s.image.clone()).collect();
        let mut others = of(&others, &AttackKind::ALL)?.into_iter();
        Ok(CnnInputs {
            nuaa: of(&nuaa, &[])?.swap_remove(0),
            others: others.next().expect("the photos as they are"),
            simulated: others.collect(),
            unseen: of(&data.unseen, &[])?.swap_remove(0),
        })
    }
}

/// A model compared.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum Learner {
    /// The LBP features' logistic model ([`crate::liveness::train`]).
    Lbp(Recipe),
    /// The CNN, trained on NUAA's frames, the other cameras' training persons' live photos and,
    /// when `simulated_attacks`, their simulated prints and screens.
    Cnn { simulated_attacks: bool, config: TrainingConfig },
}

/// Where the photos scored come from.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Source {
    Nuaa,
    Others,
    Simulated(usize),
    Unseen,
}

enum Fitted {
    Lbp(LogisticFit, Vec<usize>),
    Cnn(LivenessNet),
}

/// Both models' data: the LBP features and the CNN's inputs of the same photos.
pub struct Data<'a> {
    pub features: &'a LivenessData,
    pub inputs: &'a CnnInputs,
}

impl Data<'_> {
    /// The logits of the photos `indices` of `source` (`None`: no face).
    fn scores(&self, fitted: &Fitted, source: Source, indices: &[usize]) -> anyhow::Result<Vec<Option<f32>>> {
        match fitted {
            Fitted::Lbp(fit, cols) => {
                let features = match source {
                    Source::Nuaa => &self.features.nuaa_features,
                    Source::Others => &self.features.other_features,
                    Source::Simulated(k) => &self.features.simulated_features[k],
                    Source::Unseen => &self.features.unseen_features,
                };
                Ok(indices.iter().map(|&i| features[i].as_ref().map(|x| fit.logit_at(cols, x))).collect())
            }
            Fitted::Cnn(net) => {
                let inputs = match source {
                    Source::Nuaa => &self.inputs.nuaa,
                    Source::Others => &self.inputs.others,
                    Source::Simulated(k) => &self.inputs.simulated[k],
                    Source::Unseen => &self.inputs.unseen,
                };
                let present: Vec<&Input> = indices.iter().filter_map(|&i| inputs[i].as_ref()).collect();
                let mut logits = net.logits(&present)?.into_iter();
                Ok(indices.iter().map(|&i| inputs[i].as_ref().and_then(|_| logits.next())).collect())
            }
        }
    }

    /// `learner` fitted on the NUAA frames `nuaa` and the other cameras' training persons, but
    /// for those of the data set `without`.
    fn fit(&self, learner: &Learner, nuaa: &[usize], without: Option<Set>, progress: &dyn Progress) -> anyhow::Result<Fitted> {
        match learner {
            Learner::Lbp(recipe) => Ok(Fitted::Lbp(fit_recipe_without(self.features, recipe, nuaa, without), columns(&recipe.blocks))),
            Learner::Cnn { simulated_attacks, config } => {
                let d = self.features;
                let nuaa_of =
                    |live: bool| nuaa.iter().filter(|&&i| d.nuaa[i].live == live).filter_map(|&i| self.inputs.nuaa[i].as_ref()).collect();
                let training: Vec<usize> = d.others_in(Split::Train).into_iter().filter(|&i| Some(d.others[i].set) != without).collect();
                let mut groups = vec![
                    Group { inputs: nuaa_of(true), live: true },
                    Group { inputs: nuaa_of(false), live: false },
                    Group { inputs: training.iter().filter_map(|&i| self.inputs.others[i].as_ref()).collect(), live: true },
                ];
                if *simulated_attacks {
                    let attacks = self.inputs.simulated.iter().flat_map(|kind| training.iter().filter_map(|&i| kind[i].as_ref())).collect();
                    groups.push(Group { inputs: attacks, live: false });
                }
                Ok(Fitted::Cnn(train(&groups, config, progress)?))
            }
        }
    }
}

/// How often photos of one kind are refused (live photos) or taken for live (attacks) at logit 0.
#[derive(Debug, Clone, Serialize)]
pub struct Share {
    pub what: String,
    pub photos: usize,
    pub share: f64,
}

/// The reverse check: fitted without NUAA, on NUAA's frames.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Reverse {
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    pub at_zero: Rates,
}

/// One model's measures.
#[derive(Debug, Clone, Serialize)]
pub struct CnnReport {
    pub name: String,
    pub learner: Learner,
    /// Each NUAA subject never given, at logit 0.
    pub subjects: Vec<SubjectRates>,
    /// All held-out frames pooled, at logit 0.
    pub pooled: Rates,
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    pub worst_apcer: f64,
    pub worst_bpcer: f64,
    /// Live photos refused (IMM, ORL, LFW test persons; UMIST) and simulated attacks taken for
    /// live, by the model fitted on all nine subjects.
    pub other_cameras: Vec<Share>,
    pub reverse: Option<Reverse>,
    /// Mean wall-clock seconds per fit (the subject folds').
    pub fit_seconds: f64,
    /// The CNN's wall-clock milliseconds per face, scoring NUAA's frames one at a time (the model
    /// fitted on all nine subjects; the crops are cut beforehand). `None` for the LBP model, whose
    /// features are computed once for every fit (its cost: `cargo bench --bench liveness`).
    pub score_ms_per_face: Option<f64>,
}

/// The live and attack logits of the NUAA frames `indices` with a face.
fn split_by_class(d: &LivenessData, indices: &[usize], logits: &[Option<f32>]) -> (Vec<f32>, Vec<f32>) {
    let (mut live, mut attacks) = (Vec::new(), Vec::new());
    for (&i, l) in indices.iter().zip(logits) {
        let Some(l) = l else { continue };
        if d.nuaa[i].live { live.push(*l) } else { attacks.push(*l) }
    }
    (live, attacks)
}

/// The measures of `learner` (see the module's note).
pub fn evaluate(data: &Data, name: &str, learner: &Learner, progress: &dyn Progress) -> anyhow::Result<CnnReport> {
    let d = data.features;
    let subjects = crate::liveness::subjects::subjects(d);
    let fold_of = |s: &str| subjects.iter().position(|x| x == s).unwrap_or(0) % FOLDS;
    let (mut per_subject, mut live_all, mut attacks_all) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    for fold in 0..FOLDS {
        let train: Vec<usize> = (0..d.nuaa.len()).filter(|&i| fold_of(&d.nuaa[i].subject) != fold).collect();
        let fitted = data.fit(learner, &train, None, progress)?;
        for subject in subjects.iter().filter(|s| fold_of(s) == fold) {
            let held: Vec<usize> = (0..d.nuaa.len()).filter(|&i| &d.nuaa[i].subject == subject).collect();
            let (live, attacks) = split_by_class(d, &held, &data.scores(&fitted, Source::Nuaa, &held)?);
            let r = Rates::at(&live, &attacks, 0.0);
            per_subject.push(SubjectRates {
                subject: subject.clone(),
                threshold: 0.0,
                live: live.len(),
                attacks: attacks.len(),
                apcer: r.apcer,
                bpcer: r.bpcer,
            });
            live_all.extend(live);
            attacks_all.extend(attacks);
        }
    }
    let fit_seconds = started.elapsed().as_secs_f64() / FOLDS as f64;
    per_subject.sort_by(|a, b| a.subject.cmp(&b.subject));
    let all: Vec<usize> = (0..d.nuaa.len()).collect();
    let full = data.fit(learner, &all, None, progress)?;
    let score_ms_per_face = match full {
        Fitted::Lbp(..) => None,
        Fitted::Cnn(_) => {
            let timed = Instant::now();
            for &i in &all {
                data.scores(&full, Source::Nuaa, &[i])?;
            }
            Some(1e3 * timed.elapsed().as_secs_f64() / all.len() as f64)
        }
    };
    Ok(CnnReport {
        name: name.to_string(),
        learner: learner.clone(),
        pooled: Rates::at(&live_all, &attacks_all, 0.0),
        eer: eer(&live_all, &attacks_all),
        bpcer_at_apcer_1: fnmr_at_fmr(&live_all, &attacks_all, 0.01).0,
        worst_apcer: per_subject.iter().map(|s| s.apcer).fold(0.0, f64::max),
        worst_bpcer: per_subject.iter().map(|s| s.bpcer).fold(0.0, f64::max),
        subjects: per_subject,
        other_cameras: other_cameras(data, &full)?,
        reverse: reverse(data, learner, progress)?,
        fit_seconds,
        score_ms_per_face,
    })
}

fn other_cameras(data: &Data, full: &Fitted) -> anyhow::Result<Vec<Share>> {
    let d = data.features;
    let test = d.others_in(Split::Test);
    let share = |what: String, logits: Vec<Option<f32>>, refused: bool| {
        let v: Vec<f32> = logits.into_iter().flatten().collect();
        let n = v.iter().filter(|&&s| (s < 0.0) == refused).count();
        Share { what, photos: v.len(), share: n as f64 / v.len().max(1) as f64 }
    };
    let mut out = Vec::new();
    for set in Set::ALL {
        let of_set: Vec<usize> = test.iter().copied().filter(|&i| d.others[i].set == set).collect();
        out.push(share(format!("{} live refused", set.name()), data.scores(full, Source::Others, &of_set)?, true));
    }
    let umist: Vec<usize> = (0..d.unseen.len()).collect();
    out.push(share("UMIST live refused".into(), data.scores(full, Source::Unseen, &umist)?, true));
    for (k, kind) in AttackKind::ALL.iter().enumerate() {
        out.push(share(format!("{} taken for live", kind.name()), data.scores(full, Source::Simulated(k), &test)?, false));
    }
    Ok(out)
}

fn reverse(data: &Data, learner: &Learner, progress: &dyn Progress) -> anyhow::Result<Option<Reverse>> {
    let simulated = match learner {
        Learner::Lbp(r) => r.simulated_attacks && r.other_cameras,
        Learner::Cnn { simulated_attacks, .. } => *simulated_attacks,
    };
    if !simulated {
        return Ok(None);
    }
    let fitted = data.fit(learner, &[], None, progress)?;
    let all: Vec<usize> = (0..data.features.nuaa.len()).collect();
    let (live, attacks) = split_by_class(data.features, &all, &data.scores(&fitted, Source::Nuaa, &all)?);
    Ok(Some(Reverse {
        eer: eer(&live, &attacks),
        bpcer_at_apcer_1: fnmr_at_fmr(&live, &attacks, 0.01).0,
        at_zero: Rates::at(&live, &attacks, 0.0),
    }))
}

/// Per data set, `learner` fitted on every NUAA frame and the other sets' training persons (so
/// the set's camera is new to it), its threshold set as `facegate calibrate-liveness` would on the
/// live photos of the set's persons outside its test split, measured on its test persons' live
/// photos and simulated attacks; beside it (in the `nuaa_*` fields), logit 0, the model's own
/// even-odds point. Three fits.
pub fn camera_thresholds(data: &Data, name: &str, learner: &Learner, progress: &dyn Progress) -> anyhow::Result<Vec<CameraThreshold>> {
    let d = data.features;
    let all: Vec<usize> = (0..d.nuaa.len()).collect();
    let mut out = Vec::new();
    for set in Set::ALL {
        let fitted = data.fit(learner, &all, Some(set), progress)?;
        let of_set = |test: bool| -> Vec<usize> {
            (0..d.others.len()).filter(|&i| d.others[i].set == set && (d.others[i].split == Split::Test) == test).collect()
        };
        let scores = |source: Source, test: bool| -> anyhow::Result<Vec<f32>> {
            Ok(data.scores(&fitted, source, &of_set(test))?.into_iter().flatten().collect())
        };
        let (prints, screens) = (scores(Source::Simulated(0), true)?, scores(Source::Simulated(1), true)?);
        let measured =
            camera_threshold((name, set.name()), &scores(Source::Others, false)?, [&scores(Source::Others, true)?, &prints, &screens], 0.0);
        out.extend(measured);
    }
    Ok(out)
}
