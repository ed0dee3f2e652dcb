//! 3DMM view synthesis: a fitted, textured face rendered at another pose with its exact landmarks
//! (the 3D-ASM's training views and recognition training's re-posed copies).

use super::jaw::*;
use facegate_core::face::{IMM_POINTS, JAW};
use facegate_core::geometry::{Point, centroid};
use facegate_core::imaging::GrayF32;
use facegate_morph::{Camera, FaceModel, Pose, render};

/// A synthetic training view: the render, its exact landmarks and the camera that made it.
pub struct SyntheticView {
    pub gray: GrayF32,
    pub points: Vec<Point>,
    pub camera: Camera,
}

/// Render a fitted, textured face at `pose` in an image of the photo's size, at the photo's scale,
/// with its landmark centroid where the photo's was; `gain` is the relative illumination change
/// from the face centre to one face-width to the right (a side light).
/// `jaw`: the jaw vertices on the face seen from the front ([`photo_jaw_vertices`]). `offsets`
/// (model mm, per IMM point) move each point from its vertex to where the photo's annotator put it
/// (see [`annotation_offsets`]); a jaw point gets its offset only while it keeps its vertex of
/// `jaw` (not when it moved to the occluding outline).
#[allow(clippy::too_many_arguments)]
pub fn synthesise_view(
    fm: &FaceModel,
    fit: &facegate_morph::FittedFace,
    texture: &image::RgbaImage,
    pose: Pose,
    background: [u8; 3],
    gain: f32,
    jaw: &JawVertices,
    offsets: &[[f64; 3]],
) -> SyntheticView {
    let (w, h) = (fit.image_width as usize, fit.image_height as usize);
    let at = |v: u32| {
        let p = fit.vertices[v as usize];
        [p[0] as f64, p[1] as f64, p[2] as f64]
    };
    let mut camera = Camera::from_pose(pose, fit.camera.scale, 0.0, 0.0);
    let centre3: [f64; 3] = {
        let mut c = [0.0; 3];
        for &v in &fit.correspondence {
            let p = at(v);
            (0..3).for_each(|d| c[d] += p[d] / IMM_POINTS as f64);
        }
        c
    };
    let (was, now) = (fit.camera.project(centre3), camera.project(centre3));
    camera.tx += was[0] - now[0];
    camera.ty += was[1] - now[1];
    let projected = fm.project(&fit.vertices, &camera);
    let rgb = render::render_textured(&projected, &fm.shape.triangles, &fm.shape.texcoords, texture, w, h, background);
    let mut gray = GrayF32::from_rgb(&rgb);
    let corr = view_correspondence(fm, &at, &camera, jaw);
    let points: Vec<Point> = corr
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let mut p = at(v);
            if let Some(d) = offsets.get(i).filter(|_| !JAW.contains(&i) || v == jaw[i]) {
                (0..3).for_each(|k| p[k] += d[k]);
            }
            camera.project(p)
        })
        .map(|q| [q[0] as f32, q[1] as f32])
        .collect();
    if gain != 0.0 {
        let c = centroid(&points);
        let width = (fit.camera.scale * 140.0) as f32;
        for y in 0..h {
            for x in 0..w {
                let g = (1.0 + gain * (x as f32 - c[0]) / width).clamp(0.3, 1.7);
                let px = &mut gray.data[y * w + x];
                *px = (*px * g).clamp(0.0, 255.0);
            }
        }
    }
    SyntheticView { gray, points, camera }
}

/// Mean colour of the photo's top-left corner (IMM: the plain studio background).
pub fn background_colour(rgb: &image::RgbImage) -> [u8; 3] {
    let n = 16.min(rgb.width()).min(rgb.height());
    let mut acc = [0u32; 3];
    for y in 0..n {
        for x in 0..n {
            let p = rgb.get_pixel(x, y).0;
            (0..3).for_each(|k| acc[k] += p[k] as u32);
        }
    }
    let count = (n * n).max(1);
    acc.map(|a| (a / count) as u8)
}

/// Which of the 58 points a view shows: the model's mean face turned to `yaw` (no pitch or roll),
/// its points at the vertices the view's 3D PDM reads (`jaw` moved to the occluding outline as it
/// turns away), each visible when it is the nearest surface at its pixel
/// (`FaceModel::vertex_visibility`). Frontal views show all 58; a full profile hides the far eye,
/// brow and mouth corner.
pub fn view_visibility(fm: &FaceModel, jaw: &JawVertices, yaw: f32) -> Vec<bool> {
    // 2 px per mm in a 600-px square: the depth test's tolerance (2 model mm) is a few pixels.
    let camera = Camera::from_pose(Pose { yaw, pitch: 0.0, roll: 0.0 }, 2.0, 300.0, 300.0);
    let vertices: Vec<[f32; 3]> = fm.shape.mean.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    let at = |v: u32| {
        let p = vertices[v as usize];
        [p[0] as f64, p[1] as f64, p[2] as f64]
    };
    let correspondence = view_correspondence(fm, &at, &camera, jaw);
    fm.vertex_visibility(&vertices, &camera, &correspondence, 600, 600)
}
