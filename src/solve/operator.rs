//! The [`LinearOperator`] trait every linear map of the solvers implements, and the one
//! adjoint checker (`⟨Ax, y⟩ = ⟨x, Aᵀy⟩`) the tests run over every implementation.
//!
//! Vectors are flat row-major `f32` slices; an operator maps `input_len()` values to
//! `output_len()` values. Implementations: the image-side blurs
//! ([`crate::optics::field_operator::FieldOperator`], [`crate::solve::conv::CircularConvolution`]),
//! the kernel-side blur ([`crate::optics::kernel_operator::KernelOperator`]), the kernel TV
//! gradient ([`TvGradient`]) and the deconvolution's split operator (through
//! [`PrimalDualOperator`]).

use super::primal_dual::PrimalDual;
use super::prox::{tv_dual_len, tv_gradient, tv_gradient_adjoint};

/// A linear map `A` with its adjoint.
pub trait LinearOperator {
    /// Length of `x` in `A x`.
    fn input_len(&self) -> usize;
    /// Length of `A x`.
    fn output_len(&self) -> usize;
    /// `out = A x` (`out` is overwritten).
    fn apply(&self, x: &[f32], out: &mut [f32]);
    /// `out = Aᵀ y` (`out` is overwritten).
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]);
}

/// The `K` of a [`PrimalDual`] problem as a [`LinearOperator`].
pub struct PrimalDualOperator<'a, P: PrimalDual + ?Sized>(pub &'a P);

impl<P: PrimalDual + ?Sized> LinearOperator for PrimalDualOperator<'_, P> {
    fn input_len(&self) -> usize {
        self.0.primal_len()
    }
    fn output_len(&self) -> usize {
        self.0.dual_len()
    }
    fn apply(&self, x: &[f32], out: &mut [f32]) {
        self.0.apply_k(x, out)
    }
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
        self.0.apply_kt(y, out)
    }
}

/// The forward differences of `blocks` consecutive `k × k` kernels ([`tv_gradient`] per
/// kernel, outputs concatenated).
pub struct TvGradient {
    pub k: usize,
    pub blocks: usize,
}

impl LinearOperator for TvGradient {
    fn input_len(&self) -> usize {
        self.blocks * self.k * self.k
    }
    fn output_len(&self) -> usize {
        self.blocks * tv_dual_len(self.k)
    }
    fn apply(&self, x: &[f32], out: &mut [f32]) {
        for (xb, ob) in x.chunks(self.k * self.k).zip(out.chunks_mut(tv_dual_len(self.k))) {
            tv_gradient(xb, self.k, ob);
        }
    }
    fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
        for (yb, ob) in y.chunks(tv_dual_len(self.k)).zip(out.chunks_mut(self.k * self.k)) {
            tv_gradient_adjoint(yb, self.k, ob);
        }
    }
}

/// `(⟨Ax, y⟩, ⟨x, Aᵀy⟩)` in `f64`: equal up to round-off for a correct adjoint.
///
/// # Panics
/// When `x` or `y` do not have the operator's lengths.
pub fn adjoint_pair<A: LinearOperator + ?Sized>(op: &A, x: &[f32], y: &[f32]) -> (f64, f64) {
    assert_eq!(x.len(), op.input_len(), "input length");
    assert_eq!(y.len(), op.output_len(), "output length");
    let mut ax = vec![0.0f32; op.output_len()];
    let mut aty = vec![0.0f32; op.input_len()];
    op.apply(x, &mut ax);
    op.apply_adjoint(y, &mut aty);
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(p, q)| *p as f64 * *q as f64).sum::<f64>();
    (dot(&ax, y), dot(x, &aty))
}

#[cfg(test)]
pub(crate) mod tests {
    //! The adjoint checker run over every [`LinearOperator`] of the crate.
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::image::Plane;
    use crate::optics::field_operator::FieldOperator;
    use crate::optics::kernel_operator::KernelOperator;
    use crate::rng::Rng;
    use crate::solve::conv::CircularConvolution;
    use proptest::prelude::*;

    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut r = Rng::new(seed);
        (0..n).map(|_| r.normal() as f32).collect()
    }

    /// Checks `⟨Ax, y⟩ = ⟨x, Aᵀy⟩` on random vectors, relative to `‖Ax‖‖y‖` (the one adjoint
    /// checker; other modules' tests call it for their operators).
    pub(crate) fn check<A: LinearOperator + ?Sized>(op: &A, seed: u64) -> Result<(), TestCaseError> {
        let x = noise(op.input_len(), seed);
        let y = noise(op.output_len(), seed + 1);
        let (a, b) = adjoint_pair(op, &x, &y);
        let mut ax = vec![0.0; op.output_len()];
        op.apply(&x, &mut ax);
        let scale = ax.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt() * y.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt();
        prop_assert!((a - b).abs() <= 1e-4 * scale.max(1e-12), "⟨Ax, y⟩ {} vs ⟨x, Aᵀy⟩ {}", a, b);
        Ok(())
    }

    /// A deliberately wrong adjoint (a transposed shift that is off by one) fails the checker.
    struct WrongShift;
    impl LinearOperator for WrongShift {
        fn input_len(&self) -> usize {
            8
        }
        fn output_len(&self) -> usize {
            8
        }
        fn apply(&self, x: &[f32], out: &mut [f32]) {
            for i in 0..8 {
                out[i] = x[(i + 1) % 8];
            }
        }
        fn apply_adjoint(&self, y: &[f32], out: &mut [f32]) {
            out.copy_from_slice(y);
        }
    }

    #[test]
    fn the_checker_catches_a_wrong_adjoint() {
        assert!(check(&WrongShift, 1).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(12))]
        #[test]
        fn tv_gradient_is_adjoint(k in 1usize..8, blocks in 1usize..4, seed in 0u64..1000) {
            check(&TvGradient { k, blocks }, seed)?;
        }

        #[test]
        fn circular_convolution_is_adjoint(w in 4usize..30, h in 4usize..30, kr in 0usize..4, seed in 0u64..1000) {
            let k = Plane { width: 2 * kr + 1, height: 2 * kr + 1, data: noise((2 * kr + 1).pow(2), seed + 5) };
            check(&CircularConvolution::new(&k, w, h), seed)?;
        }

        #[test]
        fn field_operator_is_adjoint(x0 in -20isize..60, y0 in -20isize..40, seed in 0u64..1000, ch in 0usize..3) {
            let grid = SyntheticLens::new(9, 3).grid(90, 70, 3, 3, 3);
            check(&FieldOperator::new(&grid, ch, x0, y0, 48, 36, 90, 70), seed)?;
        }

        #[test]
        fn kernel_operator_is_adjoint(w in 30usize..90, h in 30usize..70, k in 1usize..5, seed in 0u64..1000) {
            let k = 2 * k + 1;
            let grid = SyntheticLens::new(k, 1).grid(w, h, 3, 2, 1);
            let sharp = Plane { width: w, height: h, data: noise(w * h, seed + 9) };
            check(&KernelOperator::new(&sharp, &grid, usize::MAX), seed)?;
        }

    }
}
