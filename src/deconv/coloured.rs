//! The coloured noise the denoising stage faces, per 8×8 DCT coefficient
//! (docs/deconvolution.md "Coloured-noise denoising", docs/method.md §9).
//!
//! # Model
//! Noise of power spectral density `S(ω)` (conventions of [`super::spectrum`]: white noise of
//! variance `σ²` has `S = σ²` in every bin) gives the coefficient of the orthonormal 8×8 DCT
//! basis function `φ_k` the variance (DEB-BM3D, Dabov et al. 2008)
//!
//! ```text
//! σ²_k = E[(φ_k · n)²] = (1/N) Σ_ω S(ω) |Φ_k(ω)|²          (coefficient variance)
//! ```
//!
//! with `Φ_k` the unnormalised DFT of `φ_k` zero-padded to the `N`-pixel grid; for white noise
//! `σ²_k = σ²` for every `k` (Parseval). [`from_psd`] evaluates it for a given `S`, e.g. the
//! regularised inverse's `σ² |T|²` ([`super::spectrum`]).
//!
//! The solver is not that linear inverse: its ℓ1 prior shrinks small (noise-sized) gradients and
//! its cross-channel term couples the channels. So the variances handed to the denoiser are
//! **propagated through the solver itself** ([`through_solver`]): a window of the photograph
//! (`deblur` takes up to 3 × 3 of them over the field, see `coloured_field` in `deconv`), with
//! white noise of the law's per-pixel variance added, restored with the kernels at the window
//! centre, each channel's `λ` at the window's level and the same options as the photograph; `σ²_k` is
//! then the mean of `(φ_k · n_out)²` over the 8×8 blocks of the restored window's interior,
//! which is the same sum evaluated by Monte Carlo. For RGB the blocks are taken in the
//! opponent space the denoiser works in (`Y = (R+G+B)/√3`, …), so the cross-channel correlation
//! the solver introduces is included (for independent channels this is `S_Y = (S_R+S_G+S_B)/3`).
//! Nothing is fitted: the inputs are the PSFs, the noise law and the solver options.
//!
//! Optionally ([`sure_scale`], `DeconvOptions::coloured_sure`, off by default) each window's
//! variances are scaled by `s²`, `s ∈ {½, 1, 2, 4, 8, 16}` chosen by Stein's unbiased risk
//! estimate of the re-blurred, denoised window. It gains on smooth scenes behind a mild blur
//! and loses on textured ones (docs/notes/deblur-history.md "Issue-12, m14").
//!
//! # Units
//! Linear full-scale values squared; `k = 8u + v` (row-major, `u` the vertical frequency).

use super::denoise::{dct2, denoise, CoefficientField, DenoiseOptions, OPP};
use super::problem::KernelSpectrum;
use crate::solve::conv::kernel_to_origin;
use super::spectrum::bin_weight;
use super::{restore_tile, TileSetup};
use crate::image::Plane;
use crate::solve::fft::Fft2;

/// Side of the largest window restored by [`through_solver`] (pixels).
pub const WINDOW: usize = 192;

/// Side of the window [`through_solver`] restores for kernels of `kernel_size` pixels: four
/// kernel widths (the interior measured lies a kernel width inside the edge), rounded up to a
/// multiple of 32, between 96 and [`WINDOW`].
pub fn window_side(kernel_size: usize) -> usize {
    (4 * kernel_size).div_ceil(32).saturating_mul(32).clamp(96, WINDOW)
}

/// The orthonormal 8×8 DCT-II basis function `φ_k` (row-major).
pub fn basis(k: usize) -> [f32; 64] {
    let (u, v) = (k / 8, k % 8);
    let a = |f: usize| if f == 0 { (1.0f64 / 8.0).sqrt() } else { (2.0f64 / 8.0).sqrt() };
    let c = |f: usize, n: usize| a(f) * (std::f64::consts::PI * (2 * n + 1) as f64 * f as f64 / 16.0).cos();
    std::array::from_fn(|i| (c(u, i / 8) * c(v, i % 8)) as f32)
}

/// `σ²_k = (1/N) Σ_ω S(ω) |Φ_k(ω)|²` for a PSD given per bin of `fft`'s half spectrum.
pub fn from_psd(fft: &Fft2, psd: &[f32]) -> [f32; 64] {
    let (w, h) = (fft.width, fft.height);
    let n = (w * h) as f64;
    std::array::from_fn(|k| {
        let phi = basis(k);
        let mut padded = vec![0.0f32; w * h];
        for r in 0..8 {
            padded[r * w..r * w + 8].copy_from_slice(&phi[r * 8..r * 8 + 8]);
        }
        let spec = fft.forward(&padded);
        let s: f64 = spec.iter().zip(psd).enumerate().map(|(i, (c, p))| bin_weight(i / h, w) * (c.norm_sqr() * p) as f64).sum();
        (s / n) as f32
    })
}

/// The mean of `(φ_k · x)²` over the 8×8 blocks (lattice step 2) of `x` (`w` wide) inside
/// `[m, w − m) × [m, h − m)`, after removing `x`'s mean there.
pub fn block_variance(x: &[f32], w: usize, h: usize, m: usize) -> [f32; 64] {
    let (x0, x1, y0, y1) = (m, w.saturating_sub(m), m, h.saturating_sub(m));
    if x1 < x0 + 8 || y1 < y0 + 8 {
        return [0.0; 64];
    }
    let cnt = ((x1 - x0) * (y1 - y0)) as f64;
    let mean = (y0..y1).flat_map(|y| (x0..x1).map(move |i| x[y * w + i] as f64)).sum::<f64>() / cnt;
    let mut acc = [0.0f64; 64];
    let (mut blocks, mut b, mut c) = (0usize, [0.0f32; 64], [0.0f32; 64]);
    for by in (y0..=y1 - 8).step_by(2) {
        for bx in (x0..=x1 - 8).step_by(2) {
            for r in 0..8 {
                for q in 0..8 {
                    b[r * 8 + q] = x[(by + r) * w + bx + q] - mean as f32;
                }
            }
            dct2(&b, &mut c);
            acc.iter_mut().zip(&c).for_each(|(a, v)| *a += (*v as f64).powi(2));
            blocks += 1;
        }
    }
    std::array::from_fn(|k| (acc[k] / blocks.max(1) as f64) as f32)
}

/// How [`through_solver`] perturbs a window `j` with the white draw `n` (the law's variance at
/// `j`) to read the solver's noise off it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Response {
    /// `(restore(j + ε n) − restore(j)) / ε`; `ε` = 1 is the response to extra noise on top of
    /// the already noisy data (the field of sessions 13–19).
    Forward(f32),
    /// `(restore(j + ε n) − restore(j − ε n)) / 2ε`: the solver's Jacobian at its operating
    /// point `j`, applied to `n`, to second order in `ε`.
    Symmetric(f32),
    /// The two-realisation noise of the solve on the re-blurred pilot: `x̂ = restore(j)`,
    /// `d = B x̂` (circular, the window's kernels), `(restore(d + n₁) − restore(d + n₂)) / √2`
    /// with `n₁`, `n₂` independent white draws of the law's variance at `d`. Three solves.
    Pilot,
}

/// Noise through the solver, per decorrelated plane (opponent for three channels) and DCT
/// coefficient: the response `Δ` of [`Response`] `response` (`restore(j + n) − restore(j)` for
/// `Forward(1)`) on square windows `base[c]` (side `setup.width`, e.g. [`window_side`]) of data
/// `j` (a flat level, or a crop of the photograph), `n` white with the per-pixel variance
/// `variance(c, j)`, `kernels[c]` the channel's kernel, `setup` the solver settings.
/// Deterministic (fixed seed). Two window solves either way.
pub fn through_solver(base: &[Vec<f32>], variance: &dyn Fn(usize, f32) -> f32, kernels: &[Plane], setup: &TileSetup) -> Propagation {
    through_solver_as(base, variance, kernels, setup, Response::Forward(1.0))
}

/// [`through_solver`] with an explicit [`Response`].
pub fn through_solver_as(base: &[Vec<f32>], variance: &dyn Fn(usize, f32) -> f32, kernels: &[Plane], setup: &TileSetup, response: Response) -> Propagation {
    let side = setup.width;
    let mut rng = crate::rng::Rng::new(0x5eed);
    // a white draw of the law's variance at the levels `at`, per channel
    let white = |at: &[Vec<f32>], rng: &mut crate::rng::Rng| -> Vec<Vec<f32>> { at.iter().enumerate().map(|(c, b)| b.iter().map(|j| (variance(c, *j).max(0.0).sqrt() as f64 * rng.normal()) as f32).collect()).collect() };
    let plus = |a: &[Vec<f32>], d: &[Vec<f32>], e: f32| -> Vec<Vec<f32>> { a.iter().zip(d).map(|(b, d)| b.iter().zip(d).map(|(j, v)| j + e * v).collect()).collect() };
    let draw = white(base, &mut rng);
    let shifted = |e: f32| plus(base, &draw, e);
    let setup = TileSetup { width: side, height: side, field: None, ..*setup };
    if response == Response::Pilot {
        let (pilot, _) = restore_tile(base, kernels, &setup);
        let fft = Fft2::plan(side, side);
        let data: Vec<Vec<f32>> = pilot.iter().zip(kernels).map(|(x, k)| super::convolve_spec(&fft, x, &KernelSpectrum::new(&fft, &kernel_to_origin(k, side, side))).iter().map(|v| v.clamp(0.0, 1.0)).collect()).collect();
        let (na, nb) = (white(&data, &mut rng), white(&data, &mut rng));
        let (a, b) = (plus(&data, &na, 1.0), plus(&data, &nb, 1.0));
        let (ra, _) = restore_tile(&a, kernels, &setup);
        let (rb, _) = restore_tile(&b, kernels, &setup);
        let diff: Vec<Vec<f32>> = ra.iter().zip(&rb).map(|(x, y)| x.iter().zip(y).map(|(p, q)| (p - q) * std::f32::consts::FRAC_1_SQRT_2).collect()).collect();
        let variances = opponent_block_variances(&diff, side, interior_margin(kernels, side));
        return Propagation { variances, restored: pilot, perturbed: ra, perturbation: draw };
    }
    let (eps, low) = match response {
        Response::Forward(e) => (e, 0.0),
        Response::Symmetric(e) => (e, -e),
        Response::Pilot => unreachable!("handled above"),
    };
    let (perturbed, _) = restore_tile(&shifted(eps), kernels, &setup);
    let (clean, _) = if low == 0.0 { restore_tile(base, kernels, &setup) } else { restore_tile(&shifted(low), kernels, &setup) };
    let scale = 1.0 / (eps - low);
    let restored: Vec<Vec<f32>> = perturbed.iter().zip(&clean).map(|(r, c)| r.iter().zip(c).map(|(a, b)| (a - b) * scale).collect()).collect();
    let variances = opponent_block_variances(&restored, side, interior_margin(kernels, side));
    let perturbation = draw.iter().map(|d| d.iter().map(|v| v * (eps - low)).collect()).collect();
    Propagation { variances, restored: clean, perturbed, perturbation }
}

/// [`block_variance`] of `d` (per channel, `side²`) per decorrelated plane: the opponent planes
/// of the denoiser for three channels, the channels otherwise.
fn opponent_block_variances(d: &[Vec<f32>], side: usize, m: usize) -> Vec<[f32; 64]> {
    let n = side * side;
    if d.len() == 3 {
        (0..3).map(|i| block_variance(&(0..n).map(|p| (0..3).map(|c| OPP[i][c] * d[c][p]).sum()).collect::<Vec<f32>>(), side, side, m)).collect()
    } else {
        d.iter().map(|p| block_variance(p, side, side, m)).collect()
    }
}

/// What [`through_solver`] measured on a window.
pub struct Propagation {
    /// `σ²_k` per decorrelated plane.
    pub variances: Vec<[f32; 64]>,
    /// `restore(j)` per channel (`restore(j − ε n)` for [`Response::Symmetric`]).
    pub restored: Vec<Vec<f32>>,
    /// `restore(j + ε n)` per channel.
    pub perturbed: Vec<Vec<f32>>,
    /// The difference of the two inputs per channel (`ε n`, `2ε n` for [`Response::Symmetric`]).
    pub perturbation: Vec<Vec<f32>>,
}

/// The margin kept clear of a window's edge when it is measured: the unknown-boundary solve
/// extrapolates the outer kernel radius, so a kernel width (at most a quarter of the side).
fn interior_margin(kernels: &[Plane], side: usize) -> usize {
    kernels.iter().map(|k| k.width).max().unwrap_or(1).min(side / 4)
}

/// Noise-level scales tried by [`sure_scale`]: powers of two from ½ to 16.
const SCALES: [f32; 6] = [0.5, 1.0, 2.0, 4.0, 8.0, 16.0];

/// A square window of the photograph (`side²`, per channel), what [`through_solver`] measured
/// on it, and the channels' kernels at its centre.
pub struct Window<'a> {
    pub data: &'a [Vec<f32>],
    pub propagation: &'a Propagation,
    pub kernels: &'a [Plane],
    pub side: usize,
}

/// The denoising stage's strength on one window, chosen by Stein's unbiased risk estimate
/// (SURE, heteroscedastic form) of the re-blurred result: for the restoration denoised with the
/// noise variances `s² σ²_k`, `f_s(j) = B x̂_s(j)`,
///
/// ```text
/// R(s) = Σ_p (f_s(j) − j)²_p − Σ_p V(j_p) + 2 Σ_p n_p (f_s(j + n) − f_s(j))_p
/// ```
///
/// over the window's interior `p`, an unbiased estimate (up to the finite difference) of
/// `Σ_p (f_s(j) − B x)²_p`, the error of the fit against the noise-free data: the last sum is the
/// Monte-Carlo divergence `Σ_p V_p ∂f_p/∂j_p` with the perturbation `n ~ N(0, V)` that
/// [`through_solver`] already restored. `s` from [`SCALES`], walking from 1 towards the smaller
/// risk while it falls. Nothing is fitted: the law `V`, the kernels and the solver define it.
pub fn sure_scale(win: &Window, variance: &dyn Fn(usize, f32) -> f32, denoiser: &DenoiseOptions) -> f32 {
    let (side, prop) = (win.side, win.propagation);
    let m = interior_margin(win.kernels, side);
    let inside: Vec<usize> = (m..side - m).flat_map(|y| (m..side - m).map(move |x| y * side + x)).collect();
    let expected: f64 = win.data.iter().enumerate().map(|(c, j)| inside.iter().map(|p| variance(c, j[*p]).max(0.0) as f64).sum::<f64>()).sum();
    let fft = Fft2::plan(side, side);
    let spectra: Vec<KernelSpectrum> = win.kernels.iter().map(|k| KernelSpectrum::new(&fft, &kernel_to_origin(k, side, side))).collect();
    let fit = |restored: &[Vec<f32>], s: f32| -> Vec<Vec<f32>> {
        let planes: Vec<Plane> = restored.iter().map(|r| Plane { width: side, height: side, data: r.clone() }).collect();
        let field = CoefficientField::uniform(prop.variances.iter().map(|v| v.map(|x| x * s * s)).collect());
        let out = denoise(&planes, &DenoiseOptions { coefficient_variance: Some(field), ..denoiser.clone() });
        out.iter().zip(&spectra).map(|(x, ks)| super::convolve_spec(&fft, &x.data, ks)).collect()
    };
    let risk = |s: f32| -> f64 {
        let (f0, f1) = (fit(&prop.restored, s), fit(&prop.perturbed, s));
        let mut r = -expected;
        for c in 0..win.data.len() {
            for &p in &inside {
                r += ((f0[c][p] - win.data[c][p]) as f64).powi(2) + 2.0 * (prop.perturbation[c][p] * (f1[c][p] - f0[c][p])) as f64;
            }
        }
        r
    };
    let one = SCALES.iter().position(|s| *s == 1.0).unwrap_or(0);
    let mut best = (one, risk(SCALES[one]));
    for dir in [1isize, -1] {
        let mut i = one as isize + dir;
        while (0..SCALES.len() as isize).contains(&i) {
            let r = risk(SCALES[i as usize]);
            if r >= best.1 {
                break;
            }
            best = (i as usize, r);
            i += dir;
        }
        if best.0 != one {
            break;
        }
    }
    SCALES[best.0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::problem::KernelSpectrum;
    use crate::deconv::spectrum::{apply, gradient_power, noise_gain, regularised_inverse};
    use crate::deconv::synth::SyntheticLens;
    use crate::solve::conv::kernel_to_origin;

    /// White noise: every coefficient's variance is the flat σ², from the PSD and measured.
    #[test]
    fn white_noise_gives_the_flat_sigma_per_coefficient() {
        let fft = Fft2::plan(64, 48);
        let sigma2 = 2.5e-5f32;
        let v = from_psd(&fft, &vec![sigma2; fft.spectrum_len()]);
        for (k, s) in v.iter().enumerate() {
            assert!((s / sigma2 - 1.0).abs() < 1e-3, "k {k}: {s:e}");
        }
        let mut rng = crate::rng::Rng::new(9);
        let (w, h) = (256, 256);
        let x: Vec<f32> = (0..w * h).map(|_| (sigma2.sqrt() as f64 * rng.normal()) as f32).collect();
        let m = block_variance(&x, w, h, 0);
        for (k, s) in m.iter().enumerate() {
            assert!((s / sigma2 - 1.0).abs() < 0.1, "k {k}: {s:e}");
        }
    }

    /// The regularised inverse of a far-defocused kernel: the block statistics of its output on
    /// white noise match `(1/N) Σ S |Φ_k|²` with `S = σ² |T|²` within 15 % per coefficient, and
    /// the low-frequency coefficients carry far more noise than the flat σ² suggests.
    #[test]
    fn psd_prediction_matches_blocks_of_coloured_noise() {
        let (w, h) = (256, 256);
        let fft = Fft2::plan(w, h);
        let kernel = SyntheticLens { chromatic: 1.0, ..SyntheticLens::new(31, 3) }.kernel(0, 0.0, 0.0, w, h);
        let ks = KernelSpectrum::new(&fft, &kernel_to_origin(&kernel, w, h));
        let t = regularised_inverse(&ks, &gradient_power(&fft), 2e-3);
        let sigma2 = 2.0e-5f32;
        let psd: Vec<f32> = noise_gain(&t).iter().map(|g| g * sigma2).collect();
        let predicted = from_psd(&fft, &psd);
        let mut rng = crate::rng::Rng::new(5);
        let mut measured = [0.0f32; 64];
        for _ in 0..4 {
            let x: Vec<f32> = (0..w * h).map(|_| (sigma2.sqrt() as f64 * rng.normal()) as f32).collect();
            let m = block_variance(&apply(&fft, &x, &t), w, h, 0);
            measured.iter_mut().zip(&m).for_each(|(a, b)| *a += b / 4.0);
        }
        for k in 1..64 {
            assert!((measured[k] / predicted[k] - 1.0).abs() < 0.15, "k {k}: measured {:e} predicted {:e}", measured[k], predicted[k]);
        }
        let hi = predicted[1..].iter().fold(0.0f32, |a, b| a.max(*b));
        let lo = predicted[1..].iter().fold(f32::INFINITY, |a, b| a.min(*b));
        assert!(hi > 10.0 * lo && hi > 5.0 * sigma2, "{lo:e} {hi:e}");
    }

    /// SURE's strength on a window with the identity kernel: a flat patch (no signal the
    /// denoiser can remove) takes more smoothing than the propagated noise suggests (`s > 1`),
    /// and more than a patch of strong, random fine texture with the same noise.
    #[test]
    fn sure_scale_smooths_flat_windows_more_than_textured_ones() {
        let side = 64;
        let mut delta = Plane::new(3, 3);
        delta.set(1, 1, 1.0);
        let kernels = vec![delta; 3];
        let opts = super::super::DeconvOptions::default();
        let (lambda, order) = (vec![2.5 * 1e-4f32; 3], vec![1usize, 0, 2]);
        let setup = TileSetup { width: side, height: side, lambda: &lambda, order: &order, opts: &opts, field: None, data_weight: None };
        let sigma2 = 1e-4f32;
        let mut rng = crate::rng::Rng::new(17);
        let mut noisy = |f: &dyn Fn(usize) -> f32| -> Vec<Vec<f32>> { (0..3).map(|_| (0..side * side).map(|p| f(p) + (sigma2.sqrt() as f64 * rng.normal()) as f32).collect()).collect() };
        let flat = noisy(&|_| 0.4);
        // random 2-px cells between 0.2 and 0.7: nothing repeats for block matching to exploit
        let mut cells = crate::rng::Rng::new(18);
        let values: Vec<f32> = (0..(side / 2) * (side / 2)).map(|_| 0.2 + 0.5 * cells.uniform() as f32).collect();
        let texture = noisy(&|p| values[(p / side / 2) * (side / 2) + (p % side) / 2]);
        let var = |_: usize, _: f32| sigma2;
        let denoiser = DenoiseOptions { parallel: false, ..DenoiseOptions::default() };
        let scale = |data: &[Vec<f32>]| {
            let prop = through_solver(data, &var, &kernels, &setup);
            sure_scale(&Window { data, propagation: &prop, kernels: &kernels, side }, &var, &denoiser)
        };
        let (sf, st) = (scale(&flat), scale(&texture));
        assert!(sf > 1.0, "flat window: s = {sf}");
        assert!(st < sf, "textured window s = {st}, flat window s = {sf}");
    }
}
