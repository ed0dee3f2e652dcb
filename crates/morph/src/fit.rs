//! Fitting the model to 2D landmarks, as in eos: a scaled orthographic camera from 2D–3D
//! correspondences (linear affine estimate, then the nearest scaled rotation), a regularised
//! linear shape fit (Aldrian & Smith), the jaw correspondences updated along the model contour,
//! a few iterations.
//!
//! Coordinates: model x to the subject's left, y up, z towards the camera (millimetres). The camera
//! maps a model point `p` to the image (pixels, y down) as
//! `u = s·(r₀·p) + tx`, `v = ty − s·(r₁·p)`; `r₂` is the viewing depth (larger = nearer).
//! `R = Rz(roll)·Rx(pitch)·Ry(yaw)`, so (see `Pose`): yaw > 0 when the nose points to the image right
//! (the subject turned to their left), pitch > 0 when the head tilts down, roll > 0 when the head
//! tilts so that the image-right eye rises (counter-clockwise as seen in the image).

use nalgebra::Matrix2x3;

use super::{Camera, FaceModel, MorphError, Pose};
use facegate_core::face::{IMM_POINTS, JAW};
use facegate_core::geometry::Point;

/// Parameters of the fit (eos defaults).
#[derive(Debug, Clone, Copy)]
pub struct FitOptions {
    /// Camera / shape / contour iterations.
    pub iterations: usize,
    /// Shape regularisation λ (on coefficients in standard deviations).
    pub lambda: f64,
    /// Standard deviation of the landmark positions in pixels (eos: √3).
    pub landmark_sigma_px: f64,
    /// Fit the 6 expression blendshapes too (when loaded).
    pub expressions: bool,
    /// Regularisation of the expression coefficients.
    pub expression_lambda: f64,
    /// Weight of the sliding jaw landmarks relative to the others (`1/k²` for a standard deviation
    /// `k` times larger): their model correspondence is a nearest outline vertex, found with the
    /// mean shape's normals, and full-weight jaw points pull the pose towards the shape prior
    /// (see docs/morph.md).
    pub jaw_weight: f64,
    /// A weight per IMM point multiplying the others (`None`: 1 each): on a profile, the points
    /// the head hides count for little (their positions are the landmark search's guesses).
    pub point_weights: Option<[f64; IMM_POINTS]>,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            iterations: 5,
            lambda: 30.0,
            landmark_sigma_px: 3f64.sqrt(),
            expressions: false,
            expression_lambda: 10.0,
            jaw_weight: 0.25,
            point_weights: None,
        }
    }
}

/// Camera from 2D–3D correspondences: least-squares affine camera (the linear Gold Standard
/// algorithm of Hartley & Zisserman, with centring for conditioning), then the nearest scaled
/// orthographic camera: rows orthonormalised through the SVD, scale = mean singular value.
pub fn estimate_camera(model_points: &[[f64; 3]], image_points: &[Point], weights: &[f64]) -> Result<Camera, MorphError> {
    let n = model_points.len();
    let sw: f64 = weights.iter().sum();
    if n < 4 || sw <= 0.0 {
        return Err(MorphError::Degenerate("fewer than 4 correspondences".into()));
    }
    // Centre both sets (the translation then falls out) and work in y-up image coordinates.
    let mut cx = [0.0f64; 3];
    let mut cu = [0.0f64; 2];
    for i in 0..n {
        for d in 0..3 {
            cx[d] += weights[i] * model_points[i][d];
        }
        cu[0] += weights[i] * image_points[i][0] as f64;
        cu[1] -= weights[i] * image_points[i][1] as f64;
    }
    cx.iter_mut().for_each(|c| *c /= sw);
    cu.iter_mut().for_each(|c| *c /= sw);
    let mut xtx = nalgebra::Matrix3::<f64>::zeros();
    let mut xtu = Matrix2x3::<f64>::zeros();
    for i in 0..n {
        let x = nalgebra::Vector3::new(model_points[i][0] - cx[0], model_points[i][1] - cx[1], model_points[i][2] - cx[2]);
        let u = nalgebra::Vector2::new(image_points[i][0] as f64 - cu[0], -(image_points[i][1] as f64) - cu[1]);
        xtx += weights[i] * x * x.transpose();
        xtu += weights[i] * u * x.transpose();
    }
    let inv = xtx.try_inverse().ok_or_else(|| MorphError::Degenerate("model points are coplanar".into()))?;
    let a = xtu * inv;
    if !a.iter().all(|v| v.is_finite()) {
        return Err(MorphError::Degenerate("non-finite camera".into()));
    }
    let svd = a.svd(true, true);
    let (u, vt) = (svd.u.expect("u requested"), svd.v_t.expect("v_t requested"));
    let (s0, s1) = (svd.singular_values[0], svd.singular_values[1]);
    if s1 <= 1e-6 * s0.max(1e-12) {
        return Err(MorphError::Degenerate("landmarks are collinear".into()));
    }
    let r12 = u * vt;
    let r0 = nalgebra::Vector3::new(r12[(0, 0)], r12[(0, 1)], r12[(0, 2)]);
    let r1 = nalgebra::Vector3::new(r12[(1, 0)], r12[(1, 1)], r12[(1, 2)]);
    let r2 = r0.cross(&r1);
    let scale = 0.5 * (s0 + s1);
    let rotation = [[r0.x, r0.y, r0.z], [r1.x, r1.y, r1.z], [r2.x, r2.y, r2.z]];
    let mut cam = Camera { scale, rotation, tx: 0.0, ty: 0.0 };
    // Translation so that the centroids match: u = s r0·cx + tx ; −v = s r1·cx − ty.
    let pc = cam.rotate(cx);
    cam.tx = cu[0] - scale * pc[0];
    cam.ty = -cu[1] + scale * pc[1];
    Ok(cam)
}

impl Camera {
    pub fn rotate(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2],
        ]
    }

    /// Image position (pixels) and depth (larger = nearer) of a model point.
    pub fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let q = self.rotate(p);
        [self.scale * q[0] + self.tx, self.ty - self.scale * q[1], self.scale * q[2]]
    }

    /// The camera of a pose: `R = Rz(roll)·Rx(pitch)·Ry(yaw)`.
    pub fn from_pose(pose: Pose, scale: f64, tx: f64, ty: f64) -> Camera {
        let (y, p, r) = ((pose.yaw as f64).to_radians(), (pose.pitch as f64).to_radians(), (pose.roll as f64).to_radians());
        let ry = nalgebra::Matrix3::new(y.cos(), 0.0, y.sin(), 0.0, 1.0, 0.0, -y.sin(), 0.0, y.cos());
        let rx = nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, p.cos(), -p.sin(), 0.0, p.sin(), p.cos());
        let rz = nalgebra::Matrix3::new(r.cos(), -r.sin(), 0.0, r.sin(), r.cos(), 0.0, 0.0, 0.0, 1.0);
        let m = rz * rx * ry;
        let rotation = [[m[(0, 0)], m[(0, 1)], m[(0, 2)]], [m[(1, 0)], m[(1, 1)], m[(1, 2)]], [m[(2, 0)], m[(2, 1)], m[(2, 2)]]];
        Camera { scale, rotation, tx, ty }
    }

    /// Yaw, pitch, roll in degrees (inverse of [`Camera::from_pose`]).
    pub fn pose(&self) -> Pose {
        let r = &self.rotation;
        let pitch = r[2][1].clamp(-1.0, 1.0).asin();
        let yaw = (-r[2][0]).atan2(r[2][2]);
        let roll = (-r[0][1]).atan2(r[1][1]);
        Pose { yaw: yaw.to_degrees() as f32, pitch: pitch.to_degrees() as f32, roll: roll.to_degrees() as f32 }
    }
}

/// The result of [`fit_landmarks`].
pub struct FitResult {
    pub camera: Camera,
    /// Shape coefficients in standard deviations.
    pub coefficients: Vec<f32>,
    pub expression: Vec<f32>,
    pub correspondence: [u32; IMM_POINTS],
    pub residual_px: f32,
}

pub fn fit_landmarks(model: &FaceModel, points: &[Point], options: &FitOptions) -> Result<FitResult, MorphError> {
    if points.len() != IMM_POINTS {
        return Err(MorphError::Input(format!("{} landmarks, expected {IMM_POINTS}", points.len())));
    }
    if points.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
        return Err(MorphError::Input("non-finite landmark coordinates".into()));
    }
    let m = model.shape.component_count();
    let ne = if options.expressions { model.blendshapes.len() } else { 0 };
    let mut alpha = vec![0.0f64; m];
    let mut psi = vec![0.0f64; ne];
    let mut corr = model.imm_vertices;
    // First pass without the sliding jaw points (their vertices are unknown until a camera exists).
    let base = options.point_weights.unwrap_or([1.0; IMM_POINTS]);
    let mut weights = base;
    for j in JAW {
        if j != 6 {
            weights[j] = 0.0;
        }
    }
    let mut camera = None;
    let mut model_pts = [[0.0f64; 3]; IMM_POINTS];
    let omega = 1.0 / (options.landmark_sigma_px * options.landmark_sigma_px);
    let mut system = ShapeSystem::new(m, ne);
    for iteration in 0..options.iterations.max(1) {
        for (i, mp) in model_pts.iter_mut().enumerate() {
            *mp = model.vertex(corr[i] as usize, &alpha, &psi);
        }
        let cam = estimate_camera(&model_pts, points, &weights)?;
        if iteration == 0 || options.iterations > 1 {
            update_contour(model, &cam, &alpha, &psi, points, &mut corr);
            for j in JAW {
                weights[j] = base[j] * if j == 6 { 1.0 } else { options.jaw_weight };
            }
        }
        // Shape (and expression) coefficients given the camera.
        system.design(model, &cam, &corr, &weights, points);
        system.normal_equations(omega, options);
        let sol = solve_spd(&system.lhs, &system.rhs, system.cols)
            .ok_or_else(|| MorphError::Degenerate("shape system is not positive definite".into()))?;
        if !sol.iter().all(|v| v.is_finite()) {
            return Err(MorphError::Degenerate("non-finite shape coefficients".into()));
        }
        alpha.copy_from_slice(&sol[..m]);
        psi.copy_from_slice(&sol[m..]);
        camera = Some(cam);
    }
    // Final camera for the final shape, and the residual it leaves.
    for (i, mp) in model_pts.iter_mut().enumerate() {
        *mp = model.vertex(corr[i] as usize, &alpha, &psi);
    }
    let cam = estimate_camera(&model_pts, points, &weights).or_else(|e| camera.ok_or(e))?;
    let mut sq = 0.0f64;
    for i in 0..IMM_POINTS {
        let q = cam.project(model_pts[i]);
        sq += (q[0] - points[i][0] as f64).powi(2) + (q[1] - points[i][1] as f64).powi(2);
    }
    let residual_px = (sq / IMM_POINTS as f64).sqrt() as f32;
    Ok(FitResult {
        camera: cam,
        coefficients: alpha.iter().map(|&a| a as f32).collect(),
        expression: psi.iter().map(|&a| a as f32).collect(),
        correspondence: corr,
        residual_px,
    })
}

/// The regularised least-squares system for the shape (and expression) coefficients given a
/// camera: a row-major design matrix with 2 rows per landmark, and its normal equations.
struct ShapeSystem {
    m: usize,
    ne: usize,
    cols: usize,
    a_rows: Vec<f64>,
    b_vec: Vec<f64>,
    lhs: Vec<f64>,
    rhs: Vec<f64>,
}

impl ShapeSystem {
    fn new(m: usize, ne: usize) -> ShapeSystem {
        let cols = m + ne;
        ShapeSystem {
            m,
            ne,
            cols,
            a_rows: vec![0.0; 2 * IMM_POINTS * cols],
            b_vec: vec![0.0; 2 * IMM_POINTS],
            lhs: vec![0.0; cols * cols],
            rhs: vec![0.0; cols],
        }
    }

    /// The rows for x and y of each point under `cam`, weighted by √weight.
    fn design(&mut self, model: &FaceModel, cam: &Camera, corr: &[u32; IMM_POINTS], weights: &[f64; IMM_POINTS], points: &[Point]) {
        self.a_rows.fill(0.0);
        for i in 0..IMM_POINTS {
            let vid = corr[i] as usize;
            let mean = model.mean_vertex(vid);
            let pm = cam.rotate(mean);
            let w = weights[i].sqrt();
            self.b_vec[2 * i] = w * (points[i][0] as f64 - (cam.scale * pm[0] + cam.tx));
            self.b_vec[2 * i + 1] = w * ((cam.ty - points[i][1] as f64) - cam.scale * pm[1]);
            for d in 0..2 {
                let r = cam.rotation[d];
                for k in 0..self.m {
                    let bx = model.scaled_basis(vid, 0, k);
                    let by = model.scaled_basis(vid, 1, k);
                    let bz = model.scaled_basis(vid, 2, k);
                    self.a_rows[(2 * i + d) * self.cols + k] = w * cam.scale * (r[0] * bx + r[1] * by + r[2] * bz);
                }
                for e in 0..self.ne {
                    let def = &model.blendshapes[e].deformation;
                    let (bx, by, bz) = (def[3 * vid] as f64, def[3 * vid + 1] as f64, def[3 * vid + 2] as f64);
                    self.a_rows[(2 * i + d) * self.cols + self.m + e] = w * cam.scale * (r[0] * bx + r[1] * by + r[2] * bz);
                }
            }
        }
    }

    /// The normal equations by hand, `lhs = AᵀA·ω + Λ`, `rhs = Aᵀb·ω` (our crate is optimised;
    /// nalgebra's dense products go through a dependency that is not, in the dev profile).
    fn normal_equations(&mut self, omega: f64, options: &FitOptions) {
        self.lhs.fill(0.0);
        self.rhs.fill(0.0);
        for r in 0..2 * IMM_POINTS {
            let row = &self.a_rows[r * self.cols..(r + 1) * self.cols];
            let br = self.b_vec[r];
            for p in 0..self.cols {
                let ap = row[p] * omega;
                if ap == 0.0 {
                    continue;
                }
                self.rhs[p] += ap * br;
                let lrow = &mut self.lhs[p * self.cols..(p + 1) * self.cols];
                for q in p..self.cols {
                    lrow[q] += ap * row[q];
                }
            }
        }
        for p in 0..self.cols {
            self.lhs[p * self.cols + p] += if p < self.m { options.lambda } else { options.expression_lambda };
            for q in 0..p {
                self.lhs[p * self.cols + q] = self.lhs[q * self.cols + p];
            }
        }
    }
}

/// Give each jaw landmark (except the chin) the vertex of its side whose projection is nearest to
/// it, among the model contour of that side (`sfm_model_contours.json`) and the cheek vertices that
/// lie on the occluding boundary at the current rotation (normal nearly perpendicular to the viewing
/// direction): as the head turns, the visible jaw outline moves over the mesh, and a fixed contour
/// line would project inside it.
fn update_contour(model: &FaceModel, cam: &Camera, alpha: &[f64], psi: &[f64], points: &[Point], corr: &mut [u32; IMM_POINTS]) {
    let r2 = cam.rotation[2];
    for (side_left, contour, cheek) in
        [(true, &model.contour_image_left, &model.cheek_image_left), (false, &model.contour_image_right, &model.cheek_image_right)]
    {
        let on_boundary = cheek.iter().copied().filter(|&v| {
            let n = model.mean_normals[v as usize];
            (r2[0] * n[0] as f64 + r2[1] * n[1] as f64 + r2[2] * n[2] as f64).abs() < SILHOUETTE_COSINE
        });
        let candidates: Vec<(u32, [f64; 2])> = contour
            .iter()
            .copied()
            .chain(on_boundary)
            .map(|v| {
                let q = cam.project(model.vertex(v as usize, alpha, psi));
                (v, [q[0], q[1]])
            })
            .collect();
        if candidates.is_empty() {
            continue;
        }
        for j in JAW {
            if j == 6 || (j < 6) != side_left {
                continue;
            }
            let p = points[j];
            let mut best = (candidates[0].0, f64::INFINITY);
            for &(v, q) in &candidates {
                let d = (q[0] - p[0] as f64).powi(2) + (q[1] - p[1] as f64).powi(2);
                if d < best.1 {
                    best = (v, d);
                }
            }
            corr[j] = best.0;
        }
    }
}

/// |cos| between a vertex normal and the viewing direction below which the vertex counts as lying
/// on the occluding boundary.
const SILHOUETTE_COSINE: f64 = 0.25;

/// Solve `A x = b` for a symmetric positive definite `A` (`n`×`n`, row-major) by nalgebra's
/// Cholesky factorisation. `None` when `A` is not positive definite.
fn solve_spd(a: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let cholesky = nalgebra::DMatrix::from_row_slice(n, n, a).cholesky()?;
    Some(cholesky.solve(&nalgebra::DVector::from_column_slice(b)).as_slice().to_vec())
}
