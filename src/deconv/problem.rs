//! One channel's deconvolution problem on one tile, in the form [`PrimalDual`] needs
//! (docs/method.md §3–§5).
//!
//! The unknown `x` is the *increment* of a residual step (§5): the tile's current estimate `I_k`
//! is fixed, the data are the residual `ΔJ = J − B I_k`, and
//!
//! ```text
//! min_x ‖M (B x − ΔJ)‖₂² + λ Σ_{a=1..5} μ_a ‖H_a x‖₁ + Σ_l β_l Σ_{a=1,2} ‖D_{p_l} (D_{i_l} H_a − D_{H_a i_l}) x‖₁
//!       + λ_b Σ_l Σ_{a=1,2} ‖D_w (H_a x − H_a (i_l − I_k))‖₂²
//! ```
//!
//! - `μ_1 = μ_2 = 1`, `μ_3 = μ_4 = μ_5 = μ₂` ([`ChannelProblem::order2_weight`]); `p_l` is the
//!   optional per-pixel factor of a cross-channel block ([`CrossChannel::pixel`], 1 if absent);
//!   the optional per-pixel weight ([`ChannelProblem::set_weight`]) multiplies every ℓ1 term.
//! - `K` stacks the ℓ1 operators with their weights inside, `F = ‖·‖₁` (dual prox: clamp to
//!   `[−1, 1]`).
//! - `G` is the data term plus the dark-region term. Without saturated pixels and without dark
//!   regions its prox is the closed-form Fourier division of docs/method.md §3. With a 0/1 saturation
//!   mask `M` or a dark-region weight `w` it is the linear system of §4,
//!   `(2τ BᵀMB + I + 2τ λ_b Σ H_aᵀ D_w² H_a) u = 2τ BᵀM ΔJ + ũ + 2τ λ_b Σ H_aᵀ D_w² H_a (i_l − I_k)`,
//!   solved by conjugate gradients preconditioned with the unmasked Fourier inverse and warm
//!   started from the previous prox.
//! - The dark term matches the gradients of the *total* `I_k + x` to those of `i_l`.
//! - With [`ChannelProblem::data_split`] (`ρ_v`), ADMM splits `v = B x`: the data term
//!   `‖M(v − ΔJ)‖²` has the elementwise prox `v_k = (2 M_k ΔJ_k + ρ_v t_k)/(2 M_k + ρ_v)`,
//!   `t = B x + u_v`, `u_v ← t − v`, and the `x`-update solves
//!   `(ρ_v BᵀB + ρ Σ HᵀH + ρ Σ CᵀC) x = ρ_v Bᵀ(v − u_v) + ρ Σ Kᵀ(z − u)` (a Fourier division
//!   without cross-channel blocks), whatever the mask `M` (Almeida & Figueiredo 2013).
//!
//! All arrays live on the tile's periodic FFT domain (`width × height`, row-major); `B` is the
//! circular convolution with the tile's kernel, whose wrap-around only touches the cropped
//! margin.

mod admm;

use super::filters::{self, Derivative, ALL, FIRST};
use crate::solve::cg::conjugate_gradient;
use crate::solve::fft::Fft2;
use crate::solve::primal_dual::PrimalDual;
use rustfft::num_complex::Complex32;
use std::cell::RefCell;

/// A restored other channel the cross-channel term compares against.
pub struct CrossChannel<'a> {
    pub beta: f32,
    /// `i_l` on the tile domain.
    pub image: &'a [f32],
    /// `H_1 i_l`, `H_2 i_l`.
    pub grad: [Vec<f32>; 2],
    /// Per-pixel factor on `beta` (`None`: 1): the block's weight is `β · p_k` at pixel `k`.
    pub pixel: Option<Vec<f32>>,
}

/// The dark-region term's fixed parts.
pub struct DarkTerm {
    pub lambda_b: f32,
    /// `w²` per pixel.
    pub w2: Vec<f32>,
    /// Number of other channels `l` (each contributes the same operator).
    pub others: usize,
    /// `Σ_l Σ_a H_aᵀ D_w² H_a (i_l − I_k)`.
    pub target: Vec<f32>,
}

/// Spectral data of one kernel on the tile domain.
pub struct KernelSpectrum {
    /// `F(B)`.
    pub b: Vec<Complex32>,
    /// `|F(B)|²`.
    pub b2: Vec<f32>,
}

impl KernelSpectrum {
    pub fn new(fft: &Fft2, kernel_at_origin: &[f32]) -> Self {
        let b = fft.forward(kernel_at_origin);
        let b2 = b.iter().map(|c| c.norm_sqr()).collect();
        Self { b, b2 }
    }
}

/// Counters a tile reports.
#[derive(Clone, Copy, Debug, Default)]
pub struct ProxCounters {
    pub prox_calls: usize,
    pub cg_iterations: usize,
}

/// The problem for one channel, one tile, one residual step.
pub struct ChannelProblem<'a> {
    w: usize,
    h: usize,
    fft: &'a Fft2,
    kernel: &'a KernelSpectrum,
    /// `conj(F B) · F(ΔJ)` (Fourier prox, no mask).
    bj: Vec<Complex32>,
    /// `Bᵀ M ΔJ` (CG prox).
    btmj: Vec<f32>,
    mask: Option<&'a [f32]>,
    /// `M ΔJ` (split data term).
    mj: Vec<f32>,
    lambda: f32,
    /// Per-pixel factor on every ℓ1 term (`K = D_w [λH; βC]`); `None`: 1.
    weight: Option<&'a [f32]>,
    cross: &'a [CrossChannel<'a>],
    dark: Option<DarkTerm>,
    /// Previous CG solution (warm start).
    u_prev: Vec<f32>,
    scratch: RefCell<Vec<f32>>,
    spec: Vec<Complex32>,
    pub counters: ProxCounters,
    /// CG cap per prox (warm started from the previous prox, so a few iterations track the
    /// slowly moving solution; the prox is inexact early on, as in inexact-prox Chambolle–Pock).
    pub cg_max_iterations: usize,
    pub cg_tolerance: f64,
    /// Reweighted ℓ1 on the derivative blocks in [`ChannelProblem::solve_admm`]: `(q, ε)` scales
    /// each pixel's threshold by `((|H_a x| + ε)/ε)^(q−1)` from the current iterate (`None`: ℓ1).
    pub reweight: Option<(f32, f32)>,
    /// Relative weight `μ₂` of the second-order derivative blocks `H_3..H_5` (the prior is
    /// `λ (Σ_{a=1,2} ‖H_a x‖₁ + μ₂ Σ_{a=3..5} ‖H_a x‖₁)`); 1: docs/method.md §3 as printed.
    pub order2_weight: f32,
    /// Penalty `ρ_v` of the data split `v = B x` in [`ChannelProblem::solve_admm`] (`None`: no
    /// split). With it the data term `‖M(v − ΔJ)‖²` is an elementwise prox, so the mask `M`
    /// (saturation, and the unknown boundary of the tile) leaves the `x`-update a Fourier
    /// division (Almeida & Figueiredo 2013).
    pub data_split: Option<f32>,
    /// Lower bound `x ≥ ℓ` in [`ChannelProblem::solve_admm`] (`None`: unconstrained): one more
    /// split `z_+ = x` whose term is the indicator of `{z_+ ≥ ℓ}` (prox: the projection
    /// `max(v, ℓ)`); `ℓ = 0` makes the restored channel non-negative (docs/deconvolution.md
    /// "Positivity").
    pub lower_bound: Option<Vec<f32>>,
}

impl<'a> ChannelProblem<'a> {
    /// Sets up the problem; `residual` is `ΔJ`, `mask` the 0/1 data weight (`None`: all 1).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        fft: &'a Fft2,
        kernel: &'a KernelSpectrum,
        residual: &[f32],
        mask: Option<&'a [f32]>,
        lambda: f32,
        cross: &'a [CrossChannel<'a>],
        dark: Option<DarkTerm>,
    ) -> Self {
        let (w, h) = (fft.width, fft.height);
        let n = w * h;
        assert_eq!(residual.len(), n);
        let mut spec = vec![Complex32::new(0.0, 0.0); fft.spectrum_len()];
        let needs_cg = mask.is_some() || dark.is_some();
        let (bj, btmj, mj) = if needs_cg {
            let masked: Vec<f32> = match mask {
                Some(m) => residual.iter().zip(m).map(|(r, m)| r * m).collect(),
                None => residual.to_vec(),
            };
            fft.forward_into(&masked, &mut spec);
            for (s, b) in spec.iter_mut().zip(&kernel.b) {
                *s *= b.conj();
            }
            let mut out = vec![0.0; n];
            fft.inverse_into(&mut spec, &mut out);
            (Vec::new(), out, masked)
        } else {
            let mut bj = fft.forward(residual);
            for (s, b) in bj.iter_mut().zip(&kernel.b) {
                *s *= b.conj();
            }
            (bj, Vec::new(), residual.to_vec())
        };
        Self {
            w,
            h,
            fft,
            kernel,
            bj,
            btmj,
            mask,
            mj,
            lambda,
            weight: None,
            cross,
            dark,
            u_prev: Vec::new(),
            scratch: RefCell::new(vec![0.0; n]),
            spec,
            counters: ProxCounters::default(),
            cg_max_iterations: 4,
            cg_tolerance: 1e-3,
            reweight: None,
            order2_weight: 1.0,
            data_split: None,
            lower_bound: None,
        }
    }

    /// Scales every ℓ1 term per pixel (a spatially varying prior weight, all values > 0).
    pub fn set_weight(&mut self, weight: Option<&'a [f32]>) {
        self.weight = weight;
    }

    fn n(&self) -> usize {
        self.w * self.h
    }

    /// The prior weight of derivative block `a` (`λ` or `λ μ₂`).
    fn block_lambda(&self, a: usize) -> f32 {
        if a < 2 {
            self.lambda
        } else {
            self.lambda * self.order2_weight
        }
    }

    /// `out = Bᵀ M B u + c_dark · Σ_a H_aᵀ D_w² H_a u` scaled as the CG system needs:
    /// `out = u + 2τ (BᵀMBu + λ_b·others·Σ H_aᵀW²H_a u)`.
    fn apply_system(&self, tau: f32, u: &[f32], out: &mut [f32], spec: &mut [Complex32]) {
        let n = self.n();
        self.fft.forward_into(u, spec);
        for (s, b) in spec.iter_mut().zip(&self.kernel.b) {
            *s *= b;
        }
        let mut bu = vec![0.0; n];
        self.fft.inverse_into(spec, &mut bu);
        if let Some(m) = self.mask {
            bu.iter_mut().zip(m).for_each(|(v, m)| *v *= m);
        }
        self.fft.forward_into(&bu, spec);
        for (s, b) in spec.iter_mut().zip(&self.kernel.b) {
            *s *= b.conj();
        }
        self.fft.inverse_into(spec, out);
        for (o, ui) in out.iter_mut().zip(u) {
            *o = ui + 2.0 * tau * *o;
        }
        if let Some(d) = &self.dark {
            let c = 2.0 * tau * d.lambda_b * d.others as f32;
            for a in FIRST {
                filters::apply(a, u, self.w, self.h, &mut bu);
                bu.iter_mut().zip(&d.w2).for_each(|(v, w2)| *v *= w2);
                filters::add_adjoint(a, &bu, self.w, self.h, c, out);
            }
        }
    }
}

impl ChannelProblem<'_> {
    /// Whether [`ChannelProblem::solve_admm`] applies (everything but the dark-region term).
    pub fn admm_applies(&self) -> bool {
        self.dark.is_none()
    }

    /// `Σ_a |Ĥ_a|²` on the spectrum layout of the tile's FFT.
    fn derivative_power(&self) -> Vec<f32> {
        (0..self.fft.spectrum_len())
            .map(|i| {
                let (fx, fy) = self.fft.frequency(i);
                let x = 4.0 * (std::f32::consts::PI * fx).sin().powi(2);
                let y = 4.0 * (std::f32::consts::PI * fy).sin().powi(2);
                x + y + x * x + y * y + x * y
            })
            .collect()
    }

    /// Minimises the same objective as the primal-dual form with ADMM on the splits
    /// `z_a = H_a x` (and `z = (D_{i_l} H_a − D_{H_a i_l}) x` per cross-channel block), each
    /// `ℓ1` term's per-pixel weight moved into its shrinkage threshold, so the `x`-update
    /// `(2BᵀMB + ρ Σ HᵀH + ρ Σ CᵀC) x = 2BᵀM ΔJ + ρ Σ Kᵀ(z − u)` is a Fourier division when
    /// there is neither a mask nor a cross-channel block, and otherwise a few conjugate-gradient
    /// steps preconditioned by that division and warm started. `x` is the warm start and the
    /// result; returns the CG iterations spent. Needs [`ChannelProblem::admm_applies`].
    pub fn solve_admm(&mut self, x: &mut [f32], iterations: usize, rho: f32, cg_iterations: usize) -> usize {
        let mut steps = admm::ChannelAdmm::new(self, x, rho, cg_iterations);
        crate::solve::admm::admm(&mut steps, x, iterations).inner_iterations
    }

    /// `out += s Σ_l Σ_a C_{la}ᵀ C_{la} v` for the cross-channel blocks
    /// `C_{la} = D_{i_l} H_a − D_{H_a i_l}` (`buf`: 3 planes of scratch).
    fn add_cross_normal(&self, v: &[f32], s: f32, buf: &mut [f32], out: &mut [f32]) {
        let n = self.n();
        let (w, h) = (self.w, self.h);
        let (g, rest) = buf.split_at_mut(n);
        let t = &mut rest[..n];
        for (a, d) in FIRST.iter().enumerate() {
            filters::apply(*d, v, w, h, g);
            for cc in self.cross {
                for ((((ti, o), im), gi), (hv, vi)) in t.iter_mut().zip(out.iter_mut()).zip(cc.image).zip(&cc.grad[a]).zip(g.iter().zip(v)) {
                    let ci = im * hv - gi * vi;
                    *ti = im * ci;
                    *o -= s * gi * ci;
                }
                filters::add_adjoint(*d, t, w, h, s, out);
            }
        }
    }

    /// The unweighted split `[H_a x; (D_{i_l} H_a − D_{H_a i_l}) x]`.
    fn apply_split(&self, x: &[f32], out: &mut [f32]) {
        let n = self.n();
        let (w, h) = (self.w, self.h);
        for (a, d) in ALL.iter().enumerate() {
            filters::apply(*d, x, w, h, &mut out[a * n..(a + 1) * n]);
        }
        let (grads, rest) = out.split_at_mut(ALL.len() * n);
        for (l, cc) in self.cross.iter().enumerate() {
            for a in 0..2 {
                let hx = &grads[a * n..(a + 1) * n];
                let o = &mut rest[(2 * l + a) * n..(2 * l + a + 1) * n];
                for ((((o, im), hx), g), x) in o.iter_mut().zip(cc.image).zip(hx).zip(&cc.grad[a]).zip(x) {
                    *o = im * hx - g * x;
                }
            }
        }
    }

    /// The adjoint of [`Self::apply_split`] (overwrites `out`).
    fn apply_split_adjoint(&self, y: &[f32], out: &mut [f32]) {
        let n = self.n();
        let (w, h) = (self.w, self.h);
        out.iter_mut().for_each(|v| *v = 0.0);
        for (a, d) in ALL.iter().enumerate() {
            filters::add_adjoint(*d, &y[a * n..(a + 1) * n], w, h, 1.0, out);
        }
        let mut tmp = self.scratch.borrow_mut();
        for (l, cc) in self.cross.iter().enumerate() {
            for (a, d) in FIRST.iter().enumerate() {
                let yy = &y[(ALL.len() + 2 * l + a) * n..(ALL.len() + 2 * l + a + 1) * n];
                for ((((t, o), im), g), y) in tmp.iter_mut().zip(out.iter_mut()).zip(cc.image).zip(&cc.grad[a]).zip(yy) {
                    *t = im * y;
                    *o -= g * y;
                }
                filters::add_adjoint(*d, &tmp, w, h, 1.0, out);
            }
        }
    }
}

impl PrimalDual for ChannelProblem<'_> {
    fn primal_len(&self) -> usize {
        self.n()
    }

    fn dual_len(&self) -> usize {
        self.n() * (ALL.len() + 2 * self.cross.len())
    }

    fn apply_k(&self, x: &[f32], out: &mut [f32]) {
        // the unweighted split, then each block's weight: λ·w on the derivatives, β·w on the
        // cross-channel terms
        self.apply_split(x, out);
        let n = self.n();
        let (grads, rest) = out.split_at_mut(ALL.len() * n);
        for (l, cc) in self.cross.iter().enumerate() {
            for o in rest[2 * l * n..(2 * l + 2) * n].chunks_mut(n) {
                o.iter_mut().for_each(|v| *v *= cc.beta);
                if let Some(p) = &cc.pixel {
                    o.iter_mut().zip(p).for_each(|(v, p)| *v *= p);
                }
                if let Some(wt) = self.weight {
                    o.iter_mut().zip(wt).for_each(|(v, w)| *v *= w);
                }
            }
        }
        match self.weight {
            Some(wt) => grads.chunks_mut(n).enumerate().for_each(|(a, g)| {
                let l = self.block_lambda(a);
                g.iter_mut().zip(wt).for_each(|(v, w)| *v *= l * w)
            }),
            None => grads.chunks_mut(n).enumerate().for_each(|(a, g)| {
                let l = self.block_lambda(a);
                g.iter_mut().for_each(|v| *v *= l)
            }),
        }
    }

    fn apply_kt(&self, y: &[f32], out: &mut [f32]) {
        let n = self.n();
        let (w, h) = (self.w, self.h);
        out.iter_mut().for_each(|v| *v = 0.0);
        let mut tmp = self.scratch.borrow_mut();
        for (a, d) in ALL.iter().enumerate() {
            let ya = &y[a * n..(a + 1) * n];
            match self.weight {
                Some(wt) => {
                    tmp.iter_mut().zip(ya).zip(wt).for_each(|((t, v), w)| *t = v * w);
                    filters::add_adjoint(*d, &tmp, w, h, self.block_lambda(a), out);
                }
                None => filters::add_adjoint(*d, ya, w, h, self.block_lambda(a), out),
            }
        }
        for (l, cc) in self.cross.iter().enumerate() {
            for (a, d) in FIRST.iter().enumerate() {
                let yy = &y[(ALL.len() + 2 * l + a) * n..(ALL.len() + 2 * l + a + 1) * n];
                for i in 0..n {
                    let v = self.weight.map_or(yy[i], |wt| wt[i] * yy[i]) * cc.pixel.as_ref().map_or(1.0, |p| p[i]);
                    tmp[i] = cc.image[i] * v;
                    out[i] -= cc.beta * cc.grad[a][i] * v;
                }
                filters::add_adjoint(*d, &tmp, w, h, cc.beta, out);
            }
        }
    }

    fn prox_f_conj(&mut self, _sigma: f32, y: &mut [f32]) {
        for v in y.iter_mut() {
            *v = v.clamp(-1.0, 1.0);
        }
    }

    fn prox_g(&mut self, tau: f32, x: &mut [f32]) {
        self.counters.prox_calls += 1;
        let mut spec = std::mem::take(&mut self.spec);
        if self.mask.is_none() && self.dark.is_none() {
            self.fft.forward_into(x, &mut spec);
            let t2 = 2.0 * tau;
            for ((s, bj), b2) in spec.iter_mut().zip(&self.bj).zip(&self.kernel.b2) {
                *s = (*s + bj * t2) / (t2 * b2 + 1.0);
            }
            self.fft.inverse_into(&mut spec, x);
        } else {
            let t2 = 2.0 * tau;
            let mut rhs: Vec<f32> = x.iter().zip(&self.btmj).map(|(u, b)| u + t2 * b).collect();
            if let Some(d) = &self.dark {
                let c = t2 * d.lambda_b;
                rhs.iter_mut().zip(&d.target).for_each(|(r, t)| *r += c * t);
            }
            let mut u = if self.u_prev.len() == x.len() { std::mem::take(&mut self.u_prev) } else { x.to_vec() };
            let mut spec2 = spec.clone();
            let this = &*self;
            let st = conjugate_gradient(
                |v, out| this.apply_system(tau, v, out, &mut spec),
                |r, out| {
                    this.fft.forward_into(r, &mut spec2);
                    for (s, b2) in spec2.iter_mut().zip(&this.kernel.b2) {
                        *s /= t2 * b2 + 1.0;
                    }
                    this.fft.inverse_into(&mut spec2, out);
                },
                &rhs,
                &mut u,
                self.cg_max_iterations,
                self.cg_tolerance,
            );
            self.counters.cg_iterations += st.iterations;
            x.copy_from_slice(&u);
            self.u_prev = u;
        }
        self.spec = spec;
    }
}

/// `Σ_a H_aᵀ D_w² H_a v` accumulated into `out` (for the dark term's right-hand side).
pub fn add_weighted_gradient_normal(v: &[f32], w2: &[f32], width: usize, height: usize, out: &mut [f32]) {
    let mut g = vec![0.0; v.len()];
    for a in FIRST {
        filters::apply(a, v, width, height, &mut g);
        g.iter_mut().zip(w2).for_each(|(x, w)| *x *= w);
        filters::add_adjoint(a, &g, width, height, 1.0, out);
    }
}

/// The first-order gradients `[H_1 v, H_2 v]`.
pub fn gradients(v: &[f32], width: usize, height: usize) -> [Vec<f32>; 2] {
    let mut gx = vec![0.0; v.len()];
    let mut gy = vec![0.0; v.len()];
    filters::apply(Derivative::Dx, v, width, height, &mut gx);
    filters::apply(Derivative::Dy, v, width, height, &mut gy);
    [gx, gy]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::conv::kernel_to_origin;
    use crate::image::Plane;

    fn field(n: usize, seed: u32) -> Vec<f32> {
        (0..n).map(|i| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed) >> 9) % 1000) as f32 / 1000.0).collect()
    }

    /// <K x, y> = <x, Kᵀ y> with cross-channel blocks present.
    #[test]
    fn k_and_kt_are_adjoint() {
        let (w, h) = (12, 10);
        let n = w * h;
        let fft = Fft2::plan(w, h);
        let k = Plane::filled(3, 3, 1.0 / 9.0);
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&k, w, h));
        let other = field(n, 5);
        let cross = vec![CrossChannel { beta: 0.7, grad: gradients(&other, w, h), image: &other, pixel: Some(field(n, 31).iter().map(|v| 0.5 + v).collect()) }];
        let wt: Vec<f32> = field(n, 23).iter().map(|v| 0.2 + v).collect();
        let mut p = ChannelProblem::new(&fft, &ks, &field(n, 1), None, 0.3, &cross, None);
        p.set_weight(Some(&wt));
        p.order2_weight = 0.4;
        crate::solve::operator::tests::check(&crate::solve::operator::PrimalDualOperator(&p), 11).expect("adjoint");
    }

    /// The primal objective `‖M(Bx − ΔJ)‖² + ‖Kx‖₁`.
    fn objective(p: &ChannelProblem, x: &[f32], data: &[f32], mask: Option<&[f32]>) -> f64 {
        let mut bx = convolve_spec_test(p, x);
        bx.iter_mut().zip(data).for_each(|(b, d)| *b -= d);
        if let Some(m) = mask {
            bx.iter_mut().zip(m).for_each(|(b, m)| *b *= m);
        }
        let mut kx = vec![0.0; p.dual_len()];
        p.apply_k(x, &mut kx);
        bx.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() + kx.iter().map(|v| v.abs() as f64).sum::<f64>()
    }

    fn convolve_spec_test(p: &ChannelProblem, x: &[f32]) -> Vec<f32> {
        let mut s = p.fft.forward(x);
        s.iter_mut().zip(&p.kernel.b).for_each(|(a, b)| *a *= b);
        p.fft.inverse(s)
    }

    /// ADMM and Chambolle–Pock minimise the same objective: with per-pixel weights, a
    /// cross-channel block and (second case) a saturation mask, ADMM's result is as good as a
    /// long Chambolle–Pock run.
    #[test]
    fn admm_reaches_the_primal_dual_minimum() {
        use crate::solve::operator::PrimalDualOperator;
        use crate::solve::power::operator_norm;
        use crate::solve::primal_dual::{chambolle_pock, Options, NORM_SAFETY};
        let (w, h) = (24, 20);
        let n = w * h;
        let fft = Fft2::plan(w, h);
        let k = Plane::from_fn(5, 5, |x, y| 1.0 / (1.0 + (x as f32 - 2.0).powi(2) + (y as f32 - 1.5).powi(2)));
        let s = k.sum() as f32;
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&k.map(|v| v / s), w, h));
        let data = field(n, 3);
        let other = field(n, 5);
        let cross = vec![CrossChannel { beta: 0.02, grad: gradients(&other, w, h), image: &other, pixel: Some(field(n, 31).iter().map(|v| 0.5 + v).collect()) }];
        let wt: Vec<f32> = field(n, 23).iter().map(|v| 0.5 + v).collect();
        let mask: Vec<f32> = (0..n).map(|i| if i % 7 == 3 { 0.0 } else { 1.0 }).collect();
        // unknown boundary: no data within 2 px of the edge (the kernel radius)
        let edge: Vec<f32> = (0..n).map(|i| if (2..w - 2).contains(&(i % w)) && (2..h - 2).contains(&(i / w)) && i % 7 != 3 { 1.0 } else { 0.0 }).collect();
        for (m, split) in [(None, None), (Some(&mask[..]), None), (Some(&mask[..]), Some(2.0)), (Some(&edge[..]), Some(2.0)), (None, Some(1.0))] {
            let mut a = ChannelProblem::new(&fft, &ks, &data, m, 0.01, &cross, None);
            a.set_weight(Some(&wt));
            a.order2_weight = 0.5;
            a.data_split = split;
            let mut xa = data.clone();
            a.solve_admm(&mut xa, if split.is_some() { 1500 } else { 400 }, 0.5, 10);
            // the split's one-step (fast) x-update reaches the same minimum
            if split.is_some() {
                let mut xf = data.clone();
                a.solve_admm(&mut xf, 3000, 0.5, 1);
                let (ff, fa) = (objective(&a, &xf, &data, m), objective(&a, &xa, &data, m));
                assert!(ff <= fa * 1.003 + 1e-6, "split fast {ff} vs CG {fa}");
            }
            let mut b = ChannelProblem::new(&fft, &ks, &data, m, 0.01, &cross, None);
            b.set_weight(Some(&wt));
            b.order2_weight = 0.5;
            b.cg_max_iterations = 50;
            b.cg_tolerance = 1e-7;
            let mut xb = data.clone();
            let mut y = vec![0.0; b.dual_len()];
            let l = operator_norm(&PrimalDualOperator(&b), 30, NORM_SAFETY);
            let opts = Options { max_iterations: 3000, min_iterations: 3000, tolerance: 0.0, check_every: 1000, sigma: 3.0 / l, theta: 1.0 };
            chambolle_pock(&mut b, &mut xb, &mut y, &opts, Some(l), |_, _| true);
            let (fa, fb) = (objective(&a, &xa, &data, m), objective(&b, &xb, &data, m));
            let start = objective(&a, &data, &data, m);
            assert!(fa < start * 0.95, "ADMM did not descend: {fa} vs start {start}");
            assert!(fa <= fb * 1.002 + 1e-6, "mask {} split {split:?}: ADMM {fa} vs CP {fb}", m.is_some());
        }
    }

    /// Positivity (`lower_bound = 0`): on noisy point sources over a zero background, where the
    /// free solution (weak prior) dips below zero, every `x`-update path (Fourier division; one-step with the
    /// data split and a cross-channel block; CG with a mask) keeps the result non-negative and
    /// reaches an objective no worse than the free solution clipped to zero (a feasible point).
    #[test]
    fn lower_bound_keeps_point_sources_non_negative() {
        let (w, h) = (32, 24);
        let n = w * h;
        let fft = Fft2::plan(w, h);
        let k = Plane::from_fn(7, 7, |x, y| (-((x as f32 - 3.0).powi(2) + (y as f32 - 3.0).powi(2)) / 4.0).exp());
        let s = k.sum() as f32;
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&k.map(|v| v / s), w, h));
        let mut truth = vec![0.0f32; n];
        for (i, v) in [(5 * w + 6, 1.0), (12 * w + 20, 0.7), (18 * w + 9, 0.9), (7 * w + 25, 0.5)] {
            truth[i] = v;
        }
        let noise = field(n, 7);
        let mut data = convolve_spec_test(&ChannelProblem::new(&fft, &ks, &truth, None, 0.0, &[], None), &truth);
        data.iter_mut().zip(&noise).for_each(|(d, z)| *d += 0.004 * (z - 0.5));
        let other: Vec<f32> = truth.iter().map(|v| 0.05 + v).collect();
        let cross = [CrossChannel { beta: 0.002, grad: gradients(&other, w, h), image: &other, pixel: None }];
        let mask: Vec<f32> = (0..n).map(|i| if i % 11 == 4 { 0.0 } else { 1.0 }).collect();
        for (m, split, cc, cg) in [(None, None, &[][..], 1), (Some(&mask[..]), Some(2.0), &cross[..], 1), (Some(&mask[..]), None, &cross[..], 10)] {
            let run = |bound: bool| {
                let mut p = ChannelProblem::new(&fft, &ks, &data, m, 1e-4, cc, None);
                p.data_split = split;
                p.lower_bound = bound.then(|| vec![0.0; n]);
                let mut x = vec![0.0; n];
                p.solve_admm(&mut x, 1500, 0.5, cg);
                let f = |x: &[f32]| objective(&p, &x.iter().map(|v| v.max(0.0)).collect::<Vec<_>>(), &data, m);
                (x.clone(), f(&x))
            };
            let (free, f_free) = run(false);
            let (pos, f_pos) = run(true);
            let lo = |x: &[f32]| x.iter().fold(f32::INFINITY, |a, b| a.min(*b));
            assert!(lo(&free) < -0.004, "nothing below zero to remove: {}", lo(&free));
            assert!(lo(&pos) > -2e-3, "split {split:?}: min {}", lo(&pos));
            assert!(f_pos <= f_free * 1.002, "split {split:?}: bounded {f_pos} vs clipped free {f_free}");
        }
    }

    /// `K` carries `λ` on the first-order blocks, `λ μ₂` on the second-order ones and
    /// `β p_k` on a cross-channel block.
    #[test]
    fn block_weights_enter_k() {
        let (w, h) = (10, 8);
        let n = w * h;
        let fft = Fft2::plan(w, h);
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&Plane::filled(1, 1, 1.0), w, h));
        let other = field(n, 5);
        let pix: Vec<f32> = field(n, 31).iter().map(|v| 0.5 + v).collect();
        let with = vec![CrossChannel { beta: 0.7, grad: gradients(&other, w, h), image: &other, pixel: Some(pix.clone()) }];
        let without = vec![CrossChannel { beta: 0.7, grad: gradients(&other, w, h), image: &other, pixel: None }];
        let x = field(n, 11);
        let mut p = ChannelProblem::new(&fft, &ks, &field(n, 1), None, 0.3, &with, None);
        p.order2_weight = 0.25;
        let q = ChannelProblem::new(&fft, &ks, &field(n, 1), None, 0.3, &without, None);
        let (mut kp, mut kq) = (vec![0.0; p.dual_len()], vec![0.0; q.dual_len()]);
        p.apply_k(&x, &mut kp);
        q.apply_k(&x, &mut kq);
        for i in 0..ALL.len() * n {
            let f = if i < 2 * n { 1.0 } else { 0.25 };
            assert!((kp[i] - f * kq[i]).abs() < 1e-6, "block {}: {} vs {}", i / n, kp[i], kq[i]);
        }
        for i in ALL.len() * n..kp.len() {
            assert!((kp[i] - pix[i % n] * kq[i]).abs() < 1e-6);
        }
    }

    /// With an all-ones mask, the CG prox equals the closed-form Fourier prox.
    #[test]
    fn cg_prox_matches_fourier_prox_for_full_mask() {
        let (w, h) = (16, 12);
        let n = w * h;
        let fft = Fft2::plan(w, h);
        let k = Plane::from_fn(5, 5, |x, y| 1.0 / (1.0 + (x as f32 - 2.0).powi(2) + (y as f32 - 2.0).powi(2)));
        let s = k.sum() as f32;
        let k = k.map(|v| v / s);
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&k, w, h));
        let j = field(n, 3);
        let ones = vec![1.0; n];
        let mut a = ChannelProblem::new(&fft, &ks, &j, None, 0.1, &[], None);
        let mut b = ChannelProblem::new(&fft, &ks, &j, Some(&ones), 0.1, &[], None);
        b.cg_max_iterations = 200;
        b.cg_tolerance = 1e-6;
        let mut xa = field(n, 9);
        let mut xb = xa.clone();
        a.prox_g(0.8, &mut xa);
        b.prox_g(0.8, &mut xb);
        for (p, q) in xa.iter().zip(&xb) {
            assert!((p - q).abs() < 1e-4, "{p} vs {q}");
        }
    }
}
