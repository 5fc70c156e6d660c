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
//! FISTA ([`crate::solve::fista`], no stall rule: a fixed number of iterations; a stop on
//! χ²'s decrease was measured never to act at 45 px, docs/notes/diagnosis-history.md "Session 18")
//! with a step `1/L` from power iteration, and the exact Euclidean projection onto
//! `{U ≥ 0, ΣU = S}` (the scaled simplex). Two steps ([`KernelStep`]): `L = 1.05 ‖AᵀWA‖` on the
//! whole space, no restart (the former step), or `L = 1.05 ‖P AᵀWA P‖` with adaptive restart (what
//! the diagnosis uses, [`super::fit::KERNEL_STEP`]), where `P` removes each kernel's mean. The
//! iterates stay on the simplices' affine hull, where the projection discards the gradient's
//! per-kernel flat component, so only the Hessian on the tangent space (zero-sum kernels) bounds
//! the step, as in [`crate::estimate::joint`]. The whole-space norm is set by the flat mode, whose
//! eigenvalue grows with `k²` (`≈ k²·mean(P)²` per pixel of weight): with it, 31–45-px kernels take
//! a step many times too small and stall far above the noise floor in the diagnosis' budgets
//! (docs/notes/diagnosis-history.md, "Realistic size").
//!
//! With the tangent step the momentum is carried from one solve to the next on the same
//! operator ([`KernelWarm`], [`crate::solve::fista::fista_resume`]): the next round of a fit
//! (whose weights and scalars moved a little) and the next round inside [`fit_kernels`]
//! continue FISTA's extrapolation `z − x` and its `t` (the offsets scaled with the common
//! sum) instead of starting again from `z = x, t = 1`; adaptive restart drops the momentum
//! where it no longer points downhill. At 45 px a fresh start spends the first 20–30 of a
//! round's 80 iterations rebuilding the momentum (docs/notes/diagnosis-history.md, "Session 18").
//! `A` and `Aᵀ` are the blocked kernel operator [`crate::optics::kernel_operator::KernelOperator`]
//! (mirrored at the image edges like [`crate::optics::forward::blur_channel`]).

use crate::image::Plane;
use crate::optics::kernel_operator::KernelOperator;
use crate::solve::fista::{fista_resume, Composite, FistaOptions, Momentum};
use crate::solve::operator::LinearOperator;
use crate::solve::power::{kernel_start, power_iteration, remove_block_means};
use crate::solve::prox::project_simplex;

/// Settings of [`fit_kernels`].
#[derive(Clone, Copy, Debug)]
pub struct KernelFitSettings {
    pub iterations: usize,
    /// Which Hessian norm sets the FISTA step (module docs, "Algorithm").
    pub step: KernelStep,
    /// Outer rounds of (kernels, common sum).
    pub rounds: usize,
}

/// The FISTA step of [`fit_kernels`]: `1/(1.05·L)` with `L` the norm of `AᵀWA`
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KernelStep {
    /// on the whole kernel space (set by the flat mode, `∝ k²`), no restart: the step the
    /// diagnosis' budgets and thresholds were tuned with.
    WholeSpace,
    /// on the simplices' tangent space (zero-sum kernels), with adaptive restart: reaches the
    /// noise floor in the base budget at 31–45 px
    /// (docs/notes/diagnosis-history.md, "Realistic size").
    Tangent,
}

/// Safety factor on the power iteration's `‖AᵀWA‖` for the FISTA step.
const STEP_SAFETY: f64 = 1.05;

/// Power-iteration products for `‖AᵀWA‖`.
const POWER_ITERATIONS: usize = 12;

/// `½‖W^{1/2}(A U − y)‖²` over the scaled simplices `ΣU_t = sum`.
struct WeightedFit<'a> {
    op: &'a KernelOperator,
    y: &'a [f32],
    weight: &'a [f32],
    k2: usize,
    sum: f32,
    pred: Vec<f32>,
}

impl Composite for WeightedFit<'_> {
    fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64 {
        let mut f = 0.0f64;
        let mut term = |pred: &mut [f32], y: &[f32], weight: &[f32]| {
            for ((p, q), w) in pred.iter_mut().zip(y).zip(weight) {
                let d = *p - q;
                *p = d * w;
                f += 0.5 * (d * *p) as f64;
            }
        };
        match self.op.kept_runs() {
            // a subsampled operator: only its kept blocks' pixels (the weights are 0 off them,
            // and the adjoint reads nothing else); the rest of `pred` stays 0. The same terms
            // in the same order as the whole-image loop, so the same bits.
            Some(runs) => {
                self.op.apply_kept(x, &mut self.pred);
                for &(a, n) in runs {
                    term(&mut self.pred[a..a + n], &self.y[a..a + n], &self.weight[a..a + n]);
                }
            }
            None => {
                self.op.apply(x, &mut self.pred);
                term(&mut self.pred, self.y, self.weight);
            }
        }
        self.op.apply_adjoint(&self.pred, out);
        f
    }

    fn prox(&mut self, _l: f32, v: &[f32], x: &mut [f32]) {
        x.copy_from_slice(v);
        for c in x.chunks_mut(self.k2) {
            project_simplex(c, self.sum);
        }
    }
}

/// Power-iteration products for `‖AᵀWA‖` from a warm start ([`StepNorm::warm`]): the previous
/// fit's dominant vector under weights that moved little.
const WARM_POWER_ITERATIONS: usize = 3;

/// `L = ‖AᵀWA‖` of a kernel problem (whole space or tangent space, [`KernelStep`]) with the
/// power iteration's last vector, which warm-starts the estimate for the next fit on the same
/// operator (the next round of a fit, whose weights moved little, or the divergence probe's
/// second solve): [`WARM_POWER_ITERATIONS`] products instead of 12.
#[derive(Clone, Debug, Default)]
pub struct StepNorm {
    vector: Option<Vec<f32>>,
}

impl StepNorm {
    /// A cold estimate (no vector yet).
    pub fn new() -> Self {
        Self::default()
    }

    /// `1.05·L` for `op` under `weight`, by power iteration from the stored vector when there
    /// is one of the right length (else from the step's cold start); stores the new vector.
    pub fn lipschitz(&mut self, op: &KernelOperator, weight: &[f32], k2: usize, step: KernelStep) -> f32 {
        let mut ax = vec![0.0f32; op.output_len()];
        let normal = |v: &[f32], out: &mut [f32]| {
            op.apply(v, &mut ax);
            ax.iter_mut().zip(weight).for_each(|(a, w)| *a *= w);
            op.apply_adjoint(&ax, out);
        };
        let warm = self.vector.take().filter(|v| v.len() == op.input_len());
        let (start, products) = match (warm, step) {
            (Some(v), _) => (v, WARM_POWER_ITERATIONS),
            (None, KernelStep::WholeSpace) => (vec![1.0; op.input_len()], POWER_ITERATIONS),
            (None, KernelStep::Tangent) => (kernel_start(op.input_len()), POWER_ITERATIONS),
        };
        let est = match step {
            KernelStep::WholeSpace => power_iteration(start, products, normal, |_| {}),
            KernelStep::Tangent => power_iteration(start, products, normal, |v| remove_block_means(v, k2)),
        };
        let norm = est.as_ref().map_or(0.0, |e| e.norm);
        self.vector = est.map(|e| e.vector);
        (STEP_SAFETY * norm.max(1e-30)) as f32
    }
}

/// What one channel's kernel solve hands to the next on the same operator (the next round of
/// a fit): the step's norm ([`StepNorm`]) and FISTA's momentum ([`Momentum`]) with the common
/// sum it was left at.
#[derive(Clone, Debug, Default)]
pub struct KernelWarm {
    pub norm: StepNorm,
    momentum: Momentum,
    /// The common sum `S` the momentum's offsets refer to.
    sum: f32,
}

impl KernelWarm {
    /// Whether no solve has left a momentum here.
    pub fn is_empty(&self) -> bool {
        self.momentum.ahead.is_empty()
    }
}

/// Pixels per kernel, `k²` (1 without kernels).
fn kernel_area(init: &[Plane]) -> usize {
    init.first().map_or(1, |k| k.width * k.height).max(1)
}

/// Fits the kernels of one channel (see the module docs), starting from `init` (each tile's
/// kernel is scaled to the common sum first). Returns the kernels `U_t` (summing to the fitted
/// `S`) and `S`.
pub fn fit_kernels(op: &KernelOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings) -> (Vec<Plane>, f32) {
    fit_kernels_warm(op, y, weight, init, settings, &mut KernelWarm::default())
}

/// [`fit_kernels`] with the step's norm estimated from `warm`'s start ([`StepNorm`]) and, when
/// it holds one, FISTA's momentum continued from the previous solve; leaves both in `warm`.
pub fn fit_kernels_warm(op: &KernelOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings, warm: &mut KernelWarm) -> (Vec<Plane>, f32) {
    let l = warm.norm.lipschitz(op, weight, kernel_area(init), settings.step);
    fit_kernels_with_step(op, y, weight, init, settings, l, warm)
}

/// [`fit_kernels_warm`] with the Lipschitz constant `l` given.
fn fit_kernels_with_step(op: &KernelOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings, l: f32, warm: &mut KernelWarm) -> (Vec<Plane>, f32) {
    let mut s = (init.iter().map(|k| k.sum()).sum::<f64>() / init.len().max(1) as f64) as f32;
    let (kw, kh) = init.first().map_or((0, 0), |k| (k.width, k.height));
    let k2 = kw * kh;
    let mut x: Vec<f32> = init.iter().flat_map(|k| k.data.iter().copied()).collect();
    for c in x.chunks_mut(k2.max(1)) {
        project_simplex(c, s);
    }
    let opts = FistaOptions { max_iterations: settings.iterations, min_iterations: usize::MAX, tolerance: 0.0, restart: settings.step == KernelStep::Tangent, stall: None };
    for _ in 0..settings.rounds.max(1) {
        let mut p = WeightedFit { op, y: &y.data, weight, k2, sum: s, pred: vec![0.0; op.output_len()] };
        // the momentum is carried only under adaptive restart (which drops it where it points
        // the wrong way); its offsets were left at the common sum `warm.sum`, `x` is at `s`
        if !opts.restart {
            warm.momentum = Momentum::default();
        }
        let scale = if warm.sum > 0.0 { s / warm.sum } else { 1.0 };
        fista_resume(&mut p, &mut x, &mut warm.momentum, scale, &opts, l, |_, _| true);
        // common sum by weighted least squares
        op.apply(&x, &mut p.pred);
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for ((p, q), w) in p.pred.iter().zip(&y.data).zip(weight) {
            num += (*w * p * q) as f64;
            den += (*w * p * p) as f64;
        }
        if den > 0.0 && num > 0.0 {
            let a = (num / den) as f32;
            x.iter_mut().for_each(|v| *v *= a);
            s *= a;
        }
        warm.sum = s;
    }
    let kernels = x.chunks(k2.max(1)).map(|c| Plane { width: kw, height: kh, data: c.to_vec() }).collect();
    (kernels, s)
}

/// Probe step of [`kernel_divergence`], in noise standard deviations.
pub const PROBE_EPS: f32 = 0.25;

/// Upper clamp of [`Divergence::highpass_absorbed`] (a fit that absorbs more of the noise
/// leaves too little residual to measure it from).
pub const MAX_ABSORBED: f64 = 0.5;

/// What one probe of [`kernel_divergence`] measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Divergence {
    /// The divergence `df` (the fit's effective parameter count).
    pub df: f64,
    /// The fraction of white noise's high-pass energy the fit absorbs,
    /// `α_hp = (2·Σ(Fb)(Fh) − Σ(Fh)²) / Σ(Fb)²` with `F` the high-pass of
    /// [`super::noise::highpass`] and `h` the whitened response to the probe `b`: the
    /// residual's high-pass holds `(1 − α_hp)` of the noise's (`E‖F(I − H)b‖² = tr FᵀF −
    /// 2·tr FᵀFH + tr HᵀFᵀFH`), which [`super::noise::measure_residual`] must divide out.
    pub highpass_absorbed: f64,
}

/// Monte-Carlo divergence of the kernel fit (docs/diagnosis.md, "Effective degrees of
/// freedom"): with a Rademacher probe `b` on the weighted pixels and `σ = W^{-1/2}`,
/// `df ≈ Σ_x b(x)·(m(y + ε·σ·b) − m(y))(x) / (ε·σ(x))`, where `m(y) = A·U(y)` is the prediction
/// of [`fit_kernels`] run with `settings` from `init` on target `y`. Both solves start from
/// `init`, so what the budget leaves unconverged cancels; `ε` is [`PROBE_EPS`]. The expectation
/// over `b` is the trace of the whitened fit's Jacobian, the effective parameter count of a
/// (locally) linear smoother: `E[χ²] = N − df` on data the model describes. The same probe gives
/// the share of the noise's high-pass the fit absorbs ([`Divergence::highpass_absorbed`], over
/// the pixels whose 5-point stencil is weighted).
pub fn kernel_divergence(op: &KernelOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings, rng: &mut crate::rng::Rng) -> Divergence {
    kernel_divergence_with(op, y, weight, init, settings, &rademacher(weight.len(), rng))
}

/// `n` Rademacher values (±1) from `rng`: the probe of [`kernel_divergence`].
pub fn rademacher(n: usize, rng: &mut crate::rng::Rng) -> Vec<f32> {
    (0..n).map(|_| if rng.next_u32() & 1 == 0 { -1.0 } else { 1.0 }).collect()
}

/// [`kernel_divergence`] with the probe `b` given (one value per pixel of `weight`). The two
/// solves are independent and run concurrently.
pub fn kernel_divergence_with(op: &KernelOperator, y: &Plane, weight: &[f32], init: &[Plane], settings: KernelFitSettings, b: &[f32]) -> Divergence {
    let mut yp = y.clone();
    for ((v, w), bb) in yp.data.iter_mut().zip(weight).zip(b) {
        if *w > 0.0 {
            *v += PROBE_EPS * bb / w.sqrt();
        }
    }
    // the two solves share the weights, hence the step
    let l = StepNorm::new().lipschitz(op, weight, kernel_area(init), settings.step);
    let (mut wa, mut wb) = (KernelWarm::default(), KernelWarm::default());
    let ((pa, _), (pb, _)) = rayon::join(
        || {
            let (ua, s) = fit_kernels_with_step(op, y, weight, init, settings, l, &mut wa);
            (op.apply_planes(&ua), s)
        },
        || {
            let (ub, s) = fit_kernels_with_step(op, &yp, weight, init, settings, l, &mut wb);
            (op.apply_planes(&ub), s)
        },
    );
    // the whitened response `h = W^{1/2}·Δm/ε` and the probe, 0 off the weighted pixels
    let mut h = vec![0.0f32; weight.len()];
    let mut bw = vec![0.0f32; weight.len()];
    let mut df = 0.0f64;
    for i in 0..weight.len() {
        if weight[i] > 0.0 {
            h[i] = (pb.data[i] - pa.data[i]) * weight[i].sqrt() / PROBE_EPS;
            bw[i] = b[i];
            df += (b[i] * h[i]) as f64;
        }
    }
    let (w, rows) = (y.width, y.height);
    let (mut cross, mut hh, mut bb) = (0.0f64, 0.0f64, 0.0f64);
    for yy in 1..rows.saturating_sub(1) {
        for x in 1..w.saturating_sub(1) {
            let i = yy * w + x;
            if [i, i - 1, i + 1, i - w, i + w].iter().all(|&j| weight[j] > 0.0) {
                let (fb, fh) = (super::noise::highpass(&bw, w, i) as f64, super::noise::highpass(&h, w, i) as f64);
                cross += fb * fh;
                hh += fh * fh;
                bb += fb * fb;
            }
        }
    }
    let highpass_absorbed = if bb > 0.0 { ((2.0 * cross - hh) / bb).clamp(0.0, MAX_ABSORBED) } else { 0.0 };
    Divergence { df, highpass_absorbed }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::psf_grid::PsfGrid;
    use crate::rng::Rng;

    fn grid(w: usize, h: usize, k: usize, seed: u64) -> PsfGrid {
        crate::optics::kernel_operator::tests::grid(w, h, k, 3, 2, seed)
    }

    #[test]
    fn fit_recovers_kernels_and_sum() {
        let (w, h, k) = (90, 60, 5);
        let mut r = Rng::new(3);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let truth = grid(w, h, k, 4);
        let op = KernelOperator::new(&sharp, &truth, usize::MAX);
        let mut y = op.apply_planes(&truth.kernels[0]);
        y.scale(1.7);
        let wt = vec![1.0; w * h];
        let init: Vec<Plane> = (0..6).map(|_| Plane::filled(k, k, 1.0 / (k * k) as f32)).collect();
        let (u, s) = fit_kernels(&op, &y, &wt, &init, KernelFitSettings { iterations: 300, rounds: 2, step: KernelStep::Tangent });
        assert!((s - 1.7).abs() < 0.01, "{s}");
        for (a, b) in u.iter().zip(&truth.kernels[0]) {
            let e = crate::estimate::relative_error(&a.map(|v| v / 1.7), b);
            assert!(e < 0.05, "{e}");
        }
    }

    /// The warm-started norm ([`StepNorm`]): after a cold estimate, three products from its
    /// vector under weights that moved by up to ±20 % give the cold 12-product estimate of the
    /// new weights within 2 % (and a step that stays safe: FISTA from there still fits).
    #[test]
    fn warm_step_norm_matches_a_cold_one() {
        let (w, h, k) = (90, 60, 5);
        let mut r = Rng::new(7);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let truth = grid(w, h, k, 8);
        let op = KernelOperator::new(&sharp, &truth, usize::MAX);
        let wt: Vec<f32> = (0..w * h).map(|_| 1.0 + 0.5 * r.uniform() as f32).collect();
        let moved: Vec<f32> = wt.iter().map(|v| v * (0.8 + 0.4 * r.uniform() as f32)).collect();
        for step in [KernelStep::Tangent, KernelStep::WholeSpace] {
            let mut warm = StepNorm::new();
            warm.lipschitz(&op, &wt, k * k, step);
            let l_warm = warm.lipschitz(&op, &moved, k * k, step);
            let l_cold = StepNorm::new().lipschitz(&op, &moved, k * k, step);
            assert!((l_warm / l_cold - 1.0).abs() < 0.02, "{step:?}: warm {l_warm} cold {l_cold}");
        }
        let y = op.apply_planes(&truth.kernels[0]);
        let init: Vec<Plane> = (0..6).map(|_| Plane::filled(k, k, 1.0 / (k * k) as f32)).collect();
        let mut norm = KernelWarm::default();
        let set = KernelFitSettings { iterations: 150, rounds: 1, step: KernelStep::Tangent };
        let (u1, _) = fit_kernels_warm(&op, &y, &wt, &init, set, &mut norm);
        let (u2, _) = fit_kernels_warm(&op, &y, &moved, &u1, set, &mut norm);
        for (a, b) in u2.iter().zip(&truth.kernels[0]) {
            let e = crate::estimate::relative_error(a, b);
            assert!(e < 0.05, "{e}");
        }
    }

    /// Kernels with no zero entry (the non-negativity is inactive) fitted to convergence: the
    /// fit is a linear least-squares projection, so its divergence is its parameter count,
    /// `T·(k² − 1) + 1` (one sum per tile, and the common sum free). On a white target the
    /// tangent-space Hessian is nearly a multiple of the identity, so with the tangent-space
    /// step two iterations already respond to the noise like the converged fit (the
    /// whole-space step, ~`k²` times smaller, responded to less than half of it).
    #[test]
    fn divergence_counts_the_free_kernel_values() {
        let (w, h, k) = (120, 90, 5);
        let mut r = Rng::new(5);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let mut truth = grid(w, h, k, 6);
        for kk in truth.kernels[0].iter_mut() {
            *kk = kk.map(|v| v + 0.02);
            let s = kk.sum() as f32;
            kk.scale(1.0 / s);
        }
        let op = KernelOperator::new(&sharp, &truth, usize::MAX);
        let y = op.apply_planes(&truth.kernels[0]);
        let sigma = 0.01f32;
        let wt = vec![1.0 / (sigma * sigma); w * h];
        let nominal = (6 * (k * k - 1) + 1) as f64;
        let probe_all = |iterations: usize, seed: u64, step: KernelStep| kernel_divergence(&op, &y, &wt, &truth.kernels[0], KernelFitSettings { iterations, rounds: 2, step }, &mut Rng::new(seed));
        let probe = |iterations: usize, seed: u64, step: KernelStep| probe_all(iterations, seed, step).df;
        let converged = (0..4).map(|s| probe(400, s, KernelStep::Tangent)).sum::<f64>() / 4.0;
        // a white reference: the absorbed noise is white too, so its share of the high-pass
        // is its share of the whole, df / N
        let absorbed = (0..4).map(|s| probe_all(400, s, KernelStep::Tangent).highpass_absorbed).sum::<f64>() / 4.0;
        let share = converged / (w * h) as f64;
        assert!((absorbed / share - 1.0).abs() < 0.25, "high-pass share {absorbed:.4} vs df/N {share:.4}");
        assert!((converged / nominal - 1.0).abs() < 0.2, "divergence {converged:.1} vs {nominal}");
        let (early, early_whole) = (probe(2, 0, KernelStep::Tangent), probe(2, 0, KernelStep::WholeSpace));
        eprintln!("divergence: converged {converged:.1} of {nominal}, 2 iterations {early:.1} (whole-space step {early_whole:.1})");
        assert!(early > 0.8 * converged, "2 iterations: {early:.1}, converged {converged:.1}");
        assert!(early_whole < 0.5 * converged, "2 iterations, whole-space step: {early_whole:.1}, converged {converged:.1}");
    }

    /// The probe on a spread subset of blocks (the diagnosis' screening subset): its absorbed
    /// high-pass share, scaled by the subset's share of the pixels (what `Fit::set_dof` stores),
    /// matches the whole image's; unscaled it would be `1/share` times too large.
    #[test]
    fn subset_probe_scaled_by_its_share_matches_the_whole_image() {
        let (w, h, k) = (160, 120, 5);
        let mut r = Rng::new(7);
        let sharp = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
        let mut truth = grid(w, h, k, 6);
        for kk in truth.kernels[0].iter_mut() {
            *kk = kk.map(|v| v + 0.02);
            let s = kk.sum() as f32;
            kk.scale(1.0 / s);
        }
        let settings = KernelFitSettings { iterations: 400, rounds: 2, step: KernelStep::Tangent };
        let probe = |max_pixels: usize| {
            let op = KernelOperator::new(&sharp, &truth, max_pixels);
            let y = op.apply_planes(&truth.kernels[0]);
            let wt: Vec<f32> = op.covered().iter().map(|&c| if c { 1e4 } else { 0.0 }).collect();
            let share = op.covered().iter().filter(|&&c| c).count() as f64 / (w * h) as f64;
            let d: Vec<Divergence> = (0..4).map(|s| kernel_divergence(&op, &y, &wt, &truth.kernels[0], settings, &mut Rng::new(s))).collect();
            let mean = |f: &dyn Fn(&Divergence) -> f64| d.iter().map(f).sum::<f64>() / d.len() as f64;
            (mean(&|d| d.df), mean(&|d| d.highpass_absorbed), share)
        };
        let (df_all, alpha_all, share_all) = probe(usize::MAX);
        let (df_sub, alpha_sub, share) = probe(w * h / 3);
        assert_eq!(share_all, 1.0);
        assert!(share < 0.6, "the subset keeps {share:.2} of the pixels");
        eprintln!("probe: every pixel df {df_all:.1} α {alpha_all:.4}; subset ({share:.2}) df {df_sub:.1} α {alpha_sub:.4} → scaled {:.4}", alpha_sub * share);
        assert!((alpha_sub * share / alpha_all - 1.0).abs() < 0.25, "scaled {:.4} vs {alpha_all:.4}", alpha_sub * share);
        assert!((df_sub / df_all - 1.0).abs() < 0.25, "df on the subset {df_sub:.1} vs {df_all:.1}");
    }

    /// The 31-px low-pass problem of the two tests below (a natural image's falling spectrum
    /// makes the kernel problem ill-conditioned): compact Gaussian kernels (σ 2.5 px) on a 2 × 2
    /// grid over blurred noise, 144 × 108, white noise σ = 0.002; `floor` is χ² at the truth.
    struct LowPass { op: KernelOperator, y: Plane, wt: Vec<f32>, k: usize, floor: f64 }

    impl LowPass {
        const SIGMA: f32 = 0.002;

        fn new() -> LowPass {
            let (w, h, k) = (144, 108, 31);
            let mut r = Rng::new(7);
            let noise = Plane::from_fn(w, h, |_, _| r.uniform() as f32);
            let sharp = crate::image::filter::gaussian_blur(&noise, 1.2).map(|v| 0.2 + v);
            let truth = PsfGrid { kernels: vec![gaussian_kernels(k, 4, 2.5)], ..grid(w, h, k, 0) };
            let truth = PsfGrid { columns: 2, rows: 2, centers: PsfGrid::regular_centers(w, h, 2, 2), ..truth };
            let op = KernelOperator::new(&sharp, &truth, usize::MAX);
            let mut y = op.apply_planes(&truth.kernels[0]);
            y.data.iter_mut().for_each(|v| *v += Self::SIGMA * r.normal() as f32);
            let wt = vec![1.0 / (Self::SIGMA * Self::SIGMA); w * h];
            let floor = Self::chi2_of(&op, &y, &truth.kernels[0]);
            LowPass { op, y, wt, k, floor }
        }

        /// χ² of kernels `u` against the noisy data.
        fn chi2_of(op: &KernelOperator, y: &Plane, u: &[Plane]) -> f64 {
            op.apply_planes(u).data.iter().zip(&y.data).map(|(p, q)| ((p - q) / Self::SIGMA).powi(2) as f64).sum::<f64>()
        }
    }

    /// The momentum carried between solves ([`KernelWarm`]): three rounds of 20 iterations
    /// handing the momentum on end closer to a long solve's χ² than three rounds each started
    /// afresh (what the fit did before, and what a fresh `KernelWarm` per round still does), on
    /// the 31-px low-pass problem of the test below.
    #[test]
    fn carried_momentum_converges_further_than_fresh_rounds() {
        let LowPass { op, y, wt, k, floor } = LowPass::new();
        let chi2 = |u: &[Plane]| LowPass::chi2_of(&op, &y, u);
        let set = KernelFitSettings { iterations: 20, rounds: 1, step: KernelStep::Tangent };
        let (mut carried, mut fresh) = (gaussian_kernels(k, 4, 5.0), gaussian_kernels(k, 4, 5.0));
        let mut warm = KernelWarm::default();
        for _ in 0..3 {
            carried = fit_kernels_warm(&op, &y, &wt, &carried, set, &mut warm).0;
            fresh = fit_kernels(&op, &y, &wt, &fresh, set).0;
        }
        // the gaps to a long solve's χ² (the fit absorbs noise: below the true kernels' χ²)
        let (long, _) = fit_kernels(&op, &y, &wt, &gaussian_kernels(k, 4, 5.0), KernelFitSettings { iterations: 600, ..set });
        let (c, f, best) = (chi2(&carried) / floor, chi2(&fresh) / floor, chi2(&long) / floor);
        eprintln!("31 px, 3 × 20 iterations: χ²/χ²_truth carried {c:.4}, fresh {f:.4}; 600 iterations {best:.4}");
        assert!(best <= c && c < f, "carried {c:.4}, fresh {f:.4}, long {best:.4}");
        assert!(c - best < 0.9 * (f - best), "carried {c:.4} vs fresh {f:.4}: gaps to {best:.4}");
        // inside one call the rounds carry it too: 1 call of 3 rounds is the carried chain
        let (one, _) = fit_kernels(&op, &y, &wt, &gaussian_kernels(k, 4, 5.0), KernelFitSettings { rounds: 3, ..set });
        let o = chi2(&one) / floor;
        assert!((o - c).abs() < 0.25 * (f - c), "one call {o:.4}, carried {c:.4}, fresh {f:.4}");
    }

    /// A carried momentum that points uphill for the next solve (here: the previous solve's,
    /// reversed, as a fit of a different model may hand on) is dropped by the adaptive restart
    /// at the first iteration (`t` back to 1, so one iteration leaves `t = (1 + √5)/2`), while
    /// the momentum as left continues (`t` grows) and ends lower than a fresh start. The first
    /// iteration's step is still taken from the extrapolated point: the χ² after 20 more
    /// iterations is printed for a reversed momentum at its own size and at 50 times it
    /// (docs/notes/diagnosis-history.md, "Session 20 (d20)": ×50 ends above a fresh start).
    #[test]
    fn an_uphill_carried_momentum_is_dropped_at_the_first_iteration() {
        let LowPass { op, y, wt, k, floor } = LowPass::new();
        let chi2 = |u: &[Plane]| LowPass::chi2_of(&op, &y, u);
        let set = KernelFitSettings { iterations: 20, rounds: 1, step: KernelStep::Tangent };
        let mut warm = KernelWarm::default();
        let u = fit_kernels_warm(&op, &y, &wt, &gaussian_kernels(k, 4, 5.0), set, &mut warm).0;
        let t_left = warm.momentum.t;
        assert!(t_left > 2.0, "the first solve built momentum: t = {t_left}");
        let reversed = |factor: f32| {
            let mut r = warm.clone();
            r.momentum.ahead.iter_mut().for_each(|a| *a *= -factor);
            r
        };
        let one = KernelFitSettings { iterations: 1, ..set };
        let golden = 0.5 * (1.0 + 5f64.sqrt());
        let mut w = warm.clone();
        fit_kernels_warm(&op, &y, &wt, &u, one, &mut w);
        assert!(w.momentum.t > t_left, "the momentum as left continues: t {} after {t_left}", w.momentum.t);
        for factor in [1.0, 50.0] {
            let mut w = reversed(factor);
            fit_kernels_warm(&op, &y, &wt, &u, one, &mut w);
            assert!((w.momentum.t - golden).abs() < 1e-12, "the reversed momentum (×{factor}) is dropped: t = {}", w.momentum.t);
        }
        // 20 further iterations
        let after = |mut w: KernelWarm| chi2(&fit_kernels_warm(&op, &y, &wt, &u, set, &mut w).0) / floor;
        let from_fresh = after(KernelWarm { momentum: Momentum::default(), ..warm.clone() });
        let from_carried = after(warm.clone());
        let (rev1, rev50) = (after(reversed(1.0)), after(reversed(50.0)));
        eprintln!("χ²/χ²_truth after 20 more: carried {from_carried:.5}, fresh {from_fresh:.5}, reversed {rev1:.5}, reversed ×50 {rev50:.5}");
        assert!(from_carried < from_fresh, "carried {from_carried:.5} vs fresh {from_fresh:.5}");
    }

    /// A compact PSF (a Gaussian of `sigma` px, zero beyond `k/2`) in every tile.
    fn gaussian_kernels(k: usize, tiles: usize, sigma: f32) -> Vec<Plane> {
        let r = (k / 2) as f32;
        let mut p = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - r, y as f32 - r);
            let d2 = dx * dx + dy * dy;
            if d2.sqrt() > 0.8 * r { 0.0 } else { (-0.5 * d2 / (sigma * sigma)).exp() }
        });
        let s = p.sum() as f32;
        p.scale(1.0 / s);
        vec![p; tiles]
    }

    /// 31-px kernels on a low-pass target (a natural image's falling spectrum makes the kernel
    /// problem ill-conditioned) reach the noise floor within the diagnosis' base budget of 80
    /// iterations per round: the step comes from `‖AᵀWA‖` on the simplices' tangent space.
    /// The step of the whole space (set by the kernels' flat mode, whose eigenvalue grows with
    /// `k²`) is many times smaller and leaves χ² far above the floor in the same budget.
    #[test]
    fn large_kernels_reach_the_floor_in_the_base_budget() {
        let LowPass { op, y, wt, k, floor } = LowPass::new();
        let chi2 = |u: &[Plane]| LowPass::chi2_of(&op, &y, u);
        let init = gaussian_kernels(k, 4, 5.0);
        let set = KernelFitSettings { iterations: 80, rounds: 3, step: KernelStep::Tangent };
        let (u, _) = fit_kernels(&op, &y, &wt, &init, set);
        let fitted = chi2(&u);
        let (old, _) = fit_kernels(&op, &y, &wt, &init, KernelFitSettings { step: KernelStep::WholeSpace, ..set });
        let stalled = chi2(&old);
        eprintln!("31 px, 80 iterations × 3: χ²/χ²_truth {:.4} (whole-space step: {:.4})", fitted / floor, stalled / floor);
        assert!(fitted < 1.02 * floor, "χ² {fitted:.0} vs {floor:.0} at the true kernels");
        assert!(stalled > 1.2 * floor, "the whole-space step converged too: {stalled:.0} vs {floor:.0}");
    }
}
