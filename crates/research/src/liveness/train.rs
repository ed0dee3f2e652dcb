//! Training the liveness model (`facegate train liveness`): NUAA's live and printed-photo frames,
//! the service's face finder for the eye and mouth centres, the runtime's own liveness
//! [`features`](facegate_vision::liveness::features), and a ridge-penalised logistic regression,
//! with Platt's calibration fitted on leave-one-subject-out logits (the same folds
//! [`crate::liveness::eval`] reports). Live photos of the IMM, ORL and LFW *training* persons can
//! join the live class, so that another camera's live face is not taken for a print.

use std::path::{Path, PathBuf};

use facegate_core::face::EyeMouthCentres;
use facegate_vision::liveness::{Block, LivenessModel};
use facegate_vision::pipeline::FaceFinder;
use serde::Serialize;

use crate::Progress;
use crate::cache::{self, CacheKey, ModelFiles, map_samples};
use crate::liveness::attacks::{AttackKind, simulate};
use crate::liveness::video::{VideoFrame, list_video};
use crate::logistic::{LogisticFit, fit_binary};

/// One NUAA frame: `SSSS_GG_PP_EE_frame.jpg` under `real/SSSS` or `print/SSSS`.
#[derive(Debug, Clone, PartialEq)]
pub struct NuaaSample {
    pub subject: String,
    pub live: bool,
    /// Whether the subject wears glasses (`GG` 01).
    pub glasses: bool,
    /// The position and lighting code `PP` (prints: 00 held still, 01–04 moved or bent, 08 …).
    pub condition: String,
    /// The capture session `EE`.
    pub session: String,
    pub image: PathBuf,
}

/// Every frame under `dir` (`real/` and `print/`), sorted by path.
pub fn list_nuaa(dir: &Path) -> anyhow::Result<Vec<NuaaSample>> {
    let mut out = Vec::new();
    for (folder, live) in [("real", true), ("print", false)] {
        for subject in std::fs::read_dir(dir.join(folder))? {
            let subject = subject?.path();
            for entry in std::fs::read_dir(&subject)? {
                let image = entry?.path();
                let name = image.file_stem().unwrap_or_default().to_string_lossy().to_string();
                let parts: Vec<&str> = name.split('_').collect();
                anyhow::ensure!(parts.len() == 5, "{}: not a NUAA frame name", image.display());
                out.push(NuaaSample {
                    subject: parts[0].to_string(),
                    live,
                    glasses: parts[1] == "01",
                    condition: parts[2].to_string(),
                    session: parts[3].to_string(),
                    image,
                });
            }
        }
    }
    anyhow::ensure!(!out.is_empty(), "no NUAA frames under {}", dir.display());
    out.sort_by(|a, b| a.image.cmp(&b.image));
    Ok(out)
}

/// Every UMIST photo (`s*/NN.pgm`), sorted.
pub fn list_umist(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for person in std::fs::read_dir(dir)? {
        for entry in std::fs::read_dir(person?.path())? {
            let path = entry?.path();
            if path.extension().is_some_and(|e| e == "pgm") {
                out.push(path);
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The eye and mouth centres the service would use for the largest face of each photo (`None`:
/// no face, or the photo does not open), through the research cache.
pub fn centres(
    cache_dir: &Path,
    models_dir: &Path,
    images: &[PathBuf],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<EyeMouthCentres>>> {
    located(("liveness-keypoints", "find faces"), cache_dir, models_dir, images, threads, progress, |l| l.centres)
}

/// What `pick` takes of the service's landmarks of the largest face of each photo, computed by
/// the face finder of `models_dir` or read from the cache (`kind`, and what the loop is called).
fn located<R: Serialize + serde::de::DeserializeOwned + Send + Clone>(
    (kind, what): (&str, &str),
    cache_dir: &Path,
    models_dir: &Path,
    images: &[PathBuf],
    threads: usize,
    progress: &dyn Progress,
    pick: impl Fn(facegate_vision::landmarks::Landmarks) -> R + Sync,
) -> anyhow::Result<Vec<Option<R>>> {
    let key = CacheKey::new(kind, &ModelFiles::new().finder(models_dir), &[], images.iter().map(|p| p.display().to_string()));
    cache::get_or_compute(cache_dir, &key, images.len(), progress, || {
        let finder = FaceFinder::load(models_dir)?;
        Ok(map_samples(images, threads, what, progress, |path| {
            let photo = facegate_core::imaging::open(path).ok()?;
            Some(pick(finder.locate(&photo.gray).ok()?.landmarks))
        }))
    })
}

/// Every block's features ([`Block::ALL`], in order) of each photo with centres.
pub fn all_features(
    images: &[PathBuf],
    centres: &[Option<EyeMouthCentres>],
    threads: usize,
    progress: &dyn Progress,
) -> Vec<Option<Vec<f32>>> {
    let items: Vec<(&PathBuf, &Option<EyeMouthCentres>)> = images.iter().zip(centres).collect();
    map_samples(&items, threads, "liveness features", progress, |(path, centres)| {
        let centres = (*centres).as_ref()?;
        Some(block_features(&image::open(path).ok()?.to_rgb8(), centres))
    })
}

/// Every block's features of `photo` around its eye and mouth `centres`.
fn block_features(photo: &image::RgbImage, centres: &EyeMouthCentres) -> Vec<f32> {
    use facegate_vision::liveness::features::{crops, features};
    features(&crops(photo, centres), &Block::ALL)
}

/// Every block's features of each photo with centres, the photo turned into the simulated
/// attack `kind` first (seeded by its index: the same attacks on every run).
pub fn simulated_features(
    images: &[PathBuf],
    centres: &[Option<EyeMouthCentres>],
    kind: AttackKind,
    threads: usize,
    progress: &dyn Progress,
) -> Vec<Option<Vec<f32>>> {
    let items: Vec<(usize, &PathBuf, &Option<EyeMouthCentres>)> =
        images.iter().zip(centres).enumerate().map(|(i, (p, k))| (i, p, k)).collect();
    map_samples(&items, threads, kind.name(), progress, |(i, path, centres)| {
        let centres = (*centres).as_ref()?;
        Some(block_features(&simulate(&image::open(path).ok()?.to_rgb8(), kind, *i as u64), centres))
    })
}

/// The columns of `blocks` within [`Block::ALL`]'s features.
pub fn columns(blocks: &[Block]) -> Vec<usize> {
    let mut start = 0;
    let mut ranges = Vec::new();
    for b in Block::ALL {
        ranges.push((b, start..start + b.len()));
        start += b.len();
    }
    blocks.iter().flat_map(|b| ranges.iter().find(|(r, _)| r == b).map(|(_, r)| r.clone()).unwrap_or(0..0)).collect()
}

/// Weights that give the live and the attack rows equal totals, and within each class the NUAA
/// rows and the other rows (`other`: other cameras' live photos, simulated attacks) equal totals
/// too, when the class has both.
pub fn balanced_weights(live: &[bool], other: &[bool]) -> Vec<f64> {
    let n = live.len() as f64;
    // Rows per (class, from other), counted once: [live][other].
    let mut counts = [[0usize; 2]; 2];
    for (&l, &o) in live.iter().zip(other) {
        counts[usize::from(l)][usize::from(o)] += 1;
    }
    live.iter()
        .zip(other)
        .map(|(&l, &o)| {
            let [nuaa, others] = counts[usize::from(l)];
            let share = if nuaa == 0 || others == 0 { 0.5 } else { 0.25 };
            share * n / counts[usize::from(l)][usize::from(o)] as f64
        })
        .collect()
}

/// The runtime model from a fit on `blocks`, a calibration and an operating point.
pub fn model(
    name: &str,
    blocks: &[Block],
    fit: LogisticFit,
    (slope, offset): (f32, f32),
    threshold: f32,
    operating_point: String,
    trained_on: String,
) -> LivenessModel {
    LivenessModel {
        format: facegate_vision::liveness::FORMAT,
        name: name.to_string(),
        blocks: blocks.to_vec(),
        mean: fit.mean,
        scale: fit.scale,
        weights: fit.weights,
        bias: fit.bias,
        slope,
        offset,
        threshold,
        operating_point,
        trained_on,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_columns_of_a_block_are_its_place_in_every_blocks_features() {
        assert_eq!(columns(&[Block::FaceFrequency]).len(), Block::FaceFrequency.len());
        assert_eq!(columns(&[Block::FaceFrequency])[0], Block::FaceLbp.len() + Block::FaceColourLbp.len());
    }

    #[test]
    fn nuaa_names_give_subject_condition_and_session() {
        let s = list_nuaa(&facegate_paths::shared_dir().join("data/nuaa")).unwrap();
        assert!(s.iter().any(|s| s.live) && s.iter().any(|s| !s.live));
        let p = s.iter().find(|s| s.image.ends_with("print/0004/0004_01_01_03_211.jpg")).unwrap();
        assert_eq!((p.subject.as_str(), p.glasses, p.condition.as_str(), p.session.as_str(), p.live), ("0004", true, "01", "03", false));
    }

    #[test]
    fn a_plane_moved_in_perspective_fits_one_homography_and_a_turned_head_does_not() {
        // 58 points on a plane, seen again through a perspective map: no residual.
        let from: Vec<[f32; 2]> =
            (0..58).map(|i| [100.0 + (i % 8) as f32 * 10.0 + (i / 8) as f32, 100.0 + (i / 8) as f32 * 12.0]).collect();
        let warp = |p: [f32; 2]| {
            let w = 1.0 + 0.0005 * p[0];
            [(1.1 * p[0] + 0.1 * p[1] + 5.0) / w, (0.05 * p[0] + 0.95 * p[1] - 3.0) / w]
        };
        let planar: Vec<[f32; 2]> = from.iter().map(|&p| warp(p)).collect();
        assert!(homography_residual(&from, &planar).unwrap() < 1e-3);
        // Points at different depths rotating about a vertical axis: parallax no homography explains.
        let depth = |i: usize| if i % 3 == 0 { 40.0 } else { 0.0 };
        let turned: Vec<[f32; 2]> = from.iter().enumerate().map(|(i, p)| [130.0 + (p[0] - 130.0) * 0.9 + depth(i) * 0.43, p[1]]).collect();
        assert!(homography_residual(&from, &turned).unwrap() > 0.05);
    }

    #[test]
    fn each_class_weighs_half_and_within_it_nuaa_and_the_other_rows_half_each() {
        // Rows: 2 NUAA live, 1 other camera's live, 1 NUAA print, 3 simulated attacks.
        let live = [true, true, true, false, false, false, false];
        let other = [false, false, true, false, true, true, true];
        let w = balanced_weights(&live, &other);
        let total = |f: &dyn Fn(usize) -> bool| (0..w.len()).filter(|&i| f(i)).map(|i| w[i]).sum::<f64>();
        let n = live.len() as f64;
        assert!((total(&|i| live[i]) - 0.5 * n).abs() < 1e-9);
        assert!((total(&|i| !live[i] && other[i]) - 0.25 * n).abs() < 1e-9);
        assert!((total(&|i| !live[i] && !other[i]) - 0.25 * n).abs() < 1e-9);
        // A class without other rows keeps its whole half for NUAA's.
        let w = balanced_weights(&[true, false, false], &[false, false, false]);
        assert!((w[0] - 1.5).abs() < 1e-9 && (w[1] - 0.75).abs() < 1e-9);
    }
}

/// The training and evaluation photos with their features: NUAA's frames, and the live photos of
/// the IMM, ORL and LFW persons (training persons join the live class; test persons measure how
/// often another camera's live face is refused).
pub struct LivenessData {
    pub nuaa: Vec<NuaaSample>,
    /// Per NUAA frame, every block's features; `None`: no face found.
    pub nuaa_features: Vec<Option<Vec<f32>>>,
    pub others: Vec<crate::train_deep::Sample>,
    pub other_features: Vec<Option<Vec<f32>>>,
    /// Live photos of a camera no passive model is trained with (UMIST, grey, profile to frontal).
    pub unseen: Vec<PathBuf>,
    pub unseen_features: Vec<Option<Vec<f32>>>,
    /// Per [`AttackKind::ALL`], the other cameras' photos as that simulated attack: features at
    /// the photo's own centres (the simulation keeps the geometry); `None`: no face.
    pub simulated_features: Vec<Vec<Option<Vec<f32>>>>,
    /// Live frames of real video ([`crate::liveness::video`]), every person's.
    pub video: Vec<VideoFrame>,
    pub video_features: Vec<Option<Vec<f32>>>,
}

impl LivenessData {
    /// Reads `shared/data/nuaa` and the IMM, ORL and LFW lists of `shared`; the faces are found
    /// by the finder of `models_dir` (cached in `cache_dir`).
    pub fn load(
        shared: &Path,
        models_dir: &Path,
        cache_dir: &Path,
        threads: usize,
        progress: &dyn Progress,
    ) -> anyhow::Result<LivenessData> {
        let nuaa = list_nuaa(&shared.join("data/nuaa"))?;
        let others = crate::train_deep::list_samples(shared)?;
        let nuaa_images: Vec<PathBuf> = nuaa.iter().map(|s| s.image.clone()).collect();
        let other_images: Vec<PathBuf> = others.iter().map(|s| s.image.clone()).collect();
        let unseen = list_umist(&shared.join("data/umist"))?;
        let unseen_centres = centres(cache_dir, models_dir, &unseen, threads, progress)?;
        let nuaa_centres = centres(cache_dir, models_dir, &nuaa_images, threads, progress)?;
        let other_centres = centres(cache_dir, models_dir, &other_images, threads, progress)?;
        let simulated_features =
            AttackKind::ALL.iter().map(|&kind| simulated_features(&other_images, &other_centres, kind, threads, progress)).collect();
        let video = list_video(&shared.join("data/video"))?;
        let video_images: Vec<PathBuf> = video.iter().map(|f| f.image.clone()).collect();
        let video_centres = centres(cache_dir, models_dir, &video_images, threads, progress)?;
        Ok(LivenessData {
            video_features: all_features(&video_images, &video_centres, threads, progress),
            video,
            simulated_features,
            nuaa_features: all_features(&nuaa_images, &nuaa_centres, threads, progress),
            other_features: all_features(&other_images, &other_centres, threads, progress),
            unseen_features: all_features(&unseen, &unseen_centres, threads, progress),
            unseen,
            nuaa,
            others,
        })
    }

    /// The other cameras' live photos of `split`'s persons with a face: their indices.
    pub fn others_in(&self, split: crate::dataset::Split) -> Vec<usize> {
        (0..self.others.len()).filter(|&i| self.others[i].split == split && self.other_features[i].is_some()).collect()
    }
}

/// What a liveness model is made of.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Recipe {
    pub blocks: Vec<Block>,
    /// Whether the IMM, ORL and LFW training persons' live photos join the live class.
    pub other_cameras: bool,
    /// The ridge penalty per unit of total weight.
    pub ridge: f64,
    /// Whether the training persons' photos as simulated prints and screens
    /// ([`crate::liveness::attacks`]) join the attack class (needs `other_cameras`'s photos).
    pub simulated_attacks: bool,
    /// Whether real video's live frames ([`crate::liveness::video`]) join the other cameras' in
    /// the live class.
    pub video_live: bool,
}

/// A fit of `recipe` on the NUAA frames `nuaa` (indices with features) and, when the recipe says
/// so, the other cameras' training persons.
pub fn fit_recipe(data: &LivenessData, recipe: &Recipe, nuaa: &[usize]) -> LogisticFit {
    fit_recipe_without(data, recipe, nuaa, None)
}

/// [`fit_recipe`] with one of the other cameras' sets left out of the live class (`without`), to
/// measure how that camera's live faces fare with a model that never saw it.
pub fn fit_recipe_without(data: &LivenessData, recipe: &Recipe, nuaa: &[usize], without: Option<crate::train_deep::Set>) -> LogisticFit {
    fit_recipe_leaving_out(data, recipe, nuaa, without, None)
}

/// [`fit_recipe_without`], also leaving one video person's frames out of the live class
/// (`without_person`), to measure that person's clips with a model that never saw them.
pub fn fit_recipe_leaving_out(
    data: &LivenessData,
    recipe: &Recipe,
    nuaa: &[usize],
    without: Option<crate::train_deep::Set>,
    without_person: Option<&str>,
) -> LogisticFit {
    let cols = columns(&recipe.blocks);
    let pick = |f: &Vec<f32>| cols.iter().map(|&c| f[c]).collect::<Vec<f32>>();
    let mut rows: Vec<Vec<f32>> = Vec::new();
    let (mut live, mut other) = (Vec::new(), Vec::new());
    for &i in nuaa {
        if let Some(f) = &data.nuaa_features[i] {
            rows.push(pick(f));
            live.push(data.nuaa[i].live);
            other.push(false);
        }
    }
    if recipe.other_cameras {
        for i in data.others_in(crate::dataset::Split::Train).into_iter().filter(|&i| Some(data.others[i].set) != without) {
            rows.push(pick(data.other_features[i].as_ref().expect("others_in keeps photos with features")));
            live.push(true);
            other.push(true);
        }
    }
    if recipe.simulated_attacks {
        for kind in &data.simulated_features {
            for i in data.others_in(crate::dataset::Split::Train).into_iter().filter(|&i| Some(data.others[i].set) != without) {
                if let Some(f) = &kind[i] {
                    rows.push(pick(f));
                    live.push(false);
                    other.push(true);
                }
            }
        }
    }
    if recipe.video_live {
        for (frame, features) in data.video.iter().zip(&data.video_features) {
            if let Some(f) = features.as_ref().filter(|_| Some(frame.person.as_str()) != without_person) {
                rows.push(pick(f));
                live.push(true);
                other.push(true);
            }
        }
    }
    let refs: Vec<&[f32]> = rows.iter().map(Vec::as_slice).collect();
    fit_binary(&refs, &live, &balanced_weights(&live, &other), recipe.ridge)
}

/// Leave-one-subject-out logits of every NUAA frame with a face (`None` without one): each
/// subject's frames scored by the fit on the other subjects.
pub fn out_of_fold_logits(data: &LivenessData, recipe: &Recipe, progress: &dyn Progress) -> Vec<Option<f32>> {
    let cols = columns(&recipe.blocks);
    let mut subjects: Vec<&str> = data.nuaa.iter().map(|s| s.subject.as_str()).collect();
    subjects.sort_unstable();
    subjects.dedup();
    let mut out = vec![None; data.nuaa.len()];
    progress.begin(subjects.len() as u64, "subject folds");
    for subject in subjects {
        let train: Vec<usize> = (0..data.nuaa.len()).filter(|&i| data.nuaa[i].subject != subject).collect();
        let fit = fit_recipe(data, recipe, &train);
        for i in (0..data.nuaa.len()).filter(|&i| data.nuaa[i].subject == subject) {
            out[i] = data.nuaa_features[i].as_ref().map(|f| fit.logit_at(&cols, f));
        }
        progress.step();
    }
    progress.end();
    out
}

/// The service's 58 landmarks of the largest face of each photo (`None`: no face), through the
/// research cache: the motion test of [`crate::liveness::eval`] reads them.
pub fn landmarks(
    cache_dir: &Path,
    models_dir: &Path,
    images: &[PathBuf],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<Vec<facegate_core::geometry::Point>>>> {
    located(("liveness-landmarks", "landmarks"), cache_dir, models_dir, images, threads, progress, |l| l.points)
}

/// How far the points of a later frame are from the best homography of the first frame's onto
/// them: the RMS transfer error over the inter-ocular distance. A print moved or bent in front of
/// the camera stays (nearly) a plane, whose points one homography maps; a head turning in 3D does
/// not. `None` when the points are degenerate.
pub fn homography_residual(from: &[facegate_core::geometry::Point], to: &[facegate_core::geometry::Point]) -> Option<f64> {
    use nalgebra::{DMatrix, Matrix3, Vector3};
    if from.len() != to.len() || from.len() < 5 {
        return None;
    }
    // Hartley normalisation of each point set, then the DLT's null vector by SVD.
    let normalise = |p: &[facegate_core::geometry::Point]| {
        let n = p.len() as f64;
        let (mx, my) = (p.iter().map(|q| q[0] as f64).sum::<f64>() / n, p.iter().map(|q| q[1] as f64).sum::<f64>() / n);
        let spread = p.iter().map(|q| ((q[0] as f64 - mx).powi(2) + (q[1] as f64 - my).powi(2)).sqrt()).sum::<f64>() / n;
        let s = std::f64::consts::SQRT_2 / spread.max(1e-9);
        Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
    };
    let (ta, tb) = (normalise(from), normalise(to));
    let mut a = DMatrix::<f64>::zeros(2 * from.len(), 9);
    for (i, (p, q)) in from.iter().zip(to).enumerate() {
        let p = ta * Vector3::new(p[0] as f64, p[1] as f64, 1.0);
        let q = tb * Vector3::new(q[0] as f64, q[1] as f64, 1.0);
        let (x, y, u, v) = (p[0], p[1], q[0], q[1]);
        for (k, val) in [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u].into_iter().enumerate() {
            a[(2 * i, k)] = val;
        }
        for (k, val) in [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v].into_iter().enumerate() {
            a[(2 * i + 1, k)] = val;
        }
    }
    let ata = a.transpose() * &a;
    let eig = nalgebra::SymmetricEigen::new(ata);
    let smallest = eig.eigenvalues.iter().enumerate().min_by(|x, y| x.1.total_cmp(y.1))?.0;
    let h = eig.eigenvectors.column(smallest);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hm = tb.try_inverse()? * hn * ta;
    let eyes = |p: &[facegate_core::geometry::Point]| {
        let k = EyeMouthCentres::from_imm(p);
        (((k.left_eye[0] - k.right_eye[0]).powi(2) + (k.left_eye[1] - k.right_eye[1]).powi(2)) as f64).sqrt()
    };
    let scale = eyes(to).max(1.0);
    let sq = from.iter().zip(to).map(|(p, q)| {
        let m = hm * Vector3::new(p[0] as f64, p[1] as f64, 1.0);
        let (u, v) = (m[0] / m[2], m[1] / m[2]);
        (u - q[0] as f64).powi(2) + (v - q[1] as f64).powi(2)
    });
    Some((sq.sum::<f64>() / from.len() as f64).sqrt() / scale)
}
