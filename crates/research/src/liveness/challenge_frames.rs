//! Where the frames of the challenge's attempts come from ([`Source`]) and how each is made: a
//! photo as it is or mirrored, the photo as a print held turned or bent ([`print_held`]), its
//! fitted head rendered at a yaw, or a small grey camera's frame.

use std::path::PathBuf;

use image::{Rgb, RgbImage};

use facegate_core::imaging::{self, GrayF32, Photo};
use facegate_morph::{FitOptions, Pose};
use facegate_vision::pipeline::Pipeline;

/// Where one frame of a sequence comes from: a photo as it is, its mirror image, the photo as a
/// print held turned (and bent), or its fitted head rendered at a yaw.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Source {
    File(PathBuf),
    Mirror(PathBuf),
    /// Turned by `turn` degrees about the vertical axis; bent on a cylinder of radius
    /// `bend_radius` photo widths (0: flat).
    Print {
        path: PathBuf,
        turn: i32,
        bend_radius_pct: u32,
    },
    /// The fitted head of the photo rendered at `yaw` degrees.
    Avatar {
        path: PathBuf,
        yaw: i32,
    },
    /// Another source in grey at a quarter of its size (at least 92 pixels wide): a small old
    /// camera's frame, as UMIST's.
    Grey(Box<Source>),
}

/// A photo as an opened, decoded image, mirrored, printed or rendered as `source` says.
pub fn render_source(pipeline: &Pipeline, source: &Source) -> Option<Photo> {
    match source {
        Source::File(path) => imaging::open(path).ok(),
        Source::Mirror(path) => imaging::open(path).ok().map(|p| photo_of(image::imageops::flip_horizontal(&p.rgb))),
        Source::Print { path, turn, bend_radius_pct } => {
            let photo = imaging::open(path).ok()?;
            let radius = (*bend_radius_pct > 0).then(|| *bend_radius_pct as f32 / 100.0);
            Some(photo_of(print_held(&photo.rgb, *turn as f32, radius)))
        }
        Source::Avatar { path, yaw } => {
            let photo = imaging::open(path).ok()?;
            let model = pipeline.face_model.as_ref()?;
            let points = pipeline.finder.locate(&photo.gray).ok()?.landmarks.points;
            let fit = model.fit_with(&points, photo.width(), photo.height(), &FitOptions::default()).ok()?;
            let size = photo.height().min(photo.width()) as usize;
            let pose = Pose { yaw: *yaw as f32, ..Default::default() };
            let head = model.render_posed(&photo, &fit, pose, size, size.max(512)).ok()?.image;
            Some(photo_of(on_backdrop(&head, photo.width(), photo.height())))
        }
        Source::Grey(inner) => render_source(pipeline, inner).map(|p| photo_of(grey_small(&p.rgb))),
    }
}

/// `rgb` in grey (as RGB) at a quarter of its size, at least 92 pixels wide.
fn grey_small(rgb: &RgbImage) -> RgbImage {
    let width = (rgb.width() / 4).max(92.min(rgb.width()));
    let height = (rgb.height() * width / rgb.width()).max(1);
    let small = image::imageops::resize(rgb, width, height, image::imageops::FilterType::Triangle);
    RgbImage::from_fn(width, height, |x, y| {
        let [r, g, b] = small.get_pixel(x, y).0.map(f32::from);
        let l = (0.299 * r + 0.587 * g + 0.114 * b).round().clamp(0.0, 255.0) as u8;
        Rgb([l, l, l])
    })
}

fn photo_of(rgb: RgbImage) -> Photo {
    let gray = GrayF32::from_rgb(&rgb);
    Photo { rgb, gray }
}

/// The rendered head (black where nothing was drawn) in the middle of a mid-grey frame of the
/// photo's size: the screen or print an attacker would hold up.
fn on_backdrop(head: &RgbImage, width: u32, height: u32) -> RgbImage {
    let mut out = RgbImage::from_pixel(width, height, Rgb([128, 128, 128]));
    let (ox, oy) = ((width.saturating_sub(head.width())) / 2, (height.saturating_sub(head.height())) / 2);
    for (x, y, p) in head.enumerate_pixels() {
        if p.0 != [0, 0, 0] && x + ox < width && y + oy < height {
            out.put_pixel(x + ox, y + oy, *p);
        }
    }
    out
}

/// `photo` as a sheet held in front of a camera (focal length 1.2 photo widths, the sheet at that
/// distance so that, held straight, it fills the frame as the photo does), turned `turn` degrees
/// about its vertical midline (> 0: its right edge, on the image right, away from the camera, as a
/// head turning to its own left) and, with `bend_radius` (in photo widths), bent on a vertical
/// cylinder bulging towards the camera. Forward-mapped at 3 × 3 samples per pixel; the room
/// behind is mid grey.
pub fn print_held(photo: &RgbImage, turn: f32, bend_radius: Option<f32>) -> RgbImage {
    let (w, h) = (photo.width() as f32, photo.height() as f32);
    let f = 1.2 * w;
    let (s, c) = turn.to_radians().sin_cos();
    let mut out = RgbImage::from_pixel(photo.width(), photo.height(), Rgb([128, 128, 128]));
    let mut depth = vec![f32::INFINITY; (photo.width() * photo.height()) as usize];
    const SUB: usize = 3;
    for sy in 0..photo.height() as usize * SUB {
        for sx in 0..photo.width() as usize * SUB {
            let (px, py) = ((sx as f32 + 0.5) / SUB as f32, (sy as f32 + 0.5) / SUB as f32);
            let (x, y) = (px - w / 2.0, py - h / 2.0);
            // The sheet's point: on the cylinder the arc length x becomes an angle.
            let (xs, zs) = match bend_radius {
                Some(r) => {
                    let r = r * w;
                    (r * (x / r).sin(), -r * (1.0 - (x / r).cos()))
                }
                None => (x, 0.0),
            };
            // Turned about the vertical axis: z grows away from the camera.
            let (xr, zr) = (c * xs - s * zs, s * xs + c * zs);
            let z = f + zr;
            if z <= 1.0 {
                continue;
            }
            let (u, v) = (w / 2.0 + f * xr / z, h / 2.0 + f * y / z);
            if u < 0.0 || v < 0.0 || u >= w || v >= h {
                continue;
            }
            let i = v as usize * photo.width() as usize + u as usize;
            if z < depth[i] {
                depth[i] = z;
                out.put_pixel(u as u32, v as u32, *photo.get_pixel(px as u32, py as u32));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn striped(width: u32, height: u32) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| Rgb([(x * 7 % 256) as u8, (y * 5 % 256) as u8, 200]))
    }

    #[test]
    fn a_print_held_straight_is_the_photo_and_turned_it_narrows() {
        let photo = striped(120, 90);
        assert_eq!(print_held(&photo, 0.0, None), photo, "held straight at the focal distance: the photo itself");
        let turned = print_held(&photo, 45.0, None);
        let grey = |x: u32| (0..90).all(|y| turned.get_pixel(x, y).0 == [128, 128, 128]);
        assert!(grey(119), "the receding edge no longer reaches the frame's edge");
        assert!(!grey(60), "its middle is still there");
        // Turned > 0 (as a head turning to its own left): the right half recedes, so it is narrower
        // than the left, which comes nearer.
        let width = |from: u32, to: u32| (from..to).filter(|&x| !grey(x)).count();
        assert!(width(60, 120) < width(0, 60), "{} {}", width(0, 60), width(60, 120));
        // Bent, the sheet's edges curl away and it narrows even held straight.
        let bent = print_held(&photo, 0.0, Some(0.4));
        assert_ne!(bent, photo);
        assert_eq!(bent.get_pixel(0, 45).0, [128, 128, 128]);
    }
}
