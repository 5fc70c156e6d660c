//! The Chambolle–Pock primal-dual algorithm (Chambolle & Pock 2011; Heide et al. 2013, Alg. 1).
//!
//! Solves `min_x F(Kx) + G(x)` for convex `F`, `G` and a linear `K`:
//!
//! ```text
//! y      ← prox_{σF*}(y + σ K x̄)
//! x_new  ← prox_{τG}(x − τ Kᵀ y)
//! x̄      ← x_new + θ (x_new − x);   x ← x_new
//! ```
//!
//! with `σ τ L² < 1`, `L = ‖K‖₂` found by [`super::power::operator_norm`]. A problem implements
//! [`PrimalDual`]; [`chambolle_pock`] owns the loop: iteration cap, the stopping rule (relative
//! primal-dual gap when the problem can compute one, otherwise the primal-dual residuals of
//! Goldstein et al. 2013), and cancellation through the `on_check` callback.
//!
//! [`condat_vu`] is the variant for `min_x f(x) + F(Kx) + G(x)` with an extra *smooth* `f`
//! that is used only through its gradient (Condat 2013, Vũ 2013): no prox of the data term is
//! needed, so the primal variable can live on a small domain (a kernel's support) while the data
//! term's gradient is computed by FFTs on a large one.

use super::operator::PrimalDualOperator;
use super::power;

/// A convex problem `min F(Kx) + G(x)` in the form Chambolle–Pock needs.
pub trait PrimalDual {
    /// Length of the primal variable `x`.
    fn primal_len(&self) -> usize;
    /// Length of the dual variable `y` (the range of `K`).
    fn dual_len(&self) -> usize;
    /// `out = K x`.
    fn apply_k(&self, x: &[f32], out: &mut [f32]);
    /// `out = Kᵀ y`.
    fn apply_kt(&self, y: &[f32], out: &mut [f32]);
    /// `y ← prox_{σF*}(y)` in place.
    fn prox_f_conj(&mut self, sigma: f32, y: &mut [f32]);
    /// `x ← prox_{τG}(x)` in place.
    fn prox_g(&mut self, tau: f32, x: &mut [f32]);
    /// Primal objective minus dual objective at `(x, y)` and the primal objective, both
    /// finite and non-negative at feasible points; `None` when the problem has no closed-form
    /// dual (the loop then stops on residuals).
    fn gap(&mut self, _x: &[f32], _y: &[f32]) -> Option<(f64, f64)> {
        None
    }
    /// Called after every iteration with the new `x` and the extrapolated `x̄` (problems with an
    /// outer fixed point, e.g. unknown-boundary data terms, refresh it here).
    fn after_iteration(&mut self, _x: &[f32], _x_bar: &[f32]) {}
}

/// Loop settings.
#[derive(Clone, Debug)]
pub struct Options {
    pub max_iterations: usize,
    pub min_iterations: usize,
    /// Stop when `gap / max(|primal|, tiny) < tolerance` (or, without a gap, when the relative
    /// primal and dual residuals are both below it).
    pub tolerance: f64,
    /// Evaluate the stopping rule every this many iterations.
    pub check_every: usize,
    /// Dual step; `tau = 0.9 / (sigma L²)`.
    pub sigma: f32,
    pub theta: f32,
}

impl Default for Options {
    fn default() -> Self {
        Self { max_iterations: 500, min_iterations: 10, tolerance: 1e-4, check_every: 10, sigma: 10.0, theta: 1.0 }
    }
}

/// What the loop did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Stats {
    pub iterations: usize,
    pub converged: bool,
    /// Last relative gap (or residual) measured.
    pub criterion: f64,
    /// Whether `criterion` is a true duality gap.
    pub gap_based: bool,
    pub operator_norm: f32,
    pub primal_objective: f64,
}

/// Safety factor on the power iteration's `‖K‖` when [`chambolle_pock`] measures it: a 1 %
/// margin keeps `στL² < 1` when the iteration undershoots.
pub const NORM_SAFETY: f64 = 1.01;

/// `(primal_len, dual_len)`, checked against `x` and `y`.
fn lengths<P: PrimalDual + ?Sized>(p: &P, x: &[f32], y: &[f32]) -> (usize, usize) {
    let (n, m) = (p.primal_len(), p.dual_len());
    assert_eq!(x.len(), n);
    assert_eq!(y.len(), m);
    (n, m)
}

/// The dual step both loops share: `y ← prox_{σF*}(y + σ K x̄)` (`kx`: scratch, `dual_len`).
fn dual_step<P: PrimalDual + ?Sized>(p: &mut P, x_bar: &[f32], sigma: f32, kx: &mut [f32], y: &mut [f32]) {
    p.apply_k(x_bar, kx);
    for (yi, k) in y.iter_mut().zip(kx.iter()) {
        *yi += sigma * k;
    }
    p.prox_f_conj(sigma, y);
}

/// Runs Chambolle–Pock from `(x, y)` (both updated in place).
///
/// `on_check(iteration, criterion)` is called at every check; returning `false` cancels.
pub fn chambolle_pock<P: PrimalDual + ?Sized>(
    p: &mut P,
    x: &mut [f32],
    y: &mut [f32],
    opts: &Options,
    operator_norm: Option<f32>,
    mut on_check: impl FnMut(usize, f64) -> bool,
) -> Stats {
    let (n, m) = lengths(&*p, x, y);
    let l = operator_norm.unwrap_or_else(|| power::operator_norm(&PrimalDualOperator(&*p), 30, NORM_SAFETY));
    let sigma = opts.sigma;
    let tau = if l > 0.0 { 0.9 / (sigma * l * l) } else { 1.0 };
    let mut x_bar = x.to_vec();
    let mut x_old = vec![0.0; n];
    let mut y_old = vec![0.0; m];
    let mut kx = vec![0.0; m];
    let mut kty = vec![0.0; n];
    let mut stats = Stats { operator_norm: l, ..Default::default() };
    for it in 1..=opts.max_iterations {
        y_old.copy_from_slice(y);
        x_old.copy_from_slice(x);
        dual_step(p, &x_bar, sigma, &mut kx, y);
        p.apply_kt(y, &mut kty);
        for (xi, k) in x.iter_mut().zip(&kty) {
            *xi -= tau * k;
        }
        p.prox_g(tau, x);
        for i in 0..n {
            x_bar[i] = x[i] + opts.theta * (x[i] - x_old[i]);
        }
        p.after_iteration(x, &x_bar);
        stats.iterations = it;
        if it % opts.check_every == 0 || it == opts.max_iterations {
            let crit = match p.gap(x, y) {
                Some((gap, primal)) => {
                    stats.gap_based = true;
                    stats.primal_objective = primal;
                    gap.abs() / primal.abs().max(1e-30)
                }
                None => {
                    stats.gap_based = false;
                    residual_criterion(p, x, &x_old, y, &y_old, tau, sigma)
                }
            };
            if stop(&mut stats, it, crit, opts.min_iterations, opts.tolerance, &mut on_check) {
                break;
            }
        }
    }
    stats
}

/// Records `crit`, reports it to `on_check` and says whether the loop ends: cancelled, or
/// converged (`crit < tolerance` after `min_iterations`).
fn stop(stats: &mut Stats, it: usize, crit: f64, min_iterations: usize, tolerance: f64, on_check: &mut impl FnMut(usize, f64) -> bool) -> bool {
    stats.criterion = crit;
    if !on_check(it, crit) {
        return true;
    }
    if it >= min_iterations && crit < tolerance {
        stats.converged = true;
        return true;
    }
    false
}

/// Relative primal/dual residuals (Goldstein, Esser & Baraniuk 2013), the larger of the two.
fn residual_criterion<P: PrimalDual + ?Sized>(
    p: &P,
    x: &[f32],
    x_old: &[f32],
    y: &[f32],
    y_old: &[f32],
    tau: f32,
    sigma: f32,
) -> f64 {
    let dx: Vec<f32> = x.iter().zip(x_old).map(|(a, b)| a - b).collect();
    let dy: Vec<f32> = y.iter().zip(y_old).map(|(a, b)| a - b).collect();
    let mut kdx = vec![0.0; y.len()];
    let mut ktdy = vec![0.0; x.len()];
    p.apply_k(&dx, &mut kdx);
    p.apply_kt(&dy, &mut ktdy);
    let primal: f64 = dx.iter().zip(&ktdy).map(|(a, b)| ((a / tau - b) as f64).powi(2)).sum::<f64>().sqrt();
    let dual: f64 = dy.iter().zip(&kdx).map(|(a, b)| ((a / sigma - b) as f64).powi(2)).sum::<f64>().sqrt();
    let xs = x.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt().max(1e-30);
    let ys = y.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt().max(1e-30);
    (primal * tau as f64 / xs).max(dual * sigma as f64 / ys)
}

/// A problem `min f(x) + F(Kx) + G(x)` for [`condat_vu`]: [`PrimalDual`] supplies `K`, `Kᵀ`,
/// `prox_{σF*}` and `prox_{τG}` (usually a projection); this adds `f`.
pub trait SmoothPrimalDual: PrimalDual {
    /// `out = ∇f(x)`; returns `f(x)`.
    fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64;
}

/// Loop settings of [`condat_vu`].
#[derive(Clone, Debug)]
pub struct SplitOptions {
    pub max_iterations: usize,
    pub min_iterations: usize,
    /// Stop when the relative step `‖x⁺ − x‖ / ‖x⁺‖` is below this.
    pub tolerance: f64,
}

/// Condat–Vũ primal-dual iterations from `(x, y)` (both updated in place):
///
/// ```text
/// x⁺ = prox_{τG}(x − τ (∇f(x) + Kᵀy))
/// y  ← prox_{σF*}(y + σ K (2x⁺ − x))
/// ```
///
/// with `τ = 1 / L_f` and `σ = L_f / (2 L_K²)`, which satisfies the convergence condition
/// `1/τ − σ L_K² ≥ L_f / 2` (`l_smooth` = `L_f`, the Lipschitz constant of `∇f`;
/// `l_k` = `‖K‖₂`). The criterion reported to `on_check` (every iteration; `false` cancels) is
/// the relative step; `Stats::primal_objective` is `f` at the last gradient evaluation.
pub fn condat_vu<P: SmoothPrimalDual + ?Sized>(
    p: &mut P,
    x: &mut [f32],
    y: &mut [f32],
    opts: &SplitOptions,
    l_smooth: f32,
    l_k: f32,
    mut on_check: impl FnMut(usize, f64) -> bool,
) -> Stats {
    let (n, m) = lengths(&*p, x, y);
    let tau = 1.0 / l_smooth.max(1e-30);
    let sigma = 0.5 * l_smooth / (l_k * l_k).max(1e-30);
    let mut grad = vec![0.0; n];
    let mut kty = vec![0.0; n];
    let mut x_new = vec![0.0; n];
    let mut x_bar = vec![0.0; n];
    let mut kx = vec![0.0; m];
    let mut stats = Stats { operator_norm: l_k, gap_based: false, ..Default::default() };
    for it in 1..=opts.max_iterations {
        stats.primal_objective = p.gradient(x, &mut grad);
        p.apply_kt(y, &mut kty);
        for i in 0..n {
            x_new[i] = x[i] - tau * (grad[i] + kty[i]);
        }
        p.prox_g(tau, &mut x_new);
        let (mut dx2, mut x2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let d = x_new[i] - x[i];
            dx2 += (d as f64) * (d as f64);
            x2 += (x_new[i] as f64) * (x_new[i] as f64);
            x_bar[i] = x_new[i] + d;
        }
        dual_step(p, &x_bar, sigma, &mut kx, y);
        x.copy_from_slice(&x_new);
        p.after_iteration(x, &x_bar);
        stats.iterations = it;
        let crit = (dx2 / x2.max(1e-300)).sqrt();
        if stop(&mut stats, it, crit, opts.min_iterations, opts.tolerance, &mut on_check) {
            break;
        }
    }
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 1-D total-variation denoising with a known solution structure:
    /// min_x ½‖x − f‖² + λ‖Dx‖₁ with D forward differences. For a single step of height h and
    /// λ small, the solution is the step shrunk by 2λ/len on each side (taut string).
    struct Tv1d {
        f: Vec<f32>,
        lambda: f32,
    }

    impl PrimalDual for Tv1d {
        fn primal_len(&self) -> usize {
            self.f.len()
        }
        fn dual_len(&self) -> usize {
            self.f.len() - 1
        }
        fn apply_k(&self, x: &[f32], out: &mut [f32]) {
            for i in 0..out.len() {
                out[i] = x[i + 1] - x[i];
            }
        }
        fn apply_kt(&self, y: &[f32], out: &mut [f32]) {
            out.iter_mut().for_each(|v| *v = 0.0);
            for i in 0..y.len() {
                out[i + 1] += y[i];
                out[i] -= y[i];
            }
        }
        fn prox_f_conj(&mut self, _sigma: f32, y: &mut [f32]) {
            for v in y.iter_mut() {
                *v = v.clamp(-self.lambda, self.lambda);
            }
        }
        fn prox_g(&mut self, tau: f32, x: &mut [f32]) {
            for (xi, fi) in x.iter_mut().zip(&self.f) {
                *xi = (*xi + tau * fi) / (1.0 + tau);
            }
        }
        fn gap(&mut self, x: &[f32], y: &[f32]) -> Option<(f64, f64)> {
            let mut dx = vec![0.0; y.len()];
            self.apply_k(x, &mut dx);
            let primal: f64 = x.iter().zip(&self.f).map(|(a, b)| 0.5 * ((a - b) as f64).powi(2)).sum::<f64>()
                + self.lambda as f64 * dx.iter().map(|v| v.abs() as f64).sum::<f64>();
            let mut kty = vec![0.0; x.len()];
            self.apply_kt(y, &mut kty);
            // D(y) = -G*(-Kᵀy) = -(½‖Kᵀy‖² - <Kᵀy, f>)
            let dual: f64 = -kty.iter().zip(&self.f).map(|(k, f)| 0.5 * (*k as f64).powi(2) - (*k as f64) * (*f as f64)).sum::<f64>();
            Some((primal - dual, primal))
        }
    }

    #[test]
    fn tv1d_converges_to_taut_string_solution() {
        // step from 0 to 1 at the middle of 20 samples; λ = 1: each side moves by λ/10 = 0.1
        let f: Vec<f32> = (0..20).map(|i| if i < 10 { 0.0 } else { 1.0 }).collect();
        let mut p = Tv1d { f, lambda: 1.0 };
        let mut x = vec![0.0; 20];
        let mut y = vec![0.0; 19];
        let opts = Options { max_iterations: 5000, tolerance: 1e-7, sigma: 1.0, ..Default::default() };
        let st = chambolle_pock(&mut p, &mut x, &mut y, &opts, None, |_, _| true);
        assert!(st.converged && st.gap_based, "{st:?}");
        for (i, v) in x.iter().enumerate() {
            let want = if i < 10 { 0.1 } else { 0.9 };
            assert!((v - want).abs() < 1e-3, "x[{i}] = {v}");
        }
        // norm of the forward difference operator is < 2
        assert!(st.operator_norm > 1.9 && st.operator_norm < 2.03, "{}", st.operator_norm);
    }

    #[test]
    fn cancellation_stops_the_loop() {
        let mut p = Tv1d { f: vec![0.0, 1.0, 0.0], lambda: 0.1 };
        let (mut x, mut y) = (vec![0.0; 3], vec![0.0; 2]);
        let opts = Options { max_iterations: 1000, check_every: 5, tolerance: 0.0, ..Default::default() };
        let st = chambolle_pock(&mut p, &mut x, &mut y, &opts, None, |it, _| it < 20);
        assert_eq!(st.iterations, 20);
        assert!(!st.converged);
    }

    /// The same TV denoising split as smooth data term + TV + a box constraint G = ι[0, 0.95].
    struct Tv1dSmooth(Tv1d);

    impl PrimalDual for Tv1dSmooth {
        fn primal_len(&self) -> usize {
            self.0.primal_len()
        }
        fn dual_len(&self) -> usize {
            self.0.dual_len()
        }
        fn apply_k(&self, x: &[f32], out: &mut [f32]) {
            self.0.apply_k(x, out)
        }
        fn apply_kt(&self, y: &[f32], out: &mut [f32]) {
            self.0.apply_kt(y, out)
        }
        fn prox_f_conj(&mut self, s: f32, y: &mut [f32]) {
            self.0.prox_f_conj(s, y)
        }
        fn prox_g(&mut self, _tau: f32, x: &mut [f32]) {
            x.iter_mut().for_each(|v| *v = v.clamp(0.0, 0.95));
        }
    }

    impl SmoothPrimalDual for Tv1dSmooth {
        fn gradient(&mut self, x: &[f32], out: &mut [f32]) -> f64 {
            let mut f = 0.0;
            for i in 0..x.len() {
                out[i] = x[i] - self.0.f[i];
                f += 0.5 * (out[i] as f64).powi(2);
            }
            f
        }
    }

    #[test]
    fn condat_vu_solves_constrained_tv_denoising() {
        // step 0 → 1 at the middle of 20 samples, λ = 1: the free solution is 0.1 / 0.9; with the
        // box [0, 0.95] inactive it is unchanged. Then f = 0 / 1.2 pushes the upper part to the
        // bound: the constrained solution is 0.1 / 0.95 when λ/10 < 0.25.
        for (hi, want_hi) in [(1.0f32, 0.9f32), (1.2, 0.95)] {
            let f: Vec<f32> = (0..20).map(|i| if i < 10 { 0.0 } else { hi }).collect();
            let mut p = Tv1dSmooth(Tv1d { f, lambda: 1.0 });
            let (mut x, mut y) = (vec![0.0; 20], vec![0.0; 19]);
            let o = SplitOptions { max_iterations: 20000, min_iterations: 10, tolerance: 1e-7 };
            let st = condat_vu(&mut p, &mut x, &mut y, &o, 1.0, 2.0, |_, _| true);
            assert!(st.converged, "{st:?}");
            for (i, v) in x.iter().enumerate() {
                let want = if i < 10 { 0.1 } else { want_hi };
                assert!((v - want).abs() < 2e-3, "hi {hi}: x[{i}] = {v}");
            }
        }
    }
}
