//! What the liveness model looks at, in named blocks a model picks from: the face's texture in
//! grey and in colour (a print loses fine skin texture and shifts the colour gamut: Määttä et al.,
//! 2011; Boulkenafet et al., 2015), its high-frequency energy (a print is a blurred, re-sampled
//! copy: Tan et al., 2010), and the texture of a wider crop around it (the paper's edges, the hand
//! holding it). Every block is cut from the photo at the recognizer's eye and mouth centres, so it
//! covers the same part of every face whatever the photo's size.

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::Similarity;
use facegate_core::imaging::GrayF32;
use image::RgbImage;
use serde::{Deserialize, Serialize};

use super::lbp::{self, BINS, Plane};
use crate::embed::chip::chip_to_photo;

/// Side of the face crop (the deep chip's framing: the face with a quarter of padding).
pub const FACE_SIZE: usize = 64;
/// Side of the context crop.
pub const CONTEXT_SIZE: usize = 64;
/// How many face crops wide the context crop is.
pub const CONTEXT_SPAN: f32 = 3.0;

/// One block of liveness features.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Block {
    /// Grey (luma) uniform LBP of the face: LBP(8,1) on a 3×3 grid and LBP(8,2) over the whole
    /// crop (Määttä et al.).
    FaceLbp,
    /// Uniform LBP(8,1) of the face in each of H, S, V, Y, Cb and Cr (Boulkenafet et al.).
    FaceColourLbp,
    /// Energy of the face's luma in four difference-of-Gaussians bands, as log shares of the
    /// total, and the log variance of its Laplacian (Tan et al.).
    FaceFrequency,
    /// Grey uniform LBP(8,1) of the wider crop on a 2×2 grid, and LBP(8,1) of its Cb and Cr.
    ContextLbp,
}

impl Block {
    pub const ALL: [Block; 4] = [Block::FaceLbp, Block::FaceColourLbp, Block::FaceFrequency, Block::ContextLbp];

    /// How many features the block makes.
    pub fn len(self) -> usize {
        match self {
            Block::FaceLbp => 10 * BINS,
            Block::FaceColourLbp => 6 * BINS,
            Block::FaceFrequency => 5,
            Block::ContextLbp => 6 * BINS,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Block::FaceLbp => "face-lbp",
            Block::FaceColourLbp => "face-colour-lbp",
            Block::FaceFrequency => "face-frequency",
            Block::ContextLbp => "context-lbp",
        }
    }
}

/// The crops the blocks are measured on.
pub struct Crops {
    pub face: RgbImage,
    pub context: RgbImage,
}

/// The face crop and the [`CONTEXT_SPAN`]-times wider crop about the same centre, at `centres`.
pub fn crops(photo: &RgbImage, centres: &EyeMouthCentres) -> Crops {
    let to_photo = chip_to_photo(FACE_SIZE, centres.left_eye, centres.right_eye, centres.mouth);
    let face = sample_crop(photo, &to_photo, FACE_SIZE);
    // Context pixel c ↦ face-crop pixel SPAN·c − (SPAN − 1)·centre: the same centre, SPAN times wider.
    let centre = 0.5 * FACE_SIZE as f32 * (CONTEXT_SPAN - 1.0);
    let widen = Similarity { a: CONTEXT_SPAN * FACE_SIZE as f32 / CONTEXT_SIZE as f32, b: 0.0, tx: -centre, ty: -centre };
    let context = sample_crop(photo, &to_photo.compose(&widen), CONTEXT_SIZE);
    Crops { face, context }
}

/// Most samples a side per crop pixel: enough to keep a shrunk photo from aliasing into false
/// texture, few enough that a crop costs well under a millisecond.
const MAX_SAMPLES: usize = 4;

/// A `size × size` crop: each pixel the mean of an `n × n` grid of nearest photo pixels through
/// `to_photo`, `n` the shrink factor (at most [`MAX_SAMPLES`]); outside the photo, black. The
/// deep chip's bilinear `extract` costs several times more at the wide crop's scale.
fn sample_crop(photo: &RgbImage, to_photo: &Similarity, size: usize) -> RgbImage {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("sse4.1") {
        // SAFETY: the CPU has SSE4.1 (checked at run time).
        return unsafe { sample_crop_sse41(photo, to_photo, size) };
    }
    sample_crop_body(photo, to_photo, size)
}

/// [`sample_crop`] with SSE4.1's rounding instructions (on the x86-64 baseline each `round` is a
/// libm call; the same values either way).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse4.1")]
fn sample_crop_sse41(photo: &RgbImage, to_photo: &Similarity, size: usize) -> RgbImage {
    sample_crop_body(photo, to_photo, size)
}

#[inline(always)]
fn sample_crop_body(photo: &RgbImage, to_photo: &Similarity, size: usize) -> RgbImage {
    let n = to_photo.scale().floor().clamp(1.0, MAX_SAMPLES as f32) as usize;
    let step = 1.0 / n as f32;
    let (w, h) = (photo.width() as i64, photo.height() as i64);
    let raw = photo.as_raw();
    let mut out = vec![0u8; size * size * 3];
    for cy in 0..size {
        for cx in 0..size {
            let mut acc = [0u32; 3];
            for sy in 0..n {
                for sx in 0..n {
                    let [x, y] = to_photo.apply([cx as f32 + (sx as f32 + 0.5) * step - 0.5, cy as f32 + (sy as f32 + 0.5) * step - 0.5]);
                    let (x, y) = (x.round() as i64, y.round() as i64);
                    if x >= 0 && y >= 0 && x < w && y < h {
                        let at = ((y * w + x) * 3) as usize;
                        for (a, v) in acc.iter_mut().zip(&raw[at..at + 3]) {
                            *a += u32::from(*v);
                        }
                    }
                }
            }
            let at = (cy * size + cx) * 3;
            for (o, a) in out[at..at + 3].iter_mut().zip(acc) {
                *o = ((a as f32) / (n * n) as f32).round() as u8;
            }
        }
    }
    RgbImage::from_raw(size as u32, size as u32, out).expect("size × size × 3 bytes")
}

/// The features of `blocks`, concatenated in their order.
pub fn features(crops: &Crops, blocks: &[Block]) -> Vec<f32> {
    let mut out = Vec::with_capacity(blocks.iter().map(|b| b.len()).sum());
    let face = ColourPlanes::of(&crops.face);
    // The luma's LBP(8,1) serves two blocks: computed once.
    let face_luma = std::cell::OnceCell::new();
    let luma_codes = || face_luma.get_or_init(|| lbp::codes(&face.y, 1));
    for block in blocks {
        match block {
            Block::FaceLbp => {
                out.extend(lbp::grid_histograms(luma_codes(), FACE_SIZE, 3));
                out.extend(lbp::grid_histograms(&lbp::codes(&face.y, 2), FACE_SIZE, 1));
            }
            Block::FaceColourLbp => {
                for plane in [&face.h, &face.s, &face.v] {
                    out.extend(lbp::grid_histograms(&lbp::codes(plane, 1), FACE_SIZE, 1));
                }
                out.extend(lbp::grid_histograms(luma_codes(), FACE_SIZE, 1));
                for plane in [&face.cb, &face.cr] {
                    out.extend(lbp::grid_histograms(&lbp::codes(plane, 1), FACE_SIZE, 1));
                }
            }
            Block::FaceFrequency => out.extend(frequency_energy(&face.y)),
            Block::ContextLbp => {
                let context = ColourPlanes::of(&crops.context);
                out.extend(lbp::grid_histograms(&lbp::codes(&context.y, 1), CONTEXT_SIZE, 2));
                for plane in [&context.cb, &context.cr] {
                    out.extend(lbp::grid_histograms(&lbp::codes(plane, 1), CONTEXT_SIZE, 1));
                }
            }
        }
    }
    out
}

/// A crop in HSV and YCbCr (JPEG's full-range conversion), each channel 0–255.
struct ColourPlanes {
    h: Plane,
    s: Plane,
    v: Plane,
    y: Plane,
    cb: Plane,
    cr: Plane,
}

impl ColourPlanes {
    fn of(img: &RgbImage) -> ColourPlanes {
        let size = img.width() as usize;
        let n = size * size;
        let mut planes: [Vec<f32>; 6] = std::array::from_fn(|_| Vec::with_capacity(n));
        for p in img.pixels() {
            let [r, g, b] = p.0.map(f32::from);
            let (max, min) = (r.max(g).max(b), r.min(g).min(b));
            let chroma = max - min;
            let hue = if chroma == 0.0 {
                0.0
            } else if max == r {
                ((g - b) / chroma).rem_euclid(6.0)
            } else if max == g {
                (b - r) / chroma + 2.0
            } else {
                (r - g) / chroma + 4.0
            };
            let values = [
                hue * 255.0 / 6.0,
                if max > 0.0 { 255.0 * chroma / max } else { 0.0 },
                max,
                0.299 * r + 0.587 * g + 0.114 * b,
                128.0 - 0.168_736 * r - 0.331_264 * g + 0.5 * b,
                128.0 + 0.5 * r - 0.418_688 * g - 0.081_312 * b,
            ];
            for (plane, v) in planes.iter_mut().zip(values) {
                plane.push(v);
            }
        }
        let [h, s, v, y, cb, cr] = planes.map(|data| Plane { size, data });
        ColourPlanes { h, s, v, y, cb, cr }
    }
}

/// Tan et al.'s cue: a print of a face is a low-passed copy, so less of its energy lies in the
/// finest bands. The shares of the luma's variance in the difference-of-Gaussians bands
/// (σ 0 → 0.5 → 1 → 2 → 4), as logs, and the log variance of the Laplacian.
fn frequency_energy(y: &Plane) -> [f32; 5] {
    let image = GrayF32 { width: y.size, height: y.size, data: y.data.clone() };
    let blurred: Vec<GrayF32> = [0.5, 1.0, 2.0, 4.0].iter().map(|&s| image.gaussian_blur(s)).collect();
    let energy = |a: &GrayF32, b: &GrayF32| a.data.iter().zip(&b.data).map(|(p, q)| (p - q) * (p - q)).sum::<f32>() / a.data.len() as f32;
    let mean = image.data.iter().sum::<f32>() / image.data.len() as f32;
    let total = image.data.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / image.data.len() as f32 + 1e-3;
    let mut out = [0.0f32; 5];
    out[0] = (energy(&image, &blurred[0]) / total + 1e-6).ln();
    for k in 1..4 {
        out[k] = (energy(&blurred[k - 1], &blurred[k]) / total + 1e-6).ln();
    }
    let n = y.size;
    let mut laplacian = Vec::with_capacity(n * n);
    for yy in 1..n - 1 {
        for xx in 1..n - 1 {
            let at = |x: usize, y: usize| image.data[y * n + x];
            laplacian.push(at(xx - 1, yy) + at(xx + 1, yy) + at(xx, yy - 1) + at(xx, yy + 1) - 4.0 * at(xx, yy));
        }
    }
    let lm = laplacian.iter().sum::<f32>() / laplacian.len() as f32;
    out[4] = (laplacian.iter().map(|v| (v - lm) * (v - lm)).sum::<f32>() / laplacian.len() as f32 + 1e-3).ln();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn centres() -> EyeMouthCentres {
        EyeMouthCentres { left_eye: [80.0, 90.0], right_eye: [140.0, 90.0], mouth: [110.0, 160.0] }
    }

    #[test]
    fn every_block_makes_as_many_features_as_it_says() {
        let photo = RgbImage::from_fn(240, 240, |x, y| image::Rgb([(x * 7 % 256) as u8, (y * 3 % 256) as u8, ((x + y) % 256) as u8]));
        let c = crops(&photo, &centres());
        assert_eq!((c.face.width(), c.context.width()), (FACE_SIZE as u32, CONTEXT_SIZE as u32));
        for block in Block::ALL {
            let f = features(&c, &[block]);
            assert_eq!(f.len(), block.len(), "{}", block.name());
            assert!(f.iter().all(|v| v.is_finite()), "{}", block.name());
        }
        assert_eq!(features(&c, &Block::ALL).len(), Block::ALL.iter().map(|b| b.len()).sum::<usize>());
    }

    #[test]
    fn a_blurred_copy_has_less_fine_energy() {
        let sharp = RgbImage::from_fn(240, 240, |x, y| {
            let v = if (x / 2 + y / 2) % 2 == 0 { 200 } else { 60 };
            image::Rgb([v, v, v])
        });
        let blurred = image::imageops::blur(&sharp, 2.0);
        let fine = |img: &RgbImage| features(&crops(img, &centres()), &[Block::FaceFrequency])[0];
        assert!(fine(&sharp) > fine(&blurred) + 1.0, "{} vs {}", fine(&sharp), fine(&blurred));
    }

    #[test]
    fn the_context_crop_is_centred_on_the_face_crop() {
        // A photo dark everywhere but a bright square on the face: the face crop is all bright,
        // the context crop bright only in its middle third.
        let photo = RgbImage::from_fn(600, 600, |x, y| {
            let inside = (40..180).contains(&x) && (40..220).contains(&y);
            image::Rgb(if inside { [250; 3] } else { [10; 3] })
        });
        let c = crops(&photo, &centres());
        let at = |img: &RgbImage, x: u32, y: u32| img.get_pixel(x, y).0[0];
        assert!(at(&c.face, 32, 32) > 200 && at(&c.context, 32, 32) > 200);
        assert!(at(&c.context, 2, 2) < 50 && at(&c.context, 61, 61) < 50);
    }
}
