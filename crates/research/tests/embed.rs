// The network pinned to the reference implementation: `tests/data/embedding-reference.json`
// holds dlib's own embeddings (`dlib.face_recognition_model_v1.compute_face_descriptor`) of
// the chips these tests cut; `scripts/embedding-reference.sh` rebuilds it.
use std::path::PathBuf;

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::Similarity;
use facegate_nn::weights;
use facegate_nn::{Arithmetic, Embedder, Embedding, FaceChip};
use facegate_research::convert::convert_dlib;
use facegate_research::dataset::list_imm;
use facegate_vision::embed::*;

/// The reference chips: IMM photos cut with their annotated centres (frontal, turned, spot
/// light) and LFW photos' central 150×150 pixels (no resampling).
fn reference_chips() -> Vec<(String, FaceChip)> {
    let shared = facegate_paths::shared_dir();
    let imm = list_imm(&shared.join("data/imm")).unwrap();
    let mut out = Vec::new();
    for name in ["01-1m", "05-3m", "10-5m"] {
        let s = imm.iter().find(|s| s.image.file_stem().unwrap().to_string_lossy() == name).unwrap();
        let photo = facegate_core::imaging::open(&s.image).unwrap();
        let k = EyeMouthCentres::from_imm(&s.landmarks().unwrap());
        out.push((format!("imm/{name}"), face_chip(&photo.rgb, &k)));
    }
    for name in ["Hal_Sutton/Hal_Sutton_0001", "Judy_Genshaft/Judy_Genshaft_0002"] {
        let photo = facegate_core::imaging::open(&shared.join(format!("data/lfw/{name}.jpg"))).unwrap();
        let centre = Similarity { a: 1.0, b: 0.0, tx: 50.0, ty: 50.0 };
        out.push((format!("lfw/{name}"), chip::extract(&photo.rgb, &centre, CHIP_SIZE)));
    }
    out
}

#[test]
fn a_symmetric_chip_agrees_with_its_mirror_image_and_a_lopsided_one_less() {
    let embedder = load(&facegate_paths::models_dir()).unwrap();
    let (_, chip) = reference_chips().swap_remove(0);
    // The chip's left half mirrored onto its right: the chip equals its own mirror image.
    let mut symmetric = chip.clone();
    let n = symmetric.size;
    for y in 0..n {
        for x in n / 2..n {
            for k in 0..3 {
                symmetric.rgb[(y * n + x) * 3 + k] = chip.rgb[(y * n + n - 1 - x) * 3 + k];
            }
        }
    }
    assert_eq!(symmetric.mirrored(), symmetric);
    let pair = chip_mirror_pair(&embedder, &symmetric);
    assert!((pair.agreement() - 1.0).abs() < 1e-5, "{}", pair.agreement());
    assert_eq!(pair.mean(), chip_embedding(&embedder, &symmetric));
    // Half the face blacked out: the two ways disagree.
    let mut occluded = chip.clone();
    for y in 0..n {
        for x in 0..n / 2 {
            occluded.rgb[(y * n + x) * 3..(y * n + x) * 3 + 3].fill(0);
        }
    }
    let (whole, half) = (chip_mirror_pair(&embedder, &chip).agreement(), chip_mirror_pair(&embedder, &occluded).agreement());
    assert!(half < whole && whole < 1.0, "whole face {whole}, half {half}");
}

/// Float arithmetic reproduces dlib to 0.01 in distance; the 8-bit convolutions (the default
/// where the CPU has VNNI) stay within cosine 0.999 of it, a small part of the 0.6 dlib calls the
/// same person.
#[test]
fn embeddings_match_dlib_within_cosine_0_999() {
    let chips = reference_chips();
    // Rebuilding the reference: write the chips for the Python side (see the script).
    if let Some(dir) = std::env::var_os("FACEGATE_WRITE_REFERENCE_CHIPS") {
        for (name, chip) in &chips {
            let path = PathBuf::from(&dir).join(format!("{}.png", name.replace('/', "__")));
            chip.to_image().save(path).unwrap();
        }
    }
    let reference_path = facegate_paths::repository_dir().join("tests/data/embedding-reference.json");
    let reference: serde_json::Value = serde_json::from_slice(&std::fs::read(&reference_path).unwrap()).unwrap();
    let mut float_batch = Vec::new();
    for (arithmetic, max_distance) in [(Arithmetic::Float, 0.01), (Arithmetic::Int8, 0.03)] {
        let embedder = load(&facegate_paths::models_dir()).unwrap().with_arithmetic(arithmetic);
        let batch = embedder.embed_batch(&chips.iter().map(|(_, c)| c.clone()).collect::<Vec<_>>(), 2);
        if arithmetic == Arithmetic::Float {
            float_batch = batch.clone();
        } else {
            assert_ne!(batch, float_batch, "the 8-bit path ran");
        }
        for ((name, chip), from_batch) in chips.iter().zip(&batch) {
            let want: Vec<f32> = serde_json::from_value(reference["embeddings"][name].clone())
                .unwrap_or_else(|e| panic!("{name} missing from {}: {e}", reference_path.display()));
            let want = Embedding(want.try_into().expect("128 values"));
            let got = embedder.embed(chip);
            let cos = got.cosine(&want);
            assert!(cos >= 0.999, "{arithmetic:?} {name}: cosine {cos} with the reference");
            assert!(got.distance(&want) < max_distance, "{arithmetic:?} {name}: distance {}", got.distance(&want));
            assert_eq!(&got, from_batch, "{name}: the batch call computes the same as the single call");
        }
        // Different people are far apart, the same photo is not.
        assert!(batch[0].distance(&batch[3]) > 0.6);
    }
}

#[test]
fn a_file_that_is_not_dlib_is_refused() {
    assert!(
        convert_dlib(
            b"\x01\x01\x01\x05hello",
            weights::Provenance { package: "p".into(), version: "v".into(), file: "f".into(), sha256: "0".into(), licence: "l".into() }
        )
        .is_err()
    );
    let mut file = read_file(&facegate_paths::models_dir().join(weights::FILE)).unwrap();
    file.layers.swap(0, 1);
    assert!(Embedder::new(&file).is_err(), "layers out of order do not make a network");
}
