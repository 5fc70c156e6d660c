//! `lensrig simulate`: the wide-open capture a profile predicts from a sharp (pinhole) image
//! ([`lensrig::diagnose::simulate::predict`]), written as a 16-bit PNG.

use super::refuse_existing;
use anyhow::{Context, Result};
use clap::Args;
use lensrig::diagnose::simulate::predict;
use lensrig::fsutil::Overwrite;
use lensrig::image::io::write_png16;
use lensrig::profile::Profile;
use std::path::PathBuf;

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

pub fn run(a: &SimulateArgs) -> Result<()> {
    refuse_existing(&a.out, a.force)?;
    let profile = Profile::load(&a.profile)?;
    let loaded = lensrig::image::io::read_image_with(&a.sharp, lensrig::image::validate::InvalidPixels::Refuse)?;
    for note in loaded.values.notes(&a.sharp) {
        eprintln!("lensrig: note: {note}");
    }
    let mut sharp = loaded.image;
    if sharp.raw.is_some() && sharp.channels != profile.grid.channels {
        sharp = lensrig::image::raw::demosaic_bilinear(&sharp, &a.sharp)?;
    }
    sharp.transfer = profile.meta.source.transfer;
    let mut out = predict(&profile, &sharp).with_context(|| a.sharp.display().to_string())?;
    // a raw sharp image in CFA planes: the prediction is written as bilinear RGB
    out.raw = sharp.raw.clone();
    let out = lensrig::image::raw::for_output(&out, &a.out)?;
    write_png16(&a.out, &out, if a.force { Overwrite::Replace } else { Overwrite::Never })?;
    println!("wrote {} ({}x{}, {} channel(s), 16-bit)", a.out.display(), out.width(), out.height(), out.channel_count());
    Ok(())
}
