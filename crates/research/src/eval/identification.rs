//! Rank-1 identification across head pose (`facegate eval identify`, the thesis's figure 5.7
//! analogue): a model per normalisation path trained on the training persons; gallery the first
//! frontal view of each held-out person (and of the training persons as distractors), probes every
//! other view of the held-out persons, binned by IMM view group and by |yaw| of the 3DMM fit.

use std::collections::BTreeMap;

use super::verification::rank1;
use crate::Progress;
use crate::train_dlda::{self as train, AlignedFace, FaceImage, FrontEnd, TrainConfig};
use facegate_core::template::Template;
use facegate_vision::recognize::{ClassicalRecognizer, Normalization};

/// Rank-1 hits per bin: bin → (probes, hits per normalisation path, in the order measured).
pub struct IdentificationTable {
    pub bins: BTreeMap<String, (usize, Vec<usize>)>,
    /// Where the centres came from ([`centre_sources`]).
    pub centre_sources: String,
}

/// Trains a model per normalisation in `normalizations` (`config_for` gives its settings) and
/// measures rank-1 identification of the held-out persons of `faces` by pose bin.
pub fn rank1_by_pose(
    front: &FrontEnd,
    faces: &[FaceImage],
    normalizations: &[Normalization],
    config_for: impl Fn(Normalization) -> TrainConfig,
    data: &[String],
    distractors: bool,
    progress: &dyn Progress,
) -> anyhow::Result<IdentificationTable> {
    let mut table: BTreeMap<String, (usize, Vec<usize>)> = BTreeMap::new();
    let mut sources = String::new();
    for (k, &normalization) in normalizations.iter().enumerate() {
        let config = config_for(normalization);
        let aligned = train::align_all(front, faces, normalization, &config.normalize, progress);
        sources = centre_sources(&aligned);
        let (model, _) = train::train_model(&aligned, &config, data)?;
        let recognizer = ClassicalRecognizer::from_model(model);
        let held: Vec<&AlignedFace> = aligned.iter().filter(|a| a.face.held_out).collect();
        // Gallery: the first frontal view (view 1) of each held-out person (and of the training
        // persons with `distractors`); probes: every other view of the held-out persons.
        let gallery: Vec<(&str, Template)> = aligned
            .iter()
            .filter(|a| a.face.view == Some(1) && (a.face.held_out || distractors))
            .map(|a| Ok((a.face.label.as_str(), train::template_of(&recognizer, a)?)))
            .collect::<anyhow::Result<_>>()?;
        for a in held.iter().filter(|a| a.face.view != Some(1)) {
            let Some(truth) = gallery.iter().position(|(l, _)| *l == a.face.label) else { continue };
            let t = train::template_of(&recognizer, a)?;
            let row: Vec<f32> = gallery.iter().map(|(_, g)| recognizer.score(&t, std::slice::from_ref(g))).collect();
            let hit = (rank1(&[row], &[truth]) == 1.0) as usize;
            // Two tables: by IMM view group, and by |yaw| of the 3DMM fit when there is one.
            let view_group = AlignedFace { pose: None, ..(*a).clone() };
            let mut bins = vec![format!("view: {}", pose_bin(&view_group))];
            if a.pose.is_some() {
                bins.push(format!("pose: {}", pose_bin(a)));
            }
            for bin in bins {
                let entry = table.entry(bin).or_insert_with(|| (0, vec![0; normalizations.len()]));
                if k == 0 {
                    entry.0 += 1;
                }
                entry.1[k] += hit;
            }
        }
    }
    Ok(IdentificationTable { bins: table, centre_sources: sources })
}

/// The centre sources of `aligned` with their counts (`imm-annotations (54), pipeline (3)`).
pub fn centre_sources(aligned: &[AlignedFace]) -> String {
    let mut counts: std::collections::BTreeMap<&str, usize> = Default::default();
    for a in aligned {
        *counts.entry(a.centre_source).or_default() += 1;
    }
    counts.iter().map(|(s, n)| format!("{s} ({n})")).collect::<Vec<_>>().join(", ")
}

/// Pose bin of a probe: |yaw| from the 3DMM fit when there is one, else the IMM view group.
pub fn pose_bin(a: &AlignedFace) -> String {
    match a.pose {
        Some(p) => {
            let y = p.yaw.abs();
            let lo = ((y / 10.0).floor() as i32 * 10).min(40);
            if lo >= 40 { "|yaw| ≥ 40°".into() } else { format!("|yaw| {lo}–{}°", lo + 10) }
        }
        None if a.face.is_rotated_view() => "IMM views 3-4 (±30°)".into(),
        None => "IMM views 2,5,6 (frontal)".into(),
    }
}
