//! Simulated presentation attacks from live photos: a photo printed and held to the camera, or
//! shown on a screen, as the camera would see it. What a passive liveness model learns from NUAA's
//! prints of nine people can be checked on the attacks of other people and cameras, and the
//! reverse (a model that learned from simulated attacks, tried on NUAA's real prints).
//!
//! The geometry is kept (the attack fills the frame as the photo did), so the photo's own face key
//! points place the liveness crops; each attack's parameters are drawn from a seed, so a data set's
//! attacks are the same on every run.

use image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

/// What the live photo is turned into.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum AttackKind {
    /// Printed on paper: the ink's narrower gamut and gamma, a halftone dot screen, the paper's
    /// grain, the recapture's defocus and noise.
    Print,
    /// Shown on a screen: the pixel grid's sub-pixel stripes, moiré, the screen's gamma and colour
    /// cast, glare, refresh bands, defocus and noise.
    Screen,
}

impl AttackKind {
    pub const ALL: [AttackKind; 2] = [AttackKind::Print, AttackKind::Screen];

    pub fn name(self) -> &'static str {
        match self {
            AttackKind::Print => "simulated print",
            AttackKind::Screen => "simulated screen",
        }
    }
}

/// `photo` as the `kind` of attack, with parameters drawn from `seed`.
pub fn simulate(photo: &RgbImage, kind: AttackKind, seed: u64) -> RgbImage {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (kind as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let (w, h) = photo.dimensions();
    let mut planes: Vec<[f32; 3]> = photo.pixels().map(|p| [p[0] as f32 / 255.0, p[1] as f32 / 255.0, p[2] as f32 / 255.0]).collect();
    match kind {
        AttackKind::Print => print(&mut planes, w as usize, &mut rng),
        AttackKind::Screen => screen(&mut planes, w as usize, h as usize, &mut rng),
    }
    let image = to_image(&planes, w, h);
    let sigma = match kind {
        AttackKind::Print => rng.random_range(0.6..1.4),
        AttackKind::Screen => rng.random_range(0.4..1.0),
    };
    let blurred = image::imageops::blur(&image, sigma);
    sensor_noise(blurred, rng.random_range(0.006..0.02), &mut rng)
}

/// Ink on paper: the gamut between the paper's white (slightly warm) and the ink's black, a gamma
/// shift, a halftone screen per ink at its own angle, and the paper's grain.
fn print(px: &mut [[f32; 3]], width: usize, rng: &mut ChaCha8Rng) {
    let black = rng.random_range(0.04..0.15);
    let white = rng.random_range(0.80..0.96);
    let tint = [1.0, rng.random_range(0.95..1.0), rng.random_range(0.88..0.98)];
    let gamma = rng.random_range(0.8..1.3);
    let period = rng.random_range(2.2..4.5);
    let strength = rng.random_range(0.25..0.6);
    let angles = [15f32.to_radians(), 75f32.to_radians(), 0.0];
    let grain = Normal::new(0.0, rng.random_range(0.01..0.04)).expect("a positive spread");
    for (i, p) in px.iter_mut().enumerate() {
        let (x, y) = ((i % width) as f32, (i / width) as f32);
        let paper = 1.0 + grain.sample(rng);
        for c in 0..3 {
            let v = p[c].powf(gamma);
            // The ink's coverage (1 − v) against the screen's dot pattern at this ink's angle.
            let (s, co) = angles[c].sin_cos();
            let (u, t) = ((x * co + y * s) / period, (-x * s + y * co) / period);
            let screen = 0.5 + 0.5 * (std::f32::consts::TAU * u).cos() * (std::f32::consts::TAU * t).cos();
            let dot = if 1.0 - v > screen { 0.0 } else { 1.0 };
            let v = (1.0 - strength) * v + strength * dot;
            p[c] = ((black + (white - black) * v) * tint[c] * paper).clamp(0.0, 1.0);
        }
    }
}

/// A screen: sub-pixel stripes and the dark gaps between rows, a moiré of the grid against the
/// camera's, the screen's gamma and blue cast, a glare spot, and refresh bands.
fn screen(px: &mut [[f32; 3]], width: usize, height: usize, rng: &mut ChaCha8Rng) {
    let period = rng.random_range(2.0..4.0);
    let depth = rng.random_range(0.15..0.4);
    let moire_amp = rng.random_range(0.03..0.09);
    let moire_angle: f32 = rng.random_range(0.0..std::f32::consts::PI);
    let moire_period = rng.random_range(15.0..60.0);
    let gamma = rng.random_range(0.7..1.0);
    let cast = [rng.random_range(0.9..1.0), rng.random_range(0.95..1.02), rng.random_range(1.0..1.1)];
    let glare = rng.random_range(0.08..0.35);
    let (gx, gy) = (rng.random_range(0.0..width as f32), rng.random_range(0.0..height as f32));
    let glare_spread = rng.random_range(0.1..0.35) * width.max(height) as f32;
    let band_amp = rng.random_range(0.02..0.08);
    let band_period = rng.random_range(40.0..140.0);
    let band_phase = rng.random_range(0.0..std::f32::consts::TAU);
    let (ms, mc) = moire_angle.sin_cos();
    for (i, p) in px.iter_mut().enumerate() {
        let (x, y) = ((i % width) as f32, (i / width) as f32);
        let tau = std::f32::consts::TAU;
        let row_gap = 1.0 - 0.5 * depth * (0.5 + 0.5 * (tau * y / period).cos());
        let moire = 1.0 + moire_amp * (tau * (x * mc + y * ms) / moire_period).cos();
        let band = 1.0 + band_amp * (tau * y / band_period + band_phase).sin();
        let r2 = (x - gx).powi(2) + (y - gy).powi(2);
        let spot = glare * (-r2 / (2.0 * glare_spread * glare_spread)).exp();
        for c in 0..3 {
            let stripe = 1.0 - depth * (0.5 + 0.5 * (tau * (x / period - c as f32 / 3.0)).cos());
            let v = p[c].powf(gamma) * cast[c] * stripe * row_gap * moire * band + spot;
            p[c] = v.clamp(0.0, 1.0);
        }
    }
}

fn to_image(px: &[[f32; 3]], w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| {
        let p = px[(y * w + x) as usize];
        image::Rgb(p.map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8))
    })
}

fn sensor_noise(mut image: RgbImage, sigma: f32, rng: &mut ChaCha8Rng) -> RgbImage {
    let noise = Normal::new(0.0, sigma * 255.0).expect("a positive spread");
    for v in image.iter_mut() {
        *v = (*v as f32 + noise.sample(rng)).round().clamp(0.0, 255.0) as u8;
    }
    image
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient() -> RgbImage {
        RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 4) as u8, (y * 5) as u8, 128]))
    }

    #[test]
    fn the_same_seed_gives_the_same_attack_and_another_seed_another() {
        let photo = gradient();
        for kind in AttackKind::ALL {
            let a = simulate(&photo, kind, 7);
            assert_eq!(a.dimensions(), photo.dimensions());
            assert_eq!(a, simulate(&photo, kind, 7));
            assert_ne!(a, simulate(&photo, kind, 8));
            assert_ne!(a, photo);
        }
    }

    #[test]
    fn a_print_narrows_the_range_and_a_screen_leaves_a_periodic_grid() {
        // A white photo printed is no longer white (the paper's white, the ink's screen).
        let white = RgbImage::from_pixel(64, 48, image::Rgb([255, 255, 255]));
        let printed = simulate(&white, AttackKind::Print, 1);
        let mean = printed.iter().map(|&v| v as f64).sum::<f64>() / printed.len() as f64;
        assert!(mean < 250.0, "{mean}");
        // A flat grey shown on a screen varies along the rows (the sub-pixel stripes).
        let grey = RgbImage::from_pixel(64, 48, image::Rgb([128, 128, 128]));
        let shown = simulate(&grey, AttackKind::Screen, 1);
        let row: Vec<f64> = (0..64).map(|x| shown.get_pixel(x, 24)[1] as f64).collect();
        let m = row.iter().sum::<f64>() / 64.0;
        let spread = (row.iter().map(|v| (v - m).powi(2)).sum::<f64>() / 64.0).sqrt();
        assert!(spread > 3.0, "{spread}");
    }
}
