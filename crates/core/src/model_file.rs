//! The model-file reader and writer every trained model goes through: postcard with a leading
//! format number.

/// Write a model file: `value` serialised with postcard, its folder created when missing.
pub fn write_model<T: serde::Serialize>(path: &std::path::Path, value: &T) -> Result<(), String> {
    let bytes = postcard::to_stdvec(value).map_err(|e| e.to_string())?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    }
    std::fs::write(path, bytes).map_err(|e| e.to_string())
}

/// A model file written by [`write_model`], with its format number read ahead of the rest. Every
/// model struct starts with `format: u32` and postcard keeps field order, so the number can be read
/// before choosing the layout to decode (a loader may read older layouts too).
pub struct ModelFile {
    pub format: u32,
    bytes: Vec<u8>,
    /// What the file should be, for messages ("landmark model").
    kind: &'static str,
}

impl ModelFile {
    /// Reads `path`; the message of a failure is the loader's to wrap in its typed error.
    pub fn read(path: &std::path::Path, kind: &'static str) -> Result<ModelFile, String> {
        let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
        let (format, _) = postcard::take_from_bytes::<u32>(&bytes).map_err(|e| format!("not a {kind} ({e})"))?;
        Ok(ModelFile { format, bytes, kind })
    }

    /// The whole file decoded with the layout of `T`.
    pub fn decode<T: serde::de::DeserializeOwned>(&self) -> Result<T, String> {
        postcard::from_bytes(&self.bytes).map_err(|e| format!("not a {} ({e})", self.kind))
    }
}

/// Reads a model of the single format `format` this build reads (see [`ModelFile`]). A file that
/// does not decode is "not a `kind`"; one that decodes with another format number is refused with
/// the command that makes a current one (`retrain`).
pub fn read_model<T: serde::de::DeserializeOwned>(
    path: &std::path::Path,
    kind: &'static str,
    format: u32,
    retrain: &str,
) -> Result<T, String> {
    let file = ModelFile::read(path, kind)?;
    let model = file.decode()?;
    if file.format != format {
        return Err(format!("model format {} (expected {format}); retrain with `{retrain}`", file.format));
    }
    Ok(model)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_files_are_refused_by_format_and_by_layout() {
        let dir = std::env::temp_dir().join(format!("facegate-model-file-{}", std::process::id()));
        let path = dir.join("m.bin");
        // A (format, payload) model of format 7.
        write_model(&path, &(7u32, 1.5f32)).unwrap();
        assert_eq!(read_model::<(u32, f32)>(&path, "test model", 7, "retrain").unwrap(), (7, 1.5));
        let old = read_model::<(u32, f32)>(&path, "test model", 8, "facegate train x").unwrap_err();
        assert!(old.contains("model format 7 (expected 8)") && old.contains("facegate train x"), "{old}");
        std::fs::write(&path, [7u8]).unwrap();
        let cut = read_model::<(u32, f32)>(&path, "test model", 7, "retrain").unwrap_err();
        assert!(cut.starts_with("not a test model"), "{cut}");
        assert!(read_model::<(u32, f32)>(&dir.join("missing.bin"), "test model", 7, "retrain").is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
