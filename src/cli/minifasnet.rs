//! The MiniFASNet anti-spoofing networks: `convert minifasnet` (the original `.pth` files →
//! `models/minifasnet-v2.bin`, `minifasnet-v1se.bin`) and `eval minifasnet` (their APCER, BPCER
//! and EER on NUAA, per subject).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use facegate_research::convert::minifasnet::{self as convert, ORIGINALS};
use facegate_research::liveness::minifasnet::{self as research, Measures, Row};

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
        facegate_core::model_file::write_model(&out, &file).map_err(anyhow::Error::msg).with_context(|| out.display().to_string())?;
        let written = std::fs::read(&out).with_context(|| out.display().to_string())?;
        eprintln!(
            "{}: {} ({} layers, {} parameters, {} bytes, sha256 {}) from {} ({} licence, sha256 {})",
            out.display(),
            file.name,
            file.layers.len(),
            file.parameter_count(),
            written.len(),
            facegate_vision::embed::onnx::sha256_hex(&written),
            original.file,
            convert::LICENCE,
            original.sha256
        );
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalMinifasnetArgs {
    /// NUAA's folder (`real/<subject>/*.jpg`, `print/<subject>/*.jpg`); default `<shared>/data/nuaa`.
    #[arg(long)]
    pub nuaa: Option<PathBuf>,
    /// The research cache folder, where every photo's face box is kept.
    #[arg(long, default_value = facegate_research::cache::DEFAULT_DIR)]
    pub cache: PathBuf,
    /// Threads measuring photos.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Print each row as one JSON line on stdout instead of the table.
    #[arg(long)]
    pub json: bool,
}

fn cells(m: &Measures) -> String {
    format!("{:>6.2} {:>6.2} {:>6.2}", 100.0 * m.apcer, 100.0 * m.bpcer, 100.0 * m.eer)
}

/// Each network's and the fused score's APCER and BPCER at one half and EER, per NUAA subject.
pub fn run_eval(args: EvalMinifasnetArgs) -> anyhow::Result<ExitCode> {
    let nuaa = args.nuaa.clone().unwrap_or_else(|| facegate_paths::shared_dir().join("data/nuaa"));
    let samples = facegate_research::liveness::train::list_nuaa(&nuaa)?;
    let images: Vec<PathBuf> = samples.iter().map(|s| s.image.clone()).collect();
    let progress = super::Bar::default();
    let scores = research::scores(&args.cache, &facegate_paths::models_dir(), &images, args.threads, &progress)?;
    let rows: Vec<Row> = research::nuaa_rows(&samples, &scores);
    if args.json {
        for row in &rows {
            super::print_json_line(&serde_json::to_value(row)?);
        }
        return Ok(ExitCode::SUCCESS);
    }
    println!("APCER and BPCER at a live probability of {} and EER, in %", research::THRESHOLD);
    println!("{:<8} {:>5} {:>6} {:>7} | {:^20} | {:^20} | {:^20}", "subject", "live", "print", "no face", "V2", "V1SE", "fused");
    println!("{:<30} | {:^20} | {:^20} | {:^20}", "", "APCER  BPCER    EER", "APCER  BPCER    EER", "APCER  BPCER    EER");
    for r in &rows {
        println!(
            "{:<8} {:>5} {:>6} {:>7} | {} | {} | {}",
            r.subject,
            r.live,
            r.attacks,
            r.no_face,
            cells(&r.v2),
            cells(&r.v1se),
            cells(&r.fused)
        );
    }
    Ok(ExitCode::SUCCESS)
}
