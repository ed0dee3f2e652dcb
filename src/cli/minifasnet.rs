//! The MiniFASNet anti-spoofing networks: `convert minifasnet` (the original `.pth` files →
//! `models/minifasnet-v2.bin`, `minifasnet-v1se.bin`).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use crate::research::convert::minifasnet::{self as convert, ORIGINALS};

#[derive(clap::Args, Debug)]
pub struct ConvertMinifasnetArgs {
    /// The folder holding `2.7_80x80_MiniFASNetV2.pth` and `4_0_0_80x80_MiniFASNetV1SE.pth` as
    /// minivision-ai/Silent-Face-Anti-Spoofing publishes them (`resources/anti_spoof_models/`).
    #[arg(long)]
    pub input: PathBuf,
    /// Folder that receives `minifasnet-v2.bin` and `minifasnet-v1se.bin`.
    #[arg(long, default_value = "models")]
    pub output: PathBuf,
}

/// Converts both networks; each file is checked against its SHA-256 and built once before it is
/// written, so a file the runtime cannot load is never written.
pub fn run_convert(args: ConvertMinifasnetArgs) -> anyhow::Result<ExitCode> {
    for original in &ORIGINALS {
        let path = args.input.join(original.file);
        let bytes = std::fs::read(&path).with_context(|| path.display().to_string())?;
        let file = convert::convert(&bytes, original).with_context(|| path.display().to_string())?;
        let out = args.output.join(original.output);
        crate::core::model_file::write_model(&out, &file).map_err(anyhow::Error::msg).with_context(|| out.display().to_string())?;
        let written = std::fs::read(&out).with_context(|| out.display().to_string())?;
        eprintln!(
            "{}: {} ({} layers, {} parameters, {} bytes, sha256 {}) from {} ({} licence, sha256 {})",
            out.display(),
            file.name,
            file.layers.len(),
            file.parameter_count(),
            written.len(),
            crate::research::convert::wheel::sha256_hex(&written),
            original.file,
            convert::LICENCE,
            original.sha256
        );
    }
    Ok(ExitCode::SUCCESS)
}
