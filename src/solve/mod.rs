//! Numerical machinery shared by estimation, deconvolution and diagnosis: FFT plans,
//! convolution, the [`operator::LinearOperator`] trait, proxes, power iteration, and the loops
//! (Chambolle–Pock / Condat–Vũ, FISTA, ADMM, conjugate gradients). Values are `f32`, reductions
//! `f64`; FFT conventions in [`fft`], the PSF convention in [`conv`].

pub mod admm;
pub mod cg;
pub mod conv;
pub mod dense;
pub mod fft;
pub mod fista;
pub mod operator;
pub mod power;
pub mod primal_dual;
pub mod prox;
