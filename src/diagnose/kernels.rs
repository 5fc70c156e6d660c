//! The joint kernel fit of the diagnosis: every tile's kernel at once, in the same gather-form
//! forward model that predicts images ([`crate::optics::forward`]).
//!
//! # Problem (one channel)
//! `min_U ½ Σ_x W(x)·(Σ_t w_t(x)·(U_t * P)(x) − y(x))²  s.t.  U_t ≥ 0, ΣU_t = S`
//!
//! with `w_t` the hat weights of the grid, `P` the (registered, linear) pinhole plane, `y` the
//! target and `W` the inverse noise variance (0 outside the data mask). `U_t = s·K_t` carries the
//! exposure ratio, so all kernels share one sum `S` (the base model's single exposure ratio);
//! `S` itself is refitted in closed form after each solve ([`fit_kernels`]).
//!
//! The estimator ([`crate::estimate`]) fits one kernel per tile on that tile's pixels with a TV
//! prior; its kernels are the averages over a tile, not the PSF at the centre the forward model
//! interpolates from. The diagnosis must not blame physics for that, so it refines the kernels in
//! the forward model itself, without a prior (the kernel count enters the parameter penalty).
//!
//! # Algorithm
//! FISTA with a step `1/L`, `L` from power iteration on `AᵀWA`, and the exact Euclidean
//! projection onto `{U ≥ 0, ΣU = S}` (the scaled simplex). `A` and `Aᵀ` are per-tile FFT
//! products over the box where the tile's weight is non-zero, mirrored at the image edges
//! like [`crate::optics::forward::blur_channel`], tiles in parallel.

use crate::image::Plane;
use crate::optics::psf_grid::PsfGrid;
use crate::solve::conv::{kernel_from_origin, kernel_to_origin};
use crate::solve::fft::{good_size, Fft2};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use std::sync::Arc;

struct TileOp {
    x0: usize,
    y0: usize,
    bw: usize,
    bh: usize,
    fft: Arc<Fft2>,
    pspec: Vec<Complex32>,
    /// Hat weight of this tile over its box.
    weight: Vec<f32>,
}

/// The linear map from a grid's kernels to the predicted image, and its adjoint.
pub struct GatherOperator {
    width: usize,
    height: usize,
    k: usize,
    ops: Vec<TileOp>,
}

impl GatherOperator {
    /// Prepares the operator for `sharp` and the tiling of `grid` (its kernels are not used).
    pub fn new(sharp: &Plane, grid: &PsfGrid) -> Self {
        let (w, h) = (sharp.width, sharp.height);
        let k = grid.kernel_size;
        let r = k / 2;
        let ops = (0..grid.tile_count())
            .into_par_iter()
            .map(|t| {
                let (x0, x1, y0, y1) = grid.support(t, w, h);
                let (bw, bh) = (x1 - x0, y1 - y0);
                let (pw, ph) = (good_size(bw + 2 * r), good_size(bh + 2 * r));
                let fft = Fft2::plan(pw, ph);
                let win = sharp.window_reflect(x0 as isize - r as isize, y0 as isize - r as isize, pw, ph);
                let pspec = fft.forward(&win.data);
                let weight = grid.tile_weights(t, x0, x1, y0, y1);
                TileOp { x0, y0, bw, bh, fft, pspec, weight }
            })
            .collect();
        Self { width: w, height: h, k, ops }
    }

    /// `Σ_t w_t·(U_t * P)`.
    pub fn apply(&self, kernels: &[Plane]) -> Plane {
        let r = self.k / 2;
        let parts: Vec<Plane> = self
            .ops
            .par_iter()
            .zip(kernels)
            .map(|(op, u)| {
                let (pw, ph) = (op.fft.width, op.fft.height);
                let mut spec = op.fft.forward(&kernel_to_origin(u, pw, ph));
                for (s, p) in spec.iter_mut().zip(&op.pspec) {
                    *s *= p;
                }
                let full = op.fft.inverse(spec);
                Plane::from_fn(op.bw, op.bh, |x, y| op.weight[y * op.bw + x] * full[(y + r) * pw + x + r])
            })
            .collect();
        let mut out = Plane::new(self.width, self.height);
        for (op, p) in self.ops.iter().zip(parts) {
            for y in 0..op.bh {
                let row = &mut out.data[(op.y0 + y) * self.width + op.x0..(op.y0 + y) * self.width + op.x0 + op.bw];
                for (o, v) in row.iter_mut().zip(&p.data[y * op.bw..(y + 1) * op.bw]) {
                    *o += v;
                }
            }
        }
        out
    }

    /// The adjoint: per tile, the correlation of `P` with `w_t·img` at lags inside the kernel.
    pub fn adjoint(&self, img: &Plane) -> Vec<Plane> {
        let (r, k) = (self.k / 2, self.k);
        self.ops
            .par_iter()
            .map(|op| {
                let (pw, ph) = (op.fft.width, op.fft.height);
                let mut z = vec![0.0f32; pw * ph];
                for y in 0..op.bh {
                    for x in 0..op.bw {
                        z[(y + r) * pw + x + r] = op.weight[y * op.bw + x] * img.data[(op.y0 + y) * self.width + op.x0 + x];
                    }
                }
                let mut spec = op.fft.forward(&z);
                for (s, p) in spec.iter_mut().zip(&op.pspec) {
                    *s *= p.conj();
                }
                let full = op.fft.inverse(spec);
                kernel_from_origin(&full, pw, ph, k, k)
            })
            .collect()
    }
}

pub use crate::estimate::solver::project_simplex;

/// Settings of [`fit_kernels`].
#[derive(Clone, Copy, Debug)]
pub struct KernelFitSettings {
    pub iterations: usize,
    /// Outer rounds of (kernels, common sum).
    pub rounds: usize,
}

/// Fits the kernels of one channel (see the module docs), starting from `init` (each tile's
/// kernel is scaled to the common sum first). Returns the kernels `U_t` (summing to the fitted
/// `S`) and `S`.
pub fn fit_kernels(op: &GatherOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings) -> (Vec<Plane>, f32) {
    let mut s = (init.iter().map(|k| k.sum()).sum::<f64>() / init.len().max(1) as f64) as f32;
    let mut x: Vec<Plane> = init.to_vec();
    for k in &mut x {
        project_simplex(&mut k.data, s);
    }
    let wapply = |p: &Plane| -> Plane { Plane { width: p.width, height: p.height, data: p.data.iter().zip(weight).map(|(a, w)| a * w).collect() } };
    // power iteration for L = ‖AᵀWA‖
    let mut v: Vec<Plane> = x.iter().map(|k| k.map(|_| 1.0)).collect();
    let mut l = 1.0f64;
    for _ in 0..12 {
        let n = v.iter().map(|k| k.data.iter().map(|a| (*a as f64).powi(2)).sum::<f64>()).sum::<f64>().sqrt().max(1e-30);
        v.iter_mut().for_each(|k| k.scale((1.0 / n) as f32));
        v = op.adjoint(&wapply(&op.apply(&v)));
        l = v.iter().map(|k| k.data.iter().map(|a| (*a as f64).powi(2)).sum::<f64>()).sum::<f64>().sqrt();
    }
    let step = (1.0 / (1.05 * l.max(1e-30))) as f32;
    for _ in 0..settings.rounds.max(1) {
        let mut z = x.clone();
        let mut t = 1.0f64;
        for _ in 0..settings.iterations {
            let pred = op.apply(&z);
            let res = Plane { width: y.width, height: y.height, data: pred.data.iter().zip(&y.data).zip(weight).map(|((p, q), w)| (p - q) * w).collect() };
            let g = op.adjoint(&res);
            let mut xn: Vec<Plane> = z.iter().zip(&g).map(|(zk, gk)| Plane { width: zk.width, height: zk.height, data: zk.data.iter().zip(&gk.data).map(|(a, b)| a - step * b).collect() }).collect();
            for k in &mut xn {
                project_simplex(&mut k.data, s);
            }
            let tn = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
            let mom = ((t - 1.0) / tn) as f32;
            z = xn.iter().zip(&x).map(|(a, b)| Plane { width: a.width, height: a.height, data: a.data.iter().zip(&b.data).map(|(p, q)| p + mom * (p - q)).collect() }).collect();
            x = xn;
            t = tn;
        }
        // common sum by weighted least squares
        let pred = op.apply(&x);
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for ((p, q), w) in pred.data.iter().zip(&y.data).zip(weight) {
            num += (*w * p * q) as f64;
            den += (*w * p * p) as f64;
        }
        if den > 0.0 && num > 0.0 {
            let a = (num / den) as f32;
            x.iter_mut().for_each(|k| k.scale(a));
            s *= a;
        }
    }
    (x, s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::forward::blur_channel;
    use crate::rng::Rng;

    fn grid(w: usize, h: usize, k: usize, seed: u64) -> PsfGrid {
        let (cols, rows) = (3, 2);
        let mut r = Rng::new(seed);
        let kernels = vec![(0..cols * rows)
            .map(|_| {
                let mut p = Plane::from_fn(k, k, |_, _| r.uniform() as f32);
                let s = p.sum() as f32;
                p.scale(1.0 / s);
                p
            })
            .collect()];
        PsfGrid { kernel_size: k, columns: cols, rows, centers: PsfGrid::regular_centers(w, h, cols, rows), channels: vec!["Y".into()], kernels }
    }

    #[test]
    fn apply_matches_the_forward_model_and_adjoint_is_exact() {
        let (w, h, k) = (70, 50, 5);
        let mut r = Rng::new(1);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let g = grid(w, h, k, 2);
        let op = GatherOperator::new(&sharp, &g);
        let a = op.apply(&g.kernels[0]);
        let b = blur_channel(&sharp, &g, 0);
        let err = a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(err < 1e-4, "{err}");
        let img = Plane::from_fn(w, h, |_, _| r.normal() as f32);
        let at = op.adjoint(&img);
        let lhs: f64 = a.data.iter().zip(&img.data).map(|(x, y)| (*x as f64) * (*y as f64)).sum();
        let rhs: f64 = at.iter().zip(&g.kernels[0]).map(|(p, q)| p.data.iter().zip(&q.data).map(|(x, y)| (*x as f64) * (*y as f64)).sum::<f64>()).sum();
        assert!((lhs - rhs).abs() < 1e-3 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
    }

    #[test]
    fn simplex_projection_is_feasible_and_idempotent() {
        let mut v = vec![0.5, -0.2, 0.9, 0.1];
        project_simplex(&mut v, 1.0);
        assert!((v.iter().sum::<f32>() - 1.0).abs() < 1e-6 && v.iter().all(|&x| x >= 0.0), "{v:?}");
        let again = {
            let mut c = v.clone();
            project_simplex(&mut c, 1.0);
            c
        };
        assert!(v.iter().zip(&again).all(|(a, b)| (a - b).abs() < 1e-6));
    }

    #[test]
    fn fit_recovers_kernels_and_sum() {
        let (w, h, k) = (90, 60, 5);
        let mut r = Rng::new(3);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let truth = grid(w, h, k, 4);
        let op = GatherOperator::new(&sharp, &truth);
        let mut y = op.apply(&truth.kernels[0]);
        y.scale(1.7);
        let wt = vec![1.0; w * h];
        let init: Vec<Plane> = (0..6).map(|_| Plane::filled(k, k, 1.0 / (k * k) as f32)).collect();
        let (u, s) = fit_kernels(&op, &y, &wt, &init, KernelFitSettings { iterations: 300, rounds: 2 });
        assert!((s - 1.7).abs() < 0.01, "{s}");
        for (a, b) in u.iter().zip(&truth.kernels[0]) {
            let e = crate::estimate::relative_error(&a.map(|v| v / 1.7), b);
            assert!(e < 0.05, "{e}");
        }
    }
}
