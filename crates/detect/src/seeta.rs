//! SeetaFace frontal detector (funnel-structured cascade, Wu et al. 2016) through `rustface`,
//! measured against the Viola–Jones cascades.
//!
//! `rustface`'s detector takes `&mut self` and is not `Send`, so a fresh one is built from the
//! parsed model for every call (a clone of the ~1.2 MB model; its cost is in `docs/detection.md`).

use rustface::Model;

use super::{DetectError, Face};
use facegate_core::geometry::Rect;
use facegate_core::imaging::GrayF32;

pub struct SeetaDetector {
    model: Model,
    /// Detection score threshold (the crate's example uses 2.0).
    pub score_threshold: f64,
    /// Pyramid scale factor between levels (0.8 in the crate's example).
    pub pyramid_factor: f32,
    /// Sliding window step in pixels.
    pub step: u32,
}

impl SeetaDetector {
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<SeetaDetector, DetectError> {
        let model = rustface::read_model(bytes).map_err(|e| DetectError::Model { path: name.to_string(), message: e.to_string() })?;
        Ok(SeetaDetector { model, score_threshold: 2.0, pyramid_factor: 0.8, step: 4 })
    }

    /// Faces of at least `min_size` pixels (SeetaFace's window is 40 px; it cannot go below 20).
    pub fn detect(&self, gray: &GrayF32, min_size: f32) -> Vec<Face> {
        // The funnel's window is 40 pixels: smaller images hold no face it can see.
        if gray.width < 20 || gray.height < 20 {
            return Vec::new();
        }
        let bytes: Vec<u8> = gray.data.iter().map(|&v| v.round().clamp(0.0, 255.0) as u8).collect();
        let mut detector = rustface::create_detector_with_model(self.model.clone());
        detector.set_min_face_size((min_size.round() as u32).clamp(20, gray.width.min(gray.height) as u32));
        detector.set_score_thresh(self.score_threshold);
        detector.set_pyramid_scale_factor(self.pyramid_factor);
        detector.set_slide_window_step(self.step, self.step);
        let image = rustface::ImageData::new(&bytes, gray.width as u32, gray.height as u32);
        detector
            .detect(&image)
            .into_iter()
            .map(|f| {
                let b = f.bbox();
                Face {
                    rect: Rect::new(b.x() as f32, b.y() as f32, b.width() as f32, b.height() as f32),
                    score: f.score() as f32,
                    points: None,
                }
            })
            .collect()
    }
}
