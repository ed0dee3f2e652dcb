//! The descriptors of a window of candidates: the window's oriented gradients sampled once
//! (AVX2 gathers where the CPU has them), each candidate's descriptor binned from them in two 1D
//! passes, then normalised and clipped.

use facegate_core::geometry::Point;

use super::{BINS, CELL_PIXELS, CELLS, CLIP, DESCRIPTOR_LEN, Gradients, PATCH};

/// atan2 by a minimax polynomial (max error ~1e-5 rad, far below an orientation bin of 45°):
/// the library call dominated the cost of sampling a window.
#[inline]
fn fast_atan2(y: f32, x: f32) -> f32 {
    // Written with selects rather than branches (same values) so that a row of samples vectorises.
    let (ax, ay) = (x.abs(), y.abs());
    let (mn, mx) = if ax < ay { (ax, ay) } else { (ay, ax) };
    let a = mn / mx; // NaN for 0/0: replaced by 0 below
    let s = a * a;
    let r = ((-0.046_496_475 * s + 0.159_314_22) * s - 0.327_622_76) * s * a + a;
    let r = if ay > ax { std::f32::consts::FRAC_PI_2 - r } else { r };
    let r = if x < 0.0 { std::f32::consts::PI - r } else { r };
    let r = if y < 0.0 { -r } else { r };
    if mx == 0.0 { 0.0 } else { r }
}

/// One oriented gradient sample, already split between its two orientation bins (linear
/// interpolation in orientation) as a full 8-bin histogram: binning a candidate's descriptor then
/// adds whole 8-lane vectors, which the compiler vectorises, instead of two scattered scalars.
/// The other six lanes are zero, and adding `w·0` leaves a sum unchanged, so the descriptor is
/// bit-identical to the scalar binning.
type OrientedSample = [f32; BINS];

/// Oriented gradient samples over the union of the patches of a `(2r+1)²` candidate window, and
/// the patches' cell sums. Reused across landmarks: no allocation per candidate.
///
/// The weight of a patch sample in a cell (bilinear in space times the Gaussian) is a product of a
/// row factor and a column factor, `k[ci][i]·k[cj][j]`, so a descriptor is binned in two 1D
/// passes: each window row is summed into the 4 cells of a patch column once per candidate column
/// (shared by all the candidates of that column), then the 16 rows of a candidate are summed into
/// its 4×4 cells. This is the same sum as binning every sample into its four cells, in another
/// order, at about a third of the arithmetic for a window of candidates.
pub struct DescriptorGrid {
    radius: usize,
    side: usize,
    samples: Vec<OrientedSample>,
    /// Per cell along one axis: the first patch sample with a non-zero weight and the weights
    /// (bilinear spatial weight times the 1D Gaussian) of the samples from there on (zero beyond).
    taps: [(usize, usize, [f32; 2 * CELL_PIXELS]); CELLS],
    /// For candidate column `b` (window column of the patch's left edge) and window row `a`: the
    /// row's samples summed into the 4 cell columns, `[cj][bin]`, at `columns[b * side + a]`.
    columns: Vec<[[f32; BINS]; CELLS]>,
    /// The window rows already summed for each candidate column (`lo..hi`, empty when `lo == hi`).
    column_rows: Vec<(usize, usize)>,
    /// One window row's gradients along the normal and the tangent (then magnitude and
    /// orientation), reused.
    row_gn: Vec<f32>,
    row_gt: Vec<f32>,
    center: Point,
    normal: Point,
    /// The sampled rectangle of the window: rows `[0]..[1]`, columns `[2]..[3]`.
    filled: [usize; 4],
}

impl Default for DescriptorGrid {
    fn default() -> Self {
        Self::new()
    }
}

impl DescriptorGrid {
    pub fn new() -> DescriptorGrid {
        // Lowe: Gaussian weight with σ equal to half the descriptor width; exp(−(u²+v²)/2σ²) is
        // the product of the row and column factors.
        let sigma = 0.5 * PATCH as f32;
        let mut taps = [(0usize, 0usize, [0.0f32; 2 * CELL_PIXELS]); CELLS];
        for (c, (first, len, weights)) in taps.iter_mut().enumerate() {
            // Sample i sits at cell coordinate x = (i + ½)/4 − ½ and feeds cell c by 1 − |x − c|.
            let support: Vec<(usize, f32)> = (0..PATCH)
                .filter_map(|i| {
                    let x = (i as f32 + 0.5) / CELL_PIXELS as f32 - 0.5;
                    let spatial = 1.0 - (x - c as f32).abs();
                    let u = i as f32 + 0.5 - 0.5 * PATCH as f32;
                    (spatial > 0.0).then(|| (i, spatial * (-(u * u) / (2.0 * sigma * sigma)).exp()))
                })
                .collect();
            *first = support[0].0;
            *len = support.len();
            for (k, &(_, w)) in support.iter().enumerate() {
                weights[k] = w;
            }
        }
        DescriptorGrid {
            radius: 0,
            side: 0,
            samples: Vec::new(),
            taps,
            columns: Vec::new(),
            column_rows: Vec::new(),
            row_gn: Vec::new(),
            row_gt: Vec::new(),
            center: [0.0; 2],
            normal: [1.0, 0.0],
            filled: [0; 4],
        }
    }

    /// Sample the oriented gradients around `center` for candidates up to `radius` pixels away along
    /// the normal and the tangent. `normal` must be a unit vector; orientations are measured from it.
    pub fn fill(&mut self, grad: &Gradients, center: Point, normal: Point, radius: usize) {
        self.fill_within(grad, center, normal, radius, radius);
    }

    /// Like [`fill`](Self::fill) for a window of `radius`, but sample only what the candidates up
    /// to `reach` (≤ `radius`) away need; [`widen`](Self::widen) samples more on demand. A
    /// coarse-to-fine search rarely visits the window's outer ring, and skipping it is exact.
    pub fn fill_within(&mut self, grad: &Gradients, center: Point, normal: Point, radius: usize, reach: usize) {
        let reach = reach.min(radius);
        self.radius = radius;
        self.side = PATCH + 2 * radius;
        self.center = center;
        self.normal = normal;
        self.samples.resize(self.side * self.side, [0.0; BINS]);
        let candidates = 2 * radius + 1;
        self.columns.resize(candidates * self.side, [[0.0; BINS]; CELLS]);
        self.column_rows.clear();
        self.column_rows.resize(candidates, (0, 0));
        let lo = radius - reach;
        let hi = self.side - lo;
        self.filled = [lo, hi, lo, hi];
        self.sample_rect(grad, lo..hi, lo..hi);
    }

    /// Make sure the samples of the candidate at (`da`, `db`) are there, extending the sampled
    /// rectangle of the window by the missing rows and columns.
    pub fn widen(&mut self, grad: &Gradients, da: isize, db: isize) {
        let r = self.radius as isize;
        debug_assert!(da.abs() <= r && db.abs() <= r, "candidate outside the window");
        let (a0, b0) = ((da + r) as usize, (db + r) as usize);
        let [fa0, fa1, fb0, fb1] = self.filled;
        let (na0, na1) = (fa0.min(a0), fa1.max(a0 + PATCH));
        let (nb0, nb1) = (fb0.min(b0), fb1.max(b0 + PATCH));
        if (na0, na1, nb0, nb1) == (fa0, fa1, fb0, fb1) {
            return;
        }
        // New rows over the new full width, then the new columns beside the old rows.
        self.sample_rect(grad, na0..fa0, nb0..nb1);
        self.sample_rect(grad, fa1..na1, nb0..nb1);
        self.sample_rect(grad, fa0..fa1, nb0..fb0);
        self.sample_rect(grad, fa0..fa1, fb1..nb1);
        self.filled = [na0, na1, nb0, nb1];
    }

    fn sample_rect(&mut self, grad: &Gradients, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>) {
        if rows.is_empty() || cols.is_empty() {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if crate::landmarks::simd::avx2() {
            // SAFETY: the CPU has AVX2 (checked at run time).
            return unsafe { self.sample_rect_avx2(grad, rows, cols) };
        }
        self.sample_rect_body(grad, rows, cols)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn sample_rect_avx2(&mut self, grad: &Gradients, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>) {
        self.sample_rect_with(grad, rows, cols, true)
    }

    #[inline(always)]
    fn sample_rect_body(&mut self, grad: &Gradients, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>) {
        self.sample_rect_with(grad, rows, cols, false)
    }

    /// `avx2_gathers`: only from [`sample_rect_avx2`](Self::sample_rect_avx2) (the CPU has AVX2).
    #[inline(always)]
    fn sample_rect_with(&mut self, grad: &Gradients, rows: std::ops::Range<usize>, cols: std::ops::Range<usize>, avx2_gathers: bool) {
        let (center, normal, side) = (self.center, self.normal, self.side);
        let (nx, ny) = (normal[0], normal[1]);
        let (tx, ty) = (-ny, nx);
        let off = self.radius as f32 + 0.5 * PATCH as f32 - 0.5;
        let scale = BINS as f32 / std::f32::consts::TAU;
        let width = cols.len();
        self.row_gn.resize(width, 0.0);
        self.row_gt.resize(width, 0.0);
        // The sample positions are affine in (a, b): if the rectangle's four corners fall inside
        // the image (with a pixel to spare for the bilinear neighbours), every sample does, and
        // the gathers need no clamping.
        let position = |a: usize, b: usize| {
            let (da, db) = (a as f32 - off, b as f32 - off);
            [center[0] + da * nx + db * tx, center[1] + da * ny + db * ty]
        };
        let (a_last, b_last) = (rows.end - 1, cols.end - 1);
        let inside =
            [position(rows.start, cols.start), position(rows.start, b_last), position(a_last, cols.start), position(a_last, b_last)]
                .iter()
                .all(|p| p[0] >= 0.0 && p[1] >= 0.0 && p[0] < (grad.width - 1) as f32 && p[1] < (grad.height - 1) as f32);
        for a in rows {
            let da = a as f32 - off;
            // Three passes per row: the bilinear gathers (scalar), the orientation arithmetic
            // (branch-free, so the compiler vectorises it), the split into bins.
            let row_x = center[0] + da * nx;
            let row_y = center[1] + da * ny;
            let mut done = 0;
            #[cfg(target_arch = "x86_64")]
            if inside && avx2_gathers {
                // SAFETY: only reached from `sample_rect_avx2` (AVX2 present); every sample of the
                // rectangle lies inside the image (`inside`), so every gathered index is in bounds.
                done = unsafe { gather_row_avx2(grad, [row_x, row_y], cols.start, width, off, normal, &mut self.row_gn, &mut self.row_gt) };
            }
            #[cfg(not(target_arch = "x86_64"))]
            let _ = avx2_gathers;
            for (k, b) in cols.clone().enumerate().skip(done) {
                let db = b as f32 - off;
                let (x, y) = (row_x + db * tx, row_y + db * ty);
                let (gx, gy) = if inside { grad.sample_inside(x, y) } else { grad.sample(x, y) };
                self.row_gn[k] = gx * nx + gy * ny;
                self.row_gt[k] = gx * tx + gy * ty;
            }
            for (gn, gt) in self.row_gn.iter_mut().zip(self.row_gt.iter_mut()) {
                let (n, t) = (*gn, *gt);
                // Reuse the two buffers: magnitude and orientation in bins, in [0, BINS].
                *gn = (n * n + t * t).sqrt();
                *gt = (fast_atan2(t, n) + std::f32::consts::PI) * scale;
            }
            let samples = &mut self.samples[a * side + cols.start..a * side + cols.end];
            for ((hist, &magnitude), &o) in samples.iter_mut().zip(&self.row_gn).zip(&self.row_gt) {
                let o0 = (o as i32) as f32; // o ≥ 0: truncation is floor, without a libm call
                let bin = (o0 as i32).rem_euclid(BINS as i32) as usize;
                let frac = o - o0;
                *hist = [0.0f32; BINS];
                hist[bin] = magnitude * (1.0 - frac);
                hist[(bin + 1) & (BINS - 1)] = magnitude * frac;
            }
        }
    }

    /// Sum window rows `rows` of candidate column `b0` into their 4 cell columns.
    #[inline(always)]
    fn sum_columns(&mut self, b0: usize, rows: std::ops::Range<usize>) {
        let side = self.side;
        for a in rows {
            let samples = &self.samples[a * side + b0..a * side + b0 + PATCH];
            let out = &mut self.columns[b0 * side + a];
            // Fixed-size 8-lane loops: written with iterator chains over the arrays the compiler
            // fell back to scalar code with spills.
            for (cj, &(first, len, ref weights)) in self.taps.iter().enumerate() {
                let mut acc = [0.0f32; BINS];
                for k in 0..len {
                    let (w, hist) = (weights[k], &samples[first + k]);
                    for b in 0..BINS {
                        acc[b] += w * hist[b];
                    }
                }
                out[cj] = acc;
            }
        }
    }

    /// The descriptor of the candidate shifted by (`da`, `db`) ∈ [−r, r]² pixels along the normal
    /// and the tangent.
    pub fn descriptor(&mut self, da: isize, db: isize, out: &mut [f32; DESCRIPTOR_LEN]) {
        #[cfg(target_arch = "x86_64")]
        if crate::landmarks::simd::avx2() {
            // SAFETY: the CPU has AVX2 (checked at run time).
            return unsafe { self.descriptor_avx2(da, db, out) };
        }
        self.descriptor_body(da, db, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn descriptor_avx2(&mut self, da: isize, db: isize, out: &mut [f32; DESCRIPTOR_LEN]) {
        self.descriptor_body(da, db, out)
    }

    #[inline(always)]
    fn descriptor_body(&mut self, da: isize, db: isize, out: &mut [f32; DESCRIPTOR_LEN]) {
        let a0 = (da + self.radius as isize) as usize;
        let b0 = (db + self.radius as isize) as usize;
        debug_assert!(
            a0 >= self.filled[0] && a0 + PATCH <= self.filled[1] && b0 >= self.filled[2] && b0 + PATCH <= self.filled[3],
            "candidate not sampled: widen first"
        );
        // Row sums of this candidate column, for the rows not summed yet (the rows of the
        // candidates of one column overlap, so the missing ones are at either end).
        let (lo, hi) = self.column_rows[b0];
        let (need_lo, need_hi) = (a0, a0 + PATCH);
        if lo == hi || need_hi < lo || need_lo > hi {
            self.sum_columns(b0, need_lo..need_hi);
            self.column_rows[b0] = (need_lo, need_hi);
        } else {
            self.sum_columns(b0, need_lo.min(lo)..lo);
            self.sum_columns(b0, hi..need_hi.max(hi));
            self.column_rows[b0] = (need_lo.min(lo), need_hi.max(hi));
        }
        let column = &self.columns[b0 * self.side..(b0 + 1) * self.side];
        for (ci, &(first, len, ref weights)) in self.taps.iter().enumerate() {
            let mut acc = [[0.0f32; BINS]; CELLS];
            for k in 0..len {
                let (w, sums) = (weights[k], &column[a0 + first + k]);
                for cj in 0..CELLS {
                    for b in 0..BINS {
                        acc[cj][b] += w * sums[cj][b];
                    }
                }
            }
            for (cj, cell) in acc.iter().enumerate() {
                out[(ci * CELLS + cj) * BINS..(ci * CELLS + cj + 1) * BINS].copy_from_slice(cell);
            }
        }
        normalize(out);
    }
}

/// The bilinear gathers and the projections on the normal and the tangent of the first
/// `width − width mod 8` samples of a window row, eight at a time with AVX2 gathers; the same
/// operations in the same order as the scalar loop (no FMA), hence the same values. Returns how
/// many samples it did.
///
/// # Safety
/// The CPU must have AVX2, and every sample position of the row must lie in
/// `[0, width − 1) × [0, height − 1)` of `grad`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn gather_row_avx2(
    grad: &Gradients,
    row: Point,
    b_start: usize,
    width: usize,
    off: f32,
    normal: Point,
    gn: &mut [f32],
    gt: &mut [f32],
) -> usize {
    use std::arch::x86_64::*;
    let (nx, ny) = (normal[0], normal[1]);
    let (tx, ty) = (-ny, nx);
    let w = grad.width as i32;
    let base = grad.gxy.as_ptr() as *const f32;
    let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let one = _mm256_set1_ps(1.0);
    let (row_x, row_y, off_v) = (_mm256_set1_ps(row[0]), _mm256_set1_ps(row[1]), _mm256_set1_ps(off));
    let (nx_v, ny_v, tx_v, ty_v) = (_mm256_set1_ps(nx), _mm256_set1_ps(ny), _mm256_set1_ps(tx), _mm256_set1_ps(ty));
    let mut k = 0;
    while k + 8 <= width {
        let b = _mm256_add_epi32(_mm256_set1_epi32((b_start + k) as i32), lanes);
        let db = _mm256_sub_ps(_mm256_cvtepi32_ps(b), off_v);
        let x = _mm256_add_ps(row_x, _mm256_mul_ps(db, tx_v));
        let y = _mm256_add_ps(row_y, _mm256_mul_ps(db, ty_v));
        // Non-negative: truncation is floor.
        let (xi, yi) = (_mm256_cvttps_epi32(x), _mm256_cvttps_epi32(y));
        let (fx, fy) = (_mm256_sub_ps(x, _mm256_cvtepi32_ps(xi)), _mm256_sub_ps(y, _mm256_cvtepi32_ps(yi)));
        // Index of the top-left gradient's x component (two floats per pixel).
        let i00 = _mm256_slli_epi32::<1>(_mm256_add_epi32(_mm256_mullo_epi32(yi, _mm256_set1_epi32(w)), xi));
        // SAFETY: in bounds by the caller's guarantee (x0 + 1 < width, y0 + 1 < height).
        let g = |o: i32| unsafe { _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(i00, _mm256_set1_epi32(o))) };
        let (ux, uy) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy));
        let (w00, w01, w10, w11) = (_mm256_mul_ps(ux, uy), _mm256_mul_ps(fx, uy), _mm256_mul_ps(ux, fy), _mm256_mul_ps(fx, fy));
        let bilinear = |c: i32| {
            let s = _mm256_add_ps(_mm256_mul_ps(w00, g(c)), _mm256_mul_ps(w01, g(2 + c)));
            let s = _mm256_add_ps(s, _mm256_mul_ps(w10, g(2 * w + c)));
            _mm256_add_ps(s, _mm256_mul_ps(w11, g(2 * w + 2 + c)))
        };
        let (gx, gy) = (bilinear(0), bilinear(1));
        let along_n = _mm256_add_ps(_mm256_mul_ps(gx, nx_v), _mm256_mul_ps(gy, ny_v));
        let along_t = _mm256_add_ps(_mm256_mul_ps(gx, tx_v), _mm256_mul_ps(gy, ty_v));
        // SAFETY: k + 8 ≤ width ≤ the buffers' length.
        unsafe {
            _mm256_storeu_ps(gn.as_mut_ptr().add(k), along_n);
            _mm256_storeu_ps(gt.as_mut_ptr().add(k), along_t);
        }
        k += 8;
    }
    k
}

/// Unit length, clip at 0.2, unit length again (a flat patch stays all zeros).
#[inline(always)]
fn normalize(v: &mut [f32; DESCRIPTOR_LEN]) {
    let norm = sum_of_squares(v).sqrt();
    if norm <= 1e-12 {
        return;
    }
    v.iter_mut().for_each(|x| *x = (*x / norm).min(CLIP));
    let norm = sum_of_squares(v).sqrt();
    v.iter_mut().for_each(|x| *x /= norm);
}

/// Σ x² in 8 independent lanes (a sequential f32 sum cannot be vectorised and was a tenth of
/// the search time).
#[inline(always)]
fn sum_of_squares(v: &[f32; DESCRIPTOR_LEN]) -> f32 {
    let mut acc = [0.0f32; 8];
    for chunk in v.chunks_exact(8) {
        for (a, x) in acc.iter_mut().zip(chunk) {
            *a += x * x;
        }
    }
    acc.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::landmarks::sift::descriptor;
    use facegate_core::imaging::GrayF32;

    /// A textured test image: a few blobs and edges, smooth enough for bilinear sampling.
    fn pattern(w: usize, h: usize, angle: f32, cx: f32, cy: f32) -> GrayF32 {
        let (c, s) = (angle.cos(), angle.sin());
        GrayF32::from_fn(w, h, |x, y| {
            // Rotate the sampling point back by `angle` about (cx, cy): the pattern turns by `angle`.
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
            let blob = |bx: f32, by: f32, r: f32| (-((u - bx).powi(2) + (v - by).powi(2)) / (2.0 * r * r)).exp();
            100.0 + 80.0 * blob(3.0, -2.0, 3.0) - 60.0 * blob(-4.0, 4.0, 2.5) + 40.0 * ((u + 0.3 * v) / 3.0).sin() * blob(0.0, 0.0, 8.0)
        })
    }

    fn dist(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f32>().sqrt()
    }

    #[test]
    fn descriptor_turns_with_the_normal() {
        let (cx, cy) = (40.0, 40.0);
        let base = Gradients::new(&pattern(80, 80, 0.0, cx, cy));
        let d0 = descriptor(&base, [cx, cy], [1.0, 0.0]);
        assert!((d0.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-4);
        for angle in [0.5f32, 1.3, 2.6] {
            let turned = Gradients::new(&pattern(80, 80, angle, cx, cy));
            let same = descriptor(&turned, [cx, cy], [angle.cos(), angle.sin()]);
            let fixed = descriptor(&turned, [cx, cy], [1.0, 0.0]);
            let (d_same, d_fixed) = (dist(&d0, &same), dist(&d0, &fixed));
            assert!(d_same < 0.12, "angle {angle}: turned with the normal, distance {d_same}");
            assert!(d_fixed > 2.0 * d_same, "angle {angle}: a fixed normal should not match ({d_fixed} vs {d_same})");
        }
    }

    #[test]
    fn descriptor_ignores_affine_contrast_changes() {
        let img = pattern(60, 60, 0.3, 30.0, 30.0);
        let d0 = descriptor(&Gradients::new(&img), [30.0, 30.0], [0.6, 0.8]);
        let mut changed = img.clone();
        changed.data.iter_mut().for_each(|v| *v = 0.4 * *v + 37.0);
        let d1 = descriptor(&Gradients::new(&changed), [30.0, 30.0], [0.6, 0.8]);
        assert!(dist(&d0, &d1) < 1e-4);
        // …but not a different place.
        let d2 = descriptor(&Gradients::new(&img), [24.0, 33.0], [0.6, 0.8]);
        assert!(dist(&d0, &d2) > 0.2);
    }

    #[test]
    fn widened_windows_equal_full_windows() {
        let g = Gradients::new(&pattern(70, 70, 0.4, 35.0, 35.0));
        let n = [0.6f32, 0.8];
        let mut full = DescriptorGrid::new();
        full.fill(&g, [34.3, 36.1], n, 3);
        let mut lazy = DescriptorGrid::new();
        lazy.fill_within(&g, [34.3, 36.1], n, 3, 2);
        let (mut a, mut b) = ([0.0; DESCRIPTOR_LEN], [0.0; DESCRIPTOR_LEN]);
        for (da, db) in [(0, 0), (2, -2), (3, -2), (3, -3), (-3, 1), (-1, 3), (0, 0)] {
            lazy.widen(&g, da, db);
            full.descriptor(da, db, &mut a);
            lazy.descriptor(da, db, &mut b);
            assert_eq!(a, b, "candidate ({da}, {db})");
        }
    }

    /// The descriptor binned the direct way, every sample into its (up to) four cells with the
    /// bilinear weight times the 2D Gaussian: the two-pass binning must give the same values.
    fn direct_descriptor(grid: &DescriptorGrid, da: isize, db: isize) -> [f32; DESCRIPTOR_LEN] {
        let (a0, b0) = ((da + grid.radius as isize) as usize, (db + grid.radius as isize) as usize);
        let sigma = 0.5 * PATCH as f32;
        let cell_weight = |i: usize, c: usize| (1.0 - ((i as f32 + 0.5) / CELL_PIXELS as f32 - 0.5 - c as f32).abs()).max(0.0);
        let mut out = [0.0f32; DESCRIPTOR_LEN];
        for i in 0..PATCH {
            for j in 0..PATCH {
                let (u, v) = (i as f32 + 0.5 - 0.5 * PATCH as f32, j as f32 + 0.5 - 0.5 * PATCH as f32);
                let gauss = (-(u * u + v * v) / (2.0 * sigma * sigma)).exp();
                let hist = &grid.samples[(a0 + i) * grid.side + b0 + j];
                for ci in 0..CELLS {
                    for cj in 0..CELLS {
                        let w = cell_weight(i, ci) * cell_weight(j, cj) * gauss;
                        for (k, h) in hist.iter().enumerate() {
                            out[(ci * CELLS + cj) * BINS + k] += w * h;
                        }
                    }
                }
            }
        }
        normalize(&mut out);
        out
    }

    #[test]
    fn two_pass_binning_equals_direct_binning() {
        let g = Gradients::new(&pattern(70, 70, 0.7, 35.0, 35.0));
        let mut grid = DescriptorGrid::new();
        // Near the border too (clamped samples), and in an order that extends cached columns
        // upwards and downwards.
        for (centre, n) in [([35.2f32, 34.6f32], [0.6f32, -0.8f32]), ([6.0, 60.0], [-1.0, 0.0])] {
            grid.fill(&g, centre, n, 3);
            let mut out = [0.0; DESCRIPTOR_LEN];
            for (da, db) in [(0, 0), (-2, 0), (2, 0), (3, 1), (-3, -3), (1, 0), (-1, 2)] {
                grid.descriptor(da, db, &mut out);
                let reference = direct_descriptor(&grid, da, db);
                assert!(dist(&out, &reference) < 1e-5, "candidate ({da}, {db}): {}", dist(&out, &reference));
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_baseline_loops_agree_exactly() {
        if !crate::landmarks::simd::avx2() {
            return;
        }
        let g = Gradients::new(&pattern(70, 70, 0.3, 35.0, 35.0));
        let mut grid = DescriptorGrid::new();
        let (centre, n) = ([33.7f32, 36.2f32], [0.8f32, 0.6f32]);
        grid.fill(&g, centre, n, 2); // the AVX2 sampling
        let avx2_samples = grid.samples.clone();
        let side = grid.side;
        grid.sample_rect_body(&g, 0..side, 0..side); // the baseline sampling, inlined here
        assert!(avx2_samples == grid.samples);
        let (mut base, mut wide) = ([0.0; DESCRIPTOR_LEN], [0.0; DESCRIPTOR_LEN]);
        grid.descriptor_body(1, -2, &mut base);
        grid.fill(&g, centre, n, 2); // empty the cached column sums
        // SAFETY: AVX2 checked above.
        unsafe { grid.descriptor_avx2(1, -2, &mut wide) };
        assert_eq!(base, wide);
    }

    #[test]
    fn window_descriptors_match_single_descriptors() {
        let g = Gradients::new(&pattern(70, 70, 0.2, 35.0, 35.0));
        let n = [0.8f32, -0.6];
        let mut grid = DescriptorGrid::new();
        grid.fill(&g, [35.0, 35.0], n, 3);
        let mut out = [0.0; DESCRIPTOR_LEN];
        grid.descriptor(2, -1, &mut out);
        let t = [-n[1], n[0]];
        let p = [35.0 + 2.0 * n[0] - 1.0 * t[0], 35.0 + 2.0 * n[1] - 1.0 * t[1]];
        assert!(dist(&out, &descriptor(&g, p, n)) < 1e-4);
    }
}
