//! The head-turn liveness challenge under attack (`facegate eval challenge`), ISO/IEC 30107-3
//! style: for persons never used in training, live sequences made from their own photos against
//! each attack type, every capture judged by the service's own rule
//! ([`facegate_service::challenge::judge`]) on the runtime's one pipeline. Reports BPCER of the
//! live sequences and APCER per attack, with and without the passive score, the depth test's
//! distributions the limits are read from, and the CPU of a challenge. The attempts on photos
//! are [`attempts`]'s, how each of their frames is made [`frames`]'s, the video clips' captures
//! and attacks (in bursts) [`video`]'s, and the counting by kind [`tally`]'s.
//!
//! Live: IMM (enrolled with view 1, the probe view 2, front steps views 5 and 1, left view 4,
//! right view 3) and UMIST's test persons s06–s10 (enrolled with photo 18, the probe photo 19,
//! turned steps drawn among photos 10–17 and their mirror images; UMIST turns to one side and has
//! no frontal photo, so its challenges are the drawn ones without a front step). UMIST's
//! probe photo's head rendered at whichever yaw reads inside each step's range is its attack.
//! Attacks on IMM persons: the probe photo held still; the probe photo as a flat print turned by
//! ±15…60° (perspective warp) or bent on a cylinder and turned;
//! the right photos in the wrong order (left and right exchanged); another person's photo in one
//! turned step; the probe photo's fitted 3D head rendered at each step's yaw (`frontalize
//! --yaw`); and the attacker who watches the console's yaw, holding the print (or rendering the
//! head) at whichever of several angles reads inside each step's range. NUAA: each print
//! capture's frames (the print moved or bent by hand) as the steps. The
//! reused challenge is refused by the store (taken once) and is measured there.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use facegate_core::template::Template;
use facegate_service::challenge::{self as rule, ChallengeOutcome};
use facegate_service::{LivenessPoint, LivenessPolicy, Matcher, decide};
use facegate_vision::liveness::Liveness;
use facegate_vision::pipeline::{FaceAnalysis, Pipeline};

use crate::Progress;

#[path = "challenge_attempts.rs"]
mod attempts;
#[path = "challenge_frames.rs"]
mod frames;
#[path = "challenge_strangers.rs"]
mod strangers;
#[path = "challenge_tally.rs"]
mod tally;
#[path = "challenge_video.rs"]
mod video;
use attempts::adaptive_candidates;
pub use attempts::{Attempt, attempts, umist_candidates};
pub use frames::{Source, print_held, render_source};
pub use strangers::{StrangerSteps, stranger_steps};
use tally::Tally;

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
    /// LFW (`data/lfw/<person>/*.jpg`): its test persons' photos make the captures and strangers
    /// of [`StrangerSteps`], with `test_persons`.
    pub lfw: PathBuf,
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
    /// The rendered-head detector's score (probability of a camera's face) on each kind of
    /// frame by data set (camera photos and frames, rendered heads, prints): min, 5th percentile,
    /// median, 95th percentile, max. A frame passes at `challenge::RENDER_MIN`.
    pub render_quantiles: BTreeMap<String, [f32; 5]>,
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
    /// Per video clip, its frames whose largest face is another person's (left out of its live
    /// captures: `challenge_video::followed`).
    pub video_other_faces: BTreeMap<String, usize>,
    /// A stranger's photo in one step at scale: LFW's test persons' captures against every other
    /// person's photo (`None` with the training persons, or without LFW).
    pub stranger_steps: Option<StrangerSteps>,
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
        let face_of = |s: &Source| analyses.get(s).and_then(|(a, ..)| a.as_ref()).map(|a| a.face.rect);
        video::clips(config, &yaw_of, &face_of)?
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
    let stranger_steps =
        if config.test_persons && config.lfw.is_dir() { Some(lfw_stranger_steps(pipeline, config, progress)?) } else { None };
    Ok(ChallengeReport {
        persons: if config.test_persons { "test".into() } else { "train".into() },
        rows: tally.rows(),
        depth_by_kind: tally.depth,
        yaw_quantiles: yaw_quantiles(&analyses),
        render_quantiles: render_quantiles(&analyses),
        analysis_ms: timed.iter().sum::<f64>() / timed.len().max(1) as f64,
        judge_ms: tally.judge_ms / tally.judged.max(1) as f64,
        mean_steps: tally.steps as f64 / tally.judged.max(1) as f64,
        reused_passed,
        reused_attempts,
        live_refused: tally.live_refused,
        live_by_person: tally.live_by_person,
        video_other_faces: clips.iter().map(|c| (c.name.clone(), c.other_faces)).collect(),
        stranger_steps,
    })
}

/// [`stranger_steps`] on LFW's test persons' photos, each analysed by the pipeline.
fn lfw_stranger_steps(pipeline: &Pipeline, config: &ChallengeEvalConfig, progress: &dyn Progress) -> anyhow::Result<StrangerSteps> {
    use crate::dataset::{Split, lfw_split, list_labelled};
    let photos: Vec<(String, PathBuf)> = list_labelled(&config.lfw)?
        .into_iter()
        .filter(|p| p.label.strip_prefix("lfw-").is_some_and(|person| lfw_split(person) == Split::Test))
        .map(|p| (p.label, p.image))
        .collect();
    let analyses = analyze_sources(pipeline, photos.iter().map(|(_, path)| Source::File(path.clone())).collect(), config.threads, progress);
    let templates: Vec<(String, String, Template)> = photos
        .into_iter()
        .filter_map(|(person, path)| {
            let name = path.file_name()?.to_string_lossy().to_string();
            let (analysis, ..) = analyses.get(&Source::File(path))?;
            Some((person, name, analysis.as_ref()?.template.clone()))
        })
        .collect();
    Ok(stranger_steps(pipeline, &templates))
}

/// The yaw read on each kind of source: min, 5th percentile, median, 95th percentile, max.
fn yaw_quantiles(analyses: &Analyses) -> BTreeMap<String, [f32; 5]> {
    let mut by: BTreeMap<String, Vec<f32>> = BTreeMap::new();
    for (source, (analysis, ..)) in analyses {
        let Some(yaw) = analysis.as_ref().and_then(|a| a.key_point_pose).map(|p| p.yaw) else { continue };
        let key = match source {
            Source::File(p) | Source::Mirror(p) => {
                let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
                let kind = match data_set(p) {
                    "video" => "video frames".to_string(),
                    "IMM" => format!("IMM view {}", name.get(3..4).unwrap_or("?")),
                    "UMIST" => format!("UMIST {}", name.get(..2).unwrap_or("?")),
                    other => format!("{other} frames"),
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
    quantiles(by)
}

/// The rendered-head detector's score on each kind of source, by data set.
fn render_quantiles(analyses: &Analyses) -> BTreeMap<String, [f32; 5]> {
    let mut by: BTreeMap<String, Vec<f32>> = BTreeMap::new();
    for (source, (.., rendered)) in analyses {
        let Some(rendered) = rendered else { continue };
        by.entry(render_kind(source)).or_default().push(rendered.score);
    }
    quantiles(by)
}

/// The data set a photo lies in, by its folder: `video`, `UMIST`, `ORL`, `NUAA` or `IMM`.
fn data_set(path: &std::path::Path) -> &'static str {
    let under = |folder: &str| path.components().any(|c| c.as_os_str() == folder);
    if under("video") {
        "video"
    } else if path.extension().is_some_and(|e| e == "pgm") {
        if under("umist") { "UMIST" } else { "ORL" }
    } else if under("nuaa") {
        "NUAA"
    } else {
        "IMM"
    }
}

/// A source's data set and what it shows: a camera's photo, a rendered head, a print, or a grey
/// small copy.
fn render_kind(source: &Source) -> String {
    match source {
        Source::File(p) | Source::Mirror(p) => format!("{} camera", data_set(p)),
        Source::Print { path, .. } => format!("{} print", data_set(path)),
        Source::Avatar { path, .. } => format!("{} rendered head", data_set(path)),
        Source::Grey(inner) => format!("{} grey, small", render_kind(inner)),
    }
}

/// Min, 5th percentile, median, 95th percentile and max of each key's values.
fn quantiles(by: BTreeMap<String, Vec<f32>>) -> BTreeMap<String, [f32; 5]> {
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
