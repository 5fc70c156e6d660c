//! The forward model: a sharp image through spatially varying PSFs.
//!
//! `predicted(x) = Σ_t w_t(x) · (K_t * sharp)(x)`
//!
//! with the hat weights `w_t` of [`super::psf_grid`]: at every output pixel the image is
//! convolved with exactly the bilinearly interpolated kernel `Σ_t w_t(x) K_t` of that pixel
//! ("gather" form), so a profile's kernels are the true local PSFs at the tile centres and the
//! blur varies continuously across the field. Boundaries are mirrored ([`crate::solve::conv`]).
//! Each tile's convolution is computed only over the box where its weight is non-zero, tiles in
//! parallel.

use super::psf_grid::PsfGrid;
use crate::image::Plane;
use crate::solve::conv::Convolver;
use rayon::prelude::*;

/// Blurs one channel of `sharp` with the grid's kernels for `channel`.
pub fn blur_channel(sharp: &Plane, grid: &PsfGrid, channel: usize) -> Plane {
    let (w, h) = (sharp.width, sharp.height);
    let k = grid.kernel_size;
    let r = k / 2;
    let parts: Vec<(usize, usize, Plane)> = (0..grid.tile_count())
        .into_par_iter()
        .map(|t| {
            let (x0, x1, y0, y1) = grid.support(t, w, h);
            let (bw, bh) = (x1 - x0, y1 - y0);
            // the box plus a margin of the kernel radius, mirrored at the image edges
            let win = sharp.window_reflect(x0 as isize - r as isize, y0 as isize - r as isize, bw + 2 * r, bh + 2 * r);
            let conv = Convolver::new(&grid.kernels[channel][t], win.width, win.height).apply(&win);
            let weights = grid.tile_weights(t, x0, x1, y0, y1);
            let mut out = Plane::new(bw, bh);
            for y in 0..bh {
                for x in 0..bw {
                    out.data[y * bw + x] = weights[y * bw + x] * conv.get(x + r, y + r);
                }
            }
            (x0, y0, out)
        })
        .collect();
    let mut out = Plane::new(w, h);
    for (x0, y0, p) in parts {
        for y in 0..p.height {
            let row = &mut out.data[(y0 + y) * w + x0..(y0 + y) * w + x0 + p.width];
            for (o, v) in row.iter_mut().zip(&p.data[y * p.width..(y + 1) * p.width]) {
                *o += v;
            }
        }
    }
    out
}

/// Blurs every channel (`sharp.len()` must equal the grid's channel count).
pub fn blur(sharp: &[Plane], grid: &PsfGrid) -> Vec<Plane> {
    sharp.iter().enumerate().map(|(c, p)| blur_channel(p, grid, c)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::conv::convolve_direct;

    fn noise(w: usize, h: usize) -> Plane {
        let mut s = 12345u64;
        Plane::from_fn(w, h, |_, _| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
    }

    fn shifted_kernels() -> PsfGrid {
        // 2x2 tiles: different kernels per tile
        let mk = |dx: usize, dy: usize| {
            let mut k = Plane::new(5, 5);
            k.set(dx, dy, 0.6);
            k.set(2, 2, k.get(2, 2) + 0.4);
            k
        };
        PsfGrid {
            kernel_size: 5,
            columns: 2,
            rows: 2,
            centers: PsfGrid::regular_centers(40, 30, 2, 2),
            channels: vec!["Y".into()],
            kernels: vec![vec![mk(0, 2), mk(4, 2), mk(2, 0), mk(2, 4)]],
        }
    }

    #[test]
    fn gather_form_matches_direct_per_pixel_kernel() {
        let g = shifted_kernels();
        let sharp = noise(40, 30);
        let got = blur_channel(&sharp, &g, 0);
        for &(x, y) in &[(3usize, 4usize), (20, 15), (37, 28), (10, 22), (29, 7)] {
            let k = g.kernel_at(0, x as f64, y as f64);
            let want = convolve_direct(&sharp, &k).get(x, y);
            assert!((got.get(x, y) - want).abs() < 1e-4, "{x},{y}: {} vs {want}", got.get(x, y));
        }
    }

    #[test]
    fn uniform_grid_equals_plain_convolution() {
        let mut g = shifted_kernels();
        let k0 = g.kernels[0][0].clone();
        g.kernels[0] = vec![k0.clone(); 4];
        let sharp = noise(40, 30);
        let a = blur_channel(&sharp, &g, 0);
        let b = convolve_direct(&sharp, &k0);
        for (x, y) in a.data.iter().zip(&b.data) {
            assert!((x - y).abs() < 1e-4);
        }
    }
}
