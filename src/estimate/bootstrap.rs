//! Per-kernel uncertainty by a parametric bootstrap over the noise law (issue 16;
//! docs/estimation.md "Uncertainty").
//!
//! # Model
//! For a fitted kernel `b̂` of a window with sharp patch `s·I` (the solver's working domain,
//! [`super::tile_data`]), the simulated prediction is `p = s·I ⊛ b̂` (circular, the solver's
//! own forward model). Replicate `r` draws `j_r = p + √v(p) · n_r`, `n_r ~ N(0, 1)` per pixel,
//! with `v(x) = g·x + σ_read²` the channel's Poisson–Gaussian noise law
//! ([`crate::profile::noise::NoiseLaw`]), and refits the window with the same solver and
//! settings (fewer iterations). The uncertainty is the per-pixel standard deviation over the
//! `R` replicates, `u = √(Σ_r (b_r − b̄)² / (R − 1))`; the predicted relative L2 error of the
//! kernel is `‖u‖₂ / ‖b̂‖₂`.
//!
//! It measures the noise part of the error only: a bias of the prior (TV flattening a peak)
//! is the same in every replicate and does not appear in `u`.
//!
//! # Units
//! `u` is on the kernel's scale (a fraction of the point source's light per pixel), `k × k`,
//! the same geometry as the kernel.

use super::solver::{solve_tile, TileData, TileSettings};
use super::{default_window, fit_window, tile_data, Estimate, EstimateOptions};
use rayon::prelude::*;
use crate::image::Plane;
use crate::rng::Rng;
use crate::solve::conv::CircularConvolution;
use crate::solve::operator::LinearOperator;

/// Bootstrap settings.
#[derive(Clone, Debug)]
pub struct BootstrapOptions {
    /// Replicates per kernel (at least 2).
    pub replicates: usize,
    /// Iteration cap of each refit.
    pub max_iterations: usize,
    /// Seed of the noise draws (each window draws from `seed` mixed with its index).
    pub seed: u64,
}

impl Default for BootstrapOptions {
    fn default() -> Self {
        Self { replicates: 6, max_iterations: 60, seed: 17 }
    }
}

/// The per-pixel standard deviation of one window's kernel over `o.replicates` refits from
/// resampled noise (module docs); `variance(x)` is the noise variance at linear signal `x`.
pub fn bootstrap_window(td: &TileData, kernel: &Plane, variance: impl Fn(f32) -> f32, settings: &TileSettings, o: &BootstrapOptions, rng: &mut Rng) -> Plane {
    let n = td.pw * td.ph;
    let mut pred = vec![0.0f32; n];
    CircularConvolution::new(kernel, td.pw, td.ph).apply(&td.sharp, &mut pred);
    let k = kernel.width;
    let reps = o.replicates.max(2);
    let s = TileSettings { kernel_size: k, max_iterations: o.max_iterations, ..settings.clone() };
    let (mut sum, mut sum2) = (vec![0.0f64; k * k], vec![0.0f64; k * k]);
    for _ in 0..reps {
        let blurred: Vec<f32> = pred.iter().map(|&p| p + variance(p).max(0.0).sqrt() * rng.normal() as f32).collect();
        let rep = TileData { pw: td.pw, ph: td.ph, sharp: td.sharp.clone(), blurred, mask: td.mask.clone() };
        let fit = solve_tile(&rep, &s, |_, _| true);
        for (i, &v) in fit.kernel.data.iter().enumerate() {
            sum[i] += v as f64;
            sum2[i] += (v as f64) * (v as f64);
        }
    }
    let r = reps as f64;
    let data = sum.iter().zip(&sum2).map(|(&a, &b)| ((b - a * a / r).max(0.0) / (r - 1.0)).sqrt() as f32).collect();
    Plane { width: k, height: k, data }
}

/// The uncertainty of every kernel of `est` (per channel, per tile; windows in parallel): each
/// window is rebuilt as the estimate fitted it (`opts`' window and solver settings) and
/// bootstrapped around the profile's kernel with the profile's noise law (the measured white
/// noise level of the channel when the profile has none).
pub fn bootstrap_estimate(est: &Estimate, opts: &EstimateOptions, o: &BootstrapOptions) -> Vec<Vec<Plane>> {
    let g = &est.profile.grid;
    let (w, h, k) = (est.open_linear[0].width, est.open_linear[0].height, g.kernel_size);
    let window = opts.window.unwrap_or_else(|| default_window(k, w, h));
    let law = est.profile.meta.noise.as_ref().and_then(|l| l.for_channels(g.channels.len()).ok());
    let jobs: Vec<(usize, usize)> = (0..g.channels.len()).flat_map(|c| (0..g.tile_count()).map(move |t| (c, t))).collect();
    let out: Vec<Plane> = jobs
        .par_iter()
        .map(|&(c, t)| {
            let win = fit_window(g.centers[t], window, w, h);
            let s = est.profile.meta.exposure_ratio[c] as f32;
            let td = tile_data(&est.open_linear[c], &est.pinhole_registered[c], &est.valid_masks[c], s, win, k);
            let settings = TileSettings { kernel_size: k, lambda: None, lambda_scale: opts.lambda_scale as f32, noise_sigma: None, mu_relative: opts.mu_relative as f32, max_iterations: o.max_iterations, tolerance: opts.tolerance };
            let sigma = est.noise_sigma.get(c).copied().unwrap_or(0.0) as f32;
            let variance = |x: f32| law.as_ref().map_or(sigma * sigma, |l| l.variance(c, x));
            let mut rng = Rng::new(o.seed ^ ((c * g.tile_count() + t) as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            bootstrap_window(&td, &g.kernels[c][t], variance, &settings, o, &mut rng)
        })
        .collect();
    out.chunks(g.tile_count().max(1)).map(<[Plane]>::to_vec).collect()
}

/// Predicted relative L2 error of a kernel from its uncertainty: `‖u‖₂ / ‖b‖₂`.
pub fn predicted_error(unc: &Plane, kernel: &Plane) -> f64 {
    let n2 = |p: &Plane| p.data.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>();
    (n2(unc) / n2(kernel).max(1e-300)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::conv::convolve_direct;

    /// The bootstrap standard deviation shrinks with the noise: a quarter of the noise level
    /// gives well under half the predicted error (about a quarter in theory).
    #[test]
    fn bootstrap_std_shrinks_with_noise() {
        let (w, h, k) = (96usize, 96usize, 9usize);
        let mut r = Rng::new(4);
        let sharp = Plane::from_fn(w, h, |_, _| if r.uniform() < 0.5 { 0.2 } else { 0.8 });
        let mut truth = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - 4.0, y as f32 - 4.0);
            (-(dx * dx + dy * dy) / 4.0).exp()
        });
        let s = truth.sum() as f32;
        truth.scale(1.0 / s);
        let blurred = convolve_direct(&sharp, &truth);
        let valid = vec![true; w * h];
        let td = crate::estimate::tile_data(&blurred, &sharp, &valid, 1.0, (16, 80, 16, 80), k);
        let st = TileSettings { kernel_size: k, lambda: None, lambda_scale: 1.0, noise_sigma: None, mu_relative: 1.0, max_iterations: 60, tolerance: 1e-4 };
        let o = BootstrapOptions { replicates: 6, max_iterations: 60, seed: 1 };
        let err = |sigma: f32| predicted_error(&bootstrap_window(&td, &truth, |_| sigma * sigma, &st, &o, &mut Rng::new(7)), &truth);
        let (hi, lo) = (err(0.02), err(0.005));
        assert!(hi > 0.0 && lo < 0.5 * hi, "σ 0.02: {hi}, σ 0.005: {lo}");
    }
}
