//! The SIFT descriptor as the thesis specifies it (2.4.1, after Lowe 2004): 4×4 cells of 4×4
//! pixels, 8 orientation bins, Gaussian weighting, trilinear binning, normalise, clip at 0.2 and
//! renormalise. No keypoint detection and no dominant orientation: the patch and the gradient
//! orientations are expressed relative to the contour normal at the landmark, which makes the
//! descriptor turn with the face.
//!
//! Candidates on a 2D window around a landmark share most of their samples, so the window's
//! oriented gradients are sampled once into a [`DescriptorGrid`] and each candidate's descriptor
//! is binned from it.
//!
//! Here the constants, the gradient image and its sampling, and the one-point descriptor; the
//! window of candidates is `grid`'s.

mod grid;

use facegate_core::geometry::Point;
use facegate_core::imaging::GrayF32;

pub use grid::DescriptorGrid;

pub const CELLS: usize = 4;
pub const CELL_PIXELS: usize = 4;
pub const BINS: usize = 8;
pub const PATCH: usize = CELLS * CELL_PIXELS;
pub const DESCRIPTOR_LEN: usize = CELLS * CELLS * BINS;
/// Lowe's clipping of large gradient contributions, for robustness to non-linear illumination.
const CLIP: f32 = 0.2;

/// Central-difference gradients of an image (computed once per pyramid level).
#[derive(Debug, Clone)]
pub struct Gradients {
    pub width: usize,
    pub height: usize,
    /// (∂x, ∂y) per pixel, interleaved so that a bilinear sample touches half the cache lines.
    pub gxy: Vec<[f32; 2]>,
}

impl Gradients {
    pub fn new(img: &GrayF32) -> Gradients {
        let (w, h) = (img.width, img.height);
        let mut gxy = vec![[0.0f32; 2]; w * h];
        for y in 0..h {
            let (ym, yp) = (y.saturating_sub(1), (y + 1).min(h - 1));
            for x in 0..w {
                let (xm, xp) = (x.saturating_sub(1), (x + 1).min(w - 1));
                gxy[y * w + x] = [0.5 * (img.data[y * w + xp] - img.data[y * w + xm]), 0.5 * (img.data[yp * w + x] - img.data[ym * w + x])];
            }
        }
        Gradients { width: w, height: h, gxy }
    }
}

impl Gradients {
    /// Bilinear (gx, gy) at a point, clamped at the border, with the weights shared by both planes.
    #[inline]
    fn sample(&self, x: f32, y: f32) -> (f32, f32) {
        let (w, h) = (self.width, self.height);
        let x = x.clamp(0.0, (w - 1) as f32);
        let y = y.clamp(0.0, (h - 1) as f32);
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let (i00, i01, i10, i11) = (y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1);
        let (w00, w01, w10, w11) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy);
        let g = &self.gxy;
        let (g00, g01, g10, g11) = (g[i00], g[i01], g[i10], g[i11]);
        (w00 * g00[0] + w01 * g01[0] + w10 * g10[0] + w11 * g11[0], w00 * g00[1] + w01 * g01[1] + w10 * g10[1] + w11 * g11[1])
    }

    /// [`sample`](Self::sample) for a point known to lie in `[0, w−1) × [0, h−1)`: no clamping.
    #[inline(always)]
    fn sample_inside(&self, x: f32, y: f32) -> (f32, f32) {
        let w = self.width;
        let (x0, y0) = (x as usize, y as usize);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let i00 = y0 * w + x0;
        let (w00, w01, w10, w11) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy);
        let g = &self.gxy[i00..i00 + w + 2];
        let (g00, g01, g10, g11) = (g[0], g[1], g[w], g[w + 1]);
        (w00 * g00[0] + w01 * g01[0] + w10 * g10[0] + w11 * g11[0], w00 * g00[1] + w01 * g01[1] + w10 * g10[1] + w11 * g11[1])
    }
}

/// The descriptor at one point (no candidate window).
pub fn descriptor(grad: &Gradients, center: Point, normal: Point) -> [f32; DESCRIPTOR_LEN] {
    let mut grid = DescriptorGrid::new();
    grid.fill(grad, center, normal, 0);
    let mut out = [0.0; DESCRIPTOR_LEN];
    grid.descriptor(0, 0, &mut out);
    out
}
