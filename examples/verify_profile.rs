//! Where a verification's CPU goes: the service's photo work (decode, then `Pipeline::analyze`)
//! split by stage, for the default fusion recognizer and dlib's network alone, loaded in the same
//! process and run over the same photos, one at a time on this thread.
//!
//! The decode and the whole call are the thread's CPU time (`/proc/thread-self/schedstat`); the
//! stages are the pipeline's own `StageTimings` (their wall time inside the same single-threaded
//! call, so they sum to about the call's CPU on an idle core). The networks' share of the
//! template stage is timed apart by calling each member network on the same chip.
//!
//!   cargo run --release --example verify_profile [-- ROUNDS]

use facegate_core::imaging::{self, DecodeLimits};
use facegate_paths::{models_dir, shared_dir};
use facegate_research::eval::thread_cpu_ns;
use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::{Recognizer, RecognizerKind};

/// Photo sets by kind: (label, paths).
fn photo_sets() -> Vec<(&'static str, Vec<std::path::PathBuf>)> {
    let data = shared_dir().join("data");
    // IMM's file names end in the person's sex (`01-1m.jpg`, `08-1f.jpg`).
    let imm = |view: u32| {
        (1..=10)
            .filter_map(|p| ["m", "f"].iter().map(|s| data.join(format!("imm/{p:02}-{view}{s}.jpg"))).find(|p| p.exists()))
            .collect::<Vec<_>>()
    };
    let lfw: Vec<_> =
        ["Aaron_Peirsol", "Aaron_Sorkin", "Abdel_Nasser_Assidi", "Abdullah_Gul", "Adrien_Brody", "Al_Gore", "Alvaro_Uribe", "Amelia_Vega"]
            .iter()
            .filter_map(|p| std::fs::read_dir(data.join("lfw").join(p)).ok())
            .filter_map(|mut d| d.next().and_then(Result::ok).map(|e| e.path()))
            .collect();
    let orl = (1..=10).map(|s| data.join(format!("orl/s{s}/1.pgm"))).collect();
    let profile = (1..=10).map(|s| data.join(format!("umist/s{s:02}/02.pgm"))).collect();
    let turned = (1..=10).map(|s| data.join(format!("umist/s{s:02}/08.pgm"))).collect();
    vec![
        ("IMM frontal 640×480", imm(1)),
        ("IMM turned 640×480", imm(3)),
        ("LFW 250×250", lfw),
        ("ORL 92×112", orl),
        ("UMIST about 45°", turned),
        ("UMIST profile", profile),
    ]
}

#[derive(Default, Clone, Copy)]
struct Costs {
    photos: usize,
    total: f64,
    decode: f64,
    detect: f64,
    landmarks: f64,
    morph: f64,
    template: f64,
    networks: [f64; 3],
    quality: f64,
    liveness: f64,
}

fn cpu_ms(f: impl FnOnce()) -> f64 {
    let t = thread_cpu_ns().expect("Linux thread CPU time");
    f();
    (thread_cpu_ns().expect("Linux thread CPU time") - t) as f64 / 1e6
}

fn profile(pipeline: &Pipeline, bytes: &[Vec<u8>], rounds: usize) -> Costs {
    let mut c = Costs::default();
    for _ in 0..rounds {
        for b in bytes {
            let mut photo = None;
            c.decode += cpu_ms(|| photo = Some(imaging::decode(b, &DecodeLimits::default()).expect("decodes")));
            let photo = photo.unwrap();
            let mut analysis = None;
            c.total += cpu_ms(|| analysis = pipeline.analyze(&photo).ok());
            let Some(a) = analysis else { continue };
            c.photos += 1;
            let t = &a.timings;
            c.detect += t.detect_ms;
            c.landmarks += t.landmarks_ms;
            c.morph += t.morph_ms;
            c.template += t.template_ms;
            c.quality += t.quality_ms;
            c.liveness += t.liveness_ms;
            match &pipeline.recognizer {
                Recognizer::Embedding(r, _) => {
                    for (i, net) in r.networks.iter().enumerate().take(3) {
                        c.networks[i] += cpu_ms(|| {
                            std::hint::black_box(r.embed_with(net, &photo.rgb, &a.landmarks.centres, a.face.points.as_ref(), None));
                        });
                    }
                }
                Recognizer::Dlib(d) => {
                    let chip = facegate_vision::embed::face_chip(&photo.rgb, &a.landmarks.centres);
                    c.networks[0] += cpu_ms(|| {
                        std::hint::black_box(d.template_and_mirror_pair(&chip));
                    });
                }
                Recognizer::Classical(_) => {}
            }
        }
    }
    c.total += c.decode;
    c
}

fn main() {
    let rounds: usize = std::env::args().nth(1).map_or(3, |r| r.parse().expect("ROUNDS is a number"));
    let load = |recognizer| {
        Pipeline::load(&PipelineConfig {
            models_dir: models_dir(),
            sfm_dir: Some(shared_dir().join("models/sfm")),
            recognizer,
            detector: Default::default(),
        })
        .expect("models (scripts/fetch-models.sh) and ../shared/models/sfm")
    };
    let pipelines = [("fusion (default)", load(RecognizerKind::Fusion)), ("deep (dlib alone)", load(RecognizerKind::Dlib))];
    println!(
        "| photos | recognizer | faces | CPU per photo (ms) | decode | detect | landmarks | 3DMM fit | template (networks) | quality | liveness |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for (label, paths) in photo_sets() {
        let bytes: Vec<Vec<u8>> = paths.iter().map(|p| std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).collect();
        for (name, pipeline) in &pipelines {
            let _warm = profile(pipeline, &bytes[..1], 1);
            let c = profile(pipeline, &bytes, rounds);
            let n = c.photos.max(1) as f64;
            let per = |x: f64| x / n;
            let networks: Vec<String> = c.networks.iter().filter(|&&x| x > 0.0).map(|&x| format!("{:.1}", per(x))).collect();
            println!(
                "| {label} | {name} | {}/{} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} ({}) | {:.1} | {:.1} |",
                c.photos / rounds,
                bytes.len(),
                c.total / (bytes.len() * rounds) as f64,
                c.decode / (bytes.len() * rounds) as f64,
                per(c.detect),
                per(c.landmarks),
                per(c.morph),
                per(c.template),
                networks.join(" + "),
                per(c.quality),
                per(c.liveness),
            );
        }
    }
}
