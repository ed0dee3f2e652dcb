//! Training the 3D-ASM (`facegate train asm3d`): 3D PDMs drawn from the 3DMM, then per view the
//! texture models of real photos and of synthetic renders of the training faces.

use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

use crate::asm3d_synth::*;
use crate::dataset::{self, ImmSample};
use crate::landmark_models::{train_full_gaussian, train_pca_gaussian, train_pdm3d, train_shape_model};
use facegate_core::face::{IMM_POINTS, JAW};
use facegate_core::geometry::{Point, Rect, centroid};
use facegate_core::imaging::{self, GrayF32};
use facegate_detect::Detector;
use facegate_morph::{Camera, FaceModel, Pose};
use facegate_vision::landmarks::asm3d::*;
use facegate_vision::landmarks::search::{normals, pyramid, to_level};
use facegate_vision::landmarks::{AsmModel, BoxSource, LandmarkError, Placement, SearchParams, TrainInfo, profile, sift};

/// Training settings.
#[derive(Debug, Clone)]
pub struct Asm3dTrainOptions {
    pub params: SearchParams,
    /// Yaw bin centres (thesis: 7 views, −45°…+45°; [`Asm3dTrainOptions::profile`]: on to ±90°).
    pub yaws: Vec<f32>,
    /// Random 3DMM shapes the 3D PDM is built from.
    pub pdm_shapes: usize,
    pub shape_variance: f64,
    pub constrain: f32,
    /// Principal components of the internal points' SIFT models (the jaw points use profiles; their
    /// SIFT models keep one component, unused by the search).
    pub sift_modes: usize,
    pub profile_ridge: f64,
    /// UV texture side for the synthetic renders.
    pub texture_size: usize,
    /// Largest relative gain of the horizontal illumination gradient on synthetic renders.
    pub lighting: f32,
    /// Renders train only the views with fewer real training photos than this (the others learn
    /// from their real photos alone); `usize::MAX`: every view gets renders. Default 40: only the
    /// frontal view (79 real photos of the 21 training persons, 109 of all 30; the next largest
    /// has 16/20) goes without. Measured on held-out persons, refined by C-ASM: frontal views mean
    /// d_eye 0.0178 → 0.0165 (C-ASM 0.0170), turned 0.0214 → 0.0218, spot light/free 0.0252 →
    /// 0.0260, all 0.0215 → 0.0214; real photos alone also for the ±30° views (threshold 10):
    /// turned 0.0227, and the view refinement lost turned photos.
    pub renders_below_real: usize,
    pub seed: u64,
}

impl Asm3dTrainOptions {
    /// The profile model's settings (`models/asm3d-profile.bin`): the views in 15° steps from
    /// −90° to +90°; those beyond ±45° learn from renders alone (IMM's photos turn to about ±30°).
    pub fn profile() -> Self {
        Self { yaws: (-6..=6).map(|k| 15.0 * k as f32).collect(), ..Self::default() }
    }
}

impl Default for Asm3dTrainOptions {
    fn default() -> Self {
        Self {
            params: SearchParams::default(),
            yaws: (-3..=3).map(|k| 15.0 * k as f32).collect(),
            pdm_shapes: 300,
            shape_variance: 0.98,
            constrain: 3.0,
            sift_modes: 12,
            profile_ridge: 0.05,
            texture_size: 512,
            lighting: 0.3,
            renders_below_real: 40,
            seed: 7,
        }
    }
}

/// 3D PDMs for every yaw: `count` shapes drawn from the 3DMM (standard normal coefficients,
/// `seed`), their 58 points at the vertices an annotator would mark at that yaw. (Measured: giving
/// half of the shapes a random expression blendshape made the held-out mouth error worse.)
pub fn train_pdms(fm: &FaceModel, yaws: &[f32], jaw: &JawVertices, count: usize, variance: f64, constrain: f32, seed: u64) -> Vec<Pdm3d> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let m = fm.shape.component_count();
    let mut per_view: Vec<Vec<Vec<[f32; 3]>>> = vec![Vec::with_capacity(count); yaws.len()];
    for _ in 0..count {
        let alpha: Vec<f64> = (0..m).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
        let psi: [f64; 0] = [];
        // The vertices the correspondence can use, computed once per shape.
        let mut cache: std::collections::HashMap<u32, [f64; 3]> = std::collections::HashMap::new();
        for &v in fm
            .imm_vertices
            .iter()
            .chain(&fm.contour_image_left)
            .chain(&fm.contour_image_right)
            .chain(&fm.cheek_image_left)
            .chain(&fm.cheek_image_right)
            .chain(jaw)
        {
            cache.entry(v).or_insert_with(|| fm.vertex(v as usize, &alpha, &psi));
        }
        let vertex = |v: u32| cache.get(&v).copied().unwrap_or_else(|| fm.vertex(v as usize, &alpha, &psi));
        for (slot, &yaw) in per_view.iter_mut().zip(yaws) {
            let cam = Camera::from_pose(Pose { yaw, pitch: 0.0, roll: 0.0 }, 1.0, 0.0, 0.0);
            let corr = view_correspondence(fm, &vertex, &cam, jaw);
            slot.push(corr.iter().map(|&v| vertex(v)).map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]).collect());
        }
    }
    per_view.iter().map(|shapes| train_pdm3d(shapes, variance, constrain)).collect()
}

/// Per-view texture statistics accumulated during training.
struct ViewSamples {
    profiles: Vec<Vec<Vec<Vec<f32>>>>,
    sifts: Vec<Vec<Vec<Vec<f32>>>>,
    shapes: Vec<Vec<Point>>,
    real: usize,
    scale_per_width: Vec<f32>,
    dx: Vec<f32>,
    dy: Vec<f32>,
}

impl ViewSamples {
    fn new(levels: usize) -> ViewSamples {
        ViewSamples {
            profiles: vec![vec![Vec::new(); IMM_POINTS]; levels],
            sifts: vec![vec![Vec::new(); IMM_POINTS]; levels],
            shapes: Vec::new(),
            real: 0,
            scale_per_width: Vec::new(),
            dx: Vec::new(),
            dy: Vec::new(),
        }
    }

    /// Texture samples at `points` of `gray`, in the crop at the model's fixed scale.
    fn add(
        &mut self,
        gray: &GrayF32,
        points: &[Point],
        px_per_mm: f64,
        crop_px_per_mm: f32,
        params: &SearchParams,
        neighbours: &[[u16; 2]],
    ) {
        let frame = crop_frame(crop_px_per_mm / px_per_mm as f32, centroid(points), params.crop_size);
        let levels = pyramid(frame.crop(gray, params.crop_size), params.levels);
        let in_crop: Vec<Point> = points.iter().map(|&q| frame.to_crop(q)).collect();
        let mut nrm = Vec::new();
        for (l, lvl) in levels.iter().enumerate() {
            let pts: Vec<Point> = in_crop.iter().map(|&q| to_level(q, l)).collect();
            normals(&pts, neighbours, &mut nrm);
            for i in 0..IMM_POINTS {
                self.profiles[l][i].push(profile::profile(&lvl.image, pts[i], nrm[i]).to_vec());
                self.sifts[l][i].push(sift::descriptor(&lvl.gradients, pts[i], nrm[i]).to_vec());
            }
        }
        self.shapes.push(points.to_vec());
    }
}

/// Neighbours of each point on its contour, from the `.asf` connectivity.
fn neighbours(sample: &ImmSample) -> Result<Vec<[u16; 2]>, LandmarkError> {
    let shape = dataset::read_asf(&sample.asf, 1.0, 1.0).map_err(|e| LandmarkError::Training(e.to_string()))?;
    Ok(shape.points.iter().map(|p| [p.from.min(57) as u16, p.to.min(57) as u16]).collect())
}

/// A view's texture models (and its 2D shape models) from its samples, as a 2D C-ASM model.
fn view_textures(v: &ViewSamples, p: &SearchParams, neighbours: &[[u16; 2]], options: &Asm3dTrainOptions, info: &TrainInfo) -> AsmModel {
    let full = train_shape_model(&v.shapes, p.ref_width, options.shape_variance, options.constrain);
    let group = |range: std::ops::Range<usize>| {
        let sub: Vec<Vec<Point>> = v.shapes.iter().map(|s| s[range.clone()].to_vec()).collect();
        let (x0, x1) = full.mean[range].iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
        train_shape_model(&sub, x1 - x0, options.shape_variance, options.constrain)
    };
    let (contour, internal) = (group(JAW), group(facegate_core::face::INTERNAL));
    let profiles = v.profiles.iter().map(|lv| lv.iter().map(|s| train_full_gaussian(s, options.profile_ridge)).collect()).collect();
    let sifts = v
        .sifts
        .iter()
        .map(|lv| {
            lv.iter().enumerate().map(|(i, s)| train_pca_gaussian(s, if JAW.contains(&i) { 1 } else { options.sift_modes })).collect()
        })
        .collect();
    AsmModel {
        format: facegate_vision::landmarks::MODEL_FORMAT,
        params: p.clone(),
        neighbours: neighbours.to_vec(),
        full,
        internal,
        contour,
        profiles,
        sifts,
        starts: Vec::new(),
        info: info.clone(),
    }
}

/// Mean C-ASM texture cost (SIFT for internal points, profiles for the jaw) of a view's own
/// samples on the coarsest level.
fn typical_cost(textures: &AsmModel, v: &ViewSamples) -> f32 {
    let top = textures.sifts.len() - 1;
    let n = v.shapes.len();
    let mut scratch = vec![0.0f32; sift::DESCRIPTOR_LEN];
    let mut total = 0.0f64;
    for k in 0..n {
        for i in 0..IMM_POINTS {
            total += if JAW.contains(&i) {
                textures.profiles[top][i].distance(&v.profiles[top][i][k])
            } else {
                textures.sifts[top][i].distance(&v.sifts[top][i][k], &mut scratch)
            } as f64;
        }
    }
    (total / n.max(1) as f64) as f32
}

/// Train the 3D-ASM on annotated IMM photos. `tick` is called once per photo.
pub fn train(
    samples: &[ImmSample],
    fm: &FaceModel,
    detector: Option<&Detector>,
    options: &Asm3dTrainOptions,
    tick: &dyn Fn(),
) -> Result<Asm3dModel, LandmarkError> {
    train_with_jaw(samples, fm, detector, options, tick).map(|(model, _)| model)
}

/// [`train`], with the jaw vertices learnt from the photos' 3DMM fits (the profile model's
/// visibility reads the views' points at them).
fn train_with_jaw(
    samples: &[ImmSample],
    fm: &FaceModel,
    detector: Option<&Detector>,
    options: &Asm3dTrainOptions,
    tick: &dyn Fn(),
) -> Result<(Asm3dModel, JawVertices), LandmarkError> {
    if samples.len() < 3 {
        return Err(LandmarkError::Training(format!("{} annotated photos; at least 3 are needed", samples.len())));
    }
    if options.yaws.is_empty() {
        return Err(LandmarkError::Training("no view bins".into()));
    }
    let p = &options.params;
    // The 3DMM fitted to every photo's annotation first: the fits' jaw vertices give the
    // annotators' jaw convention on the mesh, which the 3D PDMs and the renders follow.
    let fits = fit_annotations(samples, fm)?;
    let jaw = annotated_jaw_vertices(fm, &fits.iter().flatten().collect::<Vec<_>>());
    let mut real_per_view = vec![0usize; options.yaws.len()];
    for f in fits.iter().flatten() {
        real_per_view[nearest_view(&options.yaws, f.pose.yaw)] += 1;
    }
    let mut pdms = train_pdms(fm, &options.yaws, &jaw, options.pdm_shapes.max(10), options.shape_variance, options.constrain, options.seed);
    // The crop scale: the frontal mean's x extent at the 2D models' reference width.
    let frontal = &pdms[nearest_view(&options.yaws, 0.0)];
    let (x0, x1) = frontal.mean.iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
    let crop_px_per_mm = p.ref_width / (x1 - x0).max(1.0);
    let neighbours = neighbours(&samples[0])?;
    let mut views: Vec<ViewSamples> = options.yaws.iter().map(|_| ViewSamples::new(p.levels)).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(options.seed ^ 0x5eed);
    let photos = RealPhotos { fm, detector, jaw: &jaw, options, real_per_view: &real_per_view, crop_px_per_mm, neighbours: &neighbours };
    let mut learnt = Learnt::new();
    for (sample, fit) in samples.iter().zip(fits) {
        photos.add(&mut learnt, &mut views, sample, fit, &mut rng)?;
        tick();
    }
    follow_annotation_convention(&mut pdms, &learnt.mean_offset, learnt.fitted_photos);
    let Learnt { misses, detected, failures, annotation_boxes, real_fits, .. } = learnt;
    let start_scales = start_scales(&pdms, &real_fits);
    let box_source = if detected >= 3 { BoxSource::Detector } else { BoxSource::Annotation };
    let own = view_placements(&mut views, box_source, &annotation_boxes)?;
    let mut persons: Vec<u32> = samples.iter().map(|s| s.person).collect();
    persons.dedup();
    let info = TrainInfo { images: samples.len(), persons: persons.clone(), box_source, detector_misses: misses };
    let out_views = finish_views(views, pdms, &own, &start_scales, &neighbours, options, &info)?;
    let model = Asm3dModel {
        format: ASM3D_FORMAT,
        params: p.clone(),
        crop_px_per_mm,
        sigma_px: 4.0,
        views: out_views,
        info: Asm3dInfo {
            photos: samples.len(),
            persons,
            box_source,
            detector_misses: misses,
            fit_failures: failures,
            pdm_shapes: options.pdm_shapes,
            seed: options.seed,
        },
    };
    Ok((model, jaw))
}

/// What the real training photos gave besides their texture samples: the detector's misses and
/// hits, the photos the 3DMM could not fit, each photo's annotation box and fit (for the views'
/// placements and start scales), and the summed annotation offsets of the fitted ones.
struct Learnt {
    misses: usize,
    detected: usize,
    failures: usize,
    annotation_boxes: Vec<(usize, f32, Rect, Point)>,
    /// (view, fitted camera, annotation) of every real photo, for the start scale.
    real_fits: Vec<(usize, Camera, Vec<Point>)>,
    mean_offset: Vec<[f64; 3]>,
    fitted_photos: usize,
}

impl Learnt {
    fn new() -> Learnt {
        Learnt {
            misses: 0,
            detected: 0,
            failures: 0,
            annotation_boxes: Vec::new(),
            real_fits: Vec::new(),
            mean_offset: vec![[0.0f64; 3]; IMM_POINTS],
            fitted_photos: 0,
        }
    }
}

/// How the real training photos are learnt from: the 3DMM, the detector, the learnt jaw
/// vertices, the settings, the real photos per view, the crop scale and contour neighbours.
struct RealPhotos<'a> {
    fm: &'a FaceModel,
    detector: Option<&'a Detector>,
    jaw: &'a JawVertices,
    options: &'a Asm3dTrainOptions,
    real_per_view: &'a [usize],
    crop_px_per_mm: f32,
    neighbours: &'a [[u16; 2]],
}

impl RealPhotos<'_> {
    /// One photo with its 3DMM `fit` (`None`: a fit failure) added to the `views`' texture
    /// samples, as itself at its fitted yaw and rendered at the others, and to `learnt`.
    fn add(
        &self,
        learnt: &mut Learnt,
        views: &mut [ViewSamples],
        sample: &ImmSample,
        fit: Option<facegate_morph::FittedFace>,
        rng: &mut impl Rng,
    ) -> Result<(), LandmarkError> {
        let (fm, options, p) = (self.fm, self.options, &self.options.params);
        let photo = imaging::open(&sample.image).map_err(|e| LandmarkError::Training(e.to_string()))?;
        let shape = sample.landmarks().map_err(|e| LandmarkError::Training(e.to_string()))?;
        let Some(fit) = fit else {
            learnt.failures += 1;
            return Ok(());
        };
        // The photo itself trains the view of its fitted yaw, and places that view's start.
        let real_view = nearest_view(&options.yaws, fit.pose.yaw);
        views[real_view].add(&photo.gray, &shape, fit.camera.scale, self.crop_px_per_mm, p, self.neighbours);
        views[real_view].real += 1;
        let c = centroid(&shape);
        learnt.annotation_boxes.push((real_view, fit.camera.scale as f32, crate::train_asm::annotation_box(&shape), c));
        learnt.real_fits.push((real_view, fit.camera, shape.clone()));
        if let Some(det) = self.detector {
            match crate::train_asm::detector_box(det, &photo.gray, &shape) {
                Some(b) => {
                    learnt.detected += 1;
                    let v = &mut views[real_view];
                    v.scale_per_width.push(fit.camera.scale as f32 / b.width);
                    v.dx.push((c[0] - b.center()[0]) / b.width);
                    v.dy.push((c[1] - b.center()[1]) / b.width);
                }
                None => learnt.misses += 1,
            }
        }
        let mut offsets = annotation_offsets(fm, &fit, &shape);
        let photo_jaw = photo_jaw_vertices(fm, &fit, self.jaw);
        // A jaw point moved to the learnt vertex has no offset from it.
        for j in JAW.filter(|&j| photo_jaw[j] != fit.correspondence[j]) {
            offsets[j] = [0.0; 3];
        }
        for (acc, d) in learnt.mean_offset.iter_mut().zip(&offsets) {
            (0..3).for_each(|k| acc[k] += d[k]);
        }
        learnt.fitted_photos += 1;
        let renders =
            Renders { fm, fit: &fit, jaw: &photo_jaw, offsets: &offsets, crop_px_per_mm: self.crop_px_per_mm, neighbours: self.neighbours };
        renders.add_to(views, &photo, self.real_per_view, options, rng);
        Ok(())
    }
}

/// The 3D PDMs' means follow the annotation convention too: the mean offset (`offset_sum` over
/// `fitted_photos`) of the internal points and the chin over the training photos.
fn follow_annotation_convention(pdms: &mut [Pdm3d], offset_sum: &[[f64; 3]], fitted_photos: usize) {
    for pdm in pdms.iter_mut() {
        for (i, (m, d)) in pdm.mean.iter_mut().zip(offset_sum).enumerate() {
            if fitted_photos > 0 && (!JAW.contains(&i) || i == 6) {
                (0..3).for_each(|k| m[k] += (d[k] / fitted_photos as f64) as f32);
            }
        }
    }
}

/// The 3DMM fitted to every photo's annotated landmarks (`None` where the fit fails).
fn fit_annotations(samples: &[ImmSample], fm: &FaceModel) -> Result<Vec<Option<facegate_morph::FittedFace>>, LandmarkError> {
    let mut fits = Vec::with_capacity(samples.len());
    for sample in samples {
        let shape = sample.landmarks().map_err(|e| LandmarkError::Training(e.to_string()))?;
        let (w, h) = image::image_dimensions(&sample.image).map_err(|e| LandmarkError::Training(e.to_string()))?;
        fits.push(fm.fit(&shape, w, h).ok());
    }
    Ok(fits)
}

/// One fitted training photo rendered at other views: its fit, its jaw vertices and annotation
/// offsets, and the crop scale and contour neighbours the texture samples are taken with.
struct Renders<'a> {
    fm: &'a FaceModel,
    fit: &'a facegate_morph::FittedFace,
    jaw: &'a JawVertices,
    offsets: &'a [[f64; 3]],
    crop_px_per_mm: f32,
    neighbours: &'a [[u16; 2]],
}

impl Renders<'_> {
    /// Adds the photo's face, textured from `photo` and rendered at each view's yaw under a random
    /// side light, to the texture samples of every view with fewer real photos than
    /// `options.renders_below_real`.
    fn add_to(
        &self,
        views: &mut [ViewSamples],
        photo: &imaging::Photo,
        real_per_view: &[usize],
        options: &Asm3dTrainOptions,
        rng: &mut impl Rng,
    ) {
        let texture = self.fm.extract_texture(&photo.rgb, self.fit, options.texture_size);
        let background = background_colour(&photo.rgb);
        for (vi, &yaw) in options.yaws.iter().enumerate() {
            // Drawn for every view, so that leaving renders out does not change the others' lighting.
            let gain = options.lighting * (2.0 * rng.random::<f32>() - 1.0);
            if real_per_view[vi] >= options.renders_below_real {
                continue;
            }
            let pose = Pose { yaw, pitch: self.fit.pose.pitch, roll: 0.0 };
            let view = synthesise_view(self.fm, self.fit, &texture, pose, background, gain, self.jaw, self.offsets);
            views[vi].add(&view.gray, &view.points, view.camera.scale, self.crop_px_per_mm, &options.params, self.neighbours);
        }
    }
}

/// The profile model: [`train`] with `options`' views (normally [`Asm3dTrainOptions::profile`]),
/// each view's visibility and the mean face's five detector points.
pub fn train_profile(
    samples: &[ImmSample],
    fm: &FaceModel,
    detector: Option<&Detector>,
    options: &Asm3dTrainOptions,
    tick: &dyn Fn(),
) -> Result<ProfileModel, LandmarkError> {
    let (asm3d, jaw) = train_with_jaw(samples, fm, detector, options, tick)?;
    let visible = options.yaws.iter().map(|&yaw| view_visibility(fm, &jaw, yaw)).collect();
    Ok(ProfileModel { format: PROFILE_FORMAT, asm3d, visible, key_points: fm.key_point_vertices().map(|p| p.map(|c| c as f32)) })
}

/// Each view's own start placement (the medians over its photos, from the detector's boxes or,
/// with `BoxSource::Annotation`, from the annotations' boxes) when it has 3 photos or more.
fn view_placements(
    views: &mut [ViewSamples],
    box_source: BoxSource,
    annotation_boxes: &[(usize, f32, Rect, Point)],
) -> Result<Vec<Option<Placement>>, LandmarkError> {
    if box_source == BoxSource::Annotation {
        for v in views.iter_mut() {
            v.scale_per_width.clear();
            v.dx.clear();
            v.dy.clear();
        }
        for (vi, scale, b, c) in annotation_boxes {
            let v = &mut views[*vi];
            v.scale_per_width.push(scale / b.width);
            v.dx.push((c[0] - b.center()[0]) / b.width);
            v.dy.push((c[1] - b.center()[1]) / b.width);
        }
    }
    let own: Vec<Option<Placement>> = views
        .iter_mut()
        .map(|v| {
            if v.scale_per_width.len() < 3 {
                return None;
            }
            Some(Placement {
                scale_per_width: facegate_core::median(&mut v.scale_per_width)?,
                dx: facegate_core::median(&mut v.dx)?,
                dy: facegate_core::median(&mut v.dy)?,
            })
        })
        .collect();
    if own.iter().all(|o| o.is_none()) {
        return Err(LandmarkError::Training("no view has 3 photos with a face box".into()));
    }
    Ok(own)
}

/// The trained views: per view its 3D PDM, its texture models, its placement (its own when it has
/// one, else the nearest view's) and its start scale.
fn finish_views(
    views: Vec<ViewSamples>,
    pdms: Vec<Pdm3d>,
    own: &[Option<Placement>],
    start_scales: &[f32],
    neighbours: &[[u16; 2]],
    options: &Asm3dTrainOptions,
    info: &TrainInfo,
) -> Result<Vec<View3d>, LandmarkError> {
    let mut out_views = Vec::with_capacity(views.len());
    for (vi, (v, pdm)) in views.into_iter().zip(pdms).enumerate() {
        if v.shapes.len() < 3 {
            return Err(LandmarkError::Training(format!("view {} has {} training shapes", options.yaws[vi], v.shapes.len())));
        }
        let placement = (0..own.len())
            .filter_map(|k| own[k].map(|pl| (k.abs_diff(vi), pl)))
            .min_by_key(|(d, _)| *d)
            .map(|(_, pl)| pl)
            .expect("one view has a placement");
        let textures = view_textures(&v, &options.params, neighbours, options, info);
        let typical_cost = typical_cost(&textures, &v);
        out_views.push(View3d {
            yaw: options.yaws[vi],
            pdm,
            textures,
            placement,
            start_scale: start_scales[vi],
            samples: v.shapes.len(),
            real_photos: v.real,
            typical_cost,
        });
    }
    Ok(out_views)
}

/// Per view, the median ratio of the least-squares scale of the view's PDM mean onto a real
/// photo's annotation (under the photo's fitted rotation) to the photo's fitted camera scale; views
/// with fewer than 3 real photos take the nearest view's that has, 1 when none has.
fn start_scales(pdms: &[Pdm3d], real_fits: &[(usize, Camera, Vec<Point>)]) -> Vec<f32> {
    let mut ratios: Vec<Vec<f32>> = vec![Vec::new(); pdms.len()];
    for (view, camera, shape) in real_fits {
        let unit = Camera { scale: 1.0, tx: 0.0, ty: 0.0, ..*camera };
        let mean = pdms[*view].project(&vec![0.0; pdms[*view].modes()], &unit);
        let (qc, ac) = (centroid(&mean), centroid(shape));
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for (q, a) in mean.iter().zip(shape) {
            let (qx, qy) = ((q[0] - qc[0]) as f64, (q[1] - qc[1]) as f64);
            num += qx * (a[0] - ac[0]) as f64 + qy * (a[1] - ac[1]) as f64;
            den += qx * qx + qy * qy;
        }
        let ratio = num / den / camera.scale;
        if den > 0.0 && ratio.is_finite() && ratio > 0.0 {
            ratios[*view].push(ratio as f32);
        }
    }
    let own: Vec<Option<f32>> = ratios.iter_mut().map(|r| if r.len() >= 3 { facegate_core::median(r) } else { None }).collect();
    (0..pdms.len())
        .map(|vi| (0..own.len()).filter_map(|k| own[k].map(|r| (k.abs_diff(vi), r))).min_by_key(|(d, _)| *d).map_or(1.0, |(_, r)| r))
        .collect()
}
