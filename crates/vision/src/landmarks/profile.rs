//! Grey-level profiles (thesis 2.3.2): `PROFILE_LEN` pixels along the normal to the contour, their
//! first derivative normalised by the sum of absolute values.

use facegate_core::geometry::Point;
use facegate_core::imaging::GrayF32;

/// Thesis 2.5.1: profiles of 17 pixels.
pub const PROFILE_LEN: usize = 17;

/// Samples along the normal for all candidates up to `radius` pixels away, reused between landmarks.
#[derive(Default)]
pub struct ProfileStrip {
    radius: usize,
    values: Vec<f32>,
}

impl ProfileStrip {
    /// Sample the image along `normal` (unit) through `center`, wide enough for the derivative of
    /// every candidate profile within `radius` pixels.
    pub fn fill(&mut self, img: &GrayF32, center: Point, normal: Point, radius: usize) {
        self.radius = radius;
        let half = (PROFILE_LEN / 2 + 1 + radius) as isize;
        self.values.clear();
        for k in -half..=half {
            let t = k as f32;
            self.values.push(img.sample(center[0] + t * normal[0], center[1] + t * normal[1]));
        }
    }

    /// The normalised derivative profile of the candidate `shift` pixels along the normal.
    pub fn profile(&self, shift: isize, out: &mut [f32; PROFILE_LEN]) {
        // values[i] is at offset i − half; the candidate's profile covers shift ± PROFILE_LEN/2.
        let half = (PROFILE_LEN / 2 + 1 + self.radius) as isize;
        let start = (shift + half - (PROFILE_LEN / 2) as isize) as usize;
        let mut sum = 0.0;
        for (k, o) in out.iter_mut().enumerate() {
            let i = start + k;
            *o = 0.5 * (self.values[i + 1] - self.values[i - 1]);
            sum += o.abs();
        }
        if sum > 1e-6 {
            out.iter_mut().for_each(|v| *v /= sum);
        }
    }
}

/// The profile at one point.
pub fn profile(img: &GrayF32, center: Point, normal: Point) -> [f32; PROFILE_LEN] {
    let mut strip = ProfileStrip::default();
    strip.fill(img, center, normal, 0);
    let mut out = [0.0; PROFILE_LEN];
    strip.profile(0, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profile_of_a_step_peaks_at_the_edge_and_shifts_with_candidates() {
        let img = GrayF32::from_fn(40, 40, |x, _| if x < 20 { 10.0 } else { 200.0 });
        let p = profile(&img, [19.5, 20.0], [1.0, 0.0]);
        let peak = p.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
        assert!((peak as isize - 8).abs() <= 1);
        assert!((p.iter().map(|v| v.abs()).sum::<f32>() - 1.0).abs() < 1e-5);
        let mut strip = ProfileStrip::default();
        strip.fill(&img, [16.5, 20.0], [1.0, 0.0], 4);
        let mut q = [0.0; PROFILE_LEN];
        strip.profile(3, &mut q);
        assert!(p.iter().zip(&q).all(|(a, b)| (a - b).abs() < 1e-5));
        // Contrast changes do not alter the normalised profile.
        let brighter = GrayF32::from_fn(40, 40, |x, y| 3.0 * img.get(x, y) + 5.0);
        let r = profile(&brighter, [19.5, 20.0], [1.0, 0.0]);
        assert!(p.iter().zip(&r).all(|(a, b)| (a - b).abs() < 1e-5));
    }
}
