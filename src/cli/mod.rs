//! The command line: arguments → a resolved plan → one function per command.
//!
//! Every command returns `anyhow::Result`; `main` prints the one-line cause on stderr and
//! exits with status 2 on error, 0 on success.

pub mod bench;
pub mod calibrate;
pub mod capture;
pub mod demo;
pub mod export;
pub mod report;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use lensrig::estimate::register::RegistrationModel;
use lensrig::estimate::{estimate, EstimateOptions};
use lensrig::fsutil::Overwrite;
use lensrig::image::io::{read_image, read_pair, write_png16};
use lensrig::image::{Image, Transfer};
use lensrig::optics::forward::blur_channel;
use lensrig::profile::Profile;
use lensrig::target::TargetSpec;
use std::path::{Path, PathBuf};

#[derive(Parser, Debug)]
#[command(name = "lensrig", version, about = "Measure a simple lens on a calibration rig, write its profile, restore and diagnose images")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Write a printable random-noise calibration target (PNG + TOML description).
    Target(TargetArgs),
    /// Estimate a lens profile (per-tile, per-channel PSFs) from a wide-open / pinhole pair.
    Estimate(EstimateArgs),
    /// Predict the wide-open capture from a sharp (pinhole) image through a profile.
    Simulate(SimulateArgs),
    /// Render a calibration pair with the lens simulator, estimate its profile and compare
    /// with the truth (no hardware needed).
    Demo(demo::DemoArgs),
    /// Time PSF estimation on the benchmark sizes and print a table.
    Bench(bench::BenchArgs),
    /// Restore an image taken through the profiled lens (cross-channel deconvolution).
    Deblur(lensrig::deconv::cli::DeblurArgs),
    /// Run a capture session on the rig (moves, exposures, frames on disk).
    Capture(capture::CaptureArgs),
    /// Load and validate a rig config; errors name the file, line and key.
    CheckConfig(capture::CheckConfigArgs),
    /// Capture with the rig, estimate a profile per stage position, write an HTML report.
    Calibrate(calibrate::CalibrateArgs),
    /// Find where the profile's simulation and the recording disagree, name the missing
    /// physics, model it and refit (report.json, predictions and an HTML report).
    Diagnose(lensrig::diagnose::cli::DiagnoseArgs),
    /// MTF and colour report of a profile or profile set.
    Report(report::ReportArgs),
    /// Lens data for other tools (lensfun).
    #[command(subcommand)]
    Export(export::ExportCommand),
}

#[derive(Args, Debug)]
pub struct TargetArgs {
    /// Output path without extension: writes OUT.png and OUT.toml.
    #[arg(long)]
    pub out: PathBuf,
    /// Paper size: A3, A4, A5 or Letter (landscape).
    #[arg(long, default_value = "A4")]
    pub paper: String,
    #[arg(long, default_value_t = 300)]
    pub dpi: u32,
    /// Printer dots per noise cell.
    #[arg(long, default_value_t = 4)]
    pub cell: u32,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Replace existing files.
    #[arg(long)]
    pub force: bool,
}

#[derive(Args, Debug)]
pub struct EstimateArgs {
    /// Wide-open capture (PNG/TIFF).
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub open: Option<PathBuf>,
    /// Pinhole-aperture capture of the same target.
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub pinhole: Option<PathBuf>,
    /// A capture session (from `capture`): one profile per stage position in OUT/<pair key>/.
    #[arg(long)]
    pub session: Option<PathBuf>,
    /// Profile directory to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Kernel size (odd, pixels); default: measured from the data.
    #[arg(long)]
    pub kernel: Option<usize>,
    /// Spacing of the PSF centres in pixels; default: about 1.8 kernels (each centre is fitted
    /// on a window of about four kernels, then all kernels jointly).
    #[arg(long)]
    pub tile: Option<usize>,
    /// How the files encode light: linear (raw, machine vision) or srgb (webcams).
    #[arg(long, default_value = "linear")]
    pub transfer: Transfer,
    /// Black level to subtract (full-scale units, e.g. 0.0625 for 4096/65535).
    #[arg(long)]
    pub black_level: Option<f32>,
    /// Global motion between the captures: none, translation, similarity.
    #[arg(long, default_value = "translation")]
    pub register: RegistrationModel,
    /// Multiplier of the automatic TV weight.
    #[arg(long, default_value_t = 1.0)]
    pub lambda_scale: f64,
    #[arg(long, default_value_t = 150)]
    pub max_iterations: usize,
    /// Iterations of the joint refinement of all kernels with the interpolated forward model
    /// (at most; it stops when χ² stalls); 0 keeps the per-window fits.
    #[arg(long, default_value_t = 40)]
    pub joint_iterations: usize,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct SimulateArgs {
    #[arg(long)]
    pub profile: PathBuf,
    /// Sharp (pinhole) image, same size and encoding as the profile's source images.
    #[arg(long)]
    pub sharp: PathBuf,
    /// Predicted wide-open image (16-bit PNG); an existing file is kept unless `--force`.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace OUT if it exists.
    #[arg(long)]
    pub force: bool,
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Target(a) => run_target(&a),
        Command::Estimate(a) => run_estimate(&a),
        Command::Simulate(a) => run_simulate(&a),
        Command::Demo(a) => demo::run(&a),
        Command::Bench(a) => bench::run(&a),
        Command::Deblur(a) => lensrig::deconv::cli::run(&a),
        Command::Capture(a) => capture::run_capture(&a),
        Command::CheckConfig(a) => capture::run_check_config(&a),
        Command::Calibrate(a) => calibrate::run(&a),
        Command::Diagnose(a) => lensrig::diagnose::cli::run(&a),
        Command::Report(a) => report::run(&a),
        Command::Export(c) => export::run(&c),
    }
}

fn run_target(a: &TargetArgs) -> Result<()> {
    let spec = TargetSpec::new(&a.paper, a.dpi, a.cell, a.seed)?;
    let dir = a.out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = a.out.file_name().context("--out needs a file name")?.to_string_lossy().to_string();
    spec.write(dir, &name, if a.force { Overwrite::Replace } else { Overwrite::Never })?;
    let (w, h) = spec.pixels();
    let (cw, ch) = spec.cells();
    println!("wrote {}.png ({w}x{h} px at {} DPI, {cw}x{ch} noise cells) and {}.toml", a.out.display(), a.dpi, a.out.display());
    Ok(())
}

/// Reads a pair, tags the transfer function the user declared, and estimates.
pub fn estimate_files(open: &Path, pinhole: &Path, opts: &EstimateOptions, transfer: Transfer) -> Result<lensrig::estimate::Estimate> {
    let (mut o, mut p) = read_pair(open, pinhole)?;
    o.transfer = transfer;
    p.transfer = transfer;
    let mut est = estimate(&o, &p, opts)?;
    est.profile.meta.source.open = Some(open.display().to_string());
    est.profile.meta.source.pinhole = Some(pinhole.display().to_string());
    Ok(est)
}

fn run_estimate(a: &EstimateArgs) -> Result<()> {
    let opts = EstimateOptions {
        kernel_size: a.kernel,
        tile: a.tile,
        lambda_scale: a.lambda_scale,
        max_iterations: a.max_iterations,
        joint_iterations: a.joint_iterations,
        registration: a.register,
        black_level: a.black_level.map(|b| vec![b]).unwrap_or_default(),
        progress: !a.quiet,
        ..Default::default()
    };
    if let Some(k) = a.kernel {
        if k % 2 == 0 {
            bail!("--kernel must be odd, got {k}");
        }
    }
    let (open, pinhole) = match (&a.open, &a.pinhole, &a.session) {
        (_, _, Some(s)) => {
            let done = capture::estimate_session(s, &a.out, &opts, !a.quiet)?;
            for (p, e) in &done {
                println!("wrote {}: {} tiles, {}px kernels", a.out.join(&p.key).display(), e.profile.grid.tile_count(), e.profile.grid.kernel_size);
            }
            return Ok(());
        }
        (Some(o), Some(p), None) => (o, p),
        _ => bail!("give --open and --pinhole, or --session"),
    };
    let est = estimate_files(open, pinhole, &opts, a.transfer)?;
    est.profile.save(&a.out)?;
    let m = &est.profile.meta;
    println!(
        "wrote {}: {} channel(s), {}x{} tiles, {}px kernels, exposure ratio {:?}, {:.1} s",
        a.out.display(),
        m.source.channels.len(),
        m.psf.columns,
        m.psf.rows,
        m.psf.kernel_size,
        m.exposure_ratio.iter().map(|v| format!("{v:.4}")).collect::<Vec<_>>(),
        m.estimation.seconds
    );
    Ok(())
}

/// The wide-open image a profile predicts from a sharp image, in the profile's encoding.
///
/// # Errors
/// When the image's size or channel count differs from the profile's source.
pub fn predict(profile: &Profile, sharp: &Image, sharp_path: &Path) -> Result<Image> {
    let src = &profile.meta.source;
    if sharp.width() != src.width || sharp.height() != src.height {
        bail!(
            "{}: image is {}x{} but the profile was estimated from {}x{} images",
            sharp_path.display(),
            sharp.width(),
            sharp.height(),
            src.width,
            src.height
        );
    }
    if sharp.channel_count() != profile.grid.channels.len() {
        bail!("{}: image has {} channel(s), the profile {}", sharp_path.display(), sharp.channel_count(), profile.grid.channels.len());
    }
    if !profile.meta.corrections.is_empty() {
        // a profile refitted by `lensrig diagnose`: its physics applies (module docs of
        // `diagnose::model`)
        return lensrig::diagnose::model::apply_corrections(profile, sharp).with_context(|| format!("{}: applying the profile's [corrections]", sharp_path.display()));
    }
    let black = &src.black_level;
    let planes: Vec<_> = sharp
        .planes
        .iter()
        .enumerate()
        .map(|(c, p)| {
            let b = black.get(c).or(black.first()).copied().unwrap_or(0.0);
            let lin = p.map(|v| src.transfer.decode(v) - b);
            let mut out = blur_channel(&lin, &profile.grid, c);
            let s = profile.meta.exposure_ratio[c] as f32;
            out.data.iter_mut().for_each(|v| *v = src.transfer.encode(*v * s + b));
            out
        })
        .collect();
    let mut img = Image::new(planes);
    img.channels = profile.grid.channels.clone();
    img.transfer = src.transfer;
    img.format = src.sample_format;
    Ok(img)
}

fn run_simulate(a: &SimulateArgs) -> Result<()> {
    if !a.force && a.out.exists() {
        bail!("{} already exists and is never overwritten (use --force to replace it)", a.out.display());
    }
    let profile = Profile::load(&a.profile)?;
    let mut sharp = read_image(&a.sharp)?;
    sharp.transfer = profile.meta.source.transfer;
    let out = predict(&profile, &sharp, &a.sharp)?;
    write_png16(&a.out, &out, if a.force { Overwrite::Replace } else { Overwrite::Never })?;
    println!("wrote {} ({}x{}, {} channel(s), 16-bit)", a.out.display(), out.width(), out.height(), out.channel_count());
    Ok(())
}
