use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    pub image: PathBuf,
    /// Output file: `.glb` (glTF binary) or `.obj` (OBJ + MTL + PNG).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct FrontalizeArgs {
    pub image: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run_reconstruct(_args: ReconstructArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("3DMM reconstruction has not landed yet")
}

pub fn run_frontalize(_args: FrontalizeArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("3DMM frontalisation has not landed yet")
}
