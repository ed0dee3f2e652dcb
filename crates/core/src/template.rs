//! What a recognizer hands the rest of the service: a template (a unit vector tagged with the
//! model version that made it) and an operating point (a decision threshold at a false match
//! rate). The store keeps templates and the service decides with operating points, neither of them
//! needing the face stages that produce them.

use serde::{Deserialize, Serialize};

/// A face template: a unit vector, tagged with the model that made it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Template {
    pub model_version: String,
    pub vector: Vec<f32>,
}

impl Template {
    /// Unit-normalise `vector` (a zero or non-finite vector becomes all zeros: it matches nothing).
    pub fn new(model_version: &str, mut vector: Vec<f32>) -> Template {
        let norm = vector.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm.is_finite() && norm > 0.0 {
            vector.iter_mut().for_each(|v| *v /= norm);
        } else {
            vector.iter_mut().for_each(|v| *v = 0.0);
        }
        Template { model_version: model_version.to_string(), vector }
    }

    /// Cosine similarity (templates are unit vectors; the norms are divided out anyway, so that
    /// hand-made vectors compare correctly). Zero when either vector is zero.
    pub fn cosine(&self, other: &Template) -> f32 {
        let (mut dot, mut na, mut nb) = (0.0f32, 0.0f32, 0.0f32);
        for (a, b) in self.vector.iter().zip(&other.vector) {
            dot += a * b;
            na += a * a;
            nb += b * b;
        }
        let denom = (na * nb).sqrt();
        if denom > 0.0 { dot / denom } else { 0.0 }
    }
}

/// A decision threshold at a false match rate: a comparison matches when `score >= threshold`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OperatingPoint {
    pub fmr: f64,
    pub threshold: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn templates_are_unit_vectors_and_a_zero_vector_matches_nothing() {
        let t = Template::new("dlda-0123abcd", vec![3.0, -4.0, 0.0]);
        assert_eq!(t.vector, vec![0.6, -0.8, 0.0]);
        assert!((t.cosine(&t) - 1.0).abs() < 1e-6);
        let zero = Template::new("v", vec![0.0; 3]);
        assert_eq!(zero.cosine(&t), 0.0);
        assert_eq!(Template::new("v", vec![f32::NAN, 1.0]).vector, vec![0.0, 0.0]);
    }
}
