//! MiniFASNet's liveness scores of photos for the liveness evaluations
//! ([`facegate_vision::liveness::minifasnet`]), and its measures on NUAA (`facegate eval
//! minifasnet`).
//!
//! The face is the one the service would take: the largest face of the service's face finder
//! ([`FaceFinder`], the detector `FaceFinder::locate` runs), its box kept in the research cache.
//! The networks' scores are computed on top every time (a few milliseconds a photo), so a change
//! of the crop or of the converted weights never needs the cache's version bumped.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use facegate_core::geometry::Rect;
use facegate_vision::liveness::minifasnet::{MiniFasNet, MiniFasScores};
use facegate_vision::pipeline::FaceFinder;
use serde::Serialize;

use crate::Progress;
use crate::cache::{self, CacheKey, ModelFiles, map_samples};
use crate::liveness::train::NuaaSample;
use crate::measures::eer;

/// The box of the largest face the service's face finder finds in each photo (`None`: no face,
/// or the photo does not open), computed by the finder of `models_dir` or read from the cache.
pub fn face_boxes(
    cache_dir: &Path,
    models_dir: &Path,
    images: &[PathBuf],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<Rect>>> {
    let models = ModelFiles::new().finder(models_dir);
    let key = CacheKey::new("minifasnet-face-boxes", &models, &[], images.iter().map(|p| p.display().to_string()));
    cache::get_or_compute(cache_dir, &key, images.len(), progress, || {
        let finder = FaceFinder::load(models_dir)?;
        Ok(map_samples(images, threads, "find faces", progress, |path| {
            let photo = facegate_core::imaging::open(path).ok()?;
            // `FaceFinder::locate`'s face: the first (largest) detection.
            finder.detect(&photo.gray).first().map(|face| face.rect)
        }))
    })
}

/// MiniFASNet V2's, V1SE's and their fused probability of a live face for each photo, `None`
/// where [`face_boxes`] found no face; the networks of `models_dir` (`minifasnet-v2.bin`,
/// `minifasnet-v1se.bin`).
pub fn scores(
    cache_dir: &Path,
    models_dir: &Path,
    images: &[PathBuf],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<MiniFasScores>>> {
    let boxes = face_boxes(cache_dir, models_dir, images, threads, progress)?;
    let networks = MiniFasNet::load(models_dir)?;
    let items: Vec<(&PathBuf, &Option<Rect>)> = images.iter().zip(&boxes).collect();
    Ok(map_samples(&items, threads, "MiniFASNet", progress, |(path, face)| {
        let face = (*face).as_ref()?;
        let photo = facegate_core::imaging::open(path).ok()?;
        Some(networks.assess(&photo.rgb, face))
    }))
}

/// The threshold the measures are taken at. A fused score at or above one half is always the
/// largest of the three classes' means, so such a face is live to the original predictor too (its
/// arg-max also takes some faces below one half for live ones).
pub const THRESHOLD: f32 = 0.5;

/// APCER (attacks taken for live faces) and BPCER (live faces taken for attacks) at
/// [`THRESHOLD`] (live when the score is at or above it), and the EER over all thresholds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Measures {
    pub apcer: f64,
    pub bpcer: f64,
    pub eer: f64,
}

impl Measures {
    fn of(live: &[f32], attacks: &[f32]) -> Measures {
        let share = |n: usize, of: usize| n as f64 / of.max(1) as f64;
        Measures {
            apcer: share(attacks.iter().filter(|&&s| s >= THRESHOLD).count(), attacks.len()),
            bpcer: share(live.iter().filter(|&&s| s < THRESHOLD).count(), live.len()),
            eer: eer(live, attacks),
        }
    }
}

/// The three scores' measures on one set of frames.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    /// A subject's number, or `all`.
    pub subject: String,
    /// Frames with a face, live and printed.
    pub live: usize,
    pub attacks: usize,
    /// Frames where no face was found (not in the measures).
    pub no_face: usize,
    pub v2: Measures,
    pub v1se: Measures,
    pub fused: Measures,
}

/// Every subject's row, then all subjects' together.
pub fn nuaa_rows(samples: &[NuaaSample], scores: &[Option<MiniFasScores>]) -> Vec<Row> {
    let mut by_subject: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, s) in samples.iter().enumerate() {
        by_subject.entry(&s.subject).or_default().push(i);
    }
    let row = |subject: &str, indices: &[usize]| {
        let pick = |live: bool, score: fn(&MiniFasScores) -> f32| -> Vec<f32> {
            indices.iter().filter(|&&i| samples[i].live == live).filter_map(|&i| scores[i].as_ref().map(score)).collect()
        };
        let measures = |score: fn(&MiniFasScores) -> f32| Measures::of(&pick(true, score), &pick(false, score));
        Row {
            subject: subject.to_string(),
            live: pick(true, |s| s.fused).len(),
            attacks: pick(false, |s| s.fused).len(),
            no_face: indices.iter().filter(|&&i| scores[i].is_none()).count(),
            v2: measures(|s| s.v2),
            v1se: measures(|s| s.v1se),
            fused: measures(|s| s.fused),
        }
    };
    let mut rows: Vec<Row> = by_subject.iter().map(|(subject, indices)| row(subject, indices)).collect();
    let all: Vec<usize> = (0..samples.len()).collect();
    rows.push(row("all", &all));
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(subject: &str, live: bool) -> NuaaSample {
        NuaaSample {
            subject: subject.into(),
            live,
            glasses: false,
            condition: "00".into(),
            session: "01".into(),
            image: PathBuf::from("x.jpg"),
        }
    }

    fn scored(v: f32) -> Option<MiniFasScores> {
        Some(MiniFasScores { v2: v, v1se: 1.0 - v, fused: 0.5 })
    }

    #[test]
    fn rows_count_errors_at_one_half_per_subject_and_overall() {
        let samples = [sample("0001", true), sample("0001", true), sample("0001", false), sample("0002", true), sample("0002", false)];
        let scores = [scored(0.9), scored(0.4), scored(0.6), None, scored(0.1)];
        let rows = nuaa_rows(&samples, &scores);
        assert_eq!(rows.len(), 3);
        let first = &rows[0];
        assert_eq!((first.subject.as_str(), first.live, first.attacks, first.no_face), ("0001", 2, 1, 0));
        // V2: live 0.9 and 0.4 (one below one half), the attack 0.6 taken for live.
        assert_eq!((first.v2.bpcer, first.v2.apcer), (0.5, 1.0));
        // V1SE (1 − v): live 0.1 and 0.6, the attack 0.4.
        assert_eq!((first.v1se.bpcer, first.v1se.apcer), (0.5, 0.0));
        // The fused score 0.5 counts as live: every attack accepted, no live face refused.
        assert_eq!((first.fused.bpcer, first.fused.apcer), (0.0, 1.0));
        let all = &rows[2];
        assert_eq!((all.subject.as_str(), all.live, all.attacks, all.no_face), ("all", 2, 2, 1));
        assert_eq!(all.v2.apcer, 0.5);
    }
}
