//! One window, one channel: the TV-regularised PSF of Heide et al. 2013, Sec. 6 / docs/method.md §6.
//!
//! # Problem
//! On a periodic working domain of `P = Pw × Ph` pixels around the fit window, with `I` the
//! registered pinhole patch already multiplied by the exposure ratio `s`, `j` the wide-open
//! patch, `M` the 0/1 mask of pixels whose prediction is exact and whose data is valid (inside
//! the window and the image, footprint inside the domain, not saturated in either capture):
//!
//! `b* = argmin_b ½‖M ⊙ (I ⊛ b − j)‖² + λ TV(b),  b ≥ 0, 1ᵀb = σ_sum, supp b ⊂ k × k`
//!
//! (docs/method.md writes the data term scaled by `1/λ` with `s` on the other side; `I` carrying `s`
//! keeps `j`'s noise unscaled.) TV is the isotropic total variation of the `k × k` kernel with
//! zero outside its support (forward differences). The paper's soft sum-to-one penalty
//! `(μ/2)(1ᵀb − 1)²` is replaced by its closed-form effect on the sum: the data term alone wants
//! `1ᵀb = ρ = Σ_M j / Σ_M (I ⊛ u)` (`u` the uniform `k × k` kernel), the penalty with weight
//! `μ_rel` relative to the data term's curvature along the sum wants 1, so
//! `σ_sum = (ρ + μ_rel) / (1 + μ_rel)`; fixing the sum exactly removes the one badly conditioned
//! direction (the DC) from the iterations.
//!
//! # Algorithm (Condat–Vũ, [`crate::solve::primal_dual::condat_vu`])
//! The primal variable is the `k × k` kernel itself (the "cropped kernel domain"). The data term
//! is the smooth part: its gradient `Pᵀ Iᵀ M (I ⊛ P b − j)` takes four FFTs of the domain
//! (`P` places the kernel with its centre at the domain's origin, [`crate::solve::conv`]); the
//! mask is exact (no boundary fill). `F = λ‖·‖₁` on `K = ∇`, `G` the projection onto
//! `{b ≥ 0, 1ᵀb = σ_sum}`. `L_f` comes from power iteration on the data term's Hessian over
//! zero-sum directions.
//!
//! Warm start: the ridge least-squares kernel (one Fourier division with the unknown pixels
//! filled by the mean) projected onto the constraint set. Phase 1 (a few iterations at a
//! provisional `λ`) measures the noise level from the masked residual, which fixes
//! `λ = c_λ · σ̂ · std(I) · √N_data`; phase 2 continues from the same iterates until the relative
//! step is below `tolerance` or the iteration cap.
//!
//! # Conventions
//! Values are linear, on the full-scale axis. Kernels are `k × k`, row-major, centre = zero
//! displacement, true convolution ([`crate::solve::conv`]).

use crate::image::Plane;
use crate::solve::conv::kernel_origin_index;
use crate::solve::fft::{Fft2, FftScratch};
use crate::solve::power::{kernel_start, power_iteration, remove_block_means};
use crate::solve::primal_dual::{condat_vu, PrimalDual, SmoothPrimalDual, SplitOptions, Stats};
use crate::solve::prox::{project_simplex, project_tv_dual, tv_dual_len, tv_gradient, tv_gradient_adjoint};
use rustfft::num_complex::Complex32;
use std::sync::Arc;

/// Inputs of one window problem, on the working domain (all `pw × ph`, row-major).
pub struct TileData {
    pub pw: usize,
    pub ph: usize,
    /// Pinhole patch times the exposure ratio.
    pub sharp: Vec<f32>,
    /// Wide-open patch.
    pub blurred: Vec<f32>,
    /// 1 where the data term counts.
    pub mask: Vec<bool>,
}

/// Solver settings for one window.
#[derive(Clone, Debug)]
pub struct TileSettings {
    pub kernel_size: usize,
    /// TV weight; `None`: `lambda_scale · σ̂ · std(s·I) · √N_data` with `σ̂` the noise level
    /// measured after phase 1.
    pub lambda: Option<f32>,
    pub lambda_scale: f32,
    /// Noise level of the wide-open data (full scale) that sets `λ`; `None`: measured from the
    /// masked residual after phase 1 (which also counts model mismatch, so it overestimates).
    pub noise_sigma: Option<f64>,
    /// Weight of the sum-to-one prior relative to the data term's curvature along the kernel sum.
    pub mu_relative: f32,
    pub max_iterations: usize,
    /// Relative step `‖Δb‖ / ‖b‖` below which the iterations stop.
    pub tolerance: f64,
}

/// Power iterations for a window's step size ([`KernelProblem::lipschitz`], safety factor
/// 1.3). 4 (8 until branch e18): the window fits and the test bed's figures of all five lenses
/// are those of 8 to the table's precision (docs/notes/estimation-history.md "Session 18: speed (e18)").
pub const WINDOW_POWER_ITERATIONS: usize = 4;

/// Iterations of phase 1 (the provisional `λ`).
pub const PHASE1_ITERATIONS: usize = 15;

/// A solved window.
pub struct TileResult {
    pub kernel: Plane,
    pub stats: Stats,
    /// RMS of `M ⊙ (I ⊛ b − j)` over the mask.
    pub residual_rms: f64,
    pub data_pixels: usize,
    /// Noise level measured after phase 1 (full scale), corrected for the fitted degrees of
    /// freedom.
    pub noise_sigma: f64,
    /// The TV weight used.
    pub lambda: f32,
}

/// The kernel-domain problem (see the module docs).
struct KernelProblem {
    fft: Arc<Fft2>,
    scratch: FftScratch,
    k: usize,
    r: usize,
    /// Domain index of every kernel coefficient (row-major `k × k`).
    index: Vec<usize>,
    a_hat: Vec<Complex32>,
    blurred: Vec<f32>,
    mask: Vec<bool>,
    /// Whether each domain row holds a masked-in pixel (the rows the data term needs).
    mask_rows: Vec<bool>,
    lambda: f32,
    total: f32,
    kbuf: Vec<f32>,
    rbuf: Vec<f32>,
    gbuf: Vec<f32>,
    spec: Vec<Complex32>,
}

impl KernelProblem {
    /// `out = Pᵀ Iᵀ M (I ⊛ P b − j)` (or without `j` when `with_data` is false); returns
    /// `½‖M (I ⊛ P b − j)‖²`.
    fn normal(&mut self, b: &[f32], out: &mut [f32], with_data: bool) -> f64 {
        #[cfg(target_arch = "x86_64")]
        if crate::solve::fft::has_avx2() {
            // SAFETY: the CPU supports AVX2 (checked at run time just above).
            return unsafe { self.normal_avx2(b, out, with_data) };
        }
        self.normal_body(b, out, with_data)
    }

    /// [`KernelProblem::normal_body`] compiled for AVX2 (the same bits: same operations, same
    /// order, no fused multiply–add; [`crate::solve::fft::has_avx2`]).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn normal_avx2(&mut self, b: &[f32], out: &mut [f32], with_data: bool) -> f64 {
        self.normal_body(b, out, with_data)
    }

    /// The body of [`KernelProblem::normal`].
    #[inline(always)]
    fn normal_body(&mut self, b: &[f32], out: &mut [f32], with_data: bool) -> f64 {
        let (pw, ph) = (self.fft.width, self.fft.height);
        for (&i, &v) in self.index.iter().zip(b) {
            self.kbuf[i] = v;
        }
        // the kernel occupies the rows within r of row 0 (wrapped): the others are zero
        let r = self.r;
        self.fft.forward_rows_with(&self.kbuf, &mut self.spec, |y| y <= r || y + r >= ph, &mut self.scratch);
        for (s, a) in self.spec.iter_mut().zip(&self.a_hat) {
            *s *= a;
        }
        // the prediction is needed, and the residual non-zero, on the rows the mask touches only
        let mask_rows = &self.mask_rows;
        let inside = |y: usize| mask_rows[y];
        self.fft.inverse_rows_with(&mut self.spec, &mut self.rbuf, inside, &mut self.scratch);
        let f = masked_residual(&mut self.rbuf[..pw * ph], &self.mask[..pw * ph], &self.blurred[..pw * ph], with_data);
        self.fft.forward_rows_with(&self.rbuf, &mut self.spec, inside, &mut self.scratch);
        for (s, a) in self.spec.iter_mut().zip(&self.a_hat) {
            *s *= a.conj();
        }
        self.fft.inverse_rows_with(&mut self.spec, &mut self.gbuf, |y| y <= r || y + r >= ph, &mut self.scratch);
        for (o, &i) in out.iter_mut().zip(&self.index) {
            *o = self.gbuf[i];
        }
        0.5 * f
    }

    /// Largest eigenvalue of the data term's Hessian over zero-sum kernels (power iteration,
    /// with a safety factor of 1.3).
    fn lipschitz(&mut self, iterations: usize) -> f32 {
        let n = self.k * self.k;
        let est = power_iteration(kernel_start(n), iterations, |v, hv| {
            self.normal(v, hv, false);
        }, |v| remove_block_means(v, n));
        est.map_or(1.0, |e| (e.rayleigh.max(1e-30) * 1.3) as f32)
    }
}

impl PrimalDual for KernelProblem {
    fn primal_len(&self) -> usize {
        self.k * self.k
    }
    fn dual_len(&self) -> usize {
        tv_dual_len(self.k)
    }
    fn apply_k(&self, x: &[f32], out: &mut [f32]) {
        tv_gradient(x, self.k, out);
    }
    fn apply_kt(&self, y: &[f32], out: &mut [f32]) {
        tv_gradient_adjoint(y, self.k, out);
    }
    fn prox_f_conj(&mut self, _sigma: f32, y: &mut [f32]) {
        project_tv_dual(y, self.lambda);
    }
    fn prox_g(&mut self, _tau: f32, x: &mut [f32]) {
        project_simplex(x, self.total);
    }
}

impl SmoothPrimalDual for KernelProblem {
    fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64 {
        self.normal(x, out, true)
    }
}

impl KernelProblem {
    /// The problem of one window with the kernel size `k` (`λ = 0`, kernel sum 1 until set).
    fn new(data: &TileData, k: usize) -> Self {
        let (pw, ph) = (data.pw, data.ph);
        let n = pw * ph;
        let fft = Fft2::plan(pw, ph);
        let mut scratch = fft.make_scratch();
        let mut a_hat = vec![Complex32::new(0.0, 0.0); fft.spectrum_len()];
        fft.forward_with(&data.sharp, &mut a_hat, &mut scratch);
        let spec = vec![Complex32::new(0.0, 0.0); fft.spectrum_len()];
        let index = kernel_origin_index(k, pw, ph);
        let (blurred, mask) = (data.blurred.clone(), data.mask.clone());
        let mask_rows = mask.chunks(pw).map(|row| row.iter().any(|&m| m)).collect();
        Self { fft, scratch, k, r: k / 2, index, a_hat, blurred, mask, mask_rows, lambda: 0.0, total: 1.0, kbuf: vec![0.0; n], rbuf: vec![0.0; n], gbuf: vec![0.0; n], spec }
    }

    /// The kernel sum `σ_sum = (ρ + μ)/(1 + μ)` with `ρ = Σ_M j / Σ_M (I ⊛ u)` the sum the data
    /// alone wants (`u` the uniform kernel), and the mean of `j` over the mask.
    fn target_sum(&mut self, mu_relative: f32) -> (f32, f64) {
        let k = self.k;
        let buf = &mut self.rbuf;
        buf.fill(0.0);
        for &i in &self.index {
            buf[i] = 1.0 / (k * k) as f32;
        }
        self.fft.forward_with(buf, &mut self.spec, &mut self.scratch);
        self.spec.iter_mut().zip(&self.a_hat).for_each(|(x, a)| *x *= a);
        self.fft.inverse_rows_with(&mut self.spec, buf, |_| true, &mut self.scratch);
        let (mut sj, mut si, mut count) = (0.0f64, 0.0f64, 0usize);
        for ((&m, &j), &b) in self.mask.iter().zip(&self.blurred).zip(buf.iter()) {
            if m {
                sj += j as f64;
                si += b as f64;
                count += 1;
            }
        }
        let rho = if si > 0.0 { sj / si } else { 1.0 };
        let mu = mu_relative.max(0.0) as f64;
        let mean_j = if count > 0 { sj / count as f64 } else { 0.0 };
        (((rho + mu) / (1.0 + mu)).max(1e-6) as f32, mean_j)
    }

    /// The warm start: ridge least squares with the unknown pixels filled by `mean_j`,
    /// projected onto the constraint set.
    fn warm_start(&mut self, mean_j: f64) -> Vec<f32> {
        let (r, ph) = (self.r, self.fft.height);
        let z: Vec<f32> = self.mask.iter().zip(&self.blurred).map(|(&m, &j)| if m { j } else { mean_j as f32 }).collect();
        self.fft.forward_with(&z, &mut self.spec, &mut self.scratch);
        let ridge = 1e-3 * self.a_hat.iter().map(|a| a.norm_sqr() as f64).sum::<f64>() as f32 / self.a_hat.len() as f32;
        for (x, a) in self.spec.iter_mut().zip(&self.a_hat) {
            *x = a.conj() * *x / (a.norm_sqr() + ridge);
        }
        self.fft.inverse_rows_with(&mut self.spec, &mut self.rbuf, |y| y <= r || y + r >= ph, &mut self.scratch);
        let mut x: Vec<f32> = self.index.iter().map(|&i| self.rbuf[i]).collect();
        project_simplex(&mut x, self.total);
        x
    }
}

/// Population standard deviation of `v`.
fn std_dev(v: &[f32]) -> f64 {
    let n = v.len().max(1) as f64;
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
    (v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n).sqrt()
}

/// Solves one window. `on_check(iteration, relative_step)` may cancel by returning false.
pub fn solve_tile(data: &TileData, s: &TileSettings, mut on_check: impl FnMut(usize, f64) -> bool) -> TileResult {
    let k = s.kernel_size;
    let data_pixels = data.mask.iter().filter(|&&b| b).count();
    let mut p = KernelProblem::new(data, k);
    let (total, mean_j) = p.target_sum(s.mu_relative);
    p.total = total;
    let mut x = p.warm_start(mean_j);
    let l_f = p.lipschitz(WINDOW_POWER_ITERATIONS);
    let l_k = 8f32.sqrt();
    let sd = std_dev(&data.sharp);
    let dof = (data_pixels as f64 - (k * k) as f64).max(data_pixels as f64 * 0.25);
    let dof_factor = (data_pixels as f64 / dof).sqrt();
    let weight = |sigma: f64| (s.lambda_scale as f64 * sigma.max(1e-7) * sd * (data_pixels.max(1) as f64).sqrt()) as f32;
    let rms = |f: f64| (2.0 * f / data_pixels.max(1) as f64).sqrt();
    let mut y = vec![0.0f32; p.dual_len()];
    let mut g = vec![0.0f32; k * k];
    let warm_rms = rms(p.normal(&x, &mut g, true));
    let mut done = 0usize;
    let mut cancelled = false;
    let noise_sigma = match (s.lambda, s.noise_sigma) {
        (Some(_), _) => warm_rms * dof_factor,
        (None, Some(sigma)) => sigma,
        (None, None) => {
            // phase 1: a provisional λ from the warm start's residual (which overestimates σ)
            p.lambda = weight(warm_rms * dof_factor * 0.5);
            let o1 = SplitOptions { max_iterations: PHASE1_ITERATIONS.min(s.max_iterations), min_iterations: usize::MAX, tolerance: 0.0 };
            let st1 = condat_vu(&mut p, &mut x, &mut y, &o1, l_f, l_k, |it, c| {
                let go = on_check(it, c);
                cancelled |= !go;
                go
            });
            done = st1.iterations;
            rms(p.normal(&x, &mut g, true)) * dof_factor
        }
    };
    let lambda = s.lambda.unwrap_or_else(|| weight(noise_sigma));
    p.lambda = lambda;
    let o2 = SplitOptions { max_iterations: if cancelled { 0 } else { s.max_iterations.saturating_sub(done) }, min_iterations: 5, tolerance: s.tolerance };
    let mut stats = condat_vu(&mut p, &mut x, &mut y, &o2, l_f, l_k, |it, c| on_check(done + it, c));
    stats.iterations += done;
    let residual_rms = rms(p.normal(&x, &mut g, true));
    let kernel = Plane { width: k, height: k, data: x };
    TileResult { kernel, stats, residual_rms, data_pixels, noise_sigma, lambda }
}


/// The residual on the mask, in place: `r_i ← m_i (r_i − [with_data] j_i)`, and its sum of
/// squares `Σ r_i²` in f64, in pixel order. A function of its own with slices, so that the sum
/// stays in a register whatever the surrounding code's inlining (inlined into
/// [`KernelProblem::normal`] it was once kept on the stack, a store-to-load chain per pixel
/// that cost the window fits 35 %; docs/benchmarks.md, seventh part).
#[inline(never)]
fn masked_residual(r: &mut [f32], mask: &[bool], blurred: &[f32], with_data: bool) -> f64 {
    let mut f = 0.0f64;
    for ((r, &m), &j) in r.iter_mut().zip(mask).zip(blurred) {
        let d = if m { *r - if with_data { j } else { 0.0 } } else { 0.0 };
        *r = d;
        f += (d as f64) * (d as f64);
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::solve::conv::convolve_direct;

    /// The data term and its gradient are the circular convolution on the padded domain, masked:
    /// `f = ½ Σ_M (Σ_p b(p) I(x − p) − j(x))²` against a direct sum, and `⟨∇f, d⟩` against the
    /// central difference (exact for a quadratic). The mask leaves whole rows empty, inside the
    /// domain and at its edges, so the rows the FFT passes skip are checked too.
    #[test]
    fn data_term_matches_the_direct_masked_convolution() {
        let (pw, ph, k) = (24usize, 20usize, 5usize);
        let r = (k / 2) as isize;
        let mut rng = Rng::new(5);
        let sharp: Vec<f32> = (0..pw * ph).map(|_| rng.uniform() as f32).collect();
        let blurred: Vec<f32> = (0..pw * ph).map(|_| rng.uniform() as f32).collect();
        let mask: Vec<bool> = (0..pw * ph).map(|i| ![0, 1, 7, 8, 19].contains(&(i / pw)) && rng.uniform() < 0.8).collect();
        let data = TileData { pw, ph, sharp: sharp.clone(), blurred: blurred.clone(), mask: mask.clone() };
        let mut p = KernelProblem::new(&data, k);
        let b: Vec<f32> = (0..k * k).map(|_| rng.uniform() as f32).collect();
        let d: Vec<f32> = (0..k * k).map(|_| rng.normal() as f32).collect();
        let mut direct = 0.0f64;
        for y in 0..ph as isize {
            for x in 0..pw as isize {
                let i = (y * pw as isize + x) as usize;
                if !mask[i] {
                    continue;
                }
                let mut pred = 0.0f64;
                for (c, &bc) in b.iter().enumerate() {
                    let (u, v) = ((c % k) as isize - r, (c / k) as isize - r);
                    pred += bc as f64 * sharp[((y - v).rem_euclid(ph as isize) * pw as isize + (x - u).rem_euclid(pw as isize)) as usize] as f64;
                }
                direct += 0.5 * (pred - blurred[i] as f64).powi(2);
            }
        }
        let mut g = vec![0.0f32; k * k];
        let f = p.normal(&b, &mut g, true);
        assert!((f - direct).abs() <= 1e-4 * direct, "f {f} vs direct {direct}");
        let eps = 0.01f32;
        let shifted = |s: f32| b.iter().zip(&d).map(|(&x, &y)| x + s * y).collect::<Vec<f32>>();
        let mut scratch = vec![0.0f32; k * k];
        let diff = (p.normal(&shifted(eps), &mut scratch, true) - p.normal(&shifted(-eps), &mut scratch, true)) / (2.0 * eps as f64);
        let dot: f64 = g.iter().zip(&d).map(|(&a, &c)| a as f64 * c as f64).sum();
        assert!((dot - diff).abs() <= 1e-3 * diff.abs().max(1.0), "⟨∇f, d⟩ {dot} vs difference {diff}");
    }

    /// The AVX2 build of the window fit's normal operator returns the same bits as the
    /// baseline build (value and gradient).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_build_returns_the_same_bits() {
        if !crate::solve::fft::tests::cpu_has_avx2() {
            return;
        }
        let (pw, ph, k) = (60usize, 54usize, 9usize);
        let mut rng = Rng::new(15);
        let sharp: Vec<f32> = (0..pw * ph).map(|_| rng.uniform() as f32).collect();
        let blurred: Vec<f32> = (0..pw * ph).map(|_| rng.uniform() as f32).collect();
        let mask: Vec<bool> = (0..pw * ph).map(|i| (i / pw) > 4 && (i / pw) < ph - 4 && rng.uniform() < 0.9).collect();
        let mut p = KernelProblem::new(&TileData { pw, ph, sharp, blurred, mask }, k);
        let b: Vec<f32> = (0..k * k).map(|_| rng.uniform() as f32).collect();
        for with_data in [true, false] {
            let (mut g0, mut g1) = (vec![0.0f32; k * k], vec![0.0f32; k * k]);
            let f0 = p.normal_body(&b, &mut g0, with_data);
            // SAFETY: AVX2 was detected above.
            let f1 = unsafe { p.normal_avx2(&b, &mut g1, with_data) };
            assert!(f0 > 0.0 && g0.iter().any(|&v| v != 0.0));
            assert_eq!(f0.to_bits(), f1.to_bits(), "with data {with_data}");
            assert_eq!(g0.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), g1.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "with data {with_data}");
        }
    }

    /// The window's step size from [`WINDOW_POWER_ITERATIONS`] power iterations (with the safety
    /// factor 1.3) bounds the data term's largest eigenvalue on zero-sum kernels (from 300
    /// iterations) from above, and by less than the factor, on a window of noise and one of
    /// 3-px cells.
    #[test]
    fn window_step_bounds_the_largest_eigenvalue() {
        let (n, k) = (96usize, 15usize);
        let mut r = Rng::new(17);
        let cells: Vec<f32> = (0..(n / 3 + 1) * (n / 3 + 1)).map(|_| if r.uniform() < 0.5 { 0.2 } else { 0.8 }).collect();
        let targets = [Plane::from_fn(n, n, |_, _| r.uniform() as f32), Plane::from_fn(n, n, |x, y| cells[(y / 3) * (n / 3 + 1) + x / 3])];
        for (i, sharp) in targets.iter().enumerate() {
            let valid = vec![true; n * n];
            let data = crate::estimate::tile_data(sharp, sharp, &valid, 1.0, (10, n - 10, 10, n - 10), k);
            let mut p = KernelProblem::new(&data, k);
            let quick = p.lipschitz(WINDOW_POWER_ITERATIONS) as f64;
            let top = p.lipschitz(300) as f64 / 1.3;
            assert!(quick >= top && quick <= 1.3 * top * 1.0001, "target {i}: step bound {quick:.4e}, eigenvalue {top:.4e}");
        }
    }

    /// A window whose PSF is uniform: the solver recovers it closely (noise 0.5% of the mean).
    #[test]
    fn recovers_a_uniform_psf() {
        let (w, h, k) = (96usize, 96usize, 11usize);
        let mut r = Rng::new(11);
        let sharp = Plane::from_fn(w, h, |_, _| if r.uniform() < 0.5 { 0.2 } else { 0.8 });
        let truth = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - 5.5, y as f32 - 4.0);
            (-(dx * dx + dy * dy) / 6.0).exp()
        });
        let mut truth = truth;
        let s = truth.sum() as f32;
        truth.scale(1.0 / s);
        let blurred = convolve_direct(&sharp, &truth);
        let blurred = Plane::from_fn(w, h, |x, y| blurred.get(x, y) + 0.0025 * r.normal() as f32);
        let valid = vec![true; w * h];
        let data = crate::estimate::tile_data(&blurred, &sharp, &valid, 1.0, (20, 76, 20, 76), k);
        let st = TileSettings { kernel_size: k, lambda: None, lambda_scale: 1.0, noise_sigma: None, mu_relative: 1.0, max_iterations: 300, tolerance: 1e-4 };
        let res = solve_tile(&data, &st, |_, _| true);
        let err = crate::estimate::relative_error(&res.kernel, &truth);
        assert!(err < 0.03, "relative error {err}");
        assert!((res.kernel.sum() - 1.0).abs() < 0.01);
        // the residual is at the noise level
        assert!(res.residual_rms < 0.0035 && res.noise_sigma > 0.0015 && res.noise_sigma < 0.0035, "{} {}", res.residual_rms, res.noise_sigma);
    }
}
