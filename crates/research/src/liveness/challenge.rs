//! The head-turn liveness challenge under attack (`facegate eval challenge`), ISO/IEC 30107-3
//! style: for persons never used in training, live sequences made from their own photos against
//! each attack type, every capture judged by the service's own rule
//! ([`facegate_service::challenge::judge`]) on the runtime's one pipeline. Reports BPCER of the
//! live sequences and APCER per attack, with and without the passive score, the depth test's
//! distributions the limits are read from, and the CPU of a challenge. The video clips'
//! captures and attacks (in bursts) are [`video`]'s.
//!
//! Live: IMM (enrolled with view 1, the probe view 2, front steps views 5 and 1, left view 4,
//! right view 3) and UMIST (enrolled with photo 18, the probe photo 19, turned steps drawn among
//! photos 15–17 and their mirror images; UMIST turns to one side and has no frontal photo, so its
//! challenges are the drawn ones without a front step, a left step answered by a photo and a
//! right one by a mirror image). Attacks on IMM persons: the probe photo held still; the probe
//! photo as a flat print turned by ±15…60° (perspective warp) or bent on a cylinder and turned;
//! the right photos in the wrong order (left and right exchanged); another person's photo in one
//! turned step; the probe photo's fitted 3D head rendered at each step's yaw (`frontalize
//! --yaw`); and the attacker who watches the console's yaw, holding the print (or rendering the
//! head) at whichever of several angles reads inside each step's range. NUAA: each print
//! capture's frames (the print moved or bent by hand) as the steps. The
//! reused challenge is refused by the store (taken once) and is measured there.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use image::{Rgb, RgbImage};
use rand::SeedableRng;
use rand::seq::{IndexedRandom, SliceRandom};
use serde::Serialize;

use facegate_core::imaging::{self, GrayF32, Photo};
use facegate_core::template::Template;
use facegate_morph::{FitOptions, Pose};
use facegate_service::challenge::{self as rule, ChallengeOutcome};
use facegate_service::{LivenessPoint, LivenessPolicy, Matcher, decide};
use facegate_vision::liveness::Liveness;
use facegate_vision::liveness::head_turn::{Step, Turn};
use facegate_vision::pipeline::{FaceAnalysis, Pipeline};

use crate::Progress;
use crate::dataset::imm_photo;

#[path = "challenge_tally.rs"]
mod tally;
#[path = "challenge_video.rs"]
mod video;
use tally::Tally;

/// Where one frame of a sequence comes from: a photo as it is, its mirror image, the photo as a
/// print held turned (and bent), or its fitted head rendered at a yaw.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Source {
    File(PathBuf),
    Mirror(PathBuf),
    /// Turned by `turn` degrees about the vertical axis; bent on a cylinder of radius
    /// `bend_radius` photo widths (0: flat).
    Print {
        path: PathBuf,
        turn: i32,
        bend_radius_pct: u32,
    },
    /// The fitted head of the photo rendered at `yaw` degrees.
    Avatar {
        path: PathBuf,
        yaw: i32,
    },
    /// Another source in grey at a quarter of its size (at least 92 pixels wide): a small old
    /// camera's frame, as UMIST's.
    Grey(Box<Source>),
}

/// One attempt: the enrolled photo, the probe, the frames answering `steps` (for each step, its
/// burst: one frame or several), and its kind.
#[derive(Debug, Clone)]
pub struct Attempt {
    pub kind: String,
    pub person: String,
    pub enrolled: Source,
    pub probe: Source,
    pub steps: Vec<Step>,
    pub frames: Vec<Vec<Source>>,
}

impl Attempt {
    /// One frame per step.
    fn single(kind: &str, person: &str, enrolled: &Source, probe: &Source, steps: &[Step], frames: Vec<Source>) -> Attempt {
        Attempt::bursts(kind, person, enrolled, probe, steps, frames.into_iter().map(|f| vec![f]).collect())
    }

    fn bursts(kind: &str, person: &str, enrolled: &Source, probe: &Source, steps: &[Step], frames: Vec<Vec<Source>>) -> Attempt {
        Attempt {
            kind: kind.to_string(),
            person: person.to_string(),
            enrolled: enrolled.clone(),
            probe: probe.clone(),
            steps: steps.to_vec(),
            frames,
        }
    }
}

/// The data sets and how many challenges each person answers.
#[derive(Debug, Clone)]
pub struct ChallengeEvalConfig {
    pub imm: PathBuf,
    pub umist: PathBuf,
    pub nuaa: PathBuf,
    /// IMM persons to use: the test persons (never trained on) or the training ones (to choose
    /// the limits on).
    pub test_persons: bool,
    pub challenges_per_person: usize,
    pub seed: u64,
    pub threads: usize,
    /// Real video of people turning (`data/video/<clip>/NNNN.jpg`), used with `test_persons`.
    pub video: PathBuf,
}

/// Attempts of one kind and how many passed.
#[derive(Debug, Clone, Serialize)]
pub struct KindRow {
    pub kind: String,
    pub attempts: usize,
    /// Passed the challenge (poses, narrowing, same person, depth, render).
    pub passed_challenge: usize,
    /// Passed the challenge, matched the enrolled subject and the fused passive score was live:
    /// what `--liveness enforce` lets through.
    pub passed_enforce: usize,
    /// Median nose crossing per step of turn ([`facegate_vision::liveness::head_turn::DepthTest::shift`]) and
    /// median z of the attempts whose poses were all right (`None`: none were).
    pub shift_median: Option<f64>,
    pub z_median: Option<f64>,
    /// The first failure reasons, by how often (a few).
    pub reasons: Vec<(String, usize)>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ChallengeReport {
    pub persons: String,
    pub rows: Vec<KindRow>,
    /// The depth test's (shift, z) and the turned steps' largest excess turn (degrees) by kind, of
    /// the attempts whose poses were right.
    pub depth_by_kind: BTreeMap<String, Vec<(f64, f64, f64)>>,
    /// The yaw the pipeline read on each source kind (degrees): min, 5th percentile, median,
    /// 95th percentile, max.
    pub yaw_quantiles: BTreeMap<String, [f32; 5]>,
    /// Mean milliseconds of one photo's analysis (decode to liveness) and of one judgement.
    pub analysis_ms: f64,
    pub judge_ms: f64,
    pub mean_steps: f64,
    /// A challenge taken from the store a second time: how often it was given out (must be 0).
    pub reused_passed: usize,
    pub reused_attempts: usize,
    /// The live sequences refused, by person: how many and the first reason.
    pub live_refused: BTreeMap<String, (usize, String)>,
    /// Live attempts by person and kind: (attempts, passed under enforce).
    pub live_by_person: BTreeMap<String, (usize, usize)>,
}

/// A photo as an opened, decoded image, mirrored, printed or rendered as `source` says.
pub fn render_source(pipeline: &Pipeline, source: &Source) -> Option<Photo> {
    match source {
        Source::File(path) => imaging::open(path).ok(),
        Source::Mirror(path) => imaging::open(path).ok().map(|p| photo_of(image::imageops::flip_horizontal(&p.rgb))),
        Source::Print { path, turn, bend_radius_pct } => {
            let photo = imaging::open(path).ok()?;
            let radius = (*bend_radius_pct > 0).then(|| *bend_radius_pct as f32 / 100.0);
            Some(photo_of(print_held(&photo.rgb, *turn as f32, radius)))
        }
        Source::Avatar { path, yaw } => {
            let photo = imaging::open(path).ok()?;
            let model = pipeline.face_model.as_ref()?;
            let points = pipeline.finder.locate(&photo.gray).ok()?.landmarks.points;
            let fit = model.fit_with(&points, photo.width(), photo.height(), &FitOptions::default()).ok()?;
            let size = photo.height().min(photo.width()) as usize;
            let pose = Pose { yaw: *yaw as f32, ..Default::default() };
            let head = model.render_posed(&photo, &fit, pose, size, size.max(512)).ok()?.image;
            Some(photo_of(on_backdrop(&head, photo.width(), photo.height())))
        }
        Source::Grey(inner) => render_source(pipeline, inner).map(|p| photo_of(grey_small(&p.rgb))),
    }
}

/// `rgb` in grey (as RGB) at a quarter of its size, at least 92 pixels wide.
fn grey_small(rgb: &RgbImage) -> RgbImage {
    let width = (rgb.width() / 4).max(92.min(rgb.width()));
    let height = (rgb.height() * width / rgb.width()).max(1);
    let small = image::imageops::resize(rgb, width, height, image::imageops::FilterType::Triangle);
    RgbImage::from_fn(width, height, |x, y| {
        let [r, g, b] = small.get_pixel(x, y).0.map(f32::from);
        let l = (0.299 * r + 0.587 * g + 0.114 * b).round().clamp(0.0, 255.0) as u8;
        Rgb([l, l, l])
    })
}

fn photo_of(rgb: RgbImage) -> Photo {
    let gray = GrayF32::from_rgb(&rgb);
    Photo { rgb, gray }
}

/// The rendered head (black where nothing was drawn) in the middle of a mid-grey frame of the
/// photo's size: the screen or print an attacker would hold up.
fn on_backdrop(head: &RgbImage, width: u32, height: u32) -> RgbImage {
    let mut out = RgbImage::from_pixel(width, height, Rgb([128, 128, 128]));
    let (ox, oy) = ((width.saturating_sub(head.width())) / 2, (height.saturating_sub(head.height())) / 2);
    for (x, y, p) in head.enumerate_pixels() {
        if p.0 != [0, 0, 0] && x + ox < width && y + oy < height {
            out.put_pixel(x + ox, y + oy, *p);
        }
    }
    out
}

/// `photo` as a sheet held in front of a camera (focal length 1.2 photo widths, the sheet at that
/// distance so that, held straight, it fills the frame as the photo does), turned `turn` degrees
/// about its vertical midline (> 0: its right edge, on the image right, away from the camera, as a
/// head turning to its own left) and, with `bend_radius` (in photo widths), bent on a vertical
/// cylinder bulging towards the camera. Forward-mapped at 3 × 3 samples per pixel; the room
/// behind is mid grey.
pub fn print_held(photo: &RgbImage, turn: f32, bend_radius: Option<f32>) -> RgbImage {
    let (w, h) = (photo.width() as f32, photo.height() as f32);
    let f = 1.2 * w;
    let (s, c) = turn.to_radians().sin_cos();
    let mut out = RgbImage::from_pixel(photo.width(), photo.height(), Rgb([128, 128, 128]));
    let mut depth = vec![f32::INFINITY; (photo.width() * photo.height()) as usize];
    const SUB: usize = 3;
    for sy in 0..photo.height() as usize * SUB {
        for sx in 0..photo.width() as usize * SUB {
            let (px, py) = ((sx as f32 + 0.5) / SUB as f32, (sy as f32 + 0.5) / SUB as f32);
            let (x, y) = (px - w / 2.0, py - h / 2.0);
            // The sheet's point: on the cylinder the arc length x becomes an angle.
            let (xs, zs) = match bend_radius {
                Some(r) => {
                    let r = r * w;
                    (r * (x / r).sin(), -r * (1.0 - (x / r).cos()))
                }
                None => (x, 0.0),
            };
            // Turned about the vertical axis: z grows away from the camera.
            let (xr, zr) = (c * xs - s * zs, s * xs + c * zs);
            let z = f + zr;
            if z <= 1.0 {
                continue;
            }
            let (u, v) = (w / 2.0 + f * xr / z, h / 2.0 + f * y / z);
            if u < 0.0 || v < 0.0 || u >= w || v >= h {
                continue;
            }
            let i = v as usize * photo.width() as usize + u as usize;
            if z < depth[i] {
                depth[i] = z;
                out.put_pixel(u as u32, v as u32, *photo.get_pixel(px as u32, py as u32));
            }
        }
    }
    out
}

/// The IMM persons `config` evaluates: the test persons, or the training ones.
fn imm_persons(config: &ChallengeEvalConfig) -> Vec<u32> {
    (1..=30).filter(|&p| crate::dataset::imm_is_test_person(p) == config.test_persons).collect()
}

/// The frame answering `step` of a live IMM person: views 5 and 1 for the front (alternately), 4
/// turned left, 3 turned right. Not view 6: its "arbitrary expression" is often a grimace, which
/// a person following a challenge on a screen would not make (its yaw reads −25° to 18°).
fn imm_live(dir: &Path, person: u32, turn: Turn, nth: usize) -> Option<Source> {
    let view = match turn {
        Turn::Front => [5, 1][nth % 2],
        Turn::Left => 4,
        Turn::Right => 3,
    };
    imm_photo(dir, person, view).map(Source::File)
}

/// Every attempt the protocol makes of `config`'s persons; `yaw_of` reads a UMIST candidate
/// frame's yaw ([`umist_candidates`]).
pub fn attempts(config: &ChallengeEvalConfig, yaw_of: &dyn Fn(&Source) -> Option<f32>) -> anyhow::Result<Vec<Attempt>> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(config.seed);
    let persons = imm_persons(config);
    let mut out = Vec::new();
    for (k, &person) in persons.iter().enumerate() {
        let (Some(enrolled), Some(probe)) = (imm_photo(&config.imm, person, 1), imm_photo(&config.imm, person, 2)) else { continue };
        let stranger = persons[(k + 1) % persons.len()];
        let name = format!("imm-{person:02}");
        for _ in 0..config.challenges_per_person {
            let steps = rule::draw_steps(&mut rng);
            let (enrolled_source, probe_source) = (Source::File(enrolled.clone()), Source::File(probe.clone()));
            let attempt = |kind: &str, frames: Vec<Source>| Attempt::single(kind, &name, &enrolled_source, &probe_source, &steps, frames);
            let nth_front = |i: usize| steps[..i].iter().filter(|s| s.turn == Turn::Front).count();
            let live: Option<Vec<Source>> =
                steps.iter().enumerate().map(|(i, s)| imm_live(&config.imm, person, s.turn, nth_front(i))).collect();
            let Some(live) = live else { continue };
            out.push(attempt("live", live.clone()));
            out.push(attempt("still photo", vec![Source::File(probe.clone()); steps.len()]));
            let held = |turn_deg: i32, bend: u32| -> Vec<Source> {
                steps
                    .iter()
                    .map(|s| {
                        let turn = match s.turn {
                            Turn::Front => 0,
                            Turn::Left => turn_deg,
                            Turn::Right => -turn_deg,
                        };
                        Source::Print { path: probe.clone(), turn, bend_radius_pct: bend }
                    })
                    .collect()
            };
            for deg in [15, 30, 45, 60] {
                out.push(attempt(print_kind(deg, false), held(deg, 0)));
            }
            for deg in [30, 45] {
                out.push(attempt(print_kind(deg, true), held(deg, 40)));
            }
            let swapped: Vec<Source> = steps
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    let turn = match s.turn {
                        Turn::Left => Turn::Right,
                        Turn::Right => Turn::Left,
                        Turn::Front => Turn::Front,
                    };
                    imm_live(&config.imm, person, turn, nth_front(i)).expect("the live views exist")
                })
                .collect();
            out.push(attempt("wrong order", swapped));
            let turned: Vec<usize> = (0..steps.len()).filter(|&i| steps[i].turn != Turn::Front).collect();
            let replaced = *turned.choose(&mut rng).expect("a turned step");
            let mut with_stranger = live.clone();
            if let Some(other) = imm_live(&config.imm, stranger, steps[replaced].turn, 0) {
                with_stranger[replaced] = other;
                out.push(attempt("stranger in one step", with_stranger));
            }
            let avatar: Vec<Source> = steps
                .iter()
                .map(|s| {
                    let yaw = match s.turn {
                        Turn::Front => 0,
                        Turn::Left => 25,
                        Turn::Right => -25,
                    };
                    Source::Avatar { path: probe.clone(), yaw }
                })
                .collect();
            out.push(attempt("avatar render", avatar));
            // The attacker with the console's own check: each step's frame the first of the
            // print's (or the avatar's) poses, in random order, that `/analyze` reads inside the
            // step's range.
            let mut prints = print_candidates(&probe);
            let frames = steps.iter().map(|step| console_pick(&mut prints, step, &mut rng, yaw_of)).collect();
            out.push(attempt("print turned until in range", frames));
            let mut avatars = avatar_candidates(&probe);
            let frames = steps.iter().map(|step| console_pick(&mut avatars, step, &mut rng, yaw_of)).collect();
            out.push(attempt("avatar turned until in range", frames));
        }
    }
    out.extend(umist_attempts(config, &mut rng, yaw_of)?);
    out.extend(nuaa_attempts(config, &mut rng)?);
    Ok(out)
}

fn print_kind(deg: i32, bent: bool) -> &'static str {
    match (deg, bent) {
        (15, false) => "flat print turned ±15°",
        (30, false) => "flat print turned ±30°",
        (45, false) => "flat print turned ±45°",
        (60, false) => "flat print turned ±60°",
        (30, true) => "bent print turned ±30°",
        _ => "bent print turned ±45°",
    }
}

/// The probe photo as a print held flat or bent, straight or turned by 15° to 60° either way:
/// what an attacker who watches the console's yaw can hold up.
fn print_candidates(probe: &Path) -> Vec<Source> {
    let turns = [-60, -45, -30, -15, 0, 15, 30, 45, 60];
    let bends = [0, 40];
    turns.iter().flat_map(|&turn| bends.map(|bend_radius_pct| Source::Print { path: probe.to_path_buf(), turn, bend_radius_pct })).collect()
}

/// The probe photo's fitted head rendered at 0° and 15° to 45° either way.
fn avatar_candidates(probe: &Path) -> Vec<Source> {
    [-45, -35, -25, -15, 0, 15, 25, 35, 45].map(|yaw| Source::Avatar { path: probe.to_path_buf(), yaw }).to_vec()
}

/// Every frame the attackers with the console's check may send, to be analysed before the
/// attempts are made: the test (or training) IMM persons' probe photos printed and rendered.
fn adaptive_candidates(config: &ChallengeEvalConfig) -> Vec<Source> {
    imm_persons(config)
        .into_iter()
        .filter_map(|p| imm_photo(&config.imm, p, 2))
        .flat_map(|probe| print_candidates(&probe).into_iter().chain(avatar_candidates(&probe)))
        .collect()
}

/// A step's frame as the console takes it: `candidates` tried in a random order, the first whose
/// yaw as `/analyze` reads it (`key_point_pose`) lies in the step's range; when none does, the
/// client's wait runs out and it sends the last one tried.
fn console_pick(
    candidates: &mut [Source],
    step: &Step,
    rng: &mut rand_chacha::ChaCha8Rng,
    yaw_of: &dyn Fn(&Source) -> Option<f32>,
) -> Source {
    candidates.shuffle(rng);
    let found = candidates.iter().find(|c| yaw_of(c).is_some_and(|y| step.admits(y)));
    found.unwrap_or_else(|| candidates.last().expect("candidates")).clone()
}

/// UMIST's photos by person: the enrolled one (18), the probe (19) and the candidates for turned
/// steps (10–17, further turned photos go to the profile) with their mirror images.
fn umist_persons(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<(String, PathBuf, PathBuf, Vec<Source>)>> {
    if !config.test_persons || !config.umist.is_dir() {
        return Ok(Vec::new());
    }
    let mut by_person: BTreeMap<String, Vec<PathBuf>> = BTreeMap::new();
    for p in crate::eval::pose::list_umist(&config.umist)? {
        by_person.entry(p.person.clone()).or_default().push(p.path);
    }
    let mut out = Vec::new();
    for (person, paths) in by_person {
        let at = |index: u32| paths.iter().find(|p| p.file_stem().and_then(|s| s.to_str()) == Some(&format!("{index:02}"))).cloned();
        let (Some(enrolled), Some(probe)) = (at(18), at(19)) else { continue };
        let candidates = (10..=17).filter_map(at).flat_map(|p| [Source::File(p.clone()), Source::Mirror(p)]).collect();
        out.push((person, enrolled, probe, candidates));
    }
    Ok(out)
}

/// Every UMIST candidate frame, to be analysed before the UMIST attempts are made.
pub fn umist_candidates(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<Source>> {
    Ok(umist_persons(config)?.into_iter().flat_map(|(.., c)| c).collect())
}

/// UMIST persons (none was trained on), with the test split: live sequences of drawn challenges
/// without a front step (UMIST has no frontal photo), each step's frame taken as the console
/// takes it: the person's photos and mirror images are tried in a random order and the first
/// whose yaw, as `/analyze` reads it, lies in the step's range is sent; when none does, the
/// client's wait runs out and it sends the last one tried. UMIST's photos are not taken at fixed
/// angles per number (photo 17 reads 3° to 94° across persons), so no photo number names a turn.
fn umist_attempts(
    config: &ChallengeEvalConfig,
    rng: &mut rand_chacha::ChaCha8Rng,
    yaw_of: &dyn Fn(&Source) -> Option<f32>,
) -> anyhow::Result<Vec<Attempt>> {
    let mut out = Vec::new();
    for (person, enrolled, probe, mut candidates) in umist_persons(config)? {
        let mut made = 0;
        while made < config.challenges_per_person {
            let steps = rule::draw_steps(rng);
            if steps.iter().any(|s| s.turn == Turn::Front) {
                continue;
            }
            made += 1;
            let frames = steps.iter().map(|step| console_pick(&mut candidates, step, rng, yaw_of)).collect();
            let (enrolled, probe) = (Source::File(enrolled.clone()), Source::File(probe.clone()));
            out.push(Attempt::single("live", &format!("umist-{person}"), &enrolled, &probe, &steps, frames));
        }
    }
    Ok(out)
}

/// NUAA print captures (subjects 0001–0009; the passive model was trained on them, the challenge
/// rule was not): enrolled with the subject's first live frame, the probe and the steps
/// successive frames of one print capture (held still, moved or bent by hand).
fn nuaa_attempts(config: &ChallengeEvalConfig, rng: &mut rand_chacha::ChaCha8Rng) -> anyhow::Result<Vec<Attempt>> {
    if !config.test_persons || !config.nuaa.is_dir() {
        return Ok(Vec::new());
    }
    let samples = crate::liveness::train::list_nuaa(&config.nuaa)?;
    let mut live_first: BTreeMap<String, PathBuf> = BTreeMap::new();
    let mut captures: BTreeMap<(String, String, String, bool), Vec<PathBuf>> = BTreeMap::new();
    for s in &samples {
        if s.live {
            live_first.entry(s.subject.clone()).or_insert_with(|| s.image.clone());
        } else {
            captures.entry((s.subject.clone(), s.condition.clone(), s.session.clone(), s.glasses)).or_default().push(s.image.clone());
        }
    }
    let mut out = Vec::new();
    let mut per_subject: BTreeMap<String, usize> = BTreeMap::new();
    for ((subject, ..), mut frames) in captures {
        let Some(enrolled) = live_first.get(&subject) else { continue };
        let made = per_subject.entry(subject.clone()).or_default();
        if *made >= config.challenges_per_person || frames.len() < 5 {
            continue;
        }
        *made += 1;
        frames.sort_by_key(|p| nuaa_frame(p));
        let steps = rule::draw_steps(rng);
        // Spread the steps over the capture: the print as the attacker moved it.
        let pick = |i: usize| frames[(i * (frames.len() - 1)) / steps.len()].clone();
        let frames = (1..=steps.len()).map(|i| Source::File(pick(i))).collect();
        let (enrolled, probe) = (Source::File(enrolled.clone()), Source::File(pick(0)));
        out.push(Attempt::single("NUAA print capture", &format!("nuaa-{subject}"), &enrolled, &probe, &steps, frames));
    }
    Ok(out)
}

fn nuaa_frame(path: &Path) -> u32 {
    path.file_stem().and_then(|s| s.to_str()).and_then(|s| s.rsplit('_').next()).and_then(|n| n.parse().ok()).unwrap_or(0)
}

/// Each source's analysis, its time (ms) and its rendered-head check (with `render.bin`).
type Analyses = HashMap<Source, (Option<FaceAnalysis>, f64, Option<Liveness>)>;

/// The analysis of every source, on `threads` threads, with each one's time.
pub fn analyze_sources(pipeline: &Pipeline, mut sources: Vec<Source>, threads: usize, progress: &dyn Progress) -> Analyses {
    sources.sort();
    sources.dedup();
    let analyses = crate::cache::map_samples(&sources, threads, "frames", progress, |source| {
        let Some(photo) = render_source(pipeline, source) else { return (None, 0.0, None) };
        let start = Instant::now();
        let analysis = pipeline.analyze(&photo).ok();
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let rendered = analysis.as_ref().and_then(|a| pipeline.render_check(&photo, a));
        (analysis, ms, rendered)
    });
    sources.into_iter().zip(analyses).collect()
}

/// One attempt judged: the challenge's verdict, whether enforcement would let it through, the
/// judgement's time and, for a passed challenge refused under enforcement, why.
pub fn judge_attempt(
    pipeline: &Pipeline,
    attempt: &Attempt,
    analyses: &Analyses,
) -> Option<(ChallengeOutcome, bool, f64, Option<&'static str>)> {
    let get = |s: &Source| analyses.get(s).and_then(|(a, ..)| a.as_ref());
    let enrolled = get(&attempt.enrolled)?;
    let probe = get(&attempt.probe);
    let bursts: Option<Vec<Vec<&FaceAnalysis>>> = attempt.frames.iter().map(|b| b.iter().map(get).collect()).collect();
    let fmr = facegate_vision::recognize::DEFAULT_FMR;
    let (Some(probe), Some(bursts)) = (probe, bursts) else {
        // A frame without a face is refused (`no-face`): the attempt does not pass.
        let outcome = ChallengeOutcome {
            passed: false,
            reason: Some("a frame shows no face".into()),
            steps: Vec::new(),
            depth: None,
            rendered: None,
        };
        return Some((outcome, false, 0.0, None));
    };
    let start = Instant::now();
    let matcher: &dyn Matcher = pipeline;
    let frames: Vec<&FaceAnalysis> = bursts.iter().flatten().copied().collect();
    let mut next = 0;
    let groups: Vec<Vec<usize>> = bursts
        .iter()
        .map(|b| {
            next += b.len();
            (next - b.len()..next).collect()
        })
        .collect();
    let templates: Vec<&Template> = frames.iter().map(|a| &a.template).collect();
    let mismatch = rule::one_person(matcher, &probe.template, &templates, &groups);
    let rendered: Option<Vec<Liveness>> = attempt.frames.iter().flatten().map(|s| analyses.get(s).and_then(|(.., r)| r.clone())).collect();
    let outcome = rule::judge(&attempt.steps, probe, &bursts, mismatch.as_ref(), rendered.as_deref());
    let judge_ms = start.elapsed().as_secs_f64() * 1e3;
    let matched = decide(matcher, &probe.template, std::slice::from_ref(&enrolled.template), fmr).is_match;
    let each: Option<Vec<_>> = std::iter::once(probe).chain(frames.iter().copied()).map(|a| a.liveness.clone()).collect();
    // The service's own decision under enforce, at the model's operating point.
    let point = pipeline.liveness.as_ref().map(LivenessPoint::of_model);
    let live = facegate_service::liveness::check_challenged_liveness(LivenessPolicy::Enforce, point.as_ref(), each, outcome.passed).is_ok();
    let enforce = outcome.passed && matched && live;
    let refusal = match (outcome.passed, matched, live) {
        (false, ..) => None,
        (true, false, _) => Some("passed the challenge; the probe does not match the enrolled photo"),
        (true, true, false) => Some("passed the challenge; the fused passive score took it for an attack"),
        (true, true, true) => None,
    };
    Some((outcome, enforce, judge_ms, refusal))
}

/// Judge every attempt and tally them by kind.
pub fn evaluate(pipeline: &Pipeline, config: &ChallengeEvalConfig, progress: &dyn Progress) -> anyhow::Result<ChallengeReport> {
    let candidates =
        umist_candidates(config)?.into_iter().chain(adaptive_candidates(config)).chain(video::frame_sources(config)?).collect();
    let mut analyses = analyze_sources(pipeline, candidates, config.threads, progress);
    let clips = {
        let yaw_of = |s: &Source| analyses.get(s).and_then(|(a, ..)| a.as_ref()).and_then(|a| a.key_point_pose).map(|p| p.yaw);
        video::clips(config, &yaw_of)?
    };
    let adaptive = clips.iter().flat_map(|c| video::attack_candidates(&c.probe)).collect();
    analyses.extend(analyze_sources(pipeline, adaptive, config.threads, progress));
    let yaw_of = |s: &Source| analyses.get(s).and_then(|(a, ..)| a.as_ref()).and_then(|a| a.key_point_pose).map(|p| p.yaw);
    let mut attempts = attempts(config, &yaw_of)?;
    attempts.extend(video::attempts(config, &clips, &yaw_of));
    let used = attempts.iter().flat_map(|a| [a.enrolled.clone(), a.probe.clone()].into_iter().chain(a.frames.iter().flatten().cloned()));
    let missing: Vec<Source> = used.filter(|s| !analyses.contains_key(s)).collect();
    analyses.extend(analyze_sources(pipeline, missing, config.threads, progress));
    let mut tally = Tally::default();
    for attempt in &attempts {
        if let Some(judged) = judge_attempt(pipeline, attempt, &analyses) {
            tally.add(attempt, judged);
        }
    }
    let timed: Vec<f64> = analyses.values().filter(|(a, ..)| a.is_some()).map(|(_, ms, _)| *ms).collect();
    let (reused_passed, reused_attempts) = reused_challenges(attempts.len().min(50))?;
    Ok(ChallengeReport {
        persons: if config.test_persons { "test".into() } else { "train".into() },
        rows: tally.rows(),
        depth_by_kind: tally.depth,
        yaw_quantiles: yaw_quantiles(&analyses),
        analysis_ms: timed.iter().sum::<f64>() / timed.len().max(1) as f64,
        judge_ms: tally.judge_ms / tally.judged.max(1) as f64,
        mean_steps: tally.steps as f64 / tally.judged.max(1) as f64,
        reused_passed,
        reused_attempts,
        live_refused: tally.live_refused,
        live_by_person: tally.live_by_person,
    })
}

/// The yaw read on each kind of source: min, 5th percentile, median, 95th percentile, max.
fn yaw_quantiles(analyses: &Analyses) -> BTreeMap<String, [f32; 5]> {
    let mut by: BTreeMap<String, Vec<f32>> = BTreeMap::new();
    for (source, (analysis, ..)) in analyses {
        let Some(yaw) = analysis.as_ref().and_then(|a| a.key_point_pose).map(|p| p.yaw) else { continue };
        let key = match source {
            Source::File(p) | Source::Mirror(p) => {
                let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
                let kind = if p.components().any(|c| c.as_os_str() == "video") {
                    "video frames".to_string()
                } else if name.len() > 4 && name.as_bytes()[2] == b'-' {
                    format!("IMM view {}", &name[3..4])
                } else if name.ends_with(".pgm") {
                    format!("UMIST {}", &name[..2])
                } else {
                    "NUAA frames".into()
                };
                if matches!(source, Source::Mirror(_)) { format!("{kind} mirrored") } else { kind }
            }
            Source::Print { turn, bend_radius_pct, .. } => {
                format!("print {} turned {turn:+}°", if *bend_radius_pct > 0 { "bent" } else { "flat" })
            }
            Source::Avatar { yaw, .. } => format!("avatar rendered at {yaw:+}°"),
            Source::Grey(_) => "grey, small".to_string(),
        };
        by.entry(key).or_default().push(yaw);
    }
    by.into_iter()
        .map(|(k, mut v)| {
            v.sort_by(f32::total_cmp);
            let at = |p: f32| v[((v.len() - 1) as f32 * p).round() as usize];
            (k, [at(0.0), at(0.05), at(0.5), at(0.95), at(1.0)])
        })
        .collect()
}

/// Challenges issued into a fresh SQLite store, each taken once as a verification would and then
/// presented again: how many of the second takes were given a challenge.
fn reused_challenges(n: usize) -> anyhow::Result<(usize, usize)> {
    let path = std::env::temp_dir().join(format!("facegate-eval-challenges-{}.db", std::process::id()));
    let _ = std::fs::remove_file(&path);
    let url = format!("sqlite://{}?mode=rwc", path.display());
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    runtime
        .block_on(async {
            let store = facegate_store::Store::connect(&url, None).await?;
            let mut rng = rand::rng();
            let mut passed = 0;
            for _ in 0..n {
                let id = rule::new_challenge_id(&mut rng);
                store.insert_challenge(&id, "[]", i64::MAX, 0).await?;
                anyhow::ensure!(store.take_challenge(&id).await?.is_some(), "a fresh challenge was not found");
                passed += store.take_challenge(&id).await?.is_some() as usize;
            }
            store.close().await;
            Ok::<_, anyhow::Error>((passed, n))
        })
        .inspect(|_| {
            let _ = std::fs::remove_file(&path);
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn striped(width: u32, height: u32) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| Rgb([(x * 7 % 256) as u8, (y * 5 % 256) as u8, 200]))
    }

    #[test]
    fn a_print_held_straight_is_the_photo_and_turned_it_narrows() {
        let photo = striped(120, 90);
        assert_eq!(print_held(&photo, 0.0, None), photo, "held straight at the focal distance: the photo itself");
        let turned = print_held(&photo, 45.0, None);
        let grey = |x: u32| (0..90).all(|y| turned.get_pixel(x, y).0 == [128, 128, 128]);
        assert!(grey(119), "the receding edge no longer reaches the frame's edge");
        assert!(!grey(60), "its middle is still there");
        // Turned > 0 (as a head turning to its own left): the right half recedes, so it is narrower
        // than the left, which comes nearer.
        let width = |from: u32, to: u32| (from..to).filter(|&x| !grey(x)).count();
        assert!(width(60, 120) < width(0, 60), "{} {}", width(0, 60), width(60, 120));
        // Bent, the sheet's edges curl away and it narrows even held straight.
        let bent = print_held(&photo, 0.0, Some(0.4));
        assert_ne!(bent, photo);
        assert_eq!(bent.get_pixel(0, 45).0, [128, 128, 128]);
    }

    #[test]
    fn every_attempt_answers_its_steps_and_live_frames_follow_the_turns() {
        let shared = facegate_paths::shared_dir();
        let config = ChallengeEvalConfig {
            imm: shared.join("data/imm"),
            umist: shared.join("data/umist"),
            nuaa: shared.join("data/nuaa"),
            test_persons: true,
            challenges_per_person: 2,
            seed: 3,
            threads: 1,
            video: shared.join("data/video"),
        };
        // A stand-in for `/analyze`: a print reads half its turn, an avatar its render's yaw.
        let yaw_of = |s: &Source| match s {
            Source::Print { turn, .. } => Some(*turn as f32 / 2.0),
            Source::Avatar { yaw, .. } => Some(*yaw as f32),
            _ => Some(20.0),
        };
        let attempts = attempts(&config, &yaw_of).unwrap();
        let kinds: std::collections::BTreeSet<&str> = attempts.iter().map(|a| a.kind.as_str()).collect();
        for kind in [
            "live",
            "still photo",
            "wrong order",
            "stranger in one step",
            "avatar render",
            "NUAA print capture",
            "flat print turned ±30°",
            "print turned until in range",
            "avatar turned until in range",
        ] {
            assert!(kinds.contains(kind), "{kind} missing from {kinds:?}");
        }
        for a in &attempts {
            assert_eq!(a.frames.len(), a.steps.len(), "{a:?}");
            assert!(a.frames.iter().all(|b| b.len() == 1), "IMM, UMIST and NUAA answer one frame a step: {a:?}");
            let frames: Vec<&Source> = a.frames.iter().flatten().collect();
            if a.kind.ends_with("until in range") {
                // Every step has a candidate inside its range here, and the attacker sends it.
                for (step, frame) in a.steps.iter().zip(frames.iter().copied()) {
                    assert!(step.admits(yaw_of(frame).unwrap()), "{step:?} answered by {frame:?}");
                }
            }
            if a.kind == "live" && a.person.starts_with("imm-") {
                for (step, frame) in a.steps.iter().zip(frames.iter().copied()) {
                    let Source::File(path) = frame else { panic!("{frame:?}") };
                    let view = path.file_name().unwrap().to_str().unwrap().as_bytes()[3];
                    let expected: &[u8] = match step.turn {
                        Turn::Front => b"15",
                        Turn::Left => b"4",
                        Turn::Right => b"3",
                    };
                    assert!(expected.contains(&view), "{step:?} answered by {}", path.display());
                }
            }
            if a.person.starts_with("umist-") {
                assert!(a.steps.iter().all(|s| s.turn != Turn::Front), "UMIST has no frontal photo: {a:?}");
            }
        }
        // Persons never trained on only.
        assert!(
            attempts
                .iter()
                .filter(|a| a.person.starts_with("imm-"))
                .all(|a| { crate::dataset::imm_is_test_person(a.person[4..].parse().unwrap()) })
        );
    }
}
