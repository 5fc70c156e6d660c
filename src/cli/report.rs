//! `lensrig report`: the MTF and colour report of a profile (or of every profile of a set),
//! written by [`lensrig::report`]; and the rig facts (pixel pitch, focal length, f-number) that
//! reports and exports read from a rig config.

use anyhow::{Context, Result};
use clap::Args;
use lensrig::profile::set::{is_set, load_profile_or_set, ProfileSet};
use lensrig::profile::uncertainty::load_uncertainty;
use lensrig::profile::Profile;
use lensrig::rig::camera::mock::MockOptics;
use lensrig::rig::config::{CameraKind, RigConfig};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct ReportArgs {
    /// Profile directory, or a profile set (a directory with index.toml).
    #[arg(long)]
    pub profile: PathBuf,
    /// Output directory (index.html, CSV files, plots).
    #[arg(long)]
    pub out: PathBuf,
    /// Rig config to read the pixel pitch from (`[lens] pixel_pitch_um`; mock rigs: the simulator's).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// Pixel pitch in µm (for lp/mm), overriding the rig config.
    #[arg(long)]
    pub pixel_pitch_um: Option<f64>,
    /// For a profile set: report the calibration for this focus distance (m)…
    #[arg(long, requires = "aperture")]
    pub distance: Option<f64>,
    /// …and aperture (f-number). Without both, every calibration of the set is reported.
    #[arg(long, requires = "distance")]
    pub aperture: Option<f64>,
}

/// Lens facts from a rig config: `[lens]` keys, or the simulator's for mock rigs.
#[derive(Clone, Copy, Debug, Default)]
pub struct RigFacts {
    pub pixel_pitch_um: Option<f64>,
    pub focal_length_mm: Option<f64>,
    pub f_number_open: Option<f64>,
}

/// Reads [`RigFacts`] from a rig config file.
pub fn rig_facts(path: &Path) -> Result<RigFacts> {
    let cfg = lensrig::rig::config::load(path).with_context(|| format!("cannot read rig config {}", path.display()))?;
    Ok(facts_of(&cfg))
}

pub fn facts_of(cfg: &RigConfig) -> RigFacts {
    let key = |k: &str| cfg.lens.as_ref().and_then(|t| t.get(k)).and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)));
    let mut f = RigFacts { pixel_pitch_um: key("pixel_pitch_um"), focal_length_mm: key("focal_length_mm"), f_number_open: key("f_number_open") };
    if cfg.camera.kind == CameraKind::Mock {
        if let Ok(o) = MockOptics::from_config(cfg) {
            // the simulator renders with its own lens; its figures are the truth
            f.pixel_pitch_um = Some(o.lens.pixel_pitch_um);
            f.focal_length_mm = Some(o.lens.focal_length_mm);
            f.f_number_open = Some(o.f_number_open);
        }
    }
    f
}

/// Writes the report of `p`; `dir` is its directory when it is a stored profile (its
/// `psf-unc-<C>.tiff` mosaics, if any, give the uncertainty maps), `None` for an interpolated one.
fn one(p: &Profile, dir: Option<&Path>, out: &Path, pitch: Option<f64>, title: &str) -> Result<()> {
    let unc = match dir {
        Some(d) => load_uncertainty(d, &p.grid).with_context(|| format!("cannot read the uncertainty mosaics of {}", d.display()))?,
        None => None,
    };
    let r = lensrig::report::write_report(out, p, unc.as_deref(), pitch, title)?;
    let a = &r.tiles[r.axis_tile];
    let figs: Vec<String> = r
        .channels
        .iter()
        .enumerate()
        .map(|(c, ch)| {
            let lp = r.lp_mm(a.mtf50_tan[c]).map(|v| format!(" = {} lp/mm", lensrig::report::significant(v, 3))).unwrap_or_default();
            format!("{ch} {} c/px{lp}", lensrig::report::fixed(a.mtf50_tan[c], 3))
        })
        .collect();
    println!("{}: on-axis MTF50 {}; report {}", title, figs.join(", "), out.join("index.html").display());
    Ok(())
}

pub fn run(a: &ReportArgs) -> Result<()> {
    let facts = match &a.rig {
        Some(r) => Some(rig_facts(r)?),
        None => None,
    };
    let pitch = a.pixel_pitch_um.or(facts.and_then(|f| f.pixel_pitch_um));
    if pitch.is_none() {
        eprintln!("note: pixel pitch unknown (give --pixel-pitch-um or --rig); MTF50 in cycles/pixel only");
    }
    if is_set(&a.profile) && a.distance.is_none() {
        let set = ProfileSet::load(&a.profile)?;
        for c in &set.calibration {
            let p = Profile::load(&a.profile.join(&c.profile)).with_context(|| format!("cannot load {}", c.profile))?;
            let dir = a.profile.join(&c.profile);
            one(&p, Some(&dir), &a.out.join(&c.profile), pitch, &format!("{} (f/{}, {} m, {} mm)", c.profile, c.aperture, c.distance, c.focal))?;
        }
        return Ok(());
    }
    let r = load_profile_or_set(&a.profile, a.distance, a.aperture).with_context(|| format!("cannot load profile {}", a.profile.display()))?;
    if is_set(&a.profile) {
        eprintln!("profile set: {}", r.description);
    }
    let dir = if is_set(&a.profile) { None } else { Some(a.profile.as_path()) };
    one(&r.profile, dir, &a.out, pitch, &format!("lensrig report: {}", r.description))
}
