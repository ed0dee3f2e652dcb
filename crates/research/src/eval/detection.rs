//! Detection measures: rate of IMM photos whose largest box holds both eye centres and the mouth
//! centre, per view class; false boxes per image on IMM photos and on face-free images (blank,
//! noise, IMM background crops); time per image; the box's position relative to the eyes and
//! mouth (what the landmark stage initialises from); and the rate on the small ORL faces.

use std::path::Path;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::dataset::{imm_is_test_person, list_imm};

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::Rect;
use facegate_core::imaging::{GrayF32, open};
use facegate_detect::{Detector, Face};

use super::thread_cpu_ns;

#[derive(Debug, Clone, Default, Serialize)]
pub struct Rate {
    pub found: usize,
    pub total: usize,
}

impl Rate {
    fn add(&mut self, ok: bool) {
        self.found += ok as usize;
        self.total += 1;
    }

    pub fn percent(&self) -> f64 {
        if self.total == 0 { f64::NAN } else { 100.0 * self.found as f64 / self.total as f64 }
    }
}

/// Mean and standard deviation of a measured quantity.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Spread {
    pub mean: f64,
    pub sd: f64,
    pub n: usize,
}

impl Spread {
    fn of(values: &[f64]) -> Spread {
        let n = values.len();
        if n == 0 {
            return Spread::default();
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n.max(2) - 1) as f64;
        Spread { mean, sd: var.sqrt(), n }
    }
}

/// Where the eyes and mouth sit in the box, in box units (0 = left/top edge, 1 = right/bottom).
#[derive(Debug, Clone, Default, Serialize)]
pub struct BoxPlacement {
    /// Midpoint of the eye centres.
    pub eyes_x: Spread,
    pub eyes_y: Spread,
    pub mouth_y: Spread,
    /// Distance between the eye centres over the box width (the box's scale consistency).
    pub eye_distance: Spread,
}

/// Results on one set of IMM persons.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ImmResult {
    pub persons: String,
    /// Views 1, 2, 5, 6.
    pub frontal: Rate,
    /// Views 3, 4.
    pub rotated: Rate,
    pub per_view: Vec<Rate>,
    /// Boxes that do not hold the annotated face's eyes and mouth (nor overlap that box).
    pub false_boxes: usize,
    pub images: usize,
    pub placement: BoxPlacement,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct Timing {
    pub images: usize,
    pub mean_ms: f64,
    pub median_ms: f64,
    pub max_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DetectionReport {
    pub detector: String,
    pub options: String,
    pub imm_test: ImmResult,
    pub imm_all: ImmResult,
    /// Face-free images: blank, noise, IMM background strips.
    pub negatives: usize,
    pub negative_false_boxes: usize,
    /// ORL: the largest box holds the frame centre and is at least a third of the frame wide.
    pub orl_test: Rate,
    pub orl_all: Rate,
    pub orl_extra_boxes: usize,
    /// Detection time per IMM photo (640×480), one thread: wall clock, and CPU time of the
    /// thread (what one free core would take).
    pub imm_timing: Timing,
    pub imm_cpu_timing: Timing,
    pub orl_timing: Timing,
    pub orl_cpu_timing: Timing,
}

fn holds(rect: &Rect, k: &EyeMouthCentres) -> bool {
    rect.contains(k.left_eye) && rect.contains(k.right_eye) && rect.contains(k.mouth)
}

fn timing(ms: &mut [f64]) -> Timing {
    if ms.is_empty() {
        return Timing::default();
    }
    ms.sort_by(f64::total_cmp);
    Timing { images: ms.len(), mean_ms: ms.iter().sum::<f64>() / ms.len() as f64, median_ms: ms[ms.len() / 2], max_ms: ms[ms.len() - 1] }
}

fn timed(detector: &Detector, gray: &GrayF32, wall_ms: &mut Vec<f64>, cpu_ms: &mut Vec<f64>) -> Vec<Face> {
    let cpu = thread_cpu_ns();
    let t = Instant::now();
    let faces = detector.detect(gray);
    wall_ms.push(t.elapsed().as_secs_f64() * 1e3);
    if let (Some(a), Some(b)) = (cpu, thread_cpu_ns()) {
        cpu_ms.push(b.saturating_sub(a) as f64 * 1e-6);
    }
    faces
}

struct ImmOutcome {
    person: u32,
    view: u32,
    ok: bool,
    false_boxes: usize,
    placement: Option<[f64; 4]>,
}

fn summarise(outcomes: &[ImmOutcome], persons: &str, keep: impl Fn(u32) -> bool) -> ImmResult {
    let mut r = ImmResult { persons: persons.to_string(), per_view: vec![Rate::default(); 6], ..ImmResult::default() };
    let mut place: [Vec<f64>; 4] = Default::default();
    for o in outcomes.iter().filter(|o| keep(o.person)) {
        r.images += 1;
        r.false_boxes += o.false_boxes;
        if (1..=6).contains(&o.view) {
            r.per_view[o.view as usize - 1].add(o.ok);
        }
        if matches!(o.view, 3 | 4) {
            r.rotated.add(o.ok)
        } else {
            r.frontal.add(o.ok)
        }
        if let Some(p) = o.placement {
            for i in 0..4 {
                place[i].push(p[i]);
            }
        }
    }
    r.placement = BoxPlacement {
        eyes_x: Spread::of(&place[0]),
        eyes_y: Spread::of(&place[1]),
        mouth_y: Spread::of(&place[2]),
        eye_distance: Spread::of(&place[3]),
    };
    r
}

/// Face-free strips of an IMM photo: the full-height bands left and right of the annotated face
/// (its landmark box widened by half its width), when at least 100 pixels wide.
fn background_strips(gray: &GrayF32, points: &[[f32; 2]]) -> Vec<GrayF32> {
    let Some(face) = Rect::bounding(points) else { return Vec::new() };
    let x0 = (face.x - 0.5 * face.width).max(0.0) as usize;
    let x1 = ((face.x + 1.5 * face.width) as usize).min(gray.width);
    let mut out = Vec::new();
    if x0 >= 100 {
        out.push(GrayF32::from_fn(x0, gray.height, |x, y| gray.get(x, y)));
    }
    if gray.width - x1 >= 100 {
        out.push(GrayF32::from_fn(gray.width - x1, gray.height, |x, y| gray.get(x1 + x, y)));
    }
    out
}

pub fn evaluate(detector: &Detector, imm_dir: &Path, orl_dir: &Path, test_only: bool) -> anyhow::Result<DetectionReport> {
    let samples = list_imm(imm_dir)?;
    let mut outcomes = Vec::new();
    let (mut imm_ms, mut imm_cpu) = (Vec::new(), Vec::new());
    let mut negatives = Vec::new();
    for s in samples.iter().filter(|s| !test_only || imm_is_test_person(s.person)) {
        let photo = open(&s.image)?;
        let points = s.landmarks()?;
        let keys = EyeMouthCentres::from_imm(&points);
        let faces = timed(detector, &photo.gray, &mut imm_ms, &mut imm_cpu);
        let ok = faces.first().is_some_and(|f| holds(&f.rect, &keys));
        let true_box = faces.iter().find(|f| holds(&f.rect, &keys)).map(|f| f.rect);
        let false_boxes = faces.iter().filter(|f| !holds(&f.rect, &keys) && true_box.is_none_or(|t| t.iou(&f.rect) < 0.3)).count();
        let placement = faces.first().filter(|_| ok).map(|f| {
            let r = f.rect;
            let eyes = [(keys.left_eye[0] + keys.right_eye[0]) / 2.0, (keys.left_eye[1] + keys.right_eye[1]) / 2.0];
            [
                ((eyes[0] - r.x) / r.width) as f64,
                ((eyes[1] - r.y) / r.height) as f64,
                ((keys.mouth[1] - r.y) / r.height) as f64,
                (facegate_core::geometry::distance(keys.left_eye, keys.right_eye) / r.width) as f64,
            ]
        });
        outcomes.push(ImmOutcome { person: s.person, view: s.view, ok, false_boxes, placement });
        if imm_is_test_person(s.person) || !test_only {
            negatives.extend(background_strips(&photo.gray, &points));
        }
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2011);
    for level in [0.0f32, 64.0, 128.0, 200.0, 255.0] {
        negatives.push(GrayF32::from_fn(640, 480, |_, _| level));
    }
    for _ in 0..10 {
        let noise = GrayF32::from_fn(640, 480, |_, _| rng.random_range(0.0..255.0f32));
        // Blurred noise has blob structure at face scales, a harder negative than white noise.
        let blurred = noise.gaussian_blur(3.0);
        negatives.push(noise);
        negatives.push(blurred);
    }
    let negative_false_boxes = negatives.iter().map(|g| detector.detect(g).len()).sum();

    let (mut orl_test, mut orl_all, mut orl_extra) = (Rate::default(), Rate::default(), 0);
    let (mut orl_ms, mut orl_cpu) = (Vec::new(), Vec::new());
    if orl_dir.is_dir() {
        for subject in 1..=40u32 {
            let dir = orl_dir.join(format!("s{subject}"));
            if !dir.is_dir() || (test_only && !imm_is_test_person(subject)) {
                continue;
            }
            for k in 1..=10 {
                let path = dir.join(format!("{k}.pgm"));
                if !path.exists() {
                    continue;
                }
                let gray = open(&path)?.gray;
                let faces = timed(detector, &gray, &mut orl_ms, &mut orl_cpu);
                let centre = [gray.width as f32 / 2.0, gray.height as f32 / 2.0];
                let ok = faces.first().is_some_and(|f| f.rect.contains(centre) && f.rect.width >= gray.width as f32 / 3.0);
                orl_extra += faces.len().saturating_sub(1);
                orl_all.add(ok);
                if imm_is_test_person(subject) {
                    orl_test.add(ok);
                }
            }
        }
    }
    Ok(DetectionReport {
        detector: format!("{:?}", detector.kind()).to_lowercase(),
        options: format!("{:?}", detector.options),
        imm_test: summarise(&outcomes, "held-out (1,2,3,5,10,15,20,25,30)", imm_is_test_person),
        imm_all: summarise(&outcomes, if test_only { "held-out only" } else { "all" }, |_| true),
        negatives: negatives.len(),
        negative_false_boxes,
        orl_test,
        orl_all,
        orl_extra_boxes: orl_extra,
        imm_timing: timing(&mut imm_ms),
        orl_timing: timing(&mut orl_ms),
        imm_cpu_timing: timing(&mut imm_cpu),
        orl_cpu_timing: timing(&mut orl_cpu),
    })
}

impl DetectionReport {
    /// A few lines for the terminal and the docs.
    pub fn summary(&self) -> String {
        let mut s = format!("detector {} {}\n", self.detector, self.options);
        for r in [&self.imm_test, &self.imm_all] {
            s += &format!(
                "IMM {}: frontal {}/{} ({:.1}%), rotated {}/{} ({:.1}%), per view [{}], false boxes {} on {} photos\n",
                r.persons,
                r.frontal.found,
                r.frontal.total,
                r.frontal.percent(),
                r.rotated.found,
                r.rotated.total,
                r.rotated.percent(),
                r.per_view.iter().map(|v| format!("{}/{}", v.found, v.total)).collect::<Vec<_>>().join(" "),
                r.false_boxes,
                r.images
            );
            let p = &r.placement;
            s += &format!(
                "  box placement (box units, mean±sd): eyes x {:.3}±{:.3} y {:.3}±{:.3}, mouth y {:.3}±{:.3}, eye distance/width {:.3}±{:.3}\n",
                p.eyes_x.mean,
                p.eyes_x.sd,
                p.eyes_y.mean,
                p.eyes_y.sd,
                p.mouth_y.mean,
                p.mouth_y.sd,
                p.eye_distance.mean,
                p.eye_distance.sd
            );
        }
        s += &format!("face-free images: {} false boxes on {} images\n", self.negative_false_boxes, self.negatives);
        s += &format!(
            "ORL: held-out {}/{} ({:.1}%), all {}/{} ({:.1}%), extra boxes {}\n",
            self.orl_test.found,
            self.orl_test.total,
            self.orl_test.percent(),
            self.orl_all.found,
            self.orl_all.total,
            self.orl_all.percent(),
            self.orl_extra_boxes
        );
        for (name, t) in [
            ("IMM 640x480 wall", &self.imm_timing),
            ("IMM 640x480 thread CPU", &self.imm_cpu_timing),
            ("ORL 92x112 wall", &self.orl_timing),
            ("ORL 92x112 thread CPU", &self.orl_cpu_timing),
        ] {
            s += &format!(
                "time {name}: mean {:.2} ms, median {:.2} ms, max {:.2} ms over {} images\n",
                t.mean_ms, t.median_ms, t.max_ms, t.images
            );
        }
        s
    }
}
