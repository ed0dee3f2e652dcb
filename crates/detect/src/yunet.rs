//! YuNet, a small multi-view CNN face detector (OpenCV Zoo's `face_detection_yunet_2023mar.onnx`,
//! MIT), run in pure Rust through `tract`.
//!
//! The network takes a 1×3×H×W float image, BGR in 0–255 with no normalisation, H and W multiples
//! of 32, and answers on three grids (strides 8, 16, 32) with, per cell: a class score and an
//! objectness (`cls_*`, `obj_*`), box deltas (`bbox_*`: centre offset in cells, log width and
//! height in strides) and five key points (`kps_*`, in cells). The decoding follows OpenCV's
//! `FaceDetectorYNImpl::postProcess`: score √(cls·obj) with both clamped to 0–1, then greedy
//! non-maximum suppression.
//!
//! tract needs a concrete input shape, so the model is compiled per input shape. A photo is
//! scaled with its aspect kept to fit a square of `side` pixels, and no larger than makes the
//! smallest face searched [`DetectOptions::yunet_min_face_px`] input pixels tall; the input is
//! that, rounded up to multiples of 32 and zero-padded (as OpenCV pads to the divisor), and the
//! boxes are mapped back to the photo's pixels. A 640×480 photo, whose smallest face searched is
//! 96 pixels, runs at 256×192 rather than 320×320: 0.48 of the work. Small images (the padded
//! ones, below `small_image_side`) keep the square. Each shape is compiled once, on first use, and
//! kept (at most (side / 32)² of them).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use tract_onnx::prelude::*;

use super::{DetectError, DetectOptions, Face};
use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::GrayF32;

/// Strides of the three output grids, in input pixels.
pub const STRIDES: [usize; 3] = [8, 16, 32];

/// The outputs in the order [`YunetDetector`] asks for them: class, objectness, box, key points,
/// each for strides 8, 16, 32 (the order of OpenCV's `output_names`).
const OUTPUT_NAMES: [&str; 12] =
    ["cls_8", "cls_16", "cls_32", "obj_8", "obj_16", "obj_32", "bbox_8", "bbox_16", "bbox_32", "kps_8", "kps_16", "kps_32"];

/// The input side is rounded up to a multiple of this (the coarsest stride).
const DIVISOR: usize = 32;

/// IoU above which the weaker of two boxes is dropped (OpenCV's default).
pub const NMS_IOU: f32 = 0.3;

/// One output grid of a run: `cls` and `obj` hold one value per cell, `bbox` four and `kps` ten,
/// cells row-major.
#[derive(Debug, Clone, Copy)]
pub struct Level<'a> {
    pub stride: usize,
    pub cols: usize,
    pub rows: usize,
    pub cls: &'a [f32],
    pub obj: &'a [f32],
    pub bbox: &'a [f32],
    pub kps: &'a [f32],
}

/// A decoded detection in input pixels: box, the five key points in the model's order (the
/// subject's right eye, left eye, nose tip, right and left mouth corner), score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub rect: Rect,
    pub points: [Point; 5],
    pub score: f32,
}

/// The cells of `levels` scoring at least `threshold`, decoded to input pixels.
pub fn decode(levels: &[Level], threshold: f32) -> Vec<Candidate> {
    let mut out = Vec::new();
    for level in levels {
        let s = level.stride as f32;
        for r in 0..level.rows {
            for c in 0..level.cols {
                let i = r * level.cols + c;
                let score = (level.cls[i].clamp(0.0, 1.0) * level.obj[i].clamp(0.0, 1.0)).sqrt();
                if score < threshold {
                    continue;
                }
                let b = &level.bbox[4 * i..4 * i + 4];
                let (cx, cy) = ((c as f32 + b[0]) * s, (r as f32 + b[1]) * s);
                let (w, h) = (b[2].exp() * s, b[3].exp() * s);
                let k = &level.kps[10 * i..10 * i + 10];
                let points = std::array::from_fn(|n| [(k[2 * n] + c as f32) * s, (k[2 * n + 1] + r as f32) * s]);
                out.push(Candidate { rect: Rect::new(cx - w / 2.0, cy - h / 2.0, w, h), points, score });
            }
        }
    }
    out
}

/// Greedy non-maximum suppression: strongest first, dropping every box that overlaps a kept
/// one by more than `iou`.
pub fn suppress(mut candidates: Vec<Candidate>, iou: f32) -> Vec<Candidate> {
    candidates.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<Candidate> = Vec::new();
    for c in candidates {
        if kept.iter().all(|k| k.rect.iou(&c.rect) <= iou) {
            kept.push(c);
        }
    }
    kept
}

/// Where an image sits in the square input: input = image · scale + offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    pub scale: f32,
    pub offset: [f32; 2],
}

impl Placement {
    /// The image with a border of `pad` of its width (left and right) and of its height (top and
    /// bottom), scaled with its aspect kept to fit a `side`-pixel square from the top left.
    pub fn fit(width: usize, height: usize, side: usize, pad: f32) -> Placement {
        let pad = pad.clamp(0.0, 1.0);
        let scale = side as f32 / ((1.0 + 2.0 * pad) * width.max(height).max(1) as f32);
        Placement::at_scale(width, height, scale, pad)
    }

    /// The image with its border (as [`Placement::fit`]) at `scale`.
    pub fn at_scale(width: usize, height: usize, scale: f32, pad: f32) -> Placement {
        let pad = pad.clamp(0.0, 1.0);
        Placement { scale, offset: [(pad * width as f32 * scale).floor(), (pad * height as f32 * scale).floor()] }
    }

    /// [`Placement::fit`] into a `side` square, shrunk further (never enlarged) so that a face of
    /// `min_face` image pixels spans `face_px` input pixels; with the input's width and height:
    /// the placed image and its border rounded up to multiples of 32. `face_px` 0 keeps the
    /// square.
    pub fn for_faces(width: usize, height: usize, side: usize, pad: f32, min_face: f32, face_px: f32) -> (Placement, usize, usize) {
        let pad = pad.clamp(0.0, 1.0);
        let fit = Placement::fit(width, height, side, pad);
        if face_px <= 0.0 || min_face <= 0.0 {
            return (fit, side, side);
        }
        let scale = fit.scale.min(face_px / min_face);
        let placed = Placement::at_scale(width, height, scale, pad);
        let input = |n: usize| {
            let extent = ((1.0 + 2.0 * pad) * n as f32 * scale).ceil() as usize;
            (extent.max(1).div_ceil(DIVISOR) * DIVISOR).min(side)
        };
        (placed, input(width), input(height))
    }

    pub fn to_image(&self, p: Point) -> Point {
        [(p[0] - self.offset[0]) / self.scale, (p[1] - self.offset[1]) / self.scale]
    }

    pub fn rect_to_image(&self, r: &Rect) -> Rect {
        let [x, y] = self.to_image([r.x, r.y]);
        Rect::new(x, y, r.width / self.scale, r.height / self.scale)
    }

    /// The candidate in image pixels, key points in the documented image order.
    pub fn face(&self, c: &Candidate) -> Face {
        // The model names points from the subject's side: their right eye and mouth corner are
        // on the image's left in an upright, unmirrored photo, which is the order `Face` keeps.
        Face { rect: self.rect_to_image(&c.rect), score: c.score, points: Some(c.points.map(|p| self.to_image(p))) }
    }
}

/// The grey image placed in a `width × height` grey plane (zeros outside), for all three input
/// channels.
fn input_plane(gray: &GrayF32, placement: &Placement, width: usize, height: usize) -> Vec<f32> {
    // Halve with a 2×2 box first while the scale is below ½, so bilinear sampling does not alias.
    let mut src = std::borrow::Cow::Borrowed(gray);
    let mut scale = placement.scale;
    while scale < 0.5 && src.width >= 2 && src.height >= 2 {
        src = std::borrow::Cow::Owned(src.downsample_half());
        scale *= 2.0;
    }
    let (ox, oy) = (placement.offset[0] as usize, placement.offset[1] as usize);
    let w = ((gray.width as f32 * placement.scale).round() as usize).min(width.saturating_sub(ox));
    let h = ((gray.height as f32 * placement.scale).round() as usize).min(height.saturating_sub(oy));
    let (sx, sy) = (src.width as f32 / (gray.width as f32 * placement.scale), src.height as f32 / (gray.height as f32 * placement.scale));
    let xs: Vec<f32> = (0..w).map(|x| (x as f32 + 0.5) * sx - 0.5).collect();
    let ys: Vec<f32> = (0..h).map(|y| (y as f32 + 0.5) * sy - 0.5).collect();
    let placed = src.sample_grid(&xs, &ys);
    let mut plane = vec![0.0f32; width * height];
    for (y, line) in placed.data.chunks_exact(w.max(1)).enumerate() {
        plane[(oy + y) * width + ox..(oy + y) * width + ox + w].copy_from_slice(line);
    }
    plane
}

/// A plan compiled for one input shape.
type Plan = Arc<TypedRunnableModel>;

/// The network, compiled for each input shape as it is first needed. `Send + Sync`: every call
/// runs its own state.
pub struct YunetDetector {
    /// The parsed file, the source of every shape's plan.
    model: InferenceModel,
    /// Plans by (width, height).
    plans: Mutex<HashMap<(usize, usize), Plan>>,
    side: usize,
}

impl YunetDetector {
    /// Parse the ONNX model, compile it for a `side`-pixel square input (rounded up to a multiple
    /// of 32) and check its outputs once on a blank input.
    pub fn from_bytes(bytes: &[u8], name: &str, side: usize) -> Result<YunetDetector, DetectError> {
        let side = side.max(DIVISOR).div_ceil(DIVISOR) * DIVISOR;
        let error = |e: TractError| DetectError::Model { path: name.to_string(), message: format!("{e:#}") };
        // The file records intermediate and output shapes for the input size it was exported
        // with; they contradict any other size (tract refuses the model), so tract recomputes them.
        let model = tract_onnx::onnx()
            .with_ignore_value_info(true)
            .with_ignore_output_shapes(true)
            .model_for_read(&mut &bytes[..])
            .and_then(|m| m.with_outputs_by_name(OUTPUT_NAMES))
            .map_err(error)?;
        let detector = YunetDetector { model, plans: Mutex::default(), side };
        let plan = detector.plan(side, side).map_err(error)?;
        detector.candidates(&plan, vec![0.0; side * side], side, side, 2.0).map_err(error)?;
        Ok(detector)
    }

    /// The largest input side (the square the model was first compiled for).
    pub fn side(&self) -> usize {
        self.side
    }

    /// The plan for a `width × height` input (multiples of 32), compiled on first use.
    fn plan(&self, width: usize, height: usize) -> TractResult<Plan> {
        if let Some(plan) = self.plans.lock().ok().and_then(|p| p.get(&(width, height)).cloned()) {
            return Ok(plan);
        }
        // Compiled outside the lock: two threads meeting a new shape at once both compile it
        // (the same plan), rather than every other call waiting.
        let plan = self
            .model
            .clone()
            .with_input_fact(0, f32::fact([1, 3, height, width]).into())
            .and_then(|m| m.into_optimized())
            .and_then(|m| m.into_runnable())?;
        if let Ok(mut plans) = self.plans.lock() {
            plans.entry((width, height)).or_insert_with(|| plan.clone());
        }
        Ok(plan)
    }

    /// Runs the network on one grey plane (copied to B, G and R) and decodes it.
    fn candidates(&self, plan: &Plan, plane: Vec<f32>, width: usize, height: usize, threshold: f32) -> TractResult<Vec<Candidate>> {
        let mut data = Vec::with_capacity(3 * width * height);
        for _ in 0..3 {
            data.extend_from_slice(&plane);
        }
        let input = tract_ndarray::Array4::from_shape_vec((1, 3, height, width), data)?.into_tensor();
        let outputs = plan.run(tvec!(input.into()))?;
        let views = outputs.iter().map(|o| o.try_as_plain_ram()).collect::<TractResult<Vec<_>>>()?;
        let slices = views.iter().map(|v| v.as_slice::<f32>()).collect::<TractResult<Vec<_>>>()?;
        let mut levels = Vec::with_capacity(STRIDES.len());
        for (i, &stride) in STRIDES.iter().enumerate() {
            let (cols, rows) = (width / stride, height / stride);
            let cells = cols * rows;
            let level = Level { stride, cols, rows, cls: slices[i], obj: slices[3 + i], bbox: slices[6 + i], kps: slices[9 + i] };
            let lens = [level.cls.len(), level.obj.len(), level.bbox.len(), level.kps.len()];
            if lens != [cells, cells, 4 * cells, 10 * cells] {
                let expected = [cells, cells, 4 * cells, 10 * cells];
                return Err(TractError::msg(format!("stride {stride}: output sizes {lens:?}, expected {expected:?}")));
            }
            levels.push(level);
        }
        Ok(decode(&levels, threshold))
    }

    /// Faces scoring at least `options.yunet_score` whose box is at least `min_size` pixels on
    /// its longer side, in image pixels (unsorted). Images with a shorter side below
    /// `options.small_image_side` get a zero border of `options.small_image_pad` of their size:
    /// a head filling a 92×112 crop, scaled to fill the input, is found less often than one with
    /// room around it (`models/yunet.md`).
    pub fn detect(&self, gray: &GrayF32, options: &DetectOptions, min_size: f32) -> Vec<Face> {
        if gray.width == 0 || gray.height == 0 {
            return Vec::new();
        }
        let small = gray.width.min(gray.height) < options.small_image_side as usize;
        let pad = if small { options.small_image_pad } else { 0.0 };
        // A small image keeps the whole square: its face fills the frame, and the five points of
        // a full profile at the smaller input pose it at 45° rather than beyond 60°.
        let face_px = if small { 0.0 } else { options.yunet_min_face_px };
        let (placement, width, height) = Placement::for_faces(gray.width, gray.height, self.side, pad, min_size, face_px);
        let plane = input_plane(gray, &placement, width, height);
        match self.plan(width, height).and_then(|plan| self.candidates(&plan, plane, width, height, options.yunet_score)) {
            Ok(found) => {
                suppress(found, NMS_IOU).iter().map(|c| placement.face(c)).filter(|f| f.rect.width.max(f.rect.height) >= min_size).collect()
            }
            Err(e) => {
                // The shapes were checked at load; a failure here is tract's own and is logged,
                // not turned into a face or a panic.
                tracing::error!(error = %e, "YuNet inference failed");
                Vec::new()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One listed cell: index, cls, obj, bbox deltas, key points.
    type Cell = (usize, f32, f32, [f32; 4], [f32; 10]);

    /// The output arrays of a grid whose cells are all silent except the listed ones.
    struct Grid {
        stride: usize,
        cols: usize,
        rows: usize,
        cls: Vec<f32>,
        obj: Vec<f32>,
        bbox: Vec<f32>,
        kps: Vec<f32>,
    }

    impl Grid {
        fn new(stride: usize, cols: usize, rows: usize, cells: &[Cell]) -> Grid {
            let n = cols * rows;
            let mut g = Grid { stride, cols, rows, cls: vec![0.0; n], obj: vec![0.0; n], bbox: vec![0.0; 4 * n], kps: vec![0.0; 10 * n] };
            for &(i, c, o, b, k) in cells {
                g.cls[i] = c;
                g.obj[i] = o;
                g.bbox[4 * i..4 * i + 4].copy_from_slice(&b);
                g.kps[10 * i..10 * i + 10].copy_from_slice(&k);
            }
            g
        }

        fn level(&self) -> Level<'_> {
            Level {
                stride: self.stride,
                cols: self.cols,
                rows: self.rows,
                cls: &self.cls,
                obj: &self.obj,
                bbox: &self.bbox,
                kps: &self.kps,
            }
        }
    }

    #[test]
    fn decodes_one_cell_into_box_points_and_score() {
        // Stride 8, 4×3 cells; cell (row 1, col 2) = index 6.
        let k = [0.1, 0.2, 0.9, 0.2, 0.5, 0.6, 0.2, 1.0, 0.8, 1.0];
        let grid = Grid::new(8, 4, 3, &[(6, 0.81, 1.0, [0.5, 0.25, 2.0f32.ln(), 0.0], k)]);
        let found = decode(&[grid.level()], 0.5);
        assert_eq!(found.len(), 1);
        let f = found[0];
        assert!((f.score - 0.9).abs() < 1e-6);
        // Centre ((2 + 0.5)·8, (1 + 0.25)·8) = (20, 10); size (2·8, 1·8).
        let r = f.rect;
        assert!((r.x - 12.0).abs() < 1e-4 && (r.y - 6.0).abs() < 1e-4, "{r:?}");
        assert!((r.width - 16.0).abs() < 1e-4 && (r.height - 8.0).abs() < 1e-4, "{r:?}");
        assert!((f.points[0][0] - 2.1 * 8.0).abs() < 1e-4 && (f.points[0][1] - 1.2 * 8.0).abs() < 1e-4);
        assert!((f.points[4][0] - 2.8 * 8.0).abs() < 1e-4 && (f.points[4][1] - 2.0 * 8.0).abs() < 1e-4);
    }

    #[test]
    fn scores_are_clamped_and_thresholded() {
        // cls above 1 and obj below 0 clamp to 1 and 0: score 0, dropped; 0.5·0.5 → 0.5 kept at 0.5.
        let hits: [Cell; 3] =
            [(0, 1.7, -0.2, [0.0; 4], [0.0; 10]), (1, 0.5, 0.5, [0.0; 4], [0.0; 10]), (2, 0.49, 0.49, [0.0; 4], [0.0; 10])];
        let grid = Grid::new(16, 3, 1, &hits);
        let lv = grid.level();
        let found = decode(&[lv], 0.5);
        assert_eq!(found.len(), 1);
        assert!((found[0].rect.center()[0] - 16.0).abs() < 1e-4);
        assert!(decode(&[lv], 0.0).len() == 3);
    }

    #[test]
    fn each_level_uses_its_own_stride() {
        let fine = Grid::new(8, 2, 2, &[(3, 1.0, 1.0, [0.0; 4], [0.0; 10])]);
        let coarse = Grid::new(32, 1, 1, &[(0, 1.0, 1.0, [0.5, 0.5, 0.0, 0.0], [0.0; 10])]);
        let found = decode(&[fine.level(), coarse.level()], 0.9);
        assert_eq!(found.len(), 2);
        assert_eq!(found[0].rect, Rect::new(4.0, 4.0, 8.0, 8.0));
        assert_eq!(found[1].rect, Rect::new(0.0, 0.0, 32.0, 32.0));
        assert_eq!(found[1].points[2], [0.0, 0.0]);
    }

    fn candidate(x: f32, score: f32) -> Candidate {
        Candidate { rect: Rect::new(x, 0.0, 10.0, 10.0), points: [[x, 0.0]; 5], score }
    }

    #[test]
    fn suppression_keeps_the_strongest_of_overlapping_boxes() {
        // Shifts of 2 (IoU 8/12 ≈ 0.67) overlap; 8 (IoU 2/18 ≈ 0.11) does not.
        let kept = suppress(vec![candidate(2.0, 0.8), candidate(0.0, 0.95), candidate(10.0, 0.7), candidate(18.0, 0.9)], NMS_IOU);
        let xs: Vec<f32> = kept.iter().map(|c| c.rect.x).collect();
        assert_eq!(xs, [0.0, 18.0, 10.0]);
        assert!(suppress(Vec::new(), NMS_IOU).is_empty());
    }

    #[test]
    fn placement_maps_input_pixels_back_to_the_image() {
        // 640×480 into 320: scale ½, no border.
        let p = Placement::fit(640, 480, 320, 0.0);
        assert_eq!(p, Placement { scale: 0.5, offset: [0.0, 0.0] });
        assert_eq!(p.to_image([100.0, 50.0]), [200.0, 100.0]);
        // 80×100 into 300 with a 25 % border: 150 × 1.5 = 300, scale 2, borders 40 and 50.
        let q = Placement::fit(80, 100, 300, 0.25);
        assert!((q.scale - 2.0).abs() < 1e-6 && q.offset == [40.0, 50.0], "{q:?}");
        let back = q.rect_to_image(&Rect::new(40.0, 50.0 + 100.0, 160.0, 100.0));
        assert_eq!(back, Rect::new(0.0, 50.0, 80.0, 50.0));
        let c = Candidate { rect: Rect::new(40.0, 50.0, 64.0, 64.0), points: [[40.0 + 160.0, 50.0]; 5], score: 0.9 };
        let face = q.face(&c);
        assert_eq!(face.points.unwrap()[3], [80.0, 0.0]);
        assert_eq!(face.score, 0.9);
        // The padded image fits by its longer side: 92×112 with 10 % takes 320 / 1.2 for 112.
        let r = Placement::fit(92, 112, 320, 0.1);
        assert!((r.scale * 112.0 - 320.0 / 1.2).abs() < 1e-3 && r.offset == [21.0, 26.0], "{r:?}");
    }

    #[test]
    fn the_input_shrinks_to_the_smallest_face_searched_and_no_further() {
        // 640×480, smallest face 96 px at 36 input px: scale 0.375, 240×180 → 256×192.
        let (p, w, h) = Placement::for_faces(640, 480, 320, 0.0, 96.0, 36.0);
        assert!((p.scale - 0.375).abs() < 1e-6 && p.offset == [0.0, 0.0], "{p:?}");
        assert_eq!((w, h), (256, 192));
        // A face limit the square already makes small enough keeps the square's scale.
        let (p, w, h) = Placement::for_faces(640, 480, 320, 0.0, 50.0, 36.0);
        assert_eq!((p, w, h), (Placement::fit(640, 480, 320, 0.0), 320, 256));
        // 0 keeps the square input; a small image keeps its border.
        assert_eq!(Placement::for_faces(640, 480, 320, 0.0, 96.0, 0.0), (Placement::fit(640, 480, 320, 0.0), 320, 320));
        let (p, w, h) = Placement::for_faces(92, 112, 320, 0.1, 24.0, 36.0);
        assert!((p.scale - 1.5).abs() < 1e-6 && p.offset == [13.0, 16.0], "{p:?}");
        assert_eq!((w, h), (192, 224));
    }

    #[test]
    fn input_plane_holds_the_scaled_image_and_zero_padding() {
        let gray = GrayF32::from_fn(64, 32, |_, _| 200.0);
        let plane = input_plane(&gray, &Placement::fit(64, 32, 32, 0.0), 32, 32);
        // Scale ½: 32×16 of image, the rest zero.
        assert_eq!(plane.len(), 32 * 32);
        assert!((plane[5 * 32 + 31] - 200.0).abs() < 1e-3);
        assert_eq!(plane[16 * 32], 0.0);
        // Shrinking by 4 goes through a box halving and keeps a flat image flat.
        let big = GrayF32::from_fn(128, 128, |x, _| if x % 2 == 0 { 0.0 } else { 100.0 });
        let small = input_plane(&big, &Placement::fit(128, 128, 32, 0.0), 32, 32);
        assert!(small.iter().all(|&v| (v - 50.0).abs() < 1e-3), "{:?}", &small[..8]);
    }
}
