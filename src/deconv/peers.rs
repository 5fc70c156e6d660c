//! Classical peers for the deblur benchmark matrix (issue 12), given the **true** PSFs:
//! Richardson–Lucy with the exact field-varying forward model and its adjoint, and a tile-wise
//! Wiener filter. Linear values, one channel at a time, row-major planes.
//!
//! **Forward model** ([`FieldBlur`]): the gather form of [`crate::optics::forward`],
//! `A x = Σ_t w_t · (k_t * x)`, with the grid's weights `w_t` and mirrored image borders; each
//! tile's convolution is evaluated over its weight support plus the kernel radius `r` on a
//! periodic FFT domain large enough that the wrap-around never reaches the kept pixels. Its
//! adjoint is the scatter form `Aᵀ y = R* Σ_t k_t ⋆ (w_t · y)`, where `R*` folds the `r`-pixel
//! band outside the image back onto its mirror pixels (the adjoint of the mirroring).
//!
//! **Richardson–Lucy** ([`richardson_lucy`]): `x₀ = max(y, ε)`,
//! `x_{n+1} = x_n · Aᵀ(y / A x_n) / Aᵀ1` (ratios with the denominators floored at `ε = 1e-6`),
//! the Poisson maximum-likelihood iteration; snapshots at the requested iteration counts. The
//! Catmull–Rom blend has negative weights, so where neighbouring kernels differ `A x` can be
//! ≤ 0 for a positive `x`; such a pixel has no Poisson likelihood and is made neutral (ratio 1:
//! it pulls no estimate up or down) instead of giving `y / ε`, which made the estimate grow
//! without bound. A prediction in `(0, ε]` keeps the floored ratio (0 where `y = 0`: the
//! dark background's pull towards zero).
//!
//! **Wiener** ([`wiener_tiled`]): every grid tile's kernel `K_t` restores a window covering the
//! tile's weight support plus a margin of two kernel sizes (the image mirrored beyond its
//! borders) by `X = K̄_t Y / (|K_t|² + b |L|²)` with the discrete Laplacian
//! `|L(f)|² = (4 − 2 cos 2πf_x − 2 cos 2πf_y)²` (scikit-image's `wiener` regulariser), and the
//! cropped windows are blended with the grid's weights `w_t` (a partition of unity). One
//! forward FFT per tile serves every balance `b` asked for.

use crate::image::{reflect_index, Plane};
use crate::optics::psf_grid::PsfGrid;
use crate::solve::conv::{kernel_to_origin, CircularConvolution};
use crate::solve::fft::{good_size, Fft2};
use crate::solve::operator::LinearOperator;
use rayon::prelude::*;

/// Floor of the Richardson–Lucy denominators.
const RL_FLOOR: f32 = 1e-6;

/// One tile of [`FieldBlur`]: its support box, weights on it and its convolution.
struct BlurTile {
    x0: usize,
    y0: usize,
    bw: usize,
    bh: usize,
    weights: Vec<f32>,
    conv: CircularConvolution,
    /// Side of the periodic domain (`pw × ph`).
    pw: usize,
    ph: usize,
}

/// The field-varying blur of one channel over a whole `width × height` image, with its adjoint.
pub struct FieldBlur {
    width: usize,
    height: usize,
    radius: usize,
    tiles: Vec<BlurTile>,
}

impl FieldBlur {
    /// The blur of `channel` of `grid` on a `width × height` image.
    ///
    /// # Panics
    /// When `channel` is not a grid channel.
    pub fn new(grid: &PsfGrid, channel: usize, width: usize, height: usize) -> Self {
        let r = grid.kernel_size / 2;
        let tiles = (0..grid.tile_count())
            .into_par_iter()
            .map(|t| {
                let (x0, x1, y0, y1) = grid.support(t, width, height);
                let (bw, bh) = (x1 - x0, y1 - y0);
                let (pw, ph) = (good_size(bw + 2 * r + 1), good_size(bh + 2 * r + 1));
                let conv = CircularConvolution::new(&grid.kernels[channel][t], pw, ph);
                BlurTile { x0, y0, bw, bh, weights: grid.tile_weights(t, x0, x1, y0, y1), conv, pw, ph }
            })
            .collect();
        Self { width, height, radius: r, tiles }
    }

    /// One tile's weighted blur `w_t · (k_t * x)` on its support box.
    fn gather_tile(&self, t: &BlurTile, x: &Plane) -> Vec<f32> {
        let r = self.radius as isize;
        let win = x.window_reflect(t.x0 as isize - r, t.y0 as isize - r, t.pw, t.ph);
        let mut conv = vec![0.0; t.pw * t.ph];
        t.conv.apply(&win.data, &mut conv);
        let r = self.radius;
        let mut out = Vec::with_capacity(t.bw * t.bh);
        for y in 0..t.bh {
            let row = &conv[(y + r) * t.pw + r..(y + r) * t.pw + r + t.bw];
            out.extend(row.iter().zip(&t.weights[y * t.bw..(y + 1) * t.bw]).map(|(c, w)| c * w));
        }
        out
    }

    /// One tile's `k_t ⋆ (w_t · y)` over its support box grown by `r` (may leave the image).
    fn scatter_tile(&self, t: &BlurTile, y: &[f32]) -> Vec<f32> {
        let r = self.radius;
        let mut v = vec![0.0; t.pw * t.ph];
        for j in 0..t.bh {
            let src = &y[(t.y0 + j) * self.width + t.x0..(t.y0 + j) * self.width + t.x0 + t.bw];
            let dst = &mut v[(j + r) * t.pw + r..(j + r) * t.pw + r + t.bw];
            for ((d, s), w) in dst.iter_mut().zip(src).zip(&t.weights[j * t.bw..(j + 1) * t.bw]) {
                *d = s * w;
            }
        }
        let mut out = vec![0.0; t.pw * t.ph];
        t.conv.apply_adjoint(&v, &mut out);
        out
    }

    fn gather(&self, x: &[f32], out: &mut [f32]) {
        let p = Plane { width: self.width, height: self.height, data: x.to_vec() };
        let parts: Vec<Vec<f32>> = self.tiles.par_iter().map(|t| self.gather_tile(t, &p)).collect();
        out.iter_mut().for_each(|v| *v = 0.0);
        for (t, part) in self.tiles.iter().zip(parts) {
            for j in 0..t.bh {
                let row = &mut out[(t.y0 + j) * self.width + t.x0..(t.y0 + j) * self.width + t.x0 + t.bw];
                row.iter_mut().zip(&part[j * t.bw..(j + 1) * t.bw]).for_each(|(o, v)| *o += v);
            }
        }
    }

    fn scatter(&self, y: &[f32], out: &mut [f32]) {
        let parts: Vec<Vec<f32>> = self.tiles.par_iter().map(|t| self.scatter_tile(t, y)).collect();
        out.iter_mut().for_each(|v| *v = 0.0);
        let r = self.radius as isize;
        for (t, part) in self.tiles.iter().zip(parts) {
            for b in 0..t.bh + 2 * self.radius {
                let iy = reflect_index(t.y0 as isize - r + b as isize, self.height);
                for a in 0..t.bw + 2 * self.radius {
                    let ix = reflect_index(t.x0 as isize - r + a as isize, self.width);
                    out[iy * self.width + ix] += part[b * t.pw + a];
                }
            }
        }
    }
}

impl LinearOperator for FieldBlur {
    fn input_len(&self) -> usize {
        self.width * self.height
    }
    fn output_len(&self) -> usize {
        self.width * self.height
    }
    fn apply(&self, x: &[f32], out: &mut [f32]) {
        self.gather(x, out)
    }
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
        self.scatter(y, out)
    }
}

/// Richardson–Lucy on `blurred` through `op`, started from `start` (or `max(y, ε)`); returns
/// the estimate after each count in `checkpoints` (ascending), e.g. `[10, 30, 100]`.
pub fn richardson_lucy(blurred: &Plane, op: &FieldBlur, start: Option<&Plane>, checkpoints: &[usize]) -> Vec<Plane> {
    let n = blurred.data.len();
    let y: Vec<f32> = blurred.data.iter().map(|v| v.max(0.0)).collect();
    let mut norm = vec![0.0; n];
    op.apply_adjoint(&vec![1.0; n], &mut norm);
    let mut x: Vec<f32> = start.map_or(&y, |p| &p.data).iter().map(|v| v.max(RL_FLOOR)).collect();
    let (mut ax, mut back) = (vec![0.0; n], vec![0.0; n]);
    let mut out = Vec::with_capacity(checkpoints.len());
    let last = checkpoints.iter().copied().max().unwrap_or(0);
    for it in 1..=last {
        op.apply(&x, &mut ax);
        ax.iter_mut().zip(&y).for_each(|(a, v)| *a = if *a > 0.0 { v / a.max(RL_FLOOR) } else { 1.0 });
        op.apply_adjoint(&ax, &mut back);
        x.iter_mut().zip(&back).zip(&norm).for_each(|((x, b), m)| *x *= b.max(0.0) / m.max(RL_FLOOR));
        if checkpoints.contains(&it) {
            out.push(Plane { width: blurred.width, height: blurred.height, data: x.clone() });
        }
    }
    out
}

/// `|L(f)|²` of the discrete Laplacian at bin `i` of `fft`'s spectrum.
fn laplacian_power(fft: &Fft2, i: usize) -> f32 {
    let (fx, fy) = fft.frequency(i);
    let tau = 2.0 * std::f32::consts::PI;
    let l = 4.0 - 2.0 * (tau * fx).cos() - 2.0 * (tau * fy).cos();
    l * l
}

/// One tile's Wiener restorations (one per balance), weighted by `w_t`, on its support box.
fn wiener_tile(blurred: &Plane, grid: &PsfGrid, channel: usize, t: usize, balances: &[f32]) -> ((usize, usize, usize, usize), Vec<Vec<f32>>) {
    let (w, h) = (blurred.width, blurred.height);
    let (x0, x1, y0, y1) = grid.support(t, w, h);
    let (bw, bh) = (x1 - x0, y1 - y0);
    let m = 2 * grid.kernel_size;
    let (pw, ph) = (good_size(bw + 2 * m), good_size(bh + 2 * m));
    let fft = Fft2::plan(pw, ph);
    let win = blurred.window_reflect(x0 as isize - m as isize, y0 as isize - m as isize, pw, ph);
    let ys = fft.forward(&win.data);
    let ks = fft.forward(&kernel_to_origin(&grid.kernels[channel][t], pw, ph));
    let lap: Vec<f32> = (0..ys.len()).map(|i| laplacian_power(&fft, i)).collect();
    let weights = grid.tile_weights(t, x0, x1, y0, y1);
    let outs = balances
        .iter()
        .map(|&b| {
            let mut spec: Vec<_> = ys.iter().zip(&ks).zip(&lap).map(|((y, k), l)| y * k.conj() / (k.norm_sqr() + b * l).max(1e-12)).collect();
            let mut full = vec![0.0; pw * ph];
            fft.inverse_into(&mut spec, &mut full);
            let mut out = Vec::with_capacity(bw * bh);
            for y in 0..bh {
                let row = &full[(y + m) * pw + m..(y + m) * pw + m + bw];
                out.extend(row.iter().zip(&weights[y * bw..(y + 1) * bw]).map(|(v, wt)| v * wt));
            }
            out
        })
        .collect();
    ((x0, x1, y0, y1), outs)
}

/// Tile-wise Wiener restoration of `channel` of `blurred` with the grid's kernels, one result
/// per balance `b` in `balances`.
pub fn wiener_tiled(blurred: &Plane, grid: &PsfGrid, channel: usize, balances: &[f32]) -> Vec<Plane> {
    let (w, h) = (blurred.width, blurred.height);
    let parts: Vec<_> = (0..grid.tile_count()).into_par_iter().map(|t| wiener_tile(blurred, grid, channel, t, balances)).collect();
    let mut out = vec![Plane::new(w, h); balances.len()];
    for ((x0, x1, y0, y1), tiles) in parts {
        let bw = x1 - x0;
        for (o, part) in out.iter_mut().zip(tiles) {
            for y in y0..y1 {
                let row = &mut o.data[y * w + x0..y * w + x1];
                row.iter_mut().zip(&part[(y - y0) * bw..(y - y0 + 1) * bw]).for_each(|(a, v)| *a += v);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::optics::forward::blur_channel;
    use crate::solve::operator::adjoint_pair;

    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 40) as f32 / (1u64 << 24) as f32
            })
            .collect()
    }

    #[test]
    fn field_blur_is_the_forward_model_and_its_adjoint_is_exact() {
        let (w, h) = (70, 52);
        let grid = SyntheticLens::new(9, 3).grid(w, h, 3, 3, 3);
        let x = Plane::from_vec(w, h, noise(w * h, 1)).unwrap();
        for c in 0..3 {
            let op = FieldBlur::new(&grid, c, w, h);
            let mut got = vec![0.0; w * h];
            op.apply(&x.data, &mut got);
            let want = blur_channel(&x, &grid, c);
            let err = got.iter().zip(&want.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(err < 1e-4, "channel {c}: max deviation {err}");
            let (a, b) = adjoint_pair(&op, &noise(w * h, 2), &noise(w * h, 3));
            assert!((a - b).abs() < 1e-4 * a.abs(), "channel {c}: ⟨Ax,y⟩ {a} vs ⟨x,Aᵀy⟩ {b}");
        }
    }

    #[test]
    fn richardson_lucy_sharpens_a_blurred_point_towards_it() {
        let (w, h) = (48, 40);
        let grid = SyntheticLens::new(9, 1).grid(w, h, 1, 2, 2);
        let mut sharp = Plane::filled(w, h, 0.01);
        sharp.set(20, 18, 1.0);
        let blurred = blur_channel(&sharp, &grid, 0);
        let op = FieldBlur::new(&grid, 0, w, h);
        let snaps = richardson_lucy(&blurred, &op, None, &[10, 100]);
        // continuing from the 10-iteration estimate for 90 more is the 100-iteration run
        let cont = richardson_lucy(&blurred, &op, Some(&snaps[0]), &[90]);
        let d = cont[0].data.iter().zip(&snaps[1].data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(d < 1e-4, "continued run deviates by {d}");
        let err = |p: &Plane| p.data.iter().zip(&sharp.data).map(|(a, b)| (a - b).powi(2)).sum::<f32>();
        let (e0, e10, e100) = (err(&blurred), err(&snaps[0]), err(&snaps[1]));
        assert!(e10 < 0.7 * e0 && e100 < 0.5 * e10, "errors blurred {e0}, 10 its {e10}, 100 its {e100}");
        assert!(snaps[1].get(20, 18) > 3.0 * blurred.get(20, 18), "peak {} vs blurred {}", snaps[1].get(20, 18), blurred.get(20, 18));
    }

    #[test]
    fn wiener_with_a_delta_kernel_returns_the_input() {
        let (w, h) = (50, 37);
        let mut grid = SyntheticLens::new(5, 1).grid(w, h, 1, 3, 2);
        for k in grid.kernels[0].iter_mut() {
            *k = Plane::new(5, 5);
            k.set(2, 2, 1.0);
        }
        let y = Plane::from_vec(w, h, noise(w * h, 4)).unwrap();
        let out = wiener_tiled(&y, &grid, 0, &[0.0, 1e-3]);
        let err = out[0].data.iter().zip(&y.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(err < 1e-4, "max deviation {err}");
        // a positive balance smooths: the result differs from the input
        let d: f32 = out[1].data.iter().zip(&y.data).map(|(a, b)| (a - b).abs()).sum();
        assert!(d > 1e-3 * (w * h) as f32, "balance 1e-3 changed nothing ({d})");
    }

    #[test]
    fn wiener_undoes_a_noise_free_blur_better_than_the_blurred_input() {
        let (w, h) = (64, 48);
        let grid = SyntheticLens::new(9, 1).grid(w, h, 1, 3, 3);
        let sharp = Plane::from_vec(w, h, noise(w * h, 5)).unwrap();
        let blurred = blur_channel(&sharp, &grid, 0);
        let out = wiener_tiled(&blurred, &grid, 0, &[1e-4]);
        let err = |p: &Plane| p.data.iter().zip(&sharp.data).map(|(a, b)| (a - b).powi(2)).sum::<f32>();
        assert!(err(&out[0]) < 0.5 * err(&blurred), "wiener {} vs blurred {}", err(&out[0]), err(&blurred));
    }

    /// The Catmull–Rom blend has negative weights, so where neighbouring kernels differ the
    /// field blur of a positive image can be negative (the achromat's blue channel on the star
    /// field: 4 pixels). A noise draw above zero there used to give the ratio `y / ε = 10⁴`,
    /// and the estimate grew without bound (8.3 dB on achromat × hubble; this test: 107 after
    /// one iteration); those pixels are now neutral (ratio 1).
    #[test]
    fn richardson_lucy_stays_bounded_where_the_blend_predicts_below_zero() {
        let (w, h) = (64, 24);
        let mut grid = SyntheticLens::new(7, 1).grid(w, h, 1, 4, 1);
        for (t, k) in grid.kernels[0].iter_mut().enumerate() {
            *k = Plane::new(7, 7);
            // the first column's kernel displaces by 3 px, the others not at all
            k.set(if t == 0 { 6 } else { 3 }, 3, 1.0);
        }
        let op = FieldBlur::new(&grid, 0, w, h);
        let mut sharp = Plane::filled(w, h, 0.001);
        for y in 0..h {
            for x in (4..w).step_by(4) {
                sharp.set(x, y, 1.0);
            }
        }
        // the capture (RL's start): the pattern, with one noise draw of 0.01 where the blend
        // of the pattern is lowest
        let mut a = vec![0.0; w * h];
        op.apply(&sharp.data, &mut a);
        let at = (0..w * h).min_by(|&i, &j| a[i].total_cmp(&a[j])).unwrap();
        let mut y = sharp.clone();
        y.data[at] = 0.01;
        op.apply(&y.data, &mut a);
        assert!(a[at] < -0.01, "the premise: the start's prediction is below zero where y > 0 ({})", a[at]);
        let snaps = richardson_lucy(&y, &op, None, &[1, 2, 5, 10, 30]);
        assert_eq!(snaps.len(), 5);
        for (its, out) in [1, 2, 5, 10, 30].iter().zip(snaps) {
            let top = out.data.iter().fold(0.0f32, |m, v| if v.is_finite() { m.max(*v) } else { f32::INFINITY });
            assert!(top < 2.0, "after {its} iterations the estimate reached {top} (the pattern's maximum is 1)");
        }
    }
}
