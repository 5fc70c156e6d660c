//! `lensrig deblur`: restore a capture with a lens profile
//! ([`lensrig::deconv::capture::restore_file`]; the module docs there give the steps).

use super::refuse_existing;
use anyhow::Result;
use clap::Args;
use lensrig::deconv::capture::{restore_file, RestoreFile, Restored};
use lensrig::image::validate::InvalidPixels;
use lensrig::deconv::DeconvOptions;
use lensrig::fsutil::Overwrite;
use lensrig::image::Transfer;
use std::path::PathBuf;

/// Arguments of `lensrig deblur`.
#[derive(Args, Debug, Clone)]
pub struct DeblurArgs {
    /// Lens profile directory (written by `lensrig estimate`), or a profile set (a directory
    /// with `index.toml`; then give --distance and --aperture).
    #[arg(long, value_name = "PROFILE_DIR")]
    pub profile: PathBuf,
    /// Focus distance (m) of the capture, to choose or interpolate within a profile set.
    #[arg(long)]
    pub distance: Option<f64>,
    /// Aperture (f-number) of the capture, to choose within a profile set.
    #[arg(long)]
    pub aperture: Option<f64>,
    /// Blurred capture (PNG or TIFF) taken through the profiled lens.
    #[arg(long = "in", value_name = "BLURRED")]
    pub input: PathBuf,
    /// Restored image, 16-bit PNG; an existing file is kept unless `--force`.
    #[arg(long, value_name = "RESTORED.png")]
    pub out: PathBuf,
    /// Replace RESTORED.png if it exists.
    #[arg(long)]
    pub force: bool,
    /// Encoding of the input values (default: the profile's source encoding).
    #[arg(long)]
    pub transfer: Option<Transfer>,
    /// Prior weight λ, one value for all channels or one per channel (default: from the noise).
    #[arg(long, value_delimiter = ',')]
    pub lambda: Option<Vec<f32>>,
    /// Cross-channel weight relative to λ (0: channels independently).
    #[arg(long, default_value_t = DeconvOptions::default().cross_weight)]
    pub cross_weight: f32,
    /// Dark-region weight λ_b (0 disables the term).
    #[arg(long, default_value_t = DeconvOptions::default().dark_weight)]
    pub dark_weight: f32,
    /// Residual deconvolution steps per scale (λ, λ/3, …).
    #[arg(long, default_value_t = DeconvOptions::default().residual_steps)]
    pub residual_steps: usize,
    /// ADMM iterations per solve.
    #[arg(long, default_value_t = DeconvOptions::default().max_iterations)]
    pub iterations: usize,
    /// Linear value at or above which pixels count as saturated (values > 1 disable).
    #[arg(long, default_value_t = 0.99)]
    pub saturation: f32,
    /// Exclude NaN/Inf pixels of the input from the data term like saturated ones (default:
    /// refuse the image); needs a saturation level ≤ 1.
    #[arg(long)]
    pub mask_invalid: bool,
    /// Noise of the input on the linear axis: `profile` (the profile's stored law, or an
    /// estimate when it has none), `estimate` (from the photo, white Gaussian), a σ, or
    /// `gain=G,read=R` (Var = G·x + R², full-scale units; `:`-separated values per channel) for
    /// photos taken at another ISO or exposure than the calibration.
    #[arg(long, default_value = "profile")]
    pub noise: lensrig::deconv::noise::NoiseSource,
    /// Turn off the no-harm rule (flat regions falling back towards the input where the
    /// restoration is noisier than it).
    #[arg(long)]
    pub no_harm_off: bool,
    /// Noise model of the denoising stage: `coloured` (each opponent plane's noise per DCT
    /// coefficient, propagated through the solver from the channel's PSF and the noise level) or
    /// `flat` (a flat spectrum at a multiple of the input σ).
    #[arg(long, value_parser = ["flat", "coloured"], default_value = if DeconvOptions::default().coloured_noise { "coloured" } else { "flat" })]
    pub denoise_noise: String,
    /// Weight each pixel of the data term by the inverse of the noise law, `V_ref / V(x)`
    /// (Poisson–Gaussian likelihood, Gaussian approximation). Opt-in: it lifts low-light and
    /// smooth shot-noise-limited photographs and loses on bright star fields
    /// (docs/notes/deblur-history.md, "Issue-12, m16"). No effect under a white noise law.
    #[arg(long)]
    pub law_weighted_data: bool,
    /// Return texture after the denoising stage: the part of the data residual whose power
    /// exceeds the noise law's floor, Wiener-deconvolved and added back. Opt-in: +0.0 to +0.16 dB
    /// on the low-light and textured matrix cells, no tuning-subset loss, and no held-out cell
    /// crossed +1.5 dB over the best peer (docs/notes/deblur-history.md, "Issue-12, m17"). The residual
    /// is taken against each tile's centre kernel: on a PSF grid much finer than 50 px it can
    /// return model mismatch as texture (−0.04 to −0.74 dB on a 32-px grid).
    #[arg(long)]
    pub texture_return: bool,
    /// Largest tile core in pixels, at least 16 (default: the largest whose tile-centre kernel
    /// error is within 5 %, from the PSF grid's spacing down to max(48, kernel side); see
    /// docs/deconvolution.md "Tile size").
    #[arg(long)]
    pub tile: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

impl DeblurArgs {
    /// Solver options these arguments select.
    pub fn options(&self) -> DeconvOptions {
        DeconvOptions {
            lambda: self.lambda.clone(),
            cross_weight: self.cross_weight,
            dark_weight: self.dark_weight,
            residual_steps: self.residual_steps,
            max_iterations: self.iterations,
            saturation: (self.saturation <= 1.0).then_some(self.saturation),
            tile_core: self.tile,
            noise: self.noise.clone(),
            coloured_noise: self.denoise_noise == "coloured",
            no_harm: lensrig::deconv::noharm::NoHarmOptions { enabled: !self.no_harm_off, ..Default::default() },
            law_data_weight: self.law_weighted_data,
            texture_return: self.texture_return,
            ..DeconvOptions::default()
        }
    }
}

/// Runs `lensrig deblur`.
///
/// # Errors
/// An existing output without `--force`, and every [`lensrig::deconv::capture::RestoreError`].
pub fn run(args: &DeblurArgs) -> Result<()> {
    if let Some(t) = args.tile.filter(|&t| t < lensrig::deconv::MIN_TILE_CORE) {
        anyhow::bail!("--tile {t}: a tile core must be at least {} px", lensrig::deconv::MIN_TILE_CORE);
    }
    refuse_existing(&args.out, args.force)?;
    let job = RestoreFile {
        profile: &args.profile,
        input: &args.input,
        out: &args.out,
        transfer: args.transfer,
        overwrite: if args.force { Overwrite::Replace } else { Overwrite::Never },
        progress: !args.quiet,
        distance: args.distance,
        aperture: args.aperture,
        invalid: if args.mask_invalid { InvalidPixels::Mask } else { InvalidPixels::Refuse },
    };
    let Restored { report, notes } = restore_file(&job, &args.options())?;
    for note in notes {
        eprintln!("lensrig: note: {note}");
    }
    for line in report.no_harm.describe(&report.channels) {
        eprintln!("lensrig: note: {line}");
    }
    for w in &report.warnings {
        eprintln!("lensrig: warning: {w}");
    }
    if !args.quiet {
        eprintln!(
            "deblur: {} tiles of {}x{} (core {} px, tile-centre kernel error {:.1} %), noise σ {:?}, λ {:?}, {} CP / {} CG iterations, {} saturated px -> {}",
            report.tiles,
            report.window[0],
            report.window[1],
            report.tile_core,
            100.0 * report.tile_kernel_error,
            report.noise_sigma,
            report.lambda,
            report.cp_iterations,
            report.cg_iterations,
            report.saturated_pixels,
            args.out.display()
        );
    }
    Ok(())
}
