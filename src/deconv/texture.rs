//! Texture return (docs/notes/deblur-history.md "Issue-12, m17"): the part of the data residual that
//! the noise law says is signal, deconvolved by a Wiener filter and added back.
//!
//! # Model
//! With the restored window `x̂` (linear values), the tile kernel `B` and the data `j`, the
//! residual of the unmasked pixels `r = M (j − B x̂)` (`M` 0 within the kernel radius of the
//! window edge and on saturated pixels, 1 elsewhere) is `M (n + B (x − x̂))`: the noise plus the
//! blurred part of the scene the prior removed (texture, the peaks of point sources). Its
//! periodogram, averaged over the `K = (2h+1)²` bins around each frequency `ω`,
//!
//! ```text
//! P(ω) = ⟨|R(ω')|²⟩_{|ω'−ω|∞ ≤ h},          E P = S_n + S(ω),     S_n = Σ_k M_k V(j̃_k)
//! ```
//!
//! has the white noise floor `S_n` the law gives (`V(x) = g x + r²` at the lightly smoothed
//! input `j̃ = G_1 * j`, or `σ²`; unnormalised DFT) and the residual signal power `S = |B|² S_Δ`.
//! The signal power is taken where `P` exceeds the floor by more than `z = 3` standard errors
//! of the average (`χ²` with `2K` degrees of freedom: relative standard error `1/√K`),
//!
//! ```text
//! S(ω) = max(P(ω) − S_n (1 + z/√K), 0)
//! ```
//!
//! and the lost signal is its Wiener (MMSE) estimate from the residual,
//!
//! ```text
//! Δ̂(ω) = B̄ S_Δ / (|B|² S_Δ + S_n) · R(ω) = S / (S + S_n) · R(ω) / B(ω),   |B(ω)|² ≥ b_min
//! ```
//!
//! (0 where the lens passes less than `b_min = 10⁻²` of the power: there `S` can only be
//! estimation error or model mismatch, and `1/B` would amplify it). `x̂ + Δ̂` is the result,
//! kept non-negative with [`super::DeconvOptions::positivity`].
//! Nothing is fitted to the benchmark: the law, the kernel and the residual define the filter;
//! `h = 4`, `z = 3` and `b_min` were set (from `h = 2`, `z = 2`, `b_min = 10⁻³`) because the
//! looser test put noise back where nothing was lost (unit test
//! `texture_return_adds_no_noise_where_nothing_was_lost`: 0.75 σ RMS against 0.002 σ).

use crate::solve::fft::Fft2;
use rustfft::num_complex::Complex32;

/// Half-width `h` (bins) of the periodogram average (`K = 81` bins).
pub const SMOOTH_BINS: usize = 4;
/// Standard errors `z` of the averaged periodogram the power must exceed the floor by.
pub const STANDARD_ERRORS: f32 = 3.0;
/// Smallest `|B(ω)|²` the lost signal is deconvolved at (amplification `1/|B|` at most 10).
pub const B2_MIN: f32 = 1e-2;

/// The Wiener estimate `Δ̂` (spatial, `fft.width × fft.height`) of the lost signal of one channel
/// window: `data` the blurred input `j`, `estimate` the restored `x̂`, `kernel` the spectrum
/// `F(B)` of the tile kernel (origin-centred), `mask` the 0/1 data mask `M`, `variance` the
/// noise variance `V(j̃_k)` per pixel.
pub fn lost_signal(fft: &Fft2, data: &[f32], estimate: &[f32], kernel: &[Complex32], mask: &[f32], variance: &[f32]) -> Vec<f32> {
    let n = fft.width * fft.height;
    assert!(data.len() == n && estimate.len() == n && mask.len() == n && variance.len() == n, "texture return: window sizes");
    let mut bx = fft.forward(estimate);
    bx.iter_mut().zip(kernel).for_each(|(s, b)| *s *= b);
    let bx = fft.inverse(bx);
    let r: Vec<f32> = (0..n).map(|k| mask[k] * (data[k] - bx[k])).collect();
    let noise: f32 = (0..n).map(|k| mask[k] * mask[k] * variance[k].max(0.0)).sum();
    if noise <= 0.0 || !noise.is_finite() {
        return vec![0.0; n];
    }
    let mut spec = fft.forward(&r);
    let power = smoothed_power(&spec, fft.half_width, fft.height, SMOOTH_BINS);
    let k = ((2 * SMOOTH_BINS + 1) * (2 * SMOOTH_BINS + 1)) as f32;
    let floor = noise * (1.0 + STANDARD_ERRORS / k.sqrt());
    for ((s, b), p) in spec.iter_mut().zip(kernel).zip(&power) {
        let b2 = b.norm_sqr();
        let signal = (p - floor).max(0.0);
        *s = if b2 >= B2_MIN && signal > 0.0 { *s * b.conj() * (signal / ((signal + noise) * b2)) } else { Complex32::new(0.0, 0.0) };
    }
    fft.inverse(spec)
}

/// `|R|²` averaged over the `(2h+1)²` bins around each bin of a column-major half spectrum
/// (`hw` bins along x, clamped at the ends; `height` along y, periodic).
fn smoothed_power(spec: &[Complex32], hw: usize, height: usize, h: usize) -> Vec<f32> {
    let p: Vec<f32> = spec.iter().map(|c| c.norm_sqr()).collect();
    // along y (contiguous within a column), periodic
    let mut py = vec![0.0f32; p.len()];
    for kx in 0..hw {
        let col = &p[kx * height..(kx + 1) * height];
        for ky in 0..height {
            let mut s = 0.0;
            for d in 0..=2 * h {
                s += col[(ky + height + d - h) % height];
            }
            py[kx * height + ky] = s;
        }
    }
    // along x, clamped
    let mut out = vec![0.0f32; p.len()];
    let norm = 1.0 / ((2 * h + 1) * (2 * h + 1)) as f32;
    for kx in 0..hw {
        for d in 0..=2 * h {
            let sx = (kx + d).saturating_sub(h).min(hw - 1);
            let (src, dst) = (&py[sx * height..(sx + 1) * height], kx * height);
            for ky in 0..height {
                out[dst + ky] += src[ky] * norm;
            }
        }
    }
    out
}
