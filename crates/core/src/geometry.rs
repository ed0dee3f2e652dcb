//! Small geometric types shared by the pipeline stages.

use serde::{Deserialize, Serialize};

/// A point in image pixels, origin top left, x to the right, y down.
pub type Point = [f32; 2];

/// An axis-aligned box in image pixels, origin top left.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Rect {
    pub x: f32,
    pub y: f32,
    pub width: f32,
    pub height: f32,
}

impl Rect {
    pub fn new(x: f32, y: f32, width: f32, height: f32) -> Self {
        Self { x, y, width, height }
    }

    pub fn area(&self) -> f32 {
        self.width.max(0.0) * self.height.max(0.0)
    }

    pub fn center(&self) -> Point {
        [self.x + 0.5 * self.width, self.y + 0.5 * self.height]
    }

    pub fn contains(&self, p: Point) -> bool {
        p[0] >= self.x && p[0] <= self.x + self.width && p[1] >= self.y && p[1] <= self.y + self.height
    }

    /// Distance between this box's centre and `other`'s.
    pub fn center_distance(&self, other: &Rect) -> f32 {
        let ([x, y], [ox, oy]) = (self.center(), other.center());
        (x - ox).hypot(y - oy)
    }

    /// Whether this box's centre lies within `last`'s width of `last`'s centre: the same face a
    /// moment later under one camera (a person moves a few pixels a frame; another person stands
    /// a face width or more away).
    pub fn follows(&self, last: &Rect) -> bool {
        self.center_distance(last) <= last.width
    }

    /// Intersection over union of two boxes.
    pub fn iou(&self, other: &Rect) -> f32 {
        let x0 = self.x.max(other.x);
        let y0 = self.y.max(other.y);
        let x1 = (self.x + self.width).min(other.x + other.width);
        let y1 = (self.y + self.height).min(other.y + other.height);
        let inter = (x1 - x0).max(0.0) * (y1 - y0).max(0.0);
        let union = self.area() + other.area() - inter;
        if union > 0.0 { inter / union } else { 0.0 }
    }

    /// The smallest box holding all the points.
    pub fn bounding(points: &[Point]) -> Option<Rect> {
        let first = points.first()?;
        let (mut x0, mut y0, mut x1, mut y1) = (first[0], first[1], first[0], first[1]);
        for p in points {
            x0 = x0.min(p[0]);
            y0 = y0.min(p[1]);
            x1 = x1.max(p[0]);
            y1 = y1.max(p[1]);
        }
        Some(Rect::new(x0, y0, x1 - x0, y1 - y0))
    }
}

/// Mean of a set of points (the centre of an eye or mouth outline).
pub fn centroid(points: &[Point]) -> Point {
    let n = points.len().max(1) as f32;
    let (sx, sy) = points.iter().fold((0.0, 0.0), |(sx, sy), p| (sx + p[0], sy + p[1]));
    [sx / n, sy / n]
}

pub fn distance(a: Point, b: Point) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

/// A 2D similarity transform `p ↦ s·R(θ)·p + t`, stored as `[a, -b; b, a]` plus translation
/// (a = s·cos θ, b = s·sin θ).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    pub a: f32,
    pub b: f32,
    pub tx: f32,
    pub ty: f32,
}

impl Similarity {
    pub const IDENTITY: Similarity = Similarity { a: 1.0, b: 0.0, tx: 0.0, ty: 0.0 };

    pub fn apply(&self, p: Point) -> Point {
        [self.a * p[0] - self.b * p[1] + self.tx, self.b * p[0] + self.a * p[1] + self.ty]
    }

    pub fn scale(&self) -> f32 {
        (self.a * self.a + self.b * self.b).sqrt()
    }

    pub fn rotation(&self) -> f32 {
        self.b.atan2(self.a)
    }

    pub fn inverse(&self) -> Similarity {
        let d = self.a * self.a + self.b * self.b;
        let (ia, ib) = (self.a / d, -self.b / d);
        Similarity { a: ia, b: ib, tx: -(ia * self.tx - ib * self.ty), ty: -(ib * self.tx + ia * self.ty) }
    }

    /// `self ∘ other`: apply `other` first.
    pub fn compose(&self, other: &Similarity) -> Similarity {
        Similarity {
            a: self.a * other.a - self.b * other.b,
            b: self.b * other.a + self.a * other.b,
            tx: self.a * other.tx - self.b * other.ty + self.tx,
            ty: self.b * other.tx + self.a * other.ty + self.ty,
        }
    }

    /// Least-squares similarity taking `from[i]` to `to[i]` (optionally weighted), in closed form
    /// (Umeyama without reflection). f64 inside: the sums are badly conditioned for large coordinates.
    pub fn fit(from: &[Point], to: &[Point], weights: Option<&[f32]>) -> Similarity {
        assert_eq!(from.len(), to.len());
        let w = |i: usize| weights.map_or(1.0, |w| w[i] as f64);
        let (mut sw, mut fx, mut fy, mut tx, mut ty) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
        for i in 0..from.len() {
            let wi = w(i);
            sw += wi;
            fx += wi * from[i][0] as f64;
            fy += wi * from[i][1] as f64;
            tx += wi * to[i][0] as f64;
            ty += wi * to[i][1] as f64;
        }
        if sw <= 0.0 {
            return Similarity::IDENTITY;
        }
        let (fx, fy, tx, ty) = (fx / sw, fy / sw, tx / sw, ty / sw);
        let (mut num_a, mut num_b, mut den) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..from.len() {
            let wi = w(i);
            let (px, py) = (from[i][0] as f64 - fx, from[i][1] as f64 - fy);
            let (qx, qy) = (to[i][0] as f64 - tx, to[i][1] as f64 - ty);
            num_a += wi * (px * qx + py * qy);
            num_b += wi * (px * qy - py * qx);
            den += wi * (px * px + py * py);
        }
        if den <= f64::EPSILON {
            return Similarity { a: 1.0, b: 0.0, tx: (tx - fx) as f32, ty: (ty - fy) as f32 };
        }
        let a = num_a / den;
        let b = num_b / den;
        Similarity { a: a as f32, b: b as f32, tx: (tx - (a * fx - b * fy)) as f32, ty: (ty - (b * fx + a * fy)) as f32 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn similarity_fit_recovers_a_known_transform() {
        let t = Similarity { a: 1.2 * 0.3f32.cos(), b: 1.2 * 0.3f32.sin(), tx: 5.0, ty: -3.0 };
        let from: Vec<Point> = vec![[0.0, 0.0], [10.0, 0.0], [3.0, 7.0], [-4.0, 2.0]];
        let to: Vec<Point> = from.iter().map(|&p| t.apply(p)).collect();
        let fit = Similarity::fit(&from, &to, None);
        assert!((fit.a - t.a).abs() < 1e-5 && (fit.b - t.b).abs() < 1e-5);
        assert!((fit.tx - t.tx).abs() < 1e-4 && (fit.ty - t.ty).abs() < 1e-4);
        let back = fit.inverse().apply(fit.apply([2.0, 3.0]));
        assert!((back[0] - 2.0).abs() < 1e-4 && (back[1] - 3.0).abs() < 1e-4);
        let id = fit.compose(&fit.inverse());
        assert!((id.a - 1.0).abs() < 1e-5 && id.b.abs() < 1e-5);
    }

    #[test]
    fn rect_iou_and_bounds() {
        let a = Rect::new(0.0, 0.0, 10.0, 10.0);
        let b = Rect::new(5.0, 0.0, 10.0, 10.0);
        assert!((a.iou(&b) - 50.0 / 150.0).abs() < 1e-6);
        let r = Rect::bounding(&[[1.0, 2.0], [4.0, -1.0]]).unwrap();
        assert_eq!(r, Rect::new(1.0, -1.0, 3.0, 3.0));
        assert!(r.contains([2.0, 0.0]) && !r.contains([0.0, 0.0]));
    }
}
