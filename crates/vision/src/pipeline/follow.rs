//! Which face of a frame is the person a camera has been following: the face nearest where the
//! person's face was in the last frame, if it lies within one face width of it. The frames of a
//! head-turn challenge come from one camera a moment apart; a second, larger face beside the
//! person (someone passing, a photo on the wall) is not the person's.

use facegate_core::geometry::Rect;
use facegate_detect::Face;

/// Where the followed face was in the last frame, as shares of that frame's width and height
/// (a frame of another size is read in its own pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FollowedFace {
    share: Rect,
}

impl FollowedFace {
    /// The face `rect` in a `width` × `height` frame.
    pub fn of(rect: &Rect, width: u32, height: u32) -> FollowedFace {
        let (w, h) = (width.max(1) as f32, height.max(1) as f32);
        FollowedFace { share: Rect::new(rect.x / w, rect.y / h, rect.width / w, rect.height / h) }
    }

    /// The followed face's box in a `width` × `height` frame's pixels.
    pub fn in_frame(&self, width: u32, height: u32) -> Rect {
        let (w, h) = (width as f32, height as f32);
        Rect::new(self.share.x * w, self.share.y * h, self.share.width * w, self.share.height * h)
    }

    /// The index in `faces` (largest first) of the person's face in a `width` × `height` frame:
    /// the face nearest the followed one among those within one face width of it
    /// ([`Rect::follows`]); `None` when none is (the person left or jumped).
    pub fn pick(&self, faces: &[Face], width: u32, height: u32) -> Option<usize> {
        let last = self.in_frame(width, height);
        faces
            .iter()
            .enumerate()
            .filter(|(_, f)| f.rect.follows(&last))
            .min_by(|a, b| a.1.rect.center_distance(&last).total_cmp(&b.1.rect.center_distance(&last)))
            .map(|(i, _)| i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn face(x: f32, y: f32, size: f32) -> Face {
        Face { rect: Rect::new(x, y, size, size), score: 1.0, points: None }
    }

    #[test]
    fn the_person_is_followed_past_a_larger_face_and_across_frame_sizes() {
        // The person at the left, 100 px wide, in a 640 × 480 frame.
        let last = FollowedFace::of(&Rect::new(60.0, 150.0, 100.0, 100.0), 640, 480);
        // A larger face at the right (first: largest), the person moved 20 px.
        let faces = [face(360.0, 100.0, 180.0), face(80.0, 155.0, 96.0)];
        assert_eq!(last.pick(&faces, 640, 480), Some(1));
        // The same frame at half size: shares, not pixels.
        let half = [face(180.0, 50.0, 90.0), face(40.0, 77.5, 48.0)];
        assert_eq!(last.pick(&half, 320, 240), Some(1));
        // The person gone: no face is theirs.
        assert_eq!(last.pick(&faces[..1], 640, 480), None);
        // Two faces near: the nearer one.
        let near = [face(110.0, 150.0, 100.0), face(62.0, 150.0, 100.0)];
        assert_eq!(last.pick(&near, 640, 480), Some(1));
        assert_eq!(last.pick(&[], 640, 480), None);
    }
}
