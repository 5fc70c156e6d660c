//! Power iteration for the largest eigenvalue of a symmetric positive semi-definite map `H`
//! (usually `KᵀK` or a data term's Hessian `AᵀWA`), the one implementation behind every step
//! size in the crate.
//!
//! The caller owns the start vector, the number of products, an optional projection onto a
//! subspace (e.g. zero-sum kernels, the simplices' tangent space) applied before every product
//! and to its result, and the safety factor it multiplies the estimate by (each call site
//! states its own: 1.01 for Chambolle–Pock's `‖K‖`, 1.05 for the diagnosis' FISTA, 1.3 for the
//! kernel fits). Sums accumulate in `f64`.

use super::operator::LinearOperator;

/// What [`power_iteration`] measured in its last step, with `v` the normalised iterate and
/// `Hv` its image.
#[derive(Clone, Debug)]
pub struct PowerEstimate {
    /// The Rayleigh quotient `⟨Hv, v⟩`.
    pub rayleigh: f64,
    /// `‖Hv‖`.
    pub norm: f64,
    /// The last (unnormalised) iterate `Hv`, a warm start for a similar operator.
    pub vector: Vec<f32>,
}

/// Runs `iterations.max(1)` steps of `v ← project(H · project(v) / ‖project(v)‖)` from `start`
/// (`apply(v, out)` writes `out = H v`). Returns `None` when the iterate vanishes (`H` is zero
/// on the subspace, or `start` is zero).
pub fn power_iteration(start: Vec<f32>, iterations: usize, mut apply: impl FnMut(&[f32], &mut [f32]), mut project: impl FnMut(&mut [f32])) -> Option<PowerEstimate> {
    let mut v = start;
    let mut hv = vec![0.0f32; v.len()];
    let (mut rayleigh, mut norm) = (0.0f64, 0.0f64);
    for _ in 0..iterations.max(1) {
        project(&mut v);
        let nrm = v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        if nrm == 0.0 {
            return None;
        }
        v.iter_mut().for_each(|x| *x = (*x as f64 / nrm) as f32);
        apply(&v, &mut hv);
        project(&mut hv);
        rayleigh = hv.iter().zip(&v).map(|(&a, &b)| a as f64 * b as f64).sum::<f64>();
        norm = hv.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        std::mem::swap(&mut v, &mut hv);
    }
    Some(PowerEstimate { rayleigh, norm, vector: v })
}

/// `‖A‖₂ · safety` by power iteration on `AᵀA` (deterministic start `1 + (i·7919 mod 13)/13`,
/// `iterations` products); 0 when `A` vanishes on the start. A `safety` slightly above 1
/// keeps a step condition such as `στL² < 1` when the iteration undershoots.
pub fn operator_norm<A: LinearOperator + ?Sized>(op: &A, iterations: usize, safety: f64) -> f32 {
    let start: Vec<f32> = (0..op.input_len()).map(|i| 1.0 + ((i * 7919) % 13) as f32 / 13.0).collect();
    let mut ax = vec![0.0f32; op.output_len()];
    let normal = |v: &[f32], out: &mut [f32]| {
        op.apply(v, &mut ax);
        op.apply_adjoint(&ax, out);
    };
    power_iteration(start, iterations, normal, |_| {}).map_or(0.0, |e| (e.norm.sqrt() * safety) as f32)
}

/// The deterministic pseudo-random start of the kernel fits: `(i·7919 mod 101)/101 − ½`.
pub fn kernel_start(n: usize) -> Vec<f32> {
    (0..n).map(|i| ((i * 7919 % 101) as f32 / 101.0) - 0.5).collect()
}

/// Removes the mean of every `block`-long chunk of `v` (the tangent space of a product of
/// simplices).
pub fn remove_block_means(v: &mut [f32], block: usize) {
    for c in v.chunks_mut(block.max(1)) {
        let m = c.iter().sum::<f32>() / c.len() as f32;
        c.iter_mut().for_each(|x| *x -= m);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A diagonal map: the estimate converges to the largest entry, and the projection keeps
    /// the iteration on its subspace.
    #[test]
    fn finds_the_largest_eigenvalue() {
        let d = [1.0f32, 4.0, 2.0, 0.5];
        let diag = |v: &[f32], out: &mut [f32]| out.iter_mut().zip(v).zip(&d).for_each(|((o, x), a)| *o = a * x);
        let e = power_iteration(vec![1.0; 4], 60, diag, |_| {}).expect("non-zero");
        assert!((e.rayleigh - 4.0).abs() < 1e-4 && (e.norm - 4.0).abs() < 1e-4, "{e:?}");
        // without the second coordinate, 2 is the largest
        let e = power_iteration(vec![1.0; 4], 60, diag, |v| v[1] = 0.0).expect("non-zero");
        assert!((e.rayleigh - 2.0).abs() < 1e-4, "{e:?}");
        assert!(power_iteration(vec![0.0; 4], 5, diag, |_| {}).is_none());
    }

    #[test]
    fn block_means_vanish() {
        let mut v = vec![1.0, 2.0, 3.0, 10.0, 10.0, 13.0];
        remove_block_means(&mut v, 3);
        assert_eq!(v, vec![-1.0, 0.0, 1.0, -1.0, -1.0, 2.0]);
    }
}
