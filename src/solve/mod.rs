//! Numerical machinery shared by estimation and deconvolution: FFT plans, convolution, linear
//! operators and the Chambolle–Pock primal-dual loop.

pub mod cg;
pub mod conv;
pub mod fft;
pub mod primal_dual;
