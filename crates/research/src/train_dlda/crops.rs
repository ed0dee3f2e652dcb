//! Geometric crops of the photos on each normalisation path and their 3DMM re-posed copies (both
//! through the research cache, [`crate::cache`], when given one), and which photos and copies
//! `train dlda` trains on ([`training_crops`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::*;
use crate::Progress;
use crate::cache::{self, CacheKey, map_samples};
use facegate_core::imaging::GrayF32;
use facegate_morph::Pose;
use facegate_vision::pipeline::recognition_input;
use facegate_vision::recognize::Normalization;
use facegate_vision::recognize::normalize::{self, NormalizeParams};

/// A photo after geometric normalisation (photometric normalisation is part of the model).
#[derive(Debug, Clone)]
pub struct AlignedFace {
    pub face: FaceImage,
    pub crop: GrayF32,
    /// The crop on the second path of a fused model (see [`align_paths`]).
    pub secondary_crop: Option<GrayF32>,
    pub pose: Option<Pose>,
    pub centre_source: &'static str,
    /// 3DMM re-posed copies of the face ([`attach_reposed_crops`]), used as extra training samples of
    /// its person: per copy, the crop on the primary path and on the second path.
    pub reposed: Vec<(GrayF32, Option<GrayF32>)>,
}

/// One face's crop as the front end made it: what the crop cache keeps per photo.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct FaceCrop {
    width: usize,
    height: usize,
    data: Vec<f32>,
    pose: Option<Pose>,
    #[serde(rename = "keypoint_source")]
    centre_source: String,
}

/// The centre source's name as [`Prepared::centre_source`] gives it.
fn source_name(s: &str) -> &'static str {
    match s {
        "imm-annotations" => "imm-annotations",
        "pipeline" => "pipeline",
        _ => "detector-box",
    }
}

/// The geometric crop of each of `faces`, on the front end's threads; `None` where the front end
/// fails (reported).
fn crop_faces(
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> Vec<Option<FaceCrop>> {
    map_samples(faces, front_end.threads, "aligning", progress, |face| match front_end.prepare(face, normalization) {
        Ok(p) => {
            let crop = normalize::geometric(&p.gray, &p.centres, params);
            let centre_source = p.centre_source.to_string();
            Some(FaceCrop { width: crop.width, height: crop.height, data: crop.data, pose: p.pose, centre_source })
        }
        Err(e) => {
            progress.note(&format!("warning: {}: skipped ({e})", face.image.display()));
            None
        }
    })
}

/// The faces that have a crop, with it.
fn assemble(faces: &[FaceImage], crops: Vec<Option<FaceCrop>>) -> Vec<AlignedFace> {
    faces
        .iter()
        .zip(crops)
        .filter_map(|(face, crop)| {
            let c = crop?;
            Some(AlignedFace {
                face: face.clone(),
                crop: GrayF32 { width: c.width, height: c.height, data: c.data },
                secondary_crop: None,
                pose: c.pose,
                centre_source: source_name(&c.centre_source),
                reposed: Vec::new(),
            })
        })
        .collect()
}

/// Geometric crops of all `faces` on the front end's threads (photos whose front end fails are
/// reported and left out).
pub fn align_all(
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> Vec<AlignedFace> {
    assemble(faces, crop_faces(front_end, faces, normalization, params, progress))
}

/// What names a face in a crop cache key: its photo's path, and whether an annotation is beside it.
fn cache_id(face: &FaceImage) -> String {
    format!("{}{}", face.image.display(), if face.asf.is_some() { " +asf" } else { "" })
}

/// The key of `kind` crops of `faces` by `front_end` under `settings`: the front end's model files
/// and centre source, the settings, the faces (see [`crate::cache`]).
fn crops_key(kind: &str, front_end: &FrontEnd, settings: &impl Serialize, faces: &[FaceImage]) -> anyhow::Result<CacheKey> {
    let settings = postcard::to_stdvec(&(front_end.source, settings))?;
    Ok(CacheKey::new(kind, &front_end.model_files(), &settings, faces.iter().map(cache_id)))
}

/// [`align_all`] through the research cache in `dir` ([`crate::cache`], kind `crops`), keyed by
/// everything that shapes the crops: the photos, the centre source, the normalisation path and
/// parameters, and the model files the front end loaded. Photos the front end skipped stay skipped.
pub fn align_all_cached(
    dir: &Path,
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    let key = crops_key("crops", front_end, &(normalization, params), faces)?;
    let crops =
        cache::get_or_compute(dir, &key, faces.len(), progress, || Ok(crop_faces(front_end, faces, normalization, params, progress)))?;
    Ok(assemble(faces, crops))
}

/// Crops of `faces` on each normalisation path of `paths` (primary first): the primary crop in
/// `crop`, the second path's in `secondary_crop`; photos that fail on any path are left out. With
/// `cache`, each path's crops go through [`align_all_cached`].
pub fn align_paths(
    cache: Option<&Path>,
    front_end: &FrontEnd,
    faces: &[FaceImage],
    paths: &[Normalization],
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    let align = |normalization| match cache {
        Some(dir) => align_all_cached(dir, front_end, faces, normalization, params, progress),
        None => Ok(align_all(front_end, faces, normalization, params, progress)),
    };
    let (&primary, rest) = paths.split_first().ok_or_else(|| anyhow::anyhow!("no normalisation path"))?;
    let mut aligned = align(primary)?;
    if let Some(&second) = rest.first() {
        let mut by_path: BTreeMap<PathBuf, GrayF32> = align(second)?.into_iter().map(|a| (a.face.image, a.crop)).collect();
        aligned.retain_mut(|a| match by_path.remove(&a.face.image) {
            Some(crop) => {
                a.secondary_crop = Some(crop);
                true
            }
            None => false,
        });
    }
    Ok(aligned)
}

/// One re-posed copy's crops: width, height, the primary path's pixels, the second path's.
type ReposedCrop = (usize, usize, Vec<f32>, Option<Vec<f32>>);

/// The crops of `face`'s re-posed copies at `offsets` on each path of `paths`; a copy that fails
/// on a path is left out, a face that cannot be re-posed has none (reported).
fn reposed_crops(
    front_end: &FrontEnd,
    face: &FaceImage,
    paths: &[Normalization],
    params: &NormalizeParams,
    offsets: &[(f32, f32)],
    progress: &dyn Progress,
) -> Vec<ReposedCrop> {
    let views = match front_end.reposed_views(face, offsets) {
        Ok(views) => views,
        Err(e) => {
            progress.note(&format!("{}: no re-posed copies ({e})", face.image.display()));
            return Vec::new();
        }
    };
    let mut copies = Vec::new();
    for (photo, landmarks) in views {
        let crop = |normalization| {
            recognition_input(front_end.face_model.as_ref(), &photo, &landmarks, normalization)
                .ok()
                .map(|input| normalize::geometric(&input.gray, &input.centres, params))
        };
        let (Some(first), second) = (crop(paths[0]), paths.get(1).map(|&p| crop(p))) else { continue };
        if second.as_ref().is_some_and(|c| c.is_none()) {
            continue;
        }
        copies.push((first.width, first.height, first.data, second.flatten().map(|c| c.data)));
    }
    copies
}

/// Crops of 3DMM re-posed copies ([`FrontEnd::reposed_views`]) of the training persons' photos
/// (held-out persons get none) on each path of `paths`, attached to `aligned` (see
/// [`AlignedFace::reposed`]); a copy that fails on a path is left out. With `cache`, the crops go
/// through the research cache there (kind `reposed-crops`), keyed like [`align_all_cached`]'s and
/// by the offsets.
pub fn attach_reposed_crops(
    cache: Option<&Path>,
    front_end: &FrontEnd,
    aligned: &mut [AlignedFace],
    paths: &[Normalization],
    params: &NormalizeParams,
    offsets: &[(f32, f32)],
    progress: &dyn Progress,
) -> anyhow::Result<()> {
    if offsets.is_empty() {
        return Ok(());
    }
    let faces: Vec<FaceImage> = aligned.iter().filter(|a| !a.face.held_out).map(|a| a.face.clone()).collect();
    let compute = || {
        map_samples(&faces, front_end.threads, "re-posing", progress, |face| {
            reposed_crops(front_end, face, paths, params, offsets, progress)
        })
    };
    let copies: Vec<Vec<ReposedCrop>> = match cache {
        Some(dir) => {
            let key = crops_key("reposed-crops", front_end, &(paths, params, offsets), &faces)?;
            cache::get_or_compute(dir, &key, faces.len(), progress, || Ok(compute()))?
        }
        None => compute(),
    };
    for (a, copies) in aligned.iter_mut().filter(|a| !a.face.held_out).zip(copies) {
        a.reposed = copies
            .into_iter()
            .map(|(w, h, first, second)| {
                let image = |data: Vec<f32>| GrayF32 { width: w, height: h, data };
                (image(first), second.map(image))
            })
            .collect();
    }
    Ok(())
}

/// What `train dlda` trains on.
#[derive(Debug, Clone)]
pub struct TrainingPhotos {
    /// Labelled folders ([`list_faces`]).
    pub data: Vec<PathBuf>,
    pub centre_origin: CentreOrigin,
    /// Leave the training persons' IMM rotated views (3, 4) out.
    pub frontal_only: bool,
    /// (yaw, pitch) offsets in degrees of the 3DMM re-posed copies of the training photos
    /// ([`repose_offsets`]); none: no copies.
    pub repose: Vec<(f32, f32)>,
    /// The research cache folder for the crops; none: no cache.
    pub cache: Option<PathBuf>,
    pub threads: usize,
}

/// The re-posing offsets: each yaw with the pitch unchanged, then each pitch with the yaw unchanged.
pub fn repose_offsets(yaw: &[f32], pitch: &[f32]) -> Vec<(f32, f32)> {
    yaw.iter().map(|&y| (y, 0.0)).chain(pitch.iter().map(|&p| (0.0, p))).collect()
}

/// The crops `train dlda` trains on: the photos of `photos.data` (without the training persons'
/// rotated views when `frontal_only`) on every path of `config`, with the re-posed copies; the
/// front end's finder loaded from `models_dir`, the 3DMM from `sfm_dir` when a path or the copies
/// need it.
pub fn training_crops(
    photos: &TrainingPhotos,
    config: &TrainConfig,
    models_dir: &Path,
    sfm_dir: &Path,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    let mut faces = list_faces(&photos.data)?;
    anyhow::ensure!(!faces.is_empty(), "no labelled images under {:?}", photos.data);
    if photos.frontal_only {
        faces.retain(|f| f.held_out || !f.is_rotated_view());
    }
    let paths = config.paths();
    // The 3DMM is needed by its path and by the re-posed copies (on the 2D path it only reports
    // the pose: the crops are the same with or without it).
    let needs_sfm = paths.contains(&Normalization::Morph) || !photos.repose.is_empty();
    let front = FrontEnd::load(photos.centre_origin, models_dir, needs_sfm.then_some(sfm_dir)).with_threads(photos.threads);
    anyhow::ensure!(
        photos.repose.is_empty() || front.face_model.is_some(),
        "the re-posed training copies (--repose-yaw, default ±20°) need the Surrey Face Model (FACEGATE_SFM); or pass --no-repose"
    );
    let cache_dir = photos.cache.as_deref();
    let mut aligned = align_paths(cache_dir, &front, &faces, &paths, &config.normalize, progress)?;
    attach_reposed_crops(cache_dir, &front, &mut aligned, &paths, &config.normalize, &photos.repose, progress)?;
    Ok(aligned)
}
