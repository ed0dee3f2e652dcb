//! The attempts of the challenge's protocol on photos (module documentation of [`super`]): the
//! live sequences of IMM and UMIST persons, the attacks on IMM persons (prints, the wrong order,
//! a stranger, rendered heads, and the attacker who watches the console's yaw), UMIST persons'
//! rendered heads, and NUAA's print captures.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand::seq::{IndexedRandom, SliceRandom};

use facegate_service::challenge as rule;
use facegate_vision::liveness::head_turn::{Step, Turn};

use super::{ChallengeEvalConfig, Source};
use crate::dataset::imm_photo;

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
    pub(super) fn single(kind: &str, person: &str, enrolled: &Source, probe: &Source, steps: &[Step], frames: Vec<Source>) -> Attempt {
        Attempt::bursts(kind, person, enrolled, probe, steps, frames.into_iter().map(|f| vec![f]).collect())
    }

    pub(super) fn bursts(kind: &str, person: &str, enrolled: &Source, probe: &Source, steps: &[Step], frames: Vec<Vec<Source>>) -> Attempt {
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

/// The IMM persons `config` evaluates: the test persons (with 31–40 where their photos are
/// given), or the training ones.
fn imm_persons(config: &ChallengeEvalConfig) -> Vec<u32> {
    (1..=40)
        .filter(|&p| crate::dataset::imm_is_test_person(p) == config.test_persons)
        .filter(|&p| imm_photo(&config.imm, p, 1).is_some())
        .collect()
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
pub(super) fn adaptive_candidates(config: &ChallengeEvalConfig) -> Vec<Source> {
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

/// UMIST's test persons' photos by person: the enrolled one (18), the probe (19) and the
/// candidates for turned steps (10–17, further turned photos go to the profile) with their mirror
/// images. Persons s01–s05 trained the rendered-head detector and are left out.
fn umist_persons(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<(String, PathBuf, PathBuf, Vec<Source>)>> {
    if !config.test_persons || !config.umist.is_dir() {
        return Ok(Vec::new());
    }
    let mut by_person: BTreeMap<String, Vec<PathBuf>> = BTreeMap::new();
    for p in crate::eval::pose::list_umist(&config.umist)? {
        if crate::dataset::umist_is_test_person(&p.person) {
            by_person.entry(p.person.clone()).or_default().push(p.path);
        }
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

/// Every UMIST candidate frame, to be analysed before the UMIST attempts are made: the persons'
/// photos and their probe photos' rendered heads.
pub fn umist_candidates(config: &ChallengeEvalConfig) -> anyhow::Result<Vec<Source>> {
    Ok(umist_persons(config)?.into_iter().flat_map(|(_, _, probe, c)| c.into_iter().chain(avatar_candidates(&probe))).collect())
}

/// UMIST's test persons, with the test split: live sequences of drawn challenges without a front
/// step (UMIST has no frontal photo), each step's frame taken as the console takes it: the
/// person's photos and mirror images are tried in a random order and the first whose yaw, as
/// `/analyze` reads it, lies in the step's range is sent; when none does, the client's wait runs
/// out and it sends the last one tried. UMIST's photos are not taken at fixed angles per number
/// (photo 17 reads 3° to 94° across persons), so no photo number names a turn. Against each
/// challenge, the attacker who renders the probe photo's head at the yaws the console wants.
fn umist_attempts(
    config: &ChallengeEvalConfig,
    rng: &mut rand_chacha::ChaCha8Rng,
    yaw_of: &dyn Fn(&Source) -> Option<f32>,
) -> anyhow::Result<Vec<Attempt>> {
    let mut out = Vec::new();
    for (person, enrolled, probe, mut candidates) in umist_persons(config)? {
        let mut avatars = avatar_candidates(&probe);
        let mut made = 0;
        while made < config.challenges_per_person {
            let steps = rule::draw_steps(rng);
            if steps.iter().any(|s| s.turn == Turn::Front) {
                continue;
            }
            made += 1;
            let frames = steps.iter().map(|step| console_pick(&mut candidates, step, rng, yaw_of)).collect();
            let rendered = steps.iter().map(|step| console_pick(&mut avatars, step, rng, yaw_of)).collect();
            let (enrolled, probe) = (Source::File(enrolled.clone()), Source::File(probe.clone()));
            let name = format!("umist-{person}");
            out.push(Attempt::single("live", &name, &enrolled, &probe, &steps, frames));
            out.push(Attempt::single("avatar turned until in range (UMIST)", &name, &enrolled, &probe, &steps, rendered));
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

#[cfg(test)]
mod tests {
    use super::*;

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
            lfw: shared.join("data/lfw"),
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
            "avatar turned until in range (UMIST)",
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
            if let Some(person) = a.person.strip_prefix("umist-") {
                assert!(a.steps.iter().all(|s| s.turn != Turn::Front), "UMIST has no frontal photo: {a:?}");
                assert!(crate::dataset::umist_is_test_person(person), "{person} trained the render detector");
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
