//! Templates: unit vectors in DLDA space tagged with the model version, their compact byte form,
//! cosine scores and the combination of several templates of one person.

use serde::{Deserialize, Serialize};

use super::RecognizeError;

/// A face template: a unit vector in DLDA space, tagged with the model that made it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Template {
    pub model_version: String,
    pub vector: Vec<f32>,
}

/// Magic and format number of [`Template::to_bytes`].
const MAGIC: &[u8; 4] = b"FGT1";

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

    /// `FGT1`, version length (u8), version (UTF-8), dimension (u16 LE), then the f32 LE values.
    pub fn to_bytes(&self) -> Vec<u8> {
        let version = self.model_version.as_bytes();
        let version = &version[..version.len().min(255)];
        let mut out = Vec::with_capacity(4 + 1 + version.len() + 2 + 4 * self.vector.len());
        out.extend_from_slice(MAGIC);
        out.push(version.len() as u8);
        out.extend_from_slice(version);
        out.extend_from_slice(&(self.vector.len().min(u16::MAX as usize) as u16).to_le_bytes());
        for v in self.vector.iter().take(u16::MAX as usize) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Template, RecognizeError> {
        let bad = |m: &str| RecognizeError::TemplateFormat(m.to_string());
        if bytes.len() < 7 || &bytes[..4] != MAGIC {
            return Err(bad("not a facegate template (missing FGT1 header)"));
        }
        let vlen = bytes[4] as usize;
        let rest = &bytes[5..];
        if rest.len() < vlen + 2 {
            return Err(bad("truncated model version"));
        }
        let model_version = std::str::from_utf8(&rest[..vlen]).map_err(|_| bad("model version is not UTF-8"))?.to_string();
        let dims = u16::from_le_bytes([rest[vlen], rest[vlen + 1]]) as usize;
        let data = &rest[vlen + 2..];
        if data.len() != 4 * dims {
            return Err(bad(&format!("{} bytes of values for {dims} dimensions", data.len())));
        }
        let vector = data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        Ok(Template { model_version, vector })
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

/// How the scores of a probe against several templates of one person combine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Combine {
    Max,
    Mean,
}

impl Combine {
    pub fn apply(&self, scores: impl Iterator<Item = f32>) -> Option<f32> {
        let (mut n, mut sum, mut max) = (0usize, 0.0f32, f32::NEG_INFINITY);
        for s in scores {
            n += 1;
            sum += s;
            max = max.max(s);
        }
        match (n, self) {
            (0, _) => None,
            (_, Combine::Max) => Some(max),
            (_, Combine::Mean) => Some(sum / n as f32),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn template_bytes_round_trip_and_reject_garbage() {
        let t = Template::new("dlda-0123abcd", vec![3.0, -4.0, 0.0]);
        assert_eq!(t.vector, vec![0.6, -0.8, 0.0]);
        let bytes = t.to_bytes();
        assert_eq!(bytes.len(), 4 + 1 + 13 + 2 + 12);
        assert_eq!(Template::from_bytes(&bytes).unwrap(), t);
        assert!(Template::from_bytes(&bytes[..bytes.len() - 1]).is_err());
        assert!(Template::from_bytes(b"hello world").is_err());
        assert!(Template::from_bytes(&[]).is_err());
        assert!((t.cosine(&t) - 1.0).abs() < 1e-6);
        let zero = Template::new("v", vec![0.0; 3]);
        assert_eq!(zero.cosine(&t), 0.0);
        assert_eq!(Combine::Mean.apply([0.2, 0.4].into_iter()), Some(0.3));
        assert_eq!(Combine::Max.apply([0.2, 0.4].into_iter()), Some(0.4));
        assert_eq!(Combine::Max.apply(std::iter::empty()), None);
    }
}
