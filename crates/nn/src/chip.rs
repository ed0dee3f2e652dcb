//! The networks' input: a square RGB image, as the face stages cut it from a photo.

use image::RgbImage;

/// A square RGB chip, row-major, 3 bytes a pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceChip {
    pub size: usize,
    pub rgb: Vec<u8>,
}

impl FaceChip {
    pub fn to_image(&self) -> RgbImage {
        RgbImage::from_raw(self.size as u32, self.size as u32, self.rgb.clone()).expect("size × size × 3 bytes")
    }

    /// The chip mirrored left to right.
    pub fn mirrored(&self) -> FaceChip {
        let mut rgb = self.rgb.clone();
        for row in rgb.chunks_exact_mut(self.size * 3) {
            for x in 0..self.size / 2 {
                let y = self.size - 1 - x;
                for k in 0..3 {
                    row.swap(x * 3 + k, y * 3 + k);
                }
            }
        }
        FaceChip { size: self.size, rgb }
    }

    pub fn from_image(img: &RgbImage) -> Option<FaceChip> {
        (img.width() == img.height()).then(|| FaceChip { size: img.width() as usize, rgb: img.as_raw().clone() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirroring_swaps_columns_and_twice_is_identity() {
        let img = RgbImage::from_fn(4, 4, |x, y| image::Rgb([x as u8, y as u8, 9]));
        let chip = FaceChip::from_image(&img).unwrap();
        let m = chip.mirrored();
        assert_eq!(&m.rgb[..3], &[3, 0, 9]);
        assert_eq!(m.mirrored(), chip);
    }
}
