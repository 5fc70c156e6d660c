//! [`ChannelProblem`]'s steps for the one ADMM loop ([`crate::solve::admm`]): the splits
//! `z_a = H_a x` and `z = (D_{i_l} H_a − D_{H_a i_l}) x` (per cross-channel block), the
//! per-pixel weights folded into the shrinkage thresholds, the optional positivity split
//! `z_+ = x` (prox: the projection onto `x ≥ ℓ`; it adds `ρ I` to the `x`-update's system),
//! the optional data split `v = B x`
//! (kept here, with its own scaled dual `u_v`), and the three `x`-updates: a Fourier division
//! (no mask, no cross-channel block), one preconditioned steepest-descent step with `P x` and
//! `ρ CᵀC x` carried along (unmasked, one CG step), or a few preconditioned, warm-started
//! conjugate-gradient steps. Arrays are on the tile's periodic FFT domain, row-major.

use super::super::filters::ALL;
use super::ChannelProblem;
use crate::solve::admm::AdmmSteps;
use crate::solve::cg::conjugate_gradient;
use rustfft::num_complex::Complex32;

/// Which `x`-update applies.
#[derive(Clone, Copy, PartialEq, Eq)]
enum XUpdate {
    /// `(data_w BᵀB + ρ ΣHᵀH) x = rhs` in Fourier.
    Direct,
    /// One preconditioned steepest-descent step (= one warm-started PCG iteration).
    Fast,
    /// Preconditioned conjugate gradients.
    Cg,
}

/// The state of one [`ChannelProblem::solve_admm`] run.
pub(super) struct ChannelAdmm<'p, 'a> {
    p: &'p ChannelProblem<'a>,
    rho: f32,
    cg_iterations: usize,
    /// `ρ_v` of the data split (`None`: no split).
    split: Option<f32>,
    /// The mask as the `x`-update sees it (`None` with the data split).
    xmask: Option<&'a [f32]>,
    mode: XUpdate,
    /// `Σ_a |Ĥ_a|²`.
    sh: Vec<f32>,
    /// `data_w |B̂|² + ρ Σ|Ĥ_a|²` and its inverse.
    denom: Vec<f32>,
    inv_denom: Vec<f32>,
    /// Shrinkage threshold per block (before the per-pixel weight): `λ/ρ`, `β_l/ρ`.
    scale: Vec<f32>,
    /// Per-pixel threshold factors of the cross-channel blocks: `w_k · p_k`.
    cross_w: Vec<Option<Vec<f32>>>,
    spec: Vec<Complex32>,
    spec2: Vec<Complex32>,
    /// `2 BᵀM ΔJ` (CG paths), or `ρ_v Bᵀ(v − u_v)` with the data split.
    two_btj: Vec<f32>,
    /// Data split: `B x`, the scaled dual `u_v`, and `v − u_v`.
    bx: Vec<f32>,
    uv: Vec<f32>,
    dv: Vec<f32>,
    rhs: Vec<f32>,
    /// Fast path: `P x`, `ρ CᵀC x`, residual, direction, `ρ CᵀC p`.
    px: Vec<f32>,
    cx: Vec<f32>,
    r: Vec<f32>,
    dir: Vec<f32>,
    cp: Vec<f32>,
    /// Three planes of cross-channel scratch.
    kbuf: Vec<f32>,
    /// CG scratch.
    s0: Vec<Complex32>,
    s1: Vec<Complex32>,
    s2: Vec<Complex32>,
    bu: Vec<f32>,
}

impl<'p, 'a> ChannelAdmm<'p, 'a> {
    /// Precomputes the spectra, thresholds and path state; `x` is the warm start.
    pub(super) fn new(p: &'p ChannelProblem<'a>, x: &[f32], rho: f32, cg_iterations: usize) -> Self {
        let n = p.n();
        // the positivity split z_+ = x adds ρ I to the x-update's system
        let sh: Vec<f32> = p.derivative_power().into_iter().map(|v| v + if p.lower_bound.is_some() { 1.0 } else { 0.0 }).collect();
        // with the data split v = Bx the data enters the x-update as ρ_v BᵀB, and the mask
        // lives in the v-prox only
        let split = p.data_split;
        let data_w = split.unwrap_or(2.0);
        let xmask = if split.is_some() { None } else { p.mask };
        let denom: Vec<f32> = sh.iter().zip(&p.kernel.b2).map(|(s, b2)| (data_w * b2 + rho * s).max(1e-12)).collect();
        let inv_denom: Vec<f32> = denom.iter().map(|d| 1.0 / d).collect();
        let direct = xmask.is_none() && p.cross.is_empty();
        // Fast inexact x-update (the default: unmasked, one CG step): one preconditioned
        // steepest-descent step with exact line search, which is what one warm-started PCG
        // iteration is, with `P x` and `ρ CᵀC x` carried along instead of recomputed: since
        // `P p = r` for `p = P⁻¹ r`, `A p = r + ρ CᵀC p` needs no transform, so a step costs two
        // FFTs and one cross-channel normal product (the generic path: seven and two).
        let fast = !direct && xmask.is_none() && cg_iterations == 1;
        let mode = if direct {
            XUpdate::Direct
        } else if fast {
            XUpdate::Fast
        } else {
            XUpdate::Cg
        };
        let scale = block_scales(p, rho);
        let cross_w = cross_weights(p);
        let spec = vec![Complex32::new(0.0, 0.0); p.fft.spectrum_len()];
        let scratch = |on: bool| if on { vec![0.0f32; n] } else { Vec::new() };
        let mut s = Self {
            p,
            rho,
            cg_iterations,
            split,
            xmask,
            mode,
            sh,
            denom,
            inv_denom,
            scale,
            cross_w,
            spec2: if split.is_some() { spec.clone() } else { Vec::new() },
            two_btj: Vec::new(),
            bx: scratch(split.is_some()),
            uv: scratch(split.is_some()),
            dv: scratch(split.is_some()),
            rhs: vec![0.0f32; n],
            px: scratch(fast),
            cx: scratch(fast),
            r: scratch(fast),
            dir: scratch(fast),
            cp: scratch(fast),
            kbuf: if direct { Vec::new() } else { vec![0.0f32; 3 * n] },
            s0: if mode == XUpdate::Cg { spec.clone() } else { Vec::new() },
            s1: if mode == XUpdate::Cg { spec.clone() } else { Vec::new() },
            s2: if mode == XUpdate::Cg { spec.clone() } else { Vec::new() },
            bu: scratch(mode == XUpdate::Cg),
            spec,
        };
        s.prime(x);
        s
    }

    /// Warm-start stage of [`Self::new`]: the data right-hand side, `B x` with the data split,
    /// and `P x`, `ρ CᵀC x` for the fast x-update.
    fn prime(&mut self, x: &[f32]) {
        self.two_btj = self.data_rhs();
        if self.split.is_some() {
            self.bx = self.blur(x);
        }
        if self.mode == XUpdate::Fast {
            self.p.fft.forward_into(x, &mut self.spec);
            self.spec.iter_mut().zip(&self.denom).for_each(|(sp, d)| *sp *= d);
            self.p.fft.inverse_into(&mut self.spec, &mut self.px);
            self.p.add_cross_normal(x, self.rho, &mut self.kbuf, &mut self.cx);
        }
    }

    /// `2 BᵀM ΔJ`, spatial, for the CG paths (zeros with the data split, which refills it
    /// every iteration; empty for the Fourier division).
    fn data_rhs(&mut self) -> Vec<f32> {
        let n = self.p.n();
        if self.mode == XUpdate::Direct {
            return Vec::new();
        }
        if self.split.is_some() {
            return vec![0.0f32; n];
        }
        let mut t = if self.p.mask.is_none() {
            let mut s = self.p.bj.clone();
            let mut t = vec![0.0; n];
            self.p.fft.inverse_into(&mut s, &mut t);
            t
        } else {
            self.p.btmj.clone()
        };
        t.iter_mut().for_each(|v| *v *= 2.0);
        t
    }

    /// `B x`, spatial.
    fn blur(&mut self, x: &[f32]) -> Vec<f32> {
        let mut bx = vec![0.0f32; self.p.n()];
        self.p.fft.forward_into(x, &mut self.spec);
        self.spec.iter_mut().zip(&self.p.kernel.b).for_each(|(s, b)| *s *= b);
        self.p.fft.inverse_into(&mut self.spec, &mut bx);
        bx
    }

    /// The Fourier division: `x = P⁻¹ (ρ rhs + data)`, with `B x` carried along under the data
    /// split.
    fn x_update_direct(&mut self, x: &mut [f32]) {
        let (p, rho) = (self.p, self.rho);
        p.fft.forward_into(&self.rhs, &mut self.spec);
        if let Some(rv) = self.split {
            p.fft.forward_into(&self.dv, &mut self.spec2);
            for (((s, s2), b), d) in self.spec.iter_mut().zip(self.spec2.iter_mut()).zip(&p.kernel.b).zip(&self.inv_denom) {
                *s = (*s * rho + *s2 * b.conj() * rv) * d;
                *s2 = *s * b;
            }
            p.fft.inverse_into(&mut self.spec, x);
            p.fft.inverse_into(&mut self.spec2, &mut self.bx);
            return;
        }
        for ((s, b), d) in self.spec.iter_mut().zip(&p.bj).zip(&self.inv_denom) {
            *s = (*s * rho + b * 2.0) * d;
        }
        p.fft.inverse_into(&mut self.spec, x);
    }

    /// One preconditioned steepest-descent step with exact line search.
    fn x_update_fast(&mut self, x: &mut [f32]) {
        let (p, n) = (self.p, self.p.n());
        for i in 0..n {
            self.r[i] = self.rhs[i] - self.px[i] - self.cx[i];
        }
        p.fft.forward_into(&self.r, &mut self.spec);
        self.spec.iter_mut().zip(&self.inv_denom).for_each(|(s, d)| *s *= d);
        if self.split.is_some() {
            // B p, to carry B x along (dv is free again: it holds B p)
            self.spec2.iter_mut().zip(&self.spec).zip(&p.kernel.b).for_each(|((t, s), b)| *t = s * b);
            p.fft.inverse_into(&mut self.spec2, &mut self.dv);
        }
        p.fft.inverse_into(&mut self.spec, &mut self.dir);
        self.cp.iter_mut().for_each(|v| *v = 0.0);
        p.add_cross_normal(&self.dir, self.rho, &mut self.kbuf, &mut self.cp);
        let (mut rz, mut pap) = (0.0f64, 0.0f64);
        for i in 0..n {
            rz += self.r[i] as f64 * self.dir[i] as f64;
            pap += self.dir[i] as f64 * (self.r[i] + self.cp[i]) as f64;
        }
        if pap > 0.0 && pap.is_finite() {
            let alpha = (rz / pap) as f32;
            for i in 0..n {
                x[i] += alpha * self.dir[i];
                self.px[i] += alpha * self.r[i];
                self.cx[i] += alpha * self.cp[i];
            }
            if self.split.is_some() {
                self.bx.iter_mut().zip(&self.dv).for_each(|(b, d)| *b += alpha * d);
            }
        }
    }

    /// Preconditioned conjugate gradients on `(data_w BᵀMB + ρ ΣHᵀH + ρ ΣCᵀC) x = rhs`;
    /// returns the iterations spent.
    fn x_update_cg(&mut self, x: &mut [f32]) -> usize {
        let Self { p, rho, xmask, denom, inv_denom, sh, kbuf, s0, s1, s2, bu, rhs, cg_iterations, .. } = self;
        let (p, rho, xmask, cg_iterations) = (*p, *rho, *xmask, *cg_iterations);
        let st = conjugate_gradient(
            |v, out| {
                // 2BᵀMBv + ρ ΣHᵀH v in Fourier when unmasked, then ρ CᵀC v
                p.fft.forward_into(v, s1);
                match xmask {
                    None => {
                        for (s, d) in s1.iter_mut().zip(denom.iter()) {
                            *s *= d;
                        }
                        p.fft.inverse_into(s1, out);
                    }
                    Some(m) => {
                        s0.copy_from_slice(s1);
                        for (s, b) in s1.iter_mut().zip(&p.kernel.b) {
                            *s *= b;
                        }
                        p.fft.inverse_into(s1, bu);
                        bu.iter_mut().zip(m).for_each(|(v, m)| *v *= m);
                        p.fft.forward_into(bu, s1);
                        for (((s, b), s0), sh) in s1.iter_mut().zip(&p.kernel.b).zip(s0.iter()).zip(sh.iter()) {
                            *s = *s * b.conj() * 2.0 + s0 * (rho * sh);
                        }
                        p.fft.inverse_into(s1, out);
                    }
                }
                if !p.cross.is_empty() {
                    p.add_cross_normal(v, rho, kbuf, out);
                }
            },
            |r, out| {
                p.fft.forward_into(r, s2);
                for (s, d) in s2.iter_mut().zip(inv_denom.iter()) {
                    *s *= d;
                }
                p.fft.inverse_into(s2, out);
            },
            rhs,
            x,
            cg_iterations,
            1e-4,
        );
        if self.split.is_some() {
            self.bx = self.blur(x);
        }
        st.iterations
    }
}

impl AdmmSteps for ChannelAdmm<'_, '_> {
    fn block_len(&self) -> usize {
        self.p.n()
    }

    fn blocks(&self) -> usize {
        self.scale.len() + usize::from(self.p.lower_bound.is_some())
    }

    /// The data split: `v = argmin ‖M(v − ΔJ)‖² + ρ_v/2 ‖v − (Bx + u_v)‖²` (elementwise),
    /// `u_v ← Bx + u_v − v`, `dv = v − u_v`, and `ρ_v Bᵀ dv` in place of `2BᵀMΔJ`.
    fn auxiliary_update(&mut self, _x: &[f32]) {
        let Some(rv) = self.split else { return };
        let p = self.p;
        let c = 2.0 / rv;
        for i in 0..p.n() {
            let t = self.bx[i] + self.uv[i];
            let m = p.mask.map_or(1.0, |m| m[i]);
            let v = (c * p.mj[i] + t) / (c * m + 1.0);
            self.uv[i] = t - v;
            self.dv[i] = v - self.uv[i];
        }
        if self.mode != XUpdate::Direct {
            p.fft.forward_into(&self.dv, &mut self.spec2);
            self.spec2.iter_mut().zip(&p.kernel.b).for_each(|(s, b)| *s *= b.conj() * rv);
            p.fft.inverse_into(&mut self.spec2, &mut self.two_btj);
        }
    }

    fn apply_split(&self, x: &[f32], out: &mut [f32]) {
        self.p.apply_split(x, out);
        if self.p.lower_bound.is_some() {
            let k = self.scale.len() * self.p.n();
            out[k..k + x.len()].copy_from_slice(x);
        }
    }

    /// Clamps to the block's threshold (times the per-pixel weight); with reweighting the
    /// derivative blocks' threshold is scaled by `((|H_a x| + ε)/ε)^(q−1)`, a
    /// hyper-Laplacian-like prior that shrinks strong edges less than noise-sized gradients.
    fn project_dual(&self, blk: usize, kx: &[f32], v: &mut [f32]) {
        let p = self.p;
        if let (Some(lb), true) = (&p.lower_bound, blk == self.scale.len()) {
            // v − max(v, ℓ): the projection onto {z ≥ ℓ} through Moreau's identity
            v.iter_mut().zip(lb).for_each(|(v, l)| *v = (*v - l).min(0.0));
            return;
        }
        let s = self.scale[blk];
        if let (Some((q, eps)), true) = (p.reweight, blk < ALL.len()) {
            let inv = 1.0 / eps;
            for (i, (k, v)) in kx.iter().zip(v.iter_mut()).enumerate() {
                let g = if q == 0.5 { 1.0 / (1.0 + k.abs() * inv).sqrt() } else { (1.0 + k.abs() * inv).powf(q - 1.0) };
                let t = s * g * p.weight.map_or(1.0, |wt| wt[i]);
                *v = v.max(-t).min(t);
            }
            return;
        }
        let blk_w = if blk >= ALL.len() { self.cross_w[(blk - ALL.len()) / 2].as_deref().or(p.weight) } else { p.weight };
        match blk_w {
            Some(wt) => {
                for (v, w) in v.iter_mut().zip(wt) {
                    let t = s * w;
                    *v = v.max(-t).min(t);
                }
            }
            None => v.iter_mut().for_each(|v| *v = v.max(-s).min(s)),
        }
    }

    /// `rhs = ρ Kᵀ(z − u) (+ 2BᵀMΔJ)`, then the path's solve.
    fn x_update(&mut self, t: &[f32], x: &mut [f32]) -> usize {
        self.p.apply_split_adjoint(t, &mut self.rhs);
        if self.p.lower_bound.is_some() {
            let k = self.scale.len() * self.p.n();
            self.rhs.iter_mut().zip(&t[k..]).for_each(|(r, t)| *r += t);
        }
        if self.mode == XUpdate::Direct {
            self.x_update_direct(x);
            return 0;
        }
        let rho = self.rho;
        self.rhs.iter_mut().zip(&self.two_btj).for_each(|(r, t)| *r = *r * rho + t);
        if self.mode == XUpdate::Fast {
            self.x_update_fast(x);
            return 1;
        }
        self.x_update_cg(x)
    }
}

/// Threshold-scale stage of [`ChannelAdmm::new`]: `λ_blk / ρ` per derivative block, `β / ρ`
/// for both blocks of each cross-channel term.
fn block_scales(p: &ChannelProblem, rho: f32) -> Vec<f32> {
    let nblk = ALL.len() + 2 * p.cross.len();
    (0..nblk).map(|blk| if blk < ALL.len() { p.block_lambda(blk) / rho } else { p.cross[(blk - ALL.len()) / 2].beta / rho }).collect()
}

/// Cross-weight stage of [`ChannelAdmm::new`]: each cross-channel term's per-pixel weight
/// times the transfer weight (`None`: no per-pixel weight).
fn cross_weights(p: &ChannelProblem) -> Vec<Option<Vec<f32>>> {
    p.cross
        .iter()
        .map(|cc| {
            cc.pixel.as_ref().map(|px| match p.weight {
                Some(wt) => px.iter().zip(wt).map(|(p, w)| p * w).collect(),
                None => px.clone(),
            })
        })
        .collect()
}
