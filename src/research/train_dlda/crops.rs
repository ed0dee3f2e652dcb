//! Geometric crops of the photos on each normalisation path, their 3DMM re-posed copies, and the
//! crop cache.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::*;
use crate::core::imaging::GrayF32;
use crate::morph::Pose;
use crate::pipeline::recognition_input;
use crate::recognize::Normalization;
use crate::recognize::normalize::{self, NormalizeParams};
use crate::research::Progress;

/// A photo after geometric normalisation (photometric normalisation is part of the model).
#[derive(Debug, Clone)]
pub struct AlignedFace {
    pub face: FaceImage,
    pub crop: GrayF32,
    /// The crop on the second path of a fused model (see [`align_paths`]).
    pub secondary_crop: Option<GrayF32>,
    pub pose: Option<Pose>,
    pub keypoint_source: &'static str,
    /// 3DMM re-posed copies of the face ([`attach_reposed_crops`]), used as extra training samples of
    /// its person: per copy, the crop on the primary path and on the second path.
    pub reposed: Vec<(GrayF32, Option<GrayF32>)>,
}

/// Geometric crops of all `faces` (photos whose front end fails are reported and left out).
pub fn align_all(
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> Vec<AlignedFace> {
    progress.begin(faces.len() as u64, "aligning");
    let mut out = Vec::with_capacity(faces.len());
    for face in faces {
        match front_end.prepare(face, normalization) {
            Ok(p) => out.push(AlignedFace {
                face: face.clone(),
                crop: normalize::geometric(&p.gray, &p.keypoints, params),
                secondary_crop: None,
                pose: p.pose,
                keypoint_source: p.keypoint_source,
                reposed: Vec::new(),
            }),
            Err(e) => progress.note(&format!("warning: {}: skipped ({e})", face.image.display())),
        }
        progress.step();
    }
    progress.end();
    out
}

/// 16 hex digits of the SHA-256 of what shapes cached crops: `settings` (serialised parameters),
/// the keypoint source, the photos, and the bytes of the landmark models the front end loaded
/// (`asm.bin`, `asm3d.bin` of its models folder).
fn cache_key(settings: &[u8], front_end: &FrontEnd, faces: &[FaceImage]) -> String {
    let source = front_end.source;
    use sha2::{Digest, Sha256};
    let mut hasher = Sha256::new();
    hasher.update(settings);
    hasher.update(format!("{source:?}"));
    for f in faces {
        hasher.update(f.image.display().to_string());
        hasher.update([f.asf.is_some() as u8]);
    }
    for model in ["asm.bin", "asm3d.bin"] {
        if let Some(Ok(bytes)) = front_end.models_dir.as_ref().map(|dir| std::fs::read(dir.join(model))) {
            hasher.update(&bytes);
        }
    }
    hasher.finalize().iter().take(8).map(|b| format!("{b:02x}")).collect()
}

/// The entries of a crop cache file (postcard), or `None` when there is no readable file (a miss:
/// the caller computes them and writes them with [`write_cache_file`]). A file that is there but
/// does not decode is an error rather than a miss, so that a cache written by another format is
/// noticed instead of silently recomputed over.
fn read_cache_file<T: serde::de::DeserializeOwned>(file: &Path) -> anyhow::Result<Option<T>> {
    match std::fs::read(file) {
        Ok(bytes) => Ok(Some(postcard::from_bytes(&bytes)?)),
        Err(_) => Ok(None),
    }
}

/// Writes crop cache `entries` (postcard) to `file`, creating its folder.
fn write_cache_file<T: Serialize>(file: &Path, entries: &T) -> anyhow::Result<()> {
    std::fs::create_dir_all(file.parent().unwrap_or(Path::new(".")))?;
    std::fs::write(file, postcard::to_stdvec(entries)?)?;
    Ok(())
}

/// [`align_all`] through a cache file in `dir`, keyed by the SHA-256 of everything that shapes the
/// crops: the photos, the keypoint source, the normalisation path and parameters, and the bytes of
/// the landmark models (`asm.bin`, `asm3d.bin`). Photos the front end skipped stay skipped.
pub fn align_all_cached(
    dir: &Path,
    front_end: &FrontEnd,
    faces: &[FaceImage],
    normalization: Normalization,
    params: &NormalizeParams,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<AlignedFace>> {
    type Entry = (String, usize, usize, Vec<f32>, String);
    let key = cache_key(&postcard::to_stdvec(&(normalization, params))?, front_end, faces);
    let path = dir.join(format!("crops-{key}.bin"));
    let source_name = |s: &str| -> &'static str {
        match s {
            "imm-annotations" => "imm-annotations",
            "pipeline" => "pipeline",
            _ => "detector-box",
        }
    };
    if let Some(entries) = read_cache_file::<Vec<Entry>>(&path)? {
        let by_path: BTreeMap<String, &Entry> = entries.iter().map(|e| (e.0.clone(), e)).collect();
        progress.note(&format!("aligned crops from cache {}", path.display()));
        return Ok(faces
            .iter()
            .filter_map(|f| by_path.get(&f.image.display().to_string()))
            .zip(faces.iter().filter(|f| by_path.contains_key(&f.image.display().to_string())))
            .map(|(e, f)| AlignedFace {
                face: f.clone(),
                crop: GrayF32 { width: e.1, height: e.2, data: e.3.clone() },
                secondary_crop: None,
                pose: None,
                keypoint_source: source_name(&e.4),
                reposed: Vec::new(),
            })
            .collect());
    }
    let aligned = align_all(front_end, faces, normalization, params, progress);
    let entries: Vec<Entry> = aligned
        .iter()
        .map(|a| (a.face.image.display().to_string(), a.crop.width, a.crop.height, a.crop.data.clone(), a.keypoint_source.to_string()))
        .collect();
    write_cache_file(&path, &entries)?;
    Ok(aligned)
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

/// Crops of 3DMM re-posed copies ([`FrontEnd::reposed_views`]) of the training persons' photos
/// (held-out persons get none) on each path of `paths`, attached to `aligned` (see
/// [`AlignedFace::reposed`]); a copy that fails on a path is left out. With `cache`, the crops are
/// kept in a file keyed like [`align_all_cached`]'s, and the offsets.
pub fn attach_reposed_crops(
    cache: Option<&Path>,
    front_end: &FrontEnd,
    aligned: &mut [AlignedFace],
    paths: &[Normalization],
    params: &NormalizeParams,
    offsets: &[(f32, f32)],
    progress: &dyn Progress,
) -> anyhow::Result<()> {
    type Entry = (String, Vec<(usize, usize, Vec<f32>, Option<Vec<f32>>)>);
    if offsets.is_empty() {
        return Ok(());
    }
    let faces: Vec<FaceImage> = aligned.iter().filter(|a| !a.face.held_out).map(|a| a.face.clone()).collect();
    let key = cache_key(&postcard::to_stdvec(&(paths, params, offsets))?, front_end, &faces);
    let file = cache.map(|dir| dir.join(format!("reposed-{key}.bin")));
    let cached = match &file {
        Some(f) => read_cache_file::<Vec<Entry>>(f)?,
        None => None,
    };
    let entries: Vec<Entry> = match cached {
        Some(entries) => entries,
        None => {
            progress.begin(faces.len() as u64, "re-posing");
            let mut entries = Vec::with_capacity(faces.len());
            for face in &faces {
                let mut copies = Vec::new();
                match front_end.reposed_views(face, offsets) {
                    Ok(views) => {
                        for (photo, landmarks) in views {
                            let crop = |normalization| {
                                recognition_input(front_end.face_model.as_ref(), &photo, &landmarks, normalization)
                                    .ok()
                                    .map(|input| normalize::geometric(&input.gray, &input.keypoints, params))
                            };
                            let (Some(first), second) = (crop(paths[0]), paths.get(1).map(|&p| crop(p))) else { continue };
                            if second.as_ref().is_some_and(|c| c.is_none()) {
                                continue;
                            }
                            copies.push((first.width, first.height, first.data, second.flatten().map(|c| c.data)));
                        }
                    }
                    Err(e) => progress.note(&format!("{}: no re-posed copies ({e})", face.image.display())),
                }
                entries.push((face.image.display().to_string(), copies));
                progress.step();
            }
            progress.end();
            if let Some(f) = &file {
                write_cache_file(f, &entries)?;
            }
            entries
        }
    };
    let by_path: BTreeMap<String, &Entry> = entries.iter().map(|e| (e.0.clone(), e)).collect();
    for a in aligned.iter_mut().filter(|a| !a.face.held_out) {
        if let Some((_, copies)) = by_path.get(&a.face.image.display().to_string()) {
            a.reposed = copies
                .iter()
                .map(|(w, h, first, second)| {
                    let image = |data: &Vec<f32>| GrayF32 { width: *w, height: *h, data: data.clone() };
                    (image(first), second.as_ref().map(image))
                })
                .collect();
        }
    }
    Ok(())
}
