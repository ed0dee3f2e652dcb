//! The 3D-ASM search ([`Asm3dLandmarker`]) and the service's switch from the C-ASM on turned faces.

use std::path::Path;

use crate::landmarks::asm3d::*;
use crate::landmarks::search::{self, Frame, Level, Workspace, from_level, pyramid, to_level};
use crate::landmarks::{AsmModel, LandmarkError, Variant};
use facegate_core::face::{EyeMouthCentres, IMM_POINTS};
use facegate_core::geometry::{Point, Rect, centroid};
use facegate_core::imaging::GrayF32;
use facegate_morph::{Camera, Pose};

/// The crop frame with `scale` crop pixels per image pixel and `centre` (image) in the middle.
pub fn crop_frame(scale: f32, centre: Point, crop_size: usize) -> Frame {
    let half = 0.5 * crop_size as f32;
    Frame { scale, origin: [centre[0] - half / scale, centre[1] - half / scale] }
}

/// The 58 points found by the 3D-ASM, with the fitted head pose.
#[derive(Debug, Clone)]
pub struct Asm3dLandmarks {
    pub points: Vec<Point>,
    pub centres: EyeMouthCentres,
    /// Pose of the fitted 3D shape (degrees, the morph module's convention).
    pub pose: Pose,
    /// Yaw of the view whose texture models were used last.
    pub view_yaw: f32,
}

/// The trained 3D-ASM, shareable across threads: the thesis's (`asm3d.bin`, every point counted)
/// or the profile model (`asm3d-profile.bin`, with its views' visibility and the five points that
/// seed it).
pub struct Asm3dLandmarker {
    pub model: Asm3dModel,
    /// Per view, per point, whether the view shows it; empty: every point counts.
    pub visible: Vec<Vec<bool>>,
    /// The mean face's five detector points (`ProfileModel::key_points`); `None` for the thesis's
    /// model, which is not seeded by a detector's points.
    pub key_points: Option<[[f32; 3]; 5]>,
}

/// Distinct views whose best start is searched on the coarse level (measured with the start
/// scale and 2 probe iterations, 0.2 minimum-face boxes: 3 views against 2 lifted held-out
/// d_eye < 0.05 from 94.4% to 96.3% and mouth < 0.1 from 96.3% to 98.1% for ≈ 1.8 ms in the dev
/// profile; with 1 probe iteration 3 views were worse than 2; 1 view lost frontal and spot-light
/// photos).
const SEARCHED_VIEWS: usize = 3;

/// Coarse-level iterations each searched view gets before the best one goes on (measured with the
/// start scale: 2 against 1 lifted held-out d_eye < 0.05 from 90.7% to 94.4%, turned views from
/// 83.3% to 94.4%, for ≈ 0.8 ms).
const PROBE_ITERATIONS: usize = 2;

/// The starts are ranked on every other point (measured: same held-out accuracy as all points at
/// half the ranking time, 2.5 ms against 4.9).
const RANK_POINT_STEP: usize = 2;

/// |yaw| (degrees) of the C-ASM's points ([`Asm3dLandmarker::yaw_of`]) from which the service uses
/// the 3D-ASM (refined by the C-ASM) instead. The crossover measured on renders of held-out faces
/// (`facegate eval landmarks`, `eval::landmarks::crossover`) is at a true |yaw| of 15°: from there
/// on the 3D-ASM has a mean d_eye at least 5% lower and as many d_eye < 0.1; at 0° they are
/// equal. But the C-ASM's points understate the turn (a true 15° gives 5–8°, 45° gives 35–38°, or
/// 8–15° where the C-ASM collapsed to a frontal shape), so the threshold on their yaw is lower:
/// measured d_eye < 0.1 of the switch on the 45° renders 76.6% with 15°, 90.6% with 10°, 93.8%
/// with 5° (the 3D-ASM on every face: 93.8%); held-out IMM photos mean d_eye 0.0213 / 0.0214 /
/// 0.0212 (C-ASM alone 0.0218), frontal views 0.0170 / 0.0170 / 0.0169 (C-ASM 0.0170).
pub const SERVICE_MIN_YAW: f32 = 5.0;

/// Views seeded from the C-ASM's points in the switched path ([`Asm3dLandmarker::fit_seeded`]):
/// the nearest to their yaw and the next on the turned side, each probed with
/// `PROBE_ITERATIONS`, the better one iterated on (measured, held-out views 3–4 mean d_eye /
/// d_eye < 0.05: 1 view 0.0226 / 94.4%; 2 views fully iterated 0.0225 / 94.4%; 2 views probed
/// 0.0218 / 94.4%; the blind search 0.0218 / 100%).
const SEEDED_VIEWS: usize = 2;

/// Weight of a point its view hides in the 3D fit (`ProfileModel::visible`): its texture candidate is
/// whatever surface stands in front of it.
pub const HIDDEN_POINT_WEIGHT: f64 = 0.05;

/// |yaw| (degrees) of the detector's five points from which the service seeds the profile model
/// from them ([`Asm3dLandmarker::fit_from_detector`]) instead of taking the C-ASM's 58 points:
/// the yaw from which the far eye and mouth corner are behind the nose and cheek, and the pose
/// comes from the five points too (`morph::key_points::HIDDEN_SIDE_YAW`). Measured on renders of
/// held-out faces (`facegate eval landmarks`): the seeded search wins from 60° on and is level at
/// 45°; a 30° threshold did better at 60° but moved the points (and the fitted pose) of UMIST's
/// 30–40° photos, where the two searches are level.
pub const DETECTOR_SEED_MIN_YAW: f32 = facegate_morph::key_points::HIDDEN_SIDE_YAW;

/// |yaw| of the chosen view beyond which the refinement is the view's own 3D search on the fine
/// level instead of a 2D model: the 2D models' texture suggestions for the points it hides pull
/// the shape, where the 3D fit weights them by [`HIDDEN_POINT_WEIGHT`].
pub const REFINE_3D_BEYOND_YAW: f32 = 45.0;

/// The camera of [`morph::key_points::key_point_camera`](facegate_morph::key_points::key_point_camera)
/// (the far eye and mouth corner down-weighted past 40°), `None` for non-finite points or a
/// degenerate camera.
fn key_point_camera(model: &[[f64; 3]; 5], points: &[Point; 5]) -> Option<Camera> {
    if points.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
        return None;
    }
    let camera = facegate_morph::key_points::key_point_camera(model, points).ok()?;
    (camera.scale.is_finite() && camera.scale > 0.0).then_some(camera)
}

/// Whether `model` has views, each with 58 points and a texture model per level and point.
fn complete(model: &Asm3dModel) -> bool {
    !model.views.is_empty()
        && model.views.iter().all(|v| {
            v.pdm.points() == IMM_POINTS
                && v.textures.neighbours.len() == IMM_POINTS
                && v.textures.sifts.len() == model.params.levels.max(1)
                && v.textures.profiles.len() == model.params.levels.max(1)
                && v.textures.sifts.iter().all(|l| l.len() == IMM_POINTS)
                && v.textures.profiles.iter().all(|l| l.len() == IMM_POINTS)
        })
}

/// The 2D model that refines the 3D search's coarse result (coarse to fine, `search::search_levels`).
#[derive(Debug, Clone, Copy)]
pub enum Refinement<'a> {
    /// The chosen view's 2D C-ASM: its texture models under its 2D shape models, trained on the
    /// view's real photos and renders.
    View,
    /// A 2D C-ASM (the service's, trained on real photos of all views) from the 3D result.
    Casm(&'a AsmModel),
}

/// The search state: current view, points (level-0 crop pixels) and the last 3D fit.
struct State {
    view: usize,
    points: Vec<Point>,
    camera: Camera,
}

impl Asm3dLandmarker {
    pub fn load(path: &Path) -> Result<Asm3dLandmarker, LandmarkError> {
        let err = |message: String| LandmarkError::Model { path: path.display().to_string(), message };
        let model: Asm3dModel =
            facegate_core::model_file::read_model(path, "3D-ASM model", ASM3D_FORMAT, "facegate train asm3d").map_err(err)?;
        if !complete(&model) {
            return Err(err("the model does not have 58 points and a texture model per level in every view".into()));
        }
        Ok(Asm3dLandmarker::new(model))
    }

    /// The thesis's 3D-ASM: every point counts in the 3D fits.
    pub fn new(model: Asm3dModel) -> Asm3dLandmarker {
        Asm3dLandmarker { model, visible: Vec::new(), key_points: None }
    }

    /// The profile model, searched from a detector's five points ([`fit_from_detector`](Self::fit_from_detector)).
    pub fn from_profile(profile: ProfileModel) -> Asm3dLandmarker {
        Asm3dLandmarker { model: profile.asm3d, visible: profile.visible, key_points: Some(profile.key_points) }
    }

    /// Loads `models/asm3d-profile.bin`.
    pub fn load_profile(path: &Path) -> Result<Asm3dLandmarker, LandmarkError> {
        let err = |message: String| LandmarkError::Model { path: path.display().to_string(), message };
        let profile: ProfileModel =
            facegate_core::model_file::read_model(path, "3D-ASM profile model", PROFILE_FORMAT, "facegate train asm3d --profile")
                .map_err(err)?;
        if !complete(&profile.asm3d) {
            return Err(err("the model does not have 58 points and a texture model per level in every view".into()));
        }
        if profile.visible.len() != profile.asm3d.views.len() || profile.visible.iter().any(|v| v.len() != IMM_POINTS) {
            return Err(err("the model does not give every view's visibility of 58 points".into()));
        }
        Ok(Asm3dLandmarker::from_profile(profile))
    }

    /// Per point, its weight in view `view`'s 3D fit: 1, or [`HIDDEN_POINT_WEIGHT`] for a point
    /// the view hides.
    fn weights(&self, view: usize) -> Vec<f64> {
        let shown = self.visible.get(view);
        (0..IMM_POINTS).map(|i| if shown.and_then(|v| v.get(i)).copied().unwrap_or(true) { 1.0 } else { HIDDEN_POINT_WEIGHT }).collect()
    }

    /// View `view`'s 3D PDM fitted to `targets` (level-0 crop pixels) with its visibility
    /// weights (all 1 for the thesis's model: the same fit as `Pdm3d::fit`).
    fn fit_view(&self, view: usize, targets: &[Point]) -> Option<Fit3d> {
        self.model.views[view].pdm.fit_weighted(targets, &self.weights(view), self.model.sigma_px as f64, 4)
    }

    pub fn save(&self, path: &Path) -> Result<(), LandmarkError> {
        facegate_core::model_file::write_model(path, &self.model)
            .map_err(|message| LandmarkError::Model { path: path.display().to_string(), message })
    }

    fn yaws(&self) -> Vec<f32> {
        self.model.views.iter().map(|v| v.yaw).collect()
    }

    /// Start shapes (level-0 crop pixels): every view's mean, upright and tilted ±`roll_start`.
    fn starts(&self, face: &Rect, frame: &Frame) -> Vec<State> {
        let m = &self.model;
        let roll = m.params.roll_start;
        let front = nearest_view(&self.yaws(), 0.0);
        let reference = m.views[front].placement.scale_per_width;
        let mut out = Vec::new();
        for (vi, view) in m.views.iter().enumerate() {
            let pl = &view.placement;
            let scale = (m.crop_px_per_mm * pl.scale_per_width / reference.max(1e-9) * view.start_scale) as f64;
            let c = face.center();
            let target = frame.to_crop([c[0] + pl.dx * face.width, c[1] + pl.dy * face.width]);
            // Tilted starts for every view (measured: with tilts for the frontal view only, two
            // more turned held-out photos failed).
            let rolls: &[f32] = if roll > 0.0 { &[0.0, 1.0, -1.0] } else { &[0.0] };
            for &r in rolls {
                let mut camera = Camera::from_pose(Pose { yaw: view.yaw, pitch: 0.0, roll: r * roll }, scale, 0.0, 0.0);
                let zero = vec![0.0f32; view.pdm.modes()];
                let pts = view.pdm.project(&zero, &camera);
                let got = centroid(&pts);
                camera.tx += (target[0] - got[0]) as f64;
                camera.ty += (target[1] - got[1]) as f64;
                out.push(State { view: vi, points: view.pdm.project(&zero, &camera), camera });
            }
        }
        out
    }

    /// One iteration on `level`: candidates by the current view's textures, 3D fit, view from its
    /// yaw (refitted with that view's PDM when it changed). Returns the texture cost and whether
    /// the configured share of points moved less than a (level) pixel.
    fn iterate(&self, levels: &[Level], level: usize, st: &mut State, ws: &mut Workspace, suggested: &mut Vec<Point>) -> (f32, bool) {
        let m = &self.model;
        let at_level: Vec<Point> = st.points.iter().map(|&p| to_level(p, level)).collect();
        let cost = search::suggest(&m.views[st.view].textures, &levels[level], level, &at_level, Variant::Casm, ws, suggested);
        let targets: Vec<Point> = suggested.iter().map(|&p| from_level(p, level)).collect();
        let Some(mut fit) = self.fit_view(st.view, &targets) else { return (cost, true) };
        let view = nearest_view(&self.yaws(), fit.camera.pose().yaw);
        if view != st.view {
            if let Some(f) = self.fit_view(view, &targets) {
                fit = f;
                st.view = view;
            }
        }
        let pixel = (1 << level) as f32;
        let still = fit.points.iter().zip(&st.points).filter(|(a, b)| facegate_core::geometry::distance(**a, **b) < pixel).count();
        st.points = fit.points;
        st.camera = fit.camera;
        (cost, still as f32 >= m.params.converged_share * IMM_POINTS as f32)
    }

    /// Search the 58 points of the face in `face` (the detector's box), refined by the chosen
    /// view's own 2D model. Never panics: degenerate boxes fall back to the whole image, tiny
    /// images give the placed frontal mean.
    pub fn fit(&self, gray: &GrayF32, face: &Rect) -> Asm3dLandmarks {
        self.fit_with(gray, face, Refinement::View)
    }

    /// Head yaw (degrees, the morph module's sign) of 58 points in image pixels: the frontal view's
    /// 3D PDM fitted to them. `None` for degenerate points.
    pub fn yaw_of(&self, points: &[Point]) -> Option<f32> {
        let m = &self.model;
        let view = &m.views[nearest_view(&self.yaws(), 0.0)];
        // The PDM's prior σ is in crop pixels: fit in the crop's scale.
        let c = centroid(points);
        let scale = {
            let (x0, x1) = points.iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
            m.params.ref_width / (x1 - x0).max(1e-3)
        };
        let local: Vec<Point> = points.iter().map(|p| [scale * (p[0] - c[0]), scale * (p[1] - c[1])]).collect();
        view.pdm.fit(&local, m.sigma_px as f64, 4).map(|f| f.camera.pose().yaw)
    }

    /// The service's landmarks: the C-ASM's (`casm`, already searched by `landmarker` in `face`)
    /// while their [`yaw_of`](Self::yaw_of) is below `min_yaw` degrees, else the 3D-ASM's seeded by
    /// them and refined by the C-ASM ([`fit_seeded`](Self::fit_seeded)). Returns the points and
    /// whether the 3D-ASM was used.
    pub fn switch(
        &self,
        gray: &GrayF32,
        face: &Rect,
        landmarker: &crate::landmarks::Landmarker,
        casm: crate::landmarks::Landmarks,
        min_yaw: f32,
    ) -> (crate::landmarks::Landmarks, bool) {
        match self.yaw_of(&casm.points) {
            Some(yaw) if yaw.abs() >= min_yaw => {
                let r = self.fit_seeded(gray, face, &casm.points, &landmarker.model);
                (crate::landmarks::Landmarks { points: r.points, centres: r.centres }, true)
            }
            _ => (casm, false),
        }
    }

    /// The search's box (degenerate boxes replaced by the whole image) and crop frame.
    fn search_frame(&self, gray: &GrayF32, face: &Rect) -> (Rect, Frame) {
        let m = &self.model;
        let finite = face.x.is_finite() && face.y.is_finite() && face.width.is_finite() && face.height.is_finite();
        let face = if finite && face.width >= 1.0 && face.height >= 1.0 && face.width < 1e6 {
            *face
        } else {
            Rect::new(0.0, 0.0, gray.width.max(1) as f32, gray.height.max(1) as f32)
        };
        let front = nearest_view(&self.yaws(), 0.0);
        let pl = &m.views[front].placement;
        let px_per_mm = (pl.scale_per_width * face.width).max(1e-6);
        let c = face.center();
        let frame = crop_frame(m.crop_px_per_mm / px_per_mm, [c[0] + pl.dx * face.width, c[1] + pl.dy * face.width], m.params.crop_size);
        (face, frame)
    }

    /// The 3D-ASM seeded by the C-ASM's result (`casm_points`, image pixels, found in `face` by
    /// the C-ASM `casm`), refined by that C-ASM: the service's switched path. Instead of ranking
    /// every view's start and probing three views ([`fit_with`](Self::fit_with)), the 3D PDMs of
    /// the view nearest the C-ASM points' yaw and of the next view on the turned side are fitted to
    /// those points, each probed on the coarse level, and the one with the lower texture cost is
    /// iterated on and refined by the C-ASM coarse to fine. Falls back to [`fit_with`](Self::fit_with) when the
    /// points are unusable.
    pub fn fit_seeded(&self, gray: &GrayF32, face: &Rect, casm_points: &[Point], casm: &AsmModel) -> Asm3dLandmarks {
        let m = &self.model;
        let blind = || self.fit_with(gray, face, Refinement::Casm(casm));
        if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height || casm_points.len() != IMM_POINTS {
            return blind();
        }
        let (_, frame) = self.search_frame(gray, face);
        let seed: Vec<Point> = casm_points.iter().map(|&p| frame.to_crop(p)).collect();
        let yaws = self.yaws();
        let sigma = m.sigma_px as f64;
        let Some(yaw) = m.views[nearest_view(&yaws, 0.0)].pdm.fit(&seed, sigma, 4).map(|f| f.camera.pose().yaw) else { return blind() };
        // The view nearest the seed's yaw and, since the C-ASM's points understate the turn, the
        // next view on the turned side.
        let near = nearest_view(&yaws, yaw);
        let mut views = vec![near];
        if SEEDED_VIEWS > 1 {
            let turned = (0..yaws.len())
                .filter(|&v| v != near && (yaws[v] - yaws[near]) * yaw.signum() > 0.0)
                .min_by(|&a, &b| (yaws[a] - yaws[near]).abs().total_cmp(&(yaws[b] - yaws[near]).abs()));
            views.extend(turned);
        }
        let levels = pyramid(frame.crop(gray, m.params.crop_size), m.params.levels);
        let mut ws = Workspace::default();
        let probe = views.len() > 1;
        let seeded: Vec<State> = views
            .into_iter()
            .filter_map(|vi| m.views[vi].pdm.fit(&seed, sigma, 4).map(|fit| State { view: vi, points: fit.points, camera: fit.camera }))
            .collect();
        // As the blind search: `PROBE_ITERATIONS` per seeded view, the rest of `max_iterations`
        // for the better one (measured, held-out views 3–4 mean d_eye: every seeded view iterated
        // to `max_iterations` 0.0225, to 2 only 0.0227, probed 0.0218).
        let Some(st) = self.search_coarse(&levels, seeded, probe, &mut ws) else { return blind() };
        self.refine(&levels, &frame, st, casm, &mut ws)
    }

    /// The mean face's five detector points in double precision (profile model only).
    fn key_point_model(&self) -> Option<[[f64; 3]; 5]> {
        self.key_points.map(|k| k.map(|p| p.map(f64::from)))
    }

    /// The head's yaw (degrees) from the detector's five points: the mean face's posed onto them
    /// ([`key_point_camera`]). `None` for degenerate points.
    pub fn detector_yaw(&self, points: &[Point; 5]) -> Option<f32> {
        key_point_camera(&self.key_point_model()?, points).map(|c| c.pose().yaw)
    }

    /// The 3D-ASM seeded by a multi-view detector's five points (`points`, image pixels: eyes,
    /// nose tip, mouth corners), for heads turned too far for the C-ASM: the mean shapes of the
    /// view nearest the points' yaw and of the next view on the turned side are posed onto them
    /// ([`key_point_camera`]) in a crop at the model's fixed scale, each probed on the coarse level,
    /// the one with the lower texture cost iterated on; then refined coarse to fine by `casm` when
    /// the chosen view is within [`REFINE_3D_BEYOND_YAW`], else by the view's own 3D search on the
    /// fine level. `None` when the points are degenerate.
    pub fn fit_from_detector(&self, gray: &GrayF32, points: &[Point; 5], casm: &AsmModel) -> Option<Asm3dLandmarks> {
        let m = &self.model;
        if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height {
            return None;
        }
        let yaws = self.yaws();
        let front = &m.views[nearest_view(&yaws, 0.0)];
        let model = self.key_point_model()?;
        let camera = key_point_camera(&model, points)?;
        let yaw = camera.pose().yaw;
        // The crop at the model's fixed pixels per mm, centred on the posed mean shape.
        let posed = front.pdm.project(&vec![0.0; front.pdm.modes()], &camera);
        let frame = crop_frame(m.crop_px_per_mm / camera.scale as f32, centroid(&posed), m.params.crop_size);
        let in_crop: [Point; 5] = points.map(|p| frame.to_crop(p));
        let camera = key_point_camera(&model, &in_crop)?;
        let near = nearest_view(&yaws, yaw);
        let turned = (0..yaws.len())
            .filter(|&v| v != near && (yaws[v] - yaws[near]) * yaw.signum() > 0.0)
            .min_by(|&a, &b| (yaws[a] - yaws[near]).abs().total_cmp(&(yaws[b] - yaws[near]).abs()));
        let seeded: Vec<State> = std::iter::once(near)
            .chain(turned)
            .map(|vi| {
                let pdm = &m.views[vi].pdm;
                State { view: vi, points: pdm.project(&vec![0.0; pdm.modes()], &camera), camera }
            })
            .collect();
        let levels = pyramid(frame.crop(gray, m.params.crop_size), m.params.levels);
        let mut ws = Workspace::default();
        let st = self.search_coarse(&levels, seeded, true, &mut ws)?;
        if m.views[st.view].yaw.abs() <= REFINE_3D_BEYOND_YAW {
            return Some(self.refine(&levels, &frame, st, casm, &mut ws));
        }
        Some(self.refine_3d(&levels, &frame, st, &mut ws))
    }

    /// `st` refined on the finer levels by the 3D search itself (candidates by the view's
    /// textures, the 3D fit with hidden points weighted down), in image pixels.
    fn refine_3d(&self, levels: &[Level], frame: &Frame, mut st: State, ws: &mut Workspace) -> Asm3dLandmarks {
        let mut suggested = Vec::with_capacity(IMM_POINTS);
        for level in (0..levels.len().saturating_sub(1)).rev() {
            for _ in 0..self.model.params.max_iterations {
                if self.iterate(levels, level, &mut st, ws, &mut suggested).1 {
                    break;
                }
            }
        }
        let points: Vec<Point> = st.points.iter().map(|&p| frame.to_image(p)).collect();
        let centres = EyeMouthCentres::from_imm(&points);
        Asm3dLandmarks { points, centres, pose: st.camera.pose(), view_yaw: self.model.views[st.view].yaw }
    }

    /// [`fit`](Self::fit) with the 2D model of the refinement stage chosen by `refinement`.
    pub fn fit_with(&self, gray: &GrayF32, face: &Rect, refinement: Refinement) -> Asm3dLandmarks {
        let m = &self.model;
        let (face, frame) = self.search_frame(gray, face);
        let front = nearest_view(&self.yaws(), 0.0);
        let mut states = self.starts(&face, &frame);
        let finish = |st: &State| {
            let points: Vec<Point> = st.points.iter().map(|&p| frame.to_image(p)).collect();
            let centres = EyeMouthCentres::from_imm(&points);
            Asm3dLandmarks { points, centres, pose: st.camera.pose(), view_yaw: m.views[st.view].yaw }
        };
        if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height {
            let k = states.iter().position(|st| st.view == front).unwrap_or(0);
            return finish(&states.swap_remove(k));
        }
        let levels = pyramid(frame.crop(gray, m.params.crop_size), m.params.levels);
        let mut ws = Workspace::default();
        // Rank the starts by the texture cost where they stand under their own view's models,
        // less that view's typical cost on its training samples.
        let mut ranked: Vec<(f32, State)> = states.into_iter().map(|st| (self.ranking_cost(&levels, &st, &mut ws), st)).collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        // The best starts of the `SEARCHED_VIEWS` best-ranked distinct views are searched on the
        // coarse level; the one with the lowest cost where it converged goes on.
        let mut chosen: Vec<State> = Vec::new();
        for (_, st) in ranked {
            if chosen.len() < SEARCHED_VIEWS && chosen.iter().all(|c| c.view != st.view) {
                chosen.push(st);
            }
        }
        let Some(st) = self.search_coarse(&levels, chosen, true, &mut ws) else {
            return finish(&self.starts(&face, &frame).swap_remove(0));
        };
        // Refinement: the 3D search gives the view and a shape on the coarse level; the view's 2D
        // C-ASM (its texture models under its 2D shape models, trained on the view's real and
        // synthetic shapes, so annotation-convention variation is in them) searches coarse to fine
        // from there. Measured: the 3D PDM alone on the fine level left the points ≈ 4 px off the
        // annotation convention (mean d_eye 0.040 → 0.027); a fine-level-only refinement helped
        // half as much.
        // Measured alternatives to refining in the 3D search's crop (held-out, dev): the C-ASM
        // from the 3D result and its own box-placed starts, cost-ranked: identical (the 3D start
        // always won); the C-ASM in a new crop at its training scale from the 3D result: mean
        // d_eye 0.0216 against 0.0215, d_eye < 0.05 96.3% against 100%.
        let model2d = match refinement {
            Refinement::View => &m.views[st.view].textures,
            Refinement::Casm(casm) => casm,
        };
        self.refine(&levels, &frame, st, model2d, &mut ws)
    }

    /// The texture cost of `st` on the coarse level under its own view's models (every
    /// `RANK_POINT_STEP`-th point), less that view's typical cost for as many points: how the
    /// starts and the probed views are ranked.
    fn ranking_cost(&self, levels: &[Level], st: &State, ws: &mut Workspace) -> f32 {
        let top = levels.len() - 1;
        let pts: Vec<Point> = st.points.iter().map(|&p| to_level(p, top)).collect();
        let view = &self.model.views[st.view];
        let cost = search::texture_cost(&view.textures, &levels[top], top, &pts, RANK_POINT_STEP, Variant::Casm, ws);
        // The typical cost is over all points: scale it to the points ranked on.
        cost - view.typical_cost * pts.len().div_ceil(RANK_POINT_STEP) as f32 / IMM_POINTS as f32
    }

    /// The 3D search on the coarse level from `candidates`: with `probe`, each gets
    /// `PROBE_ITERATIONS` and the one with the lowest [`ranking_cost`](Self::ranking_cost) then
    /// goes on to `max_iterations`; without, the first is iterated to `max_iterations` at once.
    /// `None` without candidates.
    fn search_coarse(&self, levels: &[Level], candidates: Vec<State>, probe: bool, ws: &mut Workspace) -> Option<State> {
        let max = self.model.params.max_iterations;
        let top = levels.len() - 1;
        let mut suggested = Vec::with_capacity(IMM_POINTS);
        let mut run = |st: &mut State, iterations: std::ops::Range<usize>, ws: &mut Workspace| {
            for _ in iterations {
                if self.iterate(levels, top, st, ws, &mut suggested).1 {
                    break;
                }
            }
        };
        if !probe {
            let mut st = candidates.into_iter().next()?;
            run(&mut st, 0..max, ws);
            return Some(st);
        }
        let mut best: Option<(f32, State)> = None;
        for mut st in candidates {
            run(&mut st, 0..PROBE_ITERATIONS.min(max), ws);
            let cost = self.ranking_cost(levels, &st, ws);
            if best.as_ref().is_none_or(|b| cost < b.0) {
                best = Some((cost, st));
            }
        }
        let (_, mut st) = best?;
        run(&mut st, PROBE_ITERATIONS..max, ws);
        Some(st)
    }

    /// `st` refined coarse to fine by the 2D model `model2d` (`search::search_levels`), the pose
    /// from its view's 3D PDM fitted to the refined points, in image pixels.
    fn refine(&self, levels: &[Level], frame: &Frame, mut st: State, model2d: &AsmModel, ws: &mut Workspace) -> Asm3dLandmarks {
        let view = &self.model.views[st.view];
        st.points = search::search_levels(model2d, levels, &[st.points.clone()], Variant::Casm, ws);
        // The pose reported is the 3D PDM's fitted to the refined points.
        if let Some(fit) = self.fit_view(st.view, &st.points) {
            st.camera = fit.camera;
        }
        let points: Vec<Point> = st.points.iter().map(|&p| frame.to_image(p)).collect();
        let centres = EyeMouthCentres::from_imm(&points);
        Asm3dLandmarks { points, centres, pose: st.camera.pose(), view_yaw: view.yaw }
    }
}
