//! The face types every stage shares: the IMM 58-point layout (path numbers of the `.asf` files,
//! in image terms for a frontal photo: path 0 = jaw (13 points, the open *contour* group), 1 = eye
//! on the image right, 2 = eye on the image left, 3 = eyebrow on the image right, 4 = eyebrow on
//! the image left, 5 = mouth, 6 = nose; points 13..58 form the *internal* group) and the eye and
//! mouth centres ([`EyeMouthCentres`]) the recognizer aligns on.

use std::ops::Range;

use crate::geometry::{Point, centroid};

pub const IMM_POINTS: usize = 58;
/// Jaw outline: the contour group of C-ASM (grey-level profiles).
pub const JAW: Range<usize> = 0..13;
/// Eye on the image right of a frontal face (the subject's left eye).
pub const EYE_IMAGE_RIGHT: Range<usize> = 13..21;
/// Eye on the image left of a frontal face (the subject's right eye).
pub const EYE_IMAGE_LEFT: Range<usize> = 21..29;
pub const BROW_IMAGE_RIGHT: Range<usize> = 29..34;
pub const BROW_IMAGE_LEFT: Range<usize> = 34..39;
pub const MOUTH: Range<usize> = 39..47;
pub const NOSE: Range<usize> = 47..58;
/// The internal group of C-ASM (SIFT descriptors): eyes, eyebrows, mouth, nose.
pub const INTERNAL: Range<usize> = 13..58;

/// Eye and mouth centres as the means of their outline points (thesis 2.5.1).
/// `left_eye` is the eye on the image left.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EyeMouthCentres {
    pub left_eye: Point,
    pub right_eye: Point,
    pub mouth: Point,
}

impl EyeMouthCentres {
    pub fn from_imm(points: &[Point]) -> EyeMouthCentres {
        assert_eq!(points.len(), IMM_POINTS, "an IMM shape has 58 points");
        EyeMouthCentres {
            left_eye: centroid(&points[EYE_IMAGE_LEFT]),
            right_eye: centroid(&points[EYE_IMAGE_RIGHT]),
            mouth: centroid(&points[MOUTH]),
        }
    }
}
