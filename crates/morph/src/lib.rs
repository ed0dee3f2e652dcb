//! The 3D morphable model (thesis chapters 4 and 5): the Surrey Face Model fitted to the 58 IMM
//! landmarks gives the head pose and the 3D shape; the photo's texture, completed by symmetry and
//! rendered from the front, corrects the pose before recognition; the textured mesh is an avatar.
//!
//! - [`model`]: eos file reader; [`correspondence`]: IMM points ↔ vertices;
//! - [`fit`]: camera + shape fit; [`render`]: rasteriser, texture extraction, rendering;
//! - [`export`]: glTF binary and OBJ + MTL + PNG writers.
//!
//! Pose sign convention ([`Pose`]): yaw > 0 when the nose points to the image right (the subject
//! has turned to their own left), pitch > 0 when the head tilts down, roll > 0 when the eye on the
//! image right rises (the face turns counter-clockwise in the image).

pub mod correspondence;
pub mod export;
pub mod fit;
pub mod key_points;
pub mod model;
pub mod render;

use std::path::Path;

use image::{RgbImage, RgbaImage};
use serde::{Deserialize, Serialize};

use facegate_core::face::{EYE_IMAGE_LEFT, EYE_IMAGE_RIGHT, EyeMouthCentres, IMM_POINTS, MOUTH};
use facegate_core::geometry::{Point, centroid};
use facegate_core::imaging::Photo;

pub use fit::FitOptions;
pub use model::{Blendshape, ModelContour, ShapeModel};

/// Head pose in degrees: yaw > 0 when the nose points to the image right (subject turned to their
/// left), pitch > 0 head tilted down, roll > 0 image-right eye higher. `R = Rz(roll)·Rx(pitch)·Ry(yaw)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Pose {
    pub yaw: f32,
    pub pitch: f32,
    pub roll: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum MorphError {
    #[error("cannot load the 3D morphable model from {path}: {message}")]
    Model { path: String, message: String },
    #[error("invalid landmarks: {0}")]
    Input(String),
    #[error("the model cannot be fitted to these landmarks: {0}")]
    Degenerate(String),
    #[error("cannot write {path}: {message}")]
    Export { path: String, message: String },
}

/// A scaled orthographic camera: `u = s·(r₀·p) + tx`, `v = ty − s·(r₁·p)` (pixels, y down),
/// depth `s·(r₂·p)` (larger = nearer).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub scale: f64,
    pub rotation: [[f64; 3]; 3],
    pub tx: f64,
    pub ty: f64,
}

/// Files of the eos SFM distribution that [`FaceModel::load`] reads.
pub const SHAPE_FILE: &str = "sfm_shape_3448.bin";
pub const BLENDSHAPES_FILE: &str = "expression_blendshapes_3448.bin";
pub const CONTOURS_FILE: &str = "sfm_model_contours.json";
pub const SYMMETRY_FILE: &str = "sfm_reference_symmetry.txt";

/// Side of the UV texture extracted from photos on the recognition path (the frontal rendering
/// is 144 px: a finer texture costs time without adding detail there).
pub const TEXTURE_SIZE: usize = 128;
/// Side of the frontal rendering handed to recognition.
pub const FRONTAL_SIZE: usize = 144;
/// Side of an avatar's UV texture unless asked otherwise (`facegate reconstruct`, `POST /avatar`).
pub const AVATAR_TEXTURE_SIZE: usize = 512;
/// Side of the frontal rendering shown to people (`facegate frontalize`, `POST /frontalize`).
pub const FRONTAL_VIEW_SIZE: usize = 256;

/// The file an avatar is exported as.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AvatarFormat {
    /// glTF binary (`model/gltf-binary`), metres, the texture embedded.
    #[default]
    Glb,
    /// `avatar.obj`, `avatar.mtl` and `avatar.png` in one zip archive (`application/zip`).
    Obj,
}

/// A textured avatar: the fitted shape and its UV texture, completed by symmetry. Made by
/// [`FaceModel::avatar`], the one path of `facegate reconstruct` and `POST /avatar`.
#[derive(Debug, Clone)]
pub struct Avatar {
    pub fitted: FittedFace,
    pub texture: RgbaImage,
}

/// The Surrey Face Model with the IMM correspondence, shareable across threads.
pub struct FaceModel {
    pub shape: ShapeModel,
    /// PCA basis scaled by √eigenvalue, row-major (`3·vertex + axis`, component), so that
    /// coefficients are in standard deviations.
    scaled_basis: Vec<f32>,
    /// Expression blendshapes (empty when the file is absent).
    pub blendshapes: Vec<Blendshape>,
    /// Jaw contour vertex ids on the image-left (subject's right) and image-right sides, from the
    /// top of the jaw towards the chin.
    pub contour_image_left: Vec<u32>,
    pub contour_image_right: Vec<u32>,
    /// Cheek and jaw vertices of each side (|x| > 25 mm, between chin and eye height): the
    /// candidates for the occluding jaw outline when the head turns.
    pub cheek_image_left: Vec<u32>,
    pub cheek_image_right: Vec<u32>,
    /// Unit vertex normals of the mean shape (outwards).
    pub mean_normals: Vec<[f32; 3]>,
    /// The vertex of every IMM point (jaw points other than the chin: placeholder, updated by the
    /// fit): the committed table `models/imm_to_sfm.txt` over the geometric anchors.
    pub imm_vertices: [u32; IMM_POINTS],
    /// The mirror vertex of every vertex.
    pub symmetry: Vec<u32>,
    /// The mirror triangle of every triangle (vertex-wise mirror, same barycentric order).
    mirror_triangles: Vec<[u32; 3]>,
    /// ±1 so that [`render::facing_of`] is positive for triangles facing the camera.
    winding: f32,
}

/// The result of fitting the model to 58 IMM landmarks.
#[derive(Debug, Clone)]
pub struct FittedFace {
    pub pose: Pose,
    /// RMS distance (pixels) between the landmarks and the projected model points.
    pub residual_px: f32,
    pub camera: Camera,
    /// Shape coefficients, in standard deviations.
    pub coefficients: Vec<f32>,
    /// Expression blendshape weights (empty unless fitted).
    pub expression: Vec<f32>,
    /// The vertex used for each IMM point (jaw points after the contour update).
    pub correspondence: [u32; IMM_POINTS],
    /// The fitted shape, model coordinates (mm).
    pub vertices: Vec<[f32; 3]>,
    pub image_width: u32,
    pub image_height: u32,
}

/// A frontal rendering and where the eye and mouth centres fall in it.
#[derive(Debug, Clone)]
pub struct Frontal {
    pub image: RgbImage,
    pub centres: EyeMouthCentres,
}

impl FaceModel {
    /// Load the model from an eos SFM folder (see the `*_FILE` constants; the blendshapes are optional).
    pub fn load(sfm_dir: &Path) -> Result<FaceModel, MorphError> {
        let shape_path = sfm_dir.join(SHAPE_FILE);
        if !shape_path.is_file() {
            return Err(MorphError::Model {
                path: sfm_dir.display().to_string(),
                message: format!("{SHAPE_FILE} not found (set FACEGATE_SFM or --sfm to the Surrey Face Model folder)"),
            });
        }
        let shape = model::read_shape_model(&shape_path)?;
        let nv = shape.vertex_count();
        let blend_path = sfm_dir.join(BLENDSHAPES_FILE);
        let blendshapes = if blend_path.is_file() { model::read_blendshapes(&blend_path, nv)? } else { Vec::new() };
        let contour = model::read_contours(&sfm_dir.join(CONTOURS_FILE))?;
        let reference_symmetry = model::read_symmetry(&sfm_dir.join(SYMMETRY_FILE))?;
        Self::from_parts(shape, blendshapes, contour, &reference_symmetry, &sfm_dir.display().to_string())
    }

    fn from_parts(
        shape: ShapeModel,
        blendshapes: Vec<Blendshape>,
        contour: ModelContour,
        reference_symmetry: &[u32],
        path: &str,
    ) -> Result<FaceModel, MorphError> {
        let nv = shape.vertex_count();
        let m = shape.component_count();
        let bad = |message: String| MorphError::Model { path: path.to_string(), message };
        let anchors = correspondence::imm_anchors();
        for a in &anchors {
            let ids = match *a {
                correspondence::Anchor::Vertex(v) => [v, v],
                correspondence::Anchor::Lerp(a, b, _) => [a, b],
                correspondence::Anchor::Contour { .. } => [0, 0],
            };
            if ids.iter().any(|&v| v as usize >= nv) {
                return Err(bad(format!("the IMM correspondence needs vertex {ids:?}, the model has {nv}")));
            }
        }
        if contour.left_contour.iter().chain(&contour.right_contour).any(|&v| v as usize >= nv) {
            return Err(bad("contour vertex out of range".into()));
        }
        let mut scaled_basis = vec![0.0f32; 3 * nv * m];
        for k in 0..m {
            let sd = shape.eigenvalues[k].sqrt();
            for r in 0..3 * nv {
                scaled_basis[r * m + k] = shape.basis[k * 3 * nv + r] * sd;
            }
        }
        // Which model contour lies on the image left of a frontal face: the one with negative x
        // (model x points to the subject's left = image right).
        let mean_x = |ids: &[u32]| ids.iter().map(|&v| shape.mean[3 * v as usize]).sum::<f32>() / ids.len().max(1) as f32;
        let (contour_image_left, contour_image_right) = if mean_x(&contour.right_contour) < mean_x(&contour.left_contour) {
            (contour.right_contour.clone(), contour.left_contour.clone())
        } else {
            (contour.left_contour.clone(), contour.right_contour.clone())
        };
        let geometric = correspondence::resolve(&anchors, &shape.mean);
        let imm_vertices = correspondence::parse_table(correspondence::DERIVED_TABLE, nv, geometric).map_err(bad)?;
        let symmetry = correspondence::complete_symmetry(reference_symmetry, &shape.mean);
        let mirror_triangles = shape.triangles.iter().map(|t| t.map(|v| symmetry[v as usize])).collect();
        // Winding: project the mean from the front and see which sign most triangle normals take.
        let projected: Vec<[f32; 3]> = shape.mean.chunks_exact(3).map(|p| [p[0], -p[1], p[2]]).collect();
        let total: f32 = shape.triangles.iter().map(|&t| render::facing_of(&projected, t, 1.0)).sum();
        let winding = if total >= 0.0 { 1.0 } else { -1.0 };
        let mean_normals = vertex_normals(&shape.mean, &shape.triangles, winding);
        let eye_y = shape.mean[3 * 177 + 1].max(shape.mean[3 * 610 + 1]);
        let chin_y = shape.mean[3 * 33 + 1];
        let cheek = |left: bool| -> Vec<u32> {
            (0..nv as u32)
                .filter(|&v| {
                    let p = &shape.mean[3 * v as usize..3 * v as usize + 3];
                    let side = if left { p[0] < -25.0 } else { p[0] > 25.0 };
                    side && p[1] < eye_y && p[1] > chin_y
                })
                .collect()
        };
        let (cheek_image_left, cheek_image_right) = (cheek(true), cheek(false));
        Ok(FaceModel {
            shape,
            scaled_basis,
            blendshapes,
            contour_image_left,
            contour_image_right,
            cheek_image_left,
            cheek_image_right,
            mean_normals,
            imm_vertices,
            symmetry,
            mirror_triangles,
            winding,
        })
    }

    pub fn vertex_count(&self) -> usize {
        self.shape.vertex_count()
    }

    #[inline]
    pub(crate) fn scaled_basis(&self, vertex: usize, axis: usize, component: usize) -> f64 {
        self.scaled_basis[(3 * vertex + axis) * self.shape.component_count() + component] as f64
    }

    #[inline]
    pub(crate) fn mean_vertex(&self, v: usize) -> [f64; 3] {
        [self.shape.mean[3 * v] as f64, self.shape.mean[3 * v + 1] as f64, self.shape.mean[3 * v + 2] as f64]
    }

    /// One vertex of the shape with coefficients `alpha` (standard deviations) and expression
    /// weights `psi` (may be shorter than the blendshape list).
    pub fn vertex(&self, v: usize, alpha: &[f64], psi: &[f64]) -> [f64; 3] {
        let mut p = self.mean_vertex(v);
        let m = self.shape.component_count();
        for (axis, slot) in p.iter_mut().enumerate() {
            let row = &self.scaled_basis[(3 * v + axis) * m..(3 * v + axis + 1) * m];
            *slot += row.iter().zip(alpha).map(|(&b, &a)| b as f64 * a).sum::<f64>();
            for (bs, &w) in self.blendshapes.iter().zip(psi) {
                *slot += bs.deformation[3 * v + axis] as f64 * w;
            }
        }
        p
    }

    /// All vertices of the shape with coefficients `alpha` and expression weights `psi`.
    pub fn shape_vertices(&self, alpha: &[f32], psi: &[f32]) -> Vec<[f32; 3]> {
        let m = self.shape.component_count();
        let n = alpha.len().min(m);
        let mut out = Vec::with_capacity(self.vertex_count());
        for v in 0..self.vertex_count() {
            let mut p = [0.0f32; 3];
            for (axis, slot) in p.iter_mut().enumerate() {
                let r = 3 * v + axis;
                let row = &self.scaled_basis[r * m..r * m + n];
                let mut acc = self.shape.mean[r];
                for k in 0..n {
                    acc += row[k] * alpha[k];
                }
                for (bs, &w) in self.blendshapes.iter().zip(psi) {
                    acc += bs.deformation[r] * w;
                }
                *slot = acc;
            }
            out.push(p);
        }
        out
    }

    /// Fit to 58 IMM landmarks (pixels) with the default options.
    pub fn fit(&self, points: &[Point], image_width: u32, image_height: u32) -> Result<FittedFace, MorphError> {
        self.fit_with(points, image_width, image_height, &FitOptions::default())
    }

    pub fn fit_with(&self, points: &[Point], image_width: u32, image_height: u32, options: &FitOptions) -> Result<FittedFace, MorphError> {
        let r = fit::fit_landmarks(self, points, options)?;
        let vertices = self.shape_vertices(&r.coefficients, &r.expression);
        Ok(FittedFace {
            pose: r.camera.pose(),
            residual_px: r.residual_px,
            camera: r.camera,
            coefficients: r.coefficients,
            expression: r.expression,
            correspondence: r.correspondence,
            vertices,
            image_width,
            image_height,
        })
    }

    /// Vertex positions (pixels) and depths of a shape seen by a camera.
    pub fn project(&self, vertices: &[[f32; 3]], camera: &Camera) -> Vec<[f32; 3]> {
        vertices.iter().map(|p| camera.project([p[0] as f64, p[1] as f64, p[2] as f64]).map(|c| c as f32)).collect()
    }

    /// The texture of the photo in the model's UV map (`size`×`size`, RGBA: alpha tells seen /
    /// mirrored / filled texels, see `render::TEXEL_*`).
    pub fn extract_texture(&self, photo: &image::RgbImage, fit: &FittedFace, size: usize) -> RgbaImage {
        let projected = self.project(&fit.vertices, &fit.camera);
        let facing: Vec<f32> = self.shape.triangles.iter().map(|&t| render::facing_of(&projected, t, self.winding)).collect();
        // Depth tolerance: about 2 mm of the face, in pixels.
        let tolerance = (2.0 * fit.camera.scale) as f32;
        render::extract_texture(
            photo,
            &projected,
            &facing,
            &self.shape.triangles,
            &self.shape.texcoords,
            &self.mirror_triangles,
            self.winding,
            size,
            tolerance.max(0.5),
        )
    }

    /// Render a fitted shape with its texture at any pose, filling a `width`×`height` image (the
    /// shape is centred and scaled to 90% of the smaller side).
    pub fn render_pose(&self, fit: &FittedFace, texture: &RgbaImage, pose: Pose, width: usize, height: usize) -> RgbImage {
        let camera = self.centred_camera(&fit.vertices, pose, width, height);
        let projected = self.project(&fit.vertices, &camera);
        render::render_textured(&projected, &self.shape.triangles, &self.shape.texcoords, texture, width, height, [0, 0, 0])
    }

    /// A camera at `pose` framing the mean shape's extent in a `width`×`height` image: the same
    /// scale and centre for every person, so that frontal renderings are comparable.
    pub fn centred_camera(&self, _vertices: &[[f32; 3]], pose: Pose, width: usize, height: usize) -> Camera {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in self.shape.mean.chunks_exact(3) {
            for d in 0..3 {
                lo[d] = lo[d].min(p[d]);
                hi[d] = hi[d].max(p[d]);
            }
        }
        let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1.0) as f64;
        let scale = 0.9 * width.min(height) as f64 / extent;
        let centre = [(lo[0] + hi[0]) as f64 * 0.5, (lo[1] + hi[1]) as f64 * 0.5, (lo[2] + hi[2]) as f64 * 0.5];
        let mut cam = Camera::from_pose(pose, scale, 0.0, 0.0);
        let c = cam.project(centre);
        cam.tx = width as f64 * 0.5 - c[0];
        cam.ty = height as f64 * 0.5 - c[1];
        cam
    }

    /// Render the fitted, textured face from the front ([`FRONTAL_SIZE`] square) and report where
    /// the eye and mouth centres (means of the mapped outline vertices) fall in the rendering.
    pub fn frontalize(&self, photo: &Photo, fit: &FittedFace) -> Result<Frontal, MorphError> {
        self.frontalize_sized(photo, fit, FRONTAL_SIZE, TEXTURE_SIZE)
    }

    pub fn frontalize_sized(&self, photo: &Photo, fit: &FittedFace, size: usize, texture_size: usize) -> Result<Frontal, MorphError> {
        self.render_posed(photo, fit, Pose::default(), size, texture_size)
    }

    /// The fitted, textured head of `photo` rendered at `pose` (yaw, pitch, roll in degrees, the
    /// fit's convention), centred in a `size` square on black: the frontal rendering at the zero
    /// pose, and at other yaws the avatar of one photo turned as a live head would be.
    pub fn render_posed(
        &self,
        photo: &Photo,
        fit: &FittedFace,
        pose: Pose,
        size: usize,
        texture_size: usize,
    ) -> Result<Frontal, MorphError> {
        if fit.vertices.len() != self.vertex_count() {
            return Err(MorphError::Input("the fit does not belong to this model".into()));
        }
        let texture = self.extract_texture(&photo.rgb, fit, texture_size);
        let camera = self.centred_camera(&fit.vertices, pose, size, size);
        let projected = self.project(&fit.vertices, &camera);
        let image = render::render_textured(&projected, &self.shape.triangles, &self.shape.texcoords, &texture, size, size, [0, 0, 0]);
        let centres = self.centres(&projected, &fit.correspondence);
        Ok(Frontal { image, centres })
    }

    /// Fit the model to the 58 landmarks of a face and extract its texture (`texture_size` square,
    /// the unseen side completed by symmetry).
    pub fn avatar(&self, photo: &Photo, points: &[Point], options: &FitOptions, texture_size: usize) -> Result<Avatar, MorphError> {
        let fitted = self.fit_with(points, photo.width(), photo.height(), options)?;
        let texture = self.extract_texture(&photo.rgb, &fitted, texture_size);
        Ok(Avatar { fitted, texture })
    }

    /// The avatar as a mesh to export.
    pub fn avatar_mesh<'a>(&'a self, avatar: &'a Avatar) -> export::TexturedMesh<'a> {
        export::TexturedMesh {
            vertices: &avatar.fitted.vertices,
            texcoords: &self.shape.texcoords,
            triangles: &self.shape.triangles,
            texture: &avatar.texture,
        }
    }

    /// The avatar as a glTF binary file (`model/gltf-binary`).
    pub fn avatar_glb(&self, avatar: &Avatar) -> Result<Vec<u8>, MorphError> {
        export::glb_bytes(&self.avatar_mesh(avatar)).map_err(|e| MorphError::Export { path: "glb".into(), message: e.to_string() })
    }

    /// The avatar as the bytes of `format` (the OBJ files named `avatar.*`, zipped).
    pub fn avatar_file(&self, avatar: &Avatar, format: AvatarFormat) -> Result<Vec<u8>, MorphError> {
        match format {
            AvatarFormat::Glb => self.avatar_glb(avatar),
            AvatarFormat::Obj => export::obj_zip(&self.avatar_mesh(avatar), "avatar"),
        }
    }

    /// The frontal rendering ([`FaceModel::frontalize_sized`] at `size`, texture at least as fine)
    /// as PNG bytes: the one path of `facegate frontalize` and `POST /frontalize`.
    pub fn frontal_png(&self, photo: &Photo, fit: &FittedFace, size: usize) -> Result<(Frontal, Vec<u8>), MorphError> {
        self.posed_png(photo, fit, Pose::default(), size)
    }

    /// [`FaceModel::render_posed`] at `size` (texture at least as fine) as PNG bytes: `facegate
    /// frontalize --yaw`.
    pub fn posed_png(&self, photo: &Photo, fit: &FittedFace, pose: Pose, size: usize) -> Result<(Frontal, Vec<u8>), MorphError> {
        let frontal = self.render_posed(photo, fit, pose, size, TEXTURE_SIZE.max(size))?;
        let mut png = Vec::new();
        frontal
            .image
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| MorphError::Export { path: "png".into(), message: e.to_string() })?;
        Ok((frontal, png))
    }

    /// Eye and mouth centres of projected vertices (`left_eye` = the eye on the image left).
    pub fn centres(&self, projected: &[[f32; 3]], correspondence: &[u32; IMM_POINTS]) -> EyeMouthCentres {
        let pts: Vec<Point> = correspondence.iter().map(|&v| [projected[v as usize][0], projected[v as usize][1]]).collect();
        EyeMouthCentres {
            left_eye: centroid(&pts[EYE_IMAGE_LEFT]),
            right_eye: centroid(&pts[EYE_IMAGE_RIGHT]),
            mouth: centroid(&pts[MOUTH]),
        }
    }

    /// Which of the 58 landmarks the camera sees on a fit: a point is visible when its vertex is
    /// the nearest surface at its pixel (the model's own depth buffer, 2 mm of tolerance), so the
    /// far eye, brow and jaw of a turned head come out hidden.
    pub fn landmark_visibility(&self, fit: &FittedFace) -> Vec<bool> {
        self.vertex_visibility(&fit.vertices, &fit.camera, &fit.correspondence, fit.image_width as usize, fit.image_height as usize)
    }

    /// [`landmark_visibility`](Self::landmark_visibility) for any shape (`vertices`, model mm)
    /// under `camera` in a `width` × `height` image: whether each of the vertices `points` is the
    /// nearest surface at its pixel.
    pub fn vertex_visibility(&self, vertices: &[[f32; 3]], camera: &Camera, points: &[u32], width: usize, height: usize) -> Vec<bool> {
        let projected = self.project(vertices, camera);
        let depth = render::DepthBuffer::render(&projected, &self.shape.triangles, width, height);
        let tolerance = ((2.0 * camera.scale) as f32).max(0.5);
        points
            .iter()
            .map(|&v| {
                let p = projected[v as usize];
                depth.visible(p[0], p[1], p[2], tolerance)
            })
            .collect()
    }

    /// The 58 model points of a fit projected into its photo.
    pub fn projected_landmarks(&self, fit: &FittedFace) -> Vec<Point> {
        fit.correspondence
            .iter()
            .map(|&v| {
                let p = fit.vertices[v as usize];
                let q = fit.camera.project([p[0] as f64, p[1] as f64, p[2] as f64]);
                [q[0] as f32, q[1] as f32]
            })
            .collect()
    }
}

/// Area-weighted vertex normals, oriented outwards (towards +z on the front of the face).
fn vertex_normals(mean: &[f32], triangles: &[[u32; 3]], winding: f32) -> Vec<[f32; 3]> {
    let mut normals = vec![[0.0f32; 3]; mean.len() / 3];
    let p = |i: u32| [mean[3 * i as usize], mean[3 * i as usize + 1], mean[3 * i as usize + 2]];
    for t in triangles {
        let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        // In model coordinates (y up) the image-space winding sign flips.
        let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]].map(|c| -winding * c);
        for &v in t {
            for d in 0..3 {
                normals[v as usize][d] += n[d];
            }
        }
    }
    for n in &mut normals {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            n.iter_mut().for_each(|c| *c /= len);
        }
    }
    normals
}
