//! Avatar export: glTF 2.0 binary (`.glb`, texture embedded as PNG) and Wavefront OBJ + MTL + PNG.
//! Positions are in metres in the exported files (glTF's unit), y up, the face looking along +z.

use std::io::Write;
use std::path::Path;

use image::RgbaImage;

use super::MorphError;

/// A textured triangle mesh ready to write.
pub struct TexturedMesh<'a> {
    /// Model coordinates in millimetres.
    pub vertices: &'a [[f32; 3]],
    pub texcoords: &'a [[f32; 2]],
    pub triangles: &'a [[u32; 3]],
    pub texture: &'a RgbaImage,
}

fn err(path: &Path, e: impl std::fmt::Display) -> MorphError {
    MorphError::Export { path: path.display().to_string(), message: e.to_string() }
}

fn png_bytes(texture: &RgbaImage) -> Result<Vec<u8>, image::ImageError> {
    // The alpha channel only records texel provenance: export opaque RGB.
    let rgb = image::DynamicImage::ImageRgba8(texture.clone()).to_rgb8();
    let mut out = Vec::new();
    rgb.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)?;
    Ok(out)
}

fn pad4(buf: &mut Vec<u8>, byte: u8) {
    while buf.len() % 4 != 0 {
        buf.push(byte);
    }
}

/// Write a glTF binary file ([`glb_bytes`]).
pub fn write_glb(mesh: &TexturedMesh, path: &Path) -> Result<(), MorphError> {
    let bytes = glb_bytes(mesh).map_err(|e| err(path, e))?;
    std::fs::write(path, bytes).map_err(|e| err(path, e))
}

/// A glTF binary file's bytes: one mesh, one primitive (positions, texcoords, u32 indices), one
/// material with the texture (PNG) as base colour.
pub fn glb_bytes(mesh: &TexturedMesh) -> Result<Vec<u8>, image::ImageError> {
    let n = mesh.vertices.len();
    let mut bin: Vec<u8> = Vec::new();
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in mesh.vertices {
        for d in 0..3 {
            let v = p[d] * 1e-3;
            lo[d] = lo[d].min(v);
            hi[d] = hi[d].max(v);
            bin.extend_from_slice(&v.to_le_bytes());
        }
    }
    let pos_len = bin.len();
    let uv_off = bin.len();
    for t in mesh.texcoords {
        bin.extend_from_slice(&t[0].to_le_bytes());
        bin.extend_from_slice(&t[1].to_le_bytes());
    }
    let uv_len = bin.len() - uv_off;
    let idx_off = bin.len();
    for t in mesh.triangles {
        for &i in t {
            bin.extend_from_slice(&i.to_le_bytes());
        }
    }
    let idx_len = bin.len() - idx_off;
    let png_off = bin.len();
    let png = png_bytes(mesh.texture)?;
    bin.extend_from_slice(&png);
    let png_len = png.len();
    pad4(&mut bin, 0);
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "facegate morph"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "face"}],
        "meshes": [{"name": "face", "primitives": [{
            "attributes": {"POSITION": 0, "TEXCOORD_0": 1},
            "indices": 2,
            "material": 0,
            "mode": 4
        }]}],
        "materials": [{
            "name": "face",
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "doubleSided": true
        }],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": pos_len, "target": 34962},
            {"buffer": 0, "byteOffset": uv_off, "byteLength": uv_len, "target": 34962},
            {"buffer": 0, "byteOffset": idx_off, "byteLength": idx_len, "target": 34963},
            {"buffer": 0, "byteOffset": png_off, "byteLength": png_len}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": mesh.texcoords.len(), "type": "VEC2"},
            {"bufferView": 2, "componentType": 5125, "count": 3 * mesh.triangles.len(), "type": "SCALAR"}
        ]
    });
    let mut json_bytes = serde_json::to_vec(&json).expect("a JSON value serialises");
    pad4(&mut json_bytes, b' ');
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json_bytes);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    Ok(out)
}

/// The three files of an OBJ avatar named `stem`: `stem.obj` (millimetres; OBJ texture v runs
/// upwards), `stem.mtl` and the texture `stem.png`.
pub struct ObjFiles {
    pub obj: Vec<u8>,
    pub mtl: Vec<u8>,
    pub png: Vec<u8>,
}

pub fn obj_files(mesh: &TexturedMesh, stem: &str) -> Result<ObjFiles, image::ImageError> {
    let png = png_bytes(mesh.texture)?;
    let mtl = format!("newmtl face\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {stem}.png\n").into_bytes();
    let mut obj = Vec::new();
    let mut write = || -> std::io::Result<()> {
        writeln!(obj, "# facegate morph: fitted Surrey Face Model, millimetres")?;
        writeln!(obj, "mtllib {stem}.mtl")?;
        for p in mesh.vertices {
            writeln!(obj, "v {} {} {}", p[0], p[1], p[2])?;
        }
        for t in mesh.texcoords {
            writeln!(obj, "vt {} {}", t[0], 1.0 - t[1])?;
        }
        writeln!(obj, "usemtl face")?;
        for t in mesh.triangles {
            let (a, b, c) = (t[0] + 1, t[1] + 1, t[2] + 1);
            writeln!(obj, "f {a}/{a} {b}/{b} {c}/{c}")?;
        }
        Ok(())
    };
    write().expect("writing to memory");
    Ok(ObjFiles { obj, mtl, png })
}

/// Write `path` (.obj), `path.mtl` and `path.png` beside it ([`obj_files`]).
pub fn write_obj(mesh: &TexturedMesh, path: &Path) -> Result<(), MorphError> {
    let stem = path.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "face".into());
    let files = obj_files(mesh, &stem).map_err(|e| err(path, e))?;
    for (extension, bytes) in [("png", &files.png), ("mtl", &files.mtl), ("obj", &files.obj)] {
        let file = path.with_extension(extension);
        std::fs::write(&file, bytes).map_err(|e| err(&file, e))?;
    }
    Ok(())
}

/// The [`obj_files`] of `stem` in one zip archive (deflated; no timestamps beyond zip's 1980 epoch,
/// so equal meshes give equal archives).
pub fn obj_zip(mesh: &TexturedMesh, stem: &str) -> Result<Vec<u8>, MorphError> {
    let zip_err = |e: &dyn std::fmt::Display| MorphError::Export { path: format!("{stem}.zip"), message: e.to_string() };
    let files = obj_files(mesh, stem).map_err(|e| zip_err(&e))?;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    for (extension, bytes) in [("obj", &files.obj), ("mtl", &files.mtl), ("png", &files.png)] {
        zip.start_file(format!("{stem}.{extension}"), options).map_err(|e| zip_err(&e))?;
        zip.write_all(bytes).map_err(|e| zip_err(&e))?;
    }
    Ok(zip.finish().map_err(|e| zip_err(&e))?.into_inner())
}
