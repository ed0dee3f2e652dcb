//! Feature vectors of a normalised crop, the input of DLDA: the thesis's normalised pixels, or
//! uniform LBP histograms on a grid of cells (Ahonen et al. 2006).

use serde::{Deserialize, Serialize};

use facegate_core::imaging::GrayF32;
use facegate_core::vector::unit;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FeatureKind {
    /// The masked pixels, standardised to zero mean and unit variance.
    Pixels,
    /// Uniform LBP(8,1) histograms (59 bins) on a `grid`×`grid` layout of cells, square-rooted.
    Lbp { grid: usize },
    /// Both, each part scaled to unit length, concatenated (pixels first).
    PixelsLbp { grid: usize },
    /// Pixels, LBP(8,1) and LBP(8,2) histograms (radius-2 neighbours sampled bilinearly), each part
    /// scaled to unit length, concatenated.
    PixelsLbpMulti { grid: usize },
    /// [`FeatureKind::PixelsLbpMulti`] and Gabor magnitudes ([`gabor_magnitudes`]), each part
    /// scaled to unit length, concatenated.
    PixelsLbpGabor { grid: usize },
}

impl FeatureKind {
    pub fn dims(&self, width: usize, height: usize, mask: &[bool]) -> usize {
        match *self {
            FeatureKind::Pixels => mask.iter().filter(|&&m| m).count(),
            FeatureKind::Lbp { grid } => {
                let _ = (width, height);
                grid * grid * LBP_BINS
            }
            FeatureKind::PixelsLbp { grid } => {
                FeatureKind::Pixels.dims(width, height, mask) + FeatureKind::Lbp { grid }.dims(width, height, mask)
            }
            FeatureKind::PixelsLbpMulti { grid } => {
                FeatureKind::Pixels.dims(width, height, mask) + 2 * FeatureKind::Lbp { grid }.dims(width, height, mask)
            }
            FeatureKind::PixelsLbpGabor { grid } => {
                FeatureKind::PixelsLbpMulti { grid }.dims(width, height, mask) + GABOR_FILTERS * gabor_positions(width, height).len()
            }
        }
    }

    /// Features of `crop` (already photometrically normalised) into `out`.
    pub fn extract(&self, crop: &GrayF32, mask: &[bool]) -> Vec<f32> {
        match *self {
            FeatureKind::Pixels => pixels(crop, mask),
            FeatureKind::Lbp { grid } => lbp_histograms(crop, grid),
            FeatureKind::PixelsLbp { grid } => {
                let mut out = unit(pixels(crop, mask));
                out.extend(unit(lbp_histograms(crop, grid)));
                out
            }
            FeatureKind::PixelsLbpMulti { grid } => {
                let mut out = unit(pixels(crop, mask));
                out.extend(unit(lbp_histograms(crop, grid)));
                out.extend(unit(lbp2_histograms(crop, grid)));
                out
            }
            FeatureKind::PixelsLbpGabor { grid } => {
                let mut out = FeatureKind::PixelsLbpMulti { grid }.extract(crop, mask);
                out.extend(unit(gabor_magnitudes(crop)));
                out
            }
        }
    }
}

/// A rectangle of the normalised crop, in fractions of its width and height (`x0 ≤ x < x1`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Region {
    pub x0: f32,
    pub y0: f32,
    pub x1: f32,
    pub y1: f32,
}

impl Region {
    pub fn contains(&self, fx: f32, fy: f32) -> bool {
        (self.x0..self.x1).contains(&fx) && (self.y0..self.y1).contains(&fy)
    }

    /// Inside the unit square and not empty.
    pub fn is_valid(&self) -> bool {
        (0.0..1.0).contains(&self.x0)
            && (0.0..1.0).contains(&self.y0)
            && self.x1 > self.x0
            && self.y1 > self.y0
            && self.x1 <= 1.0
            && self.y1 <= 1.0
    }
}

impl FeatureKind {
    /// Indices into [`FeatureKind::extract`]'s vector of the features that describe `region`: the
    /// masked pixels whose centre lies in it, and the LBP cells whose centre does (all their bins).
    /// A local projection reads these entries of the whole crop's features, so that the features
    /// are computed once per crop whatever the number of regions.
    pub fn indices_in(&self, width: usize, height: usize, mask: &[bool], region: &Region) -> Vec<usize> {
        let pixel_indices = || -> Vec<usize> {
            let masked = (0..width * height).filter(|&i| mask[i]);
            masked
                .enumerate()
                .filter(|&(_, i)| region.contains(((i % width) as f32 + 0.5) / width as f32, ((i / width) as f32 + 0.5) / height as f32))
                .map(|(k, _)| k)
                .collect()
        };
        let cell_indices = |grid: usize, offset: usize| -> Vec<usize> {
            let grid = grid.max(1);
            let mut out = Vec::new();
            for cell in 0..grid * grid {
                let (cx, cy) = (cell % grid, cell / grid);
                if region.contains((cx as f32 + 0.5) / grid as f32, (cy as f32 + 0.5) / grid as f32) {
                    out.extend(offset + cell * LBP_BINS..offset + (cell + 1) * LBP_BINS);
                }
            }
            out
        };
        let pixels = FeatureKind::Pixels.dims(width, height, mask);
        match *self {
            FeatureKind::Pixels => pixel_indices(),
            FeatureKind::Lbp { grid } => cell_indices(grid, 0),
            FeatureKind::PixelsLbp { grid } => {
                let mut out = pixel_indices();
                out.extend(cell_indices(grid, pixels));
                out
            }
            FeatureKind::PixelsLbpMulti { grid } => {
                let mut out = pixel_indices();
                out.extend(cell_indices(grid, pixels));
                out.extend(cell_indices(grid, pixels + grid.max(1) * grid.max(1) * LBP_BINS));
                out
            }
            FeatureKind::PixelsLbpGabor { grid } => {
                let mut out = FeatureKind::PixelsLbpMulti { grid }.indices_in(width, height, mask, region);
                let offset = FeatureKind::PixelsLbpMulti { grid }.dims(width, height, mask);
                let positions = gabor_positions(width, height);
                for filter in 0..GABOR_FILTERS {
                    let first = offset + filter * positions.len();
                    out.extend(positions.iter().enumerate().filter(|(_, (fx, fy))| region.contains(*fx, *fy)).map(|(p, _)| first + p));
                }
                out
            }
        }
    }
}

/// The entries `indices` of `features` (a region's features, see [`FeatureKind::indices_in`]).
pub fn gather(features: &[f32], indices: &[usize]) -> Vec<f32> {
    indices.iter().map(|&i| features[i]).collect()
}

fn pixels(crop: &GrayF32, mask: &[bool]) -> Vec<f32> {
    let mut out: Vec<f32> = crop.data.iter().zip(mask).filter(|(_, m)| **m).map(|(v, _)| *v).collect();
    let n = out.len().max(1) as f32;
    let mean = out.iter().sum::<f32>() / n;
    let var = out.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n;
    let inv = if var > 1e-12 { 1.0 / var.sqrt() } else { 0.0 };
    out.iter_mut().for_each(|v| *v = (*v - mean) * inv);
    out
}

const LBP_BINS: usize = 59;

/// Map from the 256 LBP codes to 59 bins: one per uniform pattern (at most two 0/1 transitions
/// around the circle), and one shared bin for the rest.
fn uniform_table() -> [u8; 256] {
    let mut table = [0u8; 256];
    let mut next = 0u8;
    for (code, slot) in table.iter_mut().enumerate() {
        let c = code as u8;
        let transitions = (c ^ c.rotate_left(1)).count_ones();
        if transitions <= 2 {
            *slot = next;
            next += 1;
        } else {
            *slot = (LBP_BINS - 1) as u8;
        }
    }
    table
}

/// Uniform LBP(8,1): the eight pixel neighbours.
fn lbp_histograms(crop: &GrayF32, grid: usize) -> Vec<f32> {
    const OFFSETS: [(isize, isize); 8] = [(-1, -1), (0, -1), (1, -1), (1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0)];
    let w = crop.width;
    lbp_cell_histograms(crop, grid, 1, |x, y, centre| {
        let mut code = 0u8;
        for (bit, (dx, dy)) in OFFSETS.iter().enumerate() {
            if crop.data[(y as isize + dy) as usize * w + (x as isize + dx) as usize] >= centre {
                code |= 1 << bit;
            }
        }
        code
    })
}

/// Uniform LBP(8,2): eight neighbours on a circle of radius 2, sampled bilinearly.
fn lbp2_histograms(crop: &GrayF32, grid: usize) -> Vec<f32> {
    let d = std::f32::consts::FRAC_1_SQRT_2 * 2.0;
    let offsets: [(f32, f32); 8] = [(-d, -d), (0.0, -2.0), (d, -d), (2.0, 0.0), (d, d), (0.0, 2.0), (-d, d), (-2.0, 0.0)];
    // The bilinear weights are the same at every pixel: per neighbour, the integer corner of its
    // 2×2 cell and the fractions (the axis neighbours fall on pixels and are read directly).
    let w = crop.width as isize;
    let taps: [(isize, f32, f32); 8] = offsets.map(|(dx, dy)| {
        let (fx, fy) = (dx - dx.floor(), dy - dy.floor());
        (dy.floor() as isize * w + dx.floor() as isize, fx, fy)
    });
    let data = &crop.data;
    lbp_cell_histograms(crop, grid, 2, |x, y, centre| {
        let at = (y * crop.width + x) as isize;
        let mut code = 0u8;
        for (bit, &(offset, fx, fy)) in taps.iter().enumerate() {
            let i = (at + offset) as usize;
            let value = if fx == 0.0 && fy == 0.0 {
                data[i]
            } else {
                // Inside the image: pixels at least 2 from the border, corners at most 1 + 1 away.
                let j = i + crop.width;
                let top = data[i] + fx * (data[i + 1] - data[i]);
                let bottom = data[j] + fx * (data[j + 1] - data[j]);
                top + fy * (bottom - top)
            };
            if value >= centre {
                code |= 1 << bit;
            }
        }
        code
    })
}

/// Histograms of uniform LBP codes on a `grid × grid` partition of `crop`, over the pixels at
/// least `radius` from the border; `code` gives the 8-bit pattern at (x, y) with its centre value.
/// Each cell's histogram is normalised to unit sum, then square-rooted (Hellinger kernel).
fn lbp_cell_histograms(crop: &GrayF32, grid: usize, radius: usize, code: impl Fn(usize, usize, f32) -> u8) -> Vec<f32> {
    let table = uniform_table();
    let (w, h) = (crop.width, crop.height);
    let grid = grid.max(1);
    let mut hist = vec![0.0f32; grid * grid * LBP_BINS];
    for y in radius..h.saturating_sub(radius) {
        let cy = (y * grid / h).min(grid - 1);
        for x in radius..w.saturating_sub(radius) {
            let cx = (x * grid / w).min(grid - 1);
            let c = code(x, y, crop.data[y * w + x]);
            hist[(cy * grid + cx) * LBP_BINS + table[c as usize] as usize] += 1.0;
        }
    }
    for cell in hist.chunks_mut(LBP_BINS) {
        let s: f32 = cell.iter().sum();
        if s > 0.0 {
            cell.iter_mut().for_each(|v| *v = (*v / s).sqrt());
        }
    }
    hist
}

/// Wavelengths (pixels of the half-size crop) and orientations of the Gabor bank.
const GABOR_WAVELENGTHS: [f32; 3] = [3.0, 4.5, 6.75];
const GABOR_ORIENTATIONS: usize = 8;
const GABOR_FILTERS: usize = GABOR_WAVELENGTHS.len() * GABOR_ORIENTATIONS;

/// One complex Gabor kernel: its radius and its (real, imaginary) taps, row-major over
/// `(2 radius + 1)²`, the real part made zero-mean so that a flat patch gives no response.
struct GaborKernel {
    radius: usize,
    taps: Vec<(f32, f32)>,
}

/// The bank, built once: envelope σ = 0.56 λ (one octave of bandwidth), cut at 2σ.
fn gabor_bank() -> &'static [GaborKernel] {
    static BANK: std::sync::OnceLock<Vec<GaborKernel>> = std::sync::OnceLock::new();
    BANK.get_or_init(|| {
        let mut bank = Vec::with_capacity(GABOR_FILTERS);
        for &lambda in &GABOR_WAVELENGTHS {
            let sigma = 0.56 * lambda;
            let radius = (2.0 * sigma).ceil() as usize;
            for o in 0..GABOR_ORIENTATIONS {
                let theta = std::f32::consts::PI * o as f32 / GABOR_ORIENTATIONS as f32;
                let (sin, cos) = theta.sin_cos();
                let r = radius as f32;
                let side = 2 * radius + 1;
                let mut envelopes = Vec::with_capacity(side * side);
                let mut taps: Vec<(f32, f32)> = Vec::with_capacity(side * side);
                for dy in 0..side {
                    for dx in 0..side {
                        let (x, y) = (dx as f32 - r, dy as f32 - r);
                        let envelope = (-(x * x + y * y) / (2.0 * sigma * sigma)).exp();
                        let phase = std::f32::consts::TAU * (x * cos + y * sin) / lambda;
                        envelopes.push(envelope);
                        taps.push((envelope * phase.cos(), envelope * phase.sin()));
                    }
                }
                // The real part's sum removed in proportion to the envelope (the imaginary part is
                // odd, its sum is zero already).
                let dc = taps.iter().map(|t| t.0).sum::<f32>() / envelopes.iter().sum::<f32>();
                for (t, e) in taps.iter_mut().zip(&envelopes) {
                    t.0 -= dc * e;
                }
                bank.push(GaborKernel { radius, taps });
            }
        }
        bank
    })
}

/// Where the Gabor magnitudes are taken on the half-size crop (`half_width` × `half_height`): every
/// other pixel (a 4-pixel step on the crop), starting at the second, row by row.
fn gabor_grid(half_width: usize, half_height: usize) -> impl Iterator<Item = (usize, usize)> {
    (1..half_height).step_by(2).flat_map(move |y| (1..half_width).step_by(2).map(move |x| (x, y)))
}

/// The [`gabor_grid`] of a `width` × `height` crop as fractions of the crop.
fn gabor_positions(width: usize, height: usize) -> Vec<(f32, f32)> {
    let (hw, hh) = ((width / 2).max(1), (height / 2).max(1));
    gabor_grid(hw, hh).map(|(x, y)| ((2 * x + 1) as f32 / width as f32, (2 * y + 1) as f32 / height as f32)).collect()
}

/// Gabor magnitude features (Liu & Wechsler 2002, reduced): the crop halved, convolved with the
/// bank at [`gabor_positions`], the square root of each complex response's magnitude (as with the
/// LBP histograms, a variance-stabilising root), filter by filter.
fn gabor_magnitudes(crop: &GrayF32) -> Vec<f32> {
    let half = crop.downsample_half();
    let bank = gabor_bank();
    let pad = bank.iter().map(|k| k.radius).max().unwrap_or(0);
    // The half-size crop with its border replicated `pad` pixels out, so the taps need no bounds checks.
    let (pw, ph) = (half.width + 2 * pad, half.height + 2 * pad);
    let padded: Vec<f32> = (0..pw * ph)
        .map(|i| {
            let (x, y) = ((i % pw) as isize - pad as isize, (i / pw) as isize - pad as isize);
            half.get(x.clamp(0, half.width as isize - 1) as usize, y.clamp(0, half.height as isize - 1) as usize)
        })
        .collect();
    let positions: Vec<(usize, usize)> = gabor_grid(half.width, half.height).map(|(x, y)| (x + pad, y + pad)).collect();
    let mut out = Vec::with_capacity(bank.len() * positions.len());
    for kernel in bank {
        let side = 2 * kernel.radius + 1;
        for &(cx, cy) in &positions {
            let (mut re, mut im) = (0.0f32, 0.0f32);
            for (row, taps) in kernel.taps.chunks_exact(side).enumerate() {
                let start = (cy + row - kernel.radius) * pw + cx - kernel.radius;
                for (&(kr, ki), &v) in taps.iter().zip(&padded[start..start + side]) {
                    re += kr * v;
                    im += ki * v;
                }
            }
            out.push((re * re + im * im).sqrt().sqrt());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixed-weight LBP(8,2) agrees with sampling every neighbour through `GrayF32::sample`.
    #[test]
    fn lbp2_matches_bilinear_sampling() {
        let crop = GrayF32::from_fn(24, 20, |x, y| ((x * 13 + y * 7 + x * y) % 17) as f32 + 0.25 * x as f32);
        let d = std::f32::consts::FRAC_1_SQRT_2 * 2.0;
        let offsets: [(f32, f32); 8] = [(-d, -d), (0.0, -2.0), (d, -d), (2.0, 0.0), (d, d), (0.0, 2.0), (-d, d), (-2.0, 0.0)];
        let reference = lbp_cell_histograms(&crop, 2, 2, |x, y, centre| {
            let mut code = 0u8;
            for (bit, (dx, dy)) in offsets.iter().enumerate() {
                if crop.sample(x as f32 + dx, y as f32 + dy) >= centre - 1e-4 {
                    code |= 1 << bit;
                }
            }
            code
        });
        let fast = lbp2_histograms(&crop, 2);
        assert!(reference.iter().zip(&fast).all(|(a, b)| (a - b).abs() < 1e-6), "{reference:?}\n{fast:?}");
    }

    /// A region's indices pick exactly its pixels and its LBP cells, in the extracted vector's order.
    #[test]
    fn region_indices_select_the_region_features() {
        let (w, h) = (16, 16);
        let mask: Vec<bool> = (0..w * h).map(|i| i % 5 != 0).collect();
        let crop = GrayF32::from_fn(w, h, |x, y| ((x * 7 + y * 3) % 11) as f32 + 0.1 * y as f32);
        let kind = FeatureKind::PixelsLbpMulti { grid: 4 };
        let features = kind.extract(&crop, &mask);
        // The upper-left quarter: 64 pixels less the masked-out ones, 4 of the 16 cells per LBP part.
        let region = Region { x0: 0.0, y0: 0.0, x1: 0.5, y1: 0.5 };
        let idx = kind.indices_in(w, h, &mask, &region);
        let pixels_in = (0..w * h).filter(|&i| mask[i] && i % w < 8 && i / w < 8).count();
        assert_eq!(idx.len(), pixels_in + 2 * 4 * LBP_BINS);
        assert!(idx.windows(2).all(|p| p[0] < p[1]) && *idx.last().unwrap() < features.len());
        // The pixel part: the standardised values of exactly those pixels.
        let all_pixels = pixels(&crop, &mask);
        let unit_scale = features[0] / all_pixels[0];
        let first_row: Vec<f32> =
            (0..8).filter(|&x| mask[x]).map(|x| all_pixels[(0..x).filter(|&i| mask[i]).count()] * unit_scale).collect();
        let picked = gather(&features, &idx[..first_row.len()]);
        assert!(picked.iter().zip(&first_row).all(|(a, b)| (a - b).abs() < 1e-6), "{picked:?} {first_row:?}");
        // The LBP(8,1) part starts with cell (0, 0); cell (1, 0) follows, then (0, 1) (row-major).
        let p = FeatureKind::Pixels.dims(w, h, &mask);
        let lbp1 = &idx[pixels_in..pixels_in + 4 * LBP_BINS];
        assert_eq!((lbp1[0], lbp1[LBP_BINS], lbp1[2 * LBP_BINS]), (p, p + LBP_BINS, p + 4 * LBP_BINS));
        assert!(Region { x0: 0.2, y0: 0.1, x1: 0.9, y1: 1.0 }.is_valid() && !Region { x0: 0.5, y0: 0.1, x1: 0.4, y1: 1.0 }.is_valid());
    }

    /// The Gabor kernels ignore flat patches; a grating responds most to the filter of its
    /// orientation and wavelength; the layout matches `dims` and `indices_in`.
    #[test]
    fn gabor_bank_is_zero_mean_and_tuned() {
        for k in gabor_bank() {
            let (re, im) = k.taps.iter().fold((0.0f32, 0.0f32), |a, t| (a.0 + t.0, a.1 + t.1));
            assert!(re.abs() < 1e-4 && im.abs() < 1e-4, "kernel sums {re} {im}");
        }
        let flat = GrayF32::from_fn(48, 48, |_, _| 100.0);
        assert!(gabor_magnitudes(&flat).iter().all(|v| v * v < 1e-2), "a flat patch responds (magnitudes below 0.01 of 100)");
        // Vertical stripes of period 9 crop pixels (4.5 on the half-size crop): orientation 0
        // (varying along x), wavelength 4.5.
        let stripes = GrayF32::from_fn(48, 48, |x, _| 100.0 + 50.0 * (std::f32::consts::TAU * x as f32 / 9.0).cos());
        let m = gabor_magnitudes(&stripes);
        let per_filter = gabor_positions(48, 48).len();
        let energy: Vec<f32> = m.chunks(per_filter).map(|c| c.iter().sum()).collect();
        let best = (0..energy.len()).max_by(|&a, &b| energy[a].total_cmp(&energy[b])).unwrap();
        assert_eq!(best, GABOR_ORIENTATIONS, "filter energies {energy:?}");
        let kind = FeatureKind::PixelsLbpGabor { grid: 4 };
        let mask = vec![true; 48 * 48];
        assert_eq!(kind.extract(&stripes, &mask).len(), kind.dims(48, 48, &mask));
        let top = kind.indices_in(48, 48, &mask, &Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 });
        let multi = FeatureKind::PixelsLbpMulti { grid: 4 };
        let gabor_top = top.len() - multi.indices_in(48, 48, &mask, &Region { x0: 0.0, y0: 0.0, x1: 1.0, y1: 0.5 }).len();
        assert_eq!(gabor_top, GABOR_FILTERS * per_filter / 2);
    }

    #[test]
    fn uniform_lbp_table_has_58_uniform_patterns() {
        let t = uniform_table();
        let uniform = (0..256).filter(|&c| (t[c] as usize) < LBP_BINS - 1).count();
        assert_eq!(uniform, 58);
        let crop = GrayF32::from_fn(32, 32, |x, y| ((x * 7 + y * 3) % 11) as f32);
        let f = FeatureKind::Lbp { grid: 4 }.extract(&crop, &[true; 1024]);
        assert_eq!(f.len(), 16 * LBP_BINS);
        // Unit sum before the square root: the squares of each cell sum to one.
        let s: f32 = f[..LBP_BINS].iter().map(|v| v * v).sum();
        assert!((s - 1.0).abs() < 1e-4);
        // The concatenations: unit length per part, dims as declared.
        let mask = vec![true; 1024];
        for kind in [FeatureKind::PixelsLbp { grid: 4 }, FeatureKind::PixelsLbpMulti { grid: 4 }] {
            let f = kind.extract(&crop, &mask);
            assert_eq!(f.len(), kind.dims(32, 32, &mask));
            let pixel_norm: f32 = f[..1024].iter().map(|v| v * v).sum();
            assert!((pixel_norm - 1.0).abs() < 1e-3);
        }
    }
}
