//! Subject ids, parsed once: a value of [`SubjectId`] is valid.

use serde::Serialize;

/// Longest subject id accepted.
pub const MAX_SUBJECT_LEN: usize = 128;

/// A subject id: 1–128 characters of `[A-Za-z0-9._-]` (safe in URLs, logs and file names), except
/// `.` and `..`, which URL clients resolve as path segments so `/subjects/{id}` could not reach
/// them. Made only by [`SubjectId::parse`], so a value of this type is valid.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(transparent)]
pub struct SubjectId(String);

/// Why a string is not a [`SubjectId`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("subject id {shown:?} is invalid: 1 to {MAX_SUBJECT_LEN} characters from A-Z a-z 0-9 . _ -, not . or ..")]
pub struct InvalidSubjectId {
    /// The start of the refused id (40 characters at most).
    pub shown: String,
}

impl SubjectId {
    pub fn parse(id: &str) -> Result<SubjectId, InvalidSubjectId> {
        let ok_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-');
        if id.is_empty() || id.len() > MAX_SUBJECT_LEN || !id.chars().all(ok_char) || id == "." || id == ".." {
            return Err(InvalidSubjectId { shown: id.chars().take(40).collect() });
        }
        Ok(SubjectId(id.to_string()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for SubjectId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subject_ids_are_checked_once() {
        for ok in ["a", "alice", "A-1_b.c", &"x".repeat(MAX_SUBJECT_LEN)] {
            assert_eq!(SubjectId::parse(ok).unwrap().as_str(), ok);
        }
        for bad in ["", "a b", "ä", "a/b", "../x", &"x".repeat(MAX_SUBJECT_LEN + 1)] {
            assert!(SubjectId::parse(bad).is_err(), "{bad}");
        }
    }
}
