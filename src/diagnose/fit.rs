//! Fitting one model (base + a set of [`Corrections`]) to a wide-open / pinhole pair, and its
//! figures: χ², reduced χ², RMS, normalised residual maps.
//!
//! # Model in the fit
//! Per channel `c` on the linear axis of the model's transfer curve:
//! `m = G(x)·(Σ_t w_t·(U_t * P̃) + g_c·(G_σ * P̃)) + β_c`
//! with `U_t = s·(1 − f)·K_t` (one common sum per channel), `g_c = s·f` the glare amplitude,
//! `G` the vignetting × gradient gain and `β_c` the offset (each present only when its
//! correction is). The fit alternates: kernels by projected FISTA ([`super::kernels`]) with the
//! other parameters fixed, then one Gauss–Newton step for the scalar parameters, then the
//! weights `1/Var` from the new prediction. Three rounds; the channels' kernel steps run
//! concurrently, and each channel's FISTA momentum and step norm carry from one round to the
//! next ([`super::kernels::KernelWarm`]), and from one fit to a fit that continues it
//! ([`Warm`], [`fit_from`]). Under `veiling_glare` or
//! `black_level`, each kernel step hands the kernels' common flat floor to the additive term
//! ([`remove_common_floor`]).
//!
//! # Noise and χ²
//! `Var = Var_open(m) + ΣK²·s²·Var_pinhole(level)` on the linear axis, from the measured
//! [`NoiseCurve`]s (the pinhole's own noise propagated through the kernel), mapped to the stored
//! axis by the transfer curve's slope. `χ² = Σ (stored − encode(m))² / Var_stored` over the
//! evaluation set: every pixel at least a kernel radius inside the image, in every channel.
//! Under `saturation`, clipped wide-open pixels are censored (no contribution while the model
//! also reaches the clip level) and pixels whose reference footprint is clipped count as one
//! (the model cannot predict them; they leave the data term).
//!
//! Parameters: `C·(T·(k² − 1) + 1)` for the kernels and sums plus each correction's own.

use super::kernels::{fit_kernels_warm, kernel_divergence_with, rademacher, Divergence, KernelFitSettings, KernelStep, KernelWarm};
use rayon::prelude::*;
use crate::optics::kernel_operator::KernelOperator;
use super::model::{model_transfer, reference_planes, Corrections, GlareCorrection};
use super::noise::{srgb_slope, NoiseCurve};
use crate::estimate::dilate;
use crate::image::{Image, Plane, Transfer};
use crate::image::filter::gaussian_blur_wide;
use crate::optics::psf_grid::PsfGrid;
use crate::profile::RegistrationInfo;
use std::sync::Arc;

/// The kernel step of every fit: [`KernelStep::Tangent`], which converges at 31–45 px where
/// the whole-space step stalls (docs/diagnosis.md, "The kernel step on the tangent space");
/// with the noise curve's corrections ([`super::noise::measure_residual`]'s level
/// normalisation, [`Fit::highpass_absorbed`]) the proof suite passes with it.
pub const KERNEL_STEP: KernelStep = KernelStep::Tangent;

/// Margin (px) by which a screening fit's scored set keeps away from the dropped blocks under
/// a reference map: the Lanczos-4 taps (4 px) and rounding.
const SCORED_MARGIN: usize = 6;

/// Stored values at or above this count as clipped.
pub const CLIP: f32 = 0.995;

/// Largest share of the wide-open noise in the residual's high-pass that the detail a restored
/// reference gives up ([`Fit::lost_detail`]) may hold before a noise curve measured from that
/// residual no longer tests the channel's Poisson–Gaussian law: the default law bound of the
/// verdict ([`super::DiagnoseOptions::consistent_noise`], 10 %), which that detail alone could
/// exceed.
pub const LOST_DETAIL_LAW_BOUND: f64 = 0.10;

/// The measured pair and what is known before any model is fitted.
///
/// The captures are borrowed, not copied (at 4000×3000 RGB each is 144 MB).
pub struct Data<'a> {
    pub open: &'a Image,
    pub pinhole: &'a Image,
    /// Per channel, the wide-open capture's noise curve.
    pub curves: Vec<NoiseCurve>,
    /// The curves come from repeated frames (a session's temporal variance), not from a
    /// model's residual: nothing the model leaves in its residual reaches them.
    pub curves_from_frames: bool,
    /// The base registration (translation, applied as an integer shift).
    pub base_registration: RegistrationInfo,
    /// The reference's noise variance relative to the wide-open capture's noise curve at the
    /// same level: `frames_open / frames_pinhole` when the captures average frames (1 for equal
    /// captures).
    pub pinhole_variance_scale: f64,
    /// The quick fits that search a candidate's parameters ([`screen`]) keep about this many
    /// pixels per channel in their data term (every pixel by default; the diagnosis sets
    /// [`super::DiagnoseOptions::screen_pixels`]).
    pub screen_pixels: usize,
    /// The fits on "every pixel" ([`fit`], [`fit_from`], [`fit_converging`]) keep about this
    /// many pixels per channel in their data term, the spread blocks of [`fit_subset`], while
    /// their figures (χ², residual, noise curve) still cover every pixel (every pixel by
    /// default; the diagnosis sets [`super::DiagnoseOptions::fit_pixels`]).
    pub fit_pixels: usize,
    /// The reference planes built ([`Setup::new`]), keyed by what they depend on
    /// ([`ReferenceKey`]): fits on the same reference geometry share one copy. Weak: the
    /// planes live as long as a fit or setup holds them; dead entries are dropped.
    reference_cache: std::sync::Mutex<Vec<(ReferenceKey, std::sync::Weak<Vec<Plane>>)>>,
}

/// What the model's reference planes depend on: the transfer that decodes the pinhole capture,
/// the registration whose integer translation shifts it and the diffraction restoration.
#[derive(Clone, Debug, PartialEq)]
struct ReferenceKey {
    transfer: Transfer,
    registration: RegistrationInfo,
    diffraction: Option<super::model::DiffractionCorrection>,
}

impl<'a> Data<'a> {
    /// The reference planes for `key`, built by `make` unless a live copy is cached.
    fn reference(&self, key: ReferenceKey, make: impl FnOnce() -> Vec<Plane>) -> Arc<Vec<Plane>> {
        let mut cache = self.reference_cache.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        cache.retain(|(_, w)| w.strong_count() > 0);
        if let Some(planes) = cache.iter().find(|(k, _)| *k == key).and_then(|(_, w)| w.upgrade()) {
            return planes;
        }
        let planes = Arc::new(make());
        cache.push((key, Arc::downgrade(&planes)));
        planes
    }

    /// The pair with the wide-open capture's noise curves (`noise::measure`, 16 level bins) and
    /// the base registration: a translation of the channels' linear sum.
    pub fn new(open: &'a Image, pinhole: &'a Image, pinhole_variance_scale: f64) -> Data<'a> {
        let curves = open.planes.iter().map(|p| super::noise::measure(p, 16)).collect();
        let lin = |img: &Image| -> Vec<Plane> { img.planes.iter().map(|p| p.map(|v| img.transfer.decode(v))).collect() };
        let model = crate::estimate::register::RegistrationModel::Translation;
        let base_registration = crate::estimate::register::register(&Plane::sum_of(&lin(open)), &Plane::sum_of(&lin(pinhole)), model).info;
        Data { open, pinhole, curves, curves_from_frames: false, base_registration, pinhole_variance_scale, screen_pixels: usize::MAX, fit_pixels: usize::MAX, reference_cache: Default::default() }
    }
}

/// A fitted model's free parameters.
#[derive(Clone, Debug)]
pub struct Model {
    pub corrections: Corrections,
    /// Kernels summing to 1.
    pub grid: PsfGrid,
    /// Exposure ratio `s` per channel (kernel part plus glare part).
    pub exposure: Vec<f64>,
}

/// Iteration budget of a fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitSettings {
    pub rounds: usize,
    pub kernel_iterations: usize,
}

impl Default for FitSettings {
    fn default() -> Self {
        Self { rounds: 3, kernel_iterations: 60 }
    }
}

/// A fitted model and its figures. The per-pixel planes are shared (`Arc`): a clone costs no
/// image memory, and fits on the same reference geometry share its planes ([`Data`]'s cache).
#[derive(Clone)]
pub struct Fit {
    pub model: Model,
    pub transfer: Transfer,
    /// Prediction on the stored axis (encoded, clipped under `saturation`).
    pub predicted: Arc<Vec<Plane>>,
    /// `(stored − predicted)/σ` on the evaluation set, 0 elsewhere.
    pub normalized: Arc<Vec<Plane>>,
    pub eval: Arc<Vec<Vec<bool>>>,
    pub chi2_channel: Vec<f64>,
    pub n_channel: Vec<usize>,
    /// Plain squared residual and variance sums per channel (stored axis).
    pub sq_channel: Vec<f64>,
    pub var_channel: Vec<f64>,
    /// The plain squared residual per channel over the pixels χ² scores as residuals: without
    /// those clipped in either capture where saturation is modelled ([`score_channel`]).
    pub sq_unclipped_channel: Vec<f64>,
    /// Nominal parameter count (kernel values, sums, corrections); BIC's penalty counts these.
    pub params: usize,
    /// Effective degrees of freedom of the kernels (Monte-Carlo divergence of the kernel fit,
    /// [`measure_kernel_dof`]; docs/diagnosis.md "Effective degrees of freedom"), once measured
    /// or inherited; `None`: the nominal kernel count stands in.
    pub kernel_dof: Option<f64>,
    /// Per channel, the fraction of the noise's high-pass energy the kernel fit absorbs
    /// ([`super::kernels::Divergence::highpass_absorbed`]), measured with `kernel_dof` or
    /// inherited: the residual's noise curve is divided by `1 − α_hp`
    /// ([`super::noise::NoiseCurve::absorbed`]). `None`: not measured.
    pub highpass_absorbed: Option<Vec<f64>>,
    /// Nominal kernel parameters (`C·(T·(k² − 1) + 1)`), part of `params`.
    pub kernel_params: usize,
    /// How badly the noise curve misfits a Poisson–Gaussian law on this model's linear axis
    /// (Σ over channels of [`super::noise::PoissonGaussian::chi2`]), and the worst relative
    /// misfit of a channel whose law the curve can test (not in `law_untested`).
    pub noise_chi2: f64,
    pub noise_misfit: f64,
    /// Per channel, the detail a restored reference gives up (`pinhole_diffraction`), as a
    /// share of the wide-open noise in the residual's high-pass, mean over the scored pixels
    /// ([`super::diffraction::propagated_energies`]); 0 without a restoration.
    pub lost_detail: Vec<f64>,
    /// The channels whose noise law `noise_misfit` leaves out: a curve measured from the
    /// residual, where the lost detail's share is above [`LOST_DETAIL_LAW_BOUND`].
    pub law_untested: Vec<usize>,
    /// The registered linear reference planes the model used.
    pub reference: Arc<Vec<Plane>>,
    /// Per channel, the variance that the reference's noise, propagated through the
    /// restoration and the kernels, contributes to the high-pass `d` of the residual
    /// ([`super::diffraction::propagated_energy`]), relative to the wide-open capture's own
    /// noise variance at that pixel: what [`super::noise::measure_residual`] must not count
    /// as the wide-open capture's noise.
    pub reference_highpass: Arc<Vec<Plane>>,
    /// The share of the evaluation set the figures cover: 1 when they cover every pixel; a
    /// screening fit on a subset ([`fit_subset`], [`screen`]) scores only the subset's pixels
    /// (`chi2_channel`, `n_channel`, `eval` are the subset's) and [`Fit::chi2`], [`Fit::n`]
    /// scale them by `1/share` to the whole evaluation set's.
    pub share: f64,
    /// Per channel, the power the noise floor puts into the normalised residual's lowest band
    /// ([`super::analysis::LOW_BAND_TOP`]), relative to white noise's (1): the reference's
    /// noise comes through the kernels with `|K̂(f)|²`, which at low frequencies exceeds its
    /// mean `ΣK²` over all frequencies (the share the variance counts). Mean over the scored
    /// pixels of `1 + ρ(x)·(⟨|Û|²⟩_band − Σ U²)/ΣU²`, `ρ` the reference's share of the variance
    /// ([`Setup::low_band_floor`]). Empty for screening fits.
    pub low_band_floor: Vec<f64>,
    /// The kernel solver's state at the end of the fit ([`Warm`]): what a later fit continuing
    /// this one ([`fit_from`], [`fit_subset_from`], [`fit_converging`])
    /// starts its FISTA momentum from.
    pub warm: Warm,
}

/// A fit's measured kernel degrees of freedom and absorbed high-pass shares with its tile
/// count ([`Fit::dof`]): what [`Fit::inherit`] scales onto another fit.
#[derive(Clone, Debug)]
pub struct InheritedDof {
    kernel_dof: Option<f64>,
    highpass_absorbed: Option<Vec<f64>>,
    tiles: usize,
}

/// The kernel solver's state a fit leaves ([`Fit::warm`]): per channel the FISTA momentum, its
/// common sum and the step norm's power vector ([`KernelWarm`]), and the data term's pixel
/// budget it was left on (`data_pixels` of the fit: the subset's blocks or every pixel).
///
/// A later fit that starts from the fitted model continues the momentum instead of starting
/// from `z = x, t = 1` (the offsets rescaled by the ratio of the common sums, as between the
/// rounds of one fit; docs/notes/diagnosis-history.md, "Session 20 (d20)"). The norm's vector is
/// kept only when the later fit runs on the same pixel budget (the same operator); across a subset
/// and every pixel it is estimated cold. Where the momentum points uphill for the new problem (a
/// new effect's parameters, new weights), adaptive restart drops it after one iteration.
#[derive(Clone, Debug, Default)]
pub struct Warm {
    channels: Vec<KernelWarm>,
    data_pixels: usize,
}

impl Warm {
    /// Whether the fit left no momentum (a fit of no rounds, or of no kernel iterations).
    pub fn is_empty(&self) -> bool {
        self.channels.iter().all(KernelWarm::is_empty)
    }
}

impl Fit {
    /// χ² over the evaluation set (estimated from the scored share when [`Fit::share`] < 1).
    pub fn chi2(&self) -> f64 {
        self.chi2_channel.iter().sum::<f64>() / self.share
    }
    /// Pixels of the evaluation set (all channels).
    pub fn n(&self) -> usize {
        (self.n_scored() as f64 / self.share).round() as usize
    }
    /// Pixels the figures were computed on (all channels).
    pub fn n_scored(&self) -> usize {
        self.n_channel.iter().sum()
    }
    /// The parameters the consistency test subtracts: the kernels' effective degrees of
    /// freedom (nominal until measured) plus the corrections' and sums' nominal count.
    pub fn effective_params(&self) -> f64 {
        let other = (self.params - self.kernel_params) as f64;
        self.kernel_dof.map_or(self.params as f64, |k| k + other)
    }
    /// χ² per effective degree of freedom: `χ² / (N − p_eff)`.
    pub fn reduced_chi2(&self) -> f64 {
        self.chi2() / (self.n() as f64 - self.effective_params()).max(1.0)
    }
    /// [`Fit::reduced_chi2`] per channel (each channel carries an equal share of `p_eff`).
    pub fn reduced_chi2_channel(&self) -> Vec<f64> {
        let p = self.effective_params() / self.chi2_channel.len().max(1) as f64;
        self.chi2_channel.iter().zip(&self.n_channel).map(|(c, n)| (c / self.share) / (*n as f64 / self.share - p).max(1.0)).collect()
    }
    /// Takes over `from`'s measured kernel degrees of freedom, scaled by the ratio of tile
    /// counts (a finer grid under `psf_field_variation` has proportionally more): a candidate
    /// is refitted from `from` with the same kernel solver, so it responds to the noise alike.
    pub fn inherit_dof(&mut self, from: &Fit) {
        self.inherit(&from.dof());
    }
    /// What [`Fit::inherit_dof`] takes from this fit, without its whole-image planes: a later
    /// fit can inherit it after this one is dropped.
    pub fn dof(&self) -> InheritedDof {
        InheritedDof { kernel_dof: self.kernel_dof, highpass_absorbed: self.highpass_absorbed.clone(), tiles: self.model.grid.tile_count() }
    }
    /// [`Fit::inherit_dof`] from a fit's [`Fit::dof`].
    pub fn inherit(&mut self, from: &InheritedDof) {
        if let Some(k) = from.kernel_dof {
            let ratio = self.model.grid.tile_count() as f64 / from.tiles.max(1) as f64;
            self.kernel_dof = Some((k * ratio).min(self.kernel_params as f64));
            self.highpass_absorbed = from.highpass_absorbed.as_ref().map(|a| a.iter().map(|v| (v * ratio).min(super::kernels::MAX_ABSORBED)).collect());
        }
    }
    /// `χ² + χ²_noise-law + p·ln N`, with the nominal count `p`. The effective count was tried
    /// (session 63): the probe that measures it runs on the screening subset and counts about
    /// half the whole image's `df_K` (a third with the one-round probe since session 66),
    /// harmless for the reduced χ² but not for a grown grid's
    /// penalty (docs/diagnosis.md, "Effective degrees of freedom").
    pub fn bic(&self) -> f64 {
        self.chi2() + self.noise_chi2 + self.params as f64 * (self.n().max(2) as f64).ln()
    }
    /// RMS of the residual (stored axis).
    pub fn rms(&self) -> f64 {
        (self.sq_channel.iter().sum::<f64>() / self.n_scored().max(1) as f64).sqrt()
    }
    /// RMS of the predicted noise (stored axis): the noise floor.
    pub fn noise_rms(&self) -> f64 {
        (self.var_channel.iter().sum::<f64>() / self.n_scored().max(1) as f64).sqrt()
    }
    /// The law test's figure, `noise_misfit`, or `None` when the curves test no channel's law
    /// (every channel in `law_untested`).
    pub fn law_misfit(&self) -> Option<f64> {
        (self.law_untested.len() < self.chi2_channel.len()).then_some(self.noise_misfit)
    }
}

/// Extra parameters each correction adds.
pub fn correction_params(c: &Corrections, channels: usize) -> usize {
    let mut p = 0;
    if c.tone_curve.is_some() {
        p += 1;
    }
    if c.pinhole_diffraction.is_some() {
        // the Airy radius and the aberration blur
        p += 2;
    }
    if c.misregistration.is_some() {
        p += 2;
    }
    if c.target_tilt.is_some() {
        p += 2;
    }
    if c.veiling_glare.is_some() {
        p += channels + 1;
    }
    if c.vignetting.is_some() {
        p += 3;
    }
    if c.illumination_gradient.is_some() {
        p += 2;
    }
    if c.black_level.is_some() {
        p += channels;
    }
    if c.saturation.is_some() {
        p += 1;
    }
    p
}

/// The kernel field of `grid` on a `columns × rows` grid whose outer centres lie on the
/// frame's edges ([`PsfGrid::edge_centers`], `psf_field_variation`'s layout): the least-squares
/// projection of the old blend onto the new one over every pixel of the `width × height` frame,
///
/// `N = M_x · K · M_yᵀ`,  `M = (W_newᵀ W_new)⁻¹ W_newᵀ W_old`
///
/// per axis (`W[x, j]` the 1-D Catmull–Rom weight of centre `j` at pixel `x`; the blend is a
/// tensor product, so the 2-D projection is the product of the 1-D ones): the start nearest the
/// current model that the new blend can hold. Interpolating the old kernels at the new centres
/// instead puts the held-constant outer kernel on the frame's edge and blends it inwards over a
/// whole spacing (twice the field misfit in `regrid_projects_the_kernel_field_onto_the_edge_layout`).
/// On the mock rig at 768×576 rendered with a tile-centred truth both starts ended 7.3–7.4 %
/// above the current model after the candidates' budget: there the layout itself fits worse.
pub fn regrid(grid: &PsfGrid, width: usize, height: usize, columns: usize, rows: usize) -> PsfGrid {
    let centers = PsfGrid::edge_centers(width, height, columns, rows);
    let new = PsfGrid { kernel_size: grid.kernel_size, columns, rows, centers, channels: grid.channels.clone(), kernels: vec![] };
    let mx = axis_projection(&grid.column_xs(), &new.column_xs(), width);
    let my = axis_projection(&grid.row_ys(), &new.row_ys(), height);
    let k = grid.kernel_size;
    let kernels = (0..grid.channels.len())
        .map(|c| {
            (0..rows * columns)
                .map(|t| {
                    let (j, i) = (t % columns, t / columns);
                    let mut out = vec![0.0f64; k * k];
                    for (l, myl) in my[i].iter().enumerate() {
                        for (kk, mxk) in mx[j].iter().enumerate() {
                            let f = myl * mxk;
                            if f != 0.0 {
                                for (o, v) in out.iter_mut().zip(&grid.kernels[c][l * grid.columns + kk].data) {
                                    *o += f * *v as f64;
                                }
                            }
                        }
                    }
                    Plane::from_vec(k, k, out.into_iter().map(|v| v as f32).collect()).expect("k × k")
                })
                .collect()
        })
        .collect();
    PsfGrid { kernels, ..new }
}

/// `M` (`new.len() × old.len()`) with `Σ_j W_new[x, j]·M[j, k] ≈ W_old[x, k]` in least squares
/// over the pixels `x ∈ [0, len)` ([`regrid`]).
fn axis_projection(old: &[f64], new: &[f64], len: usize) -> Vec<Vec<f64>> {
    use crate::optics::psf_grid::hat_weights_1d;
    let (n, m) = (new.len(), old.len());
    let (mut ata, mut atb) = (vec![vec![0.0f64; n]; n], vec![vec![0.0f64; m]; n]);
    for x in 0..len {
        let (wn, wo) = (hat_weights_1d(new, x as f64), hat_weights_1d(old, x as f64));
        for &(a, va) in &wn {
            for &(b, vb) in &wn {
                ata[a][b] += va as f64 * vb as f64;
            }
            for &(b, vb) in &wo {
                atb[a][b] += va as f64 * vb as f64;
            }
        }
    }
    // one small solve (n = a grid's columns or rows) per old centre; the normal matrix is
    // positive definite wherever centres are over a pixel apart
    let cols: Vec<Vec<f64>> = (0..m).map(|k| crate::solve::dense::solve(ata.clone(), atb.iter().map(|r| r[k]).collect(), 1e-12).unwrap_or_else(|| vec![0.0; n])).collect();
    (0..n).map(|j| cols.iter().map(|c| c[j]).collect()).collect()
}

/// The kernels of `grid` interpolated at `centers`, a `columns × rows` lattice.
pub fn resample(grid: &PsfGrid, centers: Vec<[f64; 2]>, columns: usize, rows: usize) -> PsfGrid {
    let kernels = (0..grid.channels.len()).map(|c| centers.iter().map(|p| grid.kernel_at(c, p[0], p[1])).collect()).collect();
    PsfGrid { kernel_size: grid.kernel_size, columns, rows, centers, channels: grid.channels.clone(), kernels }
}

/// The flat floor common to all `kernels` — the smallest, over kernels, of the median of each
/// kernel's outer ring (a PSF is near zero at its support's edge) — taken out of every kernel.
/// Returns the mass removed per kernel (`floor·k²`, less what the clamp at 0 keeps).
///
/// Why: over a target whose local mean varies slowly, a flat floor under every kernel,
/// `c·(B_k * P)`, is interchangeable at low frequencies with any smooth additive term — a
/// halo `c·k²·(G_σ * P)` or an offset. The base fit has no such term, so its kernels grow the
/// floor to stand for whatever additive light the data hold; a candidate that adds one
/// (`veiling_glare`, `black_level`) must get that light back from the kernels, or the kernel
/// step (slow on a flat mode) leaves it there and the fitted fraction or offset comes out
/// short. Both candidates get the same treatment, so neither wins by inheriting the other's
/// share.
pub fn remove_common_floor(kernels: &mut [Plane]) -> f64 {
    let floor = kernels
        .iter()
        .map(|k| {
            let (kw, kh) = (k.width, k.height);
            let mut ring: Vec<f32> = (0..kw * kh).filter(|&i| i % kw == 0 || i % kw + 1 == kw || i / kw == 0 || i / kw + 1 == kh).map(|i| k.data[i]).collect();
            ring.sort_by(|a, b| a.total_cmp(b));
            ring.get(ring.len() / 2).copied().unwrap_or(0.0)
        })
        .fold(f32::INFINITY, f32::min);
    if kernels.is_empty() || !(floor.is_finite() && floor > 0.0) {
        return 0.0;
    }
    let mut moved = 0.0f64;
    for k in kernels.iter_mut() {
        for v in k.data.iter_mut() {
            let d = v.min(floor);
            *v -= d;
            moved += d as f64;
        }
    }
    moved / kernels.len() as f64
}

/// The free parameters a Gauss–Newton step on the scalars updates: per-channel kernels `U`
/// (their common scale), the blur parts `A U`, glare amplitudes and black-level offsets.
struct ScalarState<'a> {
    u: &'a mut [Vec<Plane>],
    a_parts: &'a mut [Plane],
    glare_amp: &'a mut [f64],
    beta: &'a mut [f64],
}

/// The gain plane `g(x, y)` of the corrections (vignetting × illumination gradient).
/// `Plane::from_fn(w, h, f)` on the pixels where `need` is true (every pixel with `None`),
/// `off` elsewhere: a fit whose data term or figures cover a few blocks of a large capture
/// skips the per-pixel work (noise curves, transfer) on the rest. The same values where
/// computed.
fn plane_where(w: usize, h: usize, need: Option<&[bool]>, off: f32, f: impl Fn(usize, usize) -> f32) -> Plane {
    match need {
        None => Plane::from_fn(w, h, f),
        Some(_) => {
            let mut out = Plane::filled(w, h, off);
            for (y, row) in out.data.chunks_exact_mut(w.max(1)).enumerate() {
                crate::image::for_needed(row, crate::image::mask_row(need, y, w), |x, o| *o = f(x, y));
            }
            out
        }
    }
}

/// Whether any of the kernel operators keeps only part of the blocks.
fn any_partial(ops: &[KernelOperator]) -> bool {
    ops.iter().any(|o| o.kept_runs().is_some())
}

fn gain_plane(corr: &Corrections, w: usize, h: usize) -> Plane {
    Plane::from_fn(w, h, |x, y| corr.gain(x, y, w, h) as f32)
}

/// The scalar parameters of a Gauss–Newton step: `(channel, name)`, `usize::MAX` for the
/// shared ones (vignetting `k1..k3`, gradient `gx, gy`).
fn scalar_names(corr: &Corrections, nch: usize) -> Vec<(usize, &'static str)> {
    let mut names: Vec<(usize, &'static str)> = Vec::new();
    for c in 0..nch {
        names.push((c, "scale"));
        if corr.black_level.is_some() {
            names.push((c, "beta"));
        }
        if corr.veiling_glare.is_some() {
            names.push((c, "glare"));
        }
    }
    if corr.vignetting.is_some() {
        names.extend(["k1", "k2", "k3"].map(|n| (usize::MAX, n)));
    }
    if corr.illumination_gradient.is_some() {
        names.extend(["gx", "gy"].map(|n| (usize::MAX, n)));
    }
    names
}

/// The weighted normal equations `(JᵀWJ, JᵀW r)` of the scalar parameters `names` over the
/// fit mask (`J` their derivatives of the linear prediction, `W = 1/variance`).
fn scalar_normal_equations(corr: &Corrections, names: &[(usize, &'static str)], open_lin: &[Plane], variance_lin: &[Plane], fitmask: &[Vec<bool>], glare_planes: Option<&[Plane]>, st: &ScalarState) -> (Vec<Vec<f64>>, Vec<f64>) {
    let (w, h) = (open_lin[0].width, open_lin[0].height);
    let g = gain_plane(corr, w, h);
    let np = names.len();
    let mut ata = vec![vec![0.0f64; np]; np];
    let mut atb = vec![0.0f64; np];
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let hd2 = 0.25 * ((w * w + h * h) as f64);
    let (vig, grad) = (corr.vignetting, corr.illumination_gradient);
    let mut row = vec![0.0f64; np];
    for c in 0..open_lin.len() {
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !fitmask[c][i] {
                    continue;
                }
                let lp = glare_planes.map_or(0.0, |gp| gp[c].data[i] as f64);
                let a = st.a_parts[c].data[i] as f64;
                let b = a + st.glare_amp[c] * lp;
                let gg = g.data[i] as f64;
                let res = open_lin[c].data[i] as f64 - (gg * b + st.beta[c]);
                let wt = 1.0 / variance_lin[c].data[i] as f64;
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let r2 = (dx * dx + dy * dy) / hd2;
                let (xn, yn) = (dx / cx.max(0.5), dy / cy.max(0.5));
                let vv = vig.map_or(1.0, |v| 1.0 + v.k1 * r2 + v.k2 * r2 * r2 + v.k3 * r2 * r2 * r2);
                let dd = grad.map_or(1.0, |d| 1.0 + d.gx * xn + d.gy * yn);
                for (j, (ch, n)) in names.iter().enumerate() {
                    row[j] = if *ch != usize::MAX && *ch != c {
                        0.0
                    } else {
                        match *n {
                            "scale" => gg * a,
                            "beta" => 1.0,
                            "glare" => gg * lp,
                            "k1" => b * dd * r2,
                            "k2" => b * dd * r2 * r2,
                            "k3" => b * dd * r2 * r2 * r2,
                            "gx" => b * vv * xn,
                            "gy" => b * vv * yn,
                            _ => 0.0,
                        }
                    };
                }
                for j in 0..np {
                    if row[j] == 0.0 {
                        continue;
                    }
                    atb[j] += wt * row[j] * res;
                    for l in j..np {
                        ata[j][l] += wt * row[j] * row[l];
                    }
                }
            }
        }
    }
    for j in 0..np {
        for l in 0..j {
            ata[j][l] = ata[l][j];
        }
    }
    (ata, atb)
}

/// One Gauss–Newton step on the scalar parameters (see [`scalar_names`]), applied to `corr`
/// and `st`; `false` when the normal equations are singular (nothing changes).
fn gauss_newton_step(corr: &mut Corrections, open_lin: &[Plane], variance_lin: &[Plane], fitmask: &[Vec<bool>], glare_planes: Option<&[Plane]>, st: &mut ScalarState) -> bool {
    let names = scalar_names(corr, open_lin.len());
    let (ata, atb) = scalar_normal_equations(corr, &names, open_lin, variance_lin, fitmask, glare_planes, st);
    let Some(delta) = crate::solve::dense::solve(ata, atb, 1e-300) else { return false };
    for (j, (ch, n)) in names.iter().enumerate() {
        let d = delta[j];
        match *n {
            "scale" => {
                let f = (1.0 + d) as f32;
                st.u[*ch].iter_mut().for_each(|kk| kk.scale(f));
                st.a_parts[*ch].scale(f);
            }
            "beta" => st.beta[*ch] += d,
            "glare" => st.glare_amp[*ch] = (st.glare_amp[*ch] + d).max(0.0),
            "k1" | "k2" | "k3" => {
                if let Some(v) = corr.vignetting.as_mut() {
                    match *n {
                        "k1" => v.k1 += d,
                        "k2" => v.k2 += d,
                        _ => v.k3 += d,
                    }
                }
            }
            "gx" => {
                if let Some(v) = corr.illumination_gradient.as_mut() {
                    v.gx += d;
                }
            }
            "gy" => {
                if let Some(v) = corr.illumination_gradient.as_mut() {
                    v.gy += d;
                }
            }
            _ => {}
        }
    }
    true
}

/// One channel's figures on the stored axis (see [`score_channel`]).
struct ChannelScore {
    predicted: Plane,
    normalized: Plane,
    chi2: f64,
    n: usize,
    sq: f64,
    var_sum: f64,
    sq_unclipped: f64,
}

/// Encodes the linear prediction `mlin` (clipped at `clip`) and its variance `vl` onto the
/// stored axis and scores it against `open` on the `interior` pixels: the normalised residual,
/// `χ²`, the pixel count, `Σ d²`, `Σ variance` and `Σ d²` over the pixels scored as residuals
/// (not clipped in either capture). With `saturation = (clipped_open,
/// pin_clipped)`, a pixel clipped in the reference counts 1, one clipped in the open capture
/// counts only when the prediction is below the clip level.
#[allow(clippy::too_many_arguments)]
fn score_channel(mlin: &Plane, vl: &Plane, transfer: Transfer, clip: Option<f32>, interior: &[bool], open: &Plane, saturation: Option<(&[bool], &[bool])>, need: Option<&[bool]>) -> ChannelScore {
    let (w, h) = (mlin.width, mlin.height);
    let mut pred = Plane::new(w, h);
    let mut norm = Plane::new(w, h);
    let (mut chi2, mut n, mut sq, mut vs, mut squ) = (0.0f64, 0usize, 0.0f64, 0.0f64, 0.0f64);
    for i in 0..w * h {
        if need.is_some_and(|nd| !nd[i]) {
            continue;
        }
        let m = mlin.data[i];
        let mut e = transfer.encode(m);
        if let Some(l) = clip {
            e = e.min(l);
        }
        pred.data[i] = e;
        let slope = match transfer {
            Transfer::Linear => 1.0,
            Transfer::Srgb => srgb_slope(m.max(1e-4)),
        };
        let v = vl.data[i] * slope * slope;
        if !interior[i] {
            continue;
        }
        let d = open.data[i] - e;
        let contrib = match saturation {
            Some((_, pin)) if pin[i] => 1.0,
            Some((clipped, _)) if clipped[i] => {
                if e >= CLIP {
                    0.0
                } else {
                    ((CLIP - e) as f64).powi(2) / v as f64
                }
            }
            _ => {
                let d2 = (d as f64).powi(2);
                squ += d2;
                d2 / v as f64
            }
        };
        norm.data[i] = if contrib == 0.0 { 0.0 } else { (contrib.sqrt() as f32).copysign(d) };
        chi2 += contrib;
        sq += (d as f64).powi(2);
        vs += v as f64;
        n += 1;
    }
    ChannelScore { predicted: pred, normalized: norm, chi2, n, sq, var_sum: vs, sq_unclipped: squ }
}

/// Fits `corrections` (their parameter values are starting points) to `data`, starting from
/// `init`'s kernels and exposure ratios.
pub fn fit(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings) -> Fit {
    fit_on(data, corrections, init, settings, &|_, _| true, data.fit_pixels, false, None)
}

/// [`fit`] continuing the kernel solver's state `warm` (a previous fit's [`Fit::warm`], of the
/// fit whose model `init` is) instead of starting every channel's FISTA afresh.
pub fn fit_from(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings, warm: &Warm) -> Fit {
    fit_on(data, corrections, init, settings, &|_, _| true, data.fit_pixels, false, Some(warm))
}

/// [`fit`] with the data term restricted to pixels where `keep(x, y)` and, as in
/// [`fit_subset`], to a spread subset of about `data_pixels` pixels (for cross-validation;
/// the figures still cover the whole evaluation set).
///
/// Stages: `Setup::new` (linear data and reference on the model's geometry, masks, kernel
/// operators), `Setup::initial_params`, `settings.rounds` × `Setup::round` (kernels, then
/// Gauss–Newton on the scalars), `Setup::final_model` and `Setup::figures`.
pub fn fit_masked(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings, keep: &dyn Fn(usize, usize) -> bool, data_pixels: usize) -> Fit {
    fit_on(data, corrections, init, settings, keep, data_pixels, false, None)
}

/// [`fit`] with the data term on a spread subset of about `data_pixels` pixels (every n-th
/// block of the kernel operator in a staggered pattern, denser where that would leave a tile
/// without data, [`KernelOperator::covering`]): the
/// screening fit of the effect search. The figures (χ², residual maps) cover only the subset's
/// evaluation pixels (no whole-image operator is built); [`Fit::chi2`] and [`Fit::n`] scale
/// them to the whole evaluation set ([`Fit::share`]). Fits with the same grid keep the same
/// blocks, so a round's null refit and candidates are scored on the same pixels.
pub fn fit_subset(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings, data_pixels: usize) -> Fit {
    fit_on(data, corrections, init, settings, &|_, _| true, data_pixels, true, None)
}

/// [`fit_subset`] continuing the kernel solver's state `warm` ([`fit_from`]).
pub fn fit_subset_from(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings, data_pixels: usize, warm: &Warm) -> Fit {
    fit_on(data, corrections, init, settings, &|_, _| true, data_pixels, true, Some(warm))
}

/// [`fit_subset`] on [`Data::screen_pixels`]: the quick fits with which a candidate's
/// parameters are searched (glare width, similarity, keystone, Airy radius) and backward
/// elimination's refits. Every pixel when the capture has no more than that per channel.
pub fn screen(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings) -> Fit {
    fit_on(data, corrections, init, settings, &|_, _| true, data.screen_pixels, true, None)
}

/// The colour (0 or 1) of pixel `(x, y)` on the 16-px checkerboard that splits fitted from
/// held-out pixels ([`held_out_sq`], [`held_out_chi2`]: the ε ladder, the diagnosis's
/// cross-validation, the decision on a finer kernel grid).
pub fn checker(x: usize, y: usize) -> usize {
    ((x / 16) + (y / 16)) % 2
}

/// χ² (`Σ z²`, [`Fit::normalized`]) of each of `fits` on the checkerboard's colour `colour`
/// ([`checker`]) where every one of them evaluates, and that pixel count: the held-out χ² of
/// fits whose data term was the other colour ([`fit_masked`]; the diagnosis's
/// cross-validation and the decision on a finer kernel grid).
pub fn held_out_chi2<const M: usize>(fits: [&Fit; M], colour: usize) -> ([f64; M], f64) {
    let (mut chi2, mut n) = ([0.0; M], 0.0);
    let nch = fits.iter().map(|f| f.normalized.len()).min().unwrap_or(0);
    for c in 0..nch {
        let w = fits[0].normalized[c].width;
        let len = fits.iter().map(|f| f.normalized[c].data.len()).min().unwrap_or(0);
        for i in (0..len).filter(|&i| checker(i % w, i / w) == colour && fits.iter().all(|f| f.eval[c][i])) {
            for (s, f) in chi2.iter_mut().zip(&fits) {
                *s += (f.normalized[c].data[i] as f64).powi(2);
            }
            n += 1.0;
        }
    }
    (chi2, n)
}

/// The prediction's held-out error: `corrections` fitted from `init` with budget `settings` on
/// [`screen`]'s subset, its data term on the checkerboard's colour 0 ([`checker`]), and per
/// channel `Σ (stored − predicted)²` over the subset's scored pixels of colour 1 that are not
/// clipped in the wide-open capture. Unlike the fitted pixels' squared residual, it does not
/// reward a more flexible model for fitting the wide-open capture's noise.
pub fn held_out_sq(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings) -> Vec<f64> {
    let f = fit_on(data, corrections, init, settings, &|x, y| checker(x, y) == 0, data.screen_pixels, true, None);
    (0..f.predicted.len())
        .map(|c| {
            let (pred, open, eval) = (&f.predicted[c], &data.open.planes[c], &f.eval[c]);
            let w = pred.width;
            (0..pred.data.len()).filter(|&i| eval[i] && checker(i % w, i / w) == 1 && open.data[i] < CLIP).map(|i| ((open.data[i] - pred.data[i]) as f64).powi(2)).sum()
        })
        .collect()
}

/// A whole-pixel fit whose round count is set by a convergence rule instead of a count
/// ([`fit_converging`]): at most `max_rounds` rounds of `kernel_iterations` each (the
/// momentum carried between them), stopped after the first round that lowers χ² by no more
/// than `tolerance` (χ² units; `τ·√(2N)` compares the fall with χ²'s own noise).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Convergence {
    pub kernel_iterations: usize,
    pub max_rounds: usize,
    pub tolerance: f64,
}

/// [`fit`] on every pixel with rounds run while they still lower χ² ([`Convergence`]).
/// Returns the fit and χ² before the first round and after each round run (every pixel of the
/// evaluation set, the scalars refitted: the same χ² as [`Fit::chi2`] of a fit stopped there).
/// `warm`: a previous fit's solver state to continue ([`fit_from`]), or `None`.
pub fn fit_converging(data: &Data, corrections: &Corrections, init: &Model, rule: Convergence, warm: Option<&Warm>) -> (Fit, Vec<f64>) {
    let mut corr = corrections.clone();
    let mut setup = Setup::new(data, &corr, init, &|_, _| true, data.fit_pixels, true);
    if let Some(w) = warm {
        setup.continue_from(w);
    }
    let mut p = setup.initial_params(&corr, init);
    let kset = KernelFitSettings { iterations: rule.kernel_iterations, rounds: 1, step: KERNEL_STEP };
    // each evaluation's figures are kept: the last one's are the returned fit's (`finish`
    // does not score the same parameters again)
    let mut scored = setup.whole_figures(&corr, &p);
    let mut trace = vec![Setup::chi2_of(&scored)];
    for _round in 0..rule.max_rounds {
        // the last figures' χ² is in the trace: their planes go before the next are made
        drop(std::mem::take(&mut scored));
        setup.round(&mut corr, &mut p, kset);
        scored = setup.whole_figures(&corr, &p);
        let chi2 = Setup::chi2_of(&scored);
        let fall = trace[trace.len() - 1] - chi2;
        trace.push(chi2);
        if fall <= rule.tolerance {
            break;
        }
    }
    (finish_scored(data, setup, corr, p, false, Some(scored)), trace)
}

/// The channels whose Poisson–Gaussian law the noise curves cannot test ([`Fit::law_untested`]):
/// with curves from a model's residual, those whose lost detail (`lost_detail`, per channel,
/// [`Fit::lost_detail`]) is above [`LOST_DETAIL_LAW_BOUND`]; none with curves from repeated
/// frames, which no residual reaches.
pub fn law_untested(lost_detail: &[f64], curves_from_frames: bool) -> Vec<usize> {
    if curves_from_frames {
        return Vec::new();
    }
    (0..lost_detail.len()).filter(|&c| lost_detail[c] > LOST_DETAIL_LAW_BOUND).collect()
}

/// `subset_figures`: score only the kernel operators' kept blocks ([`fit_subset`]) instead of
/// every pixel.
#[allow(clippy::too_many_arguments)]
fn fit_on(data: &Data, corrections: &Corrections, init: &Model, settings: FitSettings, keep: &dyn Fn(usize, usize) -> bool, data_pixels: usize, subset_figures: bool, warm: Option<&Warm>) -> Fit {
    let mut corr = corrections.clone();
    let mut setup = Setup::new(data, &corr, init, keep, data_pixels, !subset_figures);
    if let Some(w) = warm {
        setup.continue_from(w);
    }
    let mut p = setup.initial_params(&corr, init);
    let kset = KernelFitSettings { iterations: settings.kernel_iterations, rounds: 1, step: KERNEL_STEP };
    for _round in 0..settings.rounds {
        setup.round(&mut corr, &mut p, kset);
    }
    finish(data, setup, corr, p, subset_figures)
}

/// The fitted parameters `p` into a [`Fit`]: the model, its figures and the noise law's fit.
fn finish(data: &Data, setup: Setup, corr: Corrections, p: Params, subset_figures: bool) -> Fit {
    finish_scored(data, setup, corr, p, subset_figures, None)
}

/// [`finish`] with the whole-pixel figures of `p` already computed ([`Setup::whole_figures`],
/// on the same `p`; the final model's normalisation does not change them), or `None`.
fn finish_scored(data: &Data, setup: Setup, mut corr: Corrections, mut p: Params, subset_figures: bool, scored: Option<Vec<ChannelFigures>>) -> Fit {
    let (grid, exposure) = setup.final_model(&mut corr, &p);
    let f = setup.figures(&corr, &mut p, subset_figures, scored);
    let (nch, k) = (setup.nch, setup.grid0.kernel_size);
    let laws: Vec<super::noise::PoissonGaussian> = data.curves.iter().enumerate().map(|(c, curve)| super::noise::PoissonGaussian::fit_pedestal(curve, setup.transfer, corr.black_offset(c))).collect();
    let law_untested = law_untested(&f.lost_detail, data.curves_from_frames);
    let kernel_params = nch * (grid.tile_count() * (k * k - 1) + 1);
    let params = kernel_params + correction_params(&corr, nch);
    Fit {
        model: Model { corrections: corr, grid, exposure },
        transfer: setup.transfer,
        predicted: Arc::new(f.predicted),
        normalized: Arc::new(f.normalized),
        eval: Arc::new(f.eval),
        chi2_channel: f.chi2_channel,
        n_channel: f.n_channel,
        sq_channel: f.sq_channel,
        var_channel: f.var_channel,
        sq_unclipped_channel: f.sq_unclipped_channel,
        params,
        kernel_dof: None,
        highpass_absorbed: None,
        kernel_params,
        noise_chi2: laws.iter().map(|l| l.chi2).sum(),
        noise_misfit: laws.iter().enumerate().filter(|(c, _)| !law_untested.contains(c)).map(|(_, l)| l.misfit).fold(0.0, f64::max),
        lost_detail: f.lost_detail,
        law_untested,
        reference: setup.reference,
        reference_highpass: Arc::new(f.reference_highpass),
        share: f.share,
        low_band_floor: f.low_band_floor,
        warm: Warm { channels: setup.warm.into_iter().map(|m| m.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner)).collect(), data_pixels: setup.data_pixels },
    }
}

/// The kernels' effective degrees of freedom in `fit` (docs/diagnosis.md, "Effective degrees of
/// freedom"): per channel, the Monte-Carlo divergence ([`kernel_divergence`]) of the kernel
/// solver run with `settings`' budget from the fitted kernels, on the fit's own target and
/// weights; summed over channels and clamped to `[0, nominal]`, with each channel's absorbed
/// high-pass fraction. Costs two kernel solves per channel. `seed` picks the probe.
///
/// `data_pixels`: the probe's data term keeps about this many pixels per channel, the spread
/// blocks of [`fit_subset`] (all of them below that size). The count `df` then stands for the
/// whole fit's, and the absorbed share `α_hp`, of the probe's pixels' noise, is scaled to every
/// pixel by [`KernelDof::share`] ([`Fit::set_dof`]). The subset's count is lower than the whole
/// image's (docs/diagnosis.md, "Speed at camera resolution"), but the reduced χ² barely moves:
/// with `α ≈ df/N`, `χ²/(N − df)` on a curve divided by `1 − α` is `≈ χ²_raw/N` whatever `df`.
pub fn measure_kernel_dof(data: &Data, fit: &Fit, settings: FitSettings, seed: u64, data_pixels: usize) -> KernelDof {
    let corr = fit.model.corrections.clone();
    let setup = Setup::new(data, &corr, &fit.model, &|_, _| true, data_pixels, false);
    let p = setup.initial_params(&corr, &fit.model);
    let g = gain_plane(&corr, setup.w, setup.h);
    let kset = KernelFitSettings { iterations: settings.kernel_iterations, rounds: settings.rounds.max(1), step: KERNEL_STEP };
    // the probes drawn in channel order from one generator, then the channels concurrently
    let mut rng = crate::rng::Rng::new(seed);
    let n = setup.w * setup.h;
    let probes: Vec<Vec<f32>> = (0..setup.nch).map(|_| rademacher(n, &mut rng)).collect();
    let divergences: Vec<Divergence> = {
        let (setup, g, p) = (&setup, &g, &p);
        probes
            .par_iter()
            .enumerate()
            .map(|(c, b)| {
                let var = setup.update_variance(c, &p.a_parts[c], &p.u[c], g, p.glare_amp[c], p.beta[c], setup.data_need(c));
                let (y, wt) = setup.kernel_target(c, g, p, &var);
                kernel_divergence_with(&setup.ops[c], &y, &wt, &p.u[c], kset, b)
            })
            .collect()
    };
    let mut df = 0.0;
    let mut highpass_absorbed = Vec::with_capacity(setup.nch);
    for d in &divergences {
        df += d.df;
        highpass_absorbed.push(d.highpass_absorbed);
    }
    let interior = &setup.masks.interior;
    let covered = setup.ops.first().map_or(&[][..], |o| o.covered());
    let kept = interior.iter().enumerate().filter(|&(i, &e)| e && covered.get(i).copied().unwrap_or(true)).count();
    let share = kept as f64 / interior.iter().filter(|&&b| b).count().max(1) as f64;
    KernelDof { df: df.clamp(0.0, fit.kernel_params as f64), highpass_absorbed, share }
}

/// What [`measure_kernel_dof`] measured.
#[derive(Clone, Debug)]
pub struct KernelDof {
    /// Effective kernel parameters, all channels.
    pub df: f64,
    /// Per channel, the absorbed share of the noise's high-pass on the probe's pixels; on every
    /// pixel it is `share` times this ([`Fit::set_dof`]).
    pub highpass_absorbed: Vec<f64>,
    /// The probe's pixels (the evaluation set within the kept blocks) over the evaluation
    /// set's (1 when the probe kept every pixel).
    pub share: f64,
}

impl Fit {
    /// Stores a [`measure_kernel_dof`] result: its count, and its absorbed share scaled to
    /// every pixel (`α_hp · share`: the absorbed energy is the same, the noise's is spread over
    /// `1/share` times as many pixels).
    pub fn set_dof(&mut self, d: KernelDof) {
        self.kernel_dof = Some(d.df);
        self.highpass_absorbed = Some(d.highpass_absorbed.iter().map(|a| (a * d.share).min(super::kernels::MAX_ABSORBED)).collect());
    }
}

/// The pixel sets of a fit: the evaluation set (a kernel radius inside the image), the clipped
/// wide-open pixels and clipped reference footprints per channel (under `saturation` only, the
/// one correction that reads them; empty otherwise), and the data term's pixels.
struct Masks {
    interior: Vec<bool>,
    clipped_open: Vec<Vec<bool>>,
    pin_clipped: Vec<Vec<bool>>,
    fitmask: Vec<Vec<bool>>,
    /// The model has a `saturation` correction.
    saturation: bool,
}

impl Masks {
    fn new(data: &Data, corr: &Corrections, registration: &RegistrationInfo, r: usize, keep: &dyn Fn(usize, usize) -> bool) -> Self {
        let (w, h) = (data.open.width(), data.open.height());
        let nch = data.open.channel_count();
        let saturation = corr.saturation.is_some();
        let interior: Vec<bool> = (0..w * h).map(|i| (i % w) >= r && (i % w) + r < w && (i / w) >= r && (i / w) + r < h).collect();
        let (clipped_open, pin_clipped): (Vec<Vec<bool>>, Vec<Vec<bool>>) = if saturation {
            let open = data.open.planes.par_iter().map(|p| p.data.iter().map(|&v| v >= CLIP).collect()).collect();
            let pin = data
                .pinhole
                .planes
                .par_iter()
                .map(|p| {
                    let m = Plane { width: w, height: h, data: p.data.iter().map(|&v| (v >= CLIP) as u8 as f32).collect() };
                    let reg = crate::estimate::register::apply(&m, registration);
                    dilate(&reg.data.iter().map(|&v| v > 0.0).collect::<Vec<_>>(), w, h, r)
                })
                .collect();
            (open, pin)
        } else {
            (vec![Vec::new(); nch], vec![Vec::new(); nch])
        };
        let fitmask: Vec<Vec<bool>> = (0..nch)
            .map(|c| (0..w * h).map(|i| interior[i] && keep(i % w, i / w) && (!saturation || (!clipped_open[c][i] && !pin_clipped[c][i]))).collect())
            .collect();
        Self { interior, clipped_open, pin_clipped, fitmask, saturation }
    }
}

/// The wide-open planes on the model's linear axis and, under `misregistration`, resampled onto
/// the reference geometry, with the interpolation's effect on their noise variance; the
/// resampling only at the `need` pixels (every pixel with `None`; 0 elsewhere).
fn linear_open(data: &Data, corr: &Corrections, transfer: Transfer, need: Option<&[bool]>) -> (Vec<Plane>, Option<Plane>) {
    let mut open_lin: Vec<Plane> = data.open.planes.par_iter().map(|p| p.map(|v| transfer.decode(v))).collect();
    // misregistration: the (band-limited) data onto the reference geometry, with the
    // interpolation's effect on its noise variance
    let mut noise_factor: Option<Plane> = None;
    // (and under `target_tilt`: [`super::model::reference_map`])
    if let Some(inv) = super::model::reference_map(corr).and_then(|m| m.inverse()) {
        let mut factor = None;
        open_lin = open_lin
            .iter()
            .map(|p| {
                let (q, f) = super::model::resample_map_where(p, &inv, need);
                factor = Some(f);
                q
            })
            .collect();
        noise_factor = factor;
    }
    (open_lin, noise_factor)
}

/// What a fit holds fixed while its parameters move.
struct Setup<'a> {
    data: &'a Data<'a>,
    transfer: Transfer,
    w: usize,
    h: usize,
    nch: usize,
    /// The registered linear reference planes (restored under `pinhole_diffraction`).
    reference: Arc<Vec<Plane>>,
    open_lin: Vec<Plane>,
    /// Under `misregistration`, the resampling's factor on the wide-open noise variance.
    noise_factor: Option<Plane>,
    /// The initial grid (regridded under `psf_field_variation`).
    grid0: PsfGrid,
    masks: Masks,
    /// Under `veiling_glare`, the reference blurred by the glare's Gaussian.
    glare_planes: Option<Vec<Plane>>,
    ops: Vec<KernelOperator>,
    diffraction: Option<super::model::DiffractionCorrection>,
    /// Per channel, the kernel step's norm estimate (and momentum), warm-started between rounds.
    warm: Vec<std::sync::Mutex<KernelWarm>>,
    /// The data term's pixel budget ([`Setup::new`]'s `data_pixels`).
    data_pixels: usize,
}

/// One channel's state after [`Setup::kernel_step`].
struct KernelStepResult {
    variance: Plane,
    u: Vec<Plane>,
    a_part: Plane,
    glare_amp: f64,
}

/// The free parameters of a fit while it runs (see the module doc's model).
struct Params {
    u: Vec<Vec<Plane>>,
    glare_amp: Vec<f64>,
    beta: Vec<f64>,
    /// Per channel, `Σ_t w_t·(U_t * P̃)`.
    a_parts: Vec<Plane>,
    /// Per channel, the linear-axis variance the last kernel step weighted with.
    variance_lin: Vec<Plane>,
}

/// One channel's figures on the stored axis.
struct ChannelFigures {
    score: ChannelScore,
    reference_highpass: Plane,
    /// [`Fit::lost_detail`] of the channel.
    lost_detail: f64,
}

/// All channels' figures on the stored axis.
#[derive(Default)]
struct Figures {
    predicted: Vec<Plane>,
    normalized: Vec<Plane>,
    eval: Vec<Vec<bool>>,
    chi2_channel: Vec<f64>,
    n_channel: Vec<usize>,
    sq_channel: Vec<f64>,
    var_channel: Vec<f64>,
    sq_unclipped_channel: Vec<f64>,
    reference_highpass: Vec<Plane>,
    lost_detail: Vec<f64>,
    /// The scored pixels over the evaluation set's ([`Fit::share`]).
    share: f64,
    low_band_floor: Vec<f64>,
}

impl<'a> Setup<'a> {
    /// `data_pixels`: the kernel operators keep about this many pixels (every n-th block,
    /// [`KernelOperator::covering`]: more where that share would leave a kernel without data);
    /// the data term is restricted to them.
    ///
    /// `whole_figures`: the fit's figures will score every pixel ([`Setup::figures`] without
    /// `subset_figures`); otherwise a partial operator's setup prepares the wide-open planes
    /// only on the kept blocks.
    fn new(data: &'a Data, corr: &Corrections, init: &Model, keep: &dyn Fn(usize, usize) -> bool, data_pixels: usize, whole_figures: bool) -> Self {
        let transfer = model_transfer(corr, data.open.transfer);
        let (w, h) = (data.open.width(), data.open.height());
        let nch = data.open.channel_count();
        let registration = corr.misregistration.clone().unwrap_or_else(|| data.base_registration.clone());
        let key = ReferenceKey { transfer, registration: registration.clone(), diffraction: corr.pinhole_diffraction.clone() };
        let reference = data.reference(key, || {
            let planes = reference_planes(data.pinhole, transfer, &registration);
            match &corr.pinhole_diffraction {
                Some(d) => planes.iter().enumerate().map(|(c, p)| d.restore(c, p)).collect(),
                None => planes,
            }
        });
        let grid0 = match corr.psf_field_variation {
            Some(f) if init.grid.centers != PsfGrid::edge_centers(w, h, f.columns, f.rows) => regrid(&init.grid, w, h, f.columns, f.rows),
            _ => init.grid.clone(),
        };
        let ops: Vec<KernelOperator> = reference.iter().map(|p| KernelOperator::covering(p, &grid0, data_pixels)).collect();
        let covered = ops.first().map(|o| o.covered().to_vec()).unwrap_or_default();
        // the data term reads the wide-open planes on the kept blocks only; the figures on
        // every pixel read the stored planes, but the resampling's noise factor everywhere
        let (open_lin, noise_factor) = linear_open(data, corr, transfer, (any_partial(&ops) && !whole_figures).then_some(&covered[..]));
        let kept = |x: usize, y: usize| keep(x, y) && covered.get(y * w + x).copied().unwrap_or(true);
        let masks = Masks::new(data, corr, &registration, grid0.kernel_size / 2, &kept);
        let glare_planes: Option<Vec<Plane>> = corr.veiling_glare.map(|g| reference.par_iter().map(|p| gaussian_blur_wide(p, g.sigma_px)).collect());
        let diffraction = corr.pinhole_diffraction.clone();
        let warm = (0..nch).map(|_| std::sync::Mutex::new(KernelWarm::default())).collect();
        Self { data, transfer, w, h, nch, reference, open_lin, noise_factor, grid0, masks, glare_planes, ops, diffraction, warm, data_pixels }
    }

    /// Starts every channel's kernel solver from `warm` ([`Warm`]): the momentum always (its
    /// length is checked by the solver), the norm's power vector only on the same pixel budget.
    fn continue_from(&mut self, warm: &Warm) {
        if warm.channels.len() != self.nch {
            return;
        }
        for (slot, w) in self.warm.iter_mut().zip(&warm.channels) {
            let mut w = w.clone();
            if warm.data_pixels != self.data_pixels {
                w.norm = super::kernels::StepNorm::new();
            }
            *slot = std::sync::Mutex::new(w);
        }
    }

    /// The starting parameters: the initial kernels scaled by the exposure (less the glare's
    /// share), the glare amplitude and the black-level offsets of `corr`.
    fn initial_params(&self, corr: &Corrections, init: &Model) -> Params {
        let u: Vec<Vec<Plane>> = (0..self.nch)
            .map(|c| {
                let f = corr.veiling_glare.map_or(0.0, |g| g.fraction);
                let s = init.exposure.get(c).copied().unwrap_or(1.0) * (1.0 - f);
                self.grid0.kernels[c].iter().map(|kk| kk.map(|v| v * s as f32)).collect()
            })
            .collect();
        let glare_amp: Vec<f64> = (0..self.nch).map(|c| corr.veiling_glare.map_or(0.0, |g| g.fraction * init.exposure.get(c).copied().unwrap_or(1.0))).collect();
        let beta: Vec<f64> = (0..self.nch).map(|c| corr.black_offset(c)).collect();
        let a_parts: Vec<Plane> = (0..self.nch).map(|c| self.blur_part(c, &u[c])).collect();
        Params { u, glare_amp, beta, a_parts, variance_lin: vec![Plane::new(self.w, self.h); self.nch] }
    }

    fn blur_part(&self, c: usize, u: &[Plane]) -> Plane {
        self.ops[c].apply_planes(u)
    }

    /// `Σ_t w_t(x)·ΣU_t²`, the gain of the pinhole's noise through the interpolated kernel
    /// (on the `need` pixels, [`plane_where`]).
    fn kernel_energy(&self, c: usize, u: &[Plane], need: Option<&[bool]>) -> Plane {
        let e: Vec<f32> = u
            .iter()
            .map(|kk| match &self.diffraction {
                Some(d) => {
                    let (psf, eps) = d.channel(c);
                    super::diffraction::noise_gain(kk, &psf, eps)
                }
                None => kk.data.iter().map(|v| v * v).sum::<f32>(),
            })
            .collect();
        self.grid0.blend_scalars_where(&e, self.w, self.h, need)
    }

    fn lin_var(&self, curve: &NoiseCurve, v: f32) -> f32 {
        curve.linear_variance(v, self.transfer).max(1e-12)
    }

    /// The linear-axis variance of channel `c`'s prediction: the wide-open noise at the model
    /// plus the pinhole's noise through the kernels; on the `need` pixels (1 elsewhere,
    /// [`plane_where`]).
    #[allow(clippy::too_many_arguments)]
    fn update_variance(&self, c: usize, a: &Plane, u: &[Plane], g: &Plane, glare_amp: f64, beta: f64, need: Option<&[bool]>) -> Plane {
        let (w, h) = (self.w, self.h);
        let data = self.data;
        let kq = self.kernel_energy(c, u, need);
        let s = u.iter().map(|kk| kk.sum()).sum::<f64>() / u.len().max(1) as f64;
        plane_where(w, h, need, 1.0, |x, y| {
            let i = y * w + x;
            let b = a.data[i] + glare_amp as f32 * self.glare_planes.as_ref().map_or(0.0, |gp| gp[c].data[i]);
            let m = g.data[i] * b + beta as f32;
            let level = (a.data[i] as f64 / s.max(1e-12)) as f32;
            let f = self.noise_factor.as_ref().map_or(1.0, |nf| nf.data[i]);
            f * self.lin_var(&data.curves[c], m) + g.data[i] * g.data[i] * kq.data[i] * data.pinhole_variance_scale as f32 * self.lin_var(&data.curves[c], level)
        })
    }

    /// One round: per channel the new weights and a kernel step (the channels' kernel problems
    /// are independent and run concurrently), then up to two Gauss–Newton steps on the scalar
    /// parameters (shared ones couple the channels).
    fn round(&self, corr: &mut Corrections, p: &mut Params, kset: KernelFitSettings) {
        let g = gain_plane(corr, self.w, self.h);
        let steps: Vec<KernelStepResult> = {
            let (corr, g, params) = (&*corr, &g, &*p);
            (0..self.nch).into_par_iter().map(|c| self.kernel_step(c, corr, g, params, kset)).collect()
        };
        for (c, r) in steps.into_iter().enumerate() {
            p.variance_lin[c] = r.variance;
            p.u[c] = r.u;
            p.a_parts[c] = r.a_part;
            p.glare_amp[c] = r.glare_amp;
        }
        for _ in 0..2 {
            let mut st = ScalarState { u: &mut p.u, a_parts: &mut p.a_parts, glare_amp: &mut p.glare_amp, beta: &mut p.beta };
            if !gauss_newton_step(corr, &self.open_lin, &p.variance_lin, &self.masks.fitmask, self.glare_planes.as_deref(), &mut st) {
                break;
            }
        }
    }

    /// Channel `c`'s kernel problem with the other parameters fixed: the target
    /// `y = (open − β)/G − g_c·(G_σ * P̃)` and the weights `G²/Var` (0 off the data mask), with
    /// `var` (linear axis) as the variance.
    fn kernel_target(&self, c: usize, g: &Plane, p: &Params, var: &Plane) -> (Plane, Vec<f32>) {
        let (w, h) = (self.w, self.h);
        let (glare_amp, beta) = (p.glare_amp[c], p.beta[c]);
        let y = plane_where(w, h, self.data_need(c), 0.0, |x, yy| {
            let i = yy * w + x;
            (self.open_lin[c].data[i] - beta as f32) / g.data[i] - glare_amp as f32 * self.glare_planes.as_ref().map_or(0.0, |gp| gp[c].data[i])
        });
        let fitmask = &self.masks.fitmask[c];
        let wt: Vec<f32> = (0..w * h).map(|i| if fitmask[i] { g.data[i] * g.data[i] / var.data[i] } else { 0.0 }).collect();
        (y, wt)
    }

    /// Channel `c`'s weights from the current prediction, then its kernels by projected FISTA
    /// with the scalar parameters fixed; reads only channel `c` of `p` and returns its new
    /// state (so that the channels can run concurrently).
    fn kernel_step(&self, c: usize, corr: &Corrections, g: &Plane, p: &Params, kset: KernelFitSettings) -> KernelStepResult {
        let variance = self.update_variance(c, &p.a_parts[c], &p.u[c], g, p.glare_amp[c], p.beta[c], self.data_need(c));
        let (y, wt) = self.kernel_target(c, g, p, &variance);
        let mut r = KernelStepResult { variance, u: p.u[c].clone(), a_part: p.a_parts[c].clone(), glare_amp: p.glare_amp[c] };
        if kset.iterations > 0 {
            let mut warm = self.warm[c].lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            let (nu, _s) = fit_kernels_warm(&self.ops[c], &y, &wt, &r.u, kset, &mut warm);
            r.u = nu;
            r.a_part = self.blur_part(c, &r.u);
        }
        // an additive smooth term takes the kernels' common floor (see
        // [`remove_common_floor`]); the glare amplitude starts from its mass, the offset is
        // refitted by the Gauss–Newton step (linear in β and the sums)
        if corr.veiling_glare.is_some() || corr.black_level.is_some() {
            let moved = remove_common_floor(&mut r.u);
            if moved > 0.0 {
                if corr.veiling_glare.is_some() {
                    r.glare_amp += moved;
                }
                r.a_part = self.blur_part(c, &r.u);
            }
        }
        r
    }

    /// The final parameters into the model: kernels normalised to sum 1, the exposure per
    /// channel, and the fitted glare fraction, offsets and grid into `corr`.
    fn final_model(&self, corr: &mut Corrections, p: &Params) -> (PsfGrid, Vec<f64>) {
        let nch = self.nch;
        let mut kernels = Vec::with_capacity(nch);
        let mut exposure = Vec::with_capacity(nch);
        let mut fractions = Vec::new();
        for c in 0..nch {
            let s_k = p.u[c].iter().map(|kk| kk.sum()).sum::<f64>() / p.u[c].len().max(1) as f64;
            kernels.push(p.u[c].iter().map(|kk| kk.map(|v| (v as f64 / s_k.max(1e-30)) as f32)).collect::<Vec<_>>());
            exposure.push(s_k + p.glare_amp[c]);
            fractions.push(p.glare_amp[c] / (s_k + p.glare_amp[c]).max(1e-30));
        }
        if let Some(gc) = corr.veiling_glare.as_mut() {
            *gc = GlareCorrection { fraction: fractions.iter().sum::<f64>() / nch as f64, sigma_px: gc.sigma_px };
        }
        if let Some(b) = corr.black_level.as_mut() {
            b.offset = p.beta.clone();
        }
        if let Some(f) = corr.psf_field_variation.as_mut() {
            f.columns = self.grid0.columns;
            f.rows = self.grid0.rows;
        }
        (PsfGrid { kernels, ..self.grid0.clone() }, exposure)
    }

    /// Channel `c`'s expected power of the normalised residual in the lowest band, relative to
    /// white noise's ([`Fit::low_band_floor`]): per pixel `1 + (V_low − V_ref)/Var`, with
    /// `V_ref = G²·(Σ_t w_t ΣU_t²)·Var_pinhole` the reference noise's variance (as in
    /// [`Setup::update_variance`]) and `V_low` the same with each kernel's mean `|Û_t(f)|²` over
    /// the band ([`super::analysis::band_gain`]; a restoration under `pinhole_diffraction` is
    /// ≈ 1 there); averaged over `scored`.
    fn low_band_floor(&self, c: usize, p: &Params, g: &Plane, scored: &[bool]) -> f64 {
        let (w, h, data) = (self.w, self.h, self.data);
        let u = &p.u[c];
        let bins = super::analysis::low_band_bins(w, h);
        let low: Vec<f32> = u.iter().map(|k| super::analysis::band_gain(k, &bins) as f32).collect();
        let lowq = self.grid0.blend_scalars(&low, w, h);
        let kq = self.kernel_energy(c, u, None);
        let vl = self.update_variance(c, &p.a_parts[c], u, g, p.glare_amp[c], p.beta[c], None);
        let s = u.iter().map(|kk| kk.sum()).sum::<f64>() / u.len().max(1) as f64;
        let (mut sum, mut n) = (0.0f64, 0usize);
        for i in (0..w * h).filter(|&i| scored[i]) {
            let level = (p.a_parts[c].data[i] as f64 / s.max(1e-12)) as f32;
            let vp = (g.data[i] * g.data[i]) as f64 * data.pinhole_variance_scale * self.lin_var(&data.curves[c], level) as f64;
            sum += 1.0 + vp * (lowq.data[i] as f64 - kq.data[i] as f64) / vl.data[i].max(1e-30) as f64;
            n += 1;
        }
        if n == 0 { 1.0 } else { sum / n as f64 }
    }

    /// The evaluation pixels inside the kernel operators' kept blocks, on the wide-open
    /// geometry: under a reference map (`misregistration`, `target_tilt`) the kept set less
    /// [`SCORED_MARGIN`] px is carried through the map, and a pixel counts only where every
    /// interpolation tap falls inside it.
    fn scored_mask(&self, corr: &Corrections) -> Vec<bool> {
        let covered = self.ops.first().map_or(&[][..], |o| o.covered());
        let inside: Vec<bool> = match super::model::reference_map(corr) {
            None => covered.to_vec(),
            Some(m) => {
                let outside: Vec<bool> = covered.iter().map(|&c| !c).collect();
                let near = dilate(&outside, self.w, self.h, SCORED_MARGIN);
                let safe = Plane { width: self.w, height: self.h, data: near.iter().map(|&n| if n { 0.0 } else { 1.0 }).collect() };
                // only where the map's source pixel is kept: elsewhere every tap (within 4 px
                // of it) lies in the margin, where `safe` is 0
                let (w, h) = (self.w, self.h);
                let candidate: Vec<bool> = (0..w * h)
                    .map(|i| {
                        let (sx, sy) = m.source(i % w, i / w, w, h);
                        let (x, y) = (sx.round(), sy.round());
                        self.masks.interior[i] && x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h && covered[y as usize * w + x as usize]
                    })
                    .collect();
                super::model::resample_map_where(&safe, &m, Some(&candidate)).0.data.iter().map(|&v| v > 0.999).collect()
            }
        };
        self.masks.interior.iter().zip(&inside).map(|(&a, &b)| a && b).collect()
    }

    /// Every channel's figures on the stored axis (see [`Setup::channel_figures`]). When the
    /// kernel operators keep only some blocks: with `subset_figures`, on the kept blocks'
    /// evaluation pixels ([`Setup::scored_mask`]); otherwise on every pixel, the blur parts
    /// recomputed with whole-image operators first.
    /// `scored`: every channel's [`Setup::channel_figures`] on the evaluation set, already
    /// computed for these parameters (a whole-pixel fit only), or `None`.
    fn figures(&self, corr: &Corrections, p: &mut Params, subset_figures: bool, scored_figures: Option<Vec<ChannelFigures>>) -> Figures {
        let partial = self.partial();
        // figures already scored on every pixel ([`Setup::whole_figures`]) stand
        let scored_figures = scored_figures.filter(|f| (!partial || !subset_figures) && f.len() == self.nch);
        if partial && !subset_figures {
            p.a_parts = self.whole_blur_parts(p);
        }
        let scored = if partial && subset_figures { self.scored_mask(corr) } else { self.masks.interior.clone() };
        // a subset's figures need the kept blocks' pixels only (the scored set lies inside
        // them, with the interpolation taps of a reference map)
        let need = (partial && subset_figures).then(|| self.ops[0].covered());
        let count = |m: &[bool]| m.iter().filter(|&&b| b).count();
        let g = gain_plane(corr, self.w, self.h);
        let mut f = Figures { share: count(&scored) as f64 / count(&self.masks.interior).max(1) as f64, ..Default::default() };
        if f.share <= 0.0 {
            f.share = 1.0;
        }
        let per_channel: Vec<(Option<f64>, ChannelFigures)> = {
            let (p, g, scored) = (&*p, &g, &scored);
            match scored_figures {
                Some(done) => done.into_par_iter().enumerate().map(|(c, cf)| ((!subset_figures).then(|| self.low_band_floor(c, p, g, scored)), cf)).collect(),
                None => (0..self.nch)
                    .into_par_iter()
                    .map(|c| ((!subset_figures).then(|| self.low_band_floor(c, p, g, scored)), self.channel_figures(c, corr, p, &p.a_parts[c], g, scored, need)))
                    .collect(),
            }
        };
        for (low, cf) in per_channel {
            if let Some(l) = low {
                f.low_band_floor.push(l);
            }
            let sc = cf.score;
            f.reference_highpass.push(cf.reference_highpass);
            f.lost_detail.push(cf.lost_detail);
            f.predicted.push(sc.predicted);
            f.normalized.push(sc.normalized);
            f.eval.push(scored.clone());
            f.chi2_channel.push(sc.chi2);
            f.n_channel.push(sc.n);
            f.sq_channel.push(sc.sq);
            f.var_channel.push(sc.var_sum);
            f.sq_unclipped_channel.push(sc.sq_unclipped);
        }
        f
    }

    /// Every channel's figures of the parameters `p` on every pixel of the evaluation set (the
    /// operators cover every pixel: a whole-pixel fit).
    fn whole_figures(&self, corr: &Corrections, p: &Params) -> Vec<ChannelFigures> {
        let g = gain_plane(corr, self.w, self.h);
        let scored = &self.masks.interior;
        // the blur parts on every pixel: a partial operator is zero off its kept blocks
        let whole = self.partial().then(|| self.whole_blur_parts(p));
        let parts = whole.as_ref().unwrap_or(&p.a_parts);
        (0..self.nch).into_par_iter().map(|c| self.channel_figures(c, corr, p, &parts[c], &g, scored, None)).collect()
    }

    /// Whether the kernel operators keep only part of the blocks ([`KernelOperator::covered`]).
    fn partial(&self) -> bool {
        any_partial(&self.ops)
    }

    /// The pixels channel `c`'s data term needs (its data mask, [`Masks::fitmask`]) when the
    /// operators keep part of the blocks; `None` (every pixel) when they keep all.
    fn data_need(&self, c: usize) -> Option<&[bool]> {
        self.partial().then(|| &self.masks.fitmask[c][..])
    }

    /// Per channel, `Σ_t w_t·(U_t * P̃)` on every pixel (a whole-image operator each).
    fn whole_blur_parts(&self, p: &Params) -> Vec<Plane> {
        (0..self.nch).into_par_iter().map(|c| KernelOperator::new(&self.reference[c], &self.grid0, usize::MAX).apply_planes(&p.u[c])).collect()
    }

    /// χ² of [`Setup::whole_figures`] (the channels' sum, in the order the evaluation used
    /// before the figures were kept).
    fn chi2_of(figures: &[ChannelFigures]) -> f64 {
        figures.par_iter().map(|f| f.score.chi2).sum()
    }

    /// Channel `c`'s prediction, variance and χ² on the stored axis (back on the wide-open
    /// geometry under `misregistration`), and the reference noise's share of the residual's
    /// high-pass. `a`: the channel's blur part `Σ_t w_t·(U_t * P̃)` on every scored pixel.
    /// `need`: the pixels to compute on (every pixel with `None`); the prediction and variance
    /// are 0 and 1 elsewhere, and `scored` must lie inside `need` (with a reference map's taps).
    #[allow(clippy::too_many_arguments)]
    fn channel_figures(&self, c: usize, corr: &Corrections, p: &Params, a: &Plane, g: &Plane, scored: &[bool], need: Option<&[bool]>) -> ChannelFigures {
        let (w, h) = (self.w, self.h);
        let data = self.data;
        let clip = corr.saturation.map(|s| s.clip_level);
        let back = super::model::reference_map(corr);
        let (u, glare_amp, beta) = (&p.u[c], p.glare_amp[c], p.beta[c]);
        let mut vl = self.update_variance(c, a, u, g, glare_amp, beta, need);
        let mut mlin = plane_where(w, h, need, 0.0, |x, y| {
            let i = y * w + x;
            let lp = self.glare_planes.as_ref().map_or(0.0, |gp| gp[c].data[i]);
            g.data[i] * (a.data[i] + glare_amp as f32 * lp) + beta as f32
        });
        // the reference noise's share of the residual's high-pass, relative to the open noise,
        // and the share of the detail a restoration gives up
        let (mut hp, mut lost) = {
            let (psf, eps) = self.diffraction.as_ref().map(|d| d.channel(c)).unzip();
            let (e, l): (Vec<f32>, Vec<f32>) = u.iter().map(|kk| super::diffraction::propagated_energies(kk, psf.as_ref().zip(eps), true)).unzip();
            let eq = self.grid0.blend_scalars_where(&e, w, h, need);
            let s = u.iter().map(|kk| kk.sum()).sum::<f64>() / u.len().max(1) as f64;
            let hp = plane_where(w, h, need, 0.0, |x, y| {
                let i = y * w + x;
                let level = (a.data[i] as f64 / s.max(1e-12)) as f32;
                g.data[i] * g.data[i] * eq.data[i] * data.pinhole_variance_scale as f32 * self.lin_var(&data.curves[c], level) / self.lin_var(&data.curves[c], mlin.data[i])
            });
            // the lost detail's share is the noise's times the tile's ratio of the two energies
            let lost = self.diffraction.is_some().then(|| {
                let ratio: Vec<f32> = e.iter().zip(&l).map(|(e, l)| l / e.max(1e-30)).collect();
                let rq = self.grid0.blend_scalars_where(&ratio, w, h, need);
                plane_where(w, h, need, 0.0, |x, y| hp.data[y * w + x] * rq.data[y * w + x])
            });
            (hp, lost)
        };
        // on the wide-open geometry a subset needs its scored pixels (a reference map's taps
        // from them lie inside `need`, [`Setup::scored_mask`]); without a map they lie in `need`
        let out_need = if back.is_some() { need.map(|_| scored) } else { need };
        if let Some(m) = back {
            // onto the wide-open geometry; the open's own noise there is unscaled
            if let Some(nf) = &self.noise_factor {
                vl = plane_where(w, h, need, 1.0, |x, y| {
                    let i = y * w + x;
                    let o = self.lin_var(&data.curves[c], mlin.data[i]);
                    vl.data[i] - nf.data[i] * o + o
                });
            }
            mlin = super::model::resample_map_where(&mlin, &m, out_need).0;
            vl = super::model::resample_map_where(&vl, &m, out_need).0;
            hp = super::model::resample_map_where(&hp, &m, out_need).0;
            lost = lost.map(|l| super::model::resample_map_where(&l, &m, out_need).0);
        }
        // its mean over the scored pixels (0 where it is not finite, as the report writes it)
        let lost_detail = lost.map_or(0.0, |l| {
            let (sum, n) = scored.iter().zip(&l.data).filter(|(&k, _)| k).fold((0.0f64, 0usize), |(s, n), (_, &v)| (s + v as f64, n + 1));
            Some(sum / n.max(1) as f64).filter(|v| v.is_finite()).unwrap_or(0.0)
        });
        let m = &self.masks;
        let sat = m.saturation.then_some((&m.clipped_open[c][..], &m.pin_clipped[c][..]));
        let score = score_channel(&mlin, &vl, self.transfer, clip, scored, &data.open.planes[c], sat, out_need);
        ChannelFigures { score, reference_highpass: hp, lost_detail }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// [`held_out_sq`] scores only pixels its fit did not see: moving the wide-open capture's
    /// checkerboard colour 1 by ±δ (the noise curves and registration held) leaves the fit as
    /// it is, so the mean of the two held-out sums exceeds the unmoved one by exactly δ² per
    /// scored pixel of colour 1 (a fit that saw them would follow part of the move, and fall
    /// short of it).
    #[test]
    fn the_held_out_error_scores_only_pixels_the_fit_did_not_see() {
        let spec = super::super::proof::CaseSpec::default();
        let case = super::super::proof::render_case(None, 21, &spec).expect("renders");
        let eo = crate::estimate::EstimateOptions { saturation: f32::INFINITY, ..super::super::bench::proof_options(&spec).estimate };
        let est = crate::estimate::estimate(&case.open.image, &case.pinhole.image, &eo).expect("estimates");
        let init = Model { corrections: Corrections::default(), grid: est.profile.grid, exposure: est.profile.meta.exposure_ratio };
        let base = Data::new(&case.open.image, &case.pinhole.image, 1.0 / case.pinhole_frames as f64);
        let settings = FitSettings { rounds: 2, kernel_iterations: 30 };
        let held = |delta: f32| {
            let mut open = case.open.image.clone();
            for p in open.planes.iter_mut() {
                let w = p.width;
                p.data.iter_mut().enumerate().filter(|(i, _)| checker(i % w, i / w) == 1).for_each(|(_, v)| *v += delta);
            }
            let mut data = Data::new(&open, &case.pinhole.image, base.pinhole_variance_scale);
            (data.curves, data.base_registration) = (base.curves.clone(), base.base_registration.clone());
            held_out_sq(&data, &init.corrections, &init, settings)[0]
        };
        let (w, h, r) = (spec.width, spec.height, init.grid.kernel_size / 2);
        let open = &case.open.image.planes[0];
        let n1 = (r..h - r).flat_map(|y| (r..w - r).map(move |x| (x, y))).filter(|&(x, y)| checker(x, y) == 1 && open.get(x, y) + 0.01 < CLIP).count();
        let delta = 0.01f32;
        let (s0, up, down) = (held(0.0), held(delta), held(-delta));
        let excess = 0.5 * (up + down) - s0;
        let expected = n1 as f64 * (delta as f64).powi(2);
        assert!((excess / expected - 1.0).abs() < 1e-3, "excess {excess} against n₁δ² {expected} (n₁ {n1})");
        assert!(s0 > 0.0 && up != down);
    }

    /// [`score_channel`]'s squared residuals: `sq` over every interior pixel, `sq_unclipped`
    /// only over those χ² scores as residuals (none clipped in the reference, and none clipped
    /// in the open capture); without saturation masks the two agree.
    #[test]
    fn the_unclipped_squared_residual_leaves_out_the_clipped_pixels() {
        let (w, h) = (4, 1);
        let mlin = Plane::from_fn(w, h, |x, _| [0.2, 0.4, 0.6, 0.8][x]);
        let vl = Plane::filled(w, h, 1e-4);
        let open = Plane::from_fn(w, h, |x, _| [0.25, 0.3, 0.7, 1.0][x]);
        let interior = vec![true; w * h];
        let (clipped_open, pin_clipped) = (vec![false, false, false, true], vec![false, true, false, false]);
        let s = score_channel(&mlin, &vl, Transfer::Linear, None, &interior, &open, Some((&clipped_open, &pin_clipped)), None);
        let d2 = |i: usize| ((open.data[i] - mlin.data[i]) as f64).powi(2);
        assert!((s.sq - (0..4).map(d2).sum::<f64>()).abs() < 1e-9, "{}", s.sq);
        assert!((s.sq_unclipped - (d2(0) + d2(2))).abs() < 1e-9, "{}", s.sq_unclipped);
        let plain = score_channel(&mlin, &vl, Transfer::Linear, None, &interior, &open, None, None);
        assert_eq!(plain.sq_unclipped.to_bits(), plain.sq.to_bits());
    }

    /// The law is not tested where a residual's curve holds the reference's lost detail: the
    /// shares of the 512×384 RGB `pinhole_diffraction` case (seed 71: red 22×, green 0.81×,
    /// blue 0.02× the wide-open noise) leave blue; curves from repeated frames test every
    /// channel; without a restoration (share 0) every channel is tested.
    #[test]
    fn the_law_is_not_tested_where_the_residual_holds_lost_detail() {
        let shares = [21.96, 0.81, 0.019];
        assert_eq!(law_untested(&shares, false), vec![0, 1]);
        assert!(law_untested(&shares, true).is_empty());
        assert!(law_untested(&[0.0, 0.0, 0.0], false).is_empty());
        assert_eq!(law_untested(&[LOST_DETAIL_LAW_BOUND, 1.01 * LOST_DETAIL_LAW_BOUND], false), vec![1]);
    }

    /// [`regrid`] projects the old kernel field onto the edge-anchored blend: a uniform field
    /// stays uniform; a field held constant in its outer half tiles (the estimate's 7 × 5 grid
    /// on the mock rig's 384×288 frame, 1-px "kernels" carrying a value that varies
    /// quadratically between centres) is followed on every pixel better than by the old
    /// kernels interpolated at the new centres (RMS 1.9e-2 against 3.4e-2).
    #[test]
    fn regrid_projects_the_kernel_field_onto_the_edge_layout() {
        let (w, h) = (384, 288);
        let field = |x: f64, y: f64| 1.0 + 1e-5 * ((x - 191.5).powi(2) + 2.0 * (y - 143.5).powi(2));
        let centers = PsfGrid::regular_centers(w, h, 7, 5);
        let kernels = vec![centers.iter().map(|&[x, y]| Plane::filled(1, 1, field(x, y) as f32)).collect()];
        let old = PsfGrid { kernel_size: 1, columns: 7, rows: 5, centers, channels: vec!["Y".into()], kernels };
        let new = regrid(&old, w, h, 7, 5);
        assert_eq!(new.centers, PsfGrid::edge_centers(w, h, 7, 5));
        let interpolated = resample(&old, new.centers.clone(), 7, 5);
        let misfit = |g: &PsfGrid| {
            let mut s = 0.0f64;
            for y in 0..h {
                for x in 0..w {
                    s += (g.kernel_at(0, x as f64, y as f64).data[0] as f64 - old.kernel_at(0, x as f64, y as f64).data[0] as f64).powi(2);
                }
            }
            (s / (w * h) as f64).sqrt()
        };
        let (projected, moved) = (misfit(&new), misfit(&interpolated));
        assert!(projected < 0.7 * moved, "projection {projected:.2e} vs interpolation {moved:.2e}");
        let flat = PsfGrid { kernels: vec![vec![Plane::filled(1, 1, 0.7); 35]], ..old.clone() };
        assert!(regrid(&flat, w, h, 13, 9).kernels[0].iter().all(|k| (k.data[0] - 0.7).abs() < 1e-5));
    }

    /// A small clean case (128×96, monochrome, 9-px kernels on 3×2 tiles) with its data and the
    /// model to start from: the rendered PSFs blurred (so that rounds still lower χ²).
    pub(crate) fn small_case() -> (Data<'static>, Model) {
        let spec = super::super::proof::CaseSpec { width: 128, height: 96, kernel_size: 9, ..Default::default() };
        let case = super::super::proof::render_case(None, 5, &spec).expect("a clean case renders");
        // the data borrow the captures for the test's whole run
        let case: &'static super::super::proof::Case = Box::leak(Box::new(case));
        let data = Data::new(&case.open.image, &case.pinhole.image, 1.0 / case.pinhole_frames as f64);
        let mut grid = case.open.psfs.clone().expect("rendered PSFs");
        for ks in grid.kernels.iter_mut() {
            for k in ks.iter_mut() {
                *k = Plane::filled(k.width, k.height, 1.0 / (k.width * k.height) as f32);
            }
        }
        let exposure = vec![1.0; data.open.channel_count()];
        (data, Model { corrections: Corrections::default(), grid, exposure })
    }

    /// Fits on one reference geometry share one copy of the reference planes (the cache of
    /// [`Data`]); another transfer builds its own, with other values; once no fit holds a
    /// geometry's planes they are built again, equal to the first.
    #[test]
    fn fits_on_one_reference_geometry_share_its_planes() {
        let (data, init) = small_case();
        let none = FitSettings { rounds: 0, kernel_iterations: 0 };
        let plain = Corrections::default();
        let (a, b) = (fit(&data, &plain, &init, none), fit(&data, &plain, &init, none));
        assert!(Arc::ptr_eq(&a.reference, &b.reference));
        let tone = Corrections { tone_curve: Some(super::super::model::ToneCorrection { transfer: Transfer::Srgb }), ..Corrections::default() };
        let t = fit(&data, &tone, &init, none);
        assert!(!Arc::ptr_eq(&a.reference, &t.reference));
        assert_ne!(a.reference[0].data, t.reference[0].data);
        let kept = a.reference[0].data.clone();
        drop((a, b));
        let again = fit(&data, &plain, &init, none);
        assert_eq!(again.reference[0].data, kept);
        assert!(data.reference_cache.lock().unwrap().len() <= 2, "dead entries are dropped");
    }

    /// A fit continued from another fit's solver state ([`fit_from`], [`Fit::warm`]) carries
    /// its momentum: one round after a two-round fit lands (nearly) where the three-round fit
    /// does, and nearer it than the same round started afresh from the two-round fit's model.
    #[test]
    fn a_fit_continued_from_a_fits_state_carries_its_momentum() {
        let (data, init) = small_case();
        let corr = Corrections::default();
        let s = |rounds| FitSettings { rounds, kernel_iterations: 20 };
        let two = fit(&data, &corr, &init, s(2));
        assert!(!two.warm.is_empty(), "a fit leaves its solver state");
        let three = fit(&data, &corr, &init, s(3)).chi2();
        let carried = fit_from(&data, &two.model.corrections, &two.model, s(1), &two.warm).chi2();
        let fresh = fit(&data, &two.model.corrections, &two.model, s(1)).chi2();
        eprintln!("χ²: two rounds {:.1}, three {three:.1}; a third as a new fit: carried {carried:.1}, fresh {fresh:.1}", two.chi2());
        assert!(carried < fresh, "carried {carried:.1} vs fresh {fresh:.1}");
        assert!((carried - three).abs() < 0.1 * (fresh - three), "carried {carried:.1}, fresh {fresh:.1}, three rounds {three:.1}");
        // a fit of no rounds leaves no momentum
        assert!(fit(&data, &corr, &init, s(0)).warm.is_empty());
    }

    /// A pixel cap on the whole-pixel fits ([`Data::fit_pixels`]): the data term keeps part of
    /// the blocks (the fitted χ² differs), but the figures still score every pixel of the
    /// evaluation set (the same count, share 1), a model scored without a round is the
    /// uncapped score, the converging fit's trace ends at its fit's χ², and on a third of the
    /// pixels the fit gains most of what the uncapped fit gains on every pixel.
    #[test]
    fn a_pixel_cap_fits_on_part_of_the_blocks_and_scores_every_pixel() {
        let (mut data, init) = small_case();
        let corr = Corrections::default();
        let s = |rounds| FitSettings { rounds, kernel_iterations: 20 };
        let (whole, whole0) = (fit(&data, &corr, &init, s(2)), fit(&data, &corr, &init, s(0)));
        data.fit_pixels = data.open.width() * data.open.height() / 3;
        let (capped, capped0) = (fit(&data, &corr, &init, s(2)), fit(&data, &corr, &init, s(0)));
        let kept = Setup::new(&data, &corr, &init, &|_, _| true, data.fit_pixels, true).ops[0].covered().iter().filter(|&&c| c).count() as f64 / (data.open.width() * data.open.height()) as f64;
        eprintln!("kept {:.1} % of the pixels; χ² whole {:.1}, capped {:.1}", 100.0 * kept, whole.chi2(), capped.chi2());
        assert!(kept < 0.6, "the cap keeps part of the blocks: {kept}");
        assert_eq!((capped.n(), capped.share), (whole.n(), 1.0));
        assert_ne!(capped.chi2(), whole.chi2(), "the capped data term fits other kernels");
        let gain = (whole0.chi2() - capped.chi2()) / (whole0.chi2() - whole.chi2());
        eprintln!("χ² from {:.1}: the capped fit gains {:.1} % of the whole fit's gain", whole0.chi2(), 100.0 * gain);
        assert!(gain > 0.8 && gain < 1.0, "capped {} whole {} start {}", capped.chi2(), whole.chi2(), whole0.chi2());
        assert!((capped0.chi2() / whole0.chi2() - 1.0).abs() < 1e-6, "no round: capped {} whole {}", capped0.chi2(), whole0.chi2());
        let rule = Convergence { kernel_iterations: 20, max_rounds: 2, tolerance: f64::NEG_INFINITY };
        let (conv, trace) = fit_converging(&data, &corr, &init, rule, None);
        assert!((trace[trace.len() - 1] - conv.chi2()).abs() <= 1e-9 * conv.chi2(), "trace {trace:?}, fit {}", conv.chi2());
        assert!((trace[0] / whole0.chi2() - 1.0).abs() < 1e-6, "the trace starts at the whole-pixel score: {} vs {}", trace[0], whole0.chi2());
    }

    /// A subset fit computes its data term and figures on the kept blocks only (the variance,
    /// target and prediction on them; under a reference map the resampling at the scored
    /// pixels, the wide-open planes on the kept blocks): its figures are the ones computed on
    /// every pixel, bit for bit, with and without a map, and the scored mask's shortcut (only
    /// pixels whose map source is kept) is the whole resampling's mask.
    #[test]
    fn subset_figures_on_the_kept_blocks_equal_the_whole_computation() {
        let (data, init) = small_case();
        let (w, h) = (data.open.width(), data.open.height());
        let rot = 2f64.to_radians();
        let info = RegistrationInfo { model: "similarity".into(), matrix: [rot.cos(), -rot.sin(), rot.sin(), rot.cos()], translation: [0.0, 0.0], residual_px: 0.0 };
        for corr in [Corrections::default(), Corrections { misregistration: Some(info), ..Corrections::default() }] {
            let mapped = corr.misregistration.is_some();
            let setup = Setup::new(&data, &corr, &init, &|_, _| true, w * h / 4, false);
            assert!(setup.partial(), "a quarter of the pixels keeps part of the blocks");
            let mut c = corr.clone();
            let mut p = setup.initial_params(&c, &init);
            setup.round(&mut c, &mut p, KernelFitSettings { iterations: 5, rounds: 1, step: KERNEL_STEP });
            // the same round on a setup that prepared the wide-open planes everywhere
            let everywhere = Setup::new(&data, &corr, &init, &|_, _| true, w * h / 4, true);
            let (mut c2, mut p2) = (corr.clone(), everywhere.initial_params(&corr, &init));
            everywhere.round(&mut c2, &mut p2, KernelFitSettings { iterations: 5, rounds: 1, step: KERNEL_STEP });
            let bits = |u: &[Vec<Plane>]| u.iter().flatten().flat_map(|k| k.data.iter().map(|v| v.to_bits())).collect::<Vec<u32>>();
            assert_eq!(bits(&p.u), bits(&p2.u), "mapped {mapped}: the round's kernels");
            let covered = setup.ops[0].covered();
            let scored = setup.scored_mask(&c);
            if let Some(m) = super::super::model::reference_map(&c) {
                let outside: Vec<bool> = covered.iter().map(|&b| !b).collect();
                let near = dilate(&outside, w, h, SCORED_MARGIN);
                let safe = Plane { width: w, height: h, data: near.iter().map(|&n| if n { 0.0 } else { 1.0 }).collect() };
                let whole: Vec<bool> = super::super::model::resample_map(&safe, &m).0.data.iter().zip(&setup.masks.interior).map(|(&v, &i)| i && v > 0.999).collect();
                assert_eq!(scored, whole, "the scored mask's shortcut");
            }
            let n_scored = scored.iter().filter(|&&b| b).count();
            assert!(n_scored > w * h / 50 && n_scored < w * h / 2, "mapped {mapped}: {n_scored} scored pixels");
            let g = gain_plane(&c, w, h);
            for ch in 0..setup.nch {
                let part = setup.channel_figures(ch, &c, &p, &p.a_parts[ch], &g, &scored, Some(covered));
                let all = setup.channel_figures(ch, &c, &p, &p.a_parts[ch], &g, &scored, None);
                let (a, b) = (&part.score, &all.score);
                assert!(a.n == n_scored && a.chi2 > 0.0, "mapped {mapped}: {} pixels, χ² {}", a.n, a.chi2);
                assert_eq!((a.chi2.to_bits(), a.n, a.sq.to_bits(), a.var_sum.to_bits()), (b.chi2.to_bits(), b.n, b.sq.to_bits(), b.var_sum.to_bits()), "mapped {mapped}, channel {ch}");
                for i in (0..w * h).filter(|&i| scored[i]) {
                    assert_eq!(a.predicted.data[i].to_bits(), b.predicted.data[i].to_bits(), "mapped {mapped}, pixel {i}");
                }
            }
        }
    }

    /// The convergence rule ([`fit_converging`]): its per-round χ² is the χ² of the fit it
    /// returns, with no tolerance it runs its cap and is then the fixed-count fit bit for bit
    /// (the momentum carried alike), and it stops after the first round whose fall is within
    /// the tolerance.
    #[test]
    fn converging_fit_stops_at_the_first_round_within_the_tolerance() {
        let (data, init) = small_case();
        let corr = Corrections::default();
        let rule = |max_rounds, tolerance| Convergence { kernel_iterations: 20, max_rounds, tolerance };
        let (all, trace) = fit_converging(&data, &corr, &init, rule(4, f64::NEG_INFINITY), None);
        assert_eq!(trace.len(), 5, "{trace:?}");
        assert!(trace.windows(2).all(|w| w[1] < w[0]), "χ² falls every round: {trace:?}");
        let counted = fit(&data, &corr, &init, FitSettings { rounds: 4, kernel_iterations: 20 });
        assert_eq!(all.chi2(), counted.chi2(), "a capped rule is the fixed count");
        assert!((trace[4] - all.chi2()).abs() <= 1e-9 * all.chi2(), "the trace's last χ² {} is the fit's {}", trace[4], all.chi2());
        // a tolerance between the falls of rounds 2 and 1 stops after round 2
        let falls: Vec<f64> = trace.windows(2).map(|w| w[0] - w[1]).collect();
        let tol = 0.5 * (falls[1] + falls[0]).min(2.0 * falls[1]);
        assert!(falls[1] <= tol && falls[0] > tol, "{falls:?}");
        let (two, t2) = fit_converging(&data, &corr, &init, rule(4, tol), None);
        assert_eq!(t2.len(), 3, "{t2:?}");
        assert_eq!(two.chi2(), fit(&data, &corr, &init, FitSettings { rounds: 2, kernel_iterations: 20 }).chi2());
        let (_, t1) = fit_converging(&data, &corr, &init, rule(4, f64::INFINITY), None);
        assert_eq!(t1.len(), 2, "one round when any fall is within the tolerance");
    }
}
