//! One tile, one channel: the TV-regularised PSF of Heide et al. 2013, Sec. 6 / METHOD.md §6.
//!
//! # Problem
//! On a periodic working domain of `P = Pw × Ph` pixels around the tile, with `I` the registered
//! pinhole patch already multiplied by the exposure ratio `s`, `j` the wide-open patch, `M` the
//! 0/1 mask of pixels whose prediction is exact and whose data is valid (inside the image,
//! footprint inside the domain and the image, not saturated in either capture):
//!
//! `b* = argmin_b ½‖M ⊙ (I ⊛ b − j)‖² + λ‖∇b‖₁ (isotropic) + (μ/2)(1ᵀb − 1)²,  b ≥ 0, supp b ⊂ S`
//!
//! with `S` the `k × k` kernel support around the origin. (METHOD.md writes the same objective
//! scaled by `1/λ` with `s` on the other side; `I` carrying `s` keeps `j`'s noise unscaled.)
//!
//! # Algorithm (Chambolle–Pock, [`crate::solve::primal_dual`])
//! `K = [∇; Id]`, `F(∇b, b) = λ‖∇b‖₁ + ι_C(b)` with `C = {b ≥ 0, supp b ⊂ S}` (so
//! non-negativity and the support are exact, through the dual), and
//! `G(b) = ½‖I ⊛ b − z‖² + (μ/2)(1ᵀb − 1)²` whose prox is closed-form in the Fourier domain
//! (METHOD.md §6):
//!
//! `B = (τ conj(Î) Ẑ + X̃ + τNμ·δ₀) / (τ|Î|² + 1 + τNμ·δ₀)`.
//!
//! The mask is handled by the unknown-boundary majoriser: `z = M ⊙ j + (1 − M) ⊙ (I ⊛ b)` with
//! `b` the current iterate, refreshed every iteration; at the fixed point `z`'s fill equals the
//! prediction, so the masked and periodic objectives agree. `‖K‖` comes from power iteration.
//! The loop stops on the relative primal-dual gap `(P(proj_C b) − D(y)) / P` of the current
//! surrogate, where `D(y) = −G*(−Kᵀy)` is evaluated in closed form per frequency.

use crate::image::Plane;
use crate::solve::fft::Fft2;
use crate::solve::primal_dual::{chambolle_pock, power_iteration, Options, PrimalDual, Stats};
use rustfft::num_complex::Complex32;
use std::sync::Arc;

/// Inputs of one tile problem, on the working domain (all `pw × ph`, row-major).
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

/// Solver settings for one tile.
#[derive(Clone, Debug)]
pub struct TileSettings {
    pub kernel_size: usize,
    /// TV weight; `None`: `lambda_scale · σ̂ · std(s·I) · √N_data` with `σ̂` the noise level
    /// measured from the least-squares warm start's residual.
    pub lambda: Option<f32>,
    pub lambda_scale: f32,
    /// Weight of the sum-to-one penalty, relative to the data term's DC curvature.
    pub mu_relative: f32,
    pub max_iterations: usize,
    pub tolerance: f64,
    pub sigma: f32,
}

/// A solved tile.
pub struct TileResult {
    pub kernel: Plane,
    pub stats: Stats,
    /// RMS of `M ⊙ (I ⊛ b − j)` over the mask.
    pub residual_rms: f64,
    pub data_pixels: usize,
    /// Noise level measured from the least-squares warm start (full scale).
    pub noise_sigma: f64,
    /// The TV weight used.
    pub lambda: f32,
}

struct PsfProblem {
    fft: Arc<Fft2>,
    n: usize,
    w: usize,
    a_hat: Vec<Complex32>,
    a_abs2: Vec<f32>,
    z_hat: Vec<Complex32>,
    blurred: Vec<f32>,
    mask: Vec<bool>,
    support: Vec<bool>,
    lambda: f32,
    mu_n: f32,
    x_spec: Vec<Complex32>,
    iteration: usize,
}

impl PsfProblem {
    /// Weight of a half-spectrum bin in a full-spectrum sum.
    fn bin_weight(&self, i: usize) -> f64 {
        let kx = i / self.fft.height;
        if kx == 0 || (self.fft.width % 2 == 0 && kx == self.fft.half_width - 1) {
            1.0
        } else {
            2.0
        }
    }

    fn refresh_fill(&mut self) {
        let mut s: Vec<Complex32> = self.x_spec.iter().zip(&self.a_hat).map(|(x, a)| x * a).collect();
        let mut pred = vec![0.0; self.n];
        self.fft.inverse_into(&mut s, &mut pred);
        for i in 0..self.n {
            if self.mask[i] {
                pred[i] = self.blurred[i];
            }
        }
        self.fft.forward_into(&pred, &mut self.z_hat);
    }

    fn project_c(&self, x: &[f32]) -> Vec<f32> {
        x.iter().zip(&self.support).map(|(&v, &s)| if s { v.max(0.0) } else { 0.0 }).collect()
    }

    fn tv(&self, b: &[f32]) -> f64 {
        let (w, n) = (self.w, self.n);
        let h = n / w;
        let mut acc = 0.0f64;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let dx = b[y * w + (x + 1) % w] - b[i];
                let dy = b[((y + 1) % h) * w + x] - b[i];
                acc += ((dx * dx + dy * dy) as f64).sqrt();
            }
        }
        acc
    }
}

impl PrimalDual for PsfProblem {
    fn primal_len(&self) -> usize {
        self.n
    }
    fn dual_len(&self) -> usize {
        3 * self.n
    }
    fn apply_k(&self, x: &[f32], out: &mut [f32]) {
        let (w, n) = (self.w, self.n);
        let h = n / w;
        let (gx, rest) = out.split_at_mut(n);
        let (gy, id) = rest.split_at_mut(n);
        for y in 0..h {
            let yn = (y + 1) % h;
            for xx in 0..w {
                let i = y * w + xx;
                gx[i] = x[y * w + (xx + 1) % w] - x[i];
                gy[i] = x[yn * w + xx] - x[i];
            }
        }
        id.copy_from_slice(x);
    }
    fn apply_kt(&self, yv: &[f32], out: &mut [f32]) {
        let (w, n) = (self.w, self.n);
        let h = n / w;
        let (gx, rest) = yv.split_at(n);
        let (gy, id) = rest.split_at(n);
        for y in 0..h {
            let yp = (y + h - 1) % h;
            for xx in 0..w {
                let i = y * w + xx;
                let xp = y * w + (xx + w - 1) % w;
                out[i] = gx[xp] - gx[i] + gy[yp * w + xx] - gy[i] + id[i];
            }
        }
    }
    fn prox_f_conj(&mut self, _sigma: f32, y: &mut [f32]) {
        let n = self.n;
        let lam = self.lambda;
        let (gx, rest) = y.split_at_mut(n);
        let (gy, id) = rest.split_at_mut(n);
        for i in 0..n {
            let m = (gx[i] * gx[i] + gy[i] * gy[i]).sqrt() / lam;
            if m > 1.0 {
                gx[i] /= m;
                gy[i] /= m;
            }
        }
        // prox of σ ι_C*: y − σ proj_C(y/σ) = min(y, 0) on S, y off S
        for (v, &s) in id.iter_mut().zip(&self.support) {
            if s {
                *v = v.min(0.0);
            }
        }
    }
    fn prox_g(&mut self, tau: f32, x: &mut [f32]) {
        let mut xs = self.fft.forward(x);
        for i in 0..xs.len() {
            let a = self.a_hat[i];
            let num = a.conj() * self.z_hat[i] * tau + xs[i];
            let den = tau * self.a_abs2[i] + 1.0;
            xs[i] = if i == 0 { (num + Complex32::new(tau * self.mu_n, 0.0)) / (den + tau * self.mu_n) } else { num / den };
        }
        self.x_spec.copy_from_slice(&xs);
        self.fft.inverse_into(&mut xs, x);
    }
    fn after_iteration(&mut self, _x: &[f32], _x_bar: &[f32]) {
        // the fill converges slowly anyway; refreshing it every second iteration halves its
        // FFT cost without changing the fixed point
        self.iteration += 1;
        if self.iteration % 2 == 0 {
            self.refresh_fill();
        }
    }
    fn gap(&mut self, x: &[f32], y: &[f32]) -> Option<(f64, f64)> {
        let nf = self.n as f64;
        let mu = self.mu_n as f64 / nf;
        // primal at the feasible projection
        let bc = self.project_c(x);
        let bs = self.fft.forward(&bc);
        let mut data = 0.0f64;
        for i in 0..bs.len() {
            let r = self.a_hat[i] * bs[i] - self.z_hat[i];
            data += self.bin_weight(i) * r.norm_sqr() as f64;
        }
        data /= 2.0 * nf;
        let sum_b: f64 = bc.iter().map(|&v| v as f64).sum();
        let primal = data + self.lambda as f64 * self.tv(&bc) + 0.5 * mu * (sum_b - 1.0).powi(2);
        // dual: y is feasible for F* after its prox, so D(y) = −G*(−Kᵀy)
        let mut kty = vec![0.0; self.n];
        self.apply_kt(y, &mut kty);
        kty.iter_mut().for_each(|v| *v = -*v);
        let ws = self.fft.forward(&kty);
        let mut gstar = 0.0f64;
        for i in 1..ws.len() {
            let a2 = self.a_abs2[i] as f64;
            if a2 < 1e-20 {
                if ws[i].norm_sqr() > 0.0 {
                    return Some((f64::INFINITY, primal));
                }
                continue;
            }
            let cross = (ws[i].conj() * self.z_hat[i] * self.a_hat[i].conj()).re as f64 / a2;
            gstar += self.bin_weight(i) * (cross + 0.5 * ws[i].norm_sqr() as f64 / a2) / nf;
        }
        let (a0, z0, w0) = (self.a_hat[0].re as f64, self.z_hat[0].re as f64, ws[0].re as f64);
        let qa = a0 * a0 / nf + mu;
        let lin = w0 / nf + a0 * z0 / nf + mu;
        gstar += lin * lin / (2.0 * qa) - z0 * z0 / (2.0 * nf) - mu / 2.0;
        Some((primal + gstar, primal))
    }
}

/// Solves one tile. `on_check(iteration, relative_gap)` may cancel by returning false.
pub fn solve_tile(data: &TileData, s: &TileSettings, on_check: impl FnMut(usize, f64) -> bool) -> TileResult {
    let (pw, ph) = (data.pw, data.ph);
    let n = pw * ph;
    let fft = Fft2::plan(pw, ph);
    let a_hat = fft.forward(&data.sharp);
    let a_abs2: Vec<f32> = a_hat.iter().map(|a| a.norm_sqr()).collect();
    let k = s.kernel_size;
    let r = (k / 2) as isize;
    let mut support = vec![false; n];
    for v in -r..=r {
        for u in -r..=r {
            support[(v.rem_euclid(ph as isize) as usize) * pw + u.rem_euclid(pw as isize) as usize] = true;
        }
    }
    let mean_sharp = data.sharp.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
    let mu_n = (s.mu_relative as f64 * (n as f64 * mean_sharp).powi(2)) as f32; // τNμ·δ₀ scale
    let mut p = PsfProblem {
        fft: fft.clone(),
        n,
        w: pw,
        a_hat,
        a_abs2,
        z_hat: vec![Complex32::new(0.0, 0.0); fft.spectrum_len()],
        blurred: data.blurred.clone(),
        mask: data.mask.clone(),
        support,
        lambda: 0.0,
        mu_n,
        x_spec: vec![Complex32::new(0.0, 0.0); fft.spectrum_len()],
        iteration: 0,
    };
    // Warm start: ridge least squares with a few unknown-boundary refills, projected on C.
    // Its residual on the mask measures the noise level (corrected for the k² fitted degrees of
    // freedom), which sets λ.
    let mean_j = {
        let (mut a, mut c) = (0.0f64, 0usize);
        for i in 0..n {
            if data.mask[i] {
                a += data.blurred[i] as f64;
                c += 1;
            }
        }
        if c > 0 { a / c as f64 } else { 0.0 }
    };
    let z0: Vec<f32> = (0..n).map(|i| if data.mask[i] { data.blurred[i] } else { mean_j as f32 }).collect();
    p.z_hat = fft.forward(&z0);
    let ridge = 1e-3 * p.a_abs2.iter().map(|&v| v as f64).sum::<f64>() as f32 / p.a_abs2.len() as f32;
    for _ in 0..6 {
        for i in 0..p.x_spec.len() {
            let mut v = p.a_hat[i].conj() * p.z_hat[i] / (p.a_abs2[i] + ridge);
            if i == 0 {
                v = (p.a_hat[i].conj() * p.z_hat[i] + Complex32::new(mu_n, 0.0)) / (p.a_abs2[i] + mu_n);
            }
            p.x_spec[i] = v;
        }
        p.refresh_fill();
    }
    // project the raw fit onto {b ≥ 0, Σb = 1, supp b ⊂ S}: soft-thresholds the fitted noise
    let raw = fft.inverse(p.x_spec.clone());
    let mut x = project_simplex_on(&raw, &p.support);
    p.x_spec = fft.forward(&x);
    p.refresh_fill();
    let data_pixels = data.mask.iter().filter(|&&b| b).count();
    let dof = (data_pixels as f64 - (k * k) as f64).max(data_pixels as f64 * 0.25);
    let dof_factor = (data_pixels as f64 / dof).sqrt();
    let sd = (data.sharp.iter().map(|&v| (v as f64 - mean_sharp).powi(2)).sum::<f64>() / n as f64).sqrt();
    let weight = |sigma: f64| (s.lambda_scale as f64 * sigma.max(1e-7) * sd * (data_pixels.max(1) as f64).sqrt()) as f32;
    let mut y = vec![0.0f32; 3 * n];
    let l = power_iteration(&p, 20);
    // Phase 1 (λ unknown): a short run at the warm start's residual level; its residual then
    // measures the noise level σ̂, which fixes λ for phase 2 (continued from the same iterates).
    let warm_rms = masked_residual_rms(&fft, &p.a_hat, &x, &data.blurred, &data.mask);
    let mut stats_total = 0usize;
    let noise_sigma = match s.lambda {
        Some(_) => warm_rms * dof_factor,
        None => {
            p.lambda = weight(warm_rms * dof_factor * 0.5);
            let o1 = Options { max_iterations: 60.min(s.max_iterations), min_iterations: 60, tolerance: 0.0, check_every: 60, sigma: s.sigma, theta: 1.0 };
            let st1 = chambolle_pock(&mut p, &mut x, &mut y, &o1, Some(l), |_, _| true);
            stats_total += st1.iterations;
            let b = p.project_c(&x);
            masked_residual_rms(&fft, &p.a_hat, &b, &data.blurred, &data.mask) * dof_factor
        }
    };
    let lambda = s.lambda.unwrap_or_else(|| weight(noise_sigma));
    p.lambda = lambda;
    let opts = Options { max_iterations: s.max_iterations.saturating_sub(stats_total).max(1), min_iterations: 20, tolerance: s.tolerance, check_every: 10, sigma: s.sigma, theta: 1.0 };
    let mut stats = chambolle_pock(&mut p, &mut x, &mut y, &opts, Some(l), on_check);
    stats.iterations += stats_total;
    let b = p.project_c(&x);
    let mut kernel = crate::solve::conv::kernel_from_origin(&b, pw, ph, k, k);
    let sum = kernel.sum() as f32;
    if sum > 0.0 {
        kernel.scale(1.0 / sum);
    }
    let kb = crate::solve::conv::kernel_to_origin(&kernel, pw, ph);
    let residual_rms = masked_residual_rms(&fft, &p.a_hat, &kb, &data.blurred, &data.mask);
    TileResult { kernel, stats, residual_rms, data_pixels, noise_sigma, lambda }
}

/// RMS over the mask of `I ⊛ b − j` (circular on the domain; exact on the mask).
fn masked_residual_rms(fft: &Fft2, a_hat: &[Complex32], b: &[f32], blurred: &[f32], mask: &[bool]) -> f64 {
    let mut spec = fft.forward(b);
    for (v, a) in spec.iter_mut().zip(a_hat) {
        *v *= a;
    }
    let pred = fft.inverse(spec);
    let (mut ss, mut cnt) = (0.0f64, 0usize);
    for i in 0..pred.len() {
        if mask[i] {
            ss += ((pred[i] - blurred[i]) as f64).powi(2);
            cnt += 1;
        }
    }
    if cnt > 0 { (ss / cnt as f64).sqrt() } else { 0.0 }
}

/// Euclidean projection onto `{b ≥ 0, Σ b = 1, b = 0 off the support}` (sort-based simplex
/// projection of the support's values).
pub fn project_simplex_on(v: &[f32], support: &[bool]) -> Vec<f32> {
    let mut vals: Vec<f32> = v.iter().zip(support).filter(|(_, &s)| s).map(|(&x, _)| x).collect();
    vals.sort_by(|a, b| b.total_cmp(a));
    let mut cum = 0.0f64;
    let mut theta = 0.0f64;
    for (i, &u) in vals.iter().enumerate() {
        cum += u as f64;
        let t = (cum - 1.0) / (i + 1) as f64;
        if (u as f64) - t > 0.0 {
            theta = t;
        }
    }
    v.iter().zip(support).map(|(&x, &s)| if s { (x as f64 - theta).max(0.0) as f32 } else { 0.0 }).collect()
}
