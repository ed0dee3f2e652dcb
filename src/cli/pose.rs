//! `facegate eval pose`: verification by pose band on UMIST, through the service's pipeline.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;

use crate::choices;
use facegate_research::eval::plot::{Chart, Scale, Series, line_chart};
use facegate_research::eval::pose::{self, Strategy};
use facegate_vision::pipeline::{CentreSource, Pipeline, PipelineConfig};

#[derive(Args, Debug)]
pub struct EvalPoseArgs {
    /// UMIST folder (one sub-folder per person, photos 01.pgm full profile … 19.pgm near frontal).
    #[arg(long)]
    pub data: Option<PathBuf>,
    #[arg(long, value_enum)]
    pub detector: Option<choices::Detector>,
    /// The recognizer (default: the service's).
    #[arg(long, value_enum)]
    pub recognizer: Option<choices::Recognizer>,
    /// Also enrol synthetic views: the enrolled head rendered at these yaws (degrees,
    /// comma-separated), each a template the probe is scored against.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub synthetic_yaws: Vec<f32>,
    /// With `--synthetic-yaws`: also score each probe against the enrolled head rendered at the
    /// synthetic yaw nearest its own (and the enrolled photo), instead of the best of all renders.
    #[arg(long)]
    pub at_probe_pose: bool,
    /// Also score with each photo's template made from its 3DMM frontal rendering when its fitted
    /// |yaw| is at least each of these (degrees, comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub frontal_beyond: Vec<f32>,
    /// Also calibrate a threshold per pose band on the other persons (5 person folds) and report
    /// the FMR and FNMR it gives on the persons left out, against one threshold for every pair.
    #[arg(long)]
    pub band_thresholds: bool,
    /// Write the match rate by probe photo number as an SVG chart.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// One JSON object per strategy instead of the Markdown tables.
    #[arg(long)]
    pub json: bool,
    /// Where the chip's eye and mouth centres come from on faces the detector gives points for:
    /// `landmarks`, `detector`, or `turned:T` (the detector's when its points show a turn ≥ T).
    #[arg(long = "keypoints")]
    pub centre_source: Option<String>,
    /// The |yaw| of the detector's five points from which the 3D-ASM is seeded by them (degrees;
    /// `off`: always the C-ASM, switched to the 3D-ASM by its own points).
    #[arg(long)]
    pub detector_seed: Option<String>,
    /// Also measure LFW's test persons and IMM's and ORL's held-out persons with the same
    /// pipeline (all pairs, one photo against one): the no-regression check.
    #[arg(long)]
    pub held_out: bool,
    /// Also measure genuine scores against yaw (0° to 90°) on 3DMM renderings of LFW's test
    /// persons, and plot them here (SVG).
    #[arg(long)]
    pub render_plot: Option<PathBuf>,
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
}

fn parse_centre_source(text: &str) -> anyhow::Result<CentreSource> {
    Ok(match text {
        "landmarks" => CentreSource::Landmarks,
        "detector" => CentreSource::Detector,
        _ => match text.strip_prefix("turned:") {
            Some(t) => CentreSource::DetectorWhenTurned(t.parse()?),
            None => anyhow::bail!("--keypoints: landmarks, detector or turned:T, not {text}"),
        },
    })
}

pub fn run_eval(args: EvalPoseArgs) -> anyhow::Result<ExitCode> {
    let data = args.data.clone().unwrap_or_else(|| facegate_paths::shared_dir().join("data/umist"));
    let photos = pose::list_umist(&data)?;
    let pipeline = pose_pipeline(&args)?;
    let threshold = pipeline.recognizer.operating_point(1e-3, 1).threshold;
    let readings = pose::read_photos(
        &pipeline,
        &photos,
        &args.synthetic_yaws,
        !args.frontal_beyond.is_empty(),
        args.threads,
        &crate::cli::Bar::default(),
    );
    let score = |p: &facegate_core::template::Template, e: &[facegate_core::template::Template]| pipeline.recognizer.score(p, e);
    let mut strategies = vec![Strategy::Own];
    if !args.synthetic_yaws.is_empty() {
        strategies.push(Strategy::WithSynthetic);
        if args.at_probe_pose {
            strategies.push(Strategy::AtProbePose);
        }
    }
    strategies.extend(args.frontal_beyond.iter().map(|&yaw| Strategy::FrontalBeyond(yaw)));
    let reports: Vec<pose::PoseReport> = strategies.iter().map(|&s| pose::report(&photos, &readings, s, threshold, &score)).collect();
    for r in &reports {
        if args.json {
            crate::cli::print_json_line(&serde_json::to_value(r)?);
        } else {
            println!("{}", r.markdown());
        }
    }
    if !args.json {
        let yaws: Vec<String> = reports[0].median_yaw_by_photo.iter().map(|y| y.map_or("–".into(), |y| format!("{y:.0}"))).collect();
        println!("median fitted |yaw| by photo 01–19: {}", yaws.join(" "));
    }
    if args.band_thresholds {
        print_band_thresholds(&pose::band_thresholds(&photos, &readings, 5, &score), args.json)?;
    }
    if args.held_out {
        for (name, set) in pose::held_out_sets(&facegate_paths::shared_dir())? {
            let readings = pose::read_photos(&pipeline, &set, &[], false, args.threads, &crate::cli::Bar::default());
            print_held_out(&pose::held_out(name, &set, &readings, threshold, &score), args.json)?;
        }
    }
    if let Some(path) = &args.render_plot {
        render_curve(&pipeline, threshold, &args, path)?;
    }
    if let Some(path) = &args.plot {
        plot_match_rates(&reports, path)?;
    }
    Ok(ExitCode::SUCCESS)
}

/// The pipeline `eval pose` reads with: the settings', with the command's recognizer, detector,
/// centre source and detector seed in place of theirs where given.
fn pose_pipeline(args: &EvalPoseArgs) -> anyhow::Result<Pipeline> {
    let mut config = crate::config::pipeline_config();
    if let Some(recognizer) = args.recognizer {
        config.recognizer = recognizer.into();
    }
    if let Some(d) = args.detector {
        config = PipelineConfig { detector: d.into(), ..config };
    }
    let mut pipeline = Pipeline::load(&config)?;
    if let Some(k) = &args.centre_source {
        pipeline.finder.centre_source = parse_centre_source(k)?;
    }
    match args.detector_seed.as_deref() {
        None => {}
        Some("off") => pipeline.finder.detector_seed_min_yaw = None,
        Some(yaw) => pipeline.finder.detector_seed_min_yaw = Some(yaw.parse()?),
    }
    Ok(pipeline)
}

/// `--band-thresholds`: the thresholds per pose band against one threshold, as JSON or a table.
fn print_band_thresholds(rows: &[pose::BandThresholdResult], json: bool) -> anyhow::Result<()> {
    if json {
        crate::cli::print_json_line(&serde_json::to_value(rows)?);
        return Ok(());
    }
    println!("thresholds for FMR 1e-3 calibrated on the other persons (5 person folds), rates on the persons left out:\n");
    println!("| pairs | genuine | impostor | per band: FMR / FNMR | one threshold: FMR / FNMR |");
    println!("|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} | {:.2}% / {:.2}% | {:.2}% / {:.2}% |",
            r.band,
            r.genuine,
            r.impostor,
            100.0 * r.fmr_band_threshold,
            100.0 * r.fnmr_band_threshold,
            100.0 * r.fmr_one_threshold,
            100.0 * r.fnmr_one_threshold
        );
    }
    Ok(())
}

/// `--held-out`: one held-out set's rates, as JSON or a line.
fn print_held_out(r: &pose::HeldOutResult, json: bool) -> anyhow::Result<()> {
    if json {
        crate::cli::print_json_line(&serde_json::to_value(r)?);
    } else {
        println!(
            "{}: {} of {} faces found, EER {:.2}%, FNMR {:.2}% at FMR 1e-3, FMR {:.4}% at the service's 1e-3 threshold",
            r.set,
            r.found,
            r.photos,
            100.0 * r.eer,
            100.0 * r.fnmr_at_fmr_1e3,
            100.0 * r.fmr_at_service_threshold
        );
    }
    Ok(())
}

/// `--plot`: each strategy's genuine match rate by UMIST probe photo.
fn plot_match_rates(reports: &[pose::PoseReport], path: &std::path::Path) -> anyhow::Result<()> {
    let series: Vec<Series> = reports
        .iter()
        .map(|r| Series {
            name: match r.strategy.as_str() {
                "own" => "photo's own template",
                "synthetic" => "with synthetic views",
                "at-probe-pose" => "enrolled head rendered at the probe's pose",
                _ => "frontal rendering beyond a yaw",
            },
            points: r.match_rate_by_photo.iter().enumerate().map(|(i, &m)| ((i + 1) as f64, m)).collect(),
        })
        .collect();
    let chart = Chart {
        title: "UMIST: genuine matches at the FMR 1e-3 threshold, probe against photos 12–19",
        x_label: "probe photo (01 full profile … 19 near frontal)",
        y_label: "share matched",
        x_range: (1.0, 19.0),
        y_range: (0.0, 1.0),
        x_scale: Scale::Linear,
        y_scale: Scale::Linear,
    };
    line_chart(path, &chart, &series)?;
    Ok(())
}

/// Genuine scores against yaw on renderings of LFW's test persons: printed, and plotted to `path`.
fn render_curve(pipeline: &Pipeline, threshold: f32, args: &EvalPoseArgs, path: &std::path::Path) -> anyhow::Result<()> {
    let sets = pose::held_out_sets(&facegate_paths::shared_dir())?;
    let lfw = &sets.iter().find(|(name, _)| name.starts_with("LFW")).expect("the LFW set").1;
    let yaws: Vec<f32> = (0..=6).map(|k| 15.0 * k as f32).collect();
    let curve = pose::render_curve(pipeline, lfw, &yaws, threshold, args.threads, &crate::cli::Bar::default());
    for p in &curve {
        if args.json {
            crate::cli::print_json_line(&serde_json::to_value(p)?);
        } else {
            println!(
                "LFW test renders at yaw {:>2}°: {} of {} found, mean genuine score {:.3}, {:.1}% match at the 1e-3 threshold",
                p.yaw,
                p.found,
                p.renders,
                p.mean_genuine,
                100.0 * p.match_rate
            );
        }
    }
    let chart = Chart {
        title: "LFW test persons: a 3DMM rendering at each yaw verified against another photo",
        x_label: "yaw of the rendering (degrees)",
        y_label: "score / share",
        x_range: (0.0, 90.0),
        y_range: (0.0, 1.0),
        x_scale: Scale::Linear,
        y_scale: Scale::Linear,
    };
    let series = [
        Series { name: "mean genuine score", points: curve.iter().map(|p| (p.yaw as f64, p.mean_genuine)).collect() },
        Series { name: "share matched at FMR 1e-3", points: curve.iter().map(|p| (p.yaw as f64, p.match_rate)).collect() },
        Series { name: "threshold at FMR 1e-3", points: vec![(0.0, threshold as f64), (90.0, threshold as f64)] },
    ];
    line_chart(path, &chart, &series)
}
