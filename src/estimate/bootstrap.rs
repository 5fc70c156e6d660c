//! Per-kernel uncertainty by a parametric bootstrap over both captures' noise laws, with the
//! bootstrap bias estimate (issue 16; docs/estimation.md "Uncertainty").
//!
//! # Model
//! The fitted model is the world the replicates are drawn from: the registered pinhole planes
//! `I_c` stand for the sharp scene, the profile's kernels `b̂` for the lens. The prediction of
//! the wide-open capture is `p_c = B̂_c(s_c·I_c)` (the forward model `simulate` applies,
//! [`crate::optics::forward::blur_channel`]). Replicate `r` draws both captures anew:
//!
//! `j_r = p + √v_o(p) ⊙ n_r`,   `I_r = I + √v_p(I) ⊙ n'_r`,   `n_r, n'_r ~ N(0, 1)` per pixel,
//!
//! with `v_o(x) = v_p(x) = g·x + σ²` the sensor's Poisson–Gaussian law
//! ([`crate::profile::noise::NoiseLaw`]) fitted on the model's residual `j − p` with the
//! pinhole's propagated noise taken out ([`residual_noise_law`]): both captures come from the
//! same sensor at the same gain. (A law fitted on a capture's own local differences counts
//! sharp texture as noise: on the pinhole capture it predicted five times the measured error on
//! the test bed; on the wide-open capture of a nearly sharp channel, the profile's `[noise]`,
//! it overstated the variance 17 times and the error 1.8 times.) Resampling the pinhole too
//! matters: it is dim (exposure ratio `s ≫ 1`), so its noise, amplified by `s`, enters the data
//! term as errors in the variables. Each replicate pair goes through the same fit as the
//! profile ([`super::estimate`] with the profile's kernel size and options: window fits, joint
//! refinement, re-estimated exposure ratio), giving `b*_r`, and through the same fit without
//! the prior (`c_λ = 0`, so `λ = 0`: the constrained least-squares fit, `b ≥ 0`, `1ᵀb = σ_sum`),
//! giving `b*_{0,r}`. The data themselves are also fitted without the prior, giving `b̂₀`.
//!
//! # Estimates (per kernel, per pixel `i`, `R` replicates)
//! - variance of the regularised fit: `v_i = Σ_r (b*_{r,i} − b̄_i)² / (R − 1)`;
//! - bias of the prior: the unregularised fit has no prior to flatten the kernel, but it has a
//!   bias of its own, `β₀(b) = E[b̂₀] − b` (on a wide kernel mostly the floor that the
//!   constraint `b ≥ 0` leaves where noise is clipped in the tails), and that bias is nearly the
//!   same at `b̂` as at `b`. The replicates, drawn around `b̂`, measure it: `b̄₀ − b̂ ≈ β₀`
//!   (`b̄₀` the mean of the `b*_{0,r}`). So
//!   `β = b̄₀ − b̂₀ = (b̂ + β₀) − (b + β₀) + noise`, and `E[β] = E[b̂] − b`, the prior's bias.
//!   (The plain bootstrap bias `b̄ − b̂` measures the prior's shrinkage of `b̂`, which is already
//!   flattened: on a window with a strong TV prior it is a quarter of the true bias, see the
//!   tests. Until session 53 `β = b̂ − b̂₀`, which also counted `−β₀`: on lac9's 101-px blue
//!   kernels 7.4 % of bias against 5.4 % of total error, docs/estimation.md "Uncertainty".)
//!   `‖β‖²` carries noise: its expectation is `‖bias‖² + Σ_i (d_i + v₀_i / R)` with
//!   `d_i = Var_r(b*_{r,i} − b*_{0,r,i})` (the noise of `b̂ − b̂₀`) and `v₀_i = Var_r(b*_{0,r,i})`
//!   (that of the mean `b̄₀`), so the bias energy is `B² = max(0, ‖β‖² − Σ_i (d_i + v₀_i / R))`
//!   and the bias map is `β̃_i = |β_i| · √(B² / ‖β‖²)`;
//! - convergence: the profile's joint fit continued past its end on the data
//!   (`EstimateOptions::convergence_tail`, `joint::continue_fit`) gives the chunk iterates
//!   `s_0 = b̂, …, s_C`; with `D_j = s_{j+1} − s_j` and `ρ = median ‖D_{j+1}‖/‖D_j‖` (capped),
//!   `c = s_C + D_{C−1}·ρ/(1 − ρ) − b̂` ([`convergence_map`]), the predicted step to the fit's
//!   optimum, which the replicates (same start rule, same stop) cannot show. Part of that step
//!   is noise (the optimum fits more of it than the stopped fit), not error of `b̂`: the
//!   replicates' fits are continued the same way, and their steps' variance
//!   `n_i = Var_r(c_{r,i})` is that noise, so the convergence energy is
//!   `C² = max(0, ‖c‖² − Σ_i n_i)` and the map `c̃_i = |c_i| · √(C² / ‖c‖²)` (as the bias);
//! - stored uncertainty `u_i = √(β̃_i² + v_i + c̃_i²)`, the root mean square error of pixel `i`; the
//!   predicted relative L2 error of the kernel is `‖u‖₂ / ‖b̂‖₂` ([`predicted_error`]), an
//!   estimate of `√E‖b̂ − b‖² / ‖b‖`.
//!
//! Not included: model mismatch the fitted model cannot express (a PSF that changes faster
//! than the grid's blend, light outside the `k × k` support, registration error): the
//! replicates are drawn from the fitted model, so they cannot show it.
//!
//! # Units
//! `u`, `β`, `√v`, `c` are on the kernel's scale (a fraction of the point source's light per
//! pixel), `k × k`, the geometry of the kernel.

use super::solver::{solve_tile, TileData, TileSettings};
use super::{estimate, Estimate, EstimateError, EstimateOptions};
use crate::image::{Image, Plane};
use crate::optics::forward::blur_channel;
use crate::profile::noise::NoiseLaw;
use crate::rng::Rng;
use crate::solve::conv::CircularConvolution;
use crate::solve::operator::LinearOperator;

/// Bootstrap settings.
#[derive(Clone, Debug)]
pub struct BootstrapOptions {
    /// Replicates (at least 2).
    pub replicates: usize,
    /// Seed of the noise draws.
    pub seed: u64,
}

impl Default for BootstrapOptions {
    fn default() -> Self {
        Self { replicates: 4, seed: 17 }
    }
}

/// Why the bootstrap failed.
#[derive(Debug, thiserror::Error)]
pub enum BootstrapError {
    #[error("bootstrap replicate {replicate}: {source}")]
    Estimate { replicate: usize, #[source] source: EstimateError },
    #[error("bootstrap replicate {replicate} gave a {got} grid, the profile has {want}")]
    Grid { replicate: usize, got: String, want: String },
}

/// One kernel's uncertainty: the four per-pixel maps of the module docs.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelUncertainty {
    /// `√v`, the replicate standard deviation of the regularised fit.
    pub std: Plane,
    /// `|β̃|`, the bias map scaled to the debiased bias energy.
    pub bias: Plane,
    /// `|c̃|`, the convergence term: the predicted step to the fit's optimum
    /// ([`convergence_map`]) less its noise (module docs); zero when it was not measured.
    pub convergence: Plane,
    /// `u = √(β̃² + v + c²)`, what `psf-unc-<C>.tiff` stores.
    pub total: Plane,
}

/// The convergence term of one kernel (docs/estimation.md "Uncertainty", *Convergence term*):
/// `snaps` are the kernel's iterates at the ends of the chunks of the continued fit
/// (`snaps[0] = b̂`, then one per chunk of `chunk` iterations), `iterations` the fit's own
/// iterations before them. With the chunk steps `D_j = s_{j+1} − s_j` and their contraction
/// `ρ = median_j ‖D_{j+1}‖ / ‖D_j‖`, capped at `1 − 1/H` (`H = (iterations + chunks·chunk) /
/// chunk`, the whole fit's length in chunks: the extrapolation never adds more than the fit
/// has run so far, at its last pace), the optimum is extrapolated geometrically,
///
/// `b_∞ ≈ s_C + D_{C−1} · ρ/(1 − ρ)`,
///
/// and the map is `b_∞ − b̂` per pixel (signed; its L2 norm is the distance). Zero with fewer than two
/// chunks; every value finite and ≥ 0.
pub fn convergence_map(snaps: &[&[f32]], k: usize, chunk: usize, iterations: usize) -> Plane {
    if snaps.len() < 3 || snaps.iter().any(|s| s.len() != k * k) {
        return Plane::new(k, k);
    }
    let steps: Vec<Vec<f64>> = snaps.windows(2).map(|w| w[1].iter().zip(w[0]).map(|(&a, &b)| (a - b) as f64).collect()).collect();
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let mut ratios: Vec<f64> = steps.windows(2).map(|w| if norm(&w[0]) > 0.0 { norm(&w[1]) / norm(&w[0]) } else { 0.0 }).collect();
    ratios.sort_by(f64::total_cmp);
    let horizon = (iterations + steps.len() * chunk) as f64 / chunk.max(1) as f64;
    let rho = ratios[ratios.len() / 2].clamp(0.0, 1.0 - 1.0 / horizon.max(2.0));
    let f = rho / (1.0 - rho);
    let (first, last, step) = (snaps[0], snaps[snaps.len() - 1], &steps[steps.len() - 1]);
    let data = (0..k * k).map(|i| (last[i] - first[i]) as f64 + step[i] * f).map(|c| if c.is_finite() { c as f32 } else { 0.0 }).collect();
    Plane { width: k, height: k, data }
}

/// Per-pixel running sums `Σx`, `Σx²` of a set of samples.
#[derive(Clone, Debug)]
struct Moments {
    sum: Vec<f64>,
    sum2: Vec<f64>,
    count: usize,
}

impl Moments {
    fn new(n: usize) -> Self {
        Self { sum: vec![0.0; n], sum2: vec![0.0; n], count: 0 }
    }

    fn add(&mut self, x: impl Iterator<Item = f64>) {
        for (i, v) in x.enumerate() {
            self.sum[i] += v;
            self.sum2[i] += v * v;
        }
        self.count += 1;
    }

    /// Unbiased per-pixel variance (zeros below 2 samples).
    fn variance(&self) -> Vec<f64> {
        let r = self.count as f64;
        if self.count < 2 {
            return vec![0.0; self.sum.len()];
        }
        self.sum.iter().zip(&self.sum2).map(|(&a, &b)| ((b - a * a / r) / (r - 1.0)).max(0.0)).collect()
    }
}

/// One kernel's bootstrap: the unregularised fit `b̂₀` of the data, and the running sums of the
/// replicates' regularised fits `b*_r`, unregularised fits `b*_{0,r}` and differences
/// `δ_r = b*_r − b*_{0,r}`.
#[derive(Clone, Debug)]
pub struct Replicates {
    unregularised: Vec<f64>,
    fits: Moments,
    fits0: Moments,
    diffs: Moments,
    convergence: Vec<f64>,
    /// The running sums of the replicates' own (signed) convergence terms `c_r`.
    tails: Moments,
    width: usize,
}

impl Replicates {
    /// No replicates yet, for the fitted kernel `b̂` (its geometry) and its unregularised fit `b̂₀`.
    pub fn new(fitted: &Plane, unregularised: &Plane) -> Self {
        let n = fitted.data.len();
        debug_assert_eq!(unregularised.data.len(), n, "the unregularised fit has the kernel's size");
        let unregularised = unregularised.data.iter().map(|&v| v as f64).collect();
        Self { unregularised, fits: Moments::new(n), fits0: Moments::new(n), diffs: Moments::new(n), convergence: vec![0.0; n], tails: Moments::new(n), width: fitted.width }
    }

    /// Sets the convergence term `c` of the fitted kernel ([`convergence_map`]; same size).
    pub fn with_convergence(mut self, map: &Plane) -> Self {
        if map.data.len() == self.convergence.len() {
            self.convergence = map.data.iter().map(|&v| v as f64).collect();
        }
        self
    }

    /// Adds the convergence term `c_r` of replicate `r`'s regularised fit (its fit continued
    /// the same way as the profile's, [`convergence_map`]); with two or more, their variance is
    /// taken out of the convergence energy (module docs).
    pub fn add_tail(&mut self, map: &Plane) {
        if map.data.len() == self.convergence.len() {
            self.tails.add(map.data.iter().map(|&v| v as f64));
        }
    }

    /// Adds replicate `r`: its regularised fit `b*_r` and unregularised fit `b*_{0,r}`.
    pub fn add(&mut self, fit: &Plane, unregularised: &Plane) {
        self.fits.add(fit.data.iter().map(|&v| v as f64));
        self.fits0.add(unregularised.data.iter().map(|&v| v as f64));
        self.diffs.add(fit.data.iter().zip(&unregularised.data).map(|(&a, &b)| (a - b) as f64));
    }

    /// Standard deviation, bias, convergence and total per pixel (module docs); no spread and
    /// no bias with fewer than 2 replicates. Every value is finite and ≥ 0.
    pub fn finish(&self) -> KernelUncertainty {
        let n = self.fits.sum.len();
        let r = self.fits0.count as f64;
        let v = self.fits.variance();
        // β = b̄₀ − b̂₀ and the noise energy of its two terms
        let beta: Vec<f64> = if self.fits0.count < 2 { vec![0.0; n] } else { self.fits0.sum.iter().zip(&self.unregularised).map(|(s, b0)| s / r - b0).collect() };
        let d: f64 = self.diffs.variance().iter().sum::<f64>() + self.fits0.variance().iter().sum::<f64>() / r.max(1.0);
        let b2: f64 = beta.iter().map(|b| b * b).sum();
        let scale = if b2 > 0.0 { ((b2 - d).max(0.0) / b2).sqrt() } else { 0.0 };
        let clean = |x: f64| if x.is_finite() { x as f32 } else { 0.0 };
        let plane = |f: &dyn Fn(usize) -> f64| Plane { width: self.width, height: n / self.width.max(1), data: (0..n).map(|i| clean(f(i))).collect() };
        let bias = |i: usize| beta[i].abs() * scale;
        let c2: f64 = self.convergence.iter().map(|c| c * c).sum();
        let n2: f64 = self.tails.variance().iter().sum();
        let cscale = if self.tails.count < 2 { 1.0 } else if c2 > 0.0 { ((c2 - n2).max(0.0) / c2).sqrt() } else { 0.0 };
        let c: Vec<f64> = self.convergence.iter().map(|v| v * cscale).collect();
        KernelUncertainty { std: plane(&|i| v[i].sqrt()), bias: plane(&bias), convergence: plane(&|i| c[i].abs()), total: plane(&|i| (bias(i).powi(2) + v[i] + c[i] * c[i]).sqrt()) }
    }
}

/// Adds `√v(x) · n` to every sample of `x` (`n ~ N(0, 1)`).
pub(crate) fn add_noise(x: &[f32], variance: impl Fn(f32) -> f32, rng: &mut Rng) -> Vec<f32> {
    x.iter().map(|&p| p + variance(p).max(0.0).sqrt() * rng.normal() as f32).collect()
}

/// The uncertainty of one window's kernel `b̂` (module docs, on the window's working domain
/// [`super::tile_data`]): the unregularised fit `b̂₀` of `td`, then `R` replicates
/// `j_r = s·I ⊛ b̂ + √v_o · n`, `s·I_r = s·I + √v_s · n'`, each fitted with [`solve_tile`]
/// with `settings` and with `λ = 0`. `open_var(x)` is the wide-open variance at signal `x`,
/// `sharp_var(x)` the variance of the scaled pinhole `s·I` at value `x` (`s²·v_p(x/s)`). The
/// single-window form of [`bootstrap_estimate`] (no joint refinement).
pub fn bootstrap_window(td: &TileData, fitted: &Plane, open_var: impl Fn(f32) -> f32, sharp_var: impl Fn(f32) -> f32, settings: &TileSettings, o: &BootstrapOptions, rng: &mut Rng) -> KernelUncertainty {
    let mut pred = vec![0.0f32; td.pw * td.ph];
    CircularConvolution::new(fitted, td.pw, td.ph).apply(&td.sharp, &mut pred);
    let s = TileSettings { kernel_size: fitted.width, ..settings.clone() };
    let s0 = TileSettings { lambda: Some(0.0), ..s.clone() };
    let mut acc = Replicates::new(fitted, &solve_tile(td, &s0, |_, _| true).kernel);
    for _ in 0..o.replicates.max(2) {
        let blurred = add_noise(&pred, &open_var, rng);
        let sharp = add_noise(&td.sharp, &sharp_var, rng);
        let rep = TileData { pw: td.pw, ph: td.ph, sharp, blurred, mask: td.mask.clone() };
        acc.add(&solve_tile(&rep, &s, |_, _| true).kernel, &solve_tile(&rep, &s0, |_, _| true).kernel);
    }
    acc.finish()
}

/// The fallback noise law of both captures of `est` (when [`residual_noise_law`] cannot be
/// fitted): the profile's law (fitted on the wide-open capture), else white noise at the
/// measured level. The pinhole capture is taken with the same
/// sensor at the same gain, so the same law in full-scale units applies to it: it is dimmer, not
/// noisier per unit signal. (The law cannot be fitted on the pinhole capture itself: its
/// texture is sharp and the fit's local differences would count it as noise.)
fn noise_law(est: &Estimate) -> NoiseLaw {
    let nc = est.open_linear.len();
    est.profile.meta.noise.as_ref().and_then(|l| l.for_channels(nc).ok()).unwrap_or_else(|| NoiseLaw::new(vec![0.0; nc], est.noise_sigma.clone(), "given"))
}

/// The fitted model's prediction of the wide-open capture, per channel: `p_c = B̂_c(s_c·I_c)`.
pub(crate) fn predictions(est: &Estimate) -> Vec<Plane> {
    let g = &est.profile.grid;
    let ratio = &est.profile.meta.exposure_ratio;
    (0..g.channels.len())
        .map(|c| {
            let mut sharp = est.pinhole_registered[c].clone();
            sharp.scale(ratio[c] as f32);
            blur_channel(&sharp, g, c)
        })
        .collect()
}

/// The noise law of the wide-open capture fitted on the fitted model's residual
/// (docs/estimation.md "Uncertainty", *Noise law from the residual*): per channel `c`, the
/// residual `r = j − p` (`p = B̂(s·I)`, `pred`) over the valid pixels has the variance
///
/// `Var r ≈ g·p·(1 + s·q) + σ²·(1 + s²·q)`,   `q = median_t ‖b̂_t‖²`,
///
/// the wide-open noise `g·p + σ²` plus the pinhole's noise `s²·Σ_u b̂(u)²·v(I(x − u))`
/// propagated through the kernel (with `Σ_u b̂(u)² I(x − u) ≈ q·p/s`). So
/// [`NoiseLaw::fit_residual`] of the scaled residual `r/√(1 + s²q)` against the signal
/// `p·(1 + s·q)/(1 + s²·q)` gives `g` and `σ²` of the sensor directly. Unlike the law fitted on
/// the capture alone ([`NoiseLaw::fit_image`], local differences), it does not count the
/// texture a nearly sharp channel leaves in the wide-open capture as noise. `None` when a
/// channel has too few valid pixels.
pub fn residual_noise_law(est: &Estimate, pred: &[Plane]) -> Option<NoiseLaw> {
    let g = &est.profile.grid;
    let mut signals = Vec::with_capacity(pred.len());
    let mut residuals = Vec::with_capacity(pred.len());
    for (c, p) in pred.iter().enumerate() {
        let s = est.profile.meta.exposure_ratio.get(c).copied().unwrap_or(1.0);
        let q = super::joint::median_kernel_energy(&g.kernels[c]);
        let (a, b) = ((1.0 + s * q) / (1.0 + s * s * q), 1.0 / (1.0 + s * s * q).sqrt());
        signals.push(p.map(|v| (v as f64 * a) as f32));
        residuals.push(Plane { width: p.width, height: p.height, data: est.open_linear[c].data.iter().zip(&p.data).map(|(&j, &v)| ((j - v) as f64 * b) as f32).collect() });
    }
    let mut law = NoiseLaw::fit_residual(&signals, &residuals, Some(&est.valid_masks)).ok()?;
    law.source = "residual".into();
    Some(law)
}

/// Stored planes of linear planes: `transfer.encode(x + black_c)`.
fn encoded(planes: Vec<Plane>, like: &Estimate, black: &[f32]) -> Image {
    let src = &like.profile.meta.source;
    let planes = planes
        .into_iter()
        .enumerate()
        .map(|(c, p)| {
            let b = black.get(c).or(black.first()).copied().unwrap_or(0.0);
            p.map(|v| src.transfer.encode(v + b))
        })
        .collect();
    Image { planes, channels: src.channels.clone(), format: src.sample_format, transfer: src.transfer, raw: None }
}

/// One bootstrap pair around the fitted model of `est` (module docs), as stored images.
fn replicate_pair(est: &Estimate, pred: &[Plane], law: &NoiseLaw, black: &[f32], rng: &mut Rng) -> (Image, Image) {
    let draw = |planes: &[Plane], law: &NoiseLaw, rng: &mut Rng| -> Vec<Plane> {
        planes.iter().enumerate().map(|(c, p)| Plane { width: p.width, height: p.height, data: add_noise(&p.data, |x| law.variance(c, x), rng) }).collect()
    };
    let open = draw(pred, law, rng);
    let pin = draw(&est.pinhole_registered, law, rng);
    (encoded(open, est, black), encoded(pin, est, black))
}

/// Per-kernel planes `[channel][tile]`.
type Maps = Vec<Vec<Plane>>;

/// Estimates a pair with `opts` and checks it gives the grid `g`; returns its kernels and its
/// convergence terms (empty without [`EstimateOptions::convergence_tail`]).
fn estimate_like(open: &Image, pin: &Image, opts: &EstimateOptions, g: &crate::optics::psf_grid::PsfGrid, replicate: usize) -> Result<(Maps, Maps), BootstrapError> {
    let e = estimate(open, pin, opts).map_err(|source| BootstrapError::Estimate { replicate, source })?;
    let rg = e.profile.grid;
    if (rg.columns, rg.rows, rg.kernel_size) != (g.columns, g.rows, g.kernel_size) {
        let shape = |c: usize, r: usize, k: usize| format!("{c}×{r} ({k} px)");
        return Err(BootstrapError::Grid { replicate, got: shape(rg.columns, rg.rows, rg.kernel_size), want: shape(g.columns, g.rows, g.kernel_size) });
    }
    Ok((rg.kernels, e.convergence))
}

/// The uncertainty of every kernel of `est` (`[channel][tile]`; module docs): the
/// unregularised estimate of the same data, then `o.replicates` bootstrap pairs drawn around
/// the fitted model, each estimated with `opts` and with `λ = 0` (the profile's kernel size; the
/// whole pipeline, joint refinement included). Costs `2·R + 1` estimates.
///
/// # Errors
/// An estimate that fails or gives another grid (replicate 0 is the unregularised fit of the
/// data, replicates count from 1).
pub fn bootstrap_estimate(est: &Estimate, opts: &EstimateOptions, o: &BootstrapOptions) -> Result<Vec<Vec<KernelUncertainty>>, BootstrapError> {
    let g = &est.profile.grid;
    let pred = predictions(est);
    let law = residual_noise_law(est, &pred).unwrap_or_else(|| noise_law(est));
    // the profile's kernel size and grid: a replicate neither re-probes the field nor may land
    // on another grid
    let (w, h) = (est.open_linear[0].width, est.open_linear[0].height);
    let tile = super::tile_for_grid(w, h, g.columns, g.rows).or(opts.tile);
    // the replicates' fits are continued as the profile's was, for the noise of its convergence term
    let tail = !est.convergence.is_empty();
    let ropts = EstimateOptions { kernel_size: Some(g.kernel_size), tile, progress: false, field_variation: Some(est.field_variation.clone()), convergence_tail: tail, ..opts.clone() };
    let zero = EstimateOptions { lambda_scale: 0.0, convergence_tail: false, ..ropts.clone() };
    let black = &opts.black_level;
    let data = (encoded(est.open_linear.clone(), est, black), encoded(est.pinhole_registered.clone(), est, black));
    let unreg = estimate_like(&data.0, &data.1, &zero, g, 0)?.0;
    let none = Plane::new(0, 0);
    let conv = |c: usize, t: usize| est.convergence.get(c).and_then(|m| m.get(t)).unwrap_or(&none);
    let mut acc: Vec<Vec<Replicates>> = g.kernels.iter().zip(&unreg).enumerate().map(|(c, (ks, k0))| ks.iter().zip(k0).enumerate().map(|(t, (k, k0))| Replicates::new(k, k0).with_convergence(conv(c, t))).collect()).collect();
    let mut rng = Rng::new(o.seed);
    for r in 1..=o.replicates.max(2) {
        let (open, pin) = replicate_pair(est, &pred, &law, black, &mut rng);
        let ((fit, tails), (fit0, _)) = (estimate_like(&open, &pin, &ropts, g, r)?, estimate_like(&open, &pin, &zero, g, r)?);
        for ((a, ks), k0s) in acc.iter_mut().zip(&fit).zip(&fit0) {
            a.iter_mut().zip(ks.iter().zip(k0s)).for_each(|(a, (k, k0))| a.add(k, k0));
        }
        for (a, cs) in acc.iter_mut().zip(&tails) {
            a.iter_mut().zip(cs).for_each(|(a, c)| a.add_tail(c));
        }
    }
    Ok(acc.iter().map(|a| a.iter().map(Replicates::finish).collect()).collect())
}

/// The stored maps (`u`, [`KernelUncertainty::total`]) of [`bootstrap_estimate`]'s result.
pub fn totals(unc: &[Vec<KernelUncertainty>]) -> Vec<Vec<Plane>> {
    unc.iter().map(|ks| ks.iter().map(|k| k.total.clone()).collect()).collect()
}

/// Predicted relative L2 error of a kernel from its uncertainty map: `‖u‖₂ / ‖b‖₂`.
pub fn predicted_error(unc: &Plane, kernel: &Plane) -> f64 {
    let n2 = |p: &Plane| p.data.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>();
    (n2(unc) / n2(kernel).max(1e-300)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::conv::convolve_direct;

    /// A 96² window of random 2×2 cells (values 0.2…0.8), a Gaussian truth kernel of σ 1.3 px
    /// (`k` = 11), and its exact blur.
    fn scene() -> (Plane, Plane, Plane) {
        let (w, h, k) = (96usize, 96usize, 11usize);
        let mut r = Rng::new(4);
        let cells: Vec<f32> = (0..(w / 2) * (h / 2)).map(|_| 0.2 + 0.6 * r.uniform() as f32).collect();
        let sharp = Plane::from_fn(w, h, |x, y| cells[(y / 2) * (w / 2) + x / 2]);
        let mut truth = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - 5.0, y as f32 - 5.0);
            (-(dx * dx + dy * dy) / (2.0 * 1.3 * 1.3)).exp()
        });
        let s = truth.sum() as f32;
        truth.scale(1.0 / s);
        let blurred = convolve_direct(&sharp, &truth);
        (sharp, blurred, truth)
    }

    /// One noisy realisation of the window (both captures noisy: σ_o on the blurred, σ_p on the
    /// sharp) and its fit.
    fn realisation(sharp: &Plane, blurred: &Plane, sigma: (f32, f32), st: &TileSettings, rng: &mut Rng) -> (TileData, Plane) {
        let noisy = |p: &Plane, s: f32, rng: &mut Rng| Plane { width: p.width, height: p.height, data: p.data.iter().map(|&v| v + s * rng.normal() as f32).collect() };
        let (j, i) = (noisy(blurred, sigma.0, rng), noisy(sharp, sigma.1, rng));
        let valid = vec![true; j.width * j.height];
        let td = crate::estimate::tile_data(&j, &i, &valid, 1.0, (16, 80, 16, 80), st.kernel_size);
        let k = solve_tile(&td, st, |_, _| true).kernel;
        (td, k)
    }

    /// Calibration on a window with a known truth: with a TV prior strong enough that its bias
    /// is most of the error (`c_λ` = 6) and noise in both captures, the predicted error (bias
    /// and variance, median over 3 fits) is within a factor 1.5 of the RMS error against the
    /// truth over 12 independent noise realisations; the standard deviation alone
    /// under-predicts (the bias counts).
    #[test]
    fn predicted_error_matches_the_measured_error() {
        let (sharp, blurred, truth) = scene();
        let sigma = (0.01f32, 0.01f32);
        let st = TileSettings { kernel_size: 11, lambda: None, lambda_scale: 6.0, noise_sigma: Some(sigma.0 as f64), mu_relative: 1.0, max_iterations: 120, tolerance: 1e-4 };
        let mut rng = Rng::new(21);
        let measured: Vec<f64> = (0..12).map(|_| crate::estimate::relative_error(&realisation(&sharp, &blurred, sigma, &st, &mut rng).1, &truth)).collect();
        let measured = (measured.iter().map(|e| e * e).sum::<f64>() / measured.len() as f64).sqrt();
        let o = BootstrapOptions { replicates: 8, seed: 1 };
        let mut pred = Vec::new();
        let mut std_only = Vec::new();
        for _ in 0..3 {
            let (td, k) = realisation(&sharp, &blurred, sigma, &st, &mut rng);
            let v = |_: f32| sigma.0 * sigma.0;
            let u = bootstrap_window(&td, &k, v, |_| sigma.1 * sigma.1, &st, &o, &mut rng);
            pred.push(predicted_error(&u.total, &k));
            std_only.push(predicted_error(&u.std, &k));
        }
        pred.sort_by(f64::total_cmp);
        std_only.sort_by(f64::total_cmp);
        let (p, s) = (pred[1], std_only[1]);
        assert!(p / measured > 1.0 / 1.5 && p / measured < 1.5, "predicted {p:.4}, measured {measured:.4} (std only {s:.4})");
        assert!(s < 0.8 * measured, "the bias should matter here: std only {s:.4}, measured {measured:.4}");
    }

    /// The law fitted on the model's residual recovers the sensor's law on a nearly sharp
    /// channel (Gaussian kernel of σ 0.6 px, high-contrast 2×2 cells, Poisson–Gaussian noise in
    /// both captures), where the law fitted on the capture's local differences counts the
    /// texture as noise and overestimates the variance (1.8 times here, 17 times on the test
    /// bed's simulator ×1 red channel).
    #[test]
    fn residual_law_recovers_the_sensor_on_a_sharp_channel() {
        let (w, h, k) = (160usize, 120usize, 7usize);
        let (gain, read) = (1e-4f64, 2e-3f64);
        let mut r = Rng::new(8);
        let cells: Vec<f32> = (0..(w / 2) * (h / 2)).map(|_| 0.1 + 0.8 * r.uniform() as f32).collect();
        let sharp = Plane::from_fn(w, h, |x, y| cells[(y / 2) * (w / 2) + x / 2]);
        let mut kern = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - 3.0, y as f32 - 3.0);
            (-(dx * dx + dy * dy) / (2.0 * 0.6 * 0.6)).exp()
        });
        let s = kern.sum() as f32;
        kern.scale(1.0 / s);
        let truth = NoiseLaw::new(vec![gain], vec![read], "given");
        let noisy = |p: &Plane, r: &mut Rng| Image::new(vec![Plane { width: w, height: h, data: add_noise(&p.data, |x| truth.variance(0, x), r) }]);
        let (open, pin) = (noisy(&convolve_direct(&sharp, &kern), &mut r), noisy(&sharp, &mut r));
        let opts = crate::estimate::EstimateOptions { kernel_size: Some(k), tile: Some(80), joint_iterations: 10, ..Default::default() };
        let est = estimate(&open, &pin, &opts).expect("estimate");
        let law = residual_noise_law(&est, &predictions(&est)).expect("residual law");
        let image = NoiseLaw::fit_image(&est.open_linear, 0.995).expect("image law");
        let at = |l: &NoiseLaw| l.variance(0, 0.5) as f64 / truth.variance(0, 0.5) as f64;
        assert!((at(&law) - 1.0).abs() < 0.2, "residual law {:?} / {:?}: variance ratio at 0.5 {:.3}", law.gain, law.read, at(&law));
        assert!(at(&image) > 1.5, "the image law should count the texture: ratio {:.3}", at(&image));
        // the profile stores the lower of the two fits per channel (estimate::profile_noise_law),
        // from the joint fit's prediction (the same model as `predictions`, to float rounding)
        let stored = est.profile.meta.noise.as_ref().expect("stored law");
        assert_eq!(stored.source, "residual", "{stored:?}");
        assert!((at(stored) - at(&law)).abs() < 1e-3, "stored {:?} against residual {:?}", stored, law);
    }

    /// The running sums: two replicates `b̂ ± d` give std `|d|·√2`; the bias is
    /// `β = b̄₀ − b̂₀`, counted in full when the replicates do not vary, and removed when its
    /// energy is below their noise (it is then indistinguishable from noise).
    #[test]
    fn replicate_moments() {
        let p = |v: f32| Plane::filled(2, 1, v);
        // b̂ = 0.5 with a bias: b̂₀ = 0.7 (the truth 0.6 plus the unregularised fit's own +0.1),
        // the replicates' unregularised fits 0.6 ± 0.02 (b̂ + 0.1): β = 0.6 − 0.7 = −0.1 per
        // pixel, less the noise of the mean (Var 0.0008 / 2 per pixel): bias² 0.01 − 0.0004
        let mut a = Replicates::new(&p(0.5), &p(0.7));
        a.add(&p(0.52), &p(0.62));
        a.add(&p(0.48), &p(0.58));
        let u = a.finish();
        assert!((u.std.data[0] - 0.02 * 2f32.sqrt()).abs() < 1e-6 && (u.bias.data[0] - 0.0096f32.sqrt()).abs() < 1e-6, "{u:?}");
        assert!((u.total.data[0] - (0.0096f32 + 0.0008).sqrt()).abs() < 1e-6);
        // β = 0.6 − 0.7 again, but the difference of the fits varies (0.09, −0.29): β is below
        // the noise `d` of `b̂ − b̂₀` (the mean's own noise, Var 0.0002 / 2, alone would not
        // remove it)
        let mut b = Replicates::new(&p(0.5), &p(0.7));
        b.add(&p(0.7), &p(0.61));
        b.add(&p(0.3), &p(0.59));
        assert!(b.finish().bias.data.iter().all(|&v| v == 0.0));
    }

    /// The unregularised fit's own bias is not counted as the prior's: an unbiased `b̂` whose
    /// unregularised fits all sit 0.1 high (the floor `b ≥ 0` leaves in the tails) has no bias;
    /// `b̂ − b̂₀`, the estimate before session 53, counted the 0.1.
    #[test]
    fn the_unregularised_fits_own_bias_cancels() {
        let p = |v: f32| Plane::filled(3, 1, v);
        let mut a = Replicates::new(&p(0.5), &p(0.6));
        for (f, f0) in [(0.52, 0.61), (0.48, 0.59), (0.5, 0.6)] {
            a.add(&p(f), &p(f0));
        }
        let u = a.finish();
        assert!(u.bias.data.iter().all(|&v| v == 0.0), "{u:?}");
        let former = (0.5f32 - 0.6).abs();
        assert!(u.total.data[0] < 0.5 * former, "total {} against the former bias {former}", u.total.data[0]);
    }

    /// The convergence map recovers the limit of an exactly geometric sequence
    /// `s_j = b_∞ − ρ^j e` (so `b_∞ − s_0 = e`), and the cap `ρ ≤ 1 − 1/H` bounds a sequence
    /// that does not contract.
    #[test]
    fn convergence_map_extrapolates_a_geometric_sequence() {
        let (k, rho) = (3usize, 0.6f64);
        let e: Vec<f64> = (0..k * k).map(|i| 0.01 * (i as f64 - 4.0)).collect();
        let seq: Vec<Vec<f32>> = (0..5).map(|j| e.iter().map(|&v| (0.1 - rho.powi(j) * v) as f32).collect()).collect();
        let snaps: Vec<&[f32]> = seq.iter().map(Vec::as_slice).collect();
        let m = convergence_map(&snaps, k, 5, 40);
        for (got, want) in m.data.iter().zip(&e) {
            assert!((*got as f64 - want).abs() < 1e-5, "{got} vs {want}");
        }
        // steps of constant size: ρ = 1 is capped at 1 − 1/H, H = (40 + 4·5)/5 = 12 chunks, so
        // the map is 4 steps done plus 11 more
        let flat: Vec<Vec<f32>> = (0..5).map(|j| vec![0.001 * j as f32; k * k]).collect();
        let m = convergence_map(&flat.iter().map(Vec::as_slice).collect::<Vec<_>>(), k, 5, 40);
        assert!(m.data.iter().all(|&v| (v - 0.015).abs() < 1e-6), "{:?}", m.data);
        assert!(convergence_map(&snaps[..2], k, 5, 40).data.iter().all(|&v| v == 0.0));
    }

    /// The replicates' convergence terms (issue 16, branch e17u): their variance is the noise of
    /// the profile's step `c` and is taken out of its energy (`‖c‖² = 0.02`, replicate steps
    /// `c ± 0.05`, variance sum `0.01`: half the energy stays, `c̃ = 0.1/√2`); replicates that
    /// all take the same step (deterministic convergence) leave it whole; fewer than two
    /// replicate steps leave it whole too.
    #[test]
    fn convergence_noise_is_the_replicates_variance() {
        let (f, f0) = (Plane::filled(2, 1, 0.5), Plane::filled(2, 1, 0.3));
        let c = Plane::filled(2, 1, 0.1);
        let with_tails = |tails: &[f32]| {
            let mut a = Replicates::new(&f, &f0).with_convergence(&c);
            for &t in tails {
                a.add(&Plane::filled(2, 1, 0.6), &Plane::filled(2, 1, 0.4));
                a.add_tail(&Plane::filled(2, 1, t));
            }
            a.finish().convergence
        };
        let noisy = with_tails(&[0.05, 0.15]);
        assert!(noisy.data.iter().all(|&v| (v - 0.1 / 2f32.sqrt()).abs() < 1e-6), "{noisy:?}");
        assert!(with_tails(&[0.1, 0.1]).data.iter().all(|&v| (v - 0.1).abs() < 1e-7));
        assert!(with_tails(&[0.0, 0.2, 0.1, -0.1]).data.iter().all(|&v| v == 0.0));
        assert!(with_tails(&[0.3]).data.iter().all(|&v| (v - 0.1).abs() < 1e-7));
    }

    /// The convergence term adds to the stored total in quadrature and is kept as its own map.
    #[test]
    fn convergence_adds_in_quadrature() {
        let (f, f0) = (Plane::filled(2, 1, 0.5), Plane::filled(2, 1, 0.3));
        let mut a = Replicates::new(&f, &f0);
        a.add(&Plane::filled(2, 1, 0.6), &Plane::filled(2, 1, 0.4));
        a.add(&Plane::filled(2, 1, 0.4), &Plane::filled(2, 1, 0.2));
        let u = a.clone().finish();
        let uc = a.with_convergence(&Plane::filled(2, 1, 0.1)).finish();
        for i in 0..2 {
            assert!((uc.total.data[i] - (u.total.data[i].powi(2) + 0.01).sqrt()).abs() < 1e-6 && uc.convergence.data[i] == 0.1, "{uc:?}");
        }
        assert!(u.convergence.data.iter().all(|&v| v == 0.0));
    }
}
