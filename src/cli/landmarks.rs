use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct LandmarksArgs {
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    #[arg(long)]
    pub json: bool,
    /// Landmark model variant.
    #[arg(long, default_value = "casm", value_parser = ["asm", "sift", "casm"])]
    pub variant: String,
}

#[derive(clap::Args, Debug)]
pub struct TrainAsmArgs {
    /// IMM folder with `NN-V*.jpg` photos and `.asf` annotations.
    #[arg(long)]
    pub imm: PathBuf,
    #[arg(long, default_value = "models/asm.bin")]
    pub out: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct EvalLandmarksArgs {
    #[arg(long)]
    pub imm: PathBuf,
}

pub fn run(_args: LandmarksArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("landmarks have not landed yet")
}

pub fn run_train(_args: TrainAsmArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("ASM training has not landed yet")
}

pub fn run_eval(_args: EvalLandmarksArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("landmark evaluation has not landed yet")
}
