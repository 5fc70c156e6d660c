//! The one ADMM loop (scaled form, Boyd et al. 2011 §3.1.1) for
//! `min_x f(x) + Σ_b g_b(K_b x)` with the splits `z_b = K_b x`.
//!
//! The loop owns the iteration cap, the scaled duals `u_b` and their update; the problem
//! supplies its steps through [`AdmmSteps`]:
//! - [`AdmmSteps::apply_split`] writes `K x` (all blocks stacked, each `block_len` long);
//! - [`AdmmSteps::project_dual`] turns `v = K_b x + u_b` into `v − prox_{g_b/ρ}(v)` in place
//!   (for `ℓ1` terms: the clamp to `[−t, t]`, Moreau's identity), given `K_b x`;
//! - the loop then sets `u_b ← v − z_b` (the projected value) and hands `z − u = v − 2 u_b`
//!   to [`AdmmSteps::x_update`], which minimises `f(x) + ρ/2 ‖K x − (z − u)‖²` (warm started
//!   from `x`);
//! - [`AdmmSteps::auxiliary_update`] runs first in each iteration for splits the problem keeps
//!   itself (e.g. a data split `v = B x` with its own dual).
//!
//! Values are `f32`; the arithmetic order of the dual update is fixed (`v = k + u`,
//! `z − u = v − 2 c`), so restructured callers reproduce their results bit for bit.

/// The problem-specific steps of one ADMM iteration.
pub trait AdmmSteps {
    /// Length of one split block (`K_b x`).
    fn block_len(&self) -> usize;
    /// Number of split blocks.
    fn blocks(&self) -> usize;
    /// Splits the problem handles itself, updated from the current `x` before the `z`-update.
    fn auxiliary_update(&mut self, _x: &[f32]) {}
    /// `out = K x` (`blocks() · block_len()` values).
    fn apply_split(&self, x: &[f32], out: &mut [f32]);
    /// Replaces `v = K_b x + u_b` (block `block`) by `v − prox_{g_b/ρ}(v)`; `kx` is `K_b x`.
    fn project_dual(&self, block: usize, kx: &[f32], v: &mut [f32]);
    /// Minimises `f(x) + ρ/2 ‖K x − t‖²` for `t = z − u` (warm start: `x`); returns the inner
    /// (e.g. conjugate-gradient) iterations spent.
    fn x_update(&mut self, t: &[f32], x: &mut [f32]) -> usize;
}

/// What [`admm`] reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AdmmStats {
    pub iterations: usize,
    /// Sum of what [`AdmmSteps::x_update`] returned.
    pub inner_iterations: usize,
}

/// Runs `iterations` ADMM iterations from the warm start `x` (the duals start at 0).
pub fn admm<P: AdmmSteps>(problem: &mut P, x: &mut [f32], iterations: usize) -> AdmmStats {
    let n = problem.block_len();
    let len = problem.blocks() * n;
    let mut u = vec![0.0f32; len];
    let mut kx = vec![0.0f32; len];
    let mut v = vec![0.0f32; n];
    let mut stats = AdmmStats::default();
    for _ in 0..iterations {
        problem.auxiliary_update(x);
        problem.apply_split(x, &mut kx);
        // v = Kx + u; u ← v − prox(v) (= v − z); kx ← z − u = v − 2u
        for (blk, (kb, ub)) in kx.chunks_mut(n).zip(u.chunks_mut(n)).enumerate() {
            for ((vi, k), uu) in v.iter_mut().zip(kb.iter()).zip(ub.iter_mut()) {
                *vi = *k + *uu;
                *uu = *vi;
            }
            problem.project_dual(blk, kb, ub);
            for ((k, vi), uu) in kb.iter_mut().zip(&v).zip(ub.iter()) {
                *k = vi - 2.0 * uu;
            }
        }
        stats.inner_iterations += problem.x_update(&kx, x);
        stats.iterations += 1;
    }
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `min_x ½‖x − d‖² + λ‖x‖₁` split as `z = x`: the soft threshold of `d`.
    struct Lasso {
        d: Vec<f32>,
        lambda: f32,
        rho: f32,
    }

    impl AdmmSteps for Lasso {
        fn block_len(&self) -> usize {
            self.d.len()
        }
        fn blocks(&self) -> usize {
            1
        }
        fn apply_split(&self, x: &[f32], out: &mut [f32]) {
            out.copy_from_slice(x);
        }
        fn project_dual(&self, _block: usize, _kx: &[f32], v: &mut [f32]) {
            let t = self.lambda / self.rho;
            v.iter_mut().for_each(|v| *v = v.max(-t).min(t));
        }
        fn x_update(&mut self, t: &[f32], x: &mut [f32]) -> usize {
            // (1 + ρ) x = d + ρ t
            for ((x, d), t) in x.iter_mut().zip(&self.d).zip(t) {
                *x = (d + self.rho * t) / (1.0 + self.rho);
            }
            1
        }
    }

    #[test]
    fn admm_reaches_the_soft_threshold() {
        let d = vec![3.0f32, -0.5, 0.2, -2.0, 1.0];
        let lambda = 0.7;
        let mut p = Lasso { d: d.clone(), lambda, rho: 1.0 };
        let mut x = vec![0.0f32; d.len()];
        let stats = admm(&mut p, &mut x, 300);
        assert_eq!(stats, AdmmStats { iterations: 300, inner_iterations: 300 });
        for (x, d) in x.iter().zip(&d) {
            let want = d.signum() * (d.abs() - lambda).max(0.0);
            assert!((x - want).abs() < 1e-4, "{x} vs {want}");
        }
    }
}
