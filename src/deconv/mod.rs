//! Cross-channel deconvolution with spatially varying PSFs (Heide et al. 2013, Sec. 5;
//! docs/method.md §1–§5): the restoration behind `lensrig deblur`.
//!
//! # Pipeline
//! 0. Noise ([`DeconvOptions::noise`], docs/method.md §9): with a Poisson–Gaussian law
//!    (`Var = g_c x + r_c²`, from the profile or `--noise`) `σ_c² = g_c mean(x) + r_c²` and each
//!    tile's `λ` uses the tile's mean level; the photo's own estimate is checked against it
//!    (warning beyond 2×). Without a law, as below.
//! 1. Per channel, the noise level `σ_c` of the (linear) input is estimated ([`noise`]) and the
//!    prior weight defaults to `λ_c = κ σ_c²` (MAP scaling of an ℓ2² data term against a
//!    Laplacian gradient prior; κ = 7). When the result is delivered gamma-encoded
//!    ([`DeconvOptions::output_transfer`], set by the CLI), every ℓ1 term is further weighted per
//!    pixel by `(g'(v̄)/g'(0.18))^γ`: the prior on the *encoded* image linearised about the local
//!    brightness `v̄` of the capture, which regularises dark regions (where encoding amplifies
//!    noise) more and bright ones less. On the photograph benchmark this was worth +0.4 dB
//!    (γ = 0.5); γ = 1 (the full linearisation) with κ = 7 gains a further 0.1–0.2 dB.
//!    The derivative prior is `λ (Σ_{a=1,2} ‖H_a x‖₁ + μ₂ Σ_{a=3..5} ‖H_a x‖₁)` with μ₂ = 0.5
//!    ([`DeconvOptions::order2_weight`]; the paper prints μ₂ = 1, docs/method.md §3), +0.1 to +0.3 dB.
//!    The cross-channel weight is normalised *locally*: for each pixel `k`,
//!    `β_k = cross_weight · λ / max((i_l * G_s)(k), i_l(k), 0.05)` (`G_s` a Gaussian of width
//!    `s = 4` px, [`DeconvOptions::cross_local`]) instead of by the tile mean of `i_l`, so the
//!    term `β_k |i_l ∇x − x ∇i_l|` has the units of a gradient of `x` everywhere
//!    (≈ `|∇x − x ∇i_l / i_l|`); +0.1 to +0.2 dB on hubble_deep_field/coffee. The pointwise
//!    `i_l(k)` in the maximum (issue 12) keeps the term at most `cross_weight · λ |∇x − x ∇i_l / i_l|`
//!    on point sources, where the smoothed `ī_l` is far below the peak and the weight grew by
//!    `i_l/ī_l` (5–10× on stars): +0.57 dB on the star field (synth1 × pg15k × hubble).
//! 2. Channels are ordered by the second moment of their PSF (averaged over the field): the
//!    best-focused channel is restored first with the derivative prior only; every later channel
//!    adds the cross-channel term against all channels restored before it, and the dark-region
//!    term where those are dark.
//! 3. The image is cut into overlapping tiles ([`tiles`]); each tile is restored with the
//!    profile's PSF interpolated at the tile centre ([`PsfGrid::kernel_at`]) on a mirrored,
//!    FFT-sized window, then cropped and blended with a partition of unity. Tiles run in
//!    parallel; only the input, the output and the tiles in flight are held in memory.
//!    The core is the largest whose tile-centre kernel error `e(c)`
//!    ([`tiles::tile_kernel_error`]: the blend-weighted RMS of `‖K(p) − K(centre)‖ / ‖K(p)‖`)
//!    is at most [`TILE_KERNEL_ERROR`] = 5 %, from the grid-spacing rule down to
//!    `max(48, k rounded up to 16)` px, else that floor (docs/deconvolution.md "Tile size").
//!    Optionally ([`DeconvOptions::field_passes`]) the finest level is refined by defect
//!    correction with the exact field-varying operator `A` ([`FieldOperator`]): solve with the
//!    tile kernel `B` against `j − (A − B) x_k`, whose fixed point differs from the exact
//!    problem's only by `(A − B)ᵀ` applied to the (noise-sized) residual. With the default tile
//!    size it gained +0.07 dB for +80 % time, so it is off by default; it matters for large tiles
//!    (+0.6 dB with one 512² tile).
//! 4. Per tile: optionally scale space (coarse to fine, [`pyramid`]; off by default) and at every level residual
//!    deconvolution with `λ_{k+1} = λ_k / 3`. Each solve is ADMM on the splits `z = H_a x`
//!    ([`problem::ChannelProblem::solve_admm`]): the `x`-update is one Fourier division, or with
//!    cross-channel blocks or saturated pixels one preconditioned CG step (which carries `P x` and
//!    `ρCᵀCx` along, so it costs the same two FFTs). A fixed, small iteration count (25) is
//!    enough: Chambolle–Pock needed 100–400
//!    iterations for the same PSNR, and stopping it after 100 (the former default) cost 2–3 dB.
//!    Chambolle–Pock ([`problem`]) remains for the dark-region term. A level's first step solves
//!    for the image itself, warm started from the nearest-neighbour upsampled coarser result
//!    (a speed-up only, the problem is convex); the following steps solve for increments of the
//!    residual. Putting the prior on the *increment* already at a level's first step, as a
//!    literal reading of the paper's Fig. 8 suggests, penalises the correction of the blocky
//!    upsampled start and cost 2 dB in tests.
//! 5. Pixels at or above the saturation level get weight 0 in the data term.
//! 6. Unknown boundary (Almeida & Figueiredo 2013, IEEE TIP 22(8);
//!    [`DeconvOptions::unknown_boundary`], on by default): the data term of a tile is
//!    `‖M(B x − ΔJ)‖²` with `M_k = 0` within the kernel radius `r = ⌊k/2⌋` of the window edge
//!    (where the periodic `B` wraps around) and on saturated pixels, 1 elsewhere. ADMM splits
//!    `v = B x` with penalty `ρ_v = 2 · data_split_rho`: the `v`-update is elementwise,
//!    `v_k = (2 M_k ΔJ_k + ρ_v t_k)/(2 M_k + ρ_v)` with `t = B x + u_v`, and the `x`-update stays
//!    the Fourier division by `ρ_v |B̂|² + ρ Σ_a |Ĥ_a|²` (plus the cross-channel CG step), so the
//!    estimate extends past the data by `r` instead of being fitted to the mirrored window. The
//!    mirrored margin then only has to carry the data the kept pixels need: with margin
//!    `max(3k/4, 16)` and tile cores of at most max(96, spacing/6) px (a PSF closer to the true one across the
//!    tile) the photograph benchmark gained +0.02 to +0.87 dB (the same CPU on the small scenes,
//!    ≈ +40 % on 1 MP); without the mask, the same thin margins cost up to 4 dB from ringing at
//!    the window edge.
//! 7. Denoising stage ([`denoise`]; [`DeconvOptions::denoise`], on by default), the
//!    "regularised inverse + coloured-noise denoising" idea of DEB-BM3D (Dabov et al. 2008):
//!    the solver runs with a *weaker* prior, `κ = 2.5` instead of 7
//!    ([`DeconvOptions::denoise_lambda_per_variance`]), which keeps the texture an ℓ1 gradient
//!    prior flattens (fur, foliage) and leaves more noise, and the assembled image is then
//!    denoised where PSNR is measured: on the encoded values (`e = g(x)`, the output transfer) in
//!    the orthonormal opponent space `Y = (R+G+B)/√3`, `C₁ = (R−B)/√2`, `C₂ = (R−2G+B)/√6`.
//!    The assumed noise level of a block `b` is `σ_b = s · ‖σ‖_Y · g'(0.18) · (g'(v̄_b)/g'(0.18))^p`
//!    with `s = 7` (relative to the input's estimated `σ_c`, [`DeconvOptions::denoise`]),
//!    chroma `× 1.5`, and `p = 0` (the solver's transfer weight already flattens the encoded
//!    noise; `p = 1`, the plain delta method, lost 0.05–0.1 dB). Luminance is filtered BM3D-style:
//!    for every reference block (8×8, lattice step 3) the ≤ 8 blocks within ±6 px whose mean
//!    squared difference is below `10 σ_b²` are grouped, transformed by the 2-D DCT and a Haar
//!    transform across the group, hard-thresholded at `2.7 σ_b` (stage 1), then Wiener-shrunk
//!    `Ŷ = P²/(P² + σ_b²) · Z` against the stage-1 estimate `P` (stage 2, matched on `P`), and
//!    aggregated with weights `1/(σ_b² N_kept)` resp. `1/(σ_b² Σ W²)`; chroma uses the same two
//!    stages on single sliding blocks. Measured on the photograph benchmark (defaults of this
//!    commit against the solver alone, κ = 7): astronaut +0.56, chelsea +0.54, coffee +0.64,
//!    hubble_deep_field +0.73, rocket +0.42 dB (both margins over the best peer then ≥ 1.50 dB),
//!    for 1 MP 14.1 → 14.5 CPU-s and hubble 13.5 → 15.9 CPU-s (different sessions, ±15 %).
//!    Without block matching (sliding DCT only) chelsea and rocket lost ≈ 0.05 dB; a
//!    per-frequency noise level estimated from the image (quantiles of the DCT coefficients)
//!    lost 0.3–1.5 dB; a Kaiser window, a frequency tilt of ±0.5, step 2 and larger groups or
//!    search windows changed ≤ 0.03 dB. Block matching on the chroma planes as well
//!    ([`denoise::DenoiseOptions::bm_channels`] = 3): astronaut +0.06, chelsea +0.03, coffee
//!    +0.05, hubble −0.05, rocket +0.03 dB for +31 % CPU on 1 MP (21 → 27.5 CPU-s back to back
//!    under load), which would take the 1-MP budget to its limit, so it is off (1).
//!    The stage runs in strips of rows with a halo, a few
//!    strips at a time, so it holds one extra image (the result) besides the strip buffers
//!    (12 MP: peak RSS 1.04 GB against 0.93 GB without the stage).
//!
//!    With a signal-dependent noise law ([`DeconvOptions::local_noise`], on by default) the
//!    block level is further scaled by the law at the input's local level,
//!    `√(V_c(x)/σ_c²)` with `V_c(x) = g_c (G_{s_c} * j_c)(x) + r_c²` ([`local_noise_maps`]):
//!    Poisson noise is far below the image-mean level on a dark background and above it on
//!    bright objects.
//!
//!    With [`DeconvOptions::coloured_noise`] (on by default since issue 12's matrix) the stage is instead given each
//!    opponent plane's noise variance per DCT coefficient, `σ²_k = (1/N) Σ_ω S(ω)|Φ_k(ω)|²`,
//!    evaluated by propagating the noise law through the solver ([`coloured`]) on up to
//!    3 × 3 windows spread over the field, each with its own kernels and `λ`, and blended
//!    bilinearly between the window centres ([`coloured_field`],
//!    [`denoise::CoefficientField`]): a lens whose PSF varies across the field gets a
//!    field-varying noise spectrum.
//!
//!    With [`DeconvOptions::positivity`] the ADMM solve is constrained to `x ≥ 0` by one more
//!    split `z_+ = x` whose prox is the projection `max(v, 0)`
//!    ([`problem::ChannelProblem::lower_bound`]).
//!
//!    With [`DeconvOptions::law_data_weight`] (off by default: mixed on the issue-12 matrix,
//!    docs/notes/deblur-history.md "Issue-12, m16") the data term is weighted per pixel by the inverse
//!    of the noise law, `Σ_k w_k (Bx − j)_k²`, `w_k = V_ref / V(G_1 * j)_k` ([`DataWeight`]).
//!
//!    With [`DeconvOptions::texture_return`] (off by default: +0.0 to +0.16 dB on the low-light
//!    cells, no held-out cell crossed +1.5 dB, docs/notes/deblur-history.md "Issue-12, m17") the part of
//!    each tile's residual `j − B x̂` whose power exceeds the law's noise floor is Wiener-deconvolved
//!    and added back after the denoiser ([`texture`]).
//!
//! 8. No-harm rule ([`noharm`], on by default): flat regions where the result is noisier than
//!    the input fall back towards the input; [`DeconvReport::no_harm`] says where.
//!
//! # Conventions
//! Planes are **linear** values on the full-scale axis ([`crate::image`]); decoding and
//! re-encoding is the caller's job ([`cli`]). PSFs follow [`crate::solve::conv`]. Outputs are not
//! clipped.
//!
//! # Deviation from the paper (docs/method.md §4)
//! The dark-region weight the paper prints, `w = 1 − (Σ β T(i_l) / Σ β) * K_σ` with `T = 1` on
//! dark pixels, is 0 in dark regions, which contradicts its stated purpose (and the paper's text:
//! "`D_w` is a spatial mask that selects dark regions"). lensrig uses the blurred dark fraction
//! itself, `w = (Σ β T(i_l) / Σ β) * K_σ`, which is 1 where the other channels are dark.

pub mod capture;
pub mod coloured;
pub mod denoise;
pub mod filters;
pub mod noharm;
pub mod noise;
pub mod peers;
pub mod problem;
pub mod pyramid;
pub mod quality;
pub mod spectrum;
pub mod synth;
pub mod texture;
pub mod tiles;

use crate::image::Plane;
use crate::image::filter::gaussian_blur_periodic;
use crate::optics::field_operator::FieldOperator;
use crate::optics::psf_grid::PsfGrid;
use crate::solve::conv::kernel_to_origin;
use crate::solve::fft::Fft2;
use crate::solve::operator::{LinearOperator, PrimalDualOperator};
use crate::solve::power::operator_norm;
use crate::solve::primal_dual::{chambolle_pock, Options, NORM_SAFETY};
use problem::{add_weighted_gradient_normal, gradients, ChannelProblem, CrossChannel, DarkTerm, KernelSpectrum};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Why a restoration could not run.
#[derive(Debug, thiserror::Error)]
pub enum DeconvError {
    #[error("the image has {got} channel(s) but the PSF grid has {expected} ({names})")]
    ChannelCount { got: usize, expected: usize, names: String },
    #[error("the image planes differ in size")]
    PlaneSizes,
    #[error("empty image")]
    Empty,
    #[error("invalid option: {0}")]
    Option(String),
}

/// Solver settings. [`Default`] needs no tuning on typical captures.
#[derive(Clone, Debug)]
pub struct DeconvOptions {
    /// Prior weight per channel; `None` derives it from the noise estimate.
    pub lambda: Option<Vec<f32>>,
    /// `κ` in `λ_c = κ σ_c²`.
    pub lambda_per_variance: f32,
    /// Smallest `λ` used (a noise-free input would otherwise get no prior at all).
    pub lambda_min: f32,
    /// Cross-channel weight relative to `λ`: `β = cross_weight · λ / max(ī_l, 0.05)` with `ī_l`
    /// the locally smoothed other channel ([`DeconvOptions::cross_local`]) or its tile mean;
    /// 0 restores channels independently.
    pub cross_weight: f32,
    /// `λ_b` of the dark-region term (0 disables it). Off by default: on the photograph
    /// benchmark `λ_b = 0.1` changed PSNR by −0.05 dB and cost 75 % more time (CG prox).
    pub dark_weight: f32,
    /// Dark threshold `ε` on linear values.
    pub dark_threshold: f32,
    /// Residual steps per level (`λ, λ/3, λ/9, …`). Default 1: a second step at `λ/3` added
    /// 1 dB on the cartoon-like synthetic tests but cost 1.6 dB (and twice the time) on the
    /// photograph benchmark, where it brings noise back.
    pub residual_steps: usize,
    /// Defect-correction solves with the exact field-varying operator after the tile-kernel
    /// solve at the finest level (0: the tile-centre kernel only).
    pub field_passes: usize,
    /// Most scale-space levels (1 = no pyramid). Default 1: on the photograph benchmark one level
    /// with 25 iterations costs what two levels with 20 did and gains 0 to +0.12 dB.
    pub max_levels: usize,
    /// ADMM iterations per solve (residual step or defect-correction pass).
    pub max_iterations: usize,
    /// Chambolle–Pock iteration cap per solve (used with the dark-region term or
    /// `admm_rho = 0`), and its tolerance.
    pub cp_max_iterations: usize,
    pub tolerance: f64,
    /// ADMM penalty relative to `λ` (`ρ = admm_rho · λ`); 0 selects Chambolle–Pock. ADMM is used
    /// whenever the dark-region term is off.
    pub admm_rho: f32,
    /// Conjugate-gradient steps per ADMM `x`-update when it is not a Fourier division
    /// (cross-channel blocks or saturated pixels present).
    pub admm_cg_iterations: usize,
    /// Step balance: the dual step is `σ = step_balance / L` and the primal step
    /// `τ = 0.9 / (σ L²)`, with `L = ‖K‖₂` measured per solve (the prior weights live inside `K`,
    /// so a fixed `σ` would be badly scaled for small `λ`).
    pub step_balance: f32,
    /// Linear values at or above this are saturated and dropped from the data term.
    pub saturation: Option<f32>,
    /// Largest tile core (pixels); `None` picks one from the PSF grid: the largest, from 1.5
    /// grid spacings (at most max(96, spacing / 6) with [`DeconvOptions::unknown_boundary`]) down
    /// to a floor, whose tile-centre kernel error is within [`TILE_KERNEL_ERROR`] (`default_core`).
    pub tile_core: Option<usize>,
    /// Width of the blending band between tiles.
    pub overlap: usize,
    /// Margin around the kept pixels of a tile; `None`: twice the kernel size (at least 16), or
    /// with [`DeconvOptions::unknown_boundary`] three quarters of it (at least 16).
    pub margin: Option<usize>,
    /// Restore tiles in parallel.
    pub parallel: bool,
    /// The encoding the result is delivered in. The prior then weighs gradients as they will
    /// appear after encoding: every ℓ1 term is scaled per pixel by `(g'(v̄) / g'(0.18))^γ`,
    /// `g` the transfer curve, `v̄` the smoothed local brightness of the capture (the prior
    /// on `g(x)` linearised about the capture). `None` or linear: uniform weight.
    pub output_transfer: Option<crate::image::Transfer>,
    /// `γ` above.
    pub transfer_weight: f32,
    /// Reweighted-ℓ1 exponent `q` of the derivative prior (ADMM only): each pixel's threshold is
    /// scaled by `((|H_a x| + ε)/ε)^(q−1)` from the current iterate, approximating a
    /// hyper-Laplacian `|∇x|^q`; 1 is the plain ℓ1 prior.
    pub reweight_power: f32,
    /// `ε` above (linear gradient units).
    pub reweight_eps: f32,
    /// Weight `μ₂` of the second-order derivatives relative to the first-order ones in the
    /// derivative prior ([`problem::ChannelProblem::order2_weight`]).
    pub order2_weight: f32,
    /// Smoothing scale `s` (pixels) of the local cross-channel normalisation: `β_k = cross_weight
    /// · λ / max(ī_l(k), i_l(k), 0.05)` with `ī_l` the other channel blurred by a Gaussian of width `s`;
    /// 0 normalises by the tile mean of `i_l` instead.
    pub cross_local: f32,
    /// Unknown-boundary data term (Almeida & Figueiredo 2013): the outer `r` pixels of each
    /// tile window (`r` the kernel radius) get data weight 0, and ADMM splits `v = B x` so the
    /// masked data term stays an elementwise prox ([`problem::ChannelProblem::data_split`]).
    pub unknown_boundary: bool,
    /// `ρ_v / 2` of that split (relative to the data term's weight 2).
    pub data_split_rho: f32,
    /// Final denoising stage ([`denoise`]): the noise level assumed in the deconvolved image,
    /// relative to the input's estimated noise level `σ_c`; 0 disables the stage.
    pub denoise: f32,
    /// `κ` used instead of [`DeconvOptions::lambda_per_variance`] while the denoising stage is
    /// on (a weaker prior keeps texture and leaves the noise to the denoiser).
    pub denoise_lambda_per_variance: f32,
    /// The denoiser's block, threshold, matching and noise-model settings ([`denoise`]); its
    /// `sigma`, `transfer` and `parallel` are set by [`deblur`].
    pub denoiser: denoise::DenoiseOptions,
    /// Coloured-noise denoising ([`coloured`]): the denoiser is given each opponent plane's noise
    /// variance per DCT coefficient, propagated through the solver from the channel's own PSF
    /// and the noise level, instead of the flat `denoise × σ_c` (and `chroma`). On by default:
    /// chosen on the declared tuning subset of the benchmark matrix (synth1 × Gaussian noise ×
    /// the five photographs, where it ties or wins) and confirmed on the held-out cells
    /// (docs/deconvolution.md "Benchmark matrix"); `false` is the flat model (`--denoise-noise flat`).
    pub coloured_noise: bool,
    /// Most coloured-noise propagation windows per axis ([`coloured_field`]): `min(n, grid
    /// columns) × min(n, grid rows)` windows spread evenly over the image, each with its own
    /// kernels and `λ`, blended bilinearly by the denoiser. 1: the centre window only.
    pub coloured_windows: usize,
    /// Scale each coloured-noise window's variances by `s²`, `s` chosen by Stein's unbiased
    /// risk estimate of the re-blurred, denoised window ([`coloured::sure_scale`]).
    pub coloured_sure: bool,
    /// How the coloured-noise windows read the solver's noise ([`coloured::Response`]):
    /// `Forward(1)` (default) restores the window with extra noise on top of its own, `Pilot`
    /// restores the re-blurred window restoration under two fresh noise draws (one more window
    /// solve; docs/notes/deblur-history.md "Issue-12, m20"). With [`Self::coloured_sure`] the forward
    /// response is used (the risk estimate needs `restore(j)` and `restore(j + n)`).
    pub coloured_response: coloured::Response,
    /// Positivity ([`problem::ChannelProblem::lower_bound`]): the ADMM solve keeps the restored
    /// channel non-negative (`x ≥ 0`, one more split with the projection as its prox), as light
    /// is. Not applied on the Chambolle–Pock path (dark-region term). On by default: chosen on
    /// the tuning subset (synth1 × Gaussian noise × the five photographs: +0.03 to +0.69 dB,
    /// hubble most); held out it costs sf11 × dark 0.8 dB (docs/deconvolution.md "Positivity").
    pub positivity: bool,
    /// Local noise level in the denoising stage ([`local_noise_maps`]): with a signal-dependent
    /// noise law, each block's noise level follows the law at the input's local level instead of
    /// the image mean's. No effect without a law or with a white one.
    pub local_noise: bool,
    /// Variance-weighted data term ([`DataWeight`], docs/notes/deblur-history.md "Issue-12, m16"): with a
    /// signal-dependent noise law, each data pixel is weighted by `V_ref / V(j̃_k)`, the inverse
    /// of the law's variance at the (lightly smoothed) input, relative to the level `λ` was set
    /// at; `Σ_k (B x − j)_k² / V(j̃_k)` is the Gaussian approximation of the Poisson–Gaussian
    /// likelihood. No effect without a law or with a white one.
    pub law_data_weight: bool,
    /// Texture return ([`texture`], docs/notes/deblur-history.md "Issue-12, m17"): after the denoising
    /// stage, the part of each tile's data residual `j − B x̂` whose power exceeds the noise
    /// law's floor is deconvolved by a Wiener filter and added back.
    pub texture_return: bool,
    /// Where the noise level comes from ([`noise::NoiseSource`]). With a law, a tile's
    /// `λ_c = κ (g_c x̄ + r_c²)` uses the tile's mean linear value `x̄` of the channel, and the
    /// channel's `σ_c = √(g_c · mean(x) + r_c²)` replaces Donoho's estimate everywhere else.
    pub noise: noise::NoiseSource,
    /// The no-harm rule ([`noharm`]): flat regions never come out noisier than the input.
    pub no_harm: noharm::NoHarmOptions,
}

impl Default for DeconvOptions {
    fn default() -> Self {
        Self {
            lambda: None,
            lambda_per_variance: 7.0,
            lambda_min: 2e-5,
            cross_weight: 3.0,
            dark_weight: 0.0,
            dark_threshold: 0.05,
            residual_steps: 1,
            field_passes: 0,
            max_levels: 1,
            max_iterations: 25,
            cp_max_iterations: 150,
            tolerance: 1e-3,
            step_balance: 30.0,
            admm_rho: 100.0,
            admm_cg_iterations: 1,
            saturation: Some(0.99),
            tile_core: None,
            overlap: 32,
            margin: None,
            parallel: true,
            output_transfer: None,
            transfer_weight: 1.0,
            reweight_power: 1.0,
            reweight_eps: 0.02,
            order2_weight: 0.5,
            cross_local: 4.0,
            unknown_boundary: true,
            data_split_rho: 1.0,
            denoise: 7.0,
            denoise_lambda_per_variance: 2.5,
            denoiser: denoise::DenoiseOptions::default(),
            coloured_noise: true,
            coloured_windows: 3,
            coloured_sure: false,
            coloured_response: coloured::Response::Forward(1.0),
            positivity: true,
            local_noise: true,
            law_data_weight: false,
            texture_return: false,
            noise: noise::NoiseSource::Profile,
            no_harm: noharm::NoHarmOptions::default(),
        }
    }
}

/// What a restoration did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct DeconvReport {
    /// `σ_c` used (from the law, or Donoho's estimate).
    pub noise_sigma: Vec<f32>,
    /// Donoho's estimate on the input, per channel (the check against a law).
    pub estimated_sigma: Vec<f32>,
    /// The noise law used, if any.
    pub noise_law: Option<crate::profile::noise::NoiseLaw>,
    /// Things the user should know (a photo that disagrees with the law, …).
    pub warnings: Vec<String>,
    /// Where the no-harm rule fell back towards the input.
    pub no_harm: noharm::NoHarmReport,
    pub lambda: Vec<f32>,
    /// Channel indices in restoration order.
    pub order: Vec<usize>,
    /// Channel names (the grid's).
    pub channels: Vec<String>,
    pub tiles: usize,
    /// The tile core (px) and the relative kernel error of restoring each tile with its
    /// centre's PSF ([`tiles::tile_kernel_error`]; docs/deconvolution.md "Tile size").
    pub tile_core: usize,
    pub tile_kernel_error: f64,
    pub window: [usize; 2],
    pub levels: usize,
    pub cp_iterations: usize,
    pub cg_iterations: usize,
    pub saturated_pixels: usize,
}

/// The second moment `Σ K(u,v)·|(u,v) − centroid|²` of a kernel (its blur size).
pub fn second_moment(k: &Plane) -> f64 {
    let s = k.sum().max(1e-30);
    let (mut mx, mut my) = (0.0, 0.0);
    for v in 0..k.height {
        for u in 0..k.width {
            let w = k.get(u, v) as f64 / s;
            mx += w * u as f64;
            my += w * v as f64;
        }
    }
    let mut m = 0.0;
    for v in 0..k.height {
        for u in 0..k.width {
            m += k.get(u, v) as f64 / s * ((u as f64 - mx).powi(2) + (v as f64 - my).powi(2));
        }
    }
    m
}

/// Channels sorted from the sharpest (smallest mean second moment over the field) to the
/// blurriest.
pub fn restoration_order(grid: &PsfGrid) -> Vec<usize> {
    let mut m: Vec<(usize, f64)> = grid
        .kernels
        .iter()
        .enumerate()
        .map(|(c, ks)| (c, ks.iter().map(second_moment).sum::<f64>() / ks.len().max(1) as f64))
        .collect();
    m.sort_by(|a, b| a.1.total_cmp(&b.1));
    m.into_iter().map(|(c, _)| c).collect()
}

/// The smallest `m ≥ n` of the form `2^a 3^b` with `2^levels` dividing it.
pub fn fft_size(n: usize, levels: usize) -> usize {
    let mut m = crate::solve::fft::good_size(n);
    loop {
        if m % (1 << levels.max(1)) == 0 {
            return m;
        }
        m = crate::solve::fft::good_size(m + 1);
    }
}

/// Restores `planes` (linear, one per grid channel) blurred by `grid`'s spatially varying PSFs.
///
/// `progress(done, total)` is called as tiles finish (from worker threads).
///
/// # Errors
/// [`DeconvError::ChannelCount`] when the plane count differs from the grid's channel count,
/// [`DeconvError::PlaneSizes`]/[`DeconvError::Empty`] for malformed input, and
/// [`DeconvError::Option`] for inconsistent settings.
pub fn deblur(
    planes: &[Plane],
    grid: &PsfGrid,
    opts: &DeconvOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Vec<Plane>, DeconvReport), DeconvError> {
    check_inputs(planes, grid, opts)?;
    let noise = noise_stage(planes, grid, opts)?;
    let order = restoration_order(grid);
    let layout = tile_layout(planes[0].width, planes[0].height, grid, opts);
    let (out, st, ops) = restore_tiles(planes, grid, opts, &layout, &noise, &order, progress);
    let (out, no_harm) = finish(planes, out, &noise, opts, (grid, &order), &TileOps { layout: &layout, ops: &ops });
    let mut warnings = noise.warnings;
    if tile_error_warns(layout.kernel_error) {
        warnings.push(format!(
            "the PSF changes across the field faster than tiles of {} px follow: restoring each tile with its centre's PSF is {:.1} % off in kernel L2 (more than twice the {:.0} % allowed); a smaller --tile follows it more closely, at more cost",
            layout.core,
            100.0 * layout.kernel_error,
            100.0 * TILE_KERNEL_ERROR
        ));
    }
    let report = DeconvReport {
        noise_sigma: noise.sigma,
        estimated_sigma: noise.estimated,
        noise_law: noise.law,
        warnings,
        no_harm,
        channels: grid.channels.clone(),
        lambda: noise.lambda,
        order,
        tiles: layout.xs.len() * layout.ys.len(),
        tile_core: layout.core,
        tile_kernel_error: layout.kernel_error,
        window: [layout.pw, layout.ph],
        levels: st.levels,
        cp_iterations: st.cp_iterations,
        cg_iterations: st.cg_iterations,
        saturated_pixels: st.saturated,
    };
    Ok((out, report))
}

/// Noise and prior weights of [`deblur`]'s input, per channel.
struct NoiseStage {
    /// The photo's own σ estimate.
    estimated: Vec<f32>,
    /// The noise law, if one is given.
    law: Option<crate::profile::noise::NoiseLaw>,
    /// The σ used (from the law, else the estimate).
    sigma: Vec<f32>,
    /// Disagreements between the law and the estimate.
    warnings: Vec<String>,
    /// The image-wide prior weight λ.
    lambda: Vec<f32>,
}

/// Noise stage of [`deblur`]: estimates σ, resolves the noise law and the image-wide λ.
fn noise_stage(planes: &[Plane], grid: &PsfGrid, opts: &DeconvOptions) -> Result<NoiseStage, DeconvError> {
    let nch = planes.len();
    let estimated: Vec<f32> = planes.iter().map(noise::estimate_sigma).collect();
    let law = match &opts.noise {
        noise::NoiseSource::Law(l) => Some(l.for_channels(nch).map_err(|e| DeconvError::Option(e.to_string()))?),
        _ => None,
    };
    let sigma: Vec<f32> = match &law {
        Some(l) => planes.iter().enumerate().map(|(c, p)| noise::law_sigma(l, c, &p.data)).collect(),
        None => estimated.clone(),
    };
    let warnings = law.as_ref().map(|l| noise::check_law(l, planes, &estimated, &grid.channels)).unwrap_or_default();
    let lambda: Vec<f32> = (0..nch).map(|c| lambda_for(opts, c, sigma[c] * sigma[c])).collect();
    Ok(NoiseStage { estimated, law, sigma, warnings, lambda })
}

/// Prior-weight stage of [`deblur`]: λ of channel `c` at noise `variance` (or the given λ).
fn lambda_for(opts: &DeconvOptions, c: usize, variance: f32) -> f32 {
    let kappa = if opts.denoise > 0.0 { opts.denoise_lambda_per_variance } else { opts.lambda_per_variance };
    match &opts.lambda {
        Some(l) => l[if l.len() == 1 { 0 } else { c }],
        None => (kappa * variance).max(opts.lambda_min),
    }
}

/// The tiles of [`deblur`]: spans along x and y, the FFT window size, the core and its
/// tile-centre kernel error ([`tiles::tile_kernel_error`]).
struct TileLayout {
    xs: Vec<tiles::Span>,
    ys: Vec<tiles::Span>,
    pw: usize,
    ph: usize,
    core: usize,
    kernel_error: f64,
}

/// The tile core (px) [`deblur`] takes by default for `grid` on a `width × height` image, and
/// its tile-centre kernel error ([`tiles::tile_kernel_error`]; the calibration report shows both).
pub fn default_tile_core(grid: &PsfGrid, width: usize, height: usize) -> (usize, f64) {
    let layout = tile_layout(width, height, grid, &DeconvOptions::default());
    (layout.core, layout.kernel_error)
}

/// Tile-layout stage of [`deblur`]: margin, core size, spans and FFT-sized windows.
fn tile_layout(w: usize, h: usize, grid: &PsfGrid, opts: &DeconvOptions) -> TileLayout {
    let k = grid.kernel_size;
    // the unknown-boundary data term needs no mirrored margin to absorb ringing: the estimate
    // extends past the used data by the kernel radius
    let margin = opts.margin.unwrap_or(if opts.unknown_boundary { (3 * k / 4).max(16) } else { (2 * k).max(16) });
    let levels = opts.max_levels.max(1);
    let (core, kernel_error) = match opts.tile_core.map(|c| c.max(MIN_TILE_CORE)) {
        Some(c) => (c, tiles::tile_kernel_error(grid, w, h, c, opts.overlap)),
        None => default_core(grid, opts, margin, w, h),
    };
    let mut xs = tiles::spans(w, core, opts.overlap);
    let mut ys = tiles::spans(h, core, opts.overlap);
    let core = tiles::actual_core(&xs, &ys);
    let pw = fft_size(tiles::max_keep(&xs) + 2 * margin, levels);
    let ph = fft_size(tiles::max_keep(&ys) + 2 * margin, levels);
    tiles::place_windows(&mut xs, pw);
    tiles::place_windows(&mut ys, ph);
    TileLayout { xs, ys, pw, ph, core, kernel_error }
}

/// Tile stage of [`deblur`]: restores and blends every tile (in parallel if asked); returns
/// the blended planes, the summed tile counters (`levels`: the maximum) and, when a stage after
/// the denoiser needs them ([`DeconvOptions::texture_return`]), each tile's finest-level
/// operators (index `j · xs.len() + i`; empty otherwise).
fn restore_tiles(
    planes: &[Plane],
    grid: &PsfGrid,
    opts: &DeconvOptions,
    layout: &TileLayout,
    noise: &NoiseStage,
    order: &[usize],
    progress: &(dyn Fn(usize, usize) + Sync),
) -> (Vec<Plane>, TileStats, Vec<TileOperators>) {
    let nch = planes.len();
    let (w, h) = (planes[0].width, planes[0].height);
    let TileLayout { xs, ys, pw, ph, .. } = layout;
    let keep = keeps_tile_operators(opts);
    let kept: Mutex<Vec<Option<TileOperators>>> = Mutex::new((0..xs.len() * ys.len()).map(|_| None).collect());
    let (pw, ph) = (*pw, *ph);
    let tile_list: Vec<(usize, usize)> = (0..ys.len()).flat_map(|j| (0..xs.len()).map(move |i| (i, j))).collect();
    let total = tile_list.len();
    let out = Mutex::new(vec![Plane::new(w, h); nch]);
    let done = AtomicUsize::new(0);
    let counters = Mutex::new(TileStats::default());
    let run = |&(i, j): &(usize, usize)| {
        let (sx, sy) = (&xs[i], &ys[j]);
        let windows: Vec<Vec<f32>> = planes.iter().map(|p| p.window_reflect(sx.window0, sy.window0, pw, ph).data).collect();
        let kernels: Vec<Plane> = (0..nch).map(|c| grid.kernel_at(c, sx.centre(), sy.centre())).collect();
        let field = FieldWindow { grid, x0: sx.window0, y0: sy.window0, image_width: w, image_height: h };
        // with a noise law, λ follows the tile's own signal level
        let tile_lambda: Vec<f32> = match &noise.law {
            Some(l) => (0..nch).map(|c| lambda_for(opts, c, noise::law_sigma(l, c, &windows[c]).powi(2))).collect(),
            None => noise.lambda.clone(),
        };
        let tile_variance: Vec<f32> = match &noise.law {
            Some(l) => (0..nch).map(|c| noise::law_sigma(l, c, &windows[c]).powi(2)).collect(),
            None => Vec::new(),
        };
        let data_weight = DataWeight::new(opts, noise.law.as_ref(), &tile_variance);
        let setup = TileSetup { width: pw, height: ph, lambda: &tile_lambda, order, opts, field: Some(field), data_weight };
        let (restored, st, tile_ops) = restore_tile_keeping(&windows, &kernels, &setup, keep);
        blend_tile(&mut out.lock().unwrap_or_else(|e| e.into_inner()), &restored, sx, sy, pw);
        if let Some(t) = tile_ops {
            kept.lock().unwrap_or_else(|e| e.into_inner())[j * xs.len() + i] = Some(t);
        }
        {
            let mut c = counters.lock().unwrap_or_else(|e| e.into_inner());
            c.cp_iterations += st.cp_iterations;
            c.cg_iterations += st.cg_iterations;
            c.levels = c.levels.max(st.levels);
            c.saturated += st.saturated;
        }
        progress(done.fetch_add(1, Ordering::SeqCst) + 1, total);
    };
    if opts.parallel {
        tile_list.par_iter().for_each(run);
    } else {
        tile_list.iter().for_each(run);
    }
    let stats = counters.into_inner().unwrap_or_else(|e| e.into_inner());
    let kept: Vec<TileOperators> = kept.into_inner().unwrap_or_else(|e| e.into_inner()).into_iter().flatten().collect();
    (out.into_inner().unwrap_or_else(|e| e.into_inner()), stats, kept)
}

/// Whether [`restore_tiles`] keeps each tile's [`TileOperators`] for a later stage.
fn keeps_tile_operators(opts: &DeconvOptions) -> bool {
    opts.texture_return
}

/// What the stages after the denoiser reuse of the tile stage: the layout and each tile's
/// finest-level operators (empty unless [`keeps_tile_operators`]).
struct TileOps<'a> {
    layout: &'a TileLayout,
    ops: &'a [TileOperators],
}

/// A tile's finest-level operators as the solver built them, kept for the stages after the
/// denoiser (texture return): per channel, the spectrum `F(B)` of the origin-centred tile kernel
/// on the `pw × ph` window and the 0/1 data mask `M` (0 within the kernel radius of the window
/// edge and on saturated pixels; stored as bytes, 1 = data).
pub struct TileOperators {
    pub spectra: Vec<Vec<rustfft::num_complex::Complex32>>,
    pub masks: Vec<Vec<u8>>,
}

impl TileOperators {
    /// Channel `c`'s mask as 0/1 weights.
    pub fn mask(&self, c: usize) -> Vec<f32> {
        self.masks[c].iter().map(|m| f32::from(*m)).collect()
    }
}

/// Finishing stage of [`deblur`]: the optional denoiser, then the no-harm rule.
fn finish(planes: &[Plane], mut out: Vec<Plane>, noise: &NoiseStage, opts: &DeconvOptions, lens: (&PsfGrid, &[usize]), tiles: &TileOps) -> (Vec<Plane>, noharm::NoHarmReport) {
    if opts.denoise > 0.0 {
        let d = denoise::DenoiseOptions {
            coefficient_variance: opts.coloured_noise.then(|| coloured_field(planes, lens, noise, opts)),
            local_variance: if opts.local_noise { local_noise_maps(planes, lens.0, noise) } else { None },
            sigma: noise.sigma.iter().map(|s| opts.denoise * s).collect(),
            transfer: opts.output_transfer.unwrap_or(crate::image::Transfer::Linear),
            parallel: opts.parallel,
            ..opts.denoiser.clone()
        };
        out = denoise::denoise(&out, &d);
    }
    if opts.texture_return {
        out = return_texture(planes, out, tiles, noise, opts);
    }
    let no_harm = if opts.no_harm.enabled {
        let variance = |c: usize, x: f32| match &noise.law {
            Some(l) => l.variance(c, x),
            None => noise.sigma[c] * noise.sigma[c],
        };
        noharm::apply(planes, &mut out, &variance, &opts.no_harm)
    } else {
        noharm::NoHarmReport::default()
    };
    (out, no_harm)
}
/// Texture-return stage of [`deblur`] ([`texture`]): on the tiles of [`tile_layout`], each
/// channel's lost signal `Δ̂` (Wiener estimate from the residual `M (j − B x̂)` against the law's
/// floor) is blended with the tiles' partition of unity and added to `out`. The layout, the
/// kernel spectra and the masks are the tile stage's ([`TileOps`]).
fn return_texture(planes: &[Plane], mut out: Vec<Plane>, tiles: &TileOps, noise: &NoiseStage, opts: &DeconvOptions) -> Vec<Plane> {
    let nch = planes.len();
    let (w, h) = (planes[0].width, planes[0].height);
    let TileLayout { xs, ys, pw, ph, .. } = tiles.layout;
    let (pw, ph) = (*pw, *ph);
    assert_eq!(tiles.ops.len(), xs.len() * ys.len(), "texture return: the tile stage kept no operators");
    let tile_list: Vec<(usize, usize)> = (0..ys.len()).flat_map(|j| (0..xs.len()).map(move |i| (i, j))).collect();
    let added = Mutex::new(vec![Plane::new(w, h); nch]);
    let fft = Fft2::plan(pw, ph);
    let run = |&(i, j): &(usize, usize)| {
        let (sx, sy) = (&xs[i], &ys[j]);
        let ops = &tiles.ops[j * xs.len() + i];
        let delta: Vec<Vec<f32>> = (0..nch)
            .map(|c| {
                let data = planes[c].window_reflect(sx.window0, sy.window0, pw, ph).data;
                let est = out[c].window_reflect(sx.window0, sy.window0, pw, ph).data;
                let level = gaussian_blur_periodic(&data, pw, ph, 1.0);
                let variance: Vec<f32> = match &noise.law {
                    Some(l) => level.iter().map(|v| l.variance(c, v.clamp(0.0, 1.0))).collect(),
                    None => vec![noise.sigma[c] * noise.sigma[c]; pw * ph],
                };
                texture::lost_signal(&fft, &data, &est, &ops.spectra[c], &ops.mask(c), &variance)
            })
            .collect();
        blend_tile(&mut added.lock().unwrap_or_else(|e| e.into_inner()), &delta, sx, sy, pw);
    };
    if opts.parallel {
        tile_list.par_iter().for_each(run);
    } else {
        tile_list.iter().for_each(run);
    }
    let added = added.into_inner().unwrap_or_else(|e| e.into_inner());
    // with positivity the returned image stays non-negative, as the solver's was
    let floor = if opts.positivity { 0.0 } else { f32::NEG_INFINITY };
    for (o, a) in out.iter_mut().zip(&added) {
        o.data.iter_mut().zip(&a.data).for_each(|(o, a)| *o = if *o >= floor { (*o + a).max(floor) } else { *o + a });
    }
    out
}

/// Local noise level of the denoising stage (docs/deconvolution.md "Local noise level"): with a
/// Poisson–Gaussian law, the noise of the deconvolved channel `c` near `x` has the variance
/// `V_c(x) = g_c (G_{s_c} * j_c)(x) + r_c²`, the law at the input's level averaged over the
/// restoration's reach (`G_s` a Gaussian with the per-axis RMS radius `s_c = √(m₂/2)` of the
/// channel's centre PSF, `m₂` its [`second_moment`], at least 1 px); returned as
/// `m_c = V_c / σ_c²`, `σ_c` the stationary level the denoiser is given. `None` without a law
/// or with a signal-independent one (`g = 0`: `m ≡ 1`).
fn local_noise_maps(planes: &[Plane], grid: &PsfGrid, noise: &NoiseStage) -> Option<Vec<Plane>> {
    let law = noise.law.as_ref()?;
    if law.gain.iter().all(|g| *g <= 0.0) {
        return None;
    }
    let (w, h) = (planes[0].width, planes[0].height);
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let maps = planes
        .par_iter()
        .enumerate()
        .map(|(c, p)| {
            let s = (second_moment(&grid.kernel_at(c, cx, cy)) / 2.0).sqrt().max(1.0);
            let level = crate::image::filter::gaussian_blur(&p.map(|v| v.clamp(0.0, 1.0)), s);
            let reference = (noise.sigma[c] * noise.sigma[c]).max(1e-20);
            level.map(|v| law.variance(c, v) / reference)
        })
        .collect();
    Some(maps)
}

/// Coloured-noise stage of [`deblur`] (docs/deconvolution.md "Per-tile coloured noise"): the
/// denoiser's per-coefficient noise variances as a field. On `n_x × n_y` windows
/// ([`DeconvOptions::coloured_windows`] per axis, at most the PSF grid's columns and rows)
/// centred at `((i + ½) W / n_x, (j + ½) H / n_y)`, the noise law (or σ) is propagated through
/// the solver ([`coloured::through_solver`]) with the kernels at the window centre and each
/// channel's `λ` at its image-mean level (as the single centre window did).
fn coloured_field(planes: &[Plane], lens: (&PsfGrid, &[usize]), noise: &NoiseStage, opts: &DeconvOptions) -> denoise::CoefficientField {
    let (grid, order) = lens;
    let (w, h) = (planes[0].width, planes[0].height);
    let nx = opts.coloured_windows.clamp(1, grid.columns.max(1));
    let ny = opts.coloured_windows.clamp(1, grid.rows.max(1));
    let xs: Vec<f32> = (0..nx).map(|i| (i as f32 + 0.5) * w as f32 / nx as f32 - 0.5).collect();
    let ys: Vec<f32> = (0..ny).map(|j| (j as f32 + 0.5) * h as f32 / ny as f32 - 0.5).collect();
    let side = coloured::window_side(grid.kernel_size);
    let variance = |c: usize, x: f32| match &noise.law {
        Some(l) => l.variance(c, x.clamp(0.0, 1.0)),
        None => noise.sigma[c] * noise.sigma[c],
    };
    let levels: Vec<f32> = planes.iter().map(|p| (p.mean() as f32).clamp(0.0, 1.0)).collect();
    let reference: Vec<f32> = (0..planes.len()).map(|c| variance(c, levels[c])).collect();
    let lambda: Vec<f32> = (0..planes.len()).map(|c| lambda_for(opts, c, reference[c])).collect();
    let nodes: Vec<(f32, f32)> = ys.iter().flat_map(|y| xs.iter().map(move |x| (*x, *y))).collect();
    let work = |&(cx, cy): &(f32, f32)| {
        let (x0, y0) = (cx.round() as isize - side as isize / 2, cy.round() as isize - side as isize / 2);
        let base: Vec<Vec<f32>> = planes.iter().map(|p| p.window_reflect(x0, y0, side, side).data).collect();
        let kernels: Vec<Plane> = (0..planes.len()).map(|c| grid.kernel_at(c, cx as f64, cy as f64)).collect();
        let data_weight = DataWeight::new(opts, noise.law.as_ref(), &reference);
        let setup = TileSetup { width: side, height: side, lambda: &lambda, order, opts, field: None, data_weight };
        let response = if opts.coloured_sure { coloured::Response::Forward(1.0) } else { opts.coloured_response };
        let prop = coloured::through_solver_as(&base, &variance, &kernels, &setup, response);
        let mut v = prop.variances.clone();
        if opts.coloured_sure {
            let denoiser = denoise::DenoiseOptions { transfer: opts.output_transfer.unwrap_or(crate::image::Transfer::Linear), parallel: false, ..opts.denoiser.clone() };
            let window = coloured::Window { data: &base, propagation: &prop, kernels: &kernels, side };
            let s = coloured::sure_scale(&window, &variance, &denoiser);
            v.iter_mut().for_each(|p| p.iter_mut().for_each(|x| *x *= s * s));
        }
        v
    };
    let variance_at: Vec<Vec<[f32; 64]>> = if opts.parallel { nodes.par_iter().map(work).collect() } else { nodes.iter().map(work).collect() };
    denoise::CoefficientField { xs, ys, variance: variance_at }
}

/// The argument checks of [`deblur`].
fn check_inputs(planes: &[Plane], grid: &PsfGrid, opts: &DeconvOptions) -> Result<(), DeconvError> {
    let nch = planes.len();
    if nch != grid.kernels.len() {
        return Err(DeconvError::ChannelCount { got: nch, expected: grid.kernels.len(), names: grid.channels.join(",") });
    }
    let (w, h) = (planes[0].width, planes[0].height);
    if w == 0 || h == 0 {
        return Err(DeconvError::Empty);
    }
    if planes.iter().any(|p| p.width != w || p.height != h) {
        return Err(DeconvError::PlaneSizes);
    }
    if let Some(l) = &opts.lambda {
        if l.len() != nch && l.len() != 1 {
            return Err(DeconvError::Option(format!("{} lambda values for {nch} channels", l.len())));
        }
    }
    Ok(())
}

/// The largest kernel error the tile-centre approximation may add, relative
/// (`tiles::tile_kernel_error`, a blend-weighted RMS of relative L2 errors): issue 16's bound on
/// the median relative L2 error of an estimated kernel, so that the tiling adds an error of
/// about the size the calibration is allowed (a rule of thumb: the two do not simply add).
pub const TILE_KERNEL_ERROR: f64 = 0.05;

/// Whether a tile-centre kernel error is worth a warning: above twice [`TILE_KERNEL_ERROR`]
/// (`deblur`'s report and the calibration report say the restoration is approximate).
pub fn tile_error_warns(error: f64) -> bool {
    error > 2.0 * TILE_KERNEL_ERROR
}

/// The smallest tile core (px) the restoration takes; a smaller `tile_core` is raised to it
/// (`lensrig deblur --tile` refuses one).
pub const MIN_TILE_CORE: usize = 16;

/// The smallest default tile core (px): the kernel side rounded up to a multiple of 16, and
/// at least 48 px; below it the solve windows are mostly margin (the cost per restored pixel
/// grows as `(c + o + 2m)² / c²`, `o` the blend band, `m ∝ k` the margin).
fn core_floor(grid: &PsfGrid) -> usize {
    grid.kernel_size.next_multiple_of(16).max(48)
}

/// The default tile core (px) and its tile-centre kernel error (docs/deconvolution.md "Tile
/// size"): the largest core, in 16-px steps from the spacing rule (the PSF grid spacing and the
/// FFT budget of 512-px windows) down to [`core_floor`] (or the spacing rule's core where that
/// is smaller), whose error is at most [`TILE_KERNEL_ERROR`]; the floor when none is (the
/// report warns above twice the bound).
fn default_core(grid: &PsfGrid, opts: &DeconvOptions, margin: usize, w: usize, h: usize) -> (usize, f64) {
    let budget = 512usize.saturating_sub(2 * margin + opts.overlap).max(96);
    let spacing = |v: &[f64]| if v.len() > 1 { (v[1] - v[0]).abs() as usize } else { usize::MAX };
    let gs = spacing(&grid.column_xs()).min(spacing(&grid.row_ys()));
    // small cores follow a quickly varying PSF; on a sparse grid (12-MP captures, spacing
    // ~1000 px) a core of a sixth of the spacing loses ~0.04 dB and saves a quarter of the work
    let cap = if opts.unknown_boundary { budget.min((gs / 6).max(96)) } else { budget };
    let spaced = (gs.saturating_mul(3) / 2).clamp(48, cap);
    let floor = core_floor(grid).min(spaced);
    // cores that give the same tiles have the same error: evaluate each layout once
    let layout = |c: usize| (w.div_ceil(c), h.div_ceil(c));
    let mut core = spaced;
    let mut last: Option<((usize, usize), f64)> = None;
    loop {
        let e = match last {
            Some((l, e)) if l == layout(core) => e,
            _ => tiles::tile_kernel_error(grid, w, h, core, opts.overlap),
        };
        if e <= TILE_KERNEL_ERROR || core <= floor {
            return (core, e);
        }
        last = Some((layout(core), e));
        core = core.saturating_sub(16).max(floor);
    }
}

/// Adds a restored tile's kept part (window of width `pw`), weighted by the spans' blending
/// ramps, into the output planes.
fn blend_tile(out: &mut [Plane], restored: &[Vec<f32>], sx: &tiles::Span, sy: &tiles::Span, pw: usize) {
    let (ox, oy) = ((sx.keep0 as isize - sx.window0) as usize, (sy.keep0 as isize - sy.window0) as usize);
    let wx: Vec<f32> = (sx.keep0..sx.keep1).map(|x| sx.weight(x)).collect();
    for y in sy.keep0..sy.keep1 {
        let wy = sy.weight(y);
        let ry = oy + (y - sy.keep0);
        for (c, plane) in out.iter_mut().enumerate() {
            let w = plane.width;
            let src = &restored[c][ry * pw + ox..ry * pw + ox + wx.len()];
            let dst = &mut plane.data[y * w + sx.keep0..y * w + sx.keep1];
            for ((d, s), a) in dst.iter_mut().zip(src).zip(&wx) {
                *d += wy * a * s;
            }
        }
    }
}

/// Shared settings of every tile.
pub struct TileSetup<'a> {
    pub width: usize,
    pub height: usize,
    pub lambda: &'a [f32],
    pub order: &'a [usize],
    pub opts: &'a DeconvOptions,
    /// Where the window sits in the image and the grid it was blurred with (for the exact
    /// operator); `None`: the tile kernel only.
    pub field: Option<FieldWindow<'a>>,
    /// The variance-weighted data term ([`DeconvOptions::law_data_weight`]); `None`: unweighted.
    pub data_weight: Option<DataWeight<'a>>,
}

/// Variance-weighted data term (docs/notes/deblur-history.md "Issue-12, m16"): data pixel `k` of
/// channel `c` gets the weight
///
/// ```text
/// w_k = min(V_ref,c / V_c(j̃_k), W_MAX),     j̃ = G_1 * j (a 1-px Gaussian, clamped to [0, 1])
/// ```
///
/// `V_c(x) = g_c x + r_c²` the noise law (linear axis), `V_ref,c` the variance `λ_c = κ V_ref,c`
/// was set at (the tile's mean level), so `Σ_k w_k (Bx − j)_k²` is `V_ref` times the
/// Gaussian approximation `Σ_k (Bx − j)_k² / V(j̃_k)` of the Poisson–Gaussian log-likelihood
/// and the prior keeps its scale. `W_MAX` = 10³ only keeps the weight finite where `r = 0`
/// and the input is black. Multiplies the 0/1 boundary and saturation masks.
#[derive(Clone, Copy)]
pub struct DataWeight<'a> {
    pub law: &'a crate::profile::noise::NoiseLaw,
    /// `V_ref,c` per channel.
    pub reference: &'a [f32],
}

impl<'a> DataWeight<'a> {
    /// Largest weight (numerical guard, see [`DataWeight`]).
    pub const W_MAX: f32 = 1e3;

    /// The weight when `opts.law_data_weight` is set and `law` is signal-dependent.
    pub fn new(opts: &DeconvOptions, law: Option<&'a crate::profile::noise::NoiseLaw>, reference: &'a [f32]) -> Option<Self> {
        let law = law.filter(|l| opts.law_data_weight && l.gain.iter().any(|g| *g > 0.0))?;
        (!reference.is_empty()).then_some(Self { law, reference })
    }

    /// The weights `w_k` of channel `c`'s `w × h` window `data` (periodic smoothing).
    pub fn weights(&self, c: usize, data: &[f32], w: usize, h: usize) -> Vec<f32> {
        let level = gaussian_blur_periodic(data, w, h, 1.0);
        let reference = self.reference.get(c).copied().unwrap_or(0.0).max(0.0);
        level.iter().map(|v| (reference / self.law.variance(c, v.clamp(0.0, 1.0)).max(1e-30)).min(Self::W_MAX)).collect()
    }
}

/// A tile window's place in the image.
pub struct FieldWindow<'a> {
    pub grid: &'a PsfGrid,
    pub x0: isize,
    pub y0: isize,
    pub image_width: usize,
    pub image_height: usize,
}

/// Counters of one tile.
#[derive(Clone, Copy, Debug, Default)]
pub struct TileStats {
    pub cp_iterations: usize,
    pub cg_iterations: usize,
    pub levels: usize,
    /// Saturated window pixels (all channels).
    pub saturated: usize,
}

/// The per-pixel prior weight `(g'(v̄) / g'(0.18))^γ` for a `w × h` window of linear data
/// (`None` when the transfer is linear or `γ = 0`).
pub fn transfer_weight_map(data: &[f32], w: usize, h: usize, transfer: Option<crate::image::Transfer>, gamma: f32, smooth: f32) -> Option<Vec<f32>> {
    let t = transfer.filter(|t| *t != crate::image::Transfer::Linear && gamma != 0.0)?;
    let slope = |v: f32| {
        let v = v.clamp(1e-4, 1.0);
        let d = 1e-3 * v;
        (t.encode(v + d) - t.encode(v - d)) / (2.0 * d)
    };
    let reference = slope(0.18);
    let mean = gaussian_blur_periodic(data, w, h, smooth.max(0.5));
    Some(mean.iter().map(|v| (slope(*v) / reference).powf(gamma)).collect())
}

/// Circular convolution of `v` with a kernel spectrum.
fn convolve_spec(fft: &Fft2, v: &[f32], ks: &KernelSpectrum) -> Vec<f32> {
    let mut s = fft.forward(v);
    s.iter_mut().zip(&ks.b).for_each(|(a, b)| *a *= b);
    fft.inverse(s)
}

/// 0/1 data weights that drop saturated pixels (`None` for channels without any, or without a
/// saturation level); counts them into `stats.saturated`.
fn saturation_masks(windows: &[Vec<f32>], saturation: Option<f32>, stats: &mut TileStats) -> Vec<Option<Vec<f32>>> {
    windows
        .iter()
        .map(|win| {
            let thr = saturation?;
            let n = win.iter().filter(|v| **v >= thr).count();
            stats.saturated += n;
            (n > 0).then(|| win.iter().map(|v| if *v >= thr { 0.0 } else { 1.0 }).collect())
        })
        .collect()
}

/// Pyramid depth: halve while the kernel stays informative (≥ 11 px) and the domain stays
/// sizeable (≥ 32 px, divisible).
fn pyramid_depth(kernels: &[Plane], width: usize, height: usize, max_levels: usize) -> usize {
    let mut levels = 1;
    let mut ksz = kernels.iter().map(|k| k.width).max().unwrap_or(1);
    while levels < max_levels
        && ksz >= 11
        && width % (1 << levels) == 0
        && height % (1 << levels) == 0
        && width >> levels >= 32
        && height >> levels >= 32
    {
        levels += 1;
        ksz = ksz / 2 + 1;
    }
    levels
}

/// Unknown boundary: data weight 0 within the kernel radius of the window edge (there the
/// periodic `B` wraps around), so the estimate extends past the data instead of being fitted
/// to the mirrored window.
fn mask_boundary(m: Option<Vec<f32>>, k: &Plane, w: usize, h: usize) -> Vec<f32> {
    let (rx, ry) = (k.width / 2, k.height / 2);
    let mut m = m.unwrap_or_else(|| vec![1.0; w * h]);
    for y in 0..h {
        for x in 0..w {
            if x < rx || x + rx >= w || y < ry || y + ry >= h {
                m[y * w + x] = 0.0;
            }
        }
    }
    m
}

/// The dark-region weight `w²` at pyramid level `z`: the share of the other channels that are
/// dark (≤ `threshold`) where this channel's data `own` is dark too, smoothed, squared.
fn dark_region_weight(others: &[&Vec<f32>], own: &[f32], threshold: f32, pw: usize, ph: usize, z: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; pw * ph];
    for o in others {
        t.iter_mut().zip(o.iter()).for_each(|(t, v)| *t += if *v <= threshold { 1.0 } else { 0.0 });
    }
    // the paper's T covers the other channels; also require this channel's data to be
    // dark, so a bright channel is never pulled towards a dark one's flat gradients
    t.iter_mut().zip(own).for_each(|(v, j)| *v = if *j <= threshold { *v / others.len() as f32 } else { 0.0 });
    let wgt = gaussian_blur_periodic(&t, pw, ph, (3.0 / (1u32 << z) as f32).max(0.75));
    wgt.iter().map(|v| v * v).collect::<Vec<f32>>()
}

/// The cross-channel block against the restored channel `o` at pyramid level `z`.
fn cross_channel<'a>(o: &'a [f32], opts: &DeconvOptions, lam: f32, pw: usize, ph: usize, z: usize) -> CrossChannel<'a> {
    if opts.cross_local > 0.0 {
        // β_k = cross · λ / max(ī_l(k), i_l(k), 0.05), ī_l = i_l smoothed: never above
        // cross · λ / i_l, so the term stays ≤ cross · λ |∇x − x ∇i_l / i_l| on point sources
        let sm = gaussian_blur_periodic(o, pw, ph, (opts.cross_local / (1u32 << z) as f32).max(0.75));
        let pixel = sm.iter().zip(o).map(|(v, i)| 1.0 / v.max(*i).max(0.05)).collect();
        return CrossChannel { beta: opts.cross_weight * lam, image: o, grad: gradients(o, pw, ph), pixel: Some(pixel) };
    }
    let mean = o.iter().map(|v| *v as f64).sum::<f64>() / (pw * ph) as f64;
    CrossChannel { beta: opts.cross_weight * lam / (mean as f32).max(0.05), image: o, grad: gradients(o, pw, ph), pixel: None }
}

/// Restores all channels of one tile window (`windows[c]`, `width × height`, linear) blurred
/// by `kernels[c]`; returns the restored windows (periodic domain: crop the margin).
pub fn restore_tile(windows: &[Vec<f32>], kernels: &[Plane], setup: &TileSetup) -> (Vec<Vec<f32>>, TileStats) {
    let (restored, stats, _) = restore_tile_keeping(windows, kernels, setup, false);
    (restored, stats)
}

/// [`restore_tile`], also returning (with `keep`) the finest level's kernel spectra and 0/1
/// data masks ([`TileOperators`]) for the stages after the denoiser.
pub fn restore_tile_keeping(windows: &[Vec<f32>], kernels: &[Plane], setup: &TileSetup, keep: bool) -> (Vec<Vec<f32>>, TileStats, Option<TileOperators>) {
    let opts = setup.opts;
    let nch = windows.len();
    let mut stats = TileStats::default();
    let pyr = tile_pyramid(windows, kernels, setup, keep, &mut stats);
    let mut spectra: Vec<Vec<rustfft::num_complex::Complex32>> = vec![Vec::new(); if keep { nch } else { 0 }];
    let mut prev: Option<Vec<Vec<f32>>> = None;
    for z in (0..stats.levels).rev() {
        let (pw, ph) = (setup.width >> z, setup.height >> z);
        let fft = Fft2::plan(pw, ph);
        let mut restored: Vec<Option<Vec<f32>>> = vec![None; nch];
        for (pos, &c) in setup.order.iter().enumerate() {
            let ksp = KernelSpectrum::new(&fft, &kernel_to_origin(&pyr.ks[z][c], pw, ph));
            if keep && z == 0 {
                spectra[c] = ksp.b.clone();
            }
            let data = &pyr.js[z][c];
            // warm start of the level's first (non-residual) solve: the upsampled coarser result,
            // or the blurred data at the coarsest level
            let start = match &prev {
                Some(p) => pyramid::upsample_nearest(&p[c], pw / 2, ph / 2),
                None => data.clone(),
            };
            let others: Vec<&Vec<f32>> = setup.order[..pos].iter().filter_map(|&l| restored[l].as_ref()).collect();
            let dark_w2 = (opts.dark_weight > 0.0 && !others.is_empty())
                .then(|| dark_region_weight(&others, data, opts.dark_threshold, pw, ph, z))
                .filter(|w2: &Vec<f32>| w2.iter().any(|v| *v > 1e-4));
            let weight = transfer_weight_map(data, pw, ph, opts.output_transfer, opts.transfer_weight, (2.0 / (1u32 << z) as f32).max(0.75));
            let cs = ChannelSolve { opts, fft: &fft, ksp: &ksp, mask: pyr.ms[z][c].as_deref(), others: &others, dark_w2, weight, pw, ph, z };
            let field = setup.field.as_ref().filter(|_| z == 0);
            let est = restore_channel(&cs, data, start, setup.lambda[c], field.map(|f| (f, c)), &mut stats);
            restored[c] = Some(est);
        }
        prev = Some(restored.into_iter().map(|r| r.unwrap_or_default()).collect());
    }
    let ops = keep.then(|| TileOperators { spectra, masks: pyr.data_masks.unwrap_or_default() });
    (prev.unwrap_or_default(), stats, ops)
}

/// A tile's per-level data, index 0 = finest.
struct TilePyramid {
    /// Blurred windows per level and channel.
    js: Vec<Vec<Vec<f32>>>,
    /// Data masks per level and channel (`None`: all pixels count).
    ms: Vec<Vec<Option<Vec<f32>>>>,
    /// Kernels per level and channel.
    ks: Vec<Vec<Plane>>,
    /// The finest level's 0/1 masks (unknown boundary and saturation, before any data weight)
    /// per channel, when [`restore_tile_keeping`] keeps them.
    data_masks: Option<Vec<Vec<u8>>>,
}

/// Pyramid stage of [`restore_tile`]: data masks, depth, and the downsampled windows, masks and
/// kernels; sets `stats.levels` and `stats.saturated`.
fn tile_pyramid(windows: &[Vec<f32>], kernels: &[Plane], setup: &TileSetup, keep: bool, stats: &mut TileStats) -> TilePyramid {
    let opts = setup.opts;
    // saturation masks (only channels that have saturated pixels)
    let masks0 = saturation_masks(windows, opts.saturation, stats);
    // pyramid depth: halve while the kernel stays informative and the domain stays sizeable
    let levels = pyramid_depth(kernels, setup.width, setup.height, opts.max_levels);
    stats.levels = levels;
    // unknown boundary: data weight 0 within the kernel radius of the window edge (there the
    // periodic B wraps around), so the estimate extends past the data instead of being fitted
    // to the mirrored window
    let masks0: Vec<Option<Vec<f32>>> = if opts.unknown_boundary {
        masks0.into_iter().zip(kernels).map(|(m, k)| Some(mask_boundary(m, k, setup.width, setup.height))).collect()
    } else {
        masks0
    };
    // the 0/1 masks the stages after the denoiser use: the boundary is masked there even when
    // the solver's data term is not
    let data_masks = keep.then(|| {
        masks0
            .iter()
            .zip(kernels)
            .map(|(m, k)| {
                let m = if opts.unknown_boundary { m.clone() } else { Some(mask_boundary(m.clone(), k, setup.width, setup.height)) };
                m.map(|m| m.iter().map(|v| u8::from(*v > 0.5)).collect()).unwrap_or_else(|| vec![1; setup.width * setup.height])
            })
            .collect()
    });
    let masks0: Vec<Option<Vec<f32>>> = match &setup.data_weight {
        Some(dw) => masks0
            .into_iter()
            .enumerate()
            .map(|(c, m)| {
                let wt = dw.weights(c, &windows[c], setup.width, setup.height);
                Some(match m {
                    Some(m) => m.iter().zip(&wt).map(|(a, b)| a * b).collect(),
                    None => wt,
                })
            })
            .collect(),
        None => masks0,
    };
    let mut js: Vec<Vec<Vec<f32>>> = vec![windows.to_vec()];
    let mut ms: Vec<Vec<Option<Vec<f32>>>> = vec![masks0];
    let mut ks: Vec<Vec<Plane>> = vec![kernels.to_vec()];
    for z in 1..levels {
        let (pw, ph) = (setup.width >> (z - 1), setup.height >> (z - 1));
        js.push(js[z - 1].iter().map(|v| pyramid::downsample_periodic(v, pw, ph)).collect());
        ms.push(ms[z - 1].iter().map(|m| m.as_ref().map(|m| pyramid::downsample_mask_periodic(m, pw, ph))).collect());
        ks.push(ks[z - 1].iter().map(pyramid::downsample_kernel).collect());
    }
    TilePyramid { js, ms, ks, data_masks }
}

/// One channel's solve setting at pyramid level `z` (`pw × ph`).
struct ChannelSolve<'s> {
    opts: &'s DeconvOptions,
    fft: &'s Fft2,
    ksp: &'s KernelSpectrum,
    mask: Option<&'s [f32]>,
    /// Channels restored before this one at this level.
    others: &'s [&'s Vec<f32>],
    /// Dark-region weight `w²` (`None`: no dark-region term).
    dark_w2: Option<Vec<f32>>,
    /// Per-pixel prior weight from the output transfer.
    weight: Option<Vec<f32>>,
    pw: usize,
    ph: usize,
    z: usize,
}

impl ChannelSolve<'_> {
    /// Solve stage of [`restore_tile`]: one ADMM (or Chambolle–Pock) solve for `data` at prior
    /// weight `lam`, warm started at `warm`; `est` is the current estimate (dark-region target).
    fn solve(&self, data: &[f32], warm: Vec<f32>, est: &[f32], lam: f32, stats: &mut TileStats) -> Vec<f32> {
        let (opts, others, pw, ph, z) = (self.opts, self.others, self.pw, self.ph, self.z);
        let n = pw * ph;
        let cross: Vec<CrossChannel> = if opts.cross_weight > 0.0 {
            others.iter().map(|o| cross_channel(o, opts, lam, pw, ph, z)).collect()
        } else {
            Vec::new()
        };
        let dark = self.dark_w2.as_ref().map(|w2| {
            let mut target = vec![0.0; n];
            for o in others {
                let diff: Vec<f32> = o.iter().zip(est).map(|(a, b)| a - b).collect();
                add_weighted_gradient_normal(&diff, w2, pw, ph, &mut target);
            }
            DarkTerm { lambda_b: opts.dark_weight, w2: w2.clone(), others: others.len(), target }
        });
        let mut p = ChannelProblem::new(self.fft, self.ksp, data, self.mask, lam, &cross, dark);
        p.set_weight(self.weight.as_deref());
        p.order2_weight = opts.order2_weight;
        if opts.reweight_power != 1.0 {
            p.reweight = Some((opts.reweight_power, opts.reweight_eps));
        }
        let mut x = warm;
        if opts.unknown_boundary {
            p.data_split = Some(2.0 * opts.data_split_rho);
        }
        if opts.positivity {
            // the restored channel est + x stays non-negative
            p.lower_bound = Some(est.iter().map(|e| -e).collect());
        }
        if opts.admm_rho > 0.0 && p.admm_applies() {
            stats.cg_iterations += p.solve_admm(&mut x, opts.max_iterations, opts.admm_rho * lam, opts.admm_cg_iterations);
            stats.cp_iterations += opts.max_iterations;
            return x;
        }
        let mut y = vec![0.0; crate::solve::primal_dual::PrimalDual::dual_len(&p)];
        let l = operator_norm(&PrimalDualOperator(&p), 15, NORM_SAFETY).max(1e-12);
        let cp = Options {
            max_iterations: opts.cp_max_iterations,
            min_iterations: 10,
            tolerance: opts.tolerance,
            check_every: 10,
            sigma: opts.step_balance / l,
            theta: 1.0,
        };
        let st = chambolle_pock(&mut p, &mut x, &mut y, &cp, Some(l), |_, _| true);
        stats.cp_iterations += st.iterations;
        stats.cg_iterations += p.counters.cg_iterations;
        x
    }
}

/// Channel stage of [`restore_tile`]: residual deconvolution steps from `start`, then (with
/// `field` = the window and channel, finest level only) defect correction with the exact operator.
fn restore_channel(cs: &ChannelSolve, data: &[f32], start: Vec<f32>, lam0: f32, field: Option<(&FieldWindow, usize)>, stats: &mut TileStats) -> Vec<f32> {
    let (opts, pw, ph) = (cs.opts, cs.pw, cs.ph);
    let n = pw * ph;
    let mut est = vec![0.0; n];
    let mut lam = lam0;
    for step in 0..opts.residual_steps.max(1) {
        let blurred = convolve_spec(cs.fft, &est, cs.ksp);
        let residual: Vec<f32> = data.iter().zip(&blurred).map(|(j, b)| j - b).collect();
        // step 0 solves for the image itself (warm started), later steps for increments
        let warm = if step == 0 { start.clone() } else { vec![0.0; n] };
        let x = cs.solve(&residual, warm, &est, lam, stats);
        est.iter_mut().zip(&x).for_each(|(e, d)| *e += d);
        lam /= 3.0;
    }
    // defect correction with the exact field-varying operator A (finest level only):
    // solve with the tile's kernel B against data corrected by (A − B)·estimate
    if opts.field_passes > 0 {
        if let Some((f, c)) = field {
            let op = FieldOperator::new(f.grid, c, f.x0, f.y0, pw, ph, f.image_width, f.image_height);
            let mut ax = vec![0.0; n];
            for _ in 0..opts.field_passes {
                op.apply(&est, &mut ax);
                let bx = convolve_spec(cs.fft, &est, cs.ksp);
                let corrected: Vec<f32> = data.iter().zip(&ax).zip(&bx).map(|((j, a), b)| j - a + b).collect();
                est = cs.solve(&corrected, est.clone(), &vec![0.0; n], lam0, stats);
            }
        }
    }
    est
}

#[cfg(test)]
mod tests;
