//! Uniform local binary patterns (Ojala et al., 2002), the texture code of the liveness features
//! (Määttä et al., 2011): each pixel's 8 neighbours on a circle of radius `r` (bilinear on the
//! diagonals) compared with it, the 8-bit code mapped to one of the 58 uniform patterns (at most
//! two 0/1 transitions round the circle) or the 59th bin for every other code.

/// Bins of a uniform LBP(8, r) histogram: 58 uniform patterns and one for the rest.
pub const BINS: usize = 59;

/// The bin of every 8-bit code: uniform codes numbered in increasing order, the rest in the last.
fn uniform_bins() -> [u8; 256] {
    let mut table = [0u8; 256];
    let mut next = 0u8;
    for (code, bin) in table.iter_mut().enumerate() {
        let rotated = ((code << 1) | (code >> 7)) & 0xff;
        if (code ^ rotated).count_ones() <= 2 {
            *bin = next;
            next += 1;
        } else {
            *bin = (BINS - 1) as u8;
        }
    }
    table
}

/// A square plane of one channel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    pub size: usize,
    pub data: Vec<f32>,
}

/// The uniform LBP(8, `radius`) bin of every pixel at least `radius` from the border (`None`
/// nearer), row-major over the whole plane. Each neighbour is a fixed 2×2 bilinear stencil (the
/// diagonals' weights are the same at every pixel), computed once.
pub fn codes(plane: &Plane, radius: usize) -> Vec<Option<u8>> {
    let table = uniform_bins();
    let n = plane.size;
    let mut out = vec![None; n * n];
    if n <= 2 * radius {
        return out;
    }
    let r = radius as f32;
    let d = r * std::f32::consts::FRAC_1_SQRT_2;
    // Counter-clockwise from the right neighbour, image y pointing down.
    let offsets: [(f32, f32); 8] = [(r, 0.0), (d, -d), (0.0, -r), (-d, -d), (-r, 0.0), (-d, d), (0.0, r), (d, d)];
    // Per neighbour: the offset of its stencil's top-left tap and its fractions right and down.
    let stencils: [(isize, f32, f32); 8] = offsets.map(|(dx, dy)| {
        let (x0, y0) = (dx.floor(), dy.floor());
        (y0 as isize * n as isize + x0 as isize, dx - x0, dy - y0)
    });
    let data = &plane.data;
    let row = n as isize;
    for y in radius..n - radius {
        for x in radius..n - radius {
            let i = (y * n + x) as isize;
            let centre = data[i as usize];
            let mut code = 0usize;
            for (bit, &(at, fx, fy)) in stencils.iter().enumerate() {
                let k = (i + at) as usize;
                // Interpolated as lerps, so that a flat neighbourhood stays exactly flat; an
                // integer offset (fraction 0) reads one tap only, which may sit on the plane's edge.
                let lerp = |k: usize| if fx == 0.0 { data[k] } else { data[k] + fx * (data[k + 1] - data[k]) };
                let top = lerp(k);
                let value = if fy == 0.0 { top } else { top + fy * (lerp((k as isize + row) as usize) - top) };
                if value >= centre {
                    code |= 1 << bit;
                }
            }
            out[y * n + x] = Some(table[code]);
        }
    }
    out
}

/// The histograms of `codes` (of a plane of side `size`) over a `grid × grid` split of the plane,
/// row by row, each normalised to sum 1 and square-rooted (the Hellinger map, so that a linear
/// model on them compares histograms as the χ² distance roughly does).
pub fn grid_histograms(codes: &[Option<u8>], size: usize, grid: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; grid * grid * BINS];
    for (i, code) in codes.iter().enumerate() {
        if let Some(bin) = code {
            let (x, y) = (i % size, i / size);
            let cell = (y * grid / size) * grid + x * grid / size;
            out[cell * BINS + *bin as usize] += 1.0;
        }
    }
    for cell in out.chunks_exact_mut(BINS) {
        let total: f32 = cell.iter().sum();
        if total > 0.0 {
            cell.iter_mut().for_each(|v| *v = (*v / total).sqrt());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn there_are_58_uniform_codes() {
        let table = uniform_bins();
        assert_eq!(table.iter().filter(|&&b| (b as usize) < BINS - 1).count(), 58);
        assert_eq!(table[0], 0, "all zeros is uniform");
        assert_eq!(table[0b0101_0101], (BINS - 1) as u8, "alternating bits are not");
        assert!((table[0xff] as usize) < BINS - 1);
    }

    #[test]
    fn a_flat_plane_is_all_ones_and_an_edge_splits_the_codes() {
        let flat = Plane { size: 8, data: vec![3.0; 64] };
        let c = codes(&flat, 1);
        let ones = uniform_bins()[0xff];
        assert!(c.iter().flatten().all(|&b| b == ones));
        assert_eq!(c.iter().flatten().count(), 36, "the 1-pixel border has no code");
        // A vertical step: pixels left of it see brighter right neighbours, so their codes differ.
        let step = Plane { size: 8, data: (0..64).map(|i| if i % 8 < 4 { 0.0 } else { 10.0 }).collect() };
        let h = grid_histograms(&codes(&step, 1), 8, 1);
        assert_eq!(h.len(), BINS);
        assert!(h.iter().filter(|&&v| v > 0.0).count() >= 2);
        let sum_of_squares: f32 = h.iter().map(|v| v * v).sum();
        assert!((sum_of_squares - 1.0).abs() < 1e-5, "square roots of a histogram summing to 1");
    }
}
