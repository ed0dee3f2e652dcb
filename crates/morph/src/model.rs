//! Reader for the eos model files (cereal binary archives): `sfm_shape_3448.bin` and
//! `expression_blendshapes_3448.bin`, plus the text companions (contours, symmetry, iBUG mapping).
//!
//! Layout (eos `MorphableModel`, class version 1): `u32` version, shape `PcaModel`, colour
//! `PcaModel`, texture coordinates. A `PcaModel` is `mean`, `orthonormal_pca_basis`, `eigenvalues`
//! (Eigen matrices: `i32 rows, i32 cols`, then `rows*cols` little-endian `f32`, column-major) and a
//! `triangle_list` (`u64` length, then `[i32; 3]` each). Texture coordinates: `u64` length, then
//! `(f64 u, f64 v)` pairs.

use std::path::Path;

use super::MorphError;

/// The shape PCA model of the Surrey Face Model, as stored by eos.
#[derive(Debug, Clone)]
pub struct ShapeModel {
    /// Mean shape, `3 * vertices` values (x, y, z per vertex, millimetres; x to the subject's
    /// left = image right for a frontal face, y up, z towards the camera).
    pub mean: Vec<f32>,
    /// Orthonormal PCA basis, column-major `3*vertices × components`.
    pub basis: Vec<f32>,
    pub eigenvalues: Vec<f32>,
    pub triangles: Vec<[u32; 3]>,
    /// Texture coordinates per vertex, in [0, 1], v downwards (image convention).
    pub texcoords: Vec<[f32; 2]>,
}

impl ShapeModel {
    pub fn vertex_count(&self) -> usize {
        self.mean.len() / 3
    }

    pub fn component_count(&self) -> usize {
        self.eigenvalues.len()
    }
}

/// One expression blendshape: a per-vertex offset added to the shape.
#[derive(Debug, Clone)]
pub struct Blendshape {
    pub name: String,
    pub deformation: Vec<f32>,
}

struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    path: &'a str,
}

impl<'a> Cursor<'a> {
    fn err(&self, message: impl Into<String>) -> MorphError {
        MorphError::Model { path: self.path.to_string(), message: format!("{} (at byte {})", message.into(), self.pos) }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], MorphError> {
        if n > self.bytes.len() - self.pos {
            return Err(self.err(format!("truncated file: {n} more bytes expected")));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn u32(&mut self) -> Result<u32, MorphError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }

    fn i32(&mut self) -> Result<i32, MorphError> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }

    fn u64(&mut self) -> Result<u64, MorphError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }

    fn f64(&mut self) -> Result<f64, MorphError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }

    /// A length that must fit in what is left of the file (`unit` bytes per element).
    fn length(&mut self, unit: usize) -> Result<usize, MorphError> {
        let n = self.u64()?;
        let left = (self.bytes.len() - self.pos) as u64;
        if n.saturating_mul(unit as u64) > left {
            return Err(self.err(format!("length {n} exceeds the file")));
        }
        Ok(n as usize)
    }

    /// An Eigen matrix of f32: returns (rows, cols, column-major data).
    fn matrix(&mut self) -> Result<(usize, usize, Vec<f32>), MorphError> {
        let rows = self.i32()?;
        let cols = self.i32()?;
        if rows < 0 || cols < 0 {
            return Err(self.err(format!("negative matrix size {rows}×{cols}")));
        }
        let n = rows as usize * cols as usize;
        let raw = self.take(n.checked_mul(4).ok_or_else(|| self.err("matrix too large"))?)?;
        let data = raw.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect();
        Ok((rows as usize, cols as usize, data))
    }

    fn triangles(&mut self) -> Result<Vec<[i32; 3]>, MorphError> {
        let n = self.length(12)?;
        (0..n).map(|_| Ok([self.i32()?, self.i32()?, self.i32()?])).collect()
    }
}

/// Read `sfm_shape_3448.bin` (or any eos shape model of the same layout).
pub fn read_shape_model(path: &Path) -> Result<ShapeModel, MorphError> {
    let p = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| MorphError::Model { path: p.clone(), message: e.to_string() })?;
    parse_shape_model(&bytes, &p)
}

pub fn parse_shape_model(bytes: &[u8], path: &str) -> Result<ShapeModel, MorphError> {
    let mut c = Cursor { bytes, pos: 0, path };
    let version = c.u32()?;
    if version != 1 {
        return Err(c.err(format!("unsupported eos MorphableModel version {version} (expected 1)")));
    }
    let (mr, mc, mean) = c.matrix()?;
    let (br, bc, basis) = c.matrix()?;
    let (er, ec, eigenvalues) = c.matrix()?;
    let tris = c.triangles()?;
    // The colour model: empty in the shape-only SFM, but read it to reach the texture coordinates.
    let _ = c.matrix()?;
    let _ = c.matrix()?;
    let _ = c.matrix()?;
    let _ = c.triangles()?;
    let ntc = c.length(16)?;
    let mut texcoords = Vec::with_capacity(ntc);
    for _ in 0..ntc {
        texcoords.push([c.f64()? as f32, c.f64()? as f32]);
    }
    if mc != 1 || mr % 3 != 0 || mr == 0 {
        return Err(c.err(format!("mean has shape {mr}×{mc}, expected 3n×1")));
    }
    if br != mr || er * ec != bc || ec != 1 {
        return Err(c.err(format!("basis {br}×{bc} and eigenvalues {er}×{ec} do not match the mean ({mr})")));
    }
    let nv = mr / 3;
    if ntc != nv {
        return Err(c.err(format!("{ntc} texture coordinates for {nv} vertices")));
    }
    let mut triangles = Vec::with_capacity(tris.len());
    for t in tris {
        if t.iter().any(|&i| i < 0 || i as usize >= nv) {
            return Err(c.err(format!("triangle {t:?} indexes outside {nv} vertices")));
        }
        triangles.push([t[0] as u32, t[1] as u32, t[2] as u32]);
    }
    if mean.iter().chain(&basis).chain(&eigenvalues).any(|v| !v.is_finite()) || eigenvalues.iter().any(|&e| e < 0.0) {
        return Err(c.err("non-finite values or negative eigenvalues"));
    }
    Ok(ShapeModel { mean, basis, eigenvalues, triangles, texcoords })
}

/// Read `expression_blendshapes_3448.bin`: a cereal vector of (name, deformation vector).
pub fn read_blendshapes(path: &Path, vertex_count: usize) -> Result<Vec<Blendshape>, MorphError> {
    let p = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| MorphError::Model { path: p.clone(), message: e.to_string() })?;
    let mut c = Cursor { bytes: &bytes, pos: 0, path: &p };
    let n = c.length(16)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let len = c.length(1)?;
        let name = String::from_utf8_lossy(c.take(len)?).into_owned();
        let (r, cols, deformation) = c.matrix()?;
        if r * cols != 3 * vertex_count {
            return Err(c.err(format!("blendshape {name} has {} values, expected {}", r * cols, 3 * vertex_count)));
        }
        out.push(Blendshape { name, deformation });
    }
    Ok(out)
}

/// Vertex ids of the model's left and right jaw contours (`sfm_model_contours.json`).
#[derive(Debug, Clone, serde::Deserialize)]
pub struct ModelContour {
    pub right_contour: Vec<u32>,
    pub left_contour: Vec<u32>,
}

pub fn read_contours(path: &Path) -> Result<ModelContour, MorphError> {
    #[derive(serde::Deserialize)]
    struct File {
        model_contour: ModelContour,
    }
    let p = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| MorphError::Model { path: p.clone(), message: e.to_string() })?;
    let f: File = serde_json::from_str(&text).map_err(|e| MorphError::Model { path: p, message: e.to_string() })?;
    Ok(f.model_contour)
}

/// `ibug_to_sfm.txt`: `ibug_number = vertex_id` lines of the `[landmark_mappings]` table.
pub fn read_ibug_mapping(path: &Path) -> Result<Vec<(u32, u32)>, MorphError> {
    let p = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| MorphError::Model { path: p.clone(), message: e.to_string() })?;
    let mut in_table = false;
    let mut out = Vec::new();
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.starts_with('[') {
            in_table = line == "[landmark_mappings]";
            continue;
        }
        if !in_table || line.is_empty() {
            continue;
        }
        let Some((a, b)) = line.split_once('=') else { continue };
        let (Ok(a), Ok(b)) = (a.trim().parse::<u32>(), b.trim().parse::<u32>()) else {
            return Err(MorphError::Model { path: p, message: format!("bad mapping line '{line}'") });
        };
        out.push((a, b));
    }
    Ok(out)
}

/// `sfm_reference_symmetry.txt`: one 1-based mirror id per line for the first vertices (the
/// 845-vertex reference). Returns 0-based ids.
pub fn read_symmetry(path: &Path) -> Result<Vec<u32>, MorphError> {
    let p = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| MorphError::Model { path: p.clone(), message: e.to_string() })?;
    let mut out = Vec::new();
    for line in text.lines() {
        let Some(tok) = line.split_whitespace().next() else { continue };
        match tok.parse::<u32>() {
            Ok(v) if v >= 1 => out.push(v - 1),
            _ => return Err(MorphError::Model { path: p, message: format!("bad symmetry line '{line}'") }),
        }
    }
    Ok(out)
}
