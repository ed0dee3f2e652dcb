//! Matching (thesis 2.3.3 and 2.4.2): the mean shape is placed from the face box, the face region
//! is resampled into a fixed-size crop (the shape at the model's scale), and the points are
//! searched coarse to fine over a 2-level Gaussian pyramid: move every point to its best candidate,
//! constrain by the shape model(s), repeat until ~90% of the points move less than a pixel.

use facegate_core::face::{INTERNAL, JAW};
use facegate_core::geometry::{Point, Rect, Similarity};
use facegate_core::imaging::GrayF32;

use super::profile::{PROFILE_LEN, ProfileStrip};
use super::sift::{DESCRIPTOR_LEN, DescriptorGrid, Gradients};
use super::{AsmModel, Variant};

/// Crop coordinates `c = s·(p − o)` of image point `p` (scale and translation only: the search
/// itself handles rotation through the normals and the pose of the shape model).
#[derive(Debug, Clone, Copy)]
pub struct Frame {
    pub scale: f32,
    pub origin: Point,
}

impl Frame {
    /// The frame that puts `pose(mean shape)` at the model's scale in the middle of the crop.
    pub fn from_pose(pose: &Similarity, crop_size: usize) -> Frame {
        let scale = 1.0 / pose.scale().max(1e-6);
        let half = 0.5 * crop_size as f32;
        Frame { scale, origin: [pose.tx - half / scale, pose.ty - half / scale] }
    }

    pub fn to_crop(&self, p: Point) -> Point {
        [self.scale * (p[0] - self.origin[0]), self.scale * (p[1] - self.origin[1])]
    }

    pub fn to_image(&self, c: Point) -> Point {
        [c[0] / self.scale + self.origin[0], c[1] / self.scale + self.origin[1]]
    }

    /// Resample the image into the crop. When shrinking, each crop pixel averages a 2×2 grid of
    /// bilinear samples so that the crop is not aliased. The frame is a scale and a shift, so each
    /// sample's x depends on its column only and its y on its row only ([`GrayF32::sample_grid`]).
    pub fn crop(&self, img: &GrayF32, size: usize) -> GrayF32 {
        let step = 1.0 / self.scale;
        let axis = |origin: f32| -> Vec<f32> { (0..size).map(|i| i as f32 / self.scale + origin).collect() };
        let (xs, ys) = (axis(self.origin[0]), axis(self.origin[1]));
        if step <= 1.5 {
            return img.sample_grid(&xs, &ys);
        }
        let q = 0.25 * step;
        let shifted = |axis: &[f32], by: f32| -> Vec<f32> { axis.iter().map(|v| v + by).collect() };
        let (left, right, up, down) = (shifted(&xs, -q), shifted(&xs, q), shifted(&ys, -q), shifted(&ys, q));
        let corners =
            [img.sample_grid(&left, &up), img.sample_grid(&right, &up), img.sample_grid(&left, &down), img.sample_grid(&right, &down)];
        let mut out = GrayF32::new(size, size);
        for (i, o) in out.data.iter_mut().enumerate() {
            *o = 0.25 * (corners[0].data[i] + corners[1].data[i] + corners[2].data[i] + corners[3].data[i]);
        }
        out
    }
}

/// One level of the crop's pyramid with its gradients.
pub struct Level {
    pub image: GrayF32,
    pub gradients: Gradients,
}

/// Level 0 is the crop; each next level is blurred and halved. A point `p` of level `l` is at
/// `(p − 0.5)/2` on level `l + 1` (the 2×2 average of `downsample_half`).
pub fn pyramid(crop: GrayF32, levels: usize) -> Vec<Level> {
    let mut out = Vec::with_capacity(levels);
    let mut img = crop;
    for l in 0..levels.max(1) {
        if l > 0 {
            img = img.gaussian_blur(0.8).downsample_half();
        }
        let gradients = Gradients::new(&img);
        out.push(Level { image: img.clone(), gradients });
    }
    out
}

pub fn to_level(p: Point, level: usize) -> Point {
    let mut q = p;
    for _ in 0..level {
        q = [(q[0] - 0.5) * 0.5, (q[1] - 0.5) * 0.5];
    }
    q
}

pub fn from_level(p: Point, level: usize) -> Point {
    let mut q = p;
    for _ in 0..level {
        q = [2.0 * q[0] + 0.5, 2.0 * q[1] + 0.5];
    }
    q
}

/// Unit normals of the contours at each point: perpendicular to the line joining the point's two
/// neighbours on its contour (thesis 2.4.1, "interpolation of neighbouring landmarks").
pub fn normals(points: &[Point], neighbours: &[[u16; 2]], out: &mut Vec<Point>) {
    out.clear();
    for (i, nb) in neighbours.iter().enumerate() {
        let (a, b) = (points[nb[0] as usize], points[nb[1] as usize]);
        let (mut tx, mut ty) = (b[0] - a[0], b[1] - a[1]);
        let mut len = (tx * tx + ty * ty).sqrt();
        if !(len > 1e-6) {
            // Degenerate neighbourhood: fall back to the direction to the shape's previous point.
            let p = points[i];
            let q = points[(i + points.len() - 1) % points.len()];
            tx = p[0] - q[0];
            ty = p[1] - q[1];
            len = (tx * tx + ty * ty).sqrt();
        }
        if len > 1e-6 && len.is_finite() { out.push([-ty / len, tx / len]) } else { out.push([1.0, 0.0]) }
    }
}

/// Buffers reused across points and iterations.
pub struct Workspace {
    grid: DescriptorGrid,
    strip: ProfileStrip,
    descriptor: [f32; DESCRIPTOR_LEN],
    profile: [f32; PROFILE_LEN],
    scratch: Vec<f32>,
    normals: Vec<Point>,
}

impl Default for Workspace {
    fn default() -> Self {
        Workspace {
            grid: DescriptorGrid::new(),
            strip: ProfileStrip::default(),
            descriptor: [0.0; DESCRIPTOR_LEN],
            profile: [0.0; PROFILE_LEN],
            scratch: vec![0.0; DESCRIPTOR_LEN],
            normals: Vec::new(),
        }
    }
}

fn uses_sift(variant: Variant, point: usize) -> bool {
    match variant {
        Variant::Asm => false,
        Variant::Sift => true,
        Variant::Casm | Variant::Asm3d => INTERNAL.contains(&point),
    }
}

/// Move each point to its best candidate by its texture model (thesis eq. 2.3). Returns the sum
/// of the best distances (the fit's texture cost).
pub fn suggest(
    model: &AsmModel,
    lvl: &Level,
    level: usize,
    points: &[Point],
    variant: Variant,
    ws: &mut Workspace,
    out: &mut Vec<Point>,
) -> f32 {
    normals(points, &model.neighbours, &mut ws.normals);
    out.clear();
    let mut cost = 0.0;
    let p = &model.params;
    for (i, &pt) in points.iter().enumerate() {
        let n = ws.normals[i];
        if uses_sift(variant, i) {
            let r = p.sift_radius.get(level).or(p.sift_radius.last()).copied().unwrap_or(2);
            let m = &model.sifts[level][i];
            // Coarse-to-fine over the window: every other candidate first, then the 8 neighbours
            // of the best one (the SIFT cost surface is smooth around its minimum, thesis fig. 2.3).
            // The coarse grid reaches r − (r mod 2); the outer ring is sampled only if a neighbour
            // needs it.
            ws.grid.fill_within(&lvl.gradients, pt, n, r, r - r % 2);
            let r = r as isize;
            let eval = |da: isize, db: isize, ws: &mut Workspace| {
                ws.grid.descriptor(da, db, &mut ws.descriptor);
                m.distance(&ws.descriptor, &mut ws.scratch)
            };
            let (mut best, mut best_d) = ((0isize, 0isize), f32::INFINITY);
            let mut da = -r + (r % 2);
            while da <= r {
                let mut db = -r + (r % 2);
                while db <= r {
                    let d = eval(da, db, ws);
                    if d < best_d {
                        best_d = d;
                        best = (da, db);
                    }
                    db += 2;
                }
                da += 2;
            }
            let centre = best;
            for (oa, ob) in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
                let (da, db) = (centre.0 + oa, centre.1 + ob);
                if da.abs() > r || db.abs() > r {
                    continue;
                }
                ws.grid.widen(&lvl.gradients, da, db);
                let d = eval(da, db, ws);
                if d < best_d {
                    best_d = d;
                    best = (da, db);
                }
            }
            cost += best_d;
            let (da, db) = (best.0 as f32, best.1 as f32);
            out.push([pt[0] + da * n[0] - db * n[1], pt[1] + da * n[1] + db * n[0]]);
        } else {
            let r = p.profile_radius;
            let m = &model.profiles[level][i];
            ws.strip.fill(&lvl.image, pt, n, r);
            let (mut best, mut best_d) = (0isize, f32::INFINITY);
            let r = r as isize;
            for s in -r..=r {
                ws.strip.profile(s, &mut ws.profile);
                let d = m.distance(&ws.profile);
                if d < best_d {
                    best_d = d;
                    best = s;
                }
            }
            cost += best_d;
            out.push([pt[0] + best as f32 * n[0], pt[1] + best as f32 * n[1]]);
        }
    }
    cost
}

/// Shape constraint: the full model alone (ASM, SIFT-ASM), or C-ASM's two group models first,
/// combined and constrained by the full model.
fn constrain(model: &AsmModel, suggested: &[Point], variant: Variant) -> Vec<Point> {
    match variant {
        Variant::Asm | Variant::Sift => model.full.fit(suggested).0,
        Variant::Casm | Variant::Asm3d => {
            let (contour, _, _) = model.contour.fit(&suggested[JAW]);
            let (internal, _, _) = model.internal.fit(&suggested[INTERNAL]);
            let mut combined = contour;
            combined.extend(internal);
            model.full.fit(&combined).0
        }
    }
}

/// The texture cost of every `step`-th point where it is (no candidates): ranks the starting
/// shapes (`step` 1: all points; the 3D-ASM ranks its many starts on a sample of them).
pub fn texture_cost(
    model: &AsmModel,
    lvl: &Level,
    level: usize,
    points: &[Point],
    step: usize,
    variant: Variant,
    ws: &mut Workspace,
) -> f32 {
    normals(points, &model.neighbours, &mut ws.normals);
    let mut cost = 0.0;
    for (i, &pt) in points.iter().enumerate().step_by(step.max(1)) {
        let n = ws.normals[i];
        if uses_sift(variant, i) {
            ws.grid.fill(&lvl.gradients, pt, n, 0);
            ws.grid.descriptor(0, 0, &mut ws.descriptor);
            cost += model.sifts[level][i].distance(&ws.descriptor, &mut ws.scratch);
        } else {
            ws.strip.fill(&lvl.image, pt, n, 0);
            ws.strip.profile(0, &mut ws.profile);
            cost += model.profiles[level][i].distance(&ws.profile);
        }
    }
    cost
}

/// One search iteration on a level: suggest, constrain. Returns the texture cost and whether the
/// shape converged (the configured share of points moved less than a pixel).
fn iterate(
    model: &AsmModel,
    lvl: &Level,
    level: usize,
    pts: &mut Vec<Point>,
    variant: Variant,
    ws: &mut Workspace,
    suggested: &mut Vec<Point>,
) -> (f32, bool) {
    let cost = suggest(model, lvl, level, pts, variant, ws, suggested);
    let next = constrain(model, suggested, variant);
    if next.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
        return (cost, true);
    }
    let still = next.iter().zip(pts.iter()).filter(|(a, b)| facegate_core::geometry::distance(**a, **b) < 1.0).count();
    *pts = next;
    (cost, still as f32 >= model.params.converged_share * pts.len() as f32)
}

/// Run the coarse-to-fine search on prepared pyramid levels, from `starts` (level-0 crop pixels):
/// on the coarsest level each start gets `probe_iterations` (0: none, its cost where it
/// stands), the one with the lowest texture cost goes on.
pub fn search_levels(model: &AsmModel, levels: &[Level], starts: &[Vec<Point>], variant: Variant, ws: &mut Workspace) -> Vec<Point> {
    let mut suggested = Vec::with_capacity(starts[0].len());
    let top = levels.len() - 1;
    let mut best: Option<(f32, Vec<Point>, bool, usize)> = None;
    for start in starts {
        let mut pts: Vec<Point> = start.iter().map(|&p| to_level(p, top)).collect();
        let (mut cost, mut done, mut used) = (f32::INFINITY, false, 0);
        let probe = if starts.len() > 1 { model.params.probe_iterations } else { model.params.max_iterations };
        if probe == 0 {
            cost = texture_cost(model, &levels[top], top, &pts, 1, variant, ws);
        }
        while used < probe.min(model.params.max_iterations) && !done {
            (cost, done) = iterate(model, &levels[top], top, &mut pts, variant, ws, &mut suggested);
            used += 1;
        }
        if best.as_ref().is_none_or(|b| cost < b.0) {
            best = Some((cost, pts, done, used));
        }
    }
    let (_, mut pts, mut done, used) = best.expect("at least one start");
    for _ in used..model.params.max_iterations {
        if done {
            break;
        }
        done = iterate(model, &levels[top], top, &mut pts, variant, ws, &mut suggested).1;
    }
    let mut current: Vec<Point> = pts.iter().map(|&p| from_level(p, top)).collect();
    for level in (0..top).rev() {
        let mut pts: Vec<Point> = current.iter().map(|&p| to_level(p, level)).collect();
        for _ in 0..model.params.max_iterations {
            if iterate(model, &levels[level], level, &mut pts, variant, ws, &mut suggested).1 {
                break;
            }
        }
        current = pts.iter().map(|&p| from_level(p, level)).collect();
    }
    current
}

/// Starting shapes in image pixels, each placed from the box by its learnt placement, upright and
/// (when `roll_start` is set) tilted by ±`roll_start` degrees in the image plane.
pub fn starts(model: &AsmModel, face: &Rect) -> Vec<Vec<Point>> {
    let roll = model.params.roll_start.to_radians();
    let rolls: &[f32] = if roll > 0.0 { &[0.0, 1.0, -1.0] } else { &[0.0] };
    let mut out = Vec::new();
    for st in &model.starts {
        let pose = placement_pose(&st.placement, face);
        let shape = model.full.shape(&st.b);
        for &r in rolls {
            let (c, s) = ((r * roll).cos(), (r * roll).sin());
            let turned = Similarity { a: pose.a * c, b: pose.a * s, tx: pose.tx, ty: pose.ty };
            out.push(shape.iter().map(|&p| turned.apply(p)).collect());
        }
    }
    out
}

/// The pose placing a start shape for `face`.
pub fn placement_pose(pl: &super::Placement, face: &Rect) -> Similarity {
    let c = face.center();
    let s = pl.scale_per_width * face.width;
    Similarity { a: s, b: 0.0, tx: c[0] + pl.dx * face.width, ty: c[1] + pl.dy * face.width }
}

/// The frontal start shape placed from the box, in image pixels.
pub fn place(model: &AsmModel, face: &Rect) -> Vec<Point> {
    starts(model, face).swap_remove(0)
}

fn usable_box(face: &Rect, gray: &GrayF32) -> Rect {
    let finite = face.x.is_finite() && face.y.is_finite() && face.width.is_finite() && face.height.is_finite();
    if finite && face.width >= 1.0 && face.height >= 1.0 && face.width < 1e6 {
        *face
    } else {
        Rect::new(0.0, 0.0, gray.width.max(1) as f32, gray.height.max(1) as f32)
    }
}

/// Fit the 58 points to the face in `face`. Degenerate inputs give the placed mean shape.
pub fn fit(model: &AsmModel, gray: &GrayF32, face: &Rect, variant: Variant) -> Vec<Point> {
    let face = usable_box(face, gray);
    let start = place(model, &face);
    if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height {
        return start;
    }
    let pose = placement_pose(&model.starts[0].placement, &face);
    let frame = Frame::from_pose(&pose, model.params.crop_size);
    let crop = frame.crop(gray, model.params.crop_size);
    let levels = pyramid(crop, model.params.levels);
    let starts: Vec<Vec<Point>> = starts(model, &face).iter().map(|s| s.iter().map(|&p| frame.to_crop(p)).collect()).collect();
    let mut ws = Workspace::default();
    let found = search_levels(model, &levels, &starts, variant, &mut ws);
    found.iter().map(|&p| frame.to_image(p)).collect()
}
