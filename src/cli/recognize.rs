use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    pub a: PathBuf,
    pub b: PathBuf,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct TrainDldaArgs {
    /// Labelled folders: a folder per person, or IMM names `NN-V*.jpg`.
    #[arg(long, num_args = 1.., required = true)]
    pub data: Vec<PathBuf>,
    #[arg(long, default_value = "models/dlda.bin")]
    pub out: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct EvalPairsArgs {
    /// CSV whose first two columns are image paths relative to --images (header `file_x,file_y,...`).
    #[arg(long)]
    pub pairs: PathBuf,
    #[arg(long)]
    pub images: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct EvalVerifyArgs {
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct EvalIdentifyArgs {}

pub fn run_compare(_args: CompareArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("recognition has not landed yet")
}

pub fn run_train(_args: TrainDldaArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("DLDA training has not landed yet")
}

pub fn run_eval_pairs(_args: EvalPairsArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("pair evaluation has not landed yet")
}

pub fn run_eval_verify(_args: EvalVerifyArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("verification evaluation has not landed yet")
}

pub fn run_eval_identify(_args: EvalIdentifyArgs) -> anyhow::Result<ExitCode> {
    anyhow::bail!("identification evaluation has not landed yet")
}
