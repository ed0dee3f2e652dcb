//! How the scores of a probe against several templates of one person combine.
//! [`facegate_core::template::Template`] itself
//! lives in facegate-core, so that the store and the service need nothing of the stages.

use serde::{Deserialize, Serialize};

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
    fn scores_combine_by_max_or_mean() {
        assert_eq!(Combine::Mean.apply([0.2, 0.4].into_iter()), Some(0.3));
        assert_eq!(Combine::Max.apply([0.2, 0.4].into_iter()), Some(0.4));
        assert_eq!(Combine::Max.apply(std::iter::empty()), None);
    }
}
