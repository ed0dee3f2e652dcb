//! Training the rendered-head detector (`facegate train render` → `models/render.bin`): a face
//! seen by a camera against a 3D head rendered from one photo, the attack the head-turn
//! challenge's depth test cannot tell from a head (a good render turns like one). Renders are
//! made as an attacker with facegate would make them (`frontalize --yaw`: the photo's fitted,
//! textured 3DMM head at a yaw, on a plain backdrop, [`crate::liveness::challenge::render_source`]);
//! the features are the passive liveness model's ([`facegate_vision::liveness::features`], the
//! same blocks), the fit the same ridge-penalised logistic regression
//! ([`crate::logistic::fit_binary`]), calibrated by Platt on person-fold out-of-fold
//! logits.
//!
//! Data, training persons only: the IMM training persons' six views and their mirror images
//! (camera faces) and their views 1 and 2 rendered from −45° to 45°; their turned views (and
//! mirror images) in grey at a quarter of their size against small grey renders at ±25°, ±45°; the ORL training subjects'
//! ten grey photos and their photos 1 and 2 rendered at ±15° and ±30°; LFW training persons' first
//! photos (camera faces) and every other one of them rendered at ±15° and ±30°; UMIST's training
//! persons (s01–s05) every photo and mirror image against their photos 16–19 rendered at ±15°,
//! ±30°, ±45°. IMM's, ORL's and UMIST's test persons, LFW's other persons and every video clip
//! are never used.

use std::path::PathBuf;

use facegate_vision::liveness::features::{crops, features};
use facegate_vision::liveness::{Block, LivenessModel};
use facegate_vision::pipeline::Pipeline;
use serde::Serialize;

use crate::Progress;
use crate::cache::map_samples;
use crate::liveness::challenge::{Source, render_source};
use crate::liveness::train::{balanced_weights, model};
use crate::logistic::{fit_binary, platt, platt_probability};

/// The ridge penalty per unit of total weight (the passive model's).
const RIDGE: f64 = 1e-2;
/// Yaws the IMM training persons' frontal views are rendered at.
const IMM_YAWS: [i32; 9] = [-45, -35, -25, -15, 0, 15, 25, 35, 45];
/// Yaws the LFW training persons' photos (and ORL's photos 1 and 2) are rendered at.
const LFW_YAWS: [i32; 4] = [-30, -15, 15, 30];
/// Yaws UMIST's training persons' least turned photos are rendered at: a turned step's range.
const UMIST_YAWS: [i32; 6] = [-45, -30, -15, 15, 30, 45];
/// UMIST's least turned photos (about 30°–45°), the ones rendered.
const UMIST_RENDERED: std::ops::RangeInclusive<u32> = 16..=19;
/// Person folds for the out-of-fold logits Platt's calibration is fitted on.
const FOLDS: u64 = 3;

#[derive(Debug, Clone)]
pub struct RenderTrainConfig {
    pub imm: PathBuf,
    /// ORL's grey 92 × 112 photos: a camera face need not be in colour or large.
    pub orl: PathBuf,
    pub lfw: PathBuf,
    /// UMIST's grey 92 × 112 photos of heads turned from 30° to profile: its training persons
    /// ([`crate::dataset::umist_is_test_person`]) are the small grey camera the others are not.
    pub umist: PathBuf,
    /// LFW training persons taken (their first photo each).
    pub lfw_persons: usize,
    pub threads: usize,
}

/// One training photo: where it comes from, whether a camera saw it, and whose it is.
#[derive(Debug, Clone)]
pub struct RenderSample {
    pub source: Source,
    pub camera: bool,
    /// Not one of IMM's large colour photos (ORL, LFW, UMIST, or an IMM photo made grey and
    /// small): the half of each class's weight that is not IMM's studio camera.
    pub not_imm_colour: bool,
    pub person: String,
}

/// What the training saw and how well the out-of-fold scores separate.
#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    pub camera_faces: usize,
    pub renders: usize,
    pub without_face: usize,
    /// Out of fold (persons unseen by the fold's fit), at even odds: camera faces taken for
    /// renders, renders taken for camera faces.
    pub oof_camera_refused: f64,
    pub oof_renders_passed: f64,
}

/// The training photos of `config`.
pub fn samples(config: &RenderTrainConfig) -> anyhow::Result<Vec<RenderSample>> {
    let mut out = Vec::new();
    let sample = |source, camera, not_imm_colour, person: &str| RenderSample { source, camera, not_imm_colour, person: person.to_string() };
    for person in (1..=40).filter(|&p| !crate::dataset::imm_is_test_person(p)) {
        let name = format!("imm-{person:02}");
        for view in 1..=6 {
            let Some(path) = crate::dataset::imm_photo(&config.imm, person, view) else { continue };
            out.push(sample(Source::File(path.clone()), true, false, &name));
            out.push(sample(Source::Mirror(path.clone()), true, false, &name));
            if view <= 2 {
                out.extend(IMM_YAWS.iter().map(|&yaw| sample(Source::Avatar { path: path.clone(), yaw }, false, false, &name)));
                // Small grey renders, against the small grey turned views below: size and colour
                // are not what tells a render.
                let grey_render = |yaw| Source::Grey(Box::new(Source::Avatar { path: path.clone(), yaw }));
                out.extend([-45, -25, 25, 45].map(|yaw| sample(grey_render(yaw), false, true, &name)));
            }
            if view == 3 || view == 4 {
                out.push(sample(Source::Grey(Box::new(Source::File(path.clone()))), true, true, &name));
                out.push(sample(Source::Grey(Box::new(Source::Mirror(path.clone()))), true, true, &name));
            }
        }
    }
    for person in (1..=40).filter(|&p| !crate::dataset::imm_is_test_person(p)) {
        let name = format!("orl-s{person}");
        for view in 1..=10 {
            let path = config.orl.join(format!("s{person}")).join(format!("{view}.pgm"));
            if !path.is_file() {
                continue;
            }
            out.push(sample(Source::File(path.clone()), true, true, &name));
            if view <= 2 {
                out.extend(LFW_YAWS.iter().map(|&yaw| sample(Source::Avatar { path: path.clone(), yaw }, false, true, &name)));
            }
        }
    }
    out.extend(umist_samples(&config.umist)?);
    let mut persons: Vec<PathBuf> =
        std::fs::read_dir(&config.lfw)?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    persons.sort();
    let train = persons
        .into_iter()
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| crate::dataset::lfw_split(n) == crate::dataset::Split::Train));
    for (k, dir) in train.take(config.lfw_persons).enumerate() {
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("").to_string();
        let mut photos: Vec<PathBuf> = std::fs::read_dir(&dir)?.filter_map(|e| e.ok().map(|e| e.path())).collect();
        photos.sort();
        let Some(first) = photos.into_iter().next() else { continue };
        out.push(sample(Source::File(first.clone()), true, true, &name));
        if k % 2 == 0 {
            out.extend(LFW_YAWS.iter().map(|&yaw| sample(Source::Avatar { path: first.clone(), yaw }, false, true, &name)));
        }
    }
    Ok(out)
}

/// UMIST's training persons: every photo and its mirror image (camera faces) against the least
/// turned ones rendered across a turned step's range. None when UMIST is absent.
fn umist_samples(dir: &std::path::Path) -> anyhow::Result<Vec<RenderSample>> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for path in crate::liveness::train::list_umist(dir)? {
        let person = path.parent().and_then(|p| p.file_name()).and_then(|n| n.to_str()).unwrap_or("").to_string();
        if crate::dataset::umist_is_test_person(&person) {
            continue;
        }
        let number = path.file_stem().and_then(|s| s.to_str()).and_then(|s| s.parse::<u32>().ok()).unwrap_or(0);
        let name = format!("umist-{person}");
        let sample = |source, camera| RenderSample { source, camera, not_imm_colour: true, person: name.clone() };
        out.push(sample(Source::File(path.clone()), true));
        out.push(sample(Source::Mirror(path.clone()), true));
        if UMIST_RENDERED.contains(&number) {
            out.extend(UMIST_YAWS.map(|yaw| sample(Source::Avatar { path: path.clone(), yaw }, false)));
        }
    }
    Ok(out)
}

/// Each sample's liveness features of `blocks` at its landmarks' eye and mouth centres; `None`
/// where no face was found (or the render failed).
pub fn sample_features(
    pipeline: &Pipeline,
    samples: &[RenderSample],
    blocks: &[Block],
    threads: usize,
    progress: &dyn Progress,
) -> Vec<Option<Vec<f32>>> {
    map_samples(samples, threads, "render features", progress, |s| {
        let photo = render_source(pipeline, &s.source)?;
        let centres = pipeline.finder.locate(&photo.gray).ok()?.landmarks.centres;
        Some(features(&crops(&photo.rgb, &centres), blocks))
    })
}

fn fold_of(person: &str) -> u64 {
    use sha2::Digest;
    u64::from(sha2::Sha256::digest(person.as_bytes())[0]) % FOLDS
}

/// The detector fitted on every sample, with Platt's calibration from person-fold out-of-fold
/// logits, and what the folds measured.
pub fn train(pipeline: &Pipeline, config: &RenderTrainConfig, progress: &dyn Progress) -> anyhow::Result<(LivenessModel, RenderReport)> {
    let blocks = pipeline.liveness.as_ref().map_or_else(|| Block::ALL.to_vec(), |m| m.blocks.clone());
    let all = samples(config)?;
    let features = sample_features(pipeline, &all, &blocks, config.threads, progress);
    let kept: Vec<(&RenderSample, &Vec<f32>)> = all.iter().zip(&features).filter_map(|(s, f)| Some((s, f.as_ref()?))).collect();
    anyhow::ensure!(kept.iter().any(|(s, _)| s.camera) && kept.iter().any(|(s, _)| !s.camera), "no camera face or no render was read");
    let fit_on = |rows: &[&(&RenderSample, &Vec<f32>)]| {
        let x: Vec<&[f32]> = rows.iter().map(|(_, f)| f.as_slice()).collect();
        let camera: Vec<bool> = rows.iter().map(|(s, _)| s.camera).collect();
        let not_imm_colour: Vec<bool> = rows.iter().map(|(s, _)| s.not_imm_colour).collect();
        fit_binary(&x, &camera, &balanced_weights(&camera, &not_imm_colour), RIDGE)
    };
    let mut oof = vec![0.0f32; kept.len()];
    for fold in 0..FOLDS {
        let train: Vec<&(&RenderSample, &Vec<f32>)> = kept.iter().filter(|(s, _)| fold_of(&s.person) != fold).collect();
        let fit = fit_on(&train);
        for (i, (s, f)) in kept.iter().enumerate() {
            if fold_of(&s.person) == fold {
                oof[i] = fit.logit(f);
            }
        }
    }
    let camera: Vec<bool> = kept.iter().map(|(s, _)| s.camera).collect();
    let calibration = platt(&oof, &camera);
    let rate = |want_camera: bool, wrong: &dyn Fn(f32) -> bool| {
        let picked: Vec<f32> =
            oof.iter().zip(&camera).filter(|(_, c)| **c == want_camera).map(|(l, _)| platt_probability(calibration, *l)).collect();
        picked.iter().filter(|p| wrong(**p)).count() as f64 / picked.len().max(1) as f64
    };
    let report = RenderReport {
        camera_faces: camera.iter().filter(|c| **c).count(),
        renders: camera.iter().filter(|c| !**c).count(),
        without_face: all.len() - kept.len(),
        oof_camera_refused: rate(true, &|p| p < 0.5),
        oof_renders_passed: rate(false, &|p| p >= 0.5),
    };
    let everything: Vec<&(&RenderSample, &Vec<f32>)> = kept.iter().collect();
    let detector = model(
        "render-lbp-1",
        &blocks,
        fit_on(&everything),
        calibration,
        0.5,
        "even odds (classes weighted equally)".to_string(),
        format!(
            "IMM training persons' photos and mirror images against their views 1-2 rendered at ±45° (3DMM head of the photo), ORL training subjects' photos against renders of photos 1-2 at ±15°, ±30°, {} LFW training persons' first photos against renders at ±15°, ±30°, UMIST s01-s05's photos against renders of photos 16-19 at ±15°, ±30°, ±45°; `facegate train render`",
            config.lfw_persons
        ),
    );
    Ok((detector, report))
}
