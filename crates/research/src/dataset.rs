//! Readers for the annotated face sets the project trains and measures on: IMM `.asf` shapes,
//! IMM and ORL folder layouts, and plain labelled folders (one folder per person).
//! The 58-point layout and the eye and mouth centres are the stages' own types
//! ([`facegate_core::face`]); callers import them from there.

use std::path::{Path, PathBuf};

use facegate_core::face::IMM_POINTS;
use facegate_core::geometry::Point;

/// One annotated point of an `.asf` file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AsfPoint {
    pub path: u32,
    pub kind: u32,
    /// Position in pixels (the file stores it relative to width and height).
    pub xy: Point,
    pub index: u32,
    pub from: u32,
    pub to: u32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct AsfShape {
    pub points: Vec<AsfPoint>,
    /// The host image named at the end of the file, if any.
    pub host_image: Option<String>,
}

impl AsfShape {
    pub fn xy(&self) -> Vec<Point> {
        self.points.iter().map(|p| p.xy).collect()
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: {message}")]
    Format { path: String, message: String },
}

/// Parse an IMM `.asf` file. Coordinates are relative; `width` and `height` scale them to pixels.
/// Lines with 7 or more columns are points; extra columns are ignored.
pub fn parse_asf(text: &str, width: f32, height: f32, path_for_errors: &str) -> Result<AsfShape, DatasetError> {
    let fmt = |message: String| DatasetError::Format { path: path_for_errors.to_string(), message };
    let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')).collect();
    let count: usize =
        lines.first().ok_or_else(|| fmt("empty file".into()))?.parse().map_err(|_| fmt("first value is not the point count".into()))?;
    let mut points = Vec::with_capacity(count);
    for line in &lines[1..] {
        if points.len() == count {
            break;
        }
        let cols: Vec<&str> = line.split_whitespace().collect();
        if cols.len() < 7 {
            return Err(fmt(format!("point line has {} columns, expected 7 or more: {line:?}", cols.len())));
        }
        let int = |i: usize| cols[i].parse::<u32>().map_err(|_| fmt(format!("column {} is not an integer in {line:?}", i + 1)));
        let num = |i: usize| cols[i].parse::<f32>().map_err(|_| fmt(format!("column {} is not a number in {line:?}", i + 1)));
        points.push(AsfPoint {
            path: int(0)?,
            kind: int(1)?,
            xy: [num(2)? * width, num(3)? * height],
            index: int(4)?,
            from: int(5)?,
            to: int(6)?,
        });
    }
    if points.len() != count {
        return Err(fmt(format!("expected {count} points, found {}", points.len())));
    }
    let host_image = lines.get(1 + count).map(|s| s.to_string());
    Ok(AsfShape { points, host_image })
}

pub fn read_asf(path: &Path, width: f32, height: f32) -> Result<AsfShape, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io { path: path.display().to_string(), source })?;
    parse_asf(&text, width, height, &path.display().to_string())
}

/// One photo of the IMM database: `NN-V[m|f].jpg` with its `.asf` beside it.
#[derive(Debug, Clone, PartialEq)]
pub struct ImmSample {
    pub person: u32,
    /// 1–2 frontal, 3–4 rotated about ±30°, 5 spot light, 6 free.
    pub view: u32,
    pub image: PathBuf,
    pub asf: PathBuf,
}

impl ImmSample {
    /// Read the 58 landmarks in pixels (IMM photos are 640×480, but the image size is read from
    /// the file header to be safe).
    pub fn landmarks(&self) -> Result<Vec<Point>, DatasetError> {
        let (w, h) = image::image_dimensions(&self.image)
            .map_err(|e| DatasetError::Format { path: self.image.display().to_string(), message: e.to_string() })?;
        let shape = read_asf(&self.asf, w as f32, h as f32)?;
        if shape.points.len() != IMM_POINTS {
            return Err(DatasetError::Format {
                path: self.asf.display().to_string(),
                message: format!("{} points, expected 58", shape.points.len()),
            });
        }
        Ok(shape.xy())
    }

    pub fn is_frontal(&self) -> bool {
        matches!(self.view, 1 | 2 | 5 | 6)
    }
}

/// Parse `NN-V*.ext` into (person, view).
pub fn parse_imm_name(file_name: &str) -> Option<(u32, u32)> {
    let stem = file_name.split('.').next()?;
    let (person, rest) = stem.split_once('-')?;
    let view = rest.chars().next()?.to_digit(10)?;
    Some((person.parse().ok()?, view))
}

/// All IMM samples in a folder (those with both a `.jpg` and an `.asf`), sorted by person and view.
pub fn list_imm(dir: &Path) -> Result<Vec<ImmSample>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io { path: dir.display().to_string(), source })?;
    let mut out = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().to_string();
        if !name.to_ascii_lowercase().ends_with(".jpg") {
            continue;
        }
        let Some((person, view)) = parse_imm_name(&name) else { continue };
        let asf = path.with_extension("asf");
        if asf.exists() {
            out.push(ImmSample { person, view, image: path, asf });
        }
    }
    out.sort_by(|a, b| (a.person, a.view).cmp(&(b.person, b.view)));
    Ok(out)
}

/// The project's person-disjoint split of IMM persons 01–30: every fifth person (5, 10, … 30) and
/// persons 1–3 are never used for training anything we report accuracy on.
/// Test persons: 1, 2, 3, 5, 10, 15, 20, 25, 30 (9 people); the other 21 train. Persons beyond
/// 30 (IMM's and ORL's 31–40, kept out of `../shared` for others to measure with) are test
/// persons wherever they are put: nothing trains on them.
pub fn imm_is_test_person(person: u32) -> bool {
    person <= 3 || person % 5 == 0 || person > 30
}

/// UMIST's person-disjoint split: s06–s10 are never trained on; s01–s05 train the rendered-head
/// detector (the one model that sees UMIST's small grey camera, `facegate train render`).
/// `person` is the folder name (`s01` … `s10`); a name that is not one is a test person.
pub fn umist_is_test_person(person: &str) -> bool {
    person.strip_prefix('s').and_then(|n| n.parse::<u32>().ok()).is_none_or(|n| n > 5)
}

/// Which part of the person-disjoint split a person belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Split {
    /// Trains projections.
    Train,
    /// Sets thresholds (LFW only: IMM and ORL calibrate on their held-out persons, as the
    /// classical model does).
    Calibration,
    /// Held out of everything that is reported as accuracy on people never seen.
    Test,
}

/// One IMM photo: `<dir>/<person>-<view>m.jpg` (or `f` for the women); `None` when absent.
pub fn imm_photo(dir: &Path, person: u32, view: u32) -> Option<PathBuf> {
    ["m", "f"].iter().map(|g| dir.join(format!("{person:02}-{view}{g}.jpg"))).find(|p| p.is_file())
}

/// LFW's person-disjoint split, by a hash of the person's name: 60% train, 20% calibration,
/// 20% test. Stable across machines and independent of the listing order.
pub fn lfw_split(person: &str) -> Split {
    use sha2::Digest;
    let h = sha2::Sha256::digest(person.as_bytes());
    match h[0] % 10 {
        0..=5 => Split::Train,
        6 | 7 => Split::Calibration,
        _ => Split::Test,
    }
}

/// A labelled image for recognition training and evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelledImage {
    /// Identity label, unique across sources (e.g. `imm-07`, `orl-s12`, or the folder name).
    pub label: String,
    pub image: PathBuf,
}

const IMAGE_EXTENSIONS: [&str; 7] = ["jpg", "jpeg", "png", "gif", "pgm", "ppm", "bmp"];

fn is_image(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// List labelled images under `dir`: either IMM names `NN-V*.jpg` in the folder itself (label
/// `<prefix>-NN`), or one sub-folder per person (label `<prefix>-<folder>`). `prefix` defaults to
/// the folder's name, so that sets read together do not mix identities.
pub fn list_labelled(dir: &Path) -> Result<Vec<LabelledImage>, DatasetError> {
    let prefix = dir.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io { path: dir.display().to_string(), source })?;
    let mut out = Vec::new();
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            let person = entry.file_name().to_string_lossy().to_string();
            let sub = std::fs::read_dir(&path).map_err(|source| DatasetError::Io { path: path.display().to_string(), source })?;
            for img in sub.flatten().map(|e| e.path()).filter(|p| is_image(p)) {
                out.push(LabelledImage { label: format!("{prefix}-{person}"), image: img });
            }
        } else if is_image(&path) {
            if let Some((person, _)) = parse_imm_name(&entry.file_name().to_string_lossy()) {
                out.push(LabelledImage { label: format!("{prefix}-{person:02}"), image: path });
            }
        }
    }
    out.sort_by(|a, b| (&a.label, &a.image).cmp(&(&b.label, &b.image)));
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use facegate_core::face::{EYE_IMAGE_LEFT, EYE_IMAGE_RIGHT, EyeMouthCentres, JAW, MOUTH, NOSE};

    pub(crate) fn shared_dir() -> PathBuf {
        facegate_paths::shared_dir()
    }

    #[test]
    fn imm_keeps_nine_of_its_thirty_persons_and_everyone_beyond_them_for_testing() {
        let test: Vec<u32> = (1..=40).filter(|&p| imm_is_test_person(p)).collect();
        assert_eq!(test, [1, 2, 3, 5, 10, 15, 20, 25, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40]);
    }

    #[test]
    fn umist_splits_its_ten_persons_in_halves() {
        let test: Vec<bool> = (1..=10).map(|n| umist_is_test_person(&format!("s{n:02}"))).collect();
        assert_eq!(test, [false, false, false, false, false, true, true, true, true, true]);
        assert!(umist_is_test_person("readme"), "a name that is not a person's is never trained on");
    }

    #[test]
    fn asf_parser_reads_points_and_tolerates_extra_columns() {
        let text = "# header\n3\n0 4 0.5 0.25 0 0 1 extra\n0 4 0.1 0.2 1 0 2\n1 0 1.0 1.0 2 1 2 9 9\n\nhost.jpg\n";
        let shape = parse_asf(text, 640.0, 480.0, "t").unwrap();
        assert_eq!(shape.points.len(), 3);
        assert_eq!(shape.points[0].xy, [320.0, 120.0]);
        assert_eq!(shape.points[2].path, 1);
        assert_eq!(shape.host_image.as_deref(), Some("host.jpg"));
        assert!(parse_asf("2\n0 4 0.5 0.25 0 0 1\n", 1.0, 1.0, "t").is_err());
        assert!(parse_asf("1\n0 4 0.5\n", 1.0, 1.0, "t").is_err());
    }

    #[test]
    fn reads_real_imm_files_with_the_58_point_template() {
        let samples = list_imm(&shared_dir().join("data/imm")).unwrap();
        assert_eq!(samples.len(), 180);
        let s = &samples[0];
        assert_eq!((s.person, s.view), (1, 1));
        let pts = s.landmarks().unwrap();
        assert_eq!(pts.len(), IMM_POINTS);
        let k = EyeMouthCentres::from_imm(&pts);
        // Eyes above the mouth, the image-left eye left of the image-right one, jaw below the eyes.
        assert!(k.left_eye[0] < k.right_eye[0]);
        assert!(k.mouth[1] > k.left_eye[1] + 40.0);
        assert!(pts[6][1] > k.mouth[1]);
        let shape = read_asf(&s.asf, 640.0, 480.0).unwrap();
        assert_eq!(shape.points[JAW.start].path, 0);
        assert_eq!(shape.points[EYE_IMAGE_RIGHT.start].path, 1);
        assert_eq!(shape.points[EYE_IMAGE_LEFT.start].path, 2);
        assert_eq!(shape.points[MOUTH.start].path, 5);
        assert_eq!(shape.points[NOSE.start].path, 6);
    }

    #[test]
    fn labelled_listing_handles_imm_names_and_person_folders() {
        let imm = list_labelled(&shared_dir().join("data/imm")).unwrap();
        assert_eq!(imm.len(), 180);
        assert_eq!(imm[0].label, "imm-01");
        let orl = list_labelled(&shared_dir().join("data/orl")).unwrap();
        assert_eq!(orl.len(), 300);
        assert!(orl.iter().any(|l| l.label == "orl-s12"));
    }
}
