//! Decoding photos with limits, and the f32 grey image every numeric stage works on.

use std::io::Cursor;
use std::path::Path;

use image::{DynamicImage, ImageFormat, ImageReader, RgbImage};

/// Limits applied before and during decoding, so a small file that claims a huge image
/// (a decompression bomb) is refused without allocating it.
#[derive(Debug, Clone, Copy)]
pub struct DecodeLimits {
    pub max_width: u32,
    pub max_height: u32,
    pub max_pixels: u64,
    pub max_alloc_bytes: u64,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        Self { max_width: 8192, max_height: 8192, max_pixels: 24_000_000, max_alloc_bytes: 256 << 20 }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("the data is not an image of a known format")]
    NotAnImage,
    #[error("image format {0} is not supported (JPEG, PNG, GIF, BMP, PGM/PPM are)")]
    Unsupported(String),
    #[error("image of {width}x{height} pixels exceeds the limit ({limit})")]
    TooLarge { width: u32, height: u32, limit: String },
    #[error("the image data is corrupt or truncated: {0}")]
    Corrupt(String),
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
}

/// A decoded photo: colour for texture work, f32 grey for everything numeric.
#[derive(Debug, Clone)]
pub struct Photo {
    pub rgb: RgbImage,
    pub gray: GrayF32,
}

impl Photo {
    pub fn from_dynamic(img: DynamicImage) -> Photo {
        // `into_rgb8` keeps the decoder's buffer when it is RGB already (JPEG): no copy per request.
        let rgb = img.into_rgb8();
        let gray = GrayF32::from_rgb(&rgb);
        Photo { rgb, gray }
    }

    pub fn width(&self) -> u32 {
        self.rgb.width()
    }

    pub fn height(&self) -> u32 {
        self.rgb.height()
    }
}

/// Formats we accept. Anything else the `image` crate could guess is refused as unsupported.
fn supported(format: ImageFormat) -> bool {
    matches!(format, ImageFormat::Jpeg | ImageFormat::Png | ImageFormat::Gif | ImageFormat::Bmp | ImageFormat::Pnm)
}

/// Decode bytes into a [`Photo`], checking the header's dimensions against `limits` first.
pub fn decode(bytes: &[u8], limits: &DecodeLimits) -> Result<Photo, DecodeError> {
    let reader = ImageReader::new(Cursor::new(bytes)).with_guessed_format().map_err(|e| DecodeError::Corrupt(e.to_string()))?;
    let format = reader.format().ok_or(DecodeError::NotAnImage)?;
    if !supported(format) {
        return Err(DecodeError::Unsupported(format!("{format:?}")));
    }
    if format == ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        return Err(DecodeError::Corrupt("truncated JPEG: no end-of-image marker after the last scan".into()));
    }
    let (width, height) = reader.into_dimensions().map_err(|e| classify(e))?;
    check_dimensions(width, height, limits)?;
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    let mut l = image::Limits::default();
    l.max_image_width = Some(limits.max_width);
    l.max_image_height = Some(limits.max_height);
    l.max_alloc = Some(limits.max_alloc_bytes);
    reader.limits(l);
    let img = reader.decode().map_err(classify)?;
    Ok(Photo::from_dynamic(img))
}

/// Read and decode a file with the default limits.
pub fn open(path: &Path) -> Result<Photo, DecodeError> {
    let bytes = std::fs::read(path).map_err(|source| DecodeError::Io { path: path.display().to_string(), source })?;
    decode(&bytes, &DecodeLimits::default())
}

/// A JPEG decoder fills a truncated scan with grey and reports success, so completeness is checked
/// on the markers: the end-of-image marker (FF D9) must follow the last start-of-scan (FF DA).
/// Inside entropy-coded data FF is always followed by 00 or a restart marker, so an FF D9 there is a
/// real end of image; an EXIF thumbnail's own FF D9 comes before the main scan and does not count.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    let last_marker = |m: u8| bytes.windows(2).rposition(|w| w[0] == 0xFF && w[1] == m);
    match (last_marker(0xDA), last_marker(0xD9)) {
        (Some(sos), Some(eoi)) => eoi > sos,
        _ => false,
    }
}

fn check_dimensions(width: u32, height: u32, limits: &DecodeLimits) -> Result<(), DecodeError> {
    if width == 0 || height == 0 {
        return Err(DecodeError::Corrupt("image has no pixels".into()));
    }
    let too_large = |limit: String| Err(DecodeError::TooLarge { width, height, limit });
    if width > limits.max_width || height > limits.max_height {
        return too_large(format!("{}x{} at most", limits.max_width, limits.max_height));
    }
    if width as u64 * height as u64 > limits.max_pixels {
        return too_large(format!("{} pixels at most", limits.max_pixels));
    }
    Ok(())
}

fn classify(e: image::ImageError) -> DecodeError {
    use image::ImageError as E;
    match e {
        E::Limits(l) => DecodeError::TooLarge { width: 0, height: 0, limit: l.to_string() },
        E::Unsupported(u) => DecodeError::Unsupported(u.to_string()),
        other => DecodeError::Corrupt(other.to_string()),
    }
}

/// A single-channel f32 image, row-major, values in 0..=255.
#[derive(Debug, Clone, PartialEq)]
pub struct GrayF32 {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl GrayF32 {
    pub fn new(width: usize, height: usize) -> Self {
        Self { width, height, data: vec![0.0; width * height] }
    }

    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    /// ITU-R BT.601 luma.
    pub fn from_rgb(rgb: &RgbImage) -> Self {
        // Over the raw bytes in chunks of three (same arithmetic as per pixel, vectorisable).
        let data = rgb.as_raw()[..rgb.width() as usize * rgb.height() as usize * 3]
            .chunks_exact(3)
            .map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32)
            .collect();
        Self { width: rgb.width() as usize, height: rgb.height() as usize, data }
    }

    pub fn from_luma8(img: &image::GrayImage) -> Self {
        Self { width: img.width() as usize, height: img.height() as usize, data: img.as_raw().iter().map(|&v| v as f32).collect() }
    }

    pub fn to_luma8(&self) -> image::GrayImage {
        let raw = self.data.iter().map(|&v| v.round().clamp(0.0, 255.0) as u8).collect();
        image::GrayImage::from_raw(self.width as u32, self.height as u32, raw).expect("buffer size matches")
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, v: f32) {
        self.data[y * self.width + x] = v;
    }

    /// Pixel value with coordinates clamped to the border.
    #[inline]
    pub fn get_clamped(&self, x: isize, y: isize) -> f32 {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        self.data[y * self.width + x]
    }

    /// Bilinear interpolation at (x, y) in pixel coordinates (pixel centres at integers),
    /// clamped at the border.
    #[inline]
    pub fn sample(&self, x: f32, y: f32) -> f32 {
        let w = self.width;
        // Inside the image, where nearly every sample falls (the ASM crop was a tenth of the
        // landmark search): no clamping, and truncation is the floor (no libm call). The same
        // arithmetic as the clamped path below, so the same values.
        if x >= 0.0 && y >= 0.0 && x < (w - 1) as f32 && y < (self.height - 1) as f32 {
            let (x0, y0) = (x as usize, y as usize);
            return self.lerp_inside(x0, y0, x - x0 as f32, y - y0 as f32);
        }
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        let x0 = x.floor() as usize;
        let y0 = y.floor() as usize;
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let fx = x - x0 as f32;
        let fy = y - y0 as f32;
        let row0 = y0 * self.width;
        let row1 = y1 * self.width;
        let top = self.data[row0 + x0] + fx * (self.data[row0 + x1] - self.data[row0 + x0]);
        let bottom = self.data[row1 + x0] + fx * (self.data[row1 + x1] - self.data[row1 + x0]);
        top + fy * (bottom - top)
    }

    /// The bilinear value in the cell whose top-left pixel is (x0, y0), both inside the image
    /// but for the last column and row, at fractions (fx, fy).
    #[inline(always)]
    fn lerp_inside(&self, x0: usize, y0: usize, fx: f32, fy: f32) -> f32 {
        let w = self.width;
        let d = &self.data[y0 * w + x0..y0 * w + x0 + w + 2];
        let top = d[0] + fx * (d[1] - d[0]);
        let bottom = d[w] + fx * (d[w + 1] - d[w]);
        top + fy * (bottom - top)
    }

    /// [`GrayF32::sample`] at every (xs[i], ys[j]), as an image of `xs.len() × ys.len()`: the
    /// same values, with each column's and row's cell found once rather than per sample (an
    /// axis-aligned resampling, as the landmark search's crop and the detector's input are).
    pub fn sample_grid(&self, xs: &[f32], ys: &[f32]) -> GrayF32 {
        // Per coordinate: its cell and fraction when it is inside (as `sample` tests it).
        let cells = |coords: &[f32], n: usize| -> Vec<Option<(usize, f32)>> {
            coords.iter().map(|&c| (c >= 0.0 && c < (n - 1) as f32).then(|| (c as usize, c - (c as usize) as f32))).collect()
        };
        let (columns, rows) = (cells(xs, self.width), cells(ys, self.height));
        let mut out = GrayF32::new(xs.len(), ys.len());
        for ((line, &y), row) in out.data.chunks_exact_mut(xs.len().max(1)).zip(ys).zip(&rows) {
            for ((o, &x), column) in line.iter_mut().zip(xs).zip(&columns) {
                *o = match (column, row) {
                    (Some((x0, fx)), Some((y0, fy))) => self.lerp_inside(*x0, *y0, *fx, *fy),
                    _ => self.sample(x, y),
                };
            }
        }
        out
    }

    /// Separable Gaussian blur with standard deviation `sigma` (kernel radius 3σ, borders clamped).
    /// The one blur of the project: the landmark search builds its pyramid with it on every search,
    /// so the border clamping is confined to the border pixels.
    pub fn gaussian_blur(&self, sigma: f32) -> GrayF32 {
        if sigma <= 0.0 {
            return self.clone();
        }
        let radius = (3.0 * sigma).ceil() as isize;
        let mut kernel: Vec<f32> = (-radius..=radius).map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp()).collect();
        let sum: f32 = kernel.iter().sum();
        kernel.iter_mut().for_each(|k| *k /= sum);
        let (w, h) = (self.width, self.height);
        let r = radius as usize;
        let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
        let mut tmp = GrayF32::new(w, h);
        for y in 0..h {
            let row = &self.data[y * w..(y + 1) * w];
            let dst = &mut tmp.data[y * w..(y + 1) * w];
            // The interior tap by tap across the row (vectorised), from zero in kernel order:
            // each pixel's sum is the one a per-pixel loop makes.
            if w > 2 * r {
                for (k, &kv) in kernel.iter().enumerate() {
                    for (o, v) in dst[r..w - r].iter_mut().zip(&row[k..w - 2 * r + k]) {
                        *o += kv * v;
                    }
                }
            }
            for x in (0..w).filter(|&x| x < r || x + r >= w) {
                let mut acc = 0.0;
                for (k, &kv) in kernel.iter().enumerate() {
                    acc += kv * row[clamp(x as isize + k as isize - radius, w)];
                }
                dst[x] = acc;
            }
        }
        // Row by row in kernel order: the same sums, in the same order, as per pixel.
        let mut out = GrayF32::new(w, h);
        for y in 0..h {
            let dst = &mut out.data[y * w..(y + 1) * w];
            for (k, &kv) in kernel.iter().enumerate() {
                let yi = clamp(y as isize + k as isize - radius, h);
                let src = &tmp.data[yi * w..(yi + 1) * w];
                for (o, v) in dst.iter_mut().zip(src) {
                    *o += kv * v;
                }
            }
        }
        out
    }

    /// Half-size image (2×2 box average), the next level of a pyramid after a blur.
    pub fn downsample_half(&self) -> GrayF32 {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        GrayF32::from_fn(w, h, |x, y| {
            let (x0, y0) = (2 * x, 2 * y);
            let g = |dx: usize, dy: usize| self.get((x0 + dx).min(self.width - 1), (y0 + dy).min(self.height - 1));
            0.25 * (g(0, 0) + g(1, 0) + g(0, 1) + g(1, 1))
        })
    }

    /// Resize by bilinear sampling (fine for moderate factors; blur first when shrinking a lot).
    pub fn resize(&self, width: usize, height: usize) -> GrayF32 {
        let sx = self.width as f32 / width as f32;
        let sy = self.height as f32 / height as f32;
        let xs: Vec<f32> = (0..width).map(|x| (x as f32 + 0.5) * sx - 0.5).collect();
        let ys: Vec<f32> = (0..height).map(|y| (y as f32 + 0.5) * sy - 0.5).collect();
        self.sample_grid(&xs, &ys)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png_bytes(w: u32, h: u32) -> Vec<u8> {
        let img = image::GrayImage::from_fn(w, h, |x, y| image::Luma([(x + y) as u8]));
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png).unwrap();
        out
    }

    #[test]
    fn decodes_png_and_gray_matches() {
        let photo = decode(&png_bytes(20, 10), &DecodeLimits::default()).unwrap();
        assert_eq!((photo.width(), photo.height()), (20, 10));
        assert!((photo.gray.get(3, 4) - 7.0).abs() < 0.6);
    }

    #[test]
    fn refuses_non_images_truncation_and_bombs() {
        assert!(matches!(decode(b"hello, not an image", &DecodeLimits::default()), Err(DecodeError::NotAnImage)));
        let bytes = png_bytes(64, 64);
        assert!(matches!(decode(&bytes[..bytes.len() / 2], &DecodeLimits::default()), Err(DecodeError::Corrupt(_))));
        let small = DecodeLimits { max_width: 32, ..DecodeLimits::default() };
        assert!(matches!(decode(&bytes, &small), Err(DecodeError::TooLarge { .. })));
        let few = DecodeLimits { max_pixels: 100, ..DecodeLimits::default() };
        assert!(matches!(decode(&bytes, &few), Err(DecodeError::TooLarge { .. })));
    }

    #[test]
    fn refuses_a_truncated_jpeg_that_the_decoder_would_pad() {
        let img = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, 90]));
        let mut jpeg = Vec::new();
        img.write_to(&mut Cursor::new(&mut jpeg), ImageFormat::Jpeg).unwrap();
        assert!(decode(&jpeg, &DecodeLimits::default()).is_ok());
        let cut = &jpeg[..jpeg.len() * 3 / 4];
        assert!(matches!(decode(cut, &DecodeLimits::default()), Err(DecodeError::Corrupt(_))));
        let real = std::fs::read(facegate_paths::shared_dir().join("data/imm/01-1m.jpg")).unwrap();
        assert!(decode(&real, &DecodeLimits::default()).is_ok());
        assert!(matches!(decode(&real[..real.len() - 2000], &DecodeLimits::default()), Err(DecodeError::Corrupt(_))));
    }

    #[test]
    fn sampling_and_blur_preserve_constants() {
        let img = GrayF32::from_fn(9, 7, |_, _| 42.0);
        assert!((img.sample(3.3, 4.7) - 42.0).abs() < 1e-4);
        assert!(img.gaussian_blur(1.5).data.iter().all(|v| (v - 42.0).abs() < 1e-3));
        let ramp = GrayF32::from_fn(9, 7, |x, _| x as f32);
        assert!((ramp.sample(2.25, 3.0) - 2.25).abs() < 1e-5);
        assert_eq!(ramp.downsample_half().width, 4);
    }

    #[test]
    fn blur_is_the_clamped_convolution_pixel_by_pixel() {
        let img = GrayF32::from_fn(23, 11, |x, y| ((x * 37 + y * 11) % 17) as f32 * 1.7);
        for sigma in [0.5, 1.0, 2.0, 4.0] {
            let radius = (3.0 * sigma as f32).ceil() as isize;
            let mut kernel: Vec<f32> = (-radius..=radius).map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp()).collect();
            let sum: f32 = kernel.iter().sum();
            kernel.iter_mut().for_each(|k| *k /= sum);
            let at = |x: isize, y: isize| img.get(x.clamp(0, 22) as usize, y.clamp(0, 10) as usize);
            let rows = GrayF32::from_fn(23, 11, |x, y| {
                kernel.iter().enumerate().fold(0.0, |acc, (k, kv)| acc + kv * at(x as isize + k as isize - radius, y as isize))
            });
            let want = GrayF32::from_fn(23, 11, |x, y| {
                let column = |k: usize| rows.get(x, (y as isize + k as isize - radius).clamp(0, 10) as usize);
                kernel.iter().enumerate().fold(0.0, |acc, (k, kv)| acc + kv * column(k))
            });
            assert_eq!(img.gaussian_blur(sigma).data, want.data, "sigma {sigma}");
        }
    }

    #[test]
    fn a_grid_of_samples_is_sample_at_each_point() {
        let img = GrayF32::from_fn(13, 9, |x, y| ((x * 31 + y * 17) % 11) as f32 * 2.3);
        let xs: Vec<f32> = (0..20).map(|i| -1.3 + i as f32 * 0.77).collect();
        let ys: Vec<f32> = (0..15).map(|j| -0.6 + j as f32 * 0.71).collect();
        let grid = img.sample_grid(&xs, &ys);
        for (j, &y) in ys.iter().enumerate() {
            for (i, &x) in xs.iter().enumerate() {
                assert_eq!(grid.get(i, j), img.sample(x, y), "({x}, {y})");
            }
        }
    }
}
