//! `lensrig target`: a printable random-noise calibration target (`OUT.png` and `OUT.toml`;
//! paper sizes landscape, resolution in dots per inch, noise cells in printer dots).

use anyhow::{Context, Result};
use clap::Args;
use lensrig::fsutil::Overwrite;
use lensrig::target::TargetSpec;
use std::path::{Path, PathBuf};

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

pub fn run(a: &TargetArgs) -> Result<()> {
    let spec = TargetSpec::new(&a.paper, a.dpi, a.cell, a.seed)?;
    let dir = a.out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = a.out.file_name().context("--out needs a file name")?.to_string_lossy().to_string();
    spec.write(dir, &name, if a.force { Overwrite::Replace } else { Overwrite::Never })?;
    let (w, h) = spec.pixels();
    let (cw, ch) = spec.cells();
    println!("wrote {}.png ({w}x{h} px at {} DPI, {cw}x{ch} noise cells) and {}.toml", a.out.display(), a.dpi, a.out.display());
    Ok(())
}
