//! The cascade's evaluation: the image resized per scale (as OpenCV does) into an integral image,
//! every window of a row run through the stages together (`Batch`), trees laid out against the
//! integral image's row stride so that one node is one contiguous record.

use facegate_core::geometry::Rect;
use facegate_core::imaging::GrayF32;

use super::{Cascade, Hit, ScanOptions, group_rectangles};

/// A tree node with its feature's rectangles resolved to offsets into an integral image of a
/// fixed row stride, so evaluating it touches one contiguous record.
#[derive(Debug, Clone, Copy)]
struct OptNode {
    corners: [[u32; 4]; 3],
    weights: [f32; 3],
    threshold: f32,
    left: i32,
    right: i32,
    three_rects: bool,
}

/// How a weak classifier's tree is evaluated. OpenCV's frontal cascades are made of trees of two
/// nodes (a root and one child): those are evaluated without branches (both features computed,
/// the leaf chosen by selects), because the data-dependent branch of a tree walk is mispredicted
/// about as often as not and a misprediction costs more than the second feature.
#[derive(Debug, Clone, Copy)]
enum TreeShape {
    /// One node, two leaves.
    Stump,
    /// A root whose one child is node 1.
    Pair,
    /// Anything else: walked node by node.
    General,
}

#[derive(Debug, Clone, Copy)]
struct TreePlan {
    first_node: u32,
    first_leaf: u32,
    shape: TreeShape,
}

/// The cascade laid out for one integral-image stride.
struct Plan {
    nodes: Vec<OptNode>,
    trees: Vec<TreePlan>,
    /// One past the largest offset a node reads from a window's top-left integral index: the
    /// integral rectangle of the window itself.
    extent: usize,
}

/// Sum of the integral-image rectangle whose corners are `c`, for the window at `window[0]`.
#[inline(always)]
fn rect_sum(window: &[i32], c: &[u32; 4]) -> i32 {
    debug_assert!(c.iter().all(|&o| (o as usize) < window.len()));
    // SAFETY: callers pass `window` of length `Plan::extent`, and `Cascade::plan` asserts that
    // every corner offset is below it, so these reads stay inside the slice. This is the
    // innermost loop of the detector, where the bounds checks were a large share of the work.
    let at = |o: u32| unsafe { *window.get_unchecked(o as usize) };
    // Wrapping: the result is exact (it is a sum of at most 255·20·20), and skipping the overflow
    // checks of debug builds keeps the test profile's scan as fast as the release one.
    at(c[0]).wrapping_sub(at(c[1])).wrapping_sub(at(c[2])).wrapping_add(at(c[3]))
}

/// Whether the node's feature on this window falls on its left side (`value / norm < threshold`,
/// without the division).
#[inline(always)]
fn goes_left(window: &[i32], node: &OptNode, norm: f32) -> bool {
    let mut value =
        node.weights[0] * rect_sum(window, &node.corners[0]) as f32 + node.weights[1] * rect_sum(window, &node.corners[1]) as f32;
    if node.three_rects {
        value += node.weights[2] * rect_sum(window, &node.corners[2]) as f32;
    }
    value < node.threshold * norm
}

/// `if c { a } else { b }` as arithmetic, so the compiler emits no branch.
#[inline(always)]
fn select(c: bool, a: i32, b: i32) -> i32 {
    let mask = -(c as i32);
    (a & mask) | (b & !mask)
}

/// The windows of one row still in the cascade: integral index, grid position along the row,
/// normalisation and the current stage's sum (parallel vectors, reused across rows).
#[derive(Default)]
struct Batch {
    p: Vec<usize>,
    index: Vec<u32>,
    norm: Vec<f32>,
    acc: Vec<f32>,
}

impl Batch {
    fn clear(&mut self) {
        self.p.clear();
        self.index.clear();
        self.norm.clear();
        self.acc.clear();
    }

    fn push(&mut self, p: usize, index: u32, norm: f32) {
        self.p.push(p);
        self.index.push(index);
        self.norm.push(norm);
        self.acc.push(0.0);
    }

    fn len(&self) -> usize {
        self.p.len()
    }

    /// Move window `from` to slot `to` (≤ `from`): compaction in place, order kept.
    fn keep(&mut self, from: usize, to: usize) {
        self.p[to] = self.p[from];
        self.index[to] = self.index[from];
        self.norm[to] = self.norm[from];
    }

    fn truncate(&mut self, n: usize) {
        self.p.truncate(n);
        self.index.truncate(n);
        self.norm.truncate(n);
        self.acc.truncate(n);
    }
}

/// Scratch buffers reused across the scales of one image.
struct Scratch {
    stride: usize,
    sum: Vec<i32>,
    sqsum: Vec<f64>,
    row: Vec<f32>,
}

impl Scratch {
    fn new(width: usize, height: usize) -> Scratch {
        let stride = width + 1;
        Scratch { stride, sum: vec![0; stride * (height + 1)], sqsum: vec![0.0; stride * (height + 1)], row: vec![0.0; width] }
    }
}

impl Cascade {
    fn plan(&self, stride: usize) -> Plan {
        let nodes: Vec<OptNode> = self
            .nodes
            .iter()
            .map(|n| {
                let f = &self.features[n.feature as usize];
                let mut corners = [[0u32; 4]; 3];
                for (i, r) in f.rects.iter().take(f.count as usize).enumerate() {
                    let (x, y, w, h) = (r[0] as usize, r[1] as usize, r[2] as usize, r[3] as usize);
                    corners[i] = [
                        (y * stride + x) as u32,
                        (y * stride + x + w) as u32,
                        ((y + h) * stride + x) as u32,
                        ((y + h) * stride + x + w) as u32,
                    ];
                }
                OptNode { corners, weights: f.weights, threshold: n.threshold, left: n.left, right: n.right, three_rects: f.count == 3 }
            })
            .collect();
        let trees = self
            .weaks
            .iter()
            .enumerate()
            .map(|(i, weak)| {
                let end = self.weaks.get(i + 1).map_or(self.nodes.len(), |next| next.first_node as usize);
                let tree = &self.nodes[weak.first_node as usize..end];
                let shape = match tree {
                    [root] if root.left <= 0 && root.right <= 0 => TreeShape::Stump,
                    [root, child]
                        if child.left <= 0
                            && child.right <= 0
                            && (root.left == 1) != (root.right == 1)
                            && root.left <= 1
                            && root.right <= 1 =>
                    {
                        TreeShape::Pair
                    }
                    _ => TreeShape::General,
                };
                TreePlan { first_node: weak.first_node, first_leaf: weak.first_leaf, shape }
            })
            .collect();
        let extent = self.window_height * stride + self.window_width + 1;
        // `rect_sum` reads without bounds checks on the strength of this.
        assert!(nodes.iter().all(|n: &OptNode| n.corners.iter().flatten().all(|&o| (o as usize) < extent)), "feature outside the window");
        Plan { nodes, trees, extent }
    }

    /// Stage `si` on every window of `batch`: its sum goes to `batch.acc` (trees are added in
    /// the cascade's order, so each window's sum is the one a window-by-window walk gives).
    fn stage_batch(&self, plan: &Plan, si: usize, sum: &[i32], batch: &mut Batch) {
        let stage = &self.stages[si];
        let n = batch.len();
        let (ps, norms, acc) = (&batch.p[..n], &batch.norm[..n], &mut batch.acc[..n]);
        acc.fill(0.0);
        for tree in &plan.trees[stage.first_weak as usize..(stage.first_weak + stage.weak_count) as usize] {
            let nodes = &plan.nodes[tree.first_node as usize..];
            let leaves = &self.leaves[tree.first_leaf as usize..];
            // The leaf is `-idx` once `idx` ≤ 0.
            match tree.shape {
                TreeShape::Stump => {
                    let root = &nodes[0];
                    for k in 0..n {
                        let idx = select(goes_left(&sum[ps[k]..ps[k] + plan.extent], root, norms[k]), root.left, root.right);
                        acc[k] += leaves[(-idx) as usize];
                    }
                }
                TreeShape::Pair => {
                    let (root, child) = (&nodes[0], &nodes[1]);
                    for k in 0..n {
                        let window = &sum[ps[k]..ps[k] + plan.extent];
                        let at_root = select(goes_left(window, root, norms[k]), root.left, root.right);
                        let at_child = select(goes_left(window, child, norms[k]), child.left, child.right);
                        acc[k] += leaves[(-select(at_root > 0, at_child, at_root)) as usize];
                    }
                }
                TreeShape::General => {
                    for k in 0..n {
                        let window = &sum[ps[k]..ps[k] + plan.extent];
                        let mut idx = 0i32;
                        let leaf = loop {
                            let node = &nodes[idx as usize];
                            idx = if goes_left(window, node, norms[k]) { node.left } else { node.right };
                            if idx <= 0 {
                                break -idx;
                            }
                        };
                        acc[k] += leaves[leaf as usize];
                    }
                }
            }
        }
    }

    /// Multi-scale scan of `gray`: raw window hits (input pixels), not yet grouped.
    pub fn scan(&self, gray: &GrayF32, opts: &ScanOptions, hits: &mut Vec<Rect>) {
        let (ww, wh) = (self.window_width as f32, self.window_height as f32);
        let (w, h) = (gray.width, gray.height);
        if w < self.window_width || h < self.window_height {
            return;
        }
        // Below 1 the image is upscaled (faces smaller than the window); at most 4× to bound memory.
        let first_scale = (opts.min_size / ww.min(wh)).max(0.25);
        // Working downscale: halve (2×2 average, which also low-passes) while the smallest scale
        // stays at or above 2, so each level is a mild bilinear resize of a small base image.
        let mut base_cow: Option<GrayF32> = None;
        let mut base_factor = 1.0f32;
        while first_scale / base_factor >= 2.0 {
            let src = base_cow.as_ref().unwrap_or(gray);
            if src.width / 2 < self.window_width || src.height / 2 < self.window_height {
                break;
            }
            base_cow = Some(src.downsample_half());
            base_factor *= 2.0;
        }
        let base = base_cow.as_ref().unwrap_or(gray);
        // Levels upscale at most to the first one, so the integral buffers sized for it fit all.
        let level0 = (
            (base.width as f32 * base_factor / first_scale).round() as usize,
            (base.height as f32 * base_factor / first_scale).round() as usize,
        );
        let mut scratch = Scratch::new(level0.0.max(1), level0.1.max(1));
        let plan = self.plan(scratch.stride);
        let norm_area = ((self.window_width - 2) * (self.window_height - 2)) as f64;
        let norm_ofs = [
            scratch.stride + 1,
            scratch.stride + self.window_width - 1,
            (self.window_height - 1) * scratch.stride + 1,
            (self.window_height - 1) * scratch.stride + self.window_width - 1,
        ];

        let mut batch = Batch::default();
        let mut scale = first_scale;
        loop {
            let (lw, lh) = (((w as f32) / scale).round() as usize, ((h as f32) / scale).round() as usize);
            if lw < self.window_width || lh < self.window_height || ww * scale > opts.max_size {
                break;
            }
            let (lw, lh) = (lw.min(level0.0), lh.min(level0.1));
            fill_integral(base, lw, lh, &mut scratch);
            let step = if scale > opts.fine_above_scale { 1 } else { opts.step.max(1) };
            let nx = (lw - self.window_width) / step + 1;
            let mut y = 0;
            while y + self.window_height <= lh {
                self.row_survivors(&plan, &scratch, (norm_area, norm_ofs), (y, nx, step), &mut batch);
                for &i in &batch.index {
                    hits.push(Rect::new((i as usize * step) as f32 * scale, y as f32 * scale, ww * scale, wh * scale));
                }
                y += step;
            }
            scale *= opts.scale_step.max(1.01);
        }
    }

    /// The windows of row `y` (`nx` positions `step` apart) that pass every stage, left in
    /// `batch`: the row's windows go through the cascade stage by stage over all surviving windows
    /// at once (trees outer, windows inner): independent windows keep the core busy where one
    /// window's tree after tree waits on each comparison.
    fn row_survivors(
        &self,
        plan: &Plan,
        scratch: &Scratch,
        (norm_area, norm_ofs): (f64, [usize; 4]),
        (y, nx, step): (usize, usize, usize),
        batch: &mut Batch,
    ) {
        let (sum, sqsum, stride) = (&scratch.sum, &scratch.sqsum, scratch.stride);
        batch.clear();
        for i in 0..nx {
            let p = y * stride + i * step;
            let s = (sum[p + norm_ofs[0]] - sum[p + norm_ofs[1]] - sum[p + norm_ofs[2]] + sum[p + norm_ofs[3]]) as f64;
            let sq = sqsum[p + norm_ofs[0]] - sqsum[p + norm_ofs[1]] - sqsum[p + norm_ofs[2]] + sqsum[p + norm_ofs[3]];
            let nf = norm_area * sq - s * s;
            batch.push(p, i as u32, if nf > 0.0 { nf.sqrt() as f32 } else { 1.0 });
        }
        self.stage_batch(plan, 0, sum, batch);
        // OpenCV's walk along a row: a window rejected by the very first stage also skips the next
        // position (its neighbour is very likely no face either). The survivors of the first stage
        // among the windows the walk visits go on.
        let mut kept = 0;
        let mut i = 0;
        while i < nx {
            if batch.acc[i] < self.stages[0].threshold {
                i += 2;
            } else {
                batch.keep(i, kept);
                kept += 1;
                i += 1;
            }
        }
        batch.truncate(kept);
        for si in 1..self.stages.len() {
            if batch.len() == 0 {
                break;
            }
            self.stage_batch(plan, si, sum, batch);
            let threshold = self.stages[si].threshold;
            let mut kept = 0;
            for k in 0..batch.len() {
                if batch.acc[k] >= threshold {
                    batch.keep(k, kept);
                    kept += 1;
                }
            }
            batch.truncate(kept);
        }
    }

    /// Scan and group: the cascade's detections in input pixels.
    pub fn detect(&self, gray: &GrayF32, opts: &ScanOptions) -> Vec<Hit> {
        let mut raw = Vec::new();
        self.scan(gray, opts, &mut raw);
        group_rectangles(&raw, opts.min_neighbours, opts.group_eps)
    }
}

/// `v.round()` for a pixel clamped to 0..=255, without the libm call `round` becomes on baseline
/// x86-64 (no SSE4.1): truncation and the exact fractional part give the same half-away-from-zero
/// rounding.
#[inline(always)]
fn round_pixel(v: f32) -> i32 {
    let v = v.clamp(0.0, 255.0);
    let t = v as i32;
    t + ((v - t as f32) >= 0.5) as i32
}

/// Resize `base` bilinearly to `lw × lh` and build the integral and squared integral images of the
/// result (pixel values rounded to integers as in an 8-bit image) in `scratch`.
fn fill_integral(base: &GrayF32, lw: usize, lh: usize, scratch: &mut Scratch) {
    let stride = scratch.stride;
    let sx = base.width as f32 / lw as f32;
    let sy = base.height as f32 / lh as f32;
    let same = base.width == lw && base.height == lh;
    for v in &mut scratch.sum[..stride] {
        *v = 0;
    }
    for v in &mut scratch.sqsum[..stride] {
        *v = 0.0;
    }
    for y in 0..lh {
        let row = &mut scratch.row[..lw];
        if same {
            row.copy_from_slice(&base.data[y * lw..(y + 1) * lw]);
        } else {
            let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (base.height - 1) as f32);
            let y0 = fy as usize;
            let y1 = (y0 + 1).min(base.height - 1);
            let ty = fy - y0 as f32;
            let (r0, r1) = (&base.data[y0 * base.width..(y0 + 1) * base.width], &base.data[y1 * base.width..(y1 + 1) * base.width]);
            for (x, out) in row.iter_mut().enumerate() {
                let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (base.width - 1) as f32);
                let x0 = fx as usize;
                let x1 = (x0 + 1).min(base.width - 1);
                let tx = fx - x0 as f32;
                let top = r0[x0] + tx * (r0[x1] - r0[x0]);
                let bottom = r1[x0] + tx * (r1[x1] - r1[x0]);
                *out = top + ty * (bottom - top);
            }
        }
        let (prev, cur) = scratch.sum.split_at_mut((y + 1) * stride);
        let prev = &prev[y * stride..];
        let (qprev, qcur) = scratch.sqsum.split_at_mut((y + 1) * stride);
        let qprev = &qprev[y * stride..];
        cur[0] = 0;
        qcur[0] = 0.0;
        let (mut acc, mut qacc) = (0i32, 0.0f64);
        for x in 0..lw {
            let v = round_pixel(row[x]);
            acc += v;
            qacc += (v * v) as f64;
            cur[x + 1] = prev[x + 1] + acc;
            qcur[x + 1] = qprev[x + 1] + qacc;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain OpenCV walk, window by window and tree by tree: what the batched scan must equal.
    fn scan_window_by_window(cascade: &Cascade, gray: &GrayF32, min_size: f32) -> Vec<Rect> {
        let first_scale = min_size / cascade.window_width as f32;
        let (lw0, lh0) = ((gray.width as f32 / first_scale).round() as usize, (gray.height as f32 / first_scale).round() as usize);
        let mut scratch = Scratch::new(lw0, lh0);
        let plan = cascade.plan(scratch.stride);
        let (ww, wh, stride) = (cascade.window_width, cascade.window_height, scratch.stride);
        let mut hits = Vec::new();
        let mut scale = first_scale;
        loop {
            let (lw, lh) = (((gray.width as f32) / scale).round() as usize, ((gray.height as f32) / scale).round() as usize);
            if lw < ww || lh < wh {
                return hits;
            }
            let (lw, lh) = (lw.min(lw0), lh.min(lh0));
            fill_integral(gray, lw, lh, &mut scratch);
            let (sum, sq) = (&scratch.sum, &scratch.sqsum);
            let corner = |p: usize| [p + stride + 1, p + stride + ww - 1, p + (wh - 1) * stride + 1, p + (wh - 1) * stride + ww - 1];
            for y in (0..=lh - wh).step_by(2) {
                let mut x = 0;
                while x + ww <= lw {
                    let p = y * stride + x;
                    let c = corner(p);
                    let s = (sum[c[0]] - sum[c[1]] - sum[c[2]] + sum[c[3]]) as f64;
                    let q = sq[c[0]] - sq[c[1]] - sq[c[2]] + sq[c[3]];
                    let nf = ((ww - 2) * (wh - 2)) as f64 * q - s * s;
                    let norm = if nf > 0.0 { nf.sqrt() as f32 } else { 1.0 };
                    let window = &sum[p..p + plan.extent];
                    let rejected_at = cascade.stages.iter().position(|stage| {
                        let mut stage_sum = 0.0f32;
                        for tree in &plan.trees[stage.first_weak as usize..(stage.first_weak + stage.weak_count) as usize] {
                            let nodes = &plan.nodes[tree.first_node as usize..];
                            let mut idx = 0i32;
                            loop {
                                let node = &nodes[idx as usize];
                                idx = if goes_left(window, node, norm) { node.left } else { node.right };
                                if idx <= 0 {
                                    break;
                                }
                            }
                            stage_sum += cascade.leaves[(tree.first_leaf as i32 - idx) as usize];
                        }
                        stage_sum < stage.threshold
                    });
                    match rejected_at {
                        None => hits.push(Rect::new(x as f32 * scale, y as f32 * scale, ww as f32 * scale, wh as f32 * scale)),
                        Some(0) => x += 2,
                        Some(_) => {}
                    }
                    x += 2;
                }
            }
            scale *= 1.1;
        }
    }

    #[test]
    fn batched_scan_gives_the_window_by_window_hits() {
        let cascade = Cascade::parse(include_str!("../../../../models/cascades/haarcascade_frontalface_alt2.xml"), "alt2").unwrap();
        let photo = facegate_core::imaging::open(&facegate_paths::shared_dir().join("data/imm/01-1m.jpg")).unwrap();
        // A quarter-size photo scanned from scale 1.2 (no halving), so both scans see the same levels.
        let gray = photo.gray.resize(160, 120);
        let opts = ScanOptions { min_size: 24.0, ..ScanOptions::default() };
        let mut batched = Vec::new();
        cascade.scan(&gray, &opts, &mut batched);
        let reference = scan_window_by_window(&cascade, &gray, 24.0);
        assert!(reference.len() > 3, "the face gives several raw windows: {reference:?}");
        assert_eq!(batched, reference);
    }
}
