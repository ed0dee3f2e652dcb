//! Viola–Jones detection with OpenCV Haar cascades (the `opencv-cascade-classifier` XML format).
//!
//! A cascade is a sequence of boosted stages; each stage sums the leaf values of small decision
//! trees over Haar rectangle features and rejects the window when the sum falls below the stage
//! threshold. Features are evaluated on an integral image of the window at the cascade's training
//! size (20×20): the image is resized for each scale (as OpenCV does) rather than the features.
//! Feature values are divided by `area·σ` of the window's inner rectangle (variance normalisation),
//! which makes the detector insensitive to contrast and brightness.

use std::path::Path;

use super::DetectError;
use crate::geometry::Rect;
use crate::imaging::GrayF32;

/// One Haar feature: up to three weighted rectangles in window coordinates.
#[derive(Debug, Clone, Copy)]
struct Feature {
    rects: [[u8; 4]; 3],
    weights: [f32; 3],
    count: u8,
}

/// A decision-tree node: compare the feature with `threshold`; a child ≤ 0 names leaf `-child`.
#[derive(Debug, Clone, Copy)]
struct Node {
    feature: u32,
    threshold: f32,
    left: i32,
    right: i32,
}

#[derive(Debug, Clone, Copy)]
struct Weak {
    first_node: u32,
    first_leaf: u32,
}

#[derive(Debug, Clone, Copy)]
struct Stage {
    first_weak: u32,
    weak_count: u32,
    threshold: f32,
}

/// A parsed OpenCV Haar cascade.
#[derive(Debug, Clone)]
pub struct Cascade {
    pub window_width: usize,
    pub window_height: usize,
    features: Vec<Feature>,
    stages: Vec<Stage>,
    weaks: Vec<Weak>,
    nodes: Vec<Node>,
    leaves: Vec<f32>,
}

fn child<'a, 'i>(parent: roxmltree::Node<'a, 'i>, tag: &str) -> Option<roxmltree::Node<'a, 'i>> {
    parent.children().find(|n| n.has_tag_name(tag))
}

fn items<'a, 'i>(parent: roxmltree::Node<'a, 'i>) -> Vec<roxmltree::Node<'a, 'i>> {
    parent.children().filter(|n| n.is_element()).collect()
}

fn model_error(path: &str, message: impl Into<String>) -> DetectError {
    DetectError::Model { path: path.to_string(), message: message.into() }
}

impl Cascade {
    pub fn load(path: &Path) -> Result<Cascade, DetectError> {
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| model_error(&name, e.to_string()))?;
        Cascade::parse(&text, &name)
    }

    /// Parse the XML text of a cascade (`name` is used in error messages only).
    pub fn parse(text: &str, name: &str) -> Result<Cascade, DetectError> {
        let err = |m: String| model_error(name, m);
        let doc = roxmltree::Document::parse(text).map_err(|e| err(format!("not valid XML: {e}")))?;
        let cascade = doc
            .descendants()
            .find(|n| n.has_tag_name("cascade"))
            .ok_or_else(|| err("no <cascade> element (old-style OpenCV 1.x cascades are not supported)".into()))?;
        let text_of = |parent: roxmltree::Node<'_, '_>, tag: &str| -> Result<String, DetectError> {
            child(parent, tag).and_then(|n| n.text()).map(|t| t.trim().to_string()).ok_or_else(|| err(format!("missing <{tag}>")))
        };
        let stage_type = text_of(cascade, "stageType")?;
        let feature_type = text_of(cascade, "featureType")?;
        if stage_type != "BOOST" || feature_type != "HAAR" {
            return Err(err(format!("unsupported cascade type {stage_type}/{feature_type} (BOOST/HAAR only)")));
        }
        let parse_usize = |s: String| s.parse::<usize>().map_err(|_| err(format!("bad integer {s:?}")));
        let window_width = parse_usize(text_of(cascade, "width")?)?;
        let window_height = parse_usize(text_of(cascade, "height")?)?;
        if !(4..=255).contains(&window_width) || !(4..=255).contains(&window_height) {
            return Err(err(format!("window {window_width}x{window_height} out of range")));
        }
        let numbers = |s: &str| -> Result<Vec<f64>, DetectError> {
            s.split_whitespace().map(|v| v.parse::<f64>().map_err(|_| err(format!("bad number {v:?}")))).collect()
        };

        let features_node = child(cascade, "features").ok_or_else(|| err("missing <features>".into()))?;
        let mut features = Vec::new();
        for f in items(features_node) {
            if let Some(t) = child(f, "tilted").and_then(|n| n.text())
                && t.trim() != "0"
            {
                return Err(err("tilted (45°) Haar features are not supported".into()));
            }
            let rects_node = child(f, "rects").ok_or_else(|| err("feature without <rects>".into()))?;
            let mut feature = Feature { rects: [[0; 4]; 3], weights: [0.0; 3], count: 0 };
            for r in items(rects_node) {
                let v = numbers(r.text().unwrap_or(""))?;
                if v.len() != 5 || feature.count == 3 {
                    return Err(err("a feature rectangle needs `x y w h weight`, at most 3 per feature".into()));
                }
                let (x, y, w, h) = (v[0], v[1], v[2], v[3]);
                if x < 0.0 || y < 0.0 || w <= 0.0 || h <= 0.0 || x + w > window_width as f64 || y + h > window_height as f64 {
                    return Err(err(format!("feature rectangle {v:?} leaves the window")));
                }
                let i = feature.count as usize;
                feature.rects[i] = [x as u8, y as u8, w as u8, h as u8];
                feature.weights[i] = v[4] as f32;
                feature.count += 1;
            }
            if feature.count == 0 {
                return Err(err("feature without rectangles".into()));
            }
            features.push(feature);
        }

        let stages_node = child(cascade, "stages").ok_or_else(|| err("missing <stages>".into()))?;
        let (mut stages, mut weaks, mut nodes, mut leaves) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for s in items(stages_node) {
            let threshold = numbers(&text_of(s, "stageThreshold")?)?.first().copied().ok_or_else(|| err("empty stage threshold".into()))?;
            let weak_node = child(s, "weakClassifiers").ok_or_else(|| err("stage without <weakClassifiers>".into()))?;
            let first_weak = weaks.len() as u32;
            for w in items(weak_node) {
                let internal = numbers(&text_of(w, "internalNodes")?)?;
                let leaf_values = numbers(&text_of(w, "leafValues")?)?;
                if internal.is_empty() || internal.len() % 4 != 0 {
                    return Err(err("internalNodes must hold groups of `left right feature threshold`".into()));
                }
                let node_count = internal.len() / 4;
                for n in internal.chunks(4) {
                    let (left, right, feature) = (n[0] as i32, n[1] as i32, n[2]);
                    if feature < 0.0 || feature as usize >= features.len() {
                        return Err(err(format!("node refers to feature {feature}, only {} exist", features.len())));
                    }
                    // Children must point forward to a node or to an existing leaf, so evaluation ends.
                    for c in [left, right] {
                        let ok = if c > 0 { (c as usize) < node_count } else { ((-c) as usize) < leaf_values.len() };
                        if !ok {
                            return Err(err(format!("tree child {c} is out of range")));
                        }
                    }
                    nodes.push(Node { feature: feature as u32, threshold: n[3] as f32, left, right });
                }
                // A tree whose nodes could loop would never end: OpenCV trees only point forward.
                let base = nodes.len() - node_count;
                if nodes[base..]
                    .iter()
                    .enumerate()
                    .any(|(i, n)| (n.left > 0 && n.left as usize <= i) || (n.right > 0 && n.right as usize <= i))
                {
                    return Err(err("tree nodes must point forward".into()));
                }
                weaks.push(Weak { first_node: base as u32, first_leaf: leaves.len() as u32 });
                leaves.extend(leaf_values.iter().map(|&v| v as f32));
            }
            stages.push(Stage { first_weak, weak_count: weaks.len() as u32 - first_weak, threshold: threshold as f32 });
        }
        if stages.is_empty() {
            return Err(err("cascade has no stages".into()));
        }
        Ok(Cascade { window_width, window_height, features, stages, weaks, nodes, leaves })
    }

    /// The same cascade for the mirror image (x ↦ W − x): finds faces turned the other way.
    pub fn mirrored(&self) -> Cascade {
        let mut out = self.clone();
        let w = self.window_width as u8;
        for f in &mut out.features {
            for r in f.rects.iter_mut().take(f.count as usize) {
                r[0] = w - r[0] - r[2];
            }
        }
        out
    }

    pub fn stage_count(&self) -> usize {
        self.stages.len()
    }
}

/// Options of the multi-scale scan.
#[derive(Debug, Clone, Copy)]
pub struct ScanOptions {
    /// Smallest face side searched, in input pixels.
    pub min_size: f32,
    /// Largest face side searched (the image size bounds it anyway).
    pub max_size: f32,
    /// Ratio between successive scales.
    pub scale_step: f32,
    /// Window step in pixels of the resized image (OpenCV uses 2 below scale 2, then 1).
    pub step: usize,
    /// Overlapping raw hits needed to keep a group (OpenCV's `minNeighbors`).
    pub min_neighbours: usize,
    /// Grouping tolerance (OpenCV's `eps` in `groupRectangles`).
    pub group_eps: f32,
}

impl Default for ScanOptions {
    fn default() -> Self {
        Self { min_size: 24.0, max_size: f32::INFINITY, scale_step: 1.1, step: 2, min_neighbours: 3, group_eps: 0.2 }
    }
}

/// A grouped detection: its box in input pixels and how many raw windows voted for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub rect: Rect,
    pub neighbours: usize,
}

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
}

/// Sum of the integral-image rectangle whose corners are `c`, for the window at `window[0]`.
#[inline(always)]
fn rect_sum(window: &[i32], c: &[u32; 4]) -> i32 {
    // Wrapping: the result is exact (it is a sum of at most 255·20·20), and skipping the overflow
    // checks of debug builds keeps the test profile's scan as fast as the release one.
    window[c[0] as usize].wrapping_sub(window[c[1] as usize]).wrapping_sub(window[c[2] as usize]).wrapping_add(window[c[3] as usize])
}

/// Whether the node's feature on this window falls on its left side (`value / norm < threshold`,
/// without the division).
#[inline(always)]
fn goes_left(window: &[i32], node: &OptNode, norm: f32) -> bool {
    let mut value = node.weights[0] * rect_sum(window, &node.corners[0]) as f32 + node.weights[1] * rect_sum(window, &node.corners[1]) as f32;
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
                    [root, child] if child.left <= 0 && child.right <= 0 && (root.left == 1) != (root.right == 1) && root.left <= 1 && root.right <= 1 => {
                        TreeShape::Pair
                    }
                    _ => TreeShape::General,
                };
                TreePlan { first_node: weak.first_node, first_leaf: weak.first_leaf, shape }
            })
            .collect();
        Plan { nodes, trees }
    }

    /// Run the cascade on the window whose top-left integral index is `p`. Returns the index of
    /// the rejecting stage, or `None` when every stage accepts.
    #[inline]
    fn run_at(&self, plan: &Plan, sum: &[i32], p: usize, norm: f32) -> Option<usize> {
        let window = &sum[p..];
        for (si, stage) in self.stages.iter().enumerate() {
            let mut stage_sum = 0.0f32;
            for tree in &plan.trees[stage.first_weak as usize..(stage.first_weak + stage.weak_count) as usize] {
                let nodes = &plan.nodes[tree.first_node as usize..];
                // The leaf is `-idx` once `idx` ≤ 0.
                let idx = match tree.shape {
                    TreeShape::Stump => {
                        let root = &nodes[0];
                        select(goes_left(window, root, norm), root.left, root.right)
                    }
                    TreeShape::Pair => {
                        let (root, child) = (&nodes[0], &nodes[1]);
                        let at_root = select(goes_left(window, root, norm), root.left, root.right);
                        let at_child = select(goes_left(window, child, norm), child.left, child.right);
                        select(at_root > 0, at_child, at_root)
                    }
                    TreeShape::General => {
                        let mut idx = 0i32;
                        loop {
                            let node = &nodes[idx as usize];
                            idx = if goes_left(window, node, norm) { node.left } else { node.right };
                            if idx <= 0 {
                                break idx;
                            }
                        }
                    }
                };
                stage_sum += self.leaves[(tree.first_leaf as i32 - idx) as usize];
            }
            if stage_sum < stage.threshold {
                return Some(si);
            }
        }
        None
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

        let mut scale = first_scale;
        loop {
            let (lw, lh) = (((w as f32) / scale).round() as usize, ((h as f32) / scale).round() as usize);
            if lw < self.window_width || lh < self.window_height || ww * scale > opts.max_size {
                break;
            }
            let (lw, lh) = (lw.min(level0.0), lh.min(level0.1));
            fill_integral(base, lw, lh, &mut scratch);
            let step = opts.step.max(1);
            let (sum, sqsum, stride) = (&scratch.sum, &scratch.sqsum, scratch.stride);
            let mut y = 0;
            while y + self.window_height <= lh {
                let mut x = 0;
                while x + self.window_width <= lw {
                    let p = y * stride + x;
                    let s = (sum[p + norm_ofs[0]] - sum[p + norm_ofs[1]] - sum[p + norm_ofs[2]] + sum[p + norm_ofs[3]]) as f64;
                    let sq = sqsum[p + norm_ofs[0]] - sqsum[p + norm_ofs[1]] - sqsum[p + norm_ofs[2]] + sqsum[p + norm_ofs[3]];
                    let nf = norm_area * sq - s * s;
                    let norm = if nf > 0.0 { nf.sqrt() as f32 } else { 1.0 };
                    match self.run_at(&plan, sum, p, norm) {
                        None => hits.push(Rect::new(x as f32 * scale, y as f32 * scale, ww * scale, wh * scale)),
                        // Rejected by the very first stage: the neighbour is very likely no face either.
                        Some(0) => x += step,
                        Some(_) => {}
                    }
                    x += step;
                }
                y += step;
            }
            scale *= opts.scale_step.max(1.01);
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

/// OpenCV's `groupRectangles`: cluster raw hits whose corners agree within `eps` of their size,
/// average each cluster, drop clusters of at most `min_neighbours` hits (none when it is 0) and
/// drop boxes lying inside a stronger one.
pub fn group_rectangles(raw: &[Rect], min_neighbours: usize, eps: f32) -> Vec<Hit> {
    if min_neighbours == 0 {
        return raw.iter().map(|&rect| Hit { rect, neighbours: 1 }).collect();
    }
    let n = raw.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let similar = |a: &Rect, b: &Rect| {
        let delta = eps * 0.5 * (a.width.min(b.width) + a.height.min(b.height));
        (a.x - b.x).abs() <= delta
            && (a.y - b.y).abs() <= delta
            && (a.x + a.width - b.x - b.width).abs() <= delta
            && (a.y + a.height - b.y - b.height).abs() <= delta
    };
    for i in 0..n {
        for j in i + 1..n {
            if similar(&raw[i], &raw[j]) {
                let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                if a != b {
                    parent[a] = b;
                }
            }
        }
    }
    let mut sums: std::collections::HashMap<usize, ([f64; 4], usize)> = std::collections::HashMap::new();
    for (i, r) in raw.iter().enumerate() {
        let root = find(&mut parent, i);
        let e = sums.entry(root).or_insert(([0.0; 4], 0));
        e.0[0] += r.x as f64;
        e.0[1] += r.y as f64;
        e.0[2] += r.width as f64;
        e.0[3] += r.height as f64;
        e.1 += 1;
    }
    let mut groups: Vec<Hit> = sums
        .into_values()
        .filter(|(_, count)| *count > min_neighbours)
        .map(|(s, count)| {
            let c = count as f64;
            Hit { rect: Rect::new((s[0] / c) as f32, (s[1] / c) as f32, (s[2] / c) as f32, (s[3] / c) as f32), neighbours: count }
        })
        .collect();
    groups.sort_by(|a, b| b.neighbours.cmp(&a.neighbours).then(b.rect.area().total_cmp(&a.rect.area())));
    let kept: Vec<Hit> = groups
        .iter()
        .enumerate()
        .filter(|(i, g)| {
            let r1 = g.rect;
            !groups.iter().enumerate().any(|(j, o)| {
                let r2 = o.rect;
                let (dx, dy) = (r2.width * eps, r2.height * eps);
                *i != j
                    && r1.x >= r2.x - dx
                    && r1.y >= r2.y - dy
                    && r1.x + r1.width <= r2.x + r2.width + dx
                    && r1.y + r1.height <= r2.y + r2.height + dy
                    && (o.neighbours > g.neighbours.max(3) || g.neighbours < 3)
            })
        })
        .map(|(_, g)| *g)
        .collect();
    kept
}
