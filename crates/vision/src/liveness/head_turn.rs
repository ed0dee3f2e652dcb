//! Active liveness, the 3D part: does a capture show a head turning as a challenge asked, and is
//! it a head at all? Each frame's yaw comes from 3DMM fits: the step's from the mean face fitted
//! to the detector's five key points, the depth's from the fit to the 58 landmarks ([`FramePose`]
//! says why). A real
//! head turning moves its near and far features by different amounts: the nose tip, a good
//! centimetre in front of the eyes and mouth, crosses the cheek; a photo held up and turned, or
//! bent, stays a surface whose points one homography of the image plane maps from one view to
//! the next ([`nose_parallax`]). The measure reads the detector's five key points, where the
//! network saw them: the 58 landmarks of a turned face are the 3D-ASM's, drawn towards a head's
//! shape by its model, and on turned prints they showed as much "parallax" as real heads (one
//! homography's residual over them: docs/liveness-challenge.md). Plain data in (the steps, each
//! frame's yaw and key points), plain data out ([`HeadTurn`]); the service decides with it.

use facegate_core::geometry::Point;
use serde::{Deserialize, Serialize};

/// Where a challenge step asks the person to look. The yaw convention is the 3D fit's (and
/// `/analyze`'s): yaw > 0 when the person turned to their own left (the nose to the image right).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Turn {
    Front,
    Left,
    Right,
}

/// Most |yaw| of a frontal step, degrees, as [`FramePose::yaw`] (the key points') reads it: IMM
/// training persons' neutral frontal photos (views 1, 2, 5) and their mirror images read within
/// 9.3° (`facegate eval challenge --persons train`; docs/liveness-challenge.md, "Which yaw").
pub const FRONT_MAX_YAW: f32 = 12.0;
/// Least |yaw| of a turned step, degrees: the same persons' photos turned about 30° (views 3, 4)
/// read 16.6° to 51.1° in size (their mirror images from 14.0°); a photo held up and turned by
/// 30° reads at most 9.3°, by 45° 13.5°, by 60° 19.4° (the parallax stops those that reach a step).
pub const TURN_MIN_YAW: f32 = 12.0;
/// Most |yaw| of a turned step: past it the far eye is hidden and the pose is read less well.
pub const TURN_MAX_YAW: f32 = 60.0;

impl Turn {
    /// The yaw range (degrees, inclusive) a frame of this turn must show.
    pub fn yaw_range(self) -> (f32, f32) {
        match self {
            Turn::Front => (-FRONT_MAX_YAW, FRONT_MAX_YAW),
            Turn::Left => (TURN_MIN_YAW, TURN_MAX_YAW),
            Turn::Right => (-TURN_MAX_YAW, -TURN_MIN_YAW),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Turn::Front => "front",
            Turn::Left => "left",
            Turn::Right => "right",
        }
    }
}

/// One step of a challenge: the turn and the yaw range its frame must show.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Step {
    pub turn: Turn,
    pub yaw_min: f32,
    pub yaw_max: f32,
}

impl Step {
    pub fn of(turn: Turn) -> Step {
        let (yaw_min, yaw_max) = turn.yaw_range();
        Step { turn, yaw_min, yaw_max }
    }

    pub fn admits(&self, yaw: f32) -> bool {
        (self.yaw_min..=self.yaw_max).contains(&yaw)
    }
}

/// What was read of one frame: two yaws and the detector's five key points (`None` from a
/// detector without them).
///
/// The step is judged by `yaw`, the 3DMM's mean face fitted to the five key points: on the IMM
/// training persons it kept frontal and turned views apart where the 58-landmark fit did not
/// (docs/liveness-challenge.md, "Which yaw"). The depth divides the nose's parallax by the sine
/// of `fit_yaw` differences, the 3DMM fitted to the 58 landmarks: a yaw read from the same five
/// points would take its size from the mean face's nose and so push every nose, a rendered one
/// too, towards the mean's depth (measured: the least live depth on the training persons fell
/// from 0.659 to 0.589 and the avatars' margin below it from 0.070 to 0.025).
#[derive(Debug, Clone, Copy)]
pub struct FramePose {
    /// The key points' yaw (degrees), judged against the step's range.
    pub yaw: Option<f32>,
    /// The 58-landmark 3DMM fit's yaw (degrees), for the depth's yaw differences.
    pub fit_yaw: Option<f32>,
    pub keypoints: Option<[Point; 5]>,
}

/// One step as read: the frame's yaw and whether it lies in the step's range.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StepReading {
    pub turn: Turn,
    pub yaw: Option<f32>,
    pub ok: bool,
}

/// A capture read against a challenge's steps.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeadTurn {
    pub steps: Vec<StepReading>,
    /// The flattest turn: over the frames of turned steps (in their range), the least nose depth,
    /// each frame's [`nose_parallax`] from the view of the capture (the probe among them) whose
    /// yaw differs most from its own, over the sine of that difference. About 0 for a picture
    /// moved in the plane; `None` when no turned frame could be measured (no other view a turn
    /// away, or no key points).
    pub parallax: Option<f64>,
}

/// Read `frames` (one per step, in order) against `steps`, with `probe` as a further view for the
/// parallax reference.
pub fn read_head_turn(steps: &[Step], probe: FramePose, frames: &[FramePose]) -> HeadTurn {
    let readings = steps
        .iter()
        .zip(frames)
        .map(|(step, frame)| StepReading { turn: step.turn, yaw: frame.yaw, ok: frame.yaw.is_some_and(|y| step.admits(y)) })
        .collect();
    // Each turned frame against the view of the capture (the probe among them) whose yaw differs
    // most from its own, by at least a turn: the nose's parallax over the sine of that yaw
    // difference is the depth of the nose in front of the eyes and mouth, in eye distances.
    let views: Vec<&FramePose> = std::iter::once(&probe).chain(frames).collect();
    let turned = steps.iter().zip(frames).filter(|(step, frame)| step.turn != Turn::Front && frame.yaw.is_some_and(|y| step.admits(y)));
    let parallax = turned
        .filter_map(|(_, frame)| {
            let (to, yaw) = (frame.keypoints?, frame.fit_yaw?);
            let apart = |v: &&&FramePose| v.fit_yaw.map_or(0.0, |y| (y - yaw).abs());
            let other = views.iter().filter(|v| v.keypoints.is_some()).max_by(|a, b| apart(a).total_cmp(&apart(b)))?;
            let difference = apart(&other);
            if difference < TURN_MIN_YAW {
                return None;
            }
            Some(nose_parallax(&other.keypoints?, &to)? / (difference as f64).to_radians().sin())
        })
        .min_by(f64::total_cmp);
    HeadTurn { steps: readings, parallax }
}

/// How far the nose tip of the five key points `to` (image-left eye, image-right eye, nose tip,
/// image-left and image-right mouth corner) is from where the homography that maps the eyes and
/// mouth corners of `from` onto those of `to` puts the nose of `from`, over the inter-ocular
/// distance of `to`. A picture moved, turned or bent only a little is one plane: the nose goes
/// where the plane goes (0 up to the detector's noise). A head turned by 25° moves its nose
/// about a quarter of the eye distance off that plane. `None` when the four points are
/// degenerate.
pub fn nose_parallax(from: &[Point; 5], to: &[Point; 5]) -> Option<f64> {
    let quad = [0, 1, 3, 4];
    // h33 = 1: eight unknowns, two equations per corner.
    let mut a = nalgebra::SMatrix::<f64, 8, 8>::zeros();
    let mut b = nalgebra::SVector::<f64, 8>::zeros();
    for (row, &k) in quad.iter().enumerate() {
        let (x, y) = (from[k][0] as f64, from[k][1] as f64);
        let (u, v) = (to[k][0] as f64, to[k][1] as f64);
        let r = 2 * row;
        for (c, val) in [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y].into_iter().enumerate() {
            a[(r, c)] = val;
        }
        for (c, val) in [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y].into_iter().enumerate() {
            a[(r + 1, c)] = val;
        }
        b[r] = u;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b)?;
    let (x, y) = (from[2][0] as f64, from[2][1] as f64);
    let w = h[6] * x + h[7] * y + 1.0;
    if w.abs() < 1e-9 {
        return None;
    }
    let (u, v) = ((h[0] * x + h[1] * y + h[2]) / w, (h[3] * x + h[4] * y + h[5]) / w);
    let eyes = (((to[0][0] - to[1][0]).powi(2) + (to[0][1] - to[1][1]).powi(2)) as f64).sqrt();
    let moved = ((u - to[2][0] as f64).powi(2) + (v - to[2][1] as f64).powi(2)).sqrt() / eyes.max(1.0);
    moved.is_finite().then_some(moved)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Five key points of a head (eyes, nose tip 25 mm in front of them, mouth corners) seen by
    /// a pinhole camera turned `yaw` degrees; `flat` puts the nose in the eyes' plane (a photo).
    fn keypoints(yaw: f32, flat: bool) -> [Point; 5] {
        let (s, c) = yaw.to_radians().sin_cos();
        let head = [[-32.0, -20.0, 0.0], [32.0, -20.0, 0.0], [0.0, 10.0, 25.0], [-25.0, 40.0, -3.0], [25.0, 40.0, -3.0]];
        head.map(|[x, y, z]| {
            let z = if flat { 0.0 } else { z };
            let (xr, zr) = (c * x + s * z, -s * x + c * z);
            let depth = 600.0 - zr;
            [320.0 + 800.0 * xr / depth, 240.0 + 800.0 * y / depth]
        })
    }

    #[test]
    fn the_nose_of_a_turned_head_leaves_the_plane_of_its_eyes_and_mouth() {
        let front = keypoints(0.0, false);
        for yaw in [15.0f32, 25.0, -25.0, 40.0] {
            let head = nose_parallax(&front, &keypoints(yaw, false)).unwrap();
            let photo = nose_parallax(&keypoints(0.0, true), &keypoints(yaw, true)).unwrap();
            assert!(photo < 1e-6, "a photo turned {yaw}° keeps its nose in its plane: {photo}");
            assert!(head > 0.1, "a head turned {yaw}°: {head}");
        }
        // Degenerate corners (all four at one place) measure nothing.
        assert_eq!(nose_parallax(&[[1.0, 1.0]; 5], &front), None);
    }

    #[test]
    fn steps_read_their_frames_yaw_and_the_flattest_turn() {
        let steps = [Step::of(Turn::Left), Step::of(Turn::Front), Step::of(Turn::Right)];
        let frame = |yaw: f32, flat: bool| FramePose { yaw: Some(yaw), fit_yaw: Some(yaw), keypoints: Some(keypoints(yaw, flat)) };
        let read = read_head_turn(&steps, frame(1.0, false), &[frame(24.0, false), frame(2.0, false), frame(-26.0, false)]);
        assert!(read.steps.iter().all(|s| s.ok), "{read:?}");
        assert!(read.parallax.is_some_and(|p| p > 0.1), "{read:?}");
        // A photo turned to the same readings: the poses are right, the parallax is not there.
        let read = read_head_turn(&steps, frame(1.0, true), &[frame(24.0, true), frame(2.0, true), frame(-26.0, true)]);
        assert!(read.steps.iter().all(|s| s.ok) && read.parallax.is_some_and(|p| p < 0.01), "{read:?}");
        // The wrong order: the left frame where the right is asked.
        let read = read_head_turn(&steps, frame(1.0, false), &[frame(-26.0, false), frame(2.0, false), frame(24.0, false)]);
        assert_eq!(read.steps.iter().map(|s| s.ok).collect::<Vec<_>>(), [false, true, false]);
        assert_eq!(read.parallax, None, "no turned step was met");
        // No fit: not ok, and no reference without any yaw; no key points: no parallax.
        let none = FramePose { yaw: None, fit_yaw: None, keypoints: None };
        let read = read_head_turn(&steps, none, &[none, none, none]);
        assert!(read.steps.iter().all(|s| !s.ok && s.yaw.is_none()) && read.parallax.is_none());
        let blind = |yaw: f32| FramePose { keypoints: None, ..frame(yaw, false) };
        let read = read_head_turn(&steps, blind(1.0), &[blind(24.0), blind(2.0), blind(-26.0)]);
        assert!(read.steps.iter().all(|s| s.ok) && read.parallax.is_none(), "{read:?}");
        assert!(Step::of(Turn::Left).admits(TURN_MIN_YAW) && !Step::of(Turn::Left).admits(-20.0));
    }

    #[test]
    fn the_step_reads_the_key_points_yaw_and_the_depth_the_fits() {
        let steps = [Step::of(Turn::Left), Step::of(Turn::Right)];
        let head = |yaw: f32, fit_yaw: Option<f32>| FramePose { yaw: Some(yaw), fit_yaw, keypoints: Some(keypoints(yaw, false)) };
        let both = read_head_turn(&steps, head(0.0, Some(0.0)), &[head(25.0, Some(25.0)), head(-25.0, Some(-25.0))]);
        // The same key points, the fit reading half the turns: the steps stand, and the depth is
        // the parallax over the sines of the fit's (smaller) differences, so larger.
        let halved = read_head_turn(&steps, head(0.0, Some(0.0)), &[head(25.0, Some(12.5)), head(-25.0, Some(-12.5))]);
        assert!(halved.steps.iter().all(|s| s.ok), "{halved:?}");
        let (p, q) = (both.parallax.unwrap(), halved.parallax.unwrap());
        assert!(q > 1.5 * p, "halved yaw differences give a deeper nose: {p} then {q}");
        // No fit: the steps are judged, but no depth is measured.
        let unfit = read_head_turn(&steps, head(0.0, None), &[head(25.0, None), head(-25.0, None)]);
        assert!(unfit.steps.iter().all(|s| s.ok) && unfit.parallax.is_none(), "{unfit:?}");
    }
}
