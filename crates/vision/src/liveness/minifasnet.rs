//! Passive liveness by the two MiniFASNet networks of Silent-Face-Anti-Spoofing (`facegate_nn::
//! minifasnet`): plain data in (the photo, the detector's face box), plain data out
//! ([`MiniFasScores`]: each network's probability of a live face and their mean, as the original
//! predictor sums the two softmaxes).
//!
//! Each network sees its own crop, cut as the original's `generate_patches.py` cuts it: the face
//! box (integer left, top, width, height as its detector hands it over) scaled about its centre by
//! the network's factor (2.7 for V2, 4.0 for V1SE; less when the photo is too small for it), moved
//! back inside the photo, then resized to 80×80 by OpenCV's bilinear `resize` — reproduced here
//! bit for bit, fixed-point arithmetic included — and given to the network as blue, green, red
//! planes of 0–255 values.
//!
//! The original found faces with a RetinaFace detector; facegate gives the box of its own detector
//! (YuNet by default), whose box sits differently on the head: the crops are not exactly the ones
//! the networks were trained on.

use std::path::Path;

use facegate_core::geometry::Rect;
use facegate_nn::minifasnet::{self, LIVE_CLASS, MiniFasNetFile, MiniFasNetwork};
use image::RgbImage;
use serde::{Deserialize, Serialize};

/// The converted networks' files under the models folder (`facegate convert minifasnet`).
pub const V2_FILE: &str = "minifasnet-v2.bin";
pub const V1SE_FILE: &str = "minifasnet-v1se.bin";

/// The probability of a live face (class 1 of the softmax) by each network, and their mean.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MiniFasScores {
    /// MiniFASNetV2 on the 2.7× crop.
    pub v2: f32,
    /// MiniFASNetV1SE on the 4× crop.
    pub v1se: f32,
    /// The mean of the two: the original predictor's fused score.
    pub fused: f32,
}

#[derive(Debug, thiserror::Error)]
#[error("MiniFASNet weights {path}: {message}")]
pub struct MiniFasNetError {
    pub path: String,
    pub message: String,
}

/// The two networks, loaded. `Send + Sync`.
#[derive(Debug)]
pub struct MiniFasNet {
    pub v2: MiniFasNetwork,
    pub v1se: MiniFasNetwork,
}

fn load_network(path: &Path) -> Result<MiniFasNetwork, MiniFasNetError> {
    let fail = |message: String| MiniFasNetError { path: path.display().to_string(), message };
    let file: MiniFasNetFile =
        facegate_core::model_file::read_model(path, "MiniFASNet weight file", minifasnet::FORMAT, "facegate convert minifasnet")
            .map_err(fail)?;
    MiniFasNetwork::new(&file).map_err(|e| fail(e.to_string()))
}

impl MiniFasNet {
    /// [`V2_FILE`] and [`V1SE_FILE`] of `models_dir`.
    pub fn load(models_dir: &Path) -> Result<MiniFasNet, MiniFasNetError> {
        Ok(MiniFasNet { v2: load_network(&models_dir.join(V2_FILE))?, v1se: load_network(&models_dir.join(V1SE_FILE))? })
    }

    /// The scores of the face in `face` (the detector's box, in pixels of `photo`).
    pub fn assess(&self, photo: &RgbImage, face: &Rect) -> MiniFasScores {
        let face = PixelBox::from_rect(face);
        let live = |net: &MiniFasNetwork| {
            let crop = crop_box(photo.width(), photo.height(), face, net.crop_scale());
            net.forward(&network_input(photo, crop, net.input_size()))[LIVE_CLASS]
        };
        let (v2, v1se) = (live(&self.v2), live(&self.v1se));
        MiniFasScores { v2, v1se, fused: 0.5 * (v2 + v1se) }
    }
}

/// A face box as the original's detector hands it over (`Detection.get_bbox`): integer left and
/// top, and width and height, in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelBox {
    pub x: i64,
    pub y: i64,
    pub width: i64,
    pub height: i64,
}

impl PixelBox {
    /// `[int(left), int(top), int(right − left + 1), int(bottom − top + 1)]` of a box: Python's
    /// `int` truncates towards zero, as `as` does.
    pub fn from_rect(rect: &Rect) -> PixelBox {
        let (left, top) = (rect.x as f64, rect.y as f64);
        let (right, bottom) = (left + rect.width as f64, top + rect.height as f64);
        PixelBox { x: left as i64, y: top as i64, width: (right - left + 1.0) as i64, height: (bottom - top + 1.0) as i64 }
    }
}

/// A crop's corners, both included: columns `left..=right`, rows `top..=bottom`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropBox {
    pub left: u32,
    pub top: u32,
    pub right: u32,
    pub bottom: u32,
}

/// `CropImage._get_new_box` of `generate_patches.py`, in the same `f64` arithmetic: the box scaled
/// by `scale` about its centre (the scale lowered so that the crop fits the photo), shifted back
/// inside the photo where it overflows, its corners truncated to integers.
pub fn crop_box(width: u32, height: u32, face: PixelBox, scale: f64) -> CropBox {
    let (src_w, src_h) = (width as f64, height as f64);
    // A box of no size would divide by zero in the original; the detector never gives one.
    let (box_w, box_h) = (face.width.max(1) as f64, face.height.max(1) as f64);
    let scale = ((src_h - 1.0) / box_h).min(((src_w - 1.0) / box_w).min(scale));
    let (new_width, new_height) = (box_w * scale, box_h * scale);
    let (center_x, center_y) = (box_w / 2.0 + face.x as f64, box_h / 2.0 + face.y as f64);
    let mut left = center_x - new_width / 2.0;
    let mut top = center_y - new_height / 2.0;
    let mut right = center_x + new_width / 2.0;
    let mut bottom = center_y + new_height / 2.0;
    if left < 0.0 {
        right -= left;
        left = 0.0;
    }
    if top < 0.0 {
        bottom -= top;
        top = 0.0;
    }
    if right > src_w - 1.0 {
        left -= right - src_w + 1.0;
        right = src_w - 1.0;
    }
    if bottom > src_h - 1.0 {
        top -= bottom - src_h + 1.0;
        bottom = src_h - 1.0;
    }
    // The clamps keep every corner inside the photo up to rounding (a corner of −1e-13 truncates
    // to 0, as Python's `int` does).
    let pixel = |v: f64, limit: u32| (v.max(0.0) as u32).min(limit.saturating_sub(1));
    CropBox { left: pixel(left, width), top: pixel(top, height), right: pixel(right, width), bottom: pixel(bottom, height) }
}

/// OpenCV's fixed-point scale of the bilinear weights (`INTER_RESIZE_COEF_BITS` = 11).
const COEF_SCALE: f32 = 2048.0;

/// One output column's (or row's) source index and its two fixed-point weights.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Tap {
    /// The first source pixel; a row's may lie outside the crop (`−1`, or `len − 1`).
    index: i64,
    weights: [i32; 2],
}

/// `cv::resize`'s INTER_LINEAR coordinates of `out` outputs from `len` inputs: the source position
/// `(d + 0.5) · scale − 0.5` in `f32`, its floor and fraction, the weights `(1 − f, f)` rounded to
/// 1/2048 (half to even, as `cvRound`). Columns (`clamp_fraction`) past either border take the edge
/// value whole; rows keep their weights and only their indices are clamped, as OpenCV does.
fn taps(len: usize, out: usize, clamp_fraction: bool) -> Vec<Tap> {
    // OpenCV derives the scale from the inverse it is given: 1 / (out / len).
    let scale = 1.0 / (out as f64 / len as f64);
    (0..out)
        .map(|d| {
            let position = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let mut floor = position.floor() as i64;
            let mut fraction = position - floor as f32;
            if clamp_fraction && floor < 0 {
                (floor, fraction) = (0, 0.0);
            }
            if clamp_fraction && floor >= len as i64 - 1 {
                (floor, fraction) = (len as i64 - 1, 0.0);
            }
            let w0 = ((1.0 - fraction) * COEF_SCALE).round_ties_even() as i32;
            let w1 = (fraction * COEF_SCALE).round_ties_even() as i32;
            Tap { index: floor, weights: [w0, w1] }
        })
        .collect()
}

/// `crop` of `photo` resized to `side × side` exactly as `cv2.resize(crop, (side, side))` does on
/// 8-bit pixels, as three channel-first planes in OpenCV's order (blue, green, red) of 0–255 values.
///
/// # Panics
/// When the crop is not inside the photo ([`crop_box`]'s always is).
pub fn network_input(photo: &RgbImage, crop: CropBox, side: usize) -> Vec<f32> {
    assert!(
        crop.left <= crop.right && crop.top <= crop.bottom && crop.right < photo.width() && crop.bottom < photo.height(),
        "{crop:?} inside a {}×{} photo",
        photo.width(),
        photo.height()
    );
    let (w, h) = ((crop.right - crop.left + 1) as usize, (crop.bottom - crop.top + 1) as usize);
    let (raw, stride) = (photo.as_raw(), photo.width() as usize * 3);
    let pixel = |x: usize, y: usize| {
        let at = (crop.top as usize + y) * stride + (crop.left as usize + x) * 3;
        [raw[at], raw[at + 1], raw[at + 2]]
    };
    let plane = side * side;
    let mut planes = vec![0.0f32; 3 * plane];
    let mut put = |x: usize, y: usize, rgb: [u8; 3]| {
        for (c, v) in rgb.iter().rev().enumerate() {
            planes[c * plane + y * side + x] = *v as f32;
        }
    };
    if w == 2 * side && h == 2 * side {
        // OpenCV turns a linear resize by exactly one half into its area resize: the mean of
        // each 2×2 block, rounded.
        for y in 0..side {
            for x in 0..side {
                let quad = [pixel(2 * x, 2 * y), pixel(2 * x + 1, 2 * y), pixel(2 * x, 2 * y + 1), pixel(2 * x + 1, 2 * y + 1)];
                put(x, y, std::array::from_fn(|c| ((quad.iter().map(|p| p[c] as u32).sum::<u32>() + 2) >> 2) as u8));
            }
        }
        return planes;
    }
    let columns = taps(w, side, true);
    let rows = taps(h, side, false);
    // The horizontal pass of source row `y`, in OpenCV's fixed point (value · 2048). Only the two
    // rows each output row reads are computed (a 480-row crop reads 160 of them).
    let horizontal = |y: usize, out: &mut Vec<[i32; 3]>| {
        out.clear();
        out.extend(columns.iter().map(|t| {
            // Columns are clamped into the crop by `taps`.
            let x = t.index as usize;
            let a = pixel(x, y);
            match x + 1 < w {
                true => {
                    let b = pixel(x + 1, y);
                    std::array::from_fn(|c| a[c] as i32 * t.weights[0] + b[c] as i32 * t.weights[1])
                }
                false => std::array::from_fn(|c| a[c] as i32 * COEF_SCALE as i32),
            }
        }));
    };
    let (mut upper, mut lower) = (Vec::with_capacity(side), Vec::with_capacity(side));
    for (y, t) in rows.iter().enumerate() {
        // Rows outside the crop are its edge rows (the weights are kept).
        let row = |k: i64| (t.index + k).clamp(0, h as i64 - 1) as usize;
        horizontal(row(0), &mut upper);
        horizontal(row(1), &mut lower);
        for (x, (s0, s1)) in upper.iter().zip(&lower).enumerate() {
            // VResizeLinear<uchar, int, short>: each product shifted down on its own, then rounded.
            put(
                x,
                y,
                std::array::from_fn(|c| ((((t.weights[0] * (s0[c] >> 4)) >> 16) + ((t.weights[1] * (s1[c] >> 4)) >> 16) + 2) >> 2) as u8),
            );
        }
    }
    planes
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `_get_new_box` on boxes inside the photo, against each border, and wider than the photo:
    /// the expected corners are what `CropImage._get_new_box` of `generate_patches.py` returns
    /// for them (run in Python 3.11); the comments give the arithmetic.
    #[test]
    fn crop_boxes_follow_generate_patches() {
        // 640×480, box (200, 150, 100, 120), scale 2.7: the box is 270×324 about (250, 210):
        // 115.0, 48.0, 385.0, 372.0.
        let b = crop_box(640, 480, PixelBox { x: 200, y: 150, width: 100, height: 120 }, 2.7);
        assert_eq!(b, CropBox { left: 115, top: 48, right: 385, bottom: 372 });
        // Scale 4 on the same box: 400×480 wanted; 479/120 = 3.9917 < 4 is the scale, so
        // 399.17×479 about (250, 210): left 50.42, top −29.5 → shifted down by 29.5 to 0 …
        // bottom 449.5 + 29.5 = 479.0.
        let b = crop_box(640, 480, PixelBox { x: 200, y: 150, width: 100, height: 120 }, 4.0);
        assert_eq!(b, CropBox { left: 50, top: 0, right: 449, bottom: 479 });
        // Near the left and top borders: (−10, 5, 80, 90) × 2.7 = 216×243 about (30, 50):
        // left −78 → 0, right 138 + 78 = 216; top −71.5 → 0, bottom 171.5 + 71.5 = 243.
        let b = crop_box(640, 480, PixelBox { x: -10, y: 5, width: 80, height: 90 }, 2.7);
        assert_eq!(b, CropBox { left: 0, top: 0, right: 216, bottom: 243 });
        // Near the right and bottom borders: (600, 440, 50, 50) × 2.7 = 135×135 about (625, 465):
        // right 692.5 > 639 → left 557.5 − 53.5 = 504.0; bottom 532.5 > 479 → top 397.5 − 53.5 = 344.
        let b = crop_box(640, 480, PixelBox { x: 600, y: 440, width: 50, height: 50 }, 2.7);
        assert_eq!(b, CropBox { left: 504, top: 344, right: 639, bottom: 479 });
        // A fractional corner truncates: (201, 151, 101, 121) × 2.7 = 272.7×326.7 about
        // (251.5, 211.5): 115.15 → 115, 48.15 → 48, 387.85 → 387, 374.85 → 374.
        let b = crop_box(640, 480, PixelBox { x: 201, y: 151, width: 101, height: 121 }, 2.7);
        assert_eq!(b, CropBox { left: 115, top: 48, right: 387, bottom: 374 });
        // A box wider than the photo: the scale drops to (92 − 1)/120: 91×91 about (40, 60):
        // left −5.5 → 0, right 85.5 + 5.5 = 91 (the last column); top 14.5, bottom 105.5.
        let b = crop_box(92, 112, PixelBox { x: -20, y: 0, width: 120, height: 120 }, 4.0);
        assert_eq!(b, CropBox { left: 0, top: 14, right: 91, bottom: 105 });
    }

    #[test]
    fn pixel_boxes_truncate_like_python_int() {
        let b = PixelBox::from_rect(&Rect::new(12.7, -3.6, 100.2, 119.9));
        assert_eq!(b, PixelBox { x: 12, y: -3, width: 101, height: 120 });
    }

    /// OpenCV's weights for 270 → 80 columns (scale 3.375): the first output sits at
    /// 0.5 · 3.375 − 0.5 = 1.1875 of the source (weights 0.8125 and 0.1875 of 2048), the last at
    /// 79.5 · 3.375 − 0.5 = 267.8125.
    #[test]
    fn resize_weights_are_opencvs_fixed_point() {
        let t = taps(270, 80, true);
        assert_eq!(t[0], Tap { index: 1, weights: [1664, 384] });
        assert_eq!(t[79], Tap { index: 267, weights: [384, 1664] });
        let up = taps(40, 80, true);
        // Enlarging: the first output is left of the first pixel centre, so it takes it whole.
        assert_eq!(up[0], Tap { index: 0, weights: [2048, 0] });
        assert_eq!(up[79], Tap { index: 39, weights: [2048, 0] });
    }

    /// The converted networks against PyTorch running the original model definition on the same
    /// 80×80 inputs: NUAA frames (two live, two printed photos) decoded and cut here at YuNet's
    /// boxes, the inputs written out as float planes, and the softmaxes computed once by
    /// (torch 2.15.0 CPU, Python 3.11, the files of `../shared/models/minifasnet`):
    ///
    /// ```python
    /// import sys, numpy as np, torch, torch.nn.functional as F
    /// sys.path.insert(0, '../shared/models/minifasnet')
    /// from MiniFASNet import MiniFASNetV2, MiniFASNetV1SE
    /// from utility import get_kernel, parse_model_name
    /// def load(path):  # as anti_spoof_predict.AntiSpoofPredict._load_model
    ///     h, w, model_type, scale = parse_model_name(path.split('/')[-1])
    ///     model = {'MiniFASNetV2': MiniFASNetV2, 'MiniFASNetV1SE': MiniFASNetV1SE}[model_type](conv6_kernel=get_kernel(h, w))
    ///     state_dict = torch.load(path, map_location='cpu', weights_only=False)
    ///     model.load_state_dict({k[7:] if k.startswith('module.') else k: v for k, v in state_dict.items()})
    ///     return model.eval()
    /// model = load('../shared/models/minifasnet/2.7_80x80_MiniFASNetV2.pth')  # or 4_0_0_80x80_MiniFASNetV1SE.pth
    /// planes = np.fromfile('crop.f32', dtype='<f4').reshape(1, 3, 80, 80)  # network_input's output
    /// with torch.no_grad():
    ///     print(F.softmax(model.forward(torch.from_numpy(planes)), dim=1).numpy()[0])
    /// ```
    ///
    /// The same crops cut by the original `CropImage.crop` (cv2.resize, OpenCV 5.0) from the same
    /// decoded pixels were identical to `network_input`'s, byte for byte.
    #[test]
    fn the_networks_match_pytorch_on_nuaa_crops() {
        let networks = MiniFasNet::load(&facegate_paths::models_dir()).unwrap();
        // Frame, YuNet's box, PyTorch's softmax for V2 and V1SE.
        type Case = (&'static str, [f32; 4], [f32; minifasnet::CLASSES], [f32; minifasnet::CLASSES]);
        let cases: [Case; 4] = [
            (
                "real/0004/0004_01_00_01_109.jpg",
                [244.87904, 130.82219, 139.79492, 177.48116],
                [0.0001728, 0.9995856, 0.0002416],
                [0.0010525, 0.9973283, 0.0016193],
            ),
            (
                "real/0002/0002_01_00_01_308.jpg",
                [266.97116, 115.43467, 169.98177, 227.19414],
                [0.0001349, 0.9788387, 0.0210264],
                [0.0000400, 0.9736867, 0.0262733],
            ),
            (
                "print/0004/0004_01_00_01_107.jpg",
                [281.8395, 110.82065, 144.99121, 186.05804],
                [0.9999856, 0.0000013, 0.0000131],
                [0.9994456, 0.0000455, 0.0005088],
            ),
            (
                // A face whose 2.7× and 4× crops differ (both are the whole height elsewhere).
                "print/0007/0007_01_00_01_51.jpg",
                [260.82166, 95.98249, 126.28906, 161.76671],
                [0.9999996, 0.0000001, 0.0000002],
                [1.0000000, 0.0000000, 0.0000000],
            ),
        ];
        for (frame, [x, y, w, h], v2, v1se) in cases {
            let path = facegate_paths::shared_dir().join("data/nuaa").join(frame);
            let photo = facegate_core::imaging::open(&path).unwrap().rgb;
            let face = Rect::new(x, y, w, h);
            for (net, expected) in [(&networks.v2, v2), (&networks.v1se, v1se)] {
                let crop = crop_box(photo.width(), photo.height(), PixelBox::from_rect(&face), net.crop_scale());
                let got = net.forward(&network_input(&photo, crop, net.input_size()));
                for (g, e) in got.iter().zip(&expected) {
                    assert!((g - e).abs() < 1e-4, "{frame} {}: {got:?} against PyTorch's {expected:?}", net.name());
                }
            }
            let scores = networks.assess(&photo, &face);
            assert!((scores.v2 - v2[1]).abs() < 1e-4 && (scores.v1se - v1se[1]).abs() < 1e-4, "{frame}: {scores:?}");
            assert!((scores.fused - 0.5 * (v2[1] + v1se[1])).abs() < 1e-4, "{frame}: {scores:?}");
        }
    }

    #[test]
    fn a_uniform_crop_stays_uniform_and_channels_come_out_blue_first() {
        let photo = RgbImage::from_pixel(300, 200, image::Rgb([10, 120, 250]));
        for crop in [CropBox { left: 3, top: 7, right: 272, bottom: 190 }, CropBox { left: 0, top: 0, right: 159, bottom: 159 }] {
            let planes = network_input(&photo, crop, 80);
            assert!(planes[..6400].iter().all(|&v| v == 250.0));
            assert!(planes[6400..12800].iter().all(|&v| v == 120.0));
            assert!(planes[12800..].iter().all(|&v| v == 10.0));
        }
    }
}
