//! `lensrig export lensfun`: a lensfun database file from a profile (TCA, and distortion when
//! the profile holds `distortion.toml`), a flat-field capture (vignetting) and the lens's
//! identity. See [`lensrig::export::lensfun`] for what is
//! written and why.

use super::report::rig_facts;
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use lensrig::export::lensfun::{fit_flat, fit_tca, lensfun_xml, LensInfo, Tca, Vignetting};
use lensrig::fsutil::{write_atomic, Overwrite};
use lensrig::image::io::read_image;
use lensrig::image::Image;
use lensrig::profile::Profile;
use lensrig::target::locate::MeasuredDistortion;
use std::path::{Path, PathBuf};

#[derive(Subcommand, Debug)]
pub enum ExportCommand {
    /// A lensfun database file (format version 1): TCA and distortion (distortion.toml) from the profile, vignetting from --flat.
    Lensfun(LensfunArgs),
}

#[derive(Args, Debug)]
pub struct LensfunArgs {
    /// Profile directory (an R, G, B profile gives TCA).
    #[arg(long)]
    pub profile: PathBuf,
    /// Output file, e.g. lens.xml (lensfun reads ~/.local/share/lensfun/*.xml).
    #[arg(long)]
    pub out: PathBuf,
    /// Flat-field capture (wide open, uniform target or diffuser) for the vignetting block.
    #[arg(long)]
    pub flat: Option<PathBuf>,
    /// Dark frame of the flat field (same exposure or shorter, no light), subtracted first.
    #[arg(long, requires = "flat")]
    pub flat_dark: Option<PathBuf>,
    /// Rig config for the focal length, crop factor (from the pixel pitch) and f-number.
    #[arg(long)]
    pub rig: Option<PathBuf>,
    #[arg(long, default_value = "lensrig")]
    pub maker: String,
    #[arg(long, default_value = "Simple lens")]
    pub model: String,
    #[arg(long, default_value = "Generic")]
    pub mount: String,
    /// Focal length, mm (default: the rig config's).
    #[arg(long)]
    pub focal_mm: Option<f64>,
    /// Crop factor (default: 43.27 mm / the sensor diagonal from the rig's pixel pitch).
    #[arg(long)]
    pub crop_factor: Option<f64>,
    /// f-number of the flat field (default: the rig's open aperture).
    #[arg(long)]
    pub aperture: Option<f64>,
    /// Focus distance of the flat field, m.
    #[arg(long, default_value_t = 1000.0)]
    pub distance_m: f64,
    /// Replace the output file if it exists.
    #[arg(long)]
    pub force: bool,
}

/// The crop factor of a `w × h` sensor of `pitch_um` pixels: 43.27 mm (the 35 mm format's
/// diagonal) over the sensor diagonal.
pub fn crop_factor(pitch_um: f64, w: usize, h: usize) -> f64 {
    43.27 / (pitch_um / 1000.0 * ((w * w + h * h) as f64).sqrt())
}

/// A flat-field capture (wide open, uniform target or diffuser) and its dark frame.
pub struct FlatField {
    pub path: PathBuf,
    pub image: Image,
    pub dark: Option<Image>,
}

/// A lensfun file and what it holds.
pub struct LensfunExport {
    pub xml: String,
    pub distortion: Option<MeasuredDistortion>,
    pub tca: Option<Tca>,
    pub vignetting: Option<Vignetting>,
}

/// The lensfun database file for the profile `p` (loaded from `profile_dir`), lens `info` and
/// an optional flat field, with the provenance header saying what was measured from what.
///
/// # Errors
/// A flat field of another size than the profile's source, or too small or dark to fit; an
/// invalid `distortion.toml` or one measured on another sensor size.
pub fn lensfun_export(profile_dir: &Path, p: &Profile, info: &LensInfo, flat: Option<&FlatField>) -> Result<LensfunExport> {
    let (w, h) = (p.meta.source.width, p.meta.source.height);
    let report = lensrig::report::analyse(&p.grid, w, h, None);
    let tca = fit_tca(&report);
    let mut prov = vec![
        format!("Written by lensrig {} at {}.", env!("CARGO_PKG_VERSION"), lensrig::timestamp_utc()),
        format!("Profile {} (created {}, {}x{} px, channels {}).", profile_dir.display(), p.meta.created, w, h, p.grid.channels.join(" ")),
    ];
    match &tca {
        Some(t) => prov.push(format!("Measured: tca (poly3) from the R and B kernel centroids against G at {} tiles off axis; RMS radial residual {:.3} px.", t.tiles, t.residual_px)),
        None => prov.push("Not measured: tca (needs an R, G, B profile with at least four tiles off axis).".into()),
    }
    let vig = match flat {
        Some(f) => {
            let img = &f.image;
            if img.width() != w || img.height() != h {
                bail!("{}: is {}x{} but the profile was measured on {}x{}", f.path.display(), img.width(), img.height(), w, h);
            }
            let v = fit_flat(img, f.dark.as_ref()).with_context(|| format!("{}: too small or dark for a vignetting fit (or its dark frame differs in size)", f.path.display()))?;
            prov.push(format!(
                "Measured: vignetting (pa) from the flat field {}{} at f/{}, focus distance {} m as given ({} blocks, RMS residual {:.2} % of the centre).",
                f.path.display(),
                if f.dark.is_some() { " minus its dark frame" } else { "" },
                info.aperture,
                info.distance_m,
                v.samples,
                v.residual * 100.0
            ));
            Some(v)
        }
        None => {
            prov.push("Not measured: vignetting (no flat-field capture given; the open/pinhole exposure ratio is relative vignetting between two apertures and is not exported).".into());
            None
        }
    };
    let dist = distortion_of(profile_dir, w, h, &mut prov)?;
    let xml = lensfun_xml(info, dist.as_ref().map(MeasuredDistortion::ptlens).as_ref(), tca.as_ref(), vig.as_ref(), &prov);
    Ok(LensfunExport { xml, distortion: dist, tca, vignetting: vig })
}

/// The profile's distortion measurement (`distortion.toml`), with its provenance line.
fn distortion_of(profile_dir: &Path, w: usize, h: usize, prov: &mut Vec<String>) -> Result<Option<MeasuredDistortion>> {
    let Some(d) = MeasuredDistortion::load(profile_dir)? else {
        prov.push("Not measured: distortion (the profile holds no distortion.toml; calibrate writes one when it can register the pinhole capture to the target file).".into());
        return Ok(None);
    };
    if (d.width, d.height) != (w, h) {
        bail!("{}: measured on {}x{} but the profile on {}x{}", profile_dir.join(lensrig::target::locate::DISTORTION_FILE).display(), d.width, d.height, w, h);
    }
    prov.push(format!(
        "Measured: distortion (ptlens) at {} by registering the pinhole capture {} to the target {} ({} of {} tiles, RMS residual {:.3} px).",
        d.measured, d.capture, d.target, d.tiles_used, d.tiles_total, d.rms_residual_px
    ));
    Ok(Some(d))
}

pub fn run(c: &ExportCommand) -> Result<()> {
    match c {
        ExportCommand::Lensfun(a) => run_lensfun(a),
    }
}

fn run_lensfun(a: &LensfunArgs) -> Result<()> {
    let p = Profile::load(&a.profile).with_context(|| format!("cannot load profile {}", a.profile.display()))?;
    let (w, h) = (p.meta.source.width, p.meta.source.height);
    let facts = match &a.rig {
        Some(r) => Some(rig_facts(r)?),
        None => None,
    };
    let focal = a.focal_mm.or(facts.and_then(|f| f.focal_length_mm)).context("the focal length is unknown: give --focal-mm or --rig with [lens] focal_length_mm")?;
    let crop = match a.crop_factor {
        Some(c) => c,
        None => {
            let pitch = facts.and_then(|f| f.pixel_pitch_um).context("the crop factor is unknown: give --crop-factor, or --rig with a pixel pitch")?;
            crop_factor(pitch, w, h)
        }
    };
    let aperture = a.aperture.or(facts.and_then(|f| f.f_number_open));
    let info = LensInfo { maker: a.maker.clone(), model: a.model.clone(), mount: a.mount.clone(), focal_mm: focal, crop_factor: crop, aperture: aperture.unwrap_or(0.0), distance_m: a.distance_m, width: w, height: h };
    let flat = match &a.flat {
        Some(f) => {
            if aperture.is_none() {
                bail!("the flat field's f-number is unknown: give --aperture or --rig");
            }
            let img = read_image(f).with_context(|| format!("cannot read flat field {}", f.display()))?;
            let dark = match &a.flat_dark {
                Some(d) => Some(read_image(d).with_context(|| format!("cannot read the flat field's dark frame {}", d.display()))?),
                None => None,
            };
            Some(FlatField { path: f.clone(), image: img, dark })
        }
        None => None,
    };
    let e = lensfun_export(&a.profile, &p, &info, flat.as_ref())?;
    let (xml, tca, vig) = (e.xml, e.tca, e.vignetting);
    write_atomic(&a.out, xml.as_bytes(), if a.force { Overwrite::Replace } else { Overwrite::Never }).with_context(|| format!("cannot write {}", a.out.display()))?;
    println!(
        "wrote {} ({}{}{}; crop factor {:.2}, focal {} mm)",
        a.out.display(),
        if e.distortion.is_some() { "distortion, " } else { "no distortion, " },
        if tca.is_some() { "tca" } else { "no tca" },
        if vig.is_some() { ", vignetting" } else { ", no vignetting" },
        crop,
        focal
    );
    Ok(())
}
