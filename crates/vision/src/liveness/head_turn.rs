//! Active liveness, the 3D part: does a capture show a head turning as a challenge asked, and is
//! it a head at all? Measurement only (plain data in, plain data out); the service decides.
//!
//! Each step is answered by a burst of frames (one or more). A step is read by the median yaw of
//! its frames, the 3DMM's mean face fitted to the detector's five key points (`/analyze`'s
//! `key_point_pose`).
//!
//! Flat or not is a test between two explanations of every frame's five key points (eyes, nose
//! tip, mouth corners), [`depth_test`]:
//!
//! - **a plane** (a photo, a screen, a sheet held up, turned or tilted): one homography per frame
//!   maps the eyes and mouth corners onto a fixed canonical quad, and then the nose lands on the
//!   same canonical point in every frame, up to the detector's noise;
//! - **a rigid head**: the nose tip stands in front of the eyes and mouth, so as the head turns it
//!   crosses the canonical quad, to the image's right on a turn to the person's left and to its
//!   left on a turn to their right.
//!
//! The statistic is how far the canonical nose moves per step of turn (a least-squares slope over
//! all frames against each frame's step: left +1, front 0, right −1), in eye distances, over its
//! standard error from the noise the frames themselves show (their spread within each step's
//! burst, never taken below [`NOISE_FLOOR`]). Its square is the F statistic of the plane against
//! the head. The key points are where the network saw them, not a model's idea of a face: the 58
//! landmarks of a turned face come from the 3D-ASM, which draws even a flat picture towards a
//! head's shape.

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
/// 30° reads at most 9.3°, by 45° 13.5°, by 60° 19.4° (the depth test stops those that reach a
/// step).
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

    /// Which way the nose crosses the face for this turn: +1 to the image's right (left turn),
    /// −1 to its left (right turn), 0 for the front.
    pub fn direction(self) -> f64 {
        match self {
            Turn::Front => 0.0,
            Turn::Left => 1.0,
            Turn::Right => -1.0,
        }
    }
}

/// One step of a challenge: the turn and the yaw range its frames must show.
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

/// What was read of one frame: the key points' yaw and the detector's five key points (`None`
/// from a detector without them, or without the 3D model for the yaw).
///
/// The step is judged by `yaw`, the 3DMM's mean face fitted to the five key points: on the IMM
/// training persons it kept frontal and turned views apart where the 58-landmark fit did not
/// (docs/liveness-challenge.md, "Which yaw").
#[derive(Debug, Clone, Copy)]
pub struct FramePose {
    /// The key points' yaw (degrees), judged against the step's range.
    pub yaw: Option<f32>,
    pub keypoints: Option<[Point; 5]>,
}

/// One step as read: its burst's median yaw and whether that lies in the step's range.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StepReading {
    pub turn: Turn,
    /// The median yaw of the step's frames (those whose yaw could be read).
    pub yaw: Option<f32>,
    pub ok: bool,
    /// How many frames answered the step.
    pub frames: usize,
    /// The median of the step's frames' [`proportions`] over the capture's widest (the probe's
    /// and every frame's): about cos(yaw) for a head, whose eyes draw together as it turns while
    /// its eyes-to-mouth height stays. A picture turned far enough for its key points to read a
    /// turn is narrowed far more than that turn explains.
    pub narrowing: Option<f32>,
}

impl StepReading {
    /// How many degrees more the step's narrowing says the face turned than its yaw does (0 when
    /// it says less): acos(narrowing) − |yaw|. A head shows a few degrees; a flat picture turned
    /// by 60° to read 20° shows about 40.
    pub fn excess_turn(&self) -> Option<f32> {
        let (n, yaw) = (self.narrowing?, self.yaw?);
        Some((n.clamp(0.0, 1.0).acos().to_degrees() - yaw.abs()).max(0.0))
    }
}

/// The eye distance over the height from the eyes' midpoint to the mouth corners' midpoint, of
/// the five key points (image-left eye, image-right eye, nose, image-left and image-right mouth
/// corner). Independent of the face's size in the image.
pub fn proportions(points: &[Point; 5]) -> Option<f32> {
    let d = |a: Point, b: Point| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
    let mid = |a: Point, b: Point| [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
    let height = d(mid(points[0], points[1]), mid(points[3], points[4]));
    let ratio = d(points[0], points[1]) / height;
    (height > 1e-3 && ratio.is_finite()).then_some(ratio)
}

/// The plane against the head, over a capture's frames ([`depth_test`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DepthTest {
    /// How far the nose crosses the canonical face per step of turn (left +1, front 0, right
    /// −1), in eye distances: the least-squares slope over the frames. About 0 for a plane; a
    /// head read at the turn steps' least yaw (12°) shows about 0.15.
    pub shift: f64,
    /// The spread of one frame's canonical nose around its step's mean (eye distances), pooled
    /// over the steps' bursts; `None` with fewer than two frames beyond one per step.
    pub within_noise: Option<f64>,
    /// Σ (direction − mean direction)² over the frames: the slope's standard error is the
    /// noise over its square root.
    pub leverage: f64,
    /// Frames measured (with key points).
    pub frames: usize,
}

impl DepthTest {
    /// The noise one frame's canonical nose is taken to have: the frames' own, never below
    /// `floor` (a burst of identical frames shows none, and must not make a small shift count).
    pub fn noise(&self, floor: f64) -> f64 {
        self.within_noise.map_or(floor, |n| n.max(floor))
    }

    /// The shift over its standard error (√F of the plane against the head), one-sided: the nose
    /// must cross the way the turns ask.
    pub fn z(&self, floor: f64) -> f64 {
        self.shift * self.leverage.sqrt() / self.noise(floor)
    }
}

/// A capture read against a challenge's steps.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeadTurn {
    pub steps: Vec<StepReading>,
    /// `None` when fewer than two turn directions had a frame with key points.
    pub depth: Option<DepthTest>,
}

/// Read `bursts` (for each step in order, its frames) against `steps`, with `probe` a further
/// view for the widest proportions.
pub fn read_head_turn(steps: &[Step], probe: FramePose, bursts: &[Vec<FramePose>]) -> HeadTurn {
    let views = std::iter::once(&probe).chain(bursts.iter().flatten());
    let widest = views.filter_map(|f| proportions(f.keypoints.as_ref()?)).fold(None, |m: Option<f32>, r| Some(m.map_or(r, |m| m.max(r))));
    let readings = steps
        .iter()
        .zip(bursts)
        .map(|(step, burst)| {
            let yaw = median(burst.iter().filter_map(|f| f.yaw).collect());
            let narrowing =
                widest.and_then(|w| median(burst.iter().filter_map(|f| Some(proportions(f.keypoints.as_ref()?)? / w)).collect()));
            StepReading { turn: step.turn, yaw, ok: yaw.is_some_and(|y| step.admits(y)), frames: burst.len(), narrowing }
        })
        .collect();
    let turns: Vec<Turn> = steps.iter().map(|s| s.turn).collect();
    HeadTurn { steps: readings, depth: depth_test(&turns, bursts) }
}

fn median(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { (v[n / 2 - 1] + v[n / 2]) / 2.0 })
}

/// The plane against the head over every frame of the capture: each frame's canonical nose
/// ([`canonical_nose`], its horizontal coordinate) against its step's turn direction. The slope
/// is the nose's crossing per step of turn; the noise is the pooled spread within the steps.
pub fn depth_test(turns: &[Turn], bursts: &[Vec<FramePose>]) -> Option<DepthTest> {
    let mut samples: Vec<(usize, f64, f64)> = Vec::new();
    for (step, (turn, burst)) in turns.iter().zip(bursts).enumerate() {
        for frame in burst {
            if let Some(nose) = frame.keypoints.as_ref().and_then(canonical_nose) {
                samples.push((step, turn.direction(), nose[0]));
            }
        }
    }
    if samples.is_empty() {
        return None;
    }
    let n = samples.len() as f64;
    let mean_d = samples.iter().map(|s| s.1).sum::<f64>() / n;
    let mean_x = samples.iter().map(|s| s.2).sum::<f64>() / n;
    let leverage: f64 = samples.iter().map(|s| (s.1 - mean_d).powi(2)).sum();
    if leverage < 1e-9 {
        return None;
    }
    let shift = samples.iter().map(|s| (s.1 - mean_d) * (s.2 - mean_x)).sum::<f64>() / leverage;
    // Within each step's burst: the spread around the burst's own mean.
    let (mut within, mut dof) = (0.0, 0usize);
    for step in 0..turns.len() {
        let xs: Vec<f64> = samples.iter().filter(|s| s.0 == step).map(|s| s.2).collect();
        if xs.len() > 1 {
            let m = xs.iter().sum::<f64>() / xs.len() as f64;
            within += xs.iter().map(|x| (x - m).powi(2)).sum::<f64>();
            dof += xs.len() - 1;
        }
    }
    let within_noise = (dof >= 2).then(|| (within / dof as f64).sqrt());
    Some(DepthTest { shift, within_noise, leverage, frames: samples.len() })
}

/// The canonical face the eyes and mouth corners are mapped onto, in eye distances: the eyes at
/// (0, 0) and (1, 0), the mouth corners 1.15 below, 0.8 apart (a frontal face's proportions; any
/// fixed quad serves, this one keeps the units near eye distances).
const CANONICAL_QUAD: [[f64; 2]; 4] = [[0.0, 0.0], [1.0, 0.0], [0.1, 1.15], [0.9, 1.15]];

/// Where the homography that maps the frame's eyes and mouth corners (key points 0, 1, 3, 4:
/// image-left eye, image-right eye, image-left and image-right mouth corner) onto
/// [`CANONICAL_QUAD`] puts its nose tip (key point 2). For a picture, moved, turned or tilted,
/// the same point in every frame; for a head, it crosses the face as the head turns. `None`
/// when the quad is degenerate.
pub fn canonical_nose(points: &[Point; 5]) -> Option<[f64; 2]> {
    let from = [0, 1, 3, 4].map(|k| [points[k][0] as f64, points[k][1] as f64]);
    let h = homography(&from, &CANONICAL_QUAD)?;
    let (x, y) = (points[2][0] as f64, points[2][1] as f64);
    let w = h[6] * x + h[7] * y + 1.0;
    if w.abs() < 1e-9 {
        return None;
    }
    let nose = [(h[0] * x + h[1] * y + h[2]) / w, (h[3] * x + h[4] * y + h[5]) / w];
    (nose[0].is_finite() && nose[1].is_finite()).then_some(nose)
}

/// The homography (h33 = 1) mapping the four points `from` onto `to`: eight unknowns, two
/// equations per point. `None` when the points are degenerate.
fn homography(from: &[[f64; 2]; 4], to: &[[f64; 2]; 4]) -> Option<nalgebra::SVector<f64, 8>> {
    let mut a = nalgebra::SMatrix::<f64, 8, 8>::zeros();
    let mut b = nalgebra::SVector::<f64, 8>::zeros();
    for (row, ([x, y], [u, v])) in from.iter().zip(to).enumerate() {
        let r = 2 * row;
        for (c, val) in [*x, *y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y].into_iter().enumerate() {
            a[(r, c)] = val;
        }
        for (c, val) in [0.0, 0.0, 0.0, *x, *y, 1.0, -v * x, -v * y].into_iter().enumerate() {
            a[(r + 1, c)] = val;
        }
        b[r] = *u;
        b[r + 1] = *v;
    }
    let h = a.lu().solve(&b)?;
    h.iter().all(|v| v.is_finite()).then_some(h)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Five key points of a head (eyes, nose tip `nose` mm in front of them, mouth corners) seen
    /// by a pinhole camera turned `yaw` degrees; `nose` 0 is a photo (the nose in the eyes'
    /// plane).
    fn keypoints(yaw: f32, nose: f32) -> [Point; 5] {
        let (s, c) = yaw.to_radians().sin_cos();
        let head = [[-32.0, -20.0, 0.0], [32.0, -20.0, 0.0], [0.0, 10.0, nose], [-25.0, 40.0, 0.0], [25.0, 40.0, 0.0]];
        head.map(|[x, y, z]| {
            let (xr, zr) = (c * x + s * z, -s * x + c * z);
            let depth = 600.0 - zr;
            [320.0 + 800.0 * xr / depth, 240.0 + 800.0 * y / depth]
        })
    }

    fn frame(yaw: f32, nose: f32) -> FramePose {
        FramePose { yaw: Some(yaw), keypoints: Some(keypoints(yaw, nose)) }
    }

    #[test]
    fn a_picture_keeps_its_canonical_nose_and_a_head_moves_it_the_way_it_turns() {
        let still = canonical_nose(&keypoints(0.0, 0.0)).unwrap();
        for yaw in [-40.0f32, -15.0, 15.0, 40.0] {
            let photo = canonical_nose(&keypoints(yaw, 0.0)).unwrap();
            assert!((photo[0] - still[0]).abs() < 1e-6 && (photo[1] - still[1]).abs() < 1e-6, "{yaw}: {photo:?}");
            let head = canonical_nose(&keypoints(yaw, 25.0)).unwrap()[0] - canonical_nose(&keypoints(0.0, 25.0)).unwrap()[0];
            assert!(head * yaw as f64 > 0.0 && head.abs() > 0.1, "a head turned {yaw}° moves its nose {head}");
        }
        assert_eq!(canonical_nose(&[[1.0, 1.0]; 5]), None, "degenerate corners measure nothing");
    }

    #[test]
    fn steps_read_their_bursts_median_yaw() {
        let steps = [Step::of(Turn::Left), Step::of(Turn::Front), Step::of(Turn::Right)];
        let burst = |yaws: &[f32]| yaws.iter().map(|&y| frame(y, 25.0)).collect::<Vec<_>>();
        let probe = frame(0.0, 25.0);
        let read = read_head_turn(&steps, probe, &[burst(&[10.0, 24.0, 30.0]), burst(&[2.0]), burst(&[-26.0, -70.0])]);
        assert_eq!(
            read.steps.iter().map(|s| (s.yaw, s.ok, s.frames)).collect::<Vec<_>>(),
            [(Some(24.0), true, 3), (Some(2.0), true, 1), (Some(-48.0), true, 2)]
        );
        // The wrong order: the left frames where the right is asked.
        let read = read_head_turn(&steps, probe, &[burst(&[-26.0]), burst(&[2.0]), burst(&[24.0])]);
        assert_eq!(read.steps.iter().map(|s| s.ok).collect::<Vec<_>>(), [false, true, false]);
        assert!(read.depth.unwrap().shift < 0.0, "the nose crossed against the asked turns");
        // No yaw, no key points: not ok, and nothing to test.
        let none = FramePose { yaw: None, keypoints: None };
        let read = read_head_turn(&steps, none, &[vec![none], vec![none], vec![none]]);
        assert!(read.steps.iter().all(|s| !s.ok && s.yaw.is_none()) && read.depth.is_none());
        assert!(Step::of(Turn::Left).admits(TURN_MIN_YAW) && !Step::of(Turn::Left).admits(-20.0));
    }

    #[test]
    fn a_head_narrows_as_it_turns_and_a_picture_turned_to_read_as_much_narrows_more() {
        let steps = [Step::of(Turn::Left), Step::of(Turn::Right)];
        let head = read_head_turn(&steps, frame(0.0, 25.0), &[vec![frame(25.0, 25.0)], vec![frame(-25.0, 25.0)]]);
        for s in &head.steps {
            let n = s.narrowing.unwrap();
            assert!((n - 25f32.to_radians().cos()).abs() < 0.05 && s.excess_turn().unwrap() < 5.0, "{s:?}");
        }
        // A photo turned 60° whose key points were read as a 20° turn.
        let photo = |yaw: f32| FramePose { yaw: Some(yaw.signum() * 20.0), keypoints: Some(keypoints(yaw, 0.0)) };
        let print = read_head_turn(&steps, frame(0.0, 0.0), &[vec![photo(60.0)], vec![photo(-60.0)]]);
        assert!(print.steps.iter().all(|s| s.excess_turn().unwrap() > 30.0), "{print:?}");
        assert!(proportions(&[[0.0, 0.0]; 5]).is_none());
    }

    #[test]
    fn the_depth_test_tells_a_head_from_a_picture_whatever_its_nose() {
        let turns = [Turn::Left, Turn::Front, Turn::Right];
        // Bursts with a little detector noise: a deterministic jitter of ±0.4 px.
        let burst = |yaw: f32, nose: f32| -> Vec<FramePose> {
            (0..5)
                .map(|i| {
                    let mut f = frame(yaw + i as f32 * 0.5, nose);
                    let k = f.keypoints.as_mut().unwrap();
                    k[2][0] += [0.4, -0.4, 0.2, -0.2, 0.0][i];
                    f
                })
                .collect()
        };
        let floor = 0.02;
        for nose in [15.0f32, 25.0, 35.0] {
            let test = depth_test(&turns, &[burst(20.0, nose), burst(0.0, nose), burst(-20.0, nose)]).unwrap();
            assert!(test.shift > 0.08 && test.z(floor) > 5.0, "nose {nose} mm: {test:?}");
            assert!(test.within_noise.is_some() && test.frames == 15);
        }
        let photo = depth_test(&turns, &[burst(40.0, 0.0), burst(0.0, 0.0), burst(-40.0, 0.0)]).unwrap();
        assert!(photo.shift.abs() < 0.01 && photo.z(floor) < 2.0, "{photo:?}");
        // One frame per step: the floor is the noise.
        let single = depth_test(&turns, &[vec![frame(20.0, 25.0)], vec![frame(0.0, 25.0)], vec![frame(-20.0, 25.0)]]).unwrap();
        assert_eq!((single.within_noise, single.leverage), (None, 2.0));
        assert_eq!(single.noise(floor), floor);
        // Only front frames: no turn to test.
        assert!(depth_test(&[Turn::Front], &[burst(0.0, 25.0)]).is_none());
    }
}
