//! How much of each real-video clip's live frames a passive-liveness recipe refuses: the measure
//! of a camera the model never saw (`facegate eval liveness`, `video_refused`).

use serde::Serialize;

use crate::liveness::train::{LivenessData, Recipe, columns, fit_recipe_leaving_out};
use crate::logistic::{LogisticFit, platt_probability};

/// One clip's live frames refused by a recipe at its operating threshold: by the model fitted on
/// everything (which, for a recipe learning from video, saw the clip) and by the same recipe fitted
/// without the clip's person (a camera and a person it never saw: the measure that counts).
#[derive(Debug, Clone, Serialize)]
pub struct VideoRefusal {
    pub clip: String,
    pub person: String,
    /// The clip's frames with a face.
    pub frames: usize,
    /// The calibrated threshold (the model's operating point).
    pub threshold: f32,
    pub refused: f64,
    pub refused_person_unseen: f64,
    /// The median calibrated score by the model that never saw the person.
    pub median_person_unseen: f32,
}

/// [`VideoRefusal`] of every clip of `data`: `full` is the recipe fitted on every NUAA frame,
/// `calibration` Platt's on its out-of-fold logits and `threshold` the calibrated operating point.
pub fn video_refusals(
    data: &LivenessData,
    recipe: &Recipe,
    full: &LogisticFit,
    calibration: (f32, f32),
    threshold: f32,
) -> Vec<VideoRefusal> {
    let cols = columns(&recipe.blocks);
    let all: Vec<usize> = (0..data.nuaa.len()).collect();
    let mut clips: Vec<(&str, &str)> = data.video.iter().map(|f| (f.clip.as_str(), f.person.as_str())).collect();
    clips.dedup();
    let mut fits: Vec<(&str, LogisticFit)> = Vec::new();
    let mut out = Vec::new();
    for (clip, person) in clips {
        // A recipe that never learns from video never saw any person: its full fit is the unseen one.
        if recipe.video_live && !fits.iter().any(|(p, _)| *p == person) {
            fits.push((person, fit_recipe_leaving_out(data, recipe, &all, None, Some(person))));
        }
        let unseen = fits.iter().find(|(p, _)| *p == person).map_or(full, |(_, fit)| fit);
        let features: Vec<&Vec<f32>> =
            data.video.iter().zip(&data.video_features).filter(|(f, _)| f.clip == clip).filter_map(|(_, x)| x.as_ref()).collect();
        let scores =
            |fit: &LogisticFit| -> Vec<f32> { features.iter().map(|x| platt_probability(calibration, fit.logit_at(&cols, x))).collect() };
        let share_below = |v: &[f32]| v.iter().filter(|&&s| s < threshold).count() as f64 / v.len().max(1) as f64;
        let mut unseen_scores = scores(unseen);
        unseen_scores.sort_by(f32::total_cmp);
        out.push(VideoRefusal {
            clip: clip.to_string(),
            person: person.to_string(),
            frames: features.len(),
            threshold,
            refused: share_below(&scores(full)),
            refused_person_unseen: share_below(&unseen_scores),
            median_person_unseen: unseen_scores.get(unseen_scores.len() / 2).copied().unwrap_or(f32::NAN),
        });
    }
    out
}
