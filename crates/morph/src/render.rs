//! Our own rasteriser: z-buffered triangles with affine (orthographic) interpolation, texture
//! extraction into the model's UV map with visibility and symmetry completion, and textured
//! rendering at any camera. Buffers are allocated once per call; the per-pixel loops only index.

use image::{Rgb, RgbImage, RgbaImage};

/// Visit every pixel centre (integer coordinates) inside the triangle `p` (x, y), clipped to
/// `[0, width) × [0, height)`, with its barycentric weights. Degenerate triangles are skipped.
#[inline]
pub fn raster_triangle(p: [[f32; 2]; 3], width: usize, height: usize, mut visit: impl FnMut(usize, usize, [f32; 3])) {
    let area = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
    if !(area.abs() > 1e-8) {
        return;
    }
    let inv = 1.0 / area;
    let x0 = p[0][0].min(p[1][0]).min(p[2][0]).ceil().max(0.0);
    let x1 = p[0][0].max(p[1][0]).max(p[2][0]).floor().min(width as f32 - 1.0);
    let y0 = p[0][1].min(p[1][1]).min(p[2][1]).ceil().max(0.0);
    let y1 = p[0][1].max(p[1][1]).max(p[2][1]).floor().min(height as f32 - 1.0);
    if !(x0 <= x1 && y0 <= y1) {
        return;
    }
    let (xs, xe, ys, ye) = (x0 as usize, x1 as usize, y0 as usize, y1 as usize);
    // Barycentrics are affine in (x, y): step them incrementally along each row.
    let w0_dx = (p[1][1] - p[2][1]) * inv;
    let w1_dx = (p[2][1] - p[0][1]) * inv;
    let eps = -1e-5;
    for y in ys..=ye {
        let fy = y as f32;
        let fx = xs as f32;
        let mut w0 = ((p[1][0] - fx) * (p[2][1] - fy) - (p[2][0] - fx) * (p[1][1] - fy)) * inv;
        let mut w1 = ((p[2][0] - fx) * (p[0][1] - fy) - (p[0][0] - fx) * (p[2][1] - fy)) * inv;
        for x in xs..=xe {
            let w2 = 1.0 - w0 - w1;
            if w0 >= eps && w1 >= eps && w2 >= eps {
                visit(x, y, [w0, w1, w2]);
            }
            w0 += w0_dx;
            w1 += w1_dx;
        }
    }
}

/// A depth buffer over the part of an image the mesh covers; larger depth = nearer the camera.
pub struct DepthBuffer {
    /// Top-left corner of the buffer in image pixels.
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
    pub depth: Vec<f32>,
}

impl DepthBuffer {
    /// Render the depth of every triangle of `projected` (x, y, depth per vertex) inside an image
    /// of `image_width`×`image_height`; the buffer spans only the mesh's bounding box.
    pub fn render(projected: &[[f32; 3]], triangles: &[[u32; 3]], image_width: usize, image_height: usize) -> DepthBuffer {
        let (mut lx, mut ly, mut hx, mut hy) = (f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY);
        for p in projected {
            lx = lx.min(p[0]);
            ly = ly.min(p[1]);
            hx = hx.max(p[0]);
            hy = hy.max(p[1]);
        }
        if !(lx <= hx && ly <= hy) {
            return DepthBuffer { x0: 0, y0: 0, width: 0, height: 0, depth: Vec::new() };
        }
        let x0 = lx.floor().clamp(0.0, image_width as f32) as usize;
        let y0 = ly.floor().clamp(0.0, image_height as f32) as usize;
        let x1 = (hx.ceil() + 1.0).clamp(0.0, image_width as f32) as usize;
        let y1 = (hy.ceil() + 1.0).clamp(0.0, image_height as f32) as usize;
        let (width, height) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        let mut depth = vec![f32::NEG_INFINITY; width * height];
        let (ox, oy) = (x0 as f32, y0 as f32);
        for t in triangles {
            let (a, b, c) = (projected[t[0] as usize], projected[t[1] as usize], projected[t[2] as usize]);
            raster_triangle([[a[0] - ox, a[1] - oy], [b[0] - ox, b[1] - oy], [c[0] - ox, c[1] - oy]], width, height, |x, y, w| {
                let z = w[0] * a[2] + w[1] * b[2] + w[2] * c[2];
                let slot = &mut depth[y * width + x];
                if z > *slot {
                    *slot = z;
                }
            });
        }
        DepthBuffer { x0, y0, width, height, depth }
    }

    /// Is a surface point at image position (x, y) with depth z the nearest one there?
    #[inline]
    pub fn visible(&self, x: f32, y: f32, z: f32, tolerance: f32) -> bool {
        let (xi, yi) = ((x - self.x0 as f32).round(), (y - self.y0 as f32).round());
        if !(xi >= 0.0 && yi >= 0.0 && (xi as usize) < self.width && (yi as usize) < self.height) {
            return false;
        }
        z >= self.depth[yi as usize * self.width + xi as usize] - tolerance
    }
}

/// Bilinear sample of an RGB image at (x, y), pixel centres at integers, clamped at the borders.
#[inline]
pub fn sample_rgb(img: &RgbImage, x: f32, y: f32) -> [f32; 3] {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let xf = x.floor();
    let yf = y.floor();
    let (fx, fy) = (x - xf, y - yf);
    let (x0, y0) = (xf as i64, yf as i64);
    let raw = img.as_raw();
    if x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
        // Inside: the four neighbours without clamping.
        let i = 3 * (y0 as usize * w as usize + x0 as usize);
        let j = i + 3 * w as usize;
        let mut out = [0.0; 3];
        for k in 0..3 {
            let top = raw[i + k] as f32 + fx * (raw[i + 3 + k] as f32 - raw[i + k] as f32);
            let bottom = raw[j + k] as f32 + fx * (raw[j + 3 + k] as f32 - raw[j + k] as f32);
            out[k] = top + fy * (bottom - top);
        }
        return out;
    }
    let at = |xx: i64, yy: i64| {
        let i = 3 * (yy.clamp(0, h - 1) as usize * w as usize + xx.clamp(0, w - 1) as usize);
        [raw[i] as f32, raw[i + 1] as f32, raw[i + 2] as f32]
    };
    let (a, b, c, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
    let mut out = [0.0; 3];
    for k in 0..3 {
        let top = a[k] + fx * (b[k] - a[k]);
        let bottom = c[k] + fx * (d[k] - c[k]);
        out[k] = top + fy * (bottom - top);
    }
    out
}

/// Texel provenance in the alpha channel of an extracted texture.
pub const TEXEL_SEEN: u8 = 255;
pub const TEXEL_MIRRORED: u8 = 160;
pub const TEXEL_FILLED: u8 = 64;

/// Minimal cosine between a triangle's normal and the viewing direction for its texture to be
/// taken from the photo: grazing triangles smear a few pixels across many texels.
const MIN_FACING: f32 = 0.2;
/// From this cosine on, a triangle's own view is used alone.
const FULL_FACING: f32 = 0.6;

/// Weight of a view of a triangle from its facing cosine: 0 below `MIN_FACING`, 1 from `FULL_FACING`.
#[inline]
fn facing_ramp(cosine: f32) -> f32 {
    ((cosine - MIN_FACING) / (FULL_FACING - MIN_FACING)).clamp(0.0, 1.0)
}

/// Extract the texture of the photo into the model's UV map (`size`×`size`), with z-buffer
/// visibility. Each texel blends the photo at its own triangle (weight rising with the facing
/// cosine from 0.2 to 0.6) with the photo at the mirror triangle (symmetry completion) for what the
/// own view lacks; texels with neither take the mean colour of the seen texels.
/// `projected`: vertex image positions and depths; `facing`: per-triangle cosine to the viewer
/// (from [`facing_of`] with the model's `winding`).
pub fn extract_texture(
    photo: &RgbImage,
    projected: &[[f32; 3]],
    facing: &[f32],
    triangles: &[[u32; 3]],
    texcoords: &[[f32; 2]],
    mirror_triangles: &[[u32; 3]],
    winding: f32,
    size: usize,
    depth_tolerance: f32,
) -> RgbaImage {
    let zbuf = DepthBuffer::render(projected, triangles, photo.width() as usize, photo.height() as usize);
    let mut tex = RgbaImage::new(size as u32, size as u32);
    let (mut sum, mut count) = ([0.0f64; 3], 0usize);
    let texels = tex.as_mut();
    let fs = size as f32;
    for (ti, t) in triangles.iter().enumerate() {
        let uv = [0, 1, 2].map(|k| {
            let c = texcoords[t[k] as usize];
            [c[0] * fs - 0.5, c[1] * fs - 0.5]
        });
        let m = mirror_triangles[ti];
        // Mirroring reverses the winding of the mirror triangle's vertex order: negate.
        let mirror_facing = -facing_of(projected, m, winding);
        // Blend weights: the triangle's own view counts fully once it faces the camera well; the
        // mirror fills in what the own view lacks. Near the outline (oblique triangles) the fitted
        // and the real shape disagree most and background creeps in, so the mirror side takes
        // over smoothly there instead of along a hard seam.
        let own_weight = facing_ramp(facing[ti]);
        let mirror_weight = facing_ramp(mirror_facing);
        if own_weight <= 0.0 && mirror_weight <= 0.0 {
            continue;
        }
        let (a, b, c) = (projected[t[0] as usize], projected[t[1] as usize], projected[t[2] as usize]);
        let (ma, mb, mc) = (projected[m[0] as usize], projected[m[1] as usize], projected[m[2] as usize]);
        raster_triangle(uv, size, size, |x, y, w| {
            let i = 4 * (y * size + x);
            if texels[i + 3] == TEXEL_SEEN {
                return;
            }
            let mut own = None;
            if own_weight > 0.0 {
                let (px, py, pz) = (
                    w[0] * a[0] + w[1] * b[0] + w[2] * c[0],
                    w[0] * a[1] + w[1] * b[1] + w[2] * c[1],
                    w[0] * a[2] + w[1] * b[2] + w[2] * c[2],
                );
                if zbuf.visible(px, py, pz, depth_tolerance) {
                    own = Some(sample_rgb(photo, px, py));
                }
            }
            let wo = if own.is_some() { own_weight } else { 0.0 };
            let mut mirrored = None;
            if wo < 1.0 && mirror_weight > 0.0 {
                let (px, py, pz) = (
                    w[0] * ma[0] + w[1] * mb[0] + w[2] * mc[0],
                    w[0] * ma[1] + w[1] * mb[1] + w[2] * mc[1],
                    w[0] * ma[2] + w[1] * mb[2] + w[2] * mc[2],
                );
                if zbuf.visible(px, py, pz, depth_tolerance) {
                    mirrored = Some(sample_rgb(photo, px, py));
                }
            }
            let wm = if mirrored.is_some() { mirror_weight * (1.0 - wo) } else { 0.0 };
            let total = wo + wm;
            if total <= 0.0 {
                return;
            }
            let (o, mr) = (own.unwrap_or([0.0; 3]), mirrored.unwrap_or([0.0; 3]));
            for k in 0..3 {
                texels[i + k] = ((wo * o[k] + wm * mr[k]) / total).round().clamp(0.0, 255.0) as u8;
            }
            if wo >= wm {
                texels[i + 3] = TEXEL_SEEN;
                for k in 0..3 {
                    sum[k] += o[k] as f64;
                }
                count += 1;
            } else {
                texels[i + 3] = TEXEL_MIRRORED;
            }
        });
    }
    // Texels neither seen nor mirrored (or outside every triangle): the mean skin colour, so that
    // bilinear sampling at triangle borders and unseen regions stay plausible.
    let mean = if count > 0 { sum.map(|s| (s / count as f64) as u8) } else { [128; 3] };
    for px in texels.chunks_exact_mut(4) {
        if px[3] == 0 {
            px[..3].copy_from_slice(&mean);
            px[3] = TEXEL_FILLED;
        }
    }
    tex
}

/// Cosine between the triangle's normal and the direction towards the camera, from projected
/// positions (x right, y down, depth towards the camera): the sign follows the model's winding.
#[inline]
pub fn facing_of(projected: &[[f32; 3]], t: [u32; 3], winding: f32) -> f32 {
    let (a, b, c) = (projected[t[0] as usize], projected[t[1] as usize], projected[t[2] as usize]);
    let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    // `winding` (±1, measured on the model at load time) makes front faces positive.
    if len > 0.0 { winding * n[2] / len } else { 0.0 }
}

/// Render the textured mesh: `projected` vertex positions (x, y in pixels, depth), `texture` the
/// UV map. Background pixels take `background`. Returns the image and the coverage mask.
pub fn render_textured(
    projected: &[[f32; 3]],
    triangles: &[[u32; 3]],
    texcoords: &[[f32; 2]],
    texture: &RgbaImage,
    width: usize,
    height: usize,
    background: [u8; 3],
) -> RgbImage {
    let mut depth = vec![f32::NEG_INFINITY; width * height];
    let mut out = RgbImage::from_pixel(width as u32, height as u32, Rgb(background));
    let (tw, th) = (texture.width() as f32, texture.height() as f32);
    let traw = texture.as_raw();
    let (tw_i, th_i) = (texture.width() as i64, texture.height() as i64);
    let buf = out.as_mut();
    for t in triangles {
        let (a, b, c) = (projected[t[0] as usize], projected[t[1] as usize], projected[t[2] as usize]);
        let (ta, tb, tc) = (texcoords[t[0] as usize], texcoords[t[1] as usize], texcoords[t[2] as usize]);
        raster_triangle([[a[0], a[1]], [b[0], b[1]], [c[0], c[1]]], width, height, |x, y, w| {
            let z = w[0] * a[2] + w[1] * b[2] + w[2] * c[2];
            let slot = &mut depth[y * width + x];
            if z <= *slot {
                return;
            }
            *slot = z;
            let u = (w[0] * ta[0] + w[1] * tb[0] + w[2] * tc[0]) * tw - 0.5;
            let v = (w[0] * ta[1] + w[1] * tb[1] + w[2] * tc[1]) * th - 0.5;
            // Bilinear texture sample, inlined over the raw RGBA buffer.
            let (uf, vf) = (u.floor(), v.floor());
            let (fx, fy) = (u - uf, v - vf);
            let (x0, y0) = (uf as i64, vf as i64);
            let i = 3 * (y * width + x);
            if x0 >= 0 && y0 >= 0 && x0 + 1 < tw_i && y0 + 1 < th_i {
                let a = 4 * (y0 as usize * tw_i as usize + x0 as usize);
                let c = a + 4 * tw_i as usize;
                for k in 0..3 {
                    let top = traw[a + k] as f32 + fx * (traw[a + 4 + k] as f32 - traw[a + k] as f32);
                    let bottom = traw[c + k] as f32 + fx * (traw[c + 4 + k] as f32 - traw[c + k] as f32);
                    buf[i + k] = (top + fy * (bottom - top)).round().clamp(0.0, 255.0) as u8;
                }
                return;
            }
            let at = |xx: i64, yy: i64, k: usize| {
                traw[4 * (yy.clamp(0, th_i - 1) as usize * tw_i as usize + xx.clamp(0, tw_i - 1) as usize) + k] as f32
            };
            for k in 0..3 {
                let top = at(x0, y0, k) + fx * (at(x0 + 1, y0, k) - at(x0, y0, k));
                let bottom = at(x0, y0 + 1, k) + fx * (at(x0 + 1, y0 + 1, k) - at(x0, y0 + 1, k));
                buf[i + k] = (top + fy * (bottom - top)).round().clamp(0.0, 255.0) as u8;
            }
        });
    }
    out
}
