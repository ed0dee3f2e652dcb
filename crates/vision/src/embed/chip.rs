//! The face chip the network expects, cut from a photo with facegate's own landmarks.
//!
//! dlib aligns a face by the least-squares similarity that takes its 68-point landmarks (eyes,
//! nose and upper mouth) to a mean face shape in a `size × size` chip with 25% padding
//! (`get_face_chip_details(det, 150, 0.25)`); the network was trained on such chips. facegate has
//! the 58 IMM points instead, so it uses the points both templates share in meaning: the two eye
//! centres (the mean of each eye outline) and the mouth centre (the mean of the outer lip
//! outline), placed where dlib's mean shape puts them.

use image::RgbImage;

use facegate_core::geometry::{Point, Similarity};
use facegate_nn::FaceChip;

/// dlib's mean face shape (points 36–59 of the 68-point iBUG template, in the unit square of the
/// face; `dlib/image_transforms/interpolation.h`, Boost Software License): x then y.
const MEAN_RIGHT_EYE: [[f32; 2]; 6] =
    [[0.121737, 0.216423], [0.187122, 0.178758], [0.265825, 0.179852], [0.334606, 0.231733], [0.260918, 0.245099], [0.182743, 0.244077]];
const MEAN_LEFT_EYE: [[f32; 2]; 6] =
    [[0.645647, 0.231733], [0.714428, 0.179852], [0.793132, 0.178758], [0.858516, 0.216423], [0.79751, 0.244077], [0.719335, 0.245099]];
const MEAN_OUTER_LIPS: [[f32; 2]; 12] = [
    [0.254149, 0.780233],
    [0.340985, 0.745405],
    [0.428858, 0.727388],
    [0.490127, 0.742578],
    [0.551395, 0.727388],
    [0.639268, 0.745405],
    [0.726104, 0.780233],
    [0.642159, 0.864805],
    [0.556721, 0.902192],
    [0.490127, 0.909281],
    [0.423532, 0.902192],
    [0.338094, 0.864805],
];

/// dlib's chip padding around the mean shape, as a fraction of the face.
const PADDING: f32 = 0.25;

fn mean(points: &[[f32; 2]]) -> Point {
    let n = points.len() as f32;
    [points.iter().map(|p| p[0]).sum::<f32>() / n, points.iter().map(|p| p[1]).sum::<f32>() / n]
}

/// Where the image-left eye centre, the image-right eye centre and the mouth centre go in a chip
/// of side `size`.
pub fn chip_centres(size: usize) -> [Point; 3] {
    let place = |p: Point| {
        let s = size as f32 / (2.0 * PADDING + 1.0);
        [(PADDING + p[0]) * s, (PADDING + p[1]) * s]
    };
    [place(mean(&MEAN_RIGHT_EYE)), place(mean(&MEAN_LEFT_EYE)), place(mean(&MEAN_OUTER_LIPS))]
}

/// The similarity taking chip pixels to photo pixels, from the photo's image-left eye centre,
/// image-right eye centre and mouth centre.
pub fn chip_to_photo(size: usize, left_eye: Point, right_eye: Point, mouth: Point) -> Similarity {
    Similarity::fit(&chip_centres(size), &[left_eye, right_eye, mouth], None)
}

/// Cuts the chip: each chip pixel samples the photo through `to_photo`, bilinearly, averaging
/// `n × n` samples when the chip shrinks the face by `n` or more so that small chips of large
/// photos do not alias (dlib samples a pyramid level for the same reason). Outside the photo: black.
pub fn extract(photo: &RgbImage, to_photo: &Similarity, size: usize) -> FaceChip {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("sse4.1") {
        // SAFETY: the CPU has SSE4.1 (checked at run time).
        return unsafe { extract_sse41(photo, to_photo, size) };
    }
    extract_body(photo, to_photo, size)
}

/// [`extract`] with SSE4.1's rounding instructions: on the x86-64 baseline every `floor` and
/// `round` is a libm call, which cost more than the sampling (the same values either way).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse4.1")]
fn extract_sse41(photo: &RgbImage, to_photo: &Similarity, size: usize) -> FaceChip {
    extract_body(photo, to_photo, size)
}

#[inline(always)]
fn extract_body(photo: &RgbImage, to_photo: &Similarity, size: usize) -> FaceChip {
    extract_with::<true>(photo, to_photo, size)
}

/// The sampling of [`extract`]; `INTERIOR` reads the four pixels of a sample whose square lies
/// inside the photo without a bounds check per pixel and channel (the chip's samples nearly all
/// do). The same arithmetic either way, so the same bytes (a test compares them).
#[inline(always)]
fn extract_with<const INTERIOR: bool>(photo: &RgbImage, to_photo: &Similarity, size: usize) -> FaceChip {
    let n = to_photo.scale().floor().clamp(1.0, 8.0) as usize;
    let step = 1.0 / n as f32;
    let (w, h) = (photo.width() as i64, photo.height() as i64);
    let raw = photo.as_raw();
    let stride = w as usize * 3;
    let px = |x: i64, y: i64, ch: usize| -> f32 {
        if x < 0 || y < 0 || x >= w || y >= h { 0.0 } else { raw[((y * w + x) * 3) as usize + ch] as f32 }
    };
    let mut rgb = vec![0u8; size * size * 3];
    for cy in 0..size {
        for cx in 0..size {
            let mut acc = [0.0f32; 3];
            for sy in 0..n {
                for sx in 0..n {
                    let c = [cx as f32 + (sx as f32 + 0.5) * step - 0.5, cy as f32 + (sy as f32 + 0.5) * step - 0.5];
                    let [x, y] = to_photo.apply(c);
                    let (x0, y0) = (x.floor(), y.floor());
                    let (fx, fy) = (x - x0, y - y0);
                    let (x0, y0) = (x0 as i64, y0 as i64);
                    if INTERIOR && x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
                        let at = (y0 * w + x0) as usize * 3;
                        let (top_row, bottom_row) = (&raw[at..at + 6], &raw[at + stride..at + stride + 6]);
                        for (ch, a) in acc.iter_mut().enumerate() {
                            let top = top_row[ch] as f32 * (1.0 - fx) + top_row[ch + 3] as f32 * fx;
                            let bottom = bottom_row[ch] as f32 * (1.0 - fx) + bottom_row[ch + 3] as f32 * fx;
                            *a += top * (1.0 - fy) + bottom * fy;
                        }
                        continue;
                    }
                    for (ch, a) in acc.iter_mut().enumerate() {
                        let top = px(x0, y0, ch) * (1.0 - fx) + px(x0 + 1, y0, ch) * fx;
                        let bottom = px(x0, y0 + 1, ch) * (1.0 - fx) + px(x0 + 1, y0 + 1, ch) * fx;
                        *a += top * (1.0 - fy) + bottom * fy;
                    }
                }
            }
            let at = (cy * size + cx) * 3;
            for ch in 0..3 {
                rgb[at + ch] = (acc[ch] / (n * n) as f32).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    FaceChip { size, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centres_sit_where_dlib_puts_them() {
        let [l, r, m] = chip_centres(150);
        // Eyes level and symmetric about the chip's centre line, mouth below on that line.
        assert!((l[1] - r[1]).abs() < 1e-3);
        assert!(((l[0] + r[0]) / 2.0 - m[0]).abs() < 0.5);
        assert!(l[0] < r[0] && m[1] > l[1] + 40.0);
    }

    #[test]
    fn identity_transform_copies_pixels() {
        let img = RgbImage::from_fn(20, 20, |x, y| image::Rgb([x as u8 * 10, y as u8 * 10, 7]));
        let t = Similarity { a: 1.0, b: 0.0, tx: 3.0, ty: 4.0 };
        let chip = extract(&img, &t, 10);
        assert_eq!(&chip.rgb[..3], &[30, 40, 7]);
        let last = (9 * 10 + 9) * 3;
        assert_eq!(&chip.rgb[last..last + 3], &[120, 130, 7]);
    }

    #[test]
    fn interior_reads_give_the_checked_reads_bytes() {
        let img = RgbImage::from_fn(97, 83, |x, y| image::Rgb([(x * 7 + y * 3) as u8, (x * y) as u8, (x ^ y) as u8]));
        // Turned, scaled (1×, 2× and 3× supersampling) and partly outside the photo.
        for (a, b, tx, ty) in [(0.93, 0.21, -9.5, 4.25), (2.1, -0.4, 10.0, -20.0), (3.3, 0.7, 30.0, 5.0)] {
            let t = Similarity { a, b, tx, ty };
            assert_eq!(extract_with::<true>(&img, &t, 40), extract_with::<false>(&img, &t, 40));
        }
    }
}
