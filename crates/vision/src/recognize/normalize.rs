//! Geometric and photometric normalisation of a face (thesis 2.6; Mayoue et al. 2009).
//!
//! Geometric: the least-squares similarity taking the eye and mouth centres to fixed positions in
//! a small crop (the canonical positions are left–right symmetric, so a mirrored crop is the crop
//! of the mirrored face). Photometric: Tan–Triggs (gamma, difference of Gaussians, two-stage
//! contrast equalisation) or histogram equalisation, inside an optional elliptical mask.

use serde::{Deserialize, Serialize};

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, Similarity};
use facegate_core::imaging::GrayF32;

/// Photometric normalisation of the geometric crop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Photometric {
    /// No change (pixels are still standardised to zero mean, unit variance as features).
    None,
    HistogramEqualization,
    /// Tan & Triggs (2010): gamma 0.2, DoG σ 1 and 2, contrast equalisation α 0.1, τ 10.
    TanTriggs,
}

/// Where the centres go and how the crop is treated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NormalizeParams {
    pub width: usize,
    pub height: usize,
    /// Canonical position of the eye on the image left.
    pub left_eye: Point,
    pub right_eye: Point,
    pub mouth: Point,
    /// Weight of the mouth in the similarity fit (the eyes weigh 1).
    pub mouth_weight: f32,
    pub photometric: Photometric,
    /// Keep only an ellipse inscribed in the crop (hair and background out).
    pub elliptical_mask: bool,
}

impl Default for NormalizeParams {
    /// The measured default (docs/recognition.md): [`NormalizeParams::layout64`] scaled to a
    /// 48×48 crop, histogram equalisation, elliptical mask.
    fn default() -> Self {
        NormalizeParams { photometric: Photometric::HistogramEqualization, ..NormalizeParams::layout64().scaled(48) }
    }
}

impl NormalizeParams {
    /// 64×64, inter-ocular distance 30 px, eye–mouth distance 31 px (the mean IMM frontal ratio,
    /// 1.05 inter-ocular distances), Tan–Triggs, elliptical mask.
    pub fn layout64() -> NormalizeParams {
        NormalizeParams {
            width: 64,
            height: 64,
            left_eye: [17.0, 22.0],
            right_eye: [47.0, 22.0],
            mouth: [32.0, 53.0],
            mouth_weight: 1.0,
            photometric: Photometric::TanTriggs,
            elliptical_mask: true,
        }
    }

    /// The same layout in a square crop of `side` pixels (the defaults are for 64).
    pub fn scaled(&self, side: usize) -> NormalizeParams {
        let f = side as f32 / self.width as f32;
        let s = |p: Point| [(p[0] + 0.5) * f - 0.5, (p[1] + 0.5) * f - 0.5];
        NormalizeParams {
            width: side,
            height: (self.height as f32 * f).round() as usize,
            left_eye: s(self.left_eye),
            right_eye: s(self.right_eye),
            mouth: s(self.mouth),
            ..self.clone()
        }
    }

    /// The centre layout scaled by `factor` about the crop centre (below 1: more of the head in
    /// the crop, at a lower resolution).
    pub fn zoomed(&self, factor: f32) -> NormalizeParams {
        let c = [0.5 * (self.width as f32 - 1.0), 0.5 * (self.height as f32 - 1.0)];
        let z = |p: Point| [c[0] + (p[0] - c[0]) * factor, c[1] + (p[1] - c[1]) * factor];
        NormalizeParams { left_eye: z(self.left_eye), right_eye: z(self.right_eye), mouth: z(self.mouth), ..self.clone() }
    }

    /// Mask of the crop pixels used as features (all of them without the elliptical mask).
    pub fn mask(&self) -> Vec<bool> {
        let (w, h) = (self.width as f32, self.height as f32);
        let (cx, cy) = (0.5 * (w - 1.0), 0.5 * (h - 1.0));
        let (rx, ry) = (0.5 * w, 0.5 * h + 0.04 * h);
        let mut out = Vec::with_capacity(self.width * self.height);
        for y in 0..self.height {
            for x in 0..self.width {
                let (dx, dy) = ((x as f32 - cx) / rx, (y as f32 - cy) / ry);
                out.push(!self.elliptical_mask || dx * dx + dy * dy <= 1.0);
            }
        }
        out
    }

    /// The similarity taking image coordinates to crop coordinates for these centres.
    pub fn alignment(&self, centres: &EyeMouthCentres) -> Similarity {
        let from = [centres.left_eye, centres.right_eye, centres.mouth];
        let to = [self.left_eye, self.right_eye, self.mouth];
        Similarity::fit(&from, &to, Some(&[1.0, 1.0, self.mouth_weight]))
    }
}

/// The geometric crop: `gray` resampled so that `centres` land on the canonical positions.
/// When the crop is much smaller than the face, the source is first halved (box filter) until the
/// remaining factor is at most 2, so that bilinear sampling does not alias.
pub fn geometric(gray: &GrayF32, centres: &EyeMouthCentres, params: &NormalizeParams) -> GrayF32 {
    let to_crop = params.alignment(centres);
    let mut to_image = to_crop.inverse();
    let mut level: Option<GrayF32> = None;
    // Image pixels per crop pixel.
    let mut step = to_image.scale();
    if step.is_finite() && step > 2.0 {
        // Only the crop's footprint (plus a margin for the filters) needs downsampling.
        let corners =
            [[-1.0, -1.0], [params.width as f32, -1.0], [-1.0, params.height as f32], [params.width as f32, params.height as f32]]
                .map(|c| to_image.apply(c));
        let margin = 2.0 * step + 2.0;
        let lo = |i: usize, limit: usize| {
            (corners.iter().map(|c| c[i]).fold(f32::MAX, f32::min) - margin).floor().clamp(0.0, limit as f32) as usize
        };
        let hi = |i: usize, limit: usize| {
            (corners.iter().map(|c| c[i]).fold(f32::MIN, f32::max) + margin).ceil().clamp(0.0, limit as f32) as usize
        };
        let (x0, x1, y0, y1) = (lo(0, gray.width), hi(0, gray.width), lo(1, gray.height), hi(1, gray.height));
        if x1 > x0 + 1 && y1 > y0 + 1 && (x1 - x0) * (y1 - y0) < gray.width * gray.height {
            let region = GrayF32::from_fn(x1 - x0, y1 - y0, |x, y| gray.get(x0 + x, y0 + y));
            to_image = Similarity { a: 1.0, b: 0.0, tx: -(x0 as f32), ty: -(y0 as f32) }.compose(&to_image);
            level = Some(region);
        }
    }
    loop {
        let source = level.as_ref().unwrap_or(gray);
        if !(step.is_finite() && step > 2.0 && source.width >= 4 && source.height >= 4) {
            break;
        }
        let next = source.downsample_half();
        // A pixel centre x at one level is at (x - 0.5) / 2 at the next.
        to_image = Similarity { a: 0.5, b: 0.0, tx: -0.25, ty: -0.25 }.compose(&to_image);
        step *= 0.5;
        level = Some(next);
    }
    let source = level.as_ref().unwrap_or(gray);
    let mut out = GrayF32::new(params.width, params.height);
    for y in 0..params.height {
        for x in 0..params.width {
            let p = to_image.apply([x as f32, y as f32]);
            out.data[y * params.width + x] = if p[0].is_finite() && p[1].is_finite() { source.sample(p[0], p[1]) } else { 0.0 };
        }
    }
    out
}

/// Apply the photometric normalisation in place. `mask` selects the pixels whose statistics count.
pub fn photometric(crop: &mut GrayF32, method: Photometric, mask: &[bool]) {
    match method {
        Photometric::None => {}
        Photometric::HistogramEqualization => histogram_equalize(crop, mask),
        Photometric::TanTriggs => tan_triggs(crop, mask),
    }
    // Outside the mask, a neutral value (the middle of the output range), so that features using
    // every pixel (LBP) see no background.
    let neutral = match method {
        Photometric::None => return,
        Photometric::HistogramEqualization => 127.5,
        Photometric::TanTriggs => 0.0,
    };
    for (v, &m) in crop.data.iter_mut().zip(mask) {
        if !m {
            *v = neutral;
        }
    }
}

/// Rank-based equalisation of the masked pixels to 0..=255.
fn histogram_equalize(crop: &mut GrayF32, mask: &[bool]) {
    let mut order: Vec<usize> = (0..crop.data.len()).filter(|&i| mask[i]).collect();
    if order.len() < 2 {
        return;
    }
    order.sort_by(|&a, &b| crop.data[a].total_cmp(&crop.data[b]));
    let n = order.len();
    let mut i = 0;
    // Ties share their mean rank so that flat regions stay flat.
    while i < n {
        let mut j = i;
        while j + 1 < n && crop.data[order[j + 1]] == crop.data[order[i]] {
            j += 1;
        }
        let rank = 0.5 * (i + j) as f32 / (n - 1) as f32 * 255.0;
        for &k in &order[i..=j] {
            crop.data[k] = rank;
        }
        i = j + 1;
    }
}

/// Tan & Triggs (2010) preprocessing with their default parameters.
fn tan_triggs(crop: &mut GrayF32, mask: &[bool]) {
    const GAMMA: f32 = 0.2;
    const SIGMA0: f32 = 1.0;
    const SIGMA1: f32 = 2.0;
    const ALPHA: f32 = 0.1;
    const TAU: f32 = 10.0;
    for v in crop.data.iter_mut() {
        *v = v.max(1.0).powf(GAMMA);
    }
    let fine = crop.gaussian_blur(SIGMA0);
    let coarse = crop.gaussian_blur(SIGMA1);
    for ((v, f), c) in crop.data.iter_mut().zip(&fine.data).zip(&coarse.data) {
        *v = f - c;
    }
    let masked = |crop: &GrayF32, f: &dyn Fn(f32) -> f32| {
        let (mut s, mut n) = (0.0f64, 0usize);
        for (v, &m) in crop.data.iter().zip(mask) {
            if m {
                s += f(*v) as f64;
                n += 1;
            }
        }
        if n == 0 { 0.0 } else { (s / n as f64) as f32 }
    };
    let norm1 = masked(crop, &|v| v.abs().powf(ALPHA)).powf(1.0 / ALPHA);
    if norm1 > 0.0 {
        crop.data.iter_mut().for_each(|v| *v /= norm1);
    }
    let norm2 = masked(crop, &|v| v.abs().min(TAU).powf(ALPHA)).powf(1.0 / ALPHA);
    if norm2 > 0.0 {
        crop.data.iter_mut().for_each(|v| *v /= norm2);
    }
    crop.data.iter_mut().for_each(|v| *v = TAU * (*v / TAU).tanh());
}

/// Geometric then photometric normalisation.
pub fn normalize(gray: &GrayF32, centres: &EyeMouthCentres, params: &NormalizeParams) -> GrayF32 {
    let mut crop = geometric(gray, centres, params);
    photometric(&mut crop, params.photometric, &params.mask());
    crop
}

/// The crop mirrored left–right: the crop of the mirrored photo, since the canonical positions are
/// symmetric.
pub fn mirror(crop: &GrayF32) -> GrayF32 {
    GrayF32::from_fn(crop.width, crop.height, |x, y| crop.get(crop.width - 1 - x, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dark image with two bright eye blobs and a mouth blob at known places.
    fn synthetic_face(centres: &EyeMouthCentres, w: usize, h: usize) -> GrayF32 {
        GrayF32::from_fn(w, h, |x, y| {
            let d = |p: Point| ((x as f32 - p[0]).powi(2) + (y as f32 - p[1]).powi(2)).sqrt();
            if d(centres.left_eye) < 6.0 || d(centres.right_eye) < 6.0 {
                250.0
            } else if d(centres.mouth) < 6.0 {
                120.0
            } else {
                20.0
            }
        })
    }

    fn brightest_near(crop: &GrayF32, p: Point, radius: isize) -> Point {
        let (mut best, mut at) = (f32::MIN, [0.0, 0.0]);
        let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                let (x, y) = (p[0] as isize + dx, p[1] as isize + dy);
                let v = crop.get_clamped(x, y);
                if v > best {
                    best = v;
                    at = [x as f32, y as f32];
                }
            }
        }
        // Centre of mass of the bright blob around the maximum.
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                let (x, y) = (at[0] as isize + dx, at[1] as isize + dy);
                let v = crop.get_clamped(x, y);
                if v > 0.5 * best {
                    sx += v * x as f32;
                    sy += v * y as f32;
                    sw += v;
                }
            }
        }
        [sx / sw, sy / sw]
    }

    #[test]
    fn normalization_puts_the_eyes_where_it_says() {
        let params = NormalizeParams { photometric: Photometric::None, elliptical_mask: false, ..NormalizeParams::layout64() };
        // A face 3.1 times the crop's size, rotated by 12°, somewhere in a 640×480 photo.
        let t = Similarity { a: 3.1 * 0.21f32.cos(), b: 3.1 * 0.21f32.sin(), tx: 250.0, ty: 90.0 };
        let centres =
            EyeMouthCentres { left_eye: t.apply(params.left_eye), right_eye: t.apply(params.right_eye), mouth: t.apply(params.mouth) };
        let photo = synthetic_face(&centres, 640, 480);
        let crop = geometric(&photo, &centres, &params);
        for (canonical, name) in [(params.left_eye, "left eye"), (params.right_eye, "right eye")] {
            let found = brightest_near(&crop, canonical, 4);
            let err = ((found[0] - canonical[0]).powi(2) + (found[1] - canonical[1]).powi(2)).sqrt();
            assert!(err < 0.75, "{name} at {found:?}, expected {canonical:?}");
        }
        // The mouth blob (grey, not white) sits at its canonical position too.
        let m = crop.get(params.mouth[0] as usize, params.mouth[1] as usize);
        assert!((m - 120.0).abs() < 15.0, "mouth value {m}");
        // And the alignment itself maps the centres exactly here (the face has canonical proportions).
        let a = params.alignment(&centres).apply(centres.right_eye);
        assert!((a[0] - params.right_eye[0]).abs() < 1e-3 && (a[1] - params.right_eye[1]).abs() < 1e-3);
    }

    #[test]
    fn photometric_normalizations_remove_global_illumination() {
        let params = NormalizeParams::layout64();
        let mask = params.mask();
        let base = GrayF32::from_fn(64, 64, |x, y| 60.0 + 40.0 * ((x as f32 * 0.4).sin() * (y as f32 * 0.3).cos()));
        for method in [Photometric::TanTriggs, Photometric::HistogramEqualization] {
            let mut a = base.clone();
            let mut b = GrayF32 { data: base.data.iter().map(|v| v * 2.5).collect(), ..base.clone() };
            photometric(&mut a, method, &mask);
            photometric(&mut b, method, &mask);
            let diff = a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            assert!(diff < 0.05 * a.data.iter().map(|v| v.abs()).fold(0.0f32, f32::max), "{method:?} differs by {diff}");
        }
    }
}
