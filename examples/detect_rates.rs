//! YuNet's detection rates and CPU per photo on UMIST (frontal to full profile) and LFW, with its
//! input shrunk to the smallest face searched (the default) and with the full square input, in
//! one process (`facegate eval detect` measures IMM, ORL and face-free images).
//!
//! - UMIST (s01–s10, photos 01–19, 92×112): found = the largest box is at least a third of the
//!   frame wide and overlaps the frame (IoU > 0.2).
//! - LFW (every photo under `../shared/data/lfw`, 250×250): found = a box holds the photo centre.
//!
//!   cargo run --release --example detect_rates [-- MIN_FACE_PX...]

use facegate_core::geometry::Rect;
use facegate_core::imaging::GrayF32;
use facegate_detect::{DetectOptions, Detector, DetectorKind};
use facegate_paths::{models_dir, shared_dir};
use facegate_research::eval::thread_cpu_ns;

struct Tally {
    found: usize,
    photos: usize,
    cpu_ms: f64,
}

fn run(detector: &Detector, photos: &[GrayF32], found: impl Fn(&GrayF32, &[facegate_detect::Face]) -> bool) -> Tally {
    let mut t = Tally { found: 0, photos: photos.len(), cpu_ms: 0.0 };
    for gray in photos {
        let start = thread_cpu_ns().expect("Linux thread CPU time");
        let faces = detector.detect(gray);
        t.cpu_ms += (thread_cpu_ns().expect("Linux thread CPU time") - start) as f64 / 1e6;
        t.found += found(gray, &faces) as usize;
    }
    t
}

fn main() {
    let mut sizes: Vec<f32> = std::env::args().skip(1).map(|a| a.parse().expect("MIN_FACE_PX is a number")).collect();
    if sizes.is_empty() {
        sizes = vec![0.0, DetectOptions::default().yunet_min_face_px];
    }
    let data = shared_dir().join("data");
    let open = |p: &std::path::Path| facegate_core::imaging::open(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())).gray;
    let umist: Vec<GrayF32> =
        (1..=10).flat_map(|s| (1..=19).map(move |k| (s, k))).map(|(s, k)| open(&data.join(format!("umist/s{s:02}/{k:02}.pgm")))).collect();
    let lfw_photos = facegate_research::dataset::list_labelled(&data.join("lfw")).expect("../shared/data/lfw");
    let lfw: Vec<GrayF32> = lfw_photos.iter().map(|p| open(&p.image)).collect();
    println!("| min face in the input | UMIST found | UMIST CPU per photo | LFW found | LFW CPU per photo |");
    println!("| --- | --- | --- | --- | --- |");
    for px in sizes {
        let options = DetectOptions { yunet_min_face_px: px, ..DetectOptions::default() };
        let detector = Detector::load_with(&models_dir(), DetectorKind::Yunet, options).expect("models/yunet.onnx");
        // One call per image size first: each input shape is compiled on first use.
        for gray in umist.iter().take(1).chain(lfw.iter().take(1)) {
            detector.detect(gray);
        }
        let u = run(&detector, &umist, |gray, faces| {
            let frame = Rect::new(0.0, 0.0, gray.width as f32, gray.height as f32);
            faces.first().is_some_and(|f| f.rect.width >= gray.width as f32 / 3.0 && f.rect.iou(&frame) > 0.2)
        });
        let l = run(&detector, &lfw, |gray, faces| {
            let (cx, cy) = (gray.width as f32 / 2.0, gray.height as f32 / 2.0);
            faces.iter().any(|f| f.rect.x <= cx && cx <= f.rect.x + f.rect.width && f.rect.y <= cy && cy <= f.rect.y + f.rect.height)
        });
        let label = if px > 0.0 { format!("{px} px") } else { format!("full {} square", options.yunet_input_size) };
        println!(
            "| {label} | {}/{} | {:.2} ms | {}/{} | {:.2} ms |",
            u.found,
            u.photos,
            u.cpu_ms / u.photos as f64,
            l.found,
            l.photos,
            l.cpu_ms / l.photos as f64
        );
    }
}
