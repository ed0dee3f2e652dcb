//! Where the 58 IMM landmarks sit on the Surrey Face Model.
//!
//! Method (reproducible, computed at load time from the model files, no data involved):
//! 1. IMM points that have an iBUG equivalent take that point's vertex from `ibug_to_sfm.txt`
//!    (eye corners and lid points, eyebrows, mouth corners and lip middles, nostrils, subnasale).
//! 2. IMM points between two iBUG points (the middle of each upper and lower eyelid: IMM has 8 points
//!    per eye, iBUG 6) or on the nose flanks (no iBUG equivalent) are defined as a point on the
//!    segment between two mapped vertices of the mean shape (`Anchor::Lerp`), seen from the front,
//!    and snapped to the frontmost mean-shape vertex within 4 mm of that point in x–y (the nearest
//!    one in x–y when none is that close).
//! 3. The jaw (IMM 0–12) is the contour group: the chin (IMM 6) is iBUG 9 (vertex 33); the other
//!    twelve have no fixed vertex. At every fitting iteration each takes the vertex of the model
//!    contour of its side (`sfm_model_contours.json`) whose projection is nearest to it, so the
//!    correspondence slides along the jaw as the head turns (see `fit.rs`).

use facegate_core::face::IMM_POINTS;

/// How one IMM point is tied to the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Anchor {
    /// A fixed vertex (from `ibug_to_sfm.txt`).
    Vertex(u32),
    /// `a + t·(b − a)` on the mean shape, snapped to the frontmost nearby vertex.
    Lerp(u32, u32, f32),
    /// A jaw point: nearest projected vertex of the model contour on the image-left (`true`) or
    /// image-right side.
    Contour { image_left: bool },
}

/// iBUG vertex ids used below (`ibug_to_sfm.txt`, iBUG numbers in comments).
mod v {
    pub const CHIN: u32 = 33; // 9
    // Subject's right eye (image left in a frontal photo).
    pub const R_EYE_OUTER: u32 = 177; // 37
    pub const R_EYE_TOP_OUTER: u32 = 172; // 38
    pub const R_EYE_TOP_INNER: u32 = 191; // 39
    pub const R_EYE_INNER: u32 = 181; // 40
    pub const R_EYE_BOTTOM_INNER: u32 = 173; // 41
    pub const R_EYE_BOTTOM_OUTER: u32 = 174; // 42
    // Subject's left eye (image right).
    pub const L_EYE_INNER: u32 = 614; // 43
    pub const L_EYE_TOP_INNER: u32 = 624; // 44
    pub const L_EYE_TOP_OUTER: u32 = 605; // 45
    pub const L_EYE_OUTER: u32 = 610; // 46
    pub const L_EYE_BOTTOM_OUTER: u32 = 607; // 47
    pub const L_EYE_BOTTOM_INNER: u32 = 606; // 48
    pub const NOSE_BRIDGE: u32 = 2842; // 28
    pub const NOSE_MIDDLE: u32 = 379; // 29
    pub const R_NOSTRIL: u32 = 100; // 32
    pub const NOSE_LIP_R: u32 = 2794; // 33
    pub const SUBNASALE: u32 = 270; // 34
    pub const NOSE_LIP_L: u32 = 2797; // 35
    pub const L_NOSTRIL: u32 = 537; // 36
}

/// The anchor of every IMM point, in IMM order (see `facegate_core::face` for the template).
pub fn imm_anchors() -> [Anchor; IMM_POINTS] {
    use Anchor::*;
    let mut a = [Vertex(0); IMM_POINTS];
    // Jaw 0–12, from the image left (subject's right) through the chin to the image right.
    for (i, slot) in a.iter_mut().enumerate().take(13) {
        *slot = if i < 6 { Contour { image_left: true } } else { Contour { image_left: false } };
    }
    a[6] = Vertex(v::CHIN);
    // 13–20: eye on the image right (subject's left): outer corner, upper lid towards the nose,
    // inner corner, lower lid back.
    a[13] = Vertex(v::L_EYE_OUTER);
    a[14] = Vertex(v::L_EYE_TOP_OUTER);
    a[15] = Lerp(v::L_EYE_TOP_OUTER, v::L_EYE_TOP_INNER, 0.5);
    a[16] = Vertex(v::L_EYE_TOP_INNER);
    a[17] = Vertex(v::L_EYE_INNER);
    a[18] = Vertex(v::L_EYE_BOTTOM_INNER);
    a[19] = Lerp(v::L_EYE_BOTTOM_INNER, v::L_EYE_BOTTOM_OUTER, 0.5);
    a[20] = Vertex(v::L_EYE_BOTTOM_OUTER);
    // 21–28: eye on the image left (subject's right).
    a[21] = Vertex(v::R_EYE_OUTER);
    a[22] = Vertex(v::R_EYE_TOP_OUTER);
    a[23] = Lerp(v::R_EYE_TOP_OUTER, v::R_EYE_TOP_INNER, 0.5);
    a[24] = Vertex(v::R_EYE_TOP_INNER);
    a[25] = Vertex(v::R_EYE_INNER);
    a[26] = Vertex(v::R_EYE_BOTTOM_INNER);
    a[27] = Lerp(v::R_EYE_BOTTOM_INNER, v::R_EYE_BOTTOM_OUTER, 0.5);
    a[28] = Vertex(v::R_EYE_BOTTOM_OUTER);
    // 29–33: eyebrow on the image right (subject's left), inner to outer (iBUG 23–27).
    a[29] = Vertex(590);
    a[30] = Vertex(2091);
    a[31] = Vertex(666);
    a[32] = Vertex(662);
    a[33] = Vertex(658);
    // 34–38: eyebrow on the image left (subject's right), inner to outer (iBUG 22–18).
    a[34] = Vertex(157);
    a[35] = Vertex(2086);
    a[36] = Vertex(233);
    a[37] = Vertex(229);
    a[38] = Vertex(225);
    // 39–46: outer lip: image-left corner, upper lip (bow peak, middle, peak), image-right corner,
    // lower lip back (iBUG 49, 51, 52, 53, 55, 57, 58, 59).
    a[39] = Vertex(398);
    a[40] = Vertex(413);
    a[41] = Vertex(329);
    a[42] = Vertex(825);
    a[43] = Vertex(812);
    a[44] = Vertex(693);
    a[45] = Vertex(411);
    a[46] = Vertex(264);
    // 47–57: nose, from the bridge beside the image-left inner eye corner down the flank, round
    // the nostrils and up the other flank.
    a[47] = Lerp(v::NOSE_BRIDGE, v::R_EYE_INNER, 0.6);
    a[48] = Lerp(v::NOSE_MIDDLE, v::R_NOSTRIL, 0.4);
    a[49] = Lerp(v::R_NOSTRIL, v::R_EYE_INNER, 0.25);
    a[50] = Vertex(v::R_NOSTRIL);
    a[51] = Vertex(v::NOSE_LIP_R);
    a[52] = Vertex(v::SUBNASALE);
    a[53] = Vertex(v::NOSE_LIP_L);
    a[54] = Vertex(v::L_NOSTRIL);
    a[55] = Lerp(v::L_NOSTRIL, v::L_EYE_INNER, 0.25);
    a[56] = Lerp(v::NOSE_MIDDLE, v::L_NOSTRIL, 0.4);
    a[57] = Lerp(v::NOSE_BRIDGE, v::L_EYE_INNER, 0.6);
    a
}

/// Resolve the anchors on the mean shape (`mean`: x, y, z per vertex). Jaw points other than the
/// chin get the chin vertex as a placeholder: the fit replaces them at every iteration.
pub fn resolve(anchors: &[Anchor; IMM_POINTS], mean: &[f32]) -> [u32; IMM_POINTS] {
    let pos = |i: u32| [mean[3 * i as usize], mean[3 * i as usize + 1], mean[3 * i as usize + 2]];
    let mut out = [v::CHIN; IMM_POINTS];
    for (slot, anchor) in out.iter_mut().zip(anchors) {
        *slot = match *anchor {
            Anchor::Vertex(id) => id,
            Anchor::Contour { .. } => v::CHIN,
            Anchor::Lerp(a, b, t) => {
                let (pa, pb) = (pos(a), pos(b));
                let target = [pa[0] + t * (pb[0] - pa[0]), pa[1] + t * (pb[1] - pa[1])];
                frontmost_near(mean, target, 4.0)
            }
        };
    }
    out
}

fn frontmost_near(mean: &[f32], target: [f32; 2], radius: f32) -> u32 {
    let mut best_front: Option<(u32, f32)> = None;
    let mut best_near = (0u32, f32::INFINITY);
    for (i, p) in mean.chunks_exact(3).enumerate() {
        let d2 = (p[0] - target[0]).powi(2) + (p[1] - target[1]).powi(2);
        if d2 < best_near.1 {
            best_near = (i as u32, d2);
        }
        if d2 <= radius * radius && best_front.is_none_or(|(_, z)| p[2] > z) {
            best_front = Some((i as u32, p[2]));
        }
    }
    best_front.map_or(best_near.0, |(i, _)| i)
}

/// Mirror vertex of every vertex: the symmetry file covers the reference vertices (the first 845);
/// the others take the vertex nearest to their mirror image `(−x, y, z)` on the mean shape.
pub fn complete_symmetry(reference: &[u32], mean: &[f32]) -> Vec<u32> {
    let n = mean.len() / 3;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        if let Some(&m) = reference.get(i).filter(|&&m| (m as usize) < n) {
            out.push(m);
            continue;
        }
        let (x, y, z) = (-mean[3 * i], mean[3 * i + 1], mean[3 * i + 2]);
        let mut best = (i as u32, f32::INFINITY);
        for (j, p) in mean.chunks_exact(3).enumerate() {
            let d2 = (p[0] - x).powi(2) + (p[1] - y).powi(2) + (p[2] - z).powi(2);
            if d2 < best.1 {
                best = (j as u32, d2);
            }
        }
        out.push(best.0);
    }
    out
}

/// The committed, data-derived correspondence (`models/imm_to_sfm.txt`, written by
/// `facegate train imm-sfm`): one `imm_index vertex_id` per line for the fixed IMM points.
pub const DERIVED_TABLE: &str = include_str!("../../../models/imm_to_sfm.txt");

/// Parse a correspondence table over `fallback` (the geometric anchors resolved on the mean).
pub fn parse_table(text: &str, vertex_count: usize, fallback: [u32; IMM_POINTS]) -> Result<[u32; IMM_POINTS], String> {
    let mut out = fallback;
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut it = line.split_whitespace();
        let (Some(i), Some(v)) = (it.next().and_then(|t| t.parse::<usize>().ok()), it.next().and_then(|t| t.parse::<u32>().ok())) else {
            return Err(format!("bad correspondence line '{line}'"));
        };
        if i >= IMM_POINTS || v as usize >= vertex_count {
            return Err(format!("correspondence {i} → {v} out of range"));
        }
        out[i] = v;
    }
    Ok(out)
}
