// SFace run by tract pinned to the reference runtime (the two JPEG decoders differ by a grey level
// here and there, hence 0.999): `tests/data/sface-reference.json` holds
// onnxruntime's embeddings of the central 112×112 pixels of three LFW photos;
// `scripts/sface-reference.sh` rebuilds it.
use facegate_core::geometry::Similarity;
use facegate_nn::Arithmetic;
use facegate_nn::onnx::EngineChoice;
use facegate_vision::embed::chip;
use facegate_vision::embed::onnx::OnnxEmbedder;

fn reference() -> serde_json::Value {
    let path = facegate_paths::repository_dir().join("tests/data/sface-reference.json");
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn central_chip(photo: &str) -> facegate_nn::FaceChip {
    let rgb = facegate_core::imaging::open(&facegate_paths::shared_dir().join(format!("data/lfw/{photo}.jpg"))).unwrap().rgb;
    chip::extract(&rgb, &Similarity { a: 1.0, b: 0.0, tx: 69.0, ty: 69.0 }, 112)
}

/// Floats within cosine 0.999 of onnxruntime; the 8-bit convolutions (the default where the CPU
/// has VNNI) within 0.998.
#[test]
fn embeddings_match_onnxruntime_within_cosine_0_999() {
    let reference = reference();
    let embeddings = reference["embeddings"].as_object().unwrap();
    assert_eq!(embeddings.len(), 3);
    let mut ours = Vec::new();
    for (arithmetic, bound) in [(Arithmetic::Int8, 0.998), (Arithmetic::Float, 0.999)] {
        let network = OnnxEmbedder::load(&facegate_paths::models_dir(), "sface").unwrap().with_arithmetic(arithmetic);
        ours.clear();
        for (photo, expected) in embeddings {
            let expected: Vec<f32> = expected.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
            let e = network.embed_once(&central_chip(photo));
            let cosine: f32 = e.iter().zip(&expected).map(|(a, b)| a * b).sum();
            assert!(cosine > bound, "{arithmetic:?} {photo}: cosine {cosine} with onnxruntime's embedding");
            ours.push((photo.clone(), e));
        }
    }
    // The same person's two photos are closer than either is to another person's.
    let cos = |a: &str, b: &str| {
        let (x, y) = (&ours.iter().find(|o| o.0 == a).unwrap().1, &ours.iter().find(|o| o.0 == b).unwrap().1);
        x.iter().zip(y).map(|(p, q)| p * q).sum::<f32>()
    };
    let same = cos("Hal_Sutton/Hal_Sutton_0001", "Hal_Sutton/Hal_Sutton_0002");
    assert!(same > cos("Hal_Sutton/Hal_Sutton_0001", "Judy_Genshaft/Judy_Genshaft_0002"), "{same}");
}

#[test]
fn a_manifest_naming_another_file_is_refused() {
    let dir = facegate_paths::models_dir();
    let mut manifest: facegate_vision::embed::onnx::Manifest =
        serde_json::from_str(&std::fs::read_to_string(dir.join("sface.json")).unwrap()).unwrap();
    manifest.output_dims = 512;
    let bytes = std::fs::read(dir.join("sface.onnx")).unwrap();
    let err = OnnxEmbedder::from_bytes(&bytes, manifest, "sface.onnx").err().unwrap();
    assert!(err.to_string().contains("128 outputs, the manifest says 512"), "{err}");
}

/// In floats the own kernels agree with tract to rounding; in 8-bit convolutions (the default
/// where the CPU has VNNI) to the quantisation (cosine 0.9990 measured).
#[test]
fn the_own_kernels_run_sface_and_agree_with_tract() {
    let dir = facegate_paths::models_dir();
    let own = OnnxEmbedder::load(&dir, "sface").unwrap();
    assert_eq!(own.engine(), "facegate", "SFace is a plain chain of layers: the own kernels take it");
    let bytes = std::fs::read(dir.join("sface.onnx")).unwrap();
    let tract = OnnxEmbedder::from_bytes_on(&bytes, own.manifest.clone(), "sface.onnx", EngineChoice::Tract).unwrap();
    assert_eq!(tract.engine(), "tract");
    let int8 = OnnxEmbedder::from_bytes(&bytes, own.manifest.clone(), "sface.onnx").unwrap().with_arithmetic(Arithmetic::Int8);
    let float = own.with_arithmetic(Arithmetic::Float);
    for photo in ["Hal_Sutton/Hal_Sutton_0001", "Judy_Genshaft/Judy_Genshaft_0002"] {
        let chip = central_chip(photo);
        let reference = tract.embed_once(&chip);
        let cosine = |e: Vec<f32>| e.iter().zip(&reference).map(|(x, y)| x * y).sum::<f32>();
        let (f, i) = (cosine(float.embed_once(&chip)), cosine(int8.embed_once(&chip)));
        assert!(f > 0.99999, "{photo}: float {f}");
        assert!(i > 0.998 && i < 0.99999, "{photo}: 8-bit {i} (a value of 1 would mean the 8-bit path did not run)");
    }
}

/// The service's recognizers let go of the float weights of the layers computing in integers:
/// the embeddings stay the same bits, and such a network stays in integers when asked for floats.
#[test]
fn releasing_the_float_weights_changes_no_bit_of_an_integer_network() {
    let dir = facegate_paths::models_dir();
    let int8 = OnnxEmbedder::load(&dir, "sface").unwrap().with_arithmetic(Arithmetic::Int8);
    let mut lean = OnnxEmbedder::load(&dir, "sface").unwrap().with_arithmetic(Arithmetic::Int8);
    lean.release_float_weights();
    let float = OnnxEmbedder::load(&dir, "sface").unwrap().with_arithmetic(Arithmetic::Float);
    let chip = central_chip("Hal_Sutton/Hal_Sutton_0001");
    let reference = int8.embed_once(&chip);
    assert_eq!(lean.embed_once(&chip), reference);
    let lean = lean.with_arithmetic(Arithmetic::Float);
    assert_eq!(lean.embed_once(&chip), reference, "no floats to compute with: it stays in integers");
    assert_ne!(float.embed_once(&chip), reference, "the control: floats and integers differ");
    // dlib's network the same way.
    let file = facegate_vision::embed::read_file(&dir.join(facegate_nn::weights::FILE)).unwrap();
    let dlib = facegate_nn::Embedder::new(&file).unwrap().with_arithmetic(Arithmetic::Int8);
    let mut dlib_lean = facegate_nn::Embedder::new(&file).unwrap().with_arithmetic(Arithmetic::Int8);
    dlib_lean.release_float_weights();
    let chip = chip::extract(
        &facegate_core::imaging::open(&facegate_paths::shared_dir().join("data/lfw/Hal_Sutton/Hal_Sutton_0001.jpg")).unwrap().rgb,
        &Similarity { a: 0.6, b: 0.0, tx: 50.0, ty: 50.0 },
        150,
    );
    assert_eq!(dlib.embed(&chip).0, dlib_lean.embed(&chip).0);
}

#[test]
#[ignore = "a timing probe, not a test: cargo test --release -p facegate-research --test sface -- --ignored --nocapture"]
fn timing_probe() {
    let dir = facegate_paths::models_dir();
    let own = OnnxEmbedder::load(&dir, "sface").unwrap();
    let bytes = std::fs::read(dir.join("sface.onnx")).unwrap();
    let tract = OnnxEmbedder::from_bytes_on(&bytes, own.manifest.clone(), "sface.onnx", EngineChoice::Tract).unwrap();
    let chip = central_chip("Hal_Sutton/Hal_Sutton_0001");
    for network in [&own, &tract] {
        network.embed_once(&chip);
        let t = std::time::Instant::now();
        for _ in 0..20 {
            network.embed_once(&chip);
        }
        eprintln!("sface on {}: {:.1} ms a run", network.engine(), t.elapsed().as_secs_f64() * 1000.0 / 20.0);
    }
    // Another converted network, for the docs' bring-your-own numbers: ONNX_PROBE=<dir>/<name>.
    if let Some((dir, name)) = std::env::var("ONNX_PROBE").ok().as_deref().and_then(|p| p.rsplit_once('/')) {
        let network = OnnxEmbedder::load(std::path::Path::new(dir), name).unwrap();
        let chip = chip::extract(
            &facegate_core::imaging::open(&facegate_paths::shared_dir().join("data/lfw/Hal_Sutton/Hal_Sutton_0001.jpg")).unwrap().rgb,
            &Similarity { a: 1.0, b: 0.0, tx: 69.0, ty: 69.0 },
            network.manifest.input_size,
        );
        network.embed_once(&chip);
        let t = std::time::Instant::now();
        for _ in 0..20 {
            network.embed_once(&chip);
        }
        eprintln!("{name} on {}: {:.1} ms a run", network.engine(), t.elapsed().as_secs_f64() * 1000.0 / 20.0);
    }
}
