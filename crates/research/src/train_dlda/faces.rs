//! The labelled photos a model is trained and measured on, and the named face regions of the crop.

use std::path::PathBuf;

use crate::dataset;
use facegate_vision::recognize::features::Region;

/// One labelled photo with what the split needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceImage {
    pub label: String,
    /// The person is in the held-out set (`dataset::imm_is_test_person` on the label's number;
    /// LFW's calibration and test persons, `dataset::lfw_split`).
    pub held_out: bool,
    /// IMM view number (1–6) when the file has an IMM name.
    pub view: Option<u32>,
    pub image: PathBuf,
    /// The IMM annotation beside the photo, if any.
    pub asf: Option<PathBuf>,
}

impl FaceImage {
    /// IMM views 3 and 4 are the heads rotated by about 30°; every other photo counts as frontal or
    /// near-frontal (ORL's pose variation is mild).
    pub fn is_rotated_view(&self) -> bool {
        matches!(self.view, Some(3 | 4))
    }
}

/// The person number at the end of a label (`imm-07` → 7, `orl-s12` → 12).
pub fn person_number(label: &str) -> Option<u32> {
    let tail = label.rsplit('-').next()?;
    let digits: String = tail.chars().rev().take_while(|c| c.is_ascii_digit()).collect::<Vec<_>>().into_iter().rev().collect();
    digits.parse().ok()
}

/// All labelled photos of `dirs` (a folder per person, or IMM names).
pub fn list_faces(dirs: &[PathBuf]) -> Result<Vec<FaceImage>, dataset::DatasetError> {
    let mut out = Vec::new();
    for dir in dirs {
        for item in dataset::list_labelled(dir)? {
            let name = item.image.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            let view = dataset::parse_imm_name(&name).map(|(_, v)| v);
            let asf = Some(item.image.with_extension("asf")).filter(|p| p.exists());
            let held_out = match item.label.strip_prefix("lfw-") {
                Some(person) => dataset::lfw_split(person) != dataset::Split::Train,
                None => person_number(&item.label).is_some_and(dataset::imm_is_test_person),
            };
            out.push(FaceImage { label: item.label, held_out, view, image: item.image, asf });
        }
    }
    Ok(out)
}

/// Named regions of the normalised crop (eyes at 34 % of its height, 26 % and 73 % of its width,
/// the mouth at 82 % of its height).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaceRegion {
    /// Both eyes and brows.
    Eyes,
    /// The nose, between and below the eyes.
    Nose,
    /// The mouth and chin.
    Mouth,
    /// Everything above the nose tip (eyes, brows, forehead).
    Upper,
    /// Everything below the eyes (nose, cheeks, mouth).
    Lower,
    /// The central face without the outline (eyes to mouth).
    Inner,
    /// The eye and brow on the image's left.
    LeftEye,
    /// The eye and brow on the image's right.
    RightEye,
    /// The image's left half of the face.
    LeftHalf,
    /// The image's right half of the face.
    RightHalf,
}

impl FaceRegion {
    /// The region of the crop, in fractions of its width and height.
    pub fn region(self) -> Region {
        let r = |x0, y0, x1, y1| Region { x0, y0, x1, y1 };
        match self {
            FaceRegion::Eyes => r(0.0, 0.1, 1.0, 0.52),
            FaceRegion::Nose => r(0.25, 0.3, 0.75, 0.78),
            FaceRegion::Mouth => r(0.12, 0.64, 0.88, 1.0),
            FaceRegion::Upper => r(0.0, 0.0, 1.0, 0.6),
            FaceRegion::Lower => r(0.0, 0.45, 1.0, 1.0),
            FaceRegion::Inner => r(0.15, 0.2, 0.85, 0.95),
            FaceRegion::LeftEye => r(0.0, 0.1, 0.55, 0.55),
            FaceRegion::RightEye => r(0.45, 0.1, 1.0, 0.55),
            FaceRegion::LeftHalf => r(0.0, 0.0, 0.55, 1.0),
            FaceRegion::RightHalf => r(0.45, 0.0, 1.0, 1.0),
        }
    }
}
