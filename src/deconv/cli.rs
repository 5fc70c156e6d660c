//! `lensrig deblur`: restore a capture with a lens profile.
//!
//! Reads the input as stored, decodes it with the profile's source transfer curve (or
//! `--transfer`), subtracts the profile's black level, restores the linear planes with
//! [`super::deblur`], adds the black level back, re-encodes with the same curve and writes a
//! 16-bit PNG of the input's size. The input must have the profile's channel count and the size
//! the profile was measured on (tile centres are pixel positions).

use super::{deblur, DeconvOptions};
use crate::fsutil::Overwrite;
use crate::image::io::{read_image, write_png16};
use crate::image::Transfer;
use anyhow::{bail, Context};
use std::path::PathBuf;

/// Arguments of `lensrig deblur`.
#[derive(clap::Args, Debug, Clone)]
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
    /// Largest tile core in pixels (default: from the kernel size and the PSF grid).
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
            ..DeconvOptions::default()
        }
    }
}

/// Runs `lensrig deblur`.
///
/// # Errors
/// Unreadable profile or input, a channel count or size that does not match the profile (the
/// message names the file and both values), unwritable output.
pub fn run(args: &DeblurArgs) -> anyhow::Result<()> {
    if !args.force && args.out.exists() {
        bail!("{} already exists and is never overwritten (use --force to replace it)", args.out.display());
    }
    let resolved = crate::profile::set::load_profile_or_set(&args.profile, args.distance, args.aperture).with_context(|| format!("cannot load profile {}", args.profile.display()))?;
    if crate::profile::set::is_set(&args.profile) {
        eprintln!("profile set {}: {}", args.profile.display(), resolved.description);
    }
    let profile = resolved.profile;
    let mut img = read_image(&args.input)?;
    let grid = &profile.grid;
    let src = &profile.meta.source;
    if img.channel_count() != grid.channels.len() {
        bail!(
            "{}: has {} channel(s) but profile {} has {} ({})",
            args.input.display(),
            img.channel_count(),
            args.profile.display(),
            grid.channels.len(),
            grid.channels.join(",")
        );
    }
    if img.width() != src.width || img.height() != src.height {
        bail!(
            "{}: is {}x{} but profile {} was measured on {}x{} images (PSF tiles are pixel positions; crop or resize is not supported)",
            args.input.display(),
            img.width(),
            img.height(),
            args.profile.display(),
            src.width,
            src.height
        );
    }
    if !matches!(img.channel_count(), 1 | 3) {
        bail!("{}: has {} channels; PNG output holds 1 or 3", args.input.display(), img.channel_count());
    }
    let transfer = args.transfer.unwrap_or(src.transfer);
    img.transfer = transfer;
    let mut lin = img.to_linear();
    let black: Vec<f32> = (0..lin.channel_count()).map(|c| src.black_level.get(c).copied().unwrap_or(0.0)).collect();
    for (p, b) in lin.planes.iter_mut().zip(&black) {
        if *b != 0.0 {
            p.data.iter_mut().for_each(|v| *v -= b);
        }
    }
    let mut opts = args.options();
    // the result is re-encoded with `transfer`: weigh the prior as the encoded image will show it
    opts.output_transfer = Some(transfer);
    let bar = if args.quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(0) };
    bar.set_style(
        indicatif::ProgressStyle::with_template("deblur {bar:40} {pos}/{len} tiles {elapsed_precise} (eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let (mut planes, report) = deblur(&lin.planes, grid, &opts, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("cannot restore {}", args.input.display()))?;
    bar.finish_and_clear();
    for (p, b) in planes.iter_mut().zip(&black) {
        if *b != 0.0 {
            p.data.iter_mut().for_each(|v| *v += b);
        }
    }
    lin.planes = planes;
    lin.transfer = Transfer::Linear;
    let out = lin.encoded(transfer);
    write_png16(&args.out, &out, if args.force { Overwrite::Replace } else { Overwrite::Never })?;
    if !args.quiet {
        eprintln!(
            "deblur: {} tiles of {}x{}, noise σ {:?}, λ {:?}, {} CP / {} CG iterations, {} saturated px -> {}",
            report.tiles,
            report.window[0],
            report.window[1],
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::image::{Image, Plane, SampleFormat};
    use crate::profile::{Profile, PsfTable, SourceInfo};
    use std::collections::BTreeMap;
    use std::path::Path;

    fn profile(dir: &Path, w: usize, h: usize, transfer: Transfer) {
        let grid = SyntheticLens::new(9, 3).grid(w, h, 3, 2, 2);
        let source = SourceInfo {
            width: w,
            height: h,
            channels: grid.channels.clone(),
            sample_format: SampleFormat::U16,
            transfer,
            open: None,
            pinhole: None,
            black_level: vec![],
        };
        let table = PsfTable { kernel_size: 9, columns: 2, rows: 2, centers: grid.centers.clone(), tile_size: None, files: BTreeMap::new() };
        Profile { meta: Profile::new_meta(source, vec![1.0; 3], table), grid }.save(dir).unwrap();
    }

    fn args(dir: &Path, input: &str) -> DeblurArgs {
        DeblurArgs {
            profile: dir.join("profile"),
            distance: None,
            aperture: None,
            input: dir.join(input),
            out: dir.join("out.png"),
            transfer: None,
            lambda: None,
            cross_weight: 3.0,
            dark_weight: 0.0,
            residual_steps: 1,
            iterations: 30,
            saturation: 0.99,
            tile: None,
            quiet: true,
            force: true,
        }
    }

    fn write(dir: &Path, name: &str, planes: Vec<Plane>) {
        write_png16(&dir.join(name), &Image::new(planes), Overwrite::Replace).unwrap();
    }

    #[test]
    fn mismatched_inputs_are_rejected_naming_the_file() {
        let d = tempfile::tempdir().unwrap();
        profile(&d.path().join("profile"), 48, 40, Transfer::Linear);
        write(d.path(), "small.png", vec![Plane::filled(40, 40, 0.5); 3]);
        let e = run(&args(d.path(), "small.png")).unwrap_err().to_string();
        assert!(e.contains("small.png") && e.contains("40x40") && e.contains("48x40"), "{e}");
        write(d.path(), "gray.png", vec![Plane::filled(48, 40, 0.5)]);
        let e = run(&args(d.path(), "gray.png")).unwrap_err().to_string();
        assert!(e.contains("gray.png") && e.contains("1 channel") && e.contains("R,G,B"), "{e}");
        assert!(!d.path().join("out.png").exists());
    }

    #[test]
    fn srgb_capture_round_trips_in_size_and_encoding() {
        let d = tempfile::tempdir().unwrap();
        profile(&d.path().join("profile"), 48, 40, Transfer::Srgb);
        // a flat grey capture must come back as the same grey (decode, restore, re-encode)
        write(d.path(), "in.png", vec![Plane::filled(48, 40, 0.6); 3]);
        run(&args(d.path(), "in.png")).unwrap();
        let out = read_image(&d.path().join("out.png")).unwrap();
        assert_eq!((out.width(), out.height(), out.channel_count()), (48, 40, 3));
        for p in &out.planes {
            assert!(p.data.iter().all(|v| (v - 0.6).abs() < 2e-3), "{} .. {}", p.min(), p.max());
        }
    }
}
