//! Face-embedding networks given as ONNX files (OpenCV Zoo's SFace, or a user's own model), run
//! in pure Rust through `tract`, and described by a small [`Manifest`] kept beside the weights:
//! how the face is aligned into the network's input, how the pixels are normalised, and how many
//! values come out. The manifest is what makes a foreign network usable without Python: the
//! runtime needs nothing else from it. The network itself runs in [`facegate_nn::onnx`].

use std::path::Path;

use facegate_nn::onnx::OnnxNet;
use serde::{Deserialize, Serialize};

use super::chip;
use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, Similarity};
use facegate_nn::FaceChip;
use facegate_nn::onnx::EngineChoice;

/// The ArcFace 112×112 template of the five points (image-left eye, image-right eye, nose tip,
/// image-left and image-right mouth corner), as InsightFace aligns its training faces
/// (`insightface/utils/face_align.py`, `arcface_dst`); SFace was trained on faces aligned so too.
pub const ARCFACE_TEMPLATE: [Point; 5] =
    [[38.2946, 51.6963], [73.5318, 51.5014], [56.0252, 71.7366], [41.5493, 92.3655], [70.7299, 92.2041]];

/// The side [`ARCFACE_TEMPLATE`] is given for.
pub const ARCFACE_SIDE: usize = 112;

/// How the face is cut out for the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Alignment {
    /// The similarity taking the detector's five points to [`ARCFACE_TEMPLATE`] (scaled to the
    /// input side); without five points, the eye and mouth centres to the template's eyes and
    /// mouth-corner midpoint.
    Arcface5,
    /// The eye and mouth centres (the landmarks') onto the ArcFace template's eyes and
    /// mouth-corner midpoint, whatever the detector gave.
    ArcfaceCentres,
    /// dlib's chip (eye and mouth centres, 25% padding; [`chip::chip_to_photo`]).
    DlibChip,
}

/// Channel order of the network's input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Channels {
    Rgb,
    Bgr,
}

/// Where the weights came from (written by `facegate convert`).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Source {
    /// Registry package and version, or the user's file.
    pub package: String,
    pub member: String,
    pub licence: String,
}

/// What the runtime needs to know of an ONNX face-embedding network. Stored as JSON beside the
/// ONNX file (`<name>.json` next to `<name>.onnx`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// The network's name: `sface`, or the user's.
    pub name: String,
    pub alignment: Alignment,
    /// Side of the square input, in pixels.
    pub input_size: usize,
    pub channels: Channels,
    /// Per channel (in the input's order): value = (pixel − mean) / std, pixels 0–255.
    pub mean: [f32; 3],
    pub std: [f32; 3],
    /// Length of the embedding.
    pub output_dims: usize,
    /// Average the embedding with the mirror image's (two runs a face).
    pub mirror: bool,
    /// SHA-256 of the ONNX file: a template's version names it, and a file that differs is refused.
    pub sha256: String,
    #[serde(default)]
    pub source: Source,
}

impl Manifest {
    /// What of the manifest decides the embedding besides the weights (alignment, input,
    /// normalisation, mirror pass): a recognizer's model records it, and a manifest that differs
    /// from it is refused.
    pub fn preprocessing(&self) -> String {
        format!(
            "{:?} {} {:?} mean {:?} std {:?} mirror {}",
            self.alignment, self.input_size, self.channels, self.mean, self.std, self.mirror
        )
    }

    /// Checks that the fields describe a network this runtime can feed.
    pub fn validate(&self) -> Result<(), String> {
        if !(16..=1024).contains(&self.input_size) {
            return Err(format!("input_size {} is outside 16–1024", self.input_size));
        }
        if !(2..=4096).contains(&self.output_dims) {
            return Err(format!("output_dims {} is outside 2–4096", self.output_dims));
        }
        if self.std.iter().any(|s| !s.is_finite() || *s == 0.0) || self.mean.iter().any(|m| !m.is_finite()) {
            return Err("mean and std must be finite, std non-zero".into());
        }
        if self.name.is_empty() || !self.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_') {
            return Err(format!("name {:?} must be letters, digits, - or _", self.name));
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum OnnxError {
    #[error("{path}: {message}")]
    File { path: String, message: String },
    #[error("{path}: the network does not run as its manifest says: {message}")]
    Network { path: String, message: String },
}

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// The similarity taking the network's input pixels to photo pixels for the face with eye and
/// mouth centres `centres` and, when the detector gave them, five `points`.
pub fn input_to_photo(manifest: &Manifest, centres: &EyeMouthCentres, points: Option<&[Point; 5]>) -> Similarity {
    let side = manifest.input_size;
    match manifest.alignment {
        Alignment::DlibChip => chip::chip_to_photo(side, centres.left_eye, centres.right_eye, centres.mouth),
        Alignment::Arcface5 | Alignment::ArcfaceCentres => {
            let s = side as f32 / ARCFACE_SIDE as f32;
            let template = ARCFACE_TEMPLATE.map(|[x, y]| [x * s, y * s]);
            match points.filter(|_| manifest.alignment == Alignment::Arcface5) {
                Some(points) => Similarity::fit(&template, points, None),
                None => {
                    let [l, r, _, ml, mr] = template;
                    let mouth = [(ml[0] + mr[0]) / 2.0, (ml[1] + mr[1]) / 2.0];
                    Similarity::fit(&[l, r, mouth], &[centres.left_eye, centres.right_eye, centres.mouth], None)
                }
            }
        }
    }
}

/// An ONNX embedding network compiled for one face at a time. `Send + Sync`.
pub struct OnnxEmbedder {
    pub manifest: Manifest,
    net: OnnxNet,
}

impl OnnxEmbedder {
    /// `<dir>/<name>.onnx` with its manifest `<dir>/<name>.json`.
    pub fn load(dir: &Path, name: &str) -> Result<OnnxEmbedder, OnnxError> {
        let manifest_path = dir.join(format!("{name}.json"));
        let fail = |path: &Path, message: String| OnnxError::File { path: path.display().to_string(), message };
        let text = std::fs::read_to_string(&manifest_path).map_err(|e| fail(&manifest_path, e.to_string()))?;
        let manifest: Manifest = serde_json::from_str(&text).map_err(|e| fail(&manifest_path, e.to_string()))?;
        let onnx_path = dir.join(format!("{name}.onnx"));
        let bytes = std::fs::read(&onnx_path)
            .map_err(|e| fail(&onnx_path, format!("{e} (SFace: scripts/fetch-models.sh; any network: facegate convert)")))?;
        OnnxEmbedder::from_bytes(&bytes, manifest, &onnx_path.display().to_string())
    }

    /// Compiles `bytes` as `manifest` describes it, refused unless the bytes are the ones the
    /// manifest names and one run on a grey face gives `output_dims` finite values.
    pub fn from_bytes(bytes: &[u8], manifest: Manifest, name: &str) -> Result<OnnxEmbedder, OnnxError> {
        let file = |message: String| OnnxError::File { path: name.to_string(), message };
        manifest.validate().map_err(file)?;
        let found = sha256_hex(bytes);
        if !found.eq_ignore_ascii_case(&manifest.sha256) {
            return Err(file(format!("SHA-256 {found} is not the manifest's {}", manifest.sha256)));
        }
        let expected = manifest.output_dims;
        let (embedder, found) = OnnxEmbedder::compile(bytes, manifest, name, EngineChoice::Auto)?;
        if found != expected {
            let message = format!("{found} outputs, the manifest says {expected}");
            return Err(OnnxError::Network { path: name.to_string(), message });
        }
        Ok(embedder)
    }

    /// How many values the network gives for an input of the manifest's size (its other fields
    /// are not checked): what `facegate convert onnx-embedding` writes into a user's manifest.
    pub fn output_dims(bytes: &[u8], manifest: &Manifest, name: &str) -> Result<usize, OnnxError> {
        Ok(OnnxEmbedder::compile(bytes, manifest.clone(), name, EngineChoice::Auto)?.1)
    }

    /// [`Self::from_bytes`] on the engine `choice` allows.
    pub fn from_bytes_on(bytes: &[u8], manifest: Manifest, name: &str, choice: EngineChoice) -> Result<OnnxEmbedder, OnnxError> {
        let expected = manifest.output_dims;
        let (embedder, found) = OnnxEmbedder::compile(bytes, manifest, name, choice)?;
        if found != expected {
            return Err(OnnxError::Network { path: name.to_string(), message: format!("{found} outputs, the manifest says {expected}") });
        }
        Ok(embedder)
    }

    /// Lets go of the float weights the network no longer reads
    /// ([`OnnxNet::release_float_weights`]).
    pub fn release_float_weights(&mut self) {
        self.net.release_float_weights();
    }

    /// The same network with the own kernels computing in `arithmetic` (tract's are untouched).
    pub fn with_arithmetic(mut self, arithmetic: facegate_nn::Arithmetic) -> OnnxEmbedder {
        self.net = self.net.with_arithmetic(arithmetic);
        self
    }

    /// `facegate` when the project's own kernels run the network, `tract` otherwise.
    pub fn engine(&self) -> &'static str {
        self.net.engine()
    }

    /// The compiled network and the length of its (finite) output on a grey face.
    fn compile(bytes: &[u8], manifest: Manifest, name: &str, choice: EngineChoice) -> Result<(OnnxEmbedder, usize), OnnxError> {
        let network = |message: String| OnnxError::Network { path: name.to_string(), message };
        let side = manifest.input_size;
        let net = OnnxNet::compile(bytes, side, choice).map_err(|e| network(format!("{e:#}")))?;
        let embedder = OnnxEmbedder { manifest, net };
        let grey = FaceChip { size: side, rgb: vec![128; side * side * 3] };
        let out = embedder.run(&grey).map_err(|e| network(format!("{e:#}")))?;
        if out.is_empty() || out.iter().any(|v| !v.is_finite()) {
            return Err(network(format!("{} outputs on a grey face, not all finite", out.len())));
        }
        Ok((embedder, out.len()))
    }

    /// The network's input image of the face.
    pub fn chip(&self, photo: &image::RgbImage, centres: &EyeMouthCentres, points: Option<&[Point; 5]>) -> FaceChip {
        chip::extract(photo, &input_to_photo(&self.manifest, centres, points), self.manifest.input_size)
    }

    /// The unit embedding of a chip cut by [`Self::chip`] (mirror-averaged when the manifest says so).
    pub fn embed(&self, chip: &FaceChip) -> Vec<f32> {
        let direct = self.embed_once(chip);
        if !self.manifest.mirror {
            return direct;
        }
        let mirrored = self.embed_once(&chip.mirrored());
        facegate_core::vector::unit(direct.iter().zip(&mirrored).map(|(a, b)| a + b).collect())
    }

    /// The unit embedding of one run on `chip` (no mirror pass).
    pub fn embed_once(&self, chip: &FaceChip) -> Vec<f32> {
        // The input and output shapes were checked when the network was compiled; a failure here
        // is tract's own.
        let out = self.run(chip).unwrap_or_else(|e| panic!("{}: {e:#}", self.manifest.name));
        facegate_core::vector::unit(out)
    }

    /// One run of the network on `chip`: the raw output.
    fn run(&self, chip: &FaceChip) -> facegate_nn::onnx::TractResult<Vec<f32>> {
        let m = &self.manifest;
        let side = chip.size;
        let plane = side * side;
        let mut data = vec![0.0f32; 3 * plane];
        let order = match m.channels {
            Channels::Rgb => [0, 1, 2],
            Channels::Bgr => [2, 1, 0],
        };
        for (c, &source) in order.iter().enumerate() {
            let (mean, scale) = (m.mean[c], 1.0 / m.std[c]);
            let out = &mut data[c * plane..(c + 1) * plane];
            for (o, px) in out.iter_mut().zip(chip.rgb.chunks_exact(3)) {
                *o = (px[source] as f32 - mean) * scale;
            }
        }
        self.net.run(data, side)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest() -> Manifest {
        Manifest {
            name: "sface".into(),
            alignment: Alignment::Arcface5,
            input_size: 112,
            channels: Channels::Rgb,
            mean: [0.0; 3],
            std: [1.0; 3],
            output_dims: 128,
            mirror: false,
            sha256: String::new(),
            source: Source::default(),
        }
    }

    #[test]
    fn manifests_that_cannot_be_fed_are_refused() {
        assert!(manifest().validate().is_ok());
        assert!(Manifest { std: [1.0, 0.0, 1.0], ..manifest() }.validate().is_err());
        assert!(Manifest { input_size: 4, ..manifest() }.validate().is_err());
        assert!(Manifest { output_dims: 0, ..manifest() }.validate().is_err());
        assert!(Manifest { name: "../x".into(), ..manifest() }.validate().is_err());
    }

    #[test]
    fn five_points_map_by_their_similarity_and_three_centres_stand_in() {
        // A face whose points sit on the template scaled by 2 and shifted: the fit is that map.
        let points = ARCFACE_TEMPLATE.map(|[x, y]| [2.0 * x + 10.0, 2.0 * y + 5.0]);
        let mid = |a: Point, b: Point| [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
        let centres = EyeMouthCentres { left_eye: points[0], right_eye: points[1], mouth: mid(points[3], points[4]) };
        for given in [Some(&points), None] {
            let t = input_to_photo(&manifest(), &centres, given);
            assert!((t.scale() - 2.0).abs() < 1e-3 && t.rotation().abs() < 1e-3, "{t:?}");
            let [x, y] = t.apply(ARCFACE_TEMPLATE[0]);
            assert!((x - points[0][0]).abs() < 0.05 && (y - points[0][1]).abs() < 0.05, "{x} {y}");
        }
        // A 224-pixel input scales the template: the same face maps at half the scale.
        let t = input_to_photo(&Manifest { input_size: 224, ..manifest() }, &centres, Some(&points));
        assert!((t.scale() - 1.0).abs() < 1e-3);
    }

    #[test]
    fn manifest_round_trips_as_json_with_kebab_case_alignment() {
        let json = serde_json::to_string(&manifest()).unwrap();
        assert!(json.contains("\"alignment\":\"arcface5\""), "{json}");
        let back: Manifest = serde_json::from_str(&json).unwrap();
        assert_eq!(back, manifest());
    }

    #[test]
    fn bytes_other_than_the_manifests_are_refused_before_compiling() {
        let m = Manifest { sha256: sha256_hex(b"the real model"), ..manifest() };
        match OnnxEmbedder::from_bytes(b"another file", m, "x.onnx") {
            Err(OnnxError::File { message, .. }) => assert!(message.contains("SHA-256"), "{message}"),
            other => panic!("{:?}", other.err()),
        }
    }
}
