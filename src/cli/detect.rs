use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct DetectArgs {
    /// Images to search (JPEG, PNG, GIF, BMP, PGM/PPM).
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    /// Print one JSON object per image, line by line.
    #[arg(long)]
    pub json: bool,
}

pub fn run(_args: DetectArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("face detection has not landed yet")
}
