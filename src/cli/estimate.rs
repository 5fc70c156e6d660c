//! `lensrig estimate`: a lens profile from a wide-open / pinhole pair, or one profile per
//! finished pair of a capture session (`OUT/<pair key>/`).

use super::args::EstimateArgs;
use super::check_kernel;
use anyhow::{bail, Result};
use clap::Args;
use lensrig::estimate::bootstrap::{bootstrap_estimate, totals, BootstrapOptions};
use lensrig::estimate::register::RegistrationModel;
use lensrig::profile::uncertainty::save_uncertainty;
use lensrig::estimate::session::{estimate_session, load_finished};
use lensrig::estimate::{estimate, Estimate, EstimateOptions};
use lensrig::image::io::{depth_note, read_pair_with};
use lensrig::image::validate::InvalidPixels;
use lensrig::image::Transfer;
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct EstimateCommandArgs {
    /// Wide-open capture (PNG/TIFF).
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub open: Option<PathBuf>,
    /// Pinhole-aperture capture of the same target.
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub pinhole: Option<PathBuf>,
    /// A capture session (from `capture`): one profile per stage position in OUT/<pair key>/.
    #[arg(long)]
    pub session: Option<PathBuf>,
    /// Profile directory to write (with --session: one per pair, OUT/<pair key>/). A directory
    /// that already holds a profile is kept unless `--force`.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the profile(s) already in OUT (written atomically, file by file).
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub estimation: EstimateArgs,
    /// How the files encode light: linear (raw, machine vision) or srgb (webcams).
    #[arg(long, default_value = "linear")]
    pub transfer: Transfer,
    /// Black level to subtract (full-scale units, e.g. 0.0625 for 4096/65535).
    #[arg(long)]
    pub black_level: Option<f32>,
    /// Global motion between the captures: none, translation, similarity.
    #[arg(long, default_value = "translation")]
    pub register: RegistrationModel,
    /// Exclude NaN/Inf pixels from the data term like saturated ones (default: refuse the image).
    #[arg(long)]
    pub mask_invalid: bool,
    /// Per-kernel uncertainty (root mean square error: bootstrap bias and standard deviation) by
    /// a parametric bootstrap over both captures' noise laws with this many replicates (0: off;
    /// 4-8 is typical; each replicate costs one more estimate), written as psf-unc-<C>.tiff
    /// beside the profile.
    #[arg(long, default_value_t = 0)]
    pub bootstrap: usize,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
}

impl EstimateCommandArgs {
    /// The estimation options these arguments select.
    pub fn options(&self) -> EstimateOptions {
        EstimateOptions {
            registration: self.register,
            black_level: self.black_level.map(|b| vec![b]).unwrap_or_default(),
            progress: !self.quiet,
            ..self.estimation.options()
        }
    }
}

/// Reads a pair (non-finite pixels refused or masked per `invalid`; notes and warnings on
/// stderr), tags the transfer function the user declared, and estimates.
pub fn estimate_files(open: &Path, pinhole: &Path, opts: &EstimateOptions, transfer: Transfer, invalid: InvalidPixels) -> Result<Estimate> {
    let (lo, lp) = read_pair_with(open, pinhole, invalid)?;
    let depth = depth_note(open, &lo.image, pinhole, &lp.image);
    for note in lo.values.notes(open).into_iter().chain(lp.values.notes(pinhole)).chain(depth) {
        eprintln!("lensrig: note: {note}");
    }
    let (mut o, mut p) = (lo.image, lp.image);
    o.transfer = transfer;
    p.transfer = transfer;
    let mut est = estimate(&o, &p, opts)?;
    est.profile.meta.source.open = Some(open.display().to_string());
    est.profile.meta.source.pinhole = Some(pinhole.display().to_string());
    Ok(est)
}

/// Refuses, before any work, to write into a directory of `dirs` that already holds a profile
/// (`profile.toml`) unless `force`: a profile may have been edited by hand or be the one a
/// report cites, and a re-estimate would replace it without a trace.
fn refuse_existing_profiles(dirs: &[PathBuf], force: bool) -> Result<()> {
    if force {
        return Ok(());
    }
    if let Some(d) = dirs.iter().find(|d| d.join("profile.toml").exists()) {
        bail!("{} already holds a profile, which is kept (use --force to replace it, or choose another --out)", d.display());
    }
    Ok(())
}

pub fn run(a: &EstimateCommandArgs) -> Result<()> {
    let opts = a.options();
    check_kernel(a.estimation.kernel, 1)?;
    let (open, pinhole) = match (&a.open, &a.pinhole, &a.session) {
        (_, _, Some(s)) => {
            let keys = load_finished(s)?.pairs.into_iter().map(|p| p.key);
            refuse_existing_profiles(&keys.map(|k| a.out.join(k)).collect::<Vec<_>>(), a.force)?;
            let done = estimate_session(s, &a.out, &opts, !a.quiet)?;
            for (p, e) in &done {
                println!("wrote {}: {} tiles, {}px kernels", a.out.join(&p.key).display(), e.profile.grid.tile_count(), e.profile.grid.kernel_size);
            }
            return Ok(());
        }
        (Some(o), Some(p), None) => (o, p),
        _ => bail!("give --open and --pinhole, or --session"),
    };
    refuse_existing_profiles(std::slice::from_ref(&a.out), a.force)?;
    let invalid = if a.mask_invalid { InvalidPixels::Mask } else { InvalidPixels::Refuse };
    // the bootstrap's uncertainty includes the joint fit's convergence term, measured by
    // continuing the fit past its end (the kernels are not changed)
    let opts = EstimateOptions { convergence_tail: a.bootstrap > 0, ..opts };
    let est = estimate_files(open, pinhole, &opts, a.transfer, invalid)?;
    est.profile.save(&a.out)?;
    if a.bootstrap > 0 {
        let o = BootstrapOptions { replicates: a.bootstrap.max(2), ..BootstrapOptions::default() };
        let unc = bootstrap_estimate(&est, &opts, &o)?;
        save_uncertainty(&a.out, &est.profile.grid, &totals(&unc))?;
    }
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
