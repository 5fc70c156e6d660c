//! Model-mismatch diagnosis (`lensrig diagnose`): where the base model (tile-wise PSFs, sharp
//! pinhole reference, linear radiometry with one exposure ratio; docs/method.md §6) and the
//! recording disagree, which physics it left out (docs/method.md §7), the refit with that physics,
//! and the fit against the noise floor.
//!
//! # Pipeline
//! 1. [`noise`]: the sensor's noise curve from the wide-open capture alone.
//! 2. Base model: a profile (given, or estimated with [`crate::estimate`]), then every kernel
//!    refitted jointly in the forward model ([`kernels`], [`fit`]); its normalised residual is
//!    analysed ([`analysis`]).
//! 3. While the reduced χ² exceeds [`DiagnoseOptions::consistent`] (noise-model uncertainty
//!    included): every catalogue effect not yet in the model is added in turn and refitted
//!    from the current model ([`candidates`]); so is the current model itself with the same
//!    budget (the *null refit*, so extra iterations are never credited to physics). These
//!    screening fits keep about [`DiagnoseOptions::screen_pixels`] pixels per channel in their
//!    data term ([`fit::fit_subset`]); only the winner is refitted on every pixel. The effect
//!    with the lowest BIC (`χ² + p·ln N`) wins if it beats the null refit's BIC and removes at
//!    least [`DiagnoseOptions::min_gain`] of its χ²; a candidate that beats the BIC and removes
//!    between [`NEAR_MISS`]` · min_gain` and `min_gain` on the subset (a *near miss*: the
//!    subset's gain samples the whole image's with an error of its own) is refitted with the
//!    null refit on every pixel and judged by the same rule there (`screened`,
//!    `rescore_near_misses`). A parameter search runs only from a start
//!    that already lowers χ² ([`candidates::StartGate`]); where a geometric candidate's
//!    start (the current kernels moved by its map) does not, and the map moves a corner by a
//!    pixel or more (a quarter for a misregistration whose rotation is significant,
//!    [`candidates::registered_bound`]), its start is re-estimated under the map, pre-fitted,
//!    and proposed only if it beats the same start without the map ([`registered`], like for
//!    like); a search of many converged fits (`pinhole_diffraction`'s Airy radius, a
//!    misregistration's scale over re-estimated starts: [`candidates::Deferred`]) is deferred
//!    until its provisional candidate's screening shows it could decide the round
//!    (`in_contention`); a gated misregistration keeps its moved start where the search's
//!    re-estimated one screens no better. The polished winner is
//!    adopted only if it lowers the whole-pixel χ² by more than `3·√(2N)` (the stop rule of
//!    `adopt`). The winner's polish ends on every pixel. Where the subset thins the data, an
//!    adopted model that is not consistent with the noise is run to convergence on every pixel
//!    before the next round is decided (`converge_before_screening`): a right model short of
//!    iterations is not sent to screen for an effect it does not lack. The search's final model
//!    is polished again (the final polish) only where backward elimination changed it after the
//!    last adoption or where it is not yet consistent with the noise and not already converged
//!    (`needs_final_polish`); those whole-pixel rounds run while a round still lowers χ² by more
//!    than `3·√(2N)`, at most six (`final_polish_rule`).
//!
//!    A consistent fit whose kernels' centroids follow a rotation about the image centre
//!    ([`kernel_rotation`]: at least [`ROTATION_T`] standard errors and
//!    [`registered::MIN_ROTATION_CORNER_PX`], a quarter pixel, at the corners) has
//!    taken up a misregistration in its kernels, which no lens does: a round screens
//!    misregistration alone (`Round::Rotation`), and its winner is adopted where it fits as well
//!    (χ² not raised beyond `3·√(2N)` or `min_gain` of χ², `rotation_tolerance`) and leaves kernels that no longer rotate
//!    (`rotation_round_adopts`). Where the subset thins the data, the round's near miss goes to
//!    adoption (the full round's winner rule does not apply: χ² cannot prefer the map), and a
//!    winner refused on χ² alone with kernels that stopped rotating is converged on every pixel
//!    before the rule is asked again (`needs_rotation_convergence`). A rotation that remains is
//!    stated in the verdict.
//! 4. The final model's kernels and corrections form a profile ([`model`]); [`report`] writes
//!    `report.json`, the predictions, residual maps and `index.html`.
//!
//! # Conventions
//! χ² and RMS are on the stored axis of the wide-open file; the noise floor is the predicted
//! noise RMS (wide-open noise plus the pinhole's noise through the kernel).

pub mod analysis;
pub mod bench;
pub mod candidates;
pub mod diffraction;
pub mod fit;
pub mod kernels;
pub mod model;
pub mod noise;
pub mod proof;
pub mod prune;
pub mod registered;
pub mod report;
pub mod session;
pub mod simulate;
pub mod tilt;

use crate::estimate::{estimate, EstimateError, EstimateOptions};
use crate::image::Image;
use crate::profile::Profile;
use analysis::{analyse, Analysis};
use fit::{Data, Fit, FitSettings, Model};
use noise::{NoiseCurve, PoissonGaussian};
use serde::Serialize;

/// Why the diagnosis failed. Sizes in pixels.
#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("the images differ: wide-open is {}x{} with {} channel(s), pinhole {}x{} with {}", open[0], open[1], open[2], pinhole[0], pinhole[1], pinhole[2])]
    Mismatch { open: [usize; 3], pinhole: [usize; 3] },
    #[error("base estimate failed")]
    Estimate(#[from] EstimateError),
    /// `profile` and `images` are `[width, height, channels]`.
    #[error("the profile does not fit the images: profile is for {}x{} images with {} channel(s), the captures are {}x{} with {}", profile[0], profile[1], profile[2], images[0], images[1], images[2])]
    Profile { profile: [usize; 3], images: [usize; 3] },
    #[error(transparent)]
    Corrections(#[from] model::CorrectionError),
}

/// Settings of [`diagnose`].
#[derive(Clone, Debug)]
pub struct DiagnoseOptions {
    /// Used when no profile is given.
    pub estimate: EstimateOptions,
    /// Budget of the base fit.
    pub base_fit: FitSettings,
    /// Budget of each candidate's refit (and the null refit).
    pub candidate_fit: FitSettings,
    /// At most this many effects are added.
    pub max_effects: usize,
    /// A reduced χ² at or below this is consistent with noise: a residual RMS within 5 % of
    /// the measured floor. The slack covers the noise curve being measured, not known, and the
    /// budgeted kernel fit's own error: on clean proof data the base model ends 4–5 % above
    /// the true floor in RMS (reduced χ² 1.07–1.08 against a noise curve that no longer counts
    /// the reference's propagated noise as the wide-open capture's).
    pub consistent: f64,
    /// An effect must remove at least this fraction of the null refit's χ² on every pixel (a
    /// near miss on the screening subset, down to [`NEAR_MISS`] of it, is scored again on
    /// every pixel).
    pub min_gain: f64,
    /// The noise curve is consistent with a Poisson–Gaussian law when its RMS relative misfit
    /// is at most this.
    pub consistent_noise: f64,
    /// The reference's noise variance relative to the wide-open capture's at the same level:
    /// `frames averaged in the wide-open capture / frames averaged in the pinhole capture`.
    pub pinhole_variance_scale: f64,
    /// The wide-open capture's noise curve per channel measured from repeated frames (the
    /// variance of the *stored average*, i.e. one frame's temporal variance divided by the
    /// frames averaged). When given it is the noise model; otherwise the curve is measured
    /// from the residual of the base model ([`noise`]).
    pub repeat_noise: Option<Vec<NoiseCurve>>,
    /// Progress on stderr: the base estimate's bars, one bar per round over the candidates,
    /// and a line per added effect.
    pub progress: bool,
    /// Catalogue effects never proposed (e.g. `target_tilt`, to show the verdict on a tilted
    /// target before the catalogue modelled it).
    pub excluded: Vec<String>,
    /// The screening fits of the effect search (the null refit and every candidate) keep
    /// about this many pixels per channel in their data term: a spread of blocks over the
    /// field ([`fit::fit_subset`]). Only the winner is refitted on every pixel. Captures with
    /// fewer pixels are screened on all of them.
    pub screen_pixels: usize,
    /// The fits on every pixel (the base fit, the winner's whole-pixel round, the refits and
    /// rescores) keep about this many pixels per channel in their data term, a spread of
    /// blocks over the field as in the screening fits; their figures, residual and noise curve
    /// still cover every pixel. Captures with fewer pixels are fitted on all of them.
    pub fit_pixels: usize,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        Self {
            estimate: EstimateOptions { max_iterations: 150, joint_iterations: 0, ..Default::default() },
            base_fit: FitSettings { rounds: 3, kernel_iterations: 80 },
            candidate_fit: FitSettings { rounds: 2, kernel_iterations: 40 },
            max_effects: 4,
            consistent: 1.10,
            min_gain: 0.01,
            consistent_noise: 0.10,
            pinhole_variance_scale: 1.0,
            repeat_noise: None,
            progress: false,
            excluded: Vec::new(),
            screen_pixels: SCREEN_PIXELS,
            fit_pixels: FIT_PIXELS,
        }
    }
}

/// Default of [`DiagnoseOptions::fit_pixels`]: a 2000 × 1500 capture is fitted on every
/// pixel; a 4000 × 3000 one keeps one block in four (about 6 pixels per kernel value on its
/// grid, against 3.3 at 1024 × 768 on every pixel), so the kernel solves cost a quarter while
/// the unkept pixels' residual, out of sample, carries the kernels' error: about
/// `p_eff / N_fit` ≈ 0.6 % of the noise variance there (docs/diagnosis.md, "Speed at camera
/// resolution").
pub const FIT_PIXELS: usize = 3_000_000;

/// Default of [`DiagnoseOptions::screen_pixels`]: at 45-px kernels on a 7 × 5 grid, about
/// 2 pixels per kernel value, enough to rank candidates that all start from the current model.
pub const SCREEN_PIXELS: usize = 150_000;

/// Fit figures for the report.
#[derive(Clone, Debug, Serialize)]
pub struct Figures {
    pub reduced_chi2: f64,
    pub chi2: f64,
    pub pixels: usize,
    /// Nominal parameter count (BIC's penalty).
    pub parameters: usize,
    /// Effective parameter count the reduced χ² subtracts (docs/diagnosis.md).
    pub effective_parameters: f64,
    pub bic: f64,
    /// Residual RMS, stored axis.
    pub rms: f64,
    /// Predicted noise RMS (the floor), stored axis.
    pub noise_rms: f64,
    pub reduced_chi2_channel: Vec<f64>,
}

impl Figures {
    pub fn of(fit: &Fit) -> Figures {
        Figures {
            reduced_chi2: fit.reduced_chi2(),
            chi2: fit.chi2(),
            pixels: fit.n(),
            parameters: fit.params,
            effective_parameters: fit.effective_params(),
            bic: fit.bic(),
            rms: fit.rms(),
            noise_rms: fit.noise_rms(),
            reduced_chi2_channel: fit.reduced_chi2_channel(),
        }
    }
}

/// The noise model of one channel.
#[derive(Clone, Debug, Serialize)]
pub struct NoiseReport {
    pub channel: String,
    /// Poisson–Gaussian law on the final model's linear axis: `Var = a·L + b`.
    pub a: f64,
    pub b: f64,
    /// RMS relative misfit of the measured bins to the law.
    pub misfit: f64,
    /// The same law assuming linear data (differs from the above when a tone curve was found).
    pub a_linear: f64,
    pub b_linear: f64,
    pub misfit_linear: f64,
    /// Measured `(mean stored value, variance, pixels)` bins.
    pub curve: NoiseCurve,
    /// Noise floor of the final model (predicted noise RMS in this channel, stored axis).
    pub floor_rms: f64,
    /// Where the curve comes from: `"repeated frames"` (temporal variance over the averaged
    /// frames of a session) or `"residual"` (the base model's residual, one capture).
    pub source: &'static str,
    /// The detail a restored reference gives up, as a share of the wide-open noise in the
    /// residual's high-pass ([`fit::Fit::lost_detail`]; 0 without `pinhole_diffraction`).
    pub lost_detail: f64,
    /// Whether the verdict tests this channel's law: not where a curve from the residual
    /// holds more lost detail than [`fit::LOST_DETAIL_LAW_BOUND`].
    pub law_tested: bool,
}

/// One effect the diagnosis added.
#[derive(Clone, Debug, Serialize)]
pub struct FoundEffect {
    pub name: String,
    pub evidence: String,
    #[serde(rename = "where")]
    pub location: String,
    pub parameters: serde_json::Value,
    /// The model before the effect and with it, both scored with the noise curve measured
    /// after the effect was added (the last effect: the final model, after the final polish where
    /// one ran).
    pub before: Figures,
    pub after: Figures,
    /// BIC of the model with the effect minus the null refit's (a finer kernel grid's: minus
    /// the current model's, for information, since held-out pixels decide it,
    /// [`decide_growth`]); for an effect found again in a later round (`pinhole_diffraction`'s
    /// radius or `veiling_glare`'s width re-searched, `psf_field_variation` grown from its
    /// edge-anchored layout to a finer grid), summed over its adoptions.
    pub delta_bic: f64,
}

/// A candidate's score in one round.
#[derive(Clone, Debug, Serialize)]
pub struct CandidateScore {
    pub name: String,
    /// The candidate's fitted parameters.
    pub parameters: serde_json::Value,
    /// `None` where the candidate was not fitted: a new kernel layout, fitted on every pixel
    /// only, in a round another candidate won on the screening subset, or a finer grid, fitted
    /// only where it wins on held-out pixels ([`search_round`]).
    pub reduced_chi2: Option<f64>,
    /// ΔBIC against the null refit, on the pixels the candidate was scored on (`None` as
    /// `reduced_chi2`).
    pub delta_bic: Option<f64>,
    pub note: String,
}

impl CandidateScore {
    /// The reduced χ² (4 decimals) and ΔBIC (1 decimal) as printed, `–` where not fitted.
    pub fn figures(&self) -> [String; 2] {
        let show = |v: Option<f64>, digits: usize| v.map_or("–".to_string(), |v| format!("{v:.digits$}"));
        [show(self.reduced_chi2, 4), show(self.delta_bic, 1)]
    }
}

/// Everything the diagnosis found.
pub struct Diagnosis {
    pub noise: Vec<NoiseReport>,
    pub base: Fit,
    pub base_analysis: Analysis,
    pub final_fit: Fit,
    pub final_analysis: Analysis,
    pub effects: Vec<FoundEffect>,
    /// Per round, every candidate tried (the null refit first).
    pub rounds: Vec<Vec<CandidateScore>>,
    /// "no mismatch", "explained" or "unexplained: …".
    pub verdict: String,
    /// Held-out reduced χ² of the final model (fit on one colour of a checkerboard of blocks,
    /// evaluated on the other; `None` where neither colour holds an evaluated pixel) and the
    /// in-sample value.
    pub cross_validation: (Option<f64>, f64),
    /// The low-band test ([`low_band`]) of the base and the final model.
    pub low_band: [Option<LowBand>; 2],
    /// The corrected profile.
    pub profile: Profile,
    pub open: Image,
    /// Wall and CPU seconds per stage ([`crate::estimate::stage_clock`]): base estimate, base
    /// fit (with its degrees-of-freedom probe), effect search (rounds, polish, probes),
    /// cross-validation.
    pub stage_seconds: Vec<crate::estimate::StageTime>,
}

/// Diagnoses a wide-open / pinhole pair (as stored; `open.transfer` is the declared encoding)
/// against `profile`, or against a base profile estimated here when none is given (the module
/// docs give the stages).
///
/// # Errors
/// Size or channel mismatch, a profile for other images, or a failed base estimate.
pub fn diagnose(open: &Image, pinhole: &Image, profile: Option<&Profile>, opts: &DiagnoseOptions) -> Result<Diagnosis, DiagnoseError> {
    let dims = |i: &Image| [i.width(), i.height(), i.channel_count()];
    if dims(open) != dims(pinhole) {
        return Err(DiagnoseError::Mismatch { open: dims(open), pinhole: dims(pinhole) });
    }
    let (mut lap, mut stage_seconds) = (crate::estimate::stage_clock(), Vec::new());
    let base_profile = base_profile(open, pinhole, profile, opts)?;
    stage_seconds.push(lap("base estimate"));
    let (mut data, base, repeat_noise) = base_model(open, pinhole, &base_profile, opts);
    stage_seconds.push(lap("base fit"));
    let base_analysis = analyse(&base);
    if opts.progress {
        eprintln!("base model: reduced χ² {:.3} (noise floor {:.3e} RMS; {} pixels, {} parameters, {:.0} effective)", base.reduced_chi2(), base.noise_rms(), base.n(), base.params, base.effective_params());
    }
    progress_residual_checks(opts, "base", &base, &base_analysis);
    let search = add_effects(&mut data, base.clone(), base_analysis.clone(), repeat_noise, opts);
    stage_seconds.push(lap("effect search"));
    let (current, final_analysis, effects, rounds) = (search.current, search.analysis, search.effects, search.rounds);
    progress_residual_checks(opts, "final", &current, &final_analysis);
    let verdict = verdict(&effects, &current, &final_analysis, &open.channels, opts);
    let cross_validation = cross_validate(&data, &current, opts.candidate_fit, opts.screen_pixels);
    stage_seconds.push(lap("cross-validation"));
    let noise = noise_reports(&data, &current, open, repeat_noise);
    let out_profile = corrected_profile(&base_profile, &current, open, &verdict)?;
    let low_band = [low_band(&base, &base_analysis, opts), low_band(&current, &final_analysis, opts)];
    Ok(Diagnosis { noise, base, base_analysis, final_fit: current, final_analysis, effects, rounds, verdict, cross_validation, low_band, profile: out_profile, open: open.clone(), stage_seconds })
}

/// The given profile (checked against the captures), or one estimated from them.
fn base_profile(open: &Image, pinhole: &Image, profile: Option<&Profile>, opts: &DiagnoseOptions) -> Result<Profile, DiagnoseError> {
    match profile {
        Some(p) => {
            let s = &p.meta.source;
            let images = [open.width(), open.height(), open.channel_count()];
            if s.width != images[0] || s.height != images[1] || p.grid.channels.len() != images[2] {
                return Err(DiagnoseError::Profile { profile: [s.width, s.height, p.grid.channels.len()], images });
            }
            Ok(p.clone())
        }
        None => {
            // the base model keeps clipped pixels in the data term (that is a catalogue effect)
            let eo = EstimateOptions { saturation: f32::INFINITY, progress: opts.progress, ..opts.estimate.clone() };
            Ok(estimate(open, pinhole, &eo)?.profile)
        }
    }
}

/// The fit data and the base model fitted with its noise curve: a provisional fit, its
/// degrees-of-freedom probe on the screening subset ([`DiagnoseOptions::screen_pixels`]; the
/// absorbed share scaled to every pixel, [`Fit::set_dof`]), the noise curve from the
/// provisional fit's residual (module docs of `noise`) or from repeated frames, then the base
/// model refitted with it; the curve stays fixed for every later model. Returns whether the
/// curve came from repeated frames.
fn base_model<'a>(open: &'a Image, pinhole: &'a Image, base_profile: &Profile, opts: &DiagnoseOptions) -> (Data<'a>, Fit, bool) {
    let mut lap = crate::estimate::stage_clock();
    let mut data = Data::new(open, pinhole, opts.pinhole_variance_scale);
    data.screen_pixels = opts.screen_pixels;
    data.fit_pixels = opts.fit_pixels;
    let init = Model { corrections: model::Corrections::default(), grid: base_profile.grid.clone(), exposure: base_profile.meta.exposure_ratio.clone() };
    let (provisional_fit, probe, refit) = base_budget(screens(&data, opts), opts.base_fit);
    let mut provisional = fit::fit(&data, &init.corrections, &init, provisional_fit);
    progress_lap(opts, lap("provisional fit"));
    // the probe measures what the kernel fit absorbs (its dof, and its share of the noise's
    // high-pass, which the residual's curve is corrected for); the probe's response does not
    // depend on the curve's overall scale, so the refit inherits it
    provisional.set_dof(fit::measure_kernel_dof(&data, &provisional, probe, DOF_PROBE_SEED, opts.screen_pixels));
    progress_lap(opts, lap("dof probe"));
    let repeat_noise = opts.repeat_noise.as_ref().filter(|r| r.len() == open.channel_count() && r.iter().all(|c| !c.bins.is_empty()));
    data.curves = match repeat_noise {
        Some(r) => r.clone(),
        None => residual_curves(open, &provisional),
    };
    data.curves_from_frames = repeat_noise.is_some();
    let mut base = fit::fit_from(&data, &provisional.model.corrections, &provisional.model, refit, &provisional.warm);
    base.inherit_dof(&provisional);
    progress_lap(opts, lap("base refit"));
    (data, base, repeat_noise.is_some())
}

/// The base stage's budgets ([`base_model`]): the provisional fit, its degrees-of-freedom
/// probe and the refit on the residual's noise curve. The refit continues the provisional
/// fit's kernel momentum ([`fit::fit_from`]); where the screening subset thins the data
/// ([`screens`]) the provisional fit therefore runs one round fewer than the base budget and
/// the refit is in effect its last round: `(rounds − 1) × iterations`, the probe with
/// [`probe_budget`], then `1 × iterations` (docs/notes/diagnosis-history.md, "Session 20
/// (d20)"). Elsewhere the base budget for the fit and the probe, then one round.
fn base_budget(screens: bool, base_fit: FitSettings) -> (FitSettings, FitSettings, FitSettings) {
    let refit = FitSettings { rounds: 1, kernel_iterations: base_fit.kernel_iterations };
    let provisional = if screens { FitSettings { rounds: base_fit.rounds.saturating_sub(1).max(1), ..base_fit } } else { base_fit };
    (provisional, probe_budget(screens, base_fit), refit)
}

/// The degrees-of-freedom probe's budget ([`fit::measure_kernel_dof`]): where the screening
/// subset thins the data ([`screens`]), one round of the base budget; elsewhere the base budget.
/// The probe's count enters the reduced χ² only through `N − df` on a curve divided by
/// `1 − α_hp`, with `α_hp ≈ df/N` from the same probe, so a shorter probe that counts fewer
/// degrees of freedom leaves `χ²/(N − df) ≈ χ²_raw/N` (docs/diagnosis.md, "Speed at camera
/// resolution"): at 1024×768 RGB, one round counts 22 279 against 31 129 (clean, seed 41) and
/// costs 8.4 s instead of 17.4 s (docs/benchmarks.md, "Session 66").
fn probe_budget(screens: bool, base_fit: FitSettings) -> FitSettings {
    if screens {
        FitSettings { rounds: 1, ..base_fit }
    } else {
        base_fit
    }
}

/// The low-band test ([`low_band`]) and the rotation the kernels' centroids follow
/// ([`candidates::centroid_similarity_fit`]) of a model on stderr, with progress on.
fn progress_residual_checks(opts: &DiagnoseOptions, which: &str, f: &Fit, a: &Analysis) {
    if let Some(b) = low_band(f, a, opts).filter(|_| opts.progress) {
        eprintln!("{which} model: residual's lowest band (≤ {:.3} cycles/px) {:.3}× white noise, floor {:.3}×, bound {:.3} ({:.0} samples): {}", b.top, b.power, b.floor, b.bound, b.samples, if b.within() { "within" } else { "above" });
    }
    if let Some(c) = candidates::centroid_similarity_fit(f).filter(|_| opts.progress) {
        eprintln!(
            "{which} model: the kernels' centroids follow a rotation of {:.4}° ± {:.4}° (t = {:.1}; {:.2} px at the corners) and a scale of {:+.5} ± {:.5}",
            c.p[1].to_degrees(),
            c.se[1].to_degrees(),
            c.rotation_t(),
            c.rotation_corner_px,
            c.p[0],
            c.se[0]
        );
    }
}

/// A sub-stage's wall and CPU seconds on stderr, with progress on.
fn progress_lap(opts: &DiagnoseOptions, t: crate::estimate::StageTime) {
    progress_lap_as(opts, "", t);
}

/// [`progress_lap`] with `prefix` before the stage's name.
fn progress_lap_as(opts: &DiagnoseOptions, prefix: &str, t: crate::estimate::StageTime) {
    if opts.progress {
        eprintln!("  {prefix}{}: {:.1} s, {} CPU-s", t.stage, t.wall, t.cpu.map_or("–".to_string(), |c| format!("{c:.1}")));
    }
}

/// Measures `f`'s effective kernel degrees of freedom ([`fit::measure_kernel_dof`]) with
/// [`probe_budget`] on the screening subset; `round` seeds the probe.
fn measure_dof(data: &Data, f: &mut Fit, opts: &DiagnoseOptions, round: u64) {
    f.set_dof(fit::measure_kernel_dof(data, f, probe_budget(screens(data, opts), opts.base_fit), DOF_PROBE_SEED + round, opts.screen_pixels));
}

/// Seed of the divergence probe (any fixed value: the run stays reproducible).
const DOF_PROBE_SEED: u64 = 0x00d0_f5eed;

/// The noise curve of each channel from a fit's residual on its evaluation set, divided by
/// the share of the noise the fit keeps (`1 − α_hp`, [`Fit::highpass_absorbed`]) when that is
/// known.
pub fn residual_curves(open: &Image, f: &Fit) -> Vec<NoiseCurve> {
    let alpha: Vec<f64> = (0..open.channel_count()).map(|c| f.highpass_absorbed.as_ref().and_then(|a| a.get(c)).copied().unwrap_or(0.0)).collect();
    (0..open.channel_count()).map(|c| residual_curve(open, f, c, &f.eval[c], alpha[c])).collect()
}

fn residual_curve(open: &Image, f: &Fit, c: usize, mask: &[bool], alpha: f64) -> NoiseCurve {
    noise::measure_residual(&open.planes[c], &f.predicted[c], mask, 16, 8, Some(&f.reference_highpass[c])).absorbed(alpha)
}

/// Where the effect search ended.
struct Search {
    current: Fit,
    analysis: Analysis,
    effects: Vec<FoundEffect>,
    rounds: Vec<Vec<CandidateScore>>,
    /// The current model is an adopted winner as `adopt` left it (polished, refitted on every
    /// pixel), or that model converged further ([`converge_before_screening`]), and nothing
    /// else changed it since: the final polish would polish it again.
    polished: bool,
    /// The current model was run to convergence on every pixel ([`final_polish`]) since it last
    /// changed: a final polish would not move it.
    converged: bool,
    /// The effect adopted last, where it is not the list's last entry (an effect found again
    /// keeps its place): the one whose "after" the final model is.
    last_found: Option<String>,
}

impl Search {
    /// Makes `f` the current model, changed since any convergence: `polished` when it is an
    /// adopted winner as `adopt` leaves it. Its analysis is the caller's to redo (after a dof
    /// probe, where one follows).
    fn replace(&mut self, f: Fit, polished: bool) {
        self.current = f;
        (self.polished, self.converged) = (polished, false);
    }

    /// States the current model as the "after" of the effect adopted last.
    fn state_after(&mut self) {
        let after = Figures::of(&self.current);
        if let Some(e) = self.last_adopted() {
            e.after = after;
        }
    }

    /// The entry whose "after" is the current model's: the effect adopted last.
    fn last_adopted(&mut self) -> Option<&mut FoundEffect> {
        let i = self.last_found.as_ref().and_then(|n| self.effects.iter().position(|e| &e.name == n)).or(self.effects.len().checked_sub(1))?;
        self.effects.get_mut(i)
    }
}

/// Adds catalogue effects while the fit is not consistent with noise, or misregistration alone
/// while a consistent fit's kernels rotate ([`next_round`]; module docs, step 3), an adopted
/// model that is not consistent first converged where the subset thins the data
/// ([`converge_before_screening`]), then polishes the final model ([`final_polish`]) where backward elimination changed it since
/// the last adoption or it is not consistent ([`needs_final_polish`]).
fn add_effects(data: &mut Data, base: Fit, base_analysis: Analysis, repeat_noise: bool, opts: &DiagnoseOptions) -> Search {
    let mut s = Search { current: base, analysis: base_analysis, effects: Vec::new(), rounds: Vec::new(), polished: false, converged: false, last_found: None };
    // every round but the last adopts an effect (or finds one again): the rounds count them
    while let Some(round) = next_round(&s.current, opts).filter(|_| s.rounds.len() < opts.max_effects) {
        let mut lap = crate::estimate::stage_clock();
        if let (Round::Rotation, Some(c), true) = (round, kernel_rotation(&s.current), opts.progress) {
            eprintln!("round {}: the fit is consistent, but the kernels' centroids rotate by {:.3}° about the centre (t = {:.0}): misregistration alone is screened", s.rounds.len() + 1, c.p[1].to_degrees(), c.rotation_t());
        }
        let (scores, best) = search_round(data, &s.current, &s.analysis, round, opts);
        progress_lap(opts, lap("screening round"));
        s.rounds.push(scores);
        let Some((cand, f, dbic)) = best else {
            if opts.progress {
                eprintln!("round {}: no catalogue effect improves the fit", s.rounds.len());
            }
            break;
        };
        if opts.progress {
            let what = match round {
                Round::Full => "explains most",
                Round::Rotation => "is the rotation round's candidate, judged by its adoption rule",
            };
            eprintln!("round {}: {} {what} (reduced χ² {:.3} → {:.3}, ΔBIC {:.0})", s.rounds.len(), cand.name, s.current.reduced_chi2(), f.reduced_chi2(), dbic);
        }
        if !adopt(data, &mut s, (cand, f, dbic), repeat_noise, round, opts) {
            break;
        }
        converge_before_screening(data, &mut s, round, opts);
    }
    // backward elimination: drop effects a later one made redundant ([`prune`])
    while let Some((name, f)) = prune::weakest_redundant(data, &s.current, opts) {
        if opts.progress {
            eprintln!("{name} is redundant with the effects found after it: removed (reduced χ² {:.3} → {:.3})", s.current.reduced_chi2(), f.reduced_chi2());
        }
        s.effects.retain(|e| e.name != name);
        s.last_found = None;
        // a screening refit scores only the subset: the current model is scored on every pixel
        s.replace(if f.share < 1.0 { rescore(data, &f) } else { f }, false);
        s.analysis = analyse(&s.current);
    }
    // the effect adopted last states the final model as its "after": the polished one where
    // the polish lowered χ², otherwise (no final polish) the adoption's refit or its convergence
    if needs_final_polish(s.effects.len(), s.polished, consistent(&s.current, opts), s.converged) {
        // a last polish of the final model: more rounds, or (unthinned) a larger budget
        polish_current(data, &mut s, opts, "final polish");
    } else {
        s.state_after();
    }
    // each effect states the final model's parameters: later rounds refit them, and backward
    // elimination re-searches the glare's width (sf11, veiling glare + tone curve, seed 74:
    // 307.2 px when adopted, 102.5 px in the final model against 76.4 rendered)
    let kept = s.current.model.corrections.names();
    for e in s.effects.iter_mut().filter(|e| kept.contains(&e.name.as_str())) {
        e.parameters = candidates::parameters_json(&e.name, &s.current.model.corrections);
    }
    s
}

/// The current model polished ([`final_polish`], progress under `label`) and kept where that
/// lowered χ², as the last adopted effect's "after".
fn polish_current(data: &Data, s: &mut Search, opts: &DiagnoseOptions, label: &'static str) {
    if let Some(polished) = polished_lower(data, &s.current, opts, label) {
        s.current = polished;
        s.analysis = analyse(&s.current);
        s.state_after();
    }
}

/// `f` polished ([`final_polish`], timed under `label`) where that lowered χ², `None` otherwise:
/// the one convergence step of the convergence before the next round, the final polish and a
/// rotation round's winner ([`needs_rotation_convergence`]).
fn polished_lower(data: &Data, f: &Fit, opts: &DiagnoseOptions, label: &'static str) -> Option<Fit> {
    let mut lap = crate::estimate::stage_clock();
    let polished = final_polish(data, f, opts, label);
    progress_lap(opts, lap(label));
    (polished.chi2() < f.chi2()).then_some(polished)
}

/// Where the screening subset thins the data ([`screens`]) and a full round's adopted model is
/// not [`consistent`], its kernels are first run to convergence on every pixel (the final
/// polish's rounds, [`final_polish`]) and the consistency is judged on the converged model: the
/// adoption's polish and refit (80 + 40 iterations from the winner's subset fit) can leave a
/// right model short of the noise floor for want of iterations (misregistration seed 41 at
/// 1024×768: χ²/dof 1.179 after adoption, 0.992 after the final polish), and a round screened on
/// it finds no effect to add (docs/diagnosis.md "Adoption, the stop rule and the polishes").
/// Only a model that stays inconsistent once converged goes on to the next full round. The
/// unthinned proof cases keep their polishes as they were.
fn converge_before_screening(data: &Data, s: &mut Search, round: Round, opts: &DiagnoseOptions) {
    // just adopted (polished, not converged): the final polish's own test is consistency
    if round != Round::Full || !screens(data, opts) || !needs_final_polish(s.effects.len(), s.polished, consistent(&s.current, opts), s.converged) {
        return;
    }
    // the adopted effect's "after" becomes its model converged, as after a final polish
    polish_current(data, s, opts, "convergence before the next round");
    s.converged = true;
}

/// Whether the screening subset thins the data at this size: the kernel operator keeps every
/// block of a capture with at most [`DiagnoseOptions::screen_pixels`] pixels per channel.
fn screens(data: &Data, opts: &DiagnoseOptions) -> bool {
    data.open.width() * data.open.height() > opts.screen_pixels
}

/// Makes the round's winner `f` (a screening fit of `cand`) the current model: polished
/// ([`polish_winner`]), the noise curve re-measured from its residual (a curve from repeated
/// frames does not depend on the model), the effect's before and after stated on that same
/// curve, then refitted once on every pixel with it. Its degrees of freedom are measured again
/// only when the effect changes the kernels' linear operator ([`changes_kernel_operator`]); a
/// gain or an additive term keeps the current model's probe.
///
/// The stop rule: the polished winner must lower the whole-pixel χ² (both models on the new
/// curve) by more than χ²'s own noise allows, [`STOP_SIGMAS`]` · √(2N)`; otherwise the curve
/// is restored, the current model kept, and `false` returned (the search ends). A
/// [`Round::Rotation`] winner follows [`rotation_round_adopts`] instead (as good a fit, kernels
/// that no longer rotate), and its evidence states the rotation before and after.
fn adopt(data: &mut Data, s: &mut Search, (cand, f, dbic): (candidates::Candidate, Fit, f64), repeat_noise: bool, round: Round, opts: &DiagnoseOptions) -> bool {
    let mut lap = crate::estimate::stage_clock();
    let f = polish_winner(data, &s.current, f, cand.name, opts);
    progress_lap(opts, lap("winner's polish"));
    let parameters = candidates::parameters_json(cand.name, &f.model.corrections);
    let old_curves = data.curves.clone();
    if !repeat_noise {
        data.curves = residual_curves(data.open, &f);
    }
    let mut current = rescore(data, &f);
    // the refit below needs only the winner's model and solver state: its planes go now
    let fit::Fit { model, warm, .. } = f;
    let previous = rescore(data, &s.current);
    let noise = chi2_noise(current.n() as f64);
    let mut lowered = previous.chi2() - current.chi2();
    // what the rest needs of the current model rescored; its planes go before any convergence
    let (before, previous_chi2, previous_bic) = (Figures::of(&previous), previous.chi2(), previous.bic());
    let was = (round == Round::Rotation).then(|| kernel_rotation(&previous)).flatten();
    drop(previous);
    let mut evidence = cand.evidence;
    let mut dbic = dbic;
    // a rotation round's winner converged on every pixel ([`needs_rotation_convergence`])
    let mut converged_winner = false;
    match round {
        Round::Full if lowered <= noise => {
            if opts.progress {
                eprintln!("{} polished on every pixel lowers χ² by {lowered:.0}, within χ²'s noise ({STOP_SIGMAS}·√(2N) = {noise:.0}): not adopted", cand.name);
            }
            data.curves = old_curves;
            return false;
        }
        Round::Full => {}
        Round::Rotation => {
            // the kernels took the map up, so χ² cannot prefer it: the map is adopted when it
            // fits as well (χ² not raised beyond its noise) and leaves kernels that no longer rotate
            let mut now = candidates::centroid_similarity_fit(&current);
            let text = |c: &candidates::CentroidSimilarity| format!("{:.3}° (t = {:.1})", c.p[1].to_degrees(), c.rotation_t());
            let tolerance = rotation_tolerance(noise, previous_chi2, opts.min_gain);
            let mut kept = rotation_round_adopts(lowered, tolerance, now.as_ref());
            // kernels re-estimated under the map that stop rotating but fit worse may only be
            // short of the whole-pixel iterations the current model has had: converged, the
            // rule is asked again (where the subset thins the data)
            if needs_rotation_convergence(lowered, tolerance, now.as_ref(), screens(data, opts)) {
                if opts.progress {
                    eprintln!("{} polished on every pixel changes χ² by {:+.0} (tolerance {tolerance:.0}) with kernels that no longer rotate: converged on every pixel before the rule is applied", cand.name, -lowered);
                }
                if let Some(converged) = polished_lower(data, &current, opts, "the rotation round's winner converged") {
                    (lowered, now) = (previous_chi2 - converged.chi2(), candidates::centroid_similarity_fit(&converged));
                    current = converged;
                    kept = rotation_round_adopts(lowered, tolerance, now.as_ref());
                    converged_winner = true;
                }
            }
            let how = if converged_winner { "converged" } else { "polished" };
            let (was_text, now_text) = (was.as_ref().map_or("–".into(), text), now.as_ref().map_or("–".into(), text));
            if opts.progress {
                eprintln!(
                    "{} {how} on every pixel changes χ² by {:+.0} (tolerance {tolerance:.0}: χ²'s noise {STOP_SIGMAS}·√(2N) = {noise:.0} or {} of χ²); the kernels' centroids rotate by {now_text}, {was_text} before: {}",
                    cand.name,
                    -lowered,
                    opts.min_gain,
                    if kept { "adopted (as good a fit, with kernels that no longer rotate)" } else { "not adopted" }
                );
            }
            if !kept {
                data.curves = old_curves;
                return false;
            }
            evidence = format!("{evidence}; the fit's kernels rotated by {was_text} about the image centre, which a lens's kernels do not; under the map ({how} on every pixel) they rotate by {now_text} at a χ² {:+.0} (tolerance {tolerance:.0}), which decides a rotation round, not ΔBIC", -lowered);
            // the ΔBIC stated is the adopted model's on every pixel against the current one
            dbic = current.bic() - previous_bic;
        }
    }
    let after = Figures::of(&current);
    let found = FoundEffect { name: cand.name.to_string(), evidence, location: cand.location, parameters, before, after, delta_bic: dbic };
    // an effect found again (`pinhole_diffraction`'s radius or `veiling_glare`'s width
    // re-searched, `psf_field_variation` grown to a finer grid) keeps its place, its first
    // "before" and its evidence, which the new one extends: the order of the list is the order
    // in which effects were first named
    s.last_found = Some(found.name.clone());
    match s.effects.iter_mut().find(|e| e.name == found.name) {
        Some(e) => {
            e.evidence = format!("{}; then {}", e.evidence, found.evidence);
            (e.parameters, e.after, e.delta_bic) = (found.parameters, found.after, e.delta_bic + found.delta_bic);
        }
        None => s.effects.push(found),
    }
    // the models no longer needed go before the refit (each holds whole-image planes): the
    // rescored winner too, whose degrees of freedom the refit inherits (in round 1 the
    // current model until the refit replaces it shares its planes with `diagnose`'s base)
    let dof = current.dof();
    // a converged rotation winner is refitted from its converged state, any other from the
    // winner's (the rescore keeps the winner's model, not necessarily its exact scalars)
    let (model, warm) = if converged_winner {
        let fit::Fit { model, warm, .. } = current;
        (model, warm)
    } else {
        drop(current);
        (model, warm)
    };
    let mut refit = fit::fit_from(data, &model.corrections, &model, FitSettings { rounds: 1, kernel_iterations: opts.candidate_fit.kernel_iterations }, &warm);
    refit.inherit(&dof);
    s.replace(refit, true);
    if changes_kernel_operator(cand.name) {
        measure_dof(data, &mut s.current, opts, s.rounds.len() as u64);
    }
    s.analysis = analyse(&s.current);
    progress_lap(opts, lap(if changes_kernel_operator(cand.name) { "rescore, refit and dof probe" } else { "rescore and refit (dof kept)" }));
    true
}

/// Standard deviations of χ² (`√(2N)` for `N` pixels) a winner's whole-pixel gain must exceed
/// to be adopted ([`adopt`]).
const STOP_SIGMAS: f64 = 3.0;

/// Whether effect `name` changes the kernel fit's linear operator (the reference it blurs, its
/// geometry, the grid or the data mask), so that its effective degrees of freedom must be
/// probed again. A gain (`vignetting`, `illumination_gradient`), an offset (`black_level`) or
/// the glare's additive halo and `(1 − f)` scale leave the operator as it was; they move the
/// weights by the gain, and the reduced χ² depends on `df` only through `N − df` (`df/N` ≈ 1 %
/// at 1024×768, so a 10 % error in `df` moves it by 0.1 %).
fn changes_kernel_operator(name: &str) -> bool {
    !matches!(name, "vignetting" | "illumination_gradient" | "black_level" | "veiling_glare")
}

/// The winner (of effect `name`) polished with the base budget (kept if it lowers χ²), with
/// `current`'s degrees of freedom. Where the screening subset thins the data ([`screens`]) the
/// polish runs on the subset and one round of the base budget on every pixel follows, so that
/// the residual the noise curve is measured from is in-sample everywhere. A winner that leaves
/// the kernel operator as it was ([`changes_kernel_operator`]: a gain, an offset, the glare)
/// skips the subset rounds there: its kernels started from the current model's, converged on
/// every pixel, and moved only in its screening fit; more rounds on the subset (about 1.2
/// pixels per kernel value) fit them to the subset's noise, which one whole-pixel round does not
/// undo. Its own parameters then get that one round's Gauss–Newton steps before the stop rule,
/// not four. Vignetting seed 41 at 1024×768 RGB: polish 28.8 → 16.7 s, final χ²/dof 1.014 →
/// 1.004 (docs/benchmarks.md, "Session 66").
fn polish_winner(data: &Data, current: &Fit, f: Fit, name: &str, opts: &DiagnoseOptions) -> Fit {
    let thinned = screens(data, opts);
    let f = if thinned && !changes_kernel_operator(name) {
        f
    } else {
        let budget = if thinned { opts.screen_pixels } else { usize::MAX };
        let mut polished = fit::fit_subset_from(data, &f.model.corrections, &f.model, opts.base_fit, budget, &f.warm);
        polished.inherit_dof(current);
        // the model not kept is dropped here, before the whole-pixel round
        if polished.chi2() <= f.chi2() {
            drop(f);
            polished
        } else {
            drop(polished);
            f
        }
    };
    if !thinned {
        return f;
    }
    let whole_round = FitSettings { rounds: 1, kernel_iterations: opts.base_fit.kernel_iterations };
    let mut full = fit::fit_from(data, &f.model.corrections, &f.model, whole_round, &f.warm);
    full.inherit_dof(current);
    full
}

/// Whether the search's final model gets the final polish ([`final_polish`]): only when it
/// holds an effect (`effects` > 0) and either something changed it since `adopt` polished it
/// (`polished` false: backward elimination removed an effect) or the polished model is not yet
/// consistent with the noise ([`consistent`] false: its kernels need the larger budget, as a
/// tone curve's do once every kernel is refitted on the new axis). A consistent model just
/// polished by its adoption is not polished again: the two polishes would run back to back;
/// nor is a model `converged` since it last changed ([`converge_before_screening`]).
fn needs_final_polish(effects: usize, polished: bool, consistent: bool, converged: bool) -> bool {
    effects > 0 && !converged && (!polished || !consistent)
}

/// The final model polished. Where the screening subset thins the data ([`screens`]), rounds of
/// the base budget on every pixel, from `current` and its solver state, while they still lower
/// χ² by more than its noise ([`final_polish_rule`]); otherwise two rounds of twice the base
/// budget on every pixel. The screened path ran two subset rounds first until session 52: they
/// raised the whole-pixel χ² of misregistration seed 41 at 1024×768 from 2 490 841 to 3 219 802
/// (the kernels fitted ~2 pixels per value, docs/diagnosis.md "Adoption, the stop rule and the
/// polishes"), which six whole-pixel rounds then had to undo (71.8 s, χ² 2 102 013); from the
/// current model five rounds reach 2 096 233 in 52.6 s.
fn final_polish(data: &Data, current: &Fit, opts: &DiagnoseOptions, label: &str) -> Fit {
    let mut polished = if screens(data, opts) {
        let (f, trace) = fit::fit_converging(data, &current.model.corrections, &current.model, final_polish_rule(current.n(), opts), Some(&current.warm));
        if opts.progress {
            let falls: Vec<String> = trace.windows(2).map(|w| format!("{:.0}", w[0] - w[1])).collect();
            eprintln!("{label} on every pixel: {} rounds, χ² {:.0} → {:.0} (falls {}; noise {:.0})", trace.len() - 1, trace[0], trace[trace.len() - 1], falls.join(", "), (2.0 * current.n() as f64).sqrt());
        }
        f
    } else {
        let settings = FitSettings { rounds: 2, kernel_iterations: 2 * opts.base_fit.kernel_iterations };
        fit::fit_from(data, &current.model.corrections, &current.model, settings, &current.warm)
    };
    polished.inherit_dof(current);
    polished
}

/// Most whole-pixel rounds of the final polish ([`final_polish_rule`]).
const FINAL_POLISH_MAX_ROUNDS: usize = 6;

/// The final polish's whole-pixel rounds ([`final_polish`]): the base budget per round, run
/// while a round lowers χ² by more than [`STOP_SIGMAS`]` · √(2N)` (χ²'s own noise for `N`
/// pixels), at most [`FINAL_POLISH_MAX_ROUNDS`].
fn final_polish_rule(n: usize, opts: &DiagnoseOptions) -> fit::Convergence {
    fit::Convergence { kernel_iterations: opts.base_fit.kernel_iterations, max_rounds: FINAL_POLISH_MAX_ROUNDS, tolerance: chi2_noise(n as f64) }
}

/// `f`'s model scored with `data`'s current noise curves, unchanged (no fitting round), with
/// `f`'s degrees of freedom.
fn rescore(data: &Data, f: &Fit) -> Fit {
    let mut r = fit::fit(data, &f.model.corrections, &f.model, FitSettings { rounds: 0, kernel_iterations: 0 });
    r.inherit_dof(f);
    // the same model: a later fit continues `f`'s kernel solver state
    r.warm = f.warm.clone();
    r
}

/// A fit consistent with noise: reduced χ² and the noise law's misfit within the options'
/// bounds. The low-band test ([`low_band`]) is reported beside it, not part of it: on clean
/// 1024×768 data the base model's lowest band is above its statistical bound
/// (docs/notes/diagnosis-history.md, "Screening on the subset alone, and the low-band test").
fn consistent(f: &Fit, opts: &DiagnoseOptions) -> bool {
    f.reduced_chi2() <= opts.consistent && f.law_misfit().map_or(true, |m| m <= opts.consistent_noise)
}

/// How many standard errors the rotation the kernels' centroids follow
/// ([`candidates::centroid_similarity_fit`]) must reach before the search screens
/// misregistration although the fit is consistent (`next_round`). A rotation about the
/// image centre is what a rotationally symmetric lens cannot put into its kernels, and what
/// per-tile kernels of 45–63 px take up from a misregistration of a few pixels, leaving χ² at
/// the floor. At 1024×768 RGB, seed 41: clean data through the sf11 singlet t = 0.5, through the
/// achromat 0.2; a 0.39° misregistration through the sf11 singlet t = −101
/// (docs/notes/diagnosis-history.md, "Session 23").
pub const ROTATION_T: f64 = 10.0;

/// The rotation of the kernels' centroids ([`candidates::centroid_similarity_fit`]) when it is
/// significant: at least [`ROTATION_T`] standard errors and a displacement of at least
/// [`registered::MIN_ROTATION_CORNER_PX`] at the corners; `None` otherwise.
pub fn kernel_rotation(f: &Fit) -> Option<candidates::CentroidSimilarity> {
    candidates::centroid_similarity_fit(f).filter(rotation_significant)
}

/// At least [`ROTATION_T`] standard errors and [`registered::MIN_ROTATION_CORNER_PX`] at the
/// corners.
pub(crate) fn rotation_significant(c: &candidates::CentroidSimilarity) -> bool {
    c.rotation_t().abs() >= ROTATION_T && c.rotation_corner_px >= registered::MIN_ROTATION_CORNER_PX
}

/// The adoption rule of a [`Round::Rotation`] winner: the kernels took the map up, so χ² cannot
/// prefer it; it is adopted when it fits as well (`lowered`, the χ² it removes on every pixel,
/// not below minus `tolerance`, [`rotation_tolerance`]) and its kernels no longer rotate
/// (`after`, their centroids' similarity, not significant).
fn rotation_round_adopts(lowered: f64, tolerance: f64, after: Option<&candidates::CentroidSimilarity>) -> bool {
    lowered > -tolerance && !after.is_some_and(rotation_significant)
}

/// Whether a [`Round::Rotation`] winner that [`rotation_round_adopts`] refuses is first run to
/// convergence on every pixel ([`final_polish`]) and the rule asked again: only where the
/// subset thins the data (`thinned`; the proof cases keep their rule), and only when the kernels
/// under the map no longer rotate (`after` not significant), so that the refusal is χ² alone
/// (`lowered` below minus `tolerance`). The current model has often been converged on every
/// pixel (after a full round that left it inconsistent, [`converge_before_screening`]) and in
/// any case fitted longer on every pixel, while the winner's kernels were re-estimated under
/// the map and have had one polish: on the pair misregistration + pinhole
/// diffraction at 1024×768 (seed 41) such a start stood 13.1 % of χ² above the current model
/// after 80 whole-pixel iterations, while a model converged from 80 iterations on the
/// misregistration case fell by 16 % (χ²/dof 1.179 → 0.992; docs/diagnosis.md "The rotation
/// test").
fn needs_rotation_convergence(lowered: f64, tolerance: f64, after: Option<&candidates::CentroidSimilarity>, thinned: bool) -> bool {
    thinned && lowered <= -tolerance && !after.is_some_and(rotation_significant)
}

/// How much χ² a [`Round::Rotation`] winner may add and still fit as well: χ²'s noise
/// (`3·√(2N)`) or `min_gain` of the current model's χ², the larger. The winner's kernels were
/// re-estimated under the map and have had fewer whole-pixel iterations than the current
/// model's, so equal fits do not reach equal χ²; `min_gain` is the share of χ² the search counts
/// as a gain at all. At 1024×768 RGB through the sf11 singlet (seed 42) the map's model ends
/// 0.46 % of χ² (+9 747) above the current model with kernels that no longer rotate (t 75 → 2.9).
fn rotation_tolerance(noise: f64, current_chi2: f64, min_gain: f64) -> f64 {
    noise.max(min_gain * current_chi2)
}

/// What the search screens next ([`next_round`]).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Round {
    /// Every catalogue effect not in the model: the fit is not [`consistent`].
    Full,
    /// Misregistration alone: the fit is consistent, but the kernels' centroids follow a
    /// significant rotation ([`kernel_rotation`]), which no other catalogue effect produces.
    Rotation,
}

/// The next round of the search, `None` when it stops: [`Round::Full`] while the fit is not
/// [`consistent`]; [`Round::Rotation`] when it is, misregistration is neither in the model nor
/// excluded, and the kernels rotate ([`kernel_rotation`]).
fn next_round(f: &Fit, opts: &DiagnoseOptions) -> Option<Round> {
    let open = f.model.corrections.misregistration.is_none() && !opts.excluded.iter().any(|e| e == "misregistration");
    next_round_of(consistent(f, opts), open, || kernel_rotation(f).is_some())
}

/// [`next_round`] of a fit that is `consistent` or not, with misregistration `open` (neither in
/// the model nor excluded) or not; `rotates` is asked only where it decides.
fn next_round_of(consistent: bool, open: bool, rotates: impl FnOnce() -> bool) -> Option<Round> {
    if !consistent {
        Some(Round::Full)
    } else {
        (open && rotates()).then_some(Round::Rotation)
    }
}

impl Round {
    /// The effects the round does not propose: the options' exclusions, and in a
    /// [`Round::Rotation`] every catalogue effect but misregistration.
    fn excluded(self, opts: &DiagnoseOptions) -> Vec<String> {
        let mut out = opts.excluded.clone();
        if self == Round::Rotation {
            out.extend(proof::CONCEALED.iter().filter(|&&n| n != "misregistration").map(|n| n.to_string()));
        }
        out
    }

    /// What the round's registered starts must beat: in a [`Round::Rotation`] the current
    /// model alone ([`registered::StartRule::BeatsCurrent`]).
    fn start_rule(self) -> registered::StartRule {
        match self {
            Round::Full => registered::StartRule::LikeForLike,
            Round::Rotation => registered::StartRule::BeatsCurrent,
        }
    }
}

/// The residual's lowest band against the noise floor there (docs/notes/diagnosis-history.md,
/// "Screening on the subset alone, and the low-band test"): one χ² over millions of pixels averages
/// away a smooth misfit (a halo hiding partly in the kernels) that holds several times the floor's
/// power at the lowest frequencies.
#[derive(Clone, Debug, Serialize)]
pub struct LowBand {
    /// Upper edge of the band (cycles/px).
    pub top: f64,
    /// Measured power of the normalised residual in the band, channels averaged (white noise
    /// at the floor: 1; [`analysis::Analysis::spectrum`]).
    pub power: f64,
    /// What the noise floor puts there ([`Fit::low_band_floor`], channels averaged).
    pub floor: f64,
    /// Independent frequency samples behind `power`: the band's half-plane bins × channels ×
    /// the evaluated share of the frame.
    pub samples: f64,
    /// `floor · consistent · (1 + LOW_BAND_SIGMAS/√samples)`: the floor with the χ² test's
    /// slack for a measured noise curve, and [`LOW_BAND_SIGMAS`] standard deviations of the
    /// band power's estimate (each bin's power is exponentially distributed: relative standard
    /// deviation `1/√samples` of their mean).
    pub bound: f64,
}

impl LowBand {
    pub fn within(&self) -> bool {
        self.power <= self.bound
    }
}

/// Standard deviations of the low band's power estimate above the floor before the band counts
/// as inconsistent (one-sided; 4σ: a false alarm in about 3·10⁻⁵ of clean fits).
pub const LOW_BAND_SIGMAS: f64 = 4.0;

/// The low-band test of `f` ([`LowBand`]); `None` when the fit has no floor for it (screening
/// fits) or the spectrum has no low band.
pub fn low_band(f: &Fit, a: &Analysis, opts: &DiagnoseOptions) -> Option<LowBand> {
    let &(fc, power) = a.spectrum.first()?;
    if f.low_band_floor.is_empty() || fc > analysis::LOW_BAND_TOP {
        return None;
    }
    let nch = f.low_band_floor.len();
    let floor = f.low_band_floor.iter().sum::<f64>() / nch as f64;
    let (w, h) = (f.normalized[0].width, f.normalized[0].height);
    let evaluated = f.n_scored() as f64 / (nch * w * h).max(1) as f64;
    low_band_of(power, floor, [w, h, nch], evaluated, opts.consistent)
}

/// The [`LowBand`] of a measured band power and its floor on `nch` channels of `w × h`
/// pixels, of which the share `evaluated` is in the evaluation set; `consistent` is the χ²
/// test's slack ([`DiagnoseOptions::consistent`]).
pub fn low_band_of(power: f64, floor: f64, [w, h, nch]: [usize; 3], evaluated: f64, consistent: f64) -> Option<LowBand> {
    let samples = analysis::low_band_bins(w, h).len() as f64 * nch as f64 * evaluated;
    if samples < 1.0 {
        return None;
    }
    let bound = floor * consistent * (1.0 + LOW_BAND_SIGMAS / samples.sqrt());
    Some(LowBand { top: analysis::LOW_BAND_TOP, power, floor, samples, bound })
}

/// One round: the null refit, then every effect `round` proposes ([`Round::excluded`],
/// [`Round::start_rule`]) refitted from the current model;
/// returns every score (the null refit first) and the best effect that beats the null refit's
/// BIC and removes at least `min_gain` of its χ² (the acceptance rule, [`screened`]): on the
/// screening subset, or, for a near miss there and for a new kernel layout (whose blocks hold
/// other pixels), on every pixel ([`rescore_near_misses`]) when no candidate won on the subset;
/// a finer kernel grid last, on held-out pixels ([`decide_growth`]), when nothing else won.
fn search_round(data: &Data, current: &Fit, analysis: &Analysis, round: Round, opts: &DiagnoseOptions) -> (Vec<CandidateScore>, Option<(candidates::Candidate, Fit, f64)>) {
    let (proposed, times) = candidates::propose_timed(data, current, analysis, &round.excluded(opts), round.start_rule(), opts.progress);
    for t in times {
        progress_lap_as(opts, "proposal of ", t);
    }
    // one step per screening fit (the null refit, then each candidate), counted when done, so
    // the bar's rate and ETA are those of whole fits
    let bar = crate::estimate::progress_bar(opts.progress, proposed.len() as u64 + 1, "testing effects");
    let screen = |name: &'static str, corr: &model::Corrections, init: &Model| {
        let mut lap = crate::estimate::stage_clock();
        let mut f = fit::fit_subset(data, corr, init, opts.candidate_fit, opts.screen_pixels);
        f.inherit_dof(current);
        bar.inc(1);
        if opts.progress {
            bar.suspend(|| progress_lap_as(opts, "screening fit of ", lap(name)));
        }
        f
    };
    let null = screen("the null refit", &current.model.corrections, &current.model);
    let subset = null.share < 1.0;
    let mut scores = vec![CandidateScore { name: "(null refit)".into(), reduced_chi2: Some(null.reduced_chi2()), parameters: serde_json::Value::Null, delta_bic: Some(0.0), note: "the current model refitted with the candidates' budget".into() }];
    let mut best: Option<(candidates::Candidate, Fit, f64)> = None;
    let mut near: Vec<candidates::Candidate> = Vec::new();
    // deferred candidates with their provisional verdict, ΔBIC and entry in `scores`, and for
    // a gated misregistration ([`candidates::Deferred::GatedScale`]) the provisional candidate
    // itself with its screening fit, which stands where the search does not improve on it
    #[allow(clippy::type_complexity)]
    let mut provisional: Vec<(candidates::Candidate, Screened, f64, usize, Option<(candidates::Candidate, Fit)>)> = Vec::new();
    let on = if subset { " on the screening subset" } else { "" };
    let score = |name: &str, f: &Fit, dbic: f64, gain: f64| CandidateScore { name: name.to_string(), parameters: candidates::parameters_json(name, &f.model.corrections), reduced_chi2: Some(f.reduced_chi2()), delta_bic: Some(dbic), note: format!("removes {:.1}% of χ²{on}", 100.0 * gain) };
    // a screened candidate becomes the round's best (the lowest ΔBIC among winners) or a near miss
    let consider = |best: &mut Option<(candidates::Candidate, Fit, f64)>, near: &mut Vec<candidates::Candidate>, verdict: Screened, cand: candidates::Candidate, f: Fit, dbic: f64| match verdict {
        Screened::Winner if best.as_ref().map_or(true, |b| dbic < b.2) => *best = Some((cand, f, dbic)),
        Screened::NearMiss => near.push(cand),
        _ => {}
    };
    // a finer kernel grid is decided last, on held-out pixels ([`decide_growth`]), with its
    // entry in `scores` (a row of its own name: the layout step's row is `cand.name`'s)
    let mut growth: Option<(candidates::Candidate, usize)> = None;
    for cand in proposed {
        if candidates::grows_grid(&cand, current) {
            scores.push(unscreened(&cand, " (finer grid)", "a finer kernel grid: decided on held-out pixels, where no other candidate wins the round"));
            growth = Some((cand, scores.len() - 1));
            bar.inc(1);
            continue;
        }
        // a new kernel grid (`psf_field_variation`) cuts the image into other blocks, so a
        // subset would hold other pixels than the null refit's: it is not screened but decided
        // on every pixel, where no candidate wins on the subset (a screening fit would only
        // fill its row: 4.4 s a round at 1024×768)
        if subset && cand.corrections.psf_field_variation != current.model.corrections.psf_field_variation {
            scores.push(unscreened(&cand, "", "a new kernel grid, whose blocks hold other pixels than the null refit's: not screened, for a decision on every pixel"));
            near.push(cand);
            bar.inc(1);
            continue;
        }
        let f = screen(cand.name, &cand.corrections, cand.init.as_ref().unwrap_or(&current.model));
        let dbic = f.bic() - null.bic();
        let gain = chi2_gain(&null, &f);
        scores.push(score(cand.name, &f, dbic, gain));
        let mut verdict = screened(dbic, gain, opts.min_gain, subset);
        if verdict == Screened::Rejected && cand.init.is_some() && restarts_on_every_pixel(cand.name, gain, subset) {
            verdict = Screened::NearMiss;
            if let Some(row) = scores.last_mut() {
                row.note += &format!("; kernels re-estimated on the decoded captures, within {:.0}% of the null refit, whose kernels nearly interpolate the subset: decided on every pixel where nothing wins on the subset", 100.0 * RESTART_SLACK);
            }
        }
        if cand.deferred.is_some() {
            // decided below, against the round's best complete candidate
            let fallback = matches!(cand.deferred, Some(candidates::Deferred::GatedScale { .. })).then(|| (candidates::Candidate { deferred: None, ..cand.clone() }, f));
            provisional.push((cand, verdict, dbic, scores.len() - 1, fallback));
            continue;
        }
        consider(&mut best, &mut near, verdict, cand, f, dbic);
    }
    // a provisional candidate's deferred search runs only where its provisional score could
    // decide the round ([`in_contention`]); its completed candidate is screened again. The
    // strongest goes first ([`strongest_first`]), so that its completed score is the bar the
    // weaker ones must reach before their searches run
    strongest_first(&mut provisional, |p| p.2);
    for (cand, verdict, dbic, entry, fallback) in provisional {
        if !in_contention(verdict, dbic, best.as_ref().map(|b| b.2)) {
            scores[entry].note += "; its parameter search skipped: cannot decide the round";
            if opts.progress {
                eprintln!("{}: provisional ΔBIC {dbic:.0} ({verdict:?}) against the round's best {:?}: its parameter search skipped", cand.name, best.as_ref().map(|b| b.2.round()));
            }
            continue;
        }
        let mut lap = crate::estimate::stage_clock();
        let cand = candidates::complete(data, current, cand, opts.progress);
        progress_lap(opts, lap("deferred parameter search"));
        // a gated misregistration that kept its moved start is the provisional candidate: its
        // screening stands
        let fallback = match fallback {
            Some((before, f0)) if before.corrections == cand.corrections => {
                consider(&mut best, &mut near, verdict, before, f0, dbic);
                continue;
            }
            other => other,
        };
        let f = screen(cand.name, &cand.corrections, cand.init.as_ref().unwrap_or(&current.model));
        let (dbic2, gain) = (f.bic() - null.bic(), chi2_gain(&null, &f));
        if opts.progress {
            eprintln!("{}: provisional ΔBIC {dbic:.0}, after its parameter search {dbic2:.0}", cand.name);
        }
        // …and one whose re-estimated start screens no better keeps the provisional one
        if let Some((before, f0)) = fallback.filter(|_| dbic2 >= dbic) {
            if opts.progress {
                eprintln!("{}: the re-estimated start screens no better: the moved start kept", cand.name);
            }
            consider(&mut best, &mut near, verdict, before, f0, dbic);
            continue;
        }
        scores[entry] = score(cand.name, &f, dbic2, gain);
        consider(&mut best, &mut near, screened(dbic2, gain, opts.min_gain, subset), cand, f, dbic2);
    }
    bar.finish_and_clear();
    match &best {
        None if !near.is_empty() => {
            let mut lap = crate::estimate::stage_clock();
            best = rescore_near_misses(data, current, near, &mut scores, round, opts);
            progress_lap(opts, lap("near misses rescored on every pixel"));
        }
        // the near misses (and a new grid) wait for a later round, where they are proposed again
        Some((winner, _, _)) => {
            for cand in &near {
                if let Some(s) = scores.iter_mut().find(|s| s.name == cand.name) {
                    s.note += &format!("; not rescored: {} won the round on the subset", winner.name);
                }
            }
        }
        None => {}
    }
    if let Some((cand, entry)) = growth {
        match &best {
            None => {
                let mut lap = crate::estimate::stage_clock();
                best = decide_growth(data, current, cand, &mut scores[entry], opts);
                progress_lap(opts, lap("finer grid decided on held-out pixels"));
            }
            Some((winner, _, _)) => {
                let which = if winner.name == cand.name { " (its layout step)" } else { "" };
                scores[entry].note += &format!("; not decided: {}{which} won the round", winner.name);
            }
        }
    }
    (scores, best)
}

/// The score row of a candidate `search_round` does not screen (a new kernel layout, a finer
/// grid): its parameters, no figures until it is fitted, `note`; `suffix` follows its name.
fn unscreened(cand: &candidates::Candidate, suffix: &str, note: &str) -> CandidateScore {
    CandidateScore { name: format!("{}{suffix}", cand.name), parameters: candidates::parameters_json(cand.name, &cand.corrections), reduced_chi2: None, delta_bic: None, note: note.into() }
}

/// χ²'s own noise on `n` pixels, [`STOP_SIGMAS`]` · √(2n)`: what a change of χ² must exceed to
/// count (the stop rule, the final polish's convergence, the finer grid's held-out decision).
fn chi2_noise(n: f64) -> f64 {
    STOP_SIGMAS * (2.0 * n).sqrt()
}

/// A finer kernel grid ([`candidates::grows_grid`]) decided on held-out pixels: the current
/// model and the grown one each fitted from their own starts with the candidates' budget on
/// the 16-px checkerboard's colour 0 ([`fit::checker`]) of the fitted pixels (every pixel up to
/// [`DiagnoseOptions::fit_pixels`]; above it the kept blocks, which differ between the grids),
/// then χ² summed on colour 1 where both evaluate. The grid wins where it lowers that held-out
/// χ² by at least `min_gain` of it and by more than χ²'s own noise, [`STOP_SIGMAS`]` · √(2N)`. BIC's
/// nominal penalty (every kernel value times `ln N`) cannot decide it: a TV-regularised
/// kernel's values are far from free, so at 1024 × 768 the penalty rejects a 6 × 4 grid that
/// removes a fifth of χ² (docs/diagnosis.md, "The field case at camera size"); held-out
/// pixels charge a grid for what it fits of the noise, and only that. Both fits start from
/// kernels fitted on every pixel, which favours the current model: the rule errs towards
/// the coarser grid. The winner is fitted on every pixel; its ΔBIC, against the current model
/// (not a null refit of the same budget), is stated for information: the held-out pixels
/// decided the step, and its nominal penalty may make it positive where the grid wins. `row` is
/// the candidate's entry in the round's scores, its note the held-out figures.
fn decide_growth(data: &Data, current: &Fit, cand: candidates::Candidate, row: &mut CandidateScore, opts: &DiagnoseOptions) -> Option<(candidates::Candidate, Fit, f64)> {
    let init = cand.init.clone().unwrap_or_else(|| current.model.clone());
    let half = |corr: &model::Corrections, init: &Model| fit::fit_masked(data, corr, init, opts.candidate_fit, &|x, y| fit::checker(x, y) == 0, data.fit_pixels);
    let (coarse, fine) = (half(&current.model.corrections, &current.model), half(&cand.corrections, &init));
    let ([h0, h1], n) = fit::held_out_chi2([&coarse, &fine], 1);
    let (gain, tolerance) = ((h0 - h1) / h0.max(1e-300), chi2_noise(n));
    // written so that a NaN rejects
    let pass = gain >= opts.min_gain && h0 - h1 > tolerance && gain <= 1.0;
    let g = &current.model.grid;
    let grid = cand.corrections.psf_field_variation.map_or(String::new(), |f| format!("{}x{}", f.columns, f.rows));
    let text = format!("held out (a 16-px checkerboard, each grid fitted on the other colour): {}x{} tiles χ² {h0:.0}, {grid} {h1:.0} on {n:.0} pixels, {:.1}% lower (tolerance {tolerance:.0}){}", g.columns, g.rows, 100.0 * gain, if pass { "" } else { ", rejected" });
    if opts.progress {
        eprintln!("psf_field_variation (finer grid): {text}");
    }
    row.note = format!("a finer kernel grid, decided on held-out pixels: {text}");
    if !pass {
        return None;
    }
    drop((coarse, fine));
    let mut f = fit::fit(data, &cand.corrections, &init, opts.candidate_fit);
    f.inherit_dof(current);
    let dbic = f.bic() - current.bic();
    (row.reduced_chi2, row.delta_bic) = (Some(f.reduced_chi2()), Some(dbic));
    row.note += "; its figures on every pixel, ΔBIC against the current model (for information)";
    let cand = candidates::Candidate { evidence: format!("{}; {text}", cand.evidence), ..cand };
    Some((cand, f, dbic))
}

/// Whether a provisional candidate ([`candidates::Deferred`]) could decide its round, so that
/// its deferred parameter search must run: its provisional screening passes the acceptance
/// rule or is a near miss ([`screened`]), and either no complete candidate won the round
/// (`best` `None`) or its ΔBIC reaches [`CONTENTION`] of the best one's (both negative). The
/// search refines a start the screen already located (the radius within a factor 1.5, the
/// aberration blur added): on `pinhole_diffraction` at 1024×768 (seed 41) it took ΔBIC from
/// −2 263 714 to −4 107 681, a factor 1.8 (docs/notes/diagnosis-history.md, "Session 19"); a
/// candidate below a quarter of the best would need more than twice that.
fn in_contention(provisional: Screened, dbic: f64, best: Option<f64>) -> bool {
    provisional != Screened::Rejected && best.map_or(true, |b| dbic < CONTENTION * b)
}

/// The share of the round's best ΔBIC a provisional candidate must reach to have its search
/// run ([`in_contention`]).
const CONTENTION: f64 = 0.25;

/// Orders a round's provisional candidates by their provisional ΔBIC (`dbic`), the lowest (the
/// strongest) first, so that the deferred searches run in that order. A search only sharpens a
/// start the screen located ([`in_contention`]), so the strongest candidate's completed score
/// is the bar a weaker one must be within [`CONTENTION`] of. In the order proposed, the pair
/// misregistration + pinhole_diffraction at 1024×768 (seed 41) ran misregistration's scale
/// search first (no complete candidate had won, so it was in contention: 51.5 s, then a
/// screening fit), which took its ΔBIC from −2 239 420 to −2 520 139, while diffraction's went
/// from −9 493 224 to −9 985 445 and won the round (docs/notes/diagnosis-history.md, "Session 49").
/// Ties keep the proposal order.
fn strongest_first<T>(provisional: &mut [T], dbic: impl Fn(&T) -> f64) {
    provisional.sort_by(|a, b| dbic(a).total_cmp(&dbic(b)));
}

/// The share of the null refit's χ² (the noise law's term included) that `f` removes.
fn chi2_gain(null: &Fit, f: &Fit) -> f64 {
    let total = |f: &Fit| f.chi2() + f.noise_chi2;
    (total(null) - total(f)) / total(null).max(1e-300)
}

/// A screened candidate against the acceptance rule ([`screened`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Screened {
    /// Beats the null refit's BIC and removes at least `min_gain` of its χ².
    Winner,
    /// Beats the null refit's BIC and removes at least [`NEAR_MISS`]` · min_gain` of its χ² on
    /// a screening subset, but less than `min_gain`: scored again on every pixel.
    NearMiss,
    Rejected,
}

/// Subset gains down to this fraction of [`DiagnoseOptions::min_gain`] are scored again on every
/// pixel. The subset's gain of an effect whose χ² gain sits in a few regions depends on which
/// blocks the subset holds: `black_level` in the tone-curve case's second round (1024×768,
/// seed 41) removes 1.20 % of χ² on every pixel, and 0.62 %, 1.19 % and 2.05 % on three
/// block subsets (shares 0.17, 0.33, 0.09 of the pixels;
/// docs/notes/diagnosis-history.md, "Session 17").
pub const NEAR_MISS: f64 = 1.0 / 3.0;

/// The acceptance rule of a screened candidate, with `ΔBIC = BIC(candidate) − BIC(null refit)`
/// and `gain = (χ²_null − χ²_cand) / χ²_null` (both fits with the candidates' budget, χ² with
/// the noise law's term):
///
/// ```text
/// winner     ⇔  ΔBIC < 0  and  g_min ≤ gain ≤ 1
/// near miss  ⇔  ΔBIC < 0  and  g_min / 3 ≤ gain < g_min  and  the fits screened a subset
/// ```
///
/// A fit whose χ² is a finite non-negative sum cannot remove more than all of the null refit's,
/// so a gain above 1, or a ΔBIC or gain that is not a number, marks a broken fit and is rejected
/// whatever its ΔBIC (session 58: a candidate with a negative χ² sum under an experimental
/// restoration, docs/notes/diagnosis-history.md). A negative χ² that the noise law's term
/// outweighs is not caught here.
///
/// `g_min` is [`DiagnoseOptions::min_gain`]. `min_gain` is a fraction of the whole image's χ²;
/// a subset estimates it with a sampling error of its own, so a near miss is decided by the
/// same rule on every pixel ([`rescore_near_misses`]), except in a [`Round::Rotation`], where
/// the round's adoption rule decides. Without a subset (`subset` false) the
/// gain is the whole image's and a near miss is rejected.
fn screened(dbic: f64, gain: f64, min_gain: f64, subset: bool) -> Screened {
    // written so that a NaN rejects
    if !(dbic < 0.0 && gain <= 1.0) {
        Screened::Rejected
    } else if gain >= min_gain {
        Screened::Winner
    } else if subset && gain >= NEAR_MISS * min_gain {
        Screened::NearMiss
    } else {
        Screened::Rejected
    }
}

/// Whether a screened candidate the subset rejects is still decided on every pixel with the
/// near misses ([`rescore_near_misses`]): `tone_curve` whose start re-estimated every kernel
/// on the decoded captures (`candidates::linearised_estimate`; the caller checks that the
/// start exists), on a screening subset (`subset`), when it raises χ² by less than
/// [`RESTART_SLACK`] (`gain` above minus it, and not above 1: a broken fit). The null refit's
/// kernels start converged on every pixel and, on a subset of about 1.2 pixels per kernel
/// value (150 000 pixels per channel on 9 × 7 tiles of 45 px), take up a misfit the
/// re-estimated kernels have not learnt: on veiling glare + tone curve through the sf11 design
/// (1024×768, glare adopted) the null refit scores χ²/dof 1.247 on the subset against 1.850
/// on every pixel (seed 73, where the tone curve was a near miss at 0.8 % and removed 28.9 %
/// on every pixel); on seed 74 the tone curve read −1.0 % and −1.5 % on the subset, was never
/// decided, and removes 32.6 % on every pixel. Where the captures hold no tone curve the subset
/// rejects it by far more (χ² raised 34–2 580 % in the 1024×768 runs of sessions 63–64).
fn restarts_on_every_pixel(name: &str, gain: f64, subset: bool) -> bool {
    subset && name == "tone_curve" && gain > -RESTART_SLACK && gain <= 1.0
}

/// How much a re-estimated `tone_curve` may raise the subset's χ² and still be decided on every
/// pixel ([`restarts_on_every_pixel`]).
const RESTART_SLACK: f64 = 0.10;

/// The near misses of a round ([`Screened::NearMiss`]) refitted on every pixel with the
/// candidates' budget, against the null refit on every pixel (fitted once): the one with the
/// lowest ΔBIC among those that pass [`screened`] on every pixel wins (its whole-pixel fit is
/// the winner, polished as any other). In a [`Round::Rotation`] the near miss goes on to
/// [`adopt`] whatever its whole-pixel gain: there χ² cannot prefer the map (the kernels took it
/// up), and the round's own rule ([`rotation_round_adopts`], after the polish and, where needed,
/// convergence: [`needs_rotation_convergence`]) decides. Each near miss's note in `scores` gets
/// its whole-pixel gain; a row without figures (a new grid, not screened) gets the whole-pixel
/// fit's.
fn rescore_near_misses(data: &Data, current: &Fit, near: Vec<candidates::Candidate>, scores: &mut [CandidateScore], round: Round, opts: &DiagnoseOptions) -> Option<(candidates::Candidate, Fit, f64)> {
    let whole = |corr: &model::Corrections, init: &Model| {
        let mut f = fit::fit(data, corr, init, opts.candidate_fit);
        f.inherit_dof(current);
        f
    };
    let null = whole(&current.model.corrections, &current.model);
    let mut best: Option<(candidates::Candidate, Fit, f64)> = None;
    for cand in near {
        let f = whole(&cand.corrections, cand.init.as_ref().unwrap_or(&current.model));
        let (dbic, gain) = (f.bic() - null.bic(), chi2_gain(&null, &f));
        // a rotation round's candidate is judged by its adoption rule, after its polish
        let pass = round == Round::Rotation || screened(dbic, gain, opts.min_gain, false) == Screened::Winner;
        let outcome = match (round, pass) {
            (Round::Rotation, _) => "judged by the rotation round's adoption rule",
            (Round::Full, true) => "",
            (Round::Full, false) => "rejected",
        };
        let sep = if outcome.is_empty() { "" } else { ", " };
        if let Some(s) = scores.iter_mut().find(|s| s.name == cand.name) {
            if s.reduced_chi2.is_none() {
                (s.reduced_chi2, s.delta_bic, s.parameters) = (Some(f.reduced_chi2()), Some(dbic), candidates::parameters_json(cand.name, &f.model.corrections));
                s.note += "; its figures are on every pixel, against the null refit on every pixel";
            }
            s.note += &format!("; on every pixel: removes {:.1}% (ΔBIC {dbic:.0}){sep}{outcome}", 100.0 * gain);
        }
        if opts.progress {
            let sep = if outcome.is_empty() { "" } else { ": " };
            eprintln!("{} on every pixel: removes {:.2}% of χ² (ΔBIC {dbic:.0}){sep}{outcome}", cand.name, 100.0 * gain);
        }
        if pass && best.as_ref().map_or(true, |b| dbic < b.2) {
            best = Some((cand, f, dbic));
        }
    }
    best
}

/// "no mismatch", "explained: …" or "unexplained: …". The low-band test ([`low_band`]) is not
/// part of it: on clean 1024×768 data the base model's lowest band sits above its bound (2.28×
/// white noise against a floor of 1.70×, bound 2.01; docs/diagnosis.md), so a note there would
/// be a false alarm on every clean pair. It is reported beside the verdict ([`band_text`]).
fn verdict(effects: &[FoundEffect], current: &Fit, final_analysis: &Analysis, channels: &[String], opts: &DiagnoseOptions) -> String {
    let v = verdict_class(effects, current, final_analysis, opts);
    match untested_law_text(current, channels) {
        Some(t) if !v.starts_with("no mismatch") => format!("{v}; {t}"),
        _ => v,
    }
}

/// The verdict's note on the channels whose noise law the residual cannot test
/// ([`Fit::law_untested`]): which, and how much lost detail their residual holds.
fn untested_law_text(current: &Fit, channels: &[String]) -> Option<String> {
    if current.law_untested.is_empty() {
        return None;
    }
    let name = |c: usize| channels.get(c).cloned().unwrap_or_else(|| c.to_string());
    let list: Vec<String> = current.law_untested.iter().map(|&c| format!("{} ({:.2}×)", name(c), current.lost_detail.get(c).copied().unwrap_or(0.0))).collect();
    Some(format!(
        "the noise law is not tested in {}: there the stopped-down reference gives up detail worth that share of the wide-open noise in the residual's high-pass (bound {:.2}), which a noise curve from the residual reads as noise",
        list.join(", "),
        fit::LOST_DETAIL_LAW_BOUND
    ))
}

/// The low-band test's line for the report: measured power, floor, bound, and whether it is
/// above.
pub fn band_text(b: &LowBand) -> String {
    format!(
        "the residual's lowest band (up to {:.3} cycles/px) holds {:.2}× white noise's power where the noise floor puts {:.2}× (statistical bound {:.2}){}",
        b.top,
        b.power,
        b.floor,
        b.bound,
        if b.within() { ": within" } else { ": above — a smooth misfit that the χ² over every pixel averages away may remain (a test still being calibrated, not part of the verdict)" }
    )
}

/// The verdict's class (see [`verdict`]).
fn verdict_class(effects: &[FoundEffect], current: &Fit, final_analysis: &Analysis, opts: &DiagnoseOptions) -> String {
    // kernels that still rotate about the centre carry a misregistration they took up
    let rotation = kernel_rotation(current).filter(|_| !effects.iter().any(|e| e.name == "misregistration")).map(|c| rotation_text(&c));
    if effects.is_empty() && current.reduced_chi2() <= opts.consistent {
        if let Some(r) = rotation {
            return format!("unexplained: the base model fits to the noise floor (reduced χ² {:.3}), but {r}", current.reduced_chi2());
        }
        // the image model fits to the noise floor and no catalogue effect improved it; a noise
        // curve that departs from the Poisson–Gaussian law is reported, not called a mismatch
        let mut v = "no mismatch: the base model fits to the noise floor".to_string();
        if current.noise_misfit > opts.consistent_noise {
            v += &format!(" (the measured noise curve departs from a Poisson–Gaussian law by {:.0}%; no catalogue effect explains it)", 100.0 * current.noise_misfit);
        }
        v
    } else if consistent(current, opts) {
        let v = format!("explained: {} {} the fit to the noise floor", effects.iter().map(|e| e.name.as_str()).collect::<Vec<_>>().join(", "), if effects.len() == 1 { "brings" } else { "bring" });
        rotation.map_or(v.clone(), |r| format!("{v}; but {r}"))
    } else {
        let curvebits: Vec<String> = final_analysis
            .curves
            .iter()
            .filter(|c| c.msq_range() > 0.3 || c.mean_range() > 0.3)
            .map(|c| format!("{} (mean z spans {:.2}, z² spans {:.2})", c.name, c.mean_range(), c.msq_range()))
            .collect();
        let partial = if effects.is_empty() {
            String::new()
        } else {
            format!(" after {} (the catalogue's nearest effects; they do not reach the floor)", effects.iter().map(|e| e.name.as_str()).collect::<Vec<_>>().join(", "))
        };
        format!(
            "unexplained: {}{partial}; {}; residual depends on {}; excess kurtosis {:.2}",
            what_remains(current.reduced_chi2(), current.law_misfit(), opts),
            analysis::where_text(final_analysis),
            if curvebits.is_empty() { "no single variable".to_string() } else { curvebits.join(", ") },
            final_analysis.excess_kurtosis
        )
    }
}

/// The verdict's sentence on kernels that rotate ([`kernel_rotation`]) in a model without
/// misregistration.
fn rotation_text(c: &candidates::CentroidSimilarity) -> String {
    format!(
        "its kernels' centroids rotate by {:.3}° about the image centre (t = {:.0}; {:.1} px at the corners), which a lens's kernels do not: a misregistration the kernels take up, which a fit under the map did not confirm",
        c.p[1].to_degrees(),
        c.rotation_t(),
        c.rotation_corner_px
    )
}

/// What keeps a fit from being consistent with noise ([`consistent`]): the reduced χ² above its
/// bound, or, when χ² is within it, the noise curve's departure from a Poisson–Gaussian law
/// (which a χ² of 0.99 alone would not explain to the reader). `law_misfit`: [`Fit::law_misfit`]
/// (`None`: no channel's law tested, which the sentence says instead of a figure).
fn what_remains(reduced_chi2: f64, law_misfit: Option<f64>, opts: &DiagnoseOptions) -> String {
    let law = law_misfit.map_or("noise law not tested".to_string(), |m| format!("noise law misfit {:.0}%", 100.0 * m));
    match law_misfit {
        Some(m) if reduced_chi2 <= opts.consistent => format!(
            "the residual is at the noise floor (reduced χ² {reduced_chi2:.3}) but the measured noise curve departs from a Poisson–Gaussian law by {:.0}% (bound {:.0}%)",
            100.0 * m,
            100.0 * opts.consistent_noise
        ),
        _ => format!("reduced χ² {reduced_chi2:.3} remains ({law})"),
    }
}

/// The noise model of each channel, with the Poisson–Gaussian law on the final model's axis
/// (its transfer, shifted by its `black_level` pedestal, [`model::Corrections::black_offset`]) and on the linear
/// one.
fn noise_reports(data: &Data, current: &Fit, open: &Image, repeat_noise: bool) -> Vec<NoiseReport> {
    data.curves
        .iter()
        .enumerate()
        .map(|(c, curve)| {
            let pg = PoissonGaussian::fit_pedestal(curve, current.transfer, current.model.corrections.black_offset(c));
            let pl = PoissonGaussian::fit(curve, crate::image::Transfer::Linear);
            NoiseReport {
                channel: open.channels.get(c).cloned().unwrap_or_default(),
                a: pg.a,
                b: pg.b,
                misfit: pg.misfit,
                a_linear: pl.a,
                b_linear: pl.b,
                misfit_linear: pl.misfit,
                curve: curve.clone(),
                floor_rms: (current.var_channel[c] / current.n_channel[c].max(1) as f64).sqrt(),
                source: if repeat_noise { "repeated frames" } else { "residual" },
                lost_detail: current.lost_detail.get(c).copied().unwrap_or(0.0),
                law_tested: !current.law_untested.contains(&c),
            }
        })
        .collect()
}

/// The final model's kernels and corrections as a profile.
fn corrected_profile(base_profile: &Profile, current: &Fit, open: &Image, verdict: &str) -> Result<Profile, DiagnoseError> {
    let g = &current.model.grid;
    let mut out = base_profile.clone();
    out.grid = g.clone();
    out.meta.exposure_ratio = current.model.exposure.clone();
    out.meta.psf.columns = g.columns;
    out.meta.psf.rows = g.rows;
    out.meta.psf.centers = g.centers.clone();
    out.meta.psf.tile_size = Some(g.tile_size(open.width(), open.height()));
    out.meta.corrections = current.model.corrections.to_table()?;
    if let Some(t) = current.model.corrections.tone_curve {
        // the captures are encoded: `deblur` and `simulate` decode with the found curve
        out.meta.source.transfer = t.transfer;
    }
    out.meta.note = format!("refitted by `lensrig diagnose`: {verdict}");
    Ok(out)
}

/// Held-out χ²: the model is refitted on colour 0 of a 16-px checkerboard ([`fit::checker`])
/// and evaluated on colour 1 (half the pixels, a million at 1024×768 RGB: the other way round
/// added nothing the report reads but the same fit's cost again, 5.5 s there until session 66);
/// returns `(held-out reduced χ², in-sample reduced χ²)`, the held-out value `None` where
/// colour 1 holds no evaluated pixel (the report says it was not measured).
fn cross_validate(data: &Data, current: &Fit, settings: FitSettings, data_pixels: usize) -> (Option<f64>, f64) {
    let f = fit::fit_masked(data, &current.model.corrections, &current.model, settings, &|x, y| fit::checker(x, y) == 0, data_pixels);
    (held_out_reduced(fit::held_out_chi2([&f], 1)), current.reduced_chi2())
}

/// `χ²/n` of a held-out sum ([`fit::held_out_chi2`]); `None` without a held-out pixel or where
/// the ratio is not finite.
fn held_out_reduced(([chi2], n): ([f64; 1], f64)) -> Option<f64> {
    Some(chi2 / n).filter(|v| n > 0.0 && v.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::Plane;

    /// An inconsistent fit whose χ² is within bounds names the noise law's misfit, not a χ²
    /// that "remains"; one above the bound names the χ².
    #[test]
    fn a_consistent_fit_screens_misregistration_only_where_its_kernels_rotate() {
        assert_eq!(next_round_of(false, true, || false), Some(Round::Full));
        assert_eq!(next_round_of(false, false, || true), Some(Round::Full));
        assert_eq!(next_round_of(true, true, || true), Some(Round::Rotation));
        assert_eq!(next_round_of(true, true, || false), None);
        // misregistration in the model or excluded: the rotation is not even measured
        assert_eq!(next_round_of(true, false, || panic!("asked")), None);
        let opts = DiagnoseOptions { excluded: vec!["target_tilt".into()], ..DiagnoseOptions::default() };
        let excluded = Round::Rotation.excluded(&opts);
        assert!(proof::CONCEALED.iter().all(|n| excluded.iter().any(|e| e == n) == (*n != "misregistration")));
        assert_eq!(Round::Full.excluded(&opts), ["target_tilt"]);
        assert_eq!((Round::Full.start_rule(), Round::Rotation.start_rule()), (registered::StartRule::LikeForLike, registered::StartRule::BeatsCurrent));
    }

    #[test]
    fn a_rotation_round_adopts_an_equal_fit_whose_kernels_stop_rotating() {
        let sim = |rot_deg: f64, se_deg: f64| candidates::CentroidSimilarity::new([0.004, rot_deg.to_radians()], [1e-4, se_deg.to_radians()], 1024.0, 768.0);
        let (still, stopped, sub_pixel, tiny) = (sim(-0.37, 0.004), sim(0.001, 0.002), sim(0.05, 0.001), sim(0.02, 0.001));
        assert!(rotation_significant(&still) && !rotation_significant(&stopped));
        // t = 50 and 0.56 px at the corners: a real rotation, below the 1 px of before session 46
        // (the proof's misregistration seed 21 rotates the corners by 0.91 px at t = −23.9)
        assert!(rotation_significant(&sub_pixel));
        // t = 20 but 0.22 px at the corners: below the map's least displacement
        assert!(!rotation_significant(&tiny));
        // sf11 seed 42: +9 747 on χ² 2.12 M, noise 6 056: within 1 % of χ²
        let tol = rotation_tolerance(6056.0, 2_120_391.0, 0.01);
        assert!((tol - 21_203.91).abs() < 1e-6);
        assert_eq!(rotation_tolerance(6056.0, 100_000.0, 0.01), 6056.0);
        assert!(rotation_round_adopts(-9747.0, tol, Some(&stopped)));
        assert!(!rotation_round_adopts(-0.028 * 2_120_391.0, tol, Some(&stopped)), "the pair's −2.8 %");
        assert!(rotation_round_adopts(-2000.0, 6000.0, Some(&stopped)), "as good a fit within noise");
        assert!(rotation_round_adopts(2000.0, 6000.0, None), "no similarity to measure: nothing rotates");
        assert!(!rotation_round_adopts(-7000.0, 6000.0, Some(&stopped)), "a worse fit");
        assert!(!rotation_round_adopts(50_000.0, 6000.0, Some(&still)), "kernels still rotate");
    }

    /// A rotation round's winner refused on χ² alone, with kernels that stopped rotating, is
    /// converged before the rule is asked again; one whose kernels still rotate, and the
    /// unthinned proof cases, are not.
    #[test]
    fn a_rotation_winner_refused_on_chi2_alone_is_converged_first() {
        let sim = |rot_deg: f64, se_deg: f64| candidates::CentroidSimilarity::new([0.004, rot_deg.to_radians()], [1e-4, se_deg.to_radians()], 1024.0, 768.0);
        let (still, stopped) = (sim(-0.37, 0.004), sim(0.001, 0.002));
        let tol = rotation_tolerance(6056.0, 2_120_391.0, 0.01);
        // the pair misregistration + diffraction at 1024×768: −13.1 % on every pixel
        let pair = -0.131 * 2_120_391.0;
        assert!(!rotation_round_adopts(pair, tol, Some(&stopped)));
        assert!(needs_rotation_convergence(pair, tol, Some(&stopped), true));
        assert!(!needs_rotation_convergence(pair, tol, Some(&stopped), false), "the proof cases keep their rule");
        assert!(!needs_rotation_convergence(pair, tol, Some(&still), true), "kernels that still rotate");
        assert!(!needs_rotation_convergence(-9747.0, tol, Some(&stopped), true), "within the tolerance");
        assert!(needs_rotation_convergence(-tol, tol, None, true), "at the tolerance: refused on χ²");
    }

    /// `adopt` in a rotation round, where the subset thins the data: a winner whose polish
    /// leaves it more than the tolerance above a current model fitted longer on every pixel
    /// (here the same model, so nothing but iterations separates them) is refused by the rule
    /// as polished, then converged on every pixel and adopted, and the adopted effect states the
    /// converged model and a ΔBIC on every pixel.
    #[test]
    fn a_rotation_winner_short_of_iterations_is_converged_and_adopted() {
        let (mut data, init, corr, thinned) = thinned_case();
        let current = fit::fit(&data, &corr, &init, FitSettings { rounds: 6, kernel_iterations: 20 });
        // a short polish, so that one leaves the winner short of its iterations
        let thinned = DiagnoseOptions { base_fit: FitSettings { rounds: 1, kernel_iterations: 10 }, ..thinned };
        // the winner starts from point kernels: far from the blur, as kernels re-estimated
        // under a map start far from the converged ones
        let mut point = init.clone();
        for plane in point.grid.kernels.iter_mut().flatten() {
            plane.data.iter_mut().for_each(|v| *v = 0.0);
            let k = point.grid.kernel_size;
            plane.data[k * k / 2] = 1.0;
        }
        let winner = fit::fit(&data, &corr, &point, FitSettings { rounds: 0, kernel_iterations: 0 });
        // the rule on the polished winner alone refuses it
        let polished = rescore(&data, &polish_winner(&data, &current, winner.clone(), "misregistration", &thinned));
        let noise = chi2_noise(current.n() as f64);
        let tolerance = rotation_tolerance(noise, current.chi2(), thinned.min_gain);
        let lowered = current.chi2() - polished.chi2();
        assert!(!rotation_round_adopts(lowered, tolerance, candidates::centroid_similarity_fit(&polished).as_ref()), "polished {} current {} tolerance {tolerance}", polished.chi2(), current.chi2());
        assert!(needs_rotation_convergence(lowered, tolerance, candidates::centroid_similarity_fit(&polished).as_ref(), true));
        let cand = candidates::Candidate { name: "misregistration", corrections: corr.clone(), evidence: "test".into(), location: String::new(), init: None, deferred: None };
        let mut s = Search { analysis: analyse(&current), current, effects: Vec::new(), rounds: Vec::new(), polished: false, converged: false, last_found: None };
        let current_chi2 = s.current.chi2();
        assert!(adopt(&mut data, &mut s, (cand, winner, -1.0), true, Round::Rotation, &thinned));
        let e = &s.effects[0];
        assert_eq!(e.name, "misregistration");
        assert!(e.evidence.contains("converged on every pixel"), "{}", e.evidence);
        assert!(e.after.chi2 < polished.chi2() && e.after.chi2 - current_chi2 < tolerance, "after {} polished {} current {current_chi2}", e.after.chi2, polished.chi2());
        assert!((e.delta_bic - (e.after.bic - e.before.bic)).abs() < 1e-6 * e.after.bic.abs(), "ΔBIC {} on every pixel {}", e.delta_bic, e.after.bic - e.before.bic);
    }

    #[test]
    fn what_remains_names_the_failed_test() {
        let o = DiagnoseOptions::default();
        let law = what_remains(0.994, Some(0.18), &o);
        assert!(law.contains("noise floor") && law.contains("18%") && !law.contains("remains"), "{law}");
        let chi = what_remains(1.319, Some(0.05), &o);
        assert!(chi.starts_with("reduced χ² 1.319 remains (noise law misfit 5%)"), "{chi}");
        // no channel's law tested (a restored reference's lost detail in every channel): no
        // figure that nothing measured
        let untested = what_remains(1.319, None, &o);
        assert!(untested.starts_with("reduced χ² 1.319 remains (noise law not tested)") && !untested.contains('%'), "{untested}");
    }

    /// The acceptance rule: the tone-curve case's second round at 1024×768 (seed 41), where
    /// `black_level` removed 0.62 % of χ² on the screening subset and 1.20 % on every pixel.
    /// The old rule (`ΔBIC < 0` and gain ≥ `min_gain` on the subset alone) rejected it; the
    /// near miss is now scored on every pixel, where it wins. Below a third of `min_gain`, or
    /// without a subset, it is rejected; a ΔBIC ≥ 0 is never accepted, nor a gain above 1 or a
    /// figure that is not a number.
    #[test]
    fn a_near_miss_on_the_subset_is_judged_on_every_pixel() {
        let g = DiagnoseOptions::default().min_gain;
        assert_eq!(screened(-11_269.0, 0.00616, g, true), Screened::NearMiss);
        assert_eq!(screened(-27_363.0, 0.01195, g, false), Screened::Winner);
        assert_eq!(screened(-250_443.0, 0.057, g, true), Screened::Winner);
        assert_eq!(screened(-11_269.0, 0.00616, g, false), Screened::Rejected);
        assert_eq!(screened(-94.0, 0.00007, g, true), Screened::Rejected);
        assert_eq!(screened(-500.0, 0.3 * g, g, true), Screened::Rejected);
        assert_eq!(screened(34_493.0, 0.02, g, true), Screened::Rejected);
        assert_eq!(screened(-1.0, NEAR_MISS * g, g, true), Screened::NearMiss);
        // a fit that removes more than all of χ² (a negative χ² sum) or scores no number
        assert_eq!(screened(-8.9e11, 1.0 + 1e-9, g, true), Screened::Rejected);
        assert_eq!(screened(f64::NAN, 0.5, g, false), Screened::Rejected);
        assert_eq!(screened(-1e6, f64::NAN, g, false), Screened::Rejected);
        assert_eq!(screened(-1e6, 1.0, g, false), Screened::Winner);
    }

    /// A re-estimated tone curve the subset rejects is still decided on every pixel when it
    /// raises the subset's χ² by less than [`RESTART_SLACK`]: the figures of veiling glare +
    /// tone curve through sf11 at 1024×768 (seed 74, glare adopted: −1.0 % and −1.5 %), not
    /// those of the runs without a tone curve (χ² raised 34 % and more); not without a subset,
    /// and no other effect.
    #[test]
    fn a_re_estimated_tone_curve_close_on_the_subset_is_decided_on_every_pixel() {
        assert!(restarts_on_every_pixel("tone_curve", -0.010, true));
        assert!(restarts_on_every_pixel("tone_curve", -0.015, true));
        assert!(!restarts_on_every_pixel("tone_curve", -0.34, true));
        assert!(!restarts_on_every_pixel("tone_curve", -0.015, false), "without a subset the gain is the whole image's");
        assert!(!restarts_on_every_pixel("vignetting", -0.015, true));
        assert!(!restarts_on_every_pixel("tone_curve", f64::NAN, true), "a figure that is not a number");
        assert!(!restarts_on_every_pixel("tone_curve", 1.5, true), "a broken fit (more than all of χ² removed)");
        assert!(!restarts_on_every_pixel("tone_curve", -RESTART_SLACK, true), "the slack is exclusive");
    }

    /// A provisional candidate's parameter search (the Airy radius's golden sections of
    /// converged fits) runs only where its provisional score could decide the round:
    /// vignetting seed 42 at 1024×768, where `pinhole_diffraction` removes 10.5 % of χ² against
    /// vignetting's 83.8 %, skips it (486 CPU-s before).
    #[test]
    fn a_deferred_search_runs_only_where_the_candidate_could_win() {
        assert!(!in_contention(Screened::Winner, -1.67e6, Some(-1.3e7)), "far behind the round's best");
        assert!(!in_contention(Screened::Winner, -2.6e6, Some(-1.3e7)), "a fifth of the best");
        assert!(in_contention(Screened::Winner, -4.0e6, Some(-1.3e7)), "within reach of the best");
        assert!(in_contention(Screened::Winner, -2.0e7, Some(-1.3e7)), "ahead of the best");
        assert!(in_contention(Screened::Winner, -1.0e3, None), "no complete candidate won");
        assert!(in_contention(Screened::NearMiss, -1.0e3, None), "a near miss with no winner");
        assert!(!in_contention(Screened::NearMiss, -1.0e3, Some(-1.3e7)));
        assert!(!in_contention(Screened::Rejected, 5.0, None), "rejected even before its search");
    }

    /// The deferred searches run strongest first ([`strongest_first`]): with the figures of the
    /// pair misregistration + pinhole_diffraction at 1024×768 (seed 41, round 1; no complete
    /// candidate won), misregistration, proposed first, is in contention only as long as
    /// diffraction's search has not run; after it (−9 985 445) it is not, so its search is
    /// skipped. Equal ΔBICs keep the order proposed.
    #[test]
    fn the_strongest_provisional_candidate_is_searched_first() {
        let mut provisional = vec![("misregistration", -2_239_420.0), ("pinhole_diffraction", -9_493_224.0)];
        strongest_first(&mut provisional, |p| p.1);
        assert_eq!(provisional.iter().map(|p| p.0).collect::<Vec<_>>(), ["pinhole_diffraction", "misregistration"]);
        let best_after_search = Some(-9_985_445.0);
        assert!(!in_contention(Screened::Winner, provisional[1].1, best_after_search), "behind the completed diffraction: no search");
        let mut tie = vec![("misregistration", -1.0e6), ("pinhole_diffraction", -1.0e6)];
        strongest_first(&mut tie, |p| p.1);
        assert_eq!(tie[0].0, "misregistration", "a tie keeps the order proposed");
    }

    /// The base stage's budgets ([`base_budget`]): where the subset screens, the provisional
    /// fit runs one round fewer than the base budget (the refit, continuing the provisional
    /// fit's momentum, is the last) and its probe one round ([`probe_budget`]); elsewhere the
    /// base budget for both, then one round.
    #[test]
    fn the_base_stage_drops_a_provisional_round_only_where_the_subset_screens() {
        let base = FitSettings { rounds: 3, kernel_iterations: 80 };
        let (two, one) = (FitSettings { rounds: 2, kernel_iterations: 80 }, FitSettings { rounds: 1, kernel_iterations: 80 });
        assert_eq!(base_budget(true, base), (two, one, one));
        assert_eq!(base_budget(false, base), (base, base, one));
        assert_eq!((probe_budget(true, base), probe_budget(false, base)), (one, base));
        let single = FitSettings { rounds: 1, kernel_iterations: 40 };
        assert_eq!(base_budget(true, single), (single, single, single), "at least one provisional round");
    }

    /// The final polish runs only where the model changed since the last adoption's polish or
    /// is not yet consistent: not right after an adoption that left it consistent (the
    /// winner's polish and the final polish would run back to back on the same model), after
    /// backward elimination, after an adoption that left it above the noise (the tone curve at
    /// 1024×768: 1.24× the floor without the final polish), never without an effect.
    #[test]
    fn final_polish_only_where_the_model_changed_or_is_not_consistent() {
        assert!(!needs_final_polish(1, true, true, false), "the adopted winner is polished and consistent");
        assert!(!needs_final_polish(2, true, true, false));
        assert!(needs_final_polish(1, true, false, false), "polished but not consistent yet");
        assert!(!needs_final_polish(1, true, false, true), "not consistent, but already converged");
        assert!(needs_final_polish(1, false, true, false), "backward elimination changed the model");
        assert!(!needs_final_polish(0, false, false, false), "no effect: the base model is final");
    }

    /// Where the screening subset thins the data, the final polish runs whole-pixel rounds from
    /// the current model and never ends above it. The two subset rounds it ran first until
    /// session 52 fit the kernels on ≈ 1.6 pixels per value here (the 1024×768 cases: ≈ 2) and
    /// raise the whole-pixel χ² of a model fitted on every pixel; the same whole-pixel rounds
    /// after them end higher than from the current model (1024×768 misregistration seed 41:
    /// 2 102 013 against 2 096 233, docs/diagnosis.md "Adoption, the stop rule and the polishes").
    /// The small clean case with options whose screening subset thins it (one pixel in eight)
    /// and a short base budget.
    fn thinned_case() -> (Data<'static>, Model, model::Corrections, DiagnoseOptions) {
        let (data, init) = fit::tests::small_case();
        let (w, h) = (data.open.width(), data.open.height());
        let opts = DiagnoseOptions { screen_pixels: w * h / 8, base_fit: FitSettings { rounds: 3, kernel_iterations: 20 }, ..DiagnoseOptions::default() };
        assert!(screens(&data, &opts));
        (data, init, model::Corrections::default(), opts)
    }

    #[test]
    fn the_thinned_final_polish_starts_from_the_current_model() {
        let (data, init, corr, opts) = thinned_case();
        let current = fit::fit(&data, &corr, &init, FitSettings { rounds: 3, kernel_iterations: 20 });
        let polished = final_polish(&data, &current, &opts, "final polish");
        assert!(polished.chi2() <= current.chi2(), "polished {} current {}", polished.chi2(), current.chi2());
        let settings = FitSettings { rounds: 2, kernel_iterations: 2 * opts.base_fit.kernel_iterations };
        let subset = fit::fit_subset_from(&data, &corr, &current.model, settings, opts.screen_pixels, &current.warm);
        let whole = rescore(&data, &subset);
        // the former path: the same whole-pixel rounds, after the subset rounds
        let (former, _) = fit::fit_converging(&data, &subset.model.corrections, &subset.model, final_polish_rule(current.n(), &opts), Some(&subset.warm));
        eprintln!("χ² on every pixel: current {:.1}, after two subset rounds {:.1}, polished {:.1}, the former polish {:.1}", current.chi2(), whole.chi2(), polished.chi2(), former.chi2());
        assert!(whole.chi2() > current.chi2(), "two subset rounds raise the whole-pixel χ²: {} vs {}", whole.chi2(), current.chi2());
        assert!(polished.chi2() < former.chi2(), "from the current model the polish ends lower: {} vs {}", polished.chi2(), former.chi2());
    }

    /// A gain winner's polish skips the subset rounds where the subset thins the data: its
    /// kernels start from the current model's, and rounds on the subset fit them to the
    /// subset's noise, which the whole-pixel round that follows does not undo. (The data are
    /// clean, so no polish of the gain gets below the current model's χ²: what is compared is
    /// the two polishes.)
    #[test]
    fn a_gain_winners_polish_runs_on_every_pixel_only() {
        let (data, init, corr, opts) = thinned_case();
        let current = fit::fit(&data, &corr, &init, FitSettings { rounds: 3, kernel_iterations: 20 });
        let gain = model::Corrections { vignetting: Some(model::VignettingCorrection { k1: 0.0, k2: 0.0, k3: 0.0 }), ..corr.clone() };
        // the screening fit as `search_round` runs it: from the current model, a fresh solver
        let winner = fit::fit_subset(&data, &gain, &current.model, opts.candidate_fit, opts.screen_pixels);
        let polished = polish_winner(&data, &current, winner.clone(), "vignetting", &opts);
        // the former path: the base budget's rounds on the subset (kept where they lower the
        // subset's χ²), then the same whole-pixel round
        let sub = fit::fit_subset_from(&data, &winner.model.corrections, &winner.model, opts.base_fit, opts.screen_pixels, &winner.warm);
        let start = if sub.chi2() <= winner.chi2() { &sub } else { &winner };
        let whole_round = FitSettings { rounds: 1, kernel_iterations: opts.base_fit.kernel_iterations };
        let former = fit::fit_from(&data, &start.model.corrections, &start.model, whole_round, &start.warm);
        let after_subset = rescore(&data, start);
        eprintln!("χ² on every pixel: current {:.1}, winner after the subset rounds {:.1}, polished {:.1}, the former polish {:.1}", current.chi2(), after_subset.chi2(), polished.chi2(), former.chi2());
        assert!(after_subset.chi2() > current.chi2(), "the subset rounds raise the whole-pixel χ²: {} vs {}", after_subset.chi2(), current.chi2());
        assert!(polished.chi2() < former.chi2(), "without them the polish ends lower: {} vs {}", polished.chi2(), former.chi2());
        // a winner that changes the kernel operator keeps its subset rounds
        let moved = polish_winner(&data, &current, winner.clone(), "misregistration", &opts);
        assert_eq!(moved.chi2().to_bits(), former.chi2().to_bits());
    }

    /// The cross-validation scores the half of the checkerboard the refit did not see: kernels
    /// fitted to one half take up that half's noise, so the held-out reduced χ² lies above the
    /// in-sample one of the model fitted on every pixel. Without a held-out pixel (or with a
    /// sum that is not finite) it is not measured, not a number.
    #[test]
    fn the_cross_validation_scores_the_held_out_half() {
        assert_eq!(held_out_reduced(([0.0], 0.0)), None);
        assert_eq!(held_out_reduced(([f64::NAN], 10.0)), None);
        assert_eq!(held_out_reduced(([15.0], 10.0)), Some(1.5));
        let (data, init, corr, opts) = thinned_case();
        let current = fit::fit(&data, &corr, &init, FitSettings { rounds: 3, kernel_iterations: 20 });
        let (held_out, in_sample) = cross_validate(&data, &current, opts.candidate_fit, opts.screen_pixels);
        let held_out = held_out.expect("both colours of the checkerboard hold evaluated pixels");
        eprintln!("reduced χ²: held out {held_out:.4}, in sample {in_sample:.4}");
        assert!(held_out.is_finite() && held_out > in_sample, "held out {held_out}, in sample {in_sample}");
    }

    /// An adopted model that is not consistent is converged on every pixel before the next
    /// round is decided, where the subset thins the data and only after a full round; the
    /// converged model is the current one, its "after" figures are the adopted effect's, and no
    /// final polish follows unless the model changes again.
    #[test]
    fn an_inconsistent_adopted_model_is_converged_before_the_next_round() {
        let (data, init, corr, thinned) = thinned_case();
        // an under-fitted model: one short round, far from the noise floor
        let current = fit::fit(&data, &corr, &init, FitSettings { rounds: 1, kernel_iterations: 5 });
        assert!(!consistent(&current, &thinned), "reduced χ² {}", current.reduced_chi2());
        let figures = Figures::of(&current);
        let found = FoundEffect { name: "vignetting".into(), evidence: String::new(), location: String::new(), parameters: serde_json::Value::Null, before: figures.clone(), after: figures, delta_bic: -1.0 };
        let search = |f: &Fit| Search { current: f.clone(), analysis: analyse(f), effects: vec![found.clone()], rounds: vec![], polished: true, converged: false, last_found: None };
        // a converged search whose model is replaced (an adoption, backward elimination) is
        // converged no longer
        let mut r = search(&current);
        r.converged = true;
        r.replace(current.clone(), true);
        assert!(!r.converged && r.polished);
        r.converged = true;
        r.replace(current.clone(), false);
        assert!(!r.converged && !r.polished);
        let chi2 = current.chi2();
        // a model the thinned full round leaves alone: consistent by the bounds it is judged on
        let lenient = DiagnoseOptions { consistent: current.reduced_chi2() + 1.0, consistent_noise: f64::INFINITY, ..thinned.clone() };
        for (round, opts, moves) in [(Round::Full, &thinned, true), (Round::Rotation, &thinned, false), (Round::Full, &DiagnoseOptions::default(), false), (Round::Full, &lenient, false)] {
            let mut s = search(&current);
            converge_before_screening(&data, &mut s, round, opts);
            assert_eq!(s.converged, moves, "{round:?}");
            if moves {
                assert!(s.current.chi2() < chi2 - 3.0 * (2.0 * s.current.n() as f64).sqrt(), "χ² {} → {}", chi2, s.current.chi2());
                assert_eq!(s.effects[0].after.chi2, s.current.chi2(), "the effect's after is the converged model");
                // judged on the bounds the model failed, the flag alone spares it the final polish
                assert!(!needs_final_polish(s.effects.len(), s.polished, false, s.converged));
                assert!(needs_final_polish(s.effects.len(), s.polished, false, false));
            } else {
                assert_eq!(s.current.chi2(), chi2);
            }
        }
    }

    /// A finer grid is decided on held-out pixels ([`decide_growth`]), from the base model on
    /// the proof's 3 × 2 profile (as where its layout step lost the round): on the field case
    /// (seed 21: the lens varies on a 9 × 7 grid) the 6 × 4 grid lowers the held-out χ² by more
    /// than `min_gain` and wins, fitted on every pixel (98 774 → 20 007 on 21 538 held-out
    /// pixels); on clean data (the same seed) it raises it
    /// (22 365 → 24 489): the finer grid fits noise. The score's note states both χ².
    #[test]
    fn a_finer_grid_is_decided_on_held_out_pixels() {
        let spec = proof::CaseSpec::default();
        let opts = bench::proof_options(&spec);
        for (effect, wins) in [(Some("psf_field_variation"), true), (None, false)] {
            let case = proof::render_case(effect, 21, &spec).expect("renders");
            let est = estimate(&case.open.image, &case.pinhole.image, &EstimateOptions { saturation: f32::INFINITY, ..opts.estimate.clone() }).expect("estimates");
            let (data, current, _) = base_model(&case.open.image, &case.pinhole.image, &est.profile, &opts);
            assert_eq!((current.model.grid.columns, current.model.grid.rows), (3, 2));
            let grown = model::Corrections { psf_field_variation: Some(model::FieldCorrection { columns: 6, rows: 4 }), ..model::Corrections::default() };
            let cand = candidates::Candidate { name: "psf_field_variation", corrections: grown, evidence: String::new(), location: String::new(), init: None, deferred: None };
            let mut row = CandidateScore { name: "psf_field_variation (finer grid)".into(), reduced_chi2: None, parameters: serde_json::Value::Null, delta_bic: None, note: String::new() };
            let got = decide_growth(&data, &current, cand, &mut row, &opts);
            let note = &row.note;
            eprintln!("{effect:?}: {note}");
            assert_eq!(got.is_some(), wins, "{effect:?}: {note}");
            assert!(note.contains("3x2 tiles χ²") && note.contains("6x4") && note.contains("rejected") != wins, "{note}");
            // the row holds the winner's whole-pixel figures, a loser's none
            assert_eq!(row.reduced_chi2.is_some(), wins);
            if let Some((c, f, dbic)) = got {
                assert_eq!((f.model.grid.columns, f.model.grid.rows), (6, 4));
                assert!(c.evidence.contains("held out") && f.chi2() < current.chi2(), "{}", c.evidence);
                assert_eq!((row.reduced_chi2, row.delta_bic), (Some(f.reduced_chi2()), Some(dbic)));
            }
        }
    }

    /// Backward elimination scores a model without an effect at its best glare width
    /// (`prune`): on the 256×192 glare case (seed 21), a model holding the halo at four times
    /// its rendered width and a vignetting (the sf11 pair's end state, 303 px and a vignetting
    /// against 76 px and none) loses the vignetting, and the refit without it holds a width
    /// within a factor 2 of the rendered one (31.1 px against 22.6; the start is 4×). Without
    /// the width search no effect is found redundant.
    #[test]
    fn backward_elimination_searches_the_glare_width_again() {
        let spec = proof::CaseSpec::default();
        let opts = bench::proof_options(&spec);
        let case = proof::render_case(Some("veiling_glare"), 21, &spec).expect("renders");
        let est = estimate(&case.open.image, &case.pinhole.image, &EstimateOptions { saturation: f32::INFINITY, ..opts.estimate.clone() }).expect("estimates");
        let (data, base, _) = base_model(&case.open.image, &case.pinhole.image, &est.profile, &opts);
        let truth = case.truth["sigma_px"].as_f64().expect("a rendered width");
        let wide = model::GlareCorrection { fraction: case.truth["fraction"].as_f64().unwrap(), sigma_px: 4.0 * truth };
        let corr = model::Corrections { veiling_glare: Some(wide), vignetting: Some(model::VignettingCorrection { k1: 0.0, k2: 0.0, k3: 0.0 }), ..model::Corrections::default() };
        let mut current = fit::fit(&data, &corr, &base.model, opts.base_fit);
        current.inherit_dof(&base);
        let (name, f) = prune::weakest_redundant(&data, &current, &opts).expect("an effect is redundant");
        let sigma = f.model.corrections.veiling_glare.expect("the glare stays").sigma_px;
        eprintln!("removed {name}; width {sigma:.1} px, rendered {truth:.1}, start {:.1}", wide.sigma_px);
        assert_eq!(name, "vignetting");
        assert!((sigma / truth).ln().abs() < 4.0f64.ln() * 0.5, "width {sigma:.1} against {truth:.1} rendered");
    }

    /// A Gaussian kernel of standard deviation `sigma` (px), `±3σ`, summing to 1.
    fn gaussian_kernel(sigma: f64) -> Plane {
        let r = (3.0 * sigma).ceil() as usize;
        let k = 2 * r + 1;
        let mut p = Plane::from_fn(k, k, |x, y| (-((x as f64 - r as f64).powi(2) + (y as f64 - r as f64).powi(2)) / (2.0 * sigma * sigma)).exp() as f32);
        let s = p.sum() as f32;
        p.scale(1.0 / s);
        p
    }

    /// `p` convolved with `k` (odd size), periodic boundary: stationary noise stays stationary.
    fn convolve_periodic(p: &Plane, k: &Plane) -> Plane {
        let (w, h, r) = (p.width as isize, p.height as isize, (k.width / 2) as isize);
        Plane::from_fn(p.width, p.height, |x, y| {
            let mut acc = 0.0f32;
            for j in -r..=r {
                for i in -r..=r {
                    let (xx, yy) = ((x as isize - i).rem_euclid(w), (y as isize - j).rem_euclid(h));
                    acc += k.data[((j + r) * k.width as isize + i + r) as usize] * p.data[(yy * w + xx) as usize];
                }
            }
            acc
        })
    }

    /// The low-band test on a 256 × 192 normalised residual: the floor's own colour (a
    /// reference's noise through a wide kernel, which puts far more than white noise's power
    /// into the lowest band) stays within the bound when the floor counts it
    /// ([`analysis::band_gain`]) and is flagged when it does not; a smooth misfit that adds
    /// only 2 % to χ² (within the χ² test's slack) is flagged.
    #[test]
    fn low_band_test_flags_a_smooth_misfit_and_not_the_coloured_floor() {
        let (w, h) = (256, 192);
        let mut rng = crate::rng::Rng::new(17);
        let white = |rng: &mut crate::rng::Rng| Plane::from_fn(w, h, |_, _| rng.normal() as f32);
        let k = gaussian_kernel(4.0);
        let k2: f64 = k.data.iter().map(|v| (*v as f64).powi(2)).sum();
        // z = (n_open + K * n_ref) / √(1 + ΣK²): unit variance, coloured at low frequencies
        let (n1, n2) = (white(&mut rng), white(&mut rng));
        let through = convolve_periodic(&n2, &k);
        let norm = (1.0 + k2).sqrt() as f32;
        let z = Plane::from_fn(w, h, |x, y| (n1.get(x, y) + through.get(x, y)) / norm);
        let mask = vec![true; w * h];
        let power = analysis::radial_spectrum(&z, &mask, 16)[0].1;
        let floor = (1.0 + analysis::band_gain(&k, &analysis::low_band_bins(w, h))) / (1.0 + k2);
        assert!(floor > 1.5, "the coloured floor puts {floor:.2}× white noise's power into the low band");
        let counted = low_band_of(power, floor, [w, h, 1], 1.0, 1.10).unwrap();
        assert!(counted.within(), "{counted:?}");
        assert!((power / floor - 1.0).abs() < 4.0 / counted.samples.sqrt(), "measured {power:.3} against the floor {floor:.3}");
        let white_floor = low_band_of(power, 1.0, [w, h, 1], 1.0, 1.10).unwrap();
        assert!(!white_floor.within(), "{white_floor:?}");
        // a smooth misfit: a slow cosine holding 2 % of the variance
        let a = (2.0f64 * 0.02).sqrt() as f32;
        let halo = Plane::from_fn(w, h, |x, y| z.get(x, y) + a * (std::f32::consts::TAU * (2.0 * x as f32 / w as f32 + 1.0 * y as f32 / h as f32)).cos());
        let msq = |p: &Plane| p.data.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / (w * h) as f64;
        assert!(msq(&halo) < 1.10, "the misfit is within the χ² test's slack: {:.3}", msq(&halo));
        let p2 = analysis::radial_spectrum(&halo, &mask, 16)[0].1;
        let flagged = low_band_of(p2, floor, [w, h, 1], 1.0, 1.10).unwrap();
        assert!(!flagged.within(), "{flagged:?}");
    }
}
