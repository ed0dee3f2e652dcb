//! Viola–Jones detection with OpenCV Haar cascades (the `opencv-cascade-classifier` XML format).
//!
//! A cascade is a sequence of boosted stages; each stage sums the leaf values of small decision
//! trees over Haar rectangle features and rejects the window when the sum falls below the stage
//! threshold. Features are evaluated on an integral image of the window at the cascade's training
//! size (20×20): the image is resized for each scale (as OpenCV does) rather than the features.
//! Feature values are divided by `area·σ` of the window's inner rectangle (variance normalisation),
//! which makes the detector insensitive to contrast and brightness.
//!
//! Here the model and the grouping of raw hits; `xml` reads OpenCV's files, `scan` evaluates.

mod scan;
mod xml;

use super::DetectError;
use facegate_core::geometry::Rect;

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

fn model_error(path: &str, message: impl Into<String>) -> DetectError {
    DetectError::Model { path: path.to_string(), message: message.into() }
}

impl Cascade {
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
    /// Window step in pixels of the resized image.
    pub step: usize,
    /// Levels scanned at a scale above this use step 1 whatever `step` says (OpenCV's
    /// `detectMultiScale`: step 2 up to scale 2, then 1). Infinite: `step` on every level.
    pub fine_above_scale: f32,
    /// Overlapping raw hits needed to keep a group (OpenCV's `minNeighbors`).
    pub min_neighbours: usize,
    /// Grouping tolerance (OpenCV's `eps` in `groupRectangles`).
    pub group_eps: f32,
}

impl Default for ScanOptions {
    fn default() -> Self {
        Self {
            min_size: 24.0,
            max_size: f32::INFINITY,
            scale_step: 1.1,
            step: 2,
            fine_above_scale: f32::INFINITY,
            min_neighbours: 3,
            group_eps: 0.2,
        }
    }
}

/// A grouped detection: its box in input pixels and how many raw windows voted for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub rect: Rect,
    pub neighbours: usize,
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
