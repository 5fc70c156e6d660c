//! Restoring a capture file with a lens profile (what `lensrig deblur` runs).
//!
//! Reads the input as stored, decodes it with the profile's source transfer curve (or the one
//! given), subtracts the profile's black level (full-scale units), restores the linear planes
//! with [`super::deblur`], adds the black level back, re-encodes with the same curve and
//! writes a 16-bit PNG of the input's size (a camera raw input: a linear 16-bit TIFF, see
//! [`crate::image::raw`]). The input must have the profile's channel count
//! and the size the profile was measured on (tile centres are pixel positions).

use super::{deblur, DeconvError, DeconvOptions, DeconvReport};
use crate::fsutil::Overwrite;
use crate::image::io::{read_image_with, write_png16, ImageError};
use crate::image::validate::{InvalidPixels, MASKED_VALUE};
use crate::image::Transfer;
use crate::profile::set::{is_set, load_profile_or_set};
use crate::profile::ProfileError;
use std::path::{Path, PathBuf};

/// Why a capture could not be restored. Every variant names the input or the profile.
#[derive(Debug, thiserror::Error)]
pub enum RestoreError {
    #[error("cannot load profile {}", path.display())]
    Profile { path: PathBuf, #[source] source: ProfileError },
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{}: has {got} channel(s) but profile {} has {expected} ({names})", input.display(), profile.display())]
    Channels { input: PathBuf, profile: PathBuf, got: usize, expected: usize, names: String },
    #[error("{}: is {got_width}x{got_height} but profile {} was measured on {width}x{height} images (PSF tiles are pixel positions; crop or resize is not supported)", input.display(), profile.display())]
    Size { input: PathBuf, profile: PathBuf, got_width: usize, got_height: usize, width: usize, height: usize },
    #[error("{}: has {got} channels; PNG output holds 1 or 3", input.display())]
    PngChannels { input: PathBuf, got: usize },
    #[error("{}: --mask-invalid drops pixels through the saturation mask, which is disabled (use a saturation level ≤ 1)", input.display())]
    MaskWithoutSaturation { input: PathBuf },
    #[error("{}: a camera raw input is restored to a linear 16-bit TIFF; name the output .tiff", out.display())]
    RawOutput { out: PathBuf },
    #[error("cannot restore {}", input.display())]
    Deconv { input: PathBuf, #[source] source: DeconvError },
}

/// A restoration of one file.
#[derive(Clone, Debug)]
pub struct RestoreFile<'a> {
    /// Lens profile directory, or a profile set (a directory with `index.toml`).
    pub profile: &'a Path,
    /// Focus distance (m) and aperture (f-number) of the capture, to choose or interpolate
    /// within a profile set; ignored for a single profile.
    pub distance: Option<f64>,
    pub aperture: Option<f64>,
    pub input: &'a Path,
    /// 16-bit PNG to write.
    pub out: &'a Path,
    /// Encoding of the input values; `None`: the profile's source encoding.
    pub transfer: Option<Transfer>,
    pub overwrite: Overwrite,
    /// A progress bar on stderr.
    pub progress: bool,
    /// What to do with NaN/Inf input samples: refuse the file, or drop them from the data term
    /// through the saturation mask.
    pub invalid: InvalidPixels,
}

/// What a restoration did: the solver's report and notes on the input's values (masked or
/// negative samples) for the user.
#[derive(Clone, Debug)]
pub struct Restored {
    pub report: DeconvReport,
    pub notes: Vec<String>,
}

/// Restores `job.input` into `job.out` with `opts` (its `output_transfer` is set to the
/// input's encoding: the prior is weighed as the encoded image will show it).
///
/// # Errors
/// [`RestoreError`]: an unreadable profile or input, a channel count or size that does not
/// match the profile (naming the file and both values), a failed restoration, an unwritable
/// output.
pub fn restore_file(job: &RestoreFile, opts: &DeconvOptions) -> Result<Restored, RestoreError> {
    let resolved = load_profile_or_set(job.profile, job.distance, job.aperture).map_err(|source| RestoreError::Profile { path: job.profile.to_path_buf(), source })?;
    let mut notes = Vec::new();
    if is_set(job.profile) {
        notes.push(format!("profile set {}: {}", job.profile.display(), resolved.description));
    }
    let profile = resolved.profile;
    let loaded = read_image_with(job.input, job.invalid)?;
    if loaded.values.masked > 0 && opts.saturation.is_none() {
        return Err(RestoreError::MaskWithoutSaturation { input: job.input.into() });
    }
    notes.extend(loaded.values.notes(job.input));
    let grid = &profile.grid;
    let src = &profile.meta.source;
    let raw_in = loaded.image.raw.is_some();
    let mut img = matching_input(loaded.image, job, &profile)?;
    let transfer = job.transfer.unwrap_or(src.transfer);
    img.transfer = transfer;
    let mut lin = img.to_linear();
    let black: Vec<f32> = (0..lin.channel_count()).map(|c| src.black_level.get(c).copied().unwrap_or(0.0)).collect();
    for (p, b) in lin.planes.iter_mut().zip(&black) {
        if *b != 0.0 {
            p.data.iter_mut().for_each(|v| *v -= b);
        }
    }
    // masked samples must stay at or above the saturation level after the black-level shift
    if let Some(sat) = opts.saturation {
        for &(c, i) in &loaded.values.masked_samples {
            lin.planes[c].data[i] = MASKED_VALUE.max(sat);
        }
    }
    let opts = solver_options(opts, &profile, transfer);
    let bar = if job.progress { indicatif::ProgressBar::new(0) } else { indicatif::ProgressBar::hidden() };
    bar.set_style(
        indicatif::ProgressStyle::with_template("deblur {bar:40} {pos}/{len} tiles {elapsed_precise} (eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let (mut planes, report) = deblur(&lin.planes, grid, &opts, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .map_err(|source| RestoreError::Deconv { input: job.input.into(), source })?;
    bar.finish_and_clear();
    for (p, b) in planes.iter_mut().zip(&black) {
        if *b != 0.0 {
            p.data.iter_mut().for_each(|v| *v += b);
        }
    }
    lin.planes = planes;
    lin.transfer = Transfer::Linear;
    let out = lin.encoded(transfer);
    if raw_in {
        crate::image::raw::write_linear_tiff16(job.out, &out, job.overwrite)?;
    } else {
        write_png16(job.out, &out, job.overwrite)?;
    }
    Ok(Restored { report, notes })
}

/// Input-check stage of [`restore_file`]: demosaics a camera raw input if the profile wants
/// RGB, then checks the output format, channel count and size against the profile.
fn matching_input(mut img: crate::image::Image, job: &RestoreFile, profile: &crate::profile::Profile) -> Result<crate::image::Image, RestoreError> {
    let grid = &profile.grid;
    let src = &profile.meta.source;
    // camera raw input: CFA planes, or bilinear RGB for a profile of demosaiced channels; the
    // result is a linear 16-bit TIFF (crate::image::raw)
    let raw_in = img.raw.is_some();
    if raw_in && img.channels != grid.channels {
        img = crate::image::raw::demosaic_bilinear(&img, job.input)?;
    }
    if raw_in && !job.out.extension().is_some_and(|e| e.eq_ignore_ascii_case("tif") || e.eq_ignore_ascii_case("tiff")) {
        return Err(RestoreError::RawOutput { out: job.out.into() });
    }
    if img.channel_count() != grid.channels.len() {
        return Err(RestoreError::Channels { input: job.input.into(), profile: job.profile.into(), got: img.channel_count(), expected: grid.channels.len(), names: grid.channels.join(",") });
    }
    if img.width() != src.width || img.height() != src.height {
        return Err(RestoreError::Size { input: job.input.into(), profile: job.profile.into(), got_width: img.width(), got_height: img.height(), width: src.width, height: src.height });
    }
    if !raw_in && !matches!(img.channel_count(), 1 | 3) {
        return Err(RestoreError::PngChannels { input: job.input.into(), got: img.channel_count() });
    }
    Ok(img)
}

/// Solver-options stage of [`restore_file`]: the profile's noise law (unless the caller chose)
/// and the output transfer the prior is weighed for.
fn solver_options(opts: &DeconvOptions, profile: &crate::profile::Profile, transfer: Transfer) -> DeconvOptions {
    let mut opts = opts.clone();
    // the profile's noise law unless the caller chose (the law is on the black-subtracted axis)
    if opts.noise == super::noise::NoiseSource::Profile {
        opts.noise = match &profile.meta.noise {
            Some(law) => super::noise::NoiseSource::Law(law.clone()),
            None => super::noise::NoiseSource::Estimate,
        };
    }
    // the result is re-encoded with `transfer`: weigh the prior as the encoded image will show it
    opts.output_transfer = Some(transfer);
    opts
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deconv::synth::SyntheticLens;
    use crate::image::{Image, Plane, SampleFormat};
    use crate::profile::{Profile, PsfTable, SourceInfo};
    use std::collections::BTreeMap;

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

    /// The options `lensrig deblur` gave these tests (30 iterations, one residual step, no
    /// dark term).
    fn run(dir: &Path, input: &str) -> Result<Restored, RestoreError> {
        let (profile, input, out) = (dir.join("profile"), dir.join(input), dir.join("out.png"));
        let job = RestoreFile { profile: &profile, input: &input, out: &out, transfer: None, overwrite: Overwrite::Replace, progress: false, invalid: InvalidPixels::Refuse, distance: None, aperture: None };
        let opts = DeconvOptions { cross_weight: 3.0, dark_weight: 0.0, residual_steps: 1, max_iterations: 30, saturation: Some(0.99), ..DeconvOptions::default() };
        restore_file(&job, &opts)
    }

    fn write(dir: &Path, name: &str, planes: Vec<Plane>) {
        write_png16(&dir.join(name), &Image::new(planes), Overwrite::Replace).unwrap();
    }

    #[test]
    fn mismatched_inputs_are_rejected_naming_the_file() {
        let d = tempfile::tempdir().unwrap();
        profile(&d.path().join("profile"), 48, 40, Transfer::Linear);
        write(d.path(), "small.png", vec![Plane::filled(40, 40, 0.5); 3]);
        let e = run(d.path(), "small.png").unwrap_err().to_string();
        assert!(e.contains("small.png") && e.contains("40x40") && e.contains("48x40"), "{e}");
        write(d.path(), "gray.png", vec![Plane::filled(48, 40, 0.5)]);
        let e = run(d.path(), "gray.png").unwrap_err().to_string();
        assert!(e.contains("gray.png") && e.contains("1 channel") && e.contains("R,G,B"), "{e}");
        assert!(!d.path().join("out.png").exists());
    }

    #[test]
    fn srgb_capture_round_trips_in_size_and_encoding() {
        let d = tempfile::tempdir().unwrap();
        profile(&d.path().join("profile"), 48, 40, Transfer::Srgb);
        // a flat grey capture must come back as the same grey (decode, restore, re-encode)
        write(d.path(), "in.png", vec![Plane::filled(48, 40, 0.6); 3]);
        run(d.path(), "in.png").unwrap();
        let out = crate::image::io::read_image(&d.path().join("out.png")).unwrap();
        assert_eq!((out.width(), out.height(), out.channel_count()), (48, 40, 3));
        for p in &out.planes {
            assert!(p.data.iter().all(|v| (v - 0.6).abs() < 2e-3), "{} .. {}", p.min(), p.max());
        }
    }
}
