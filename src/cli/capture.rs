//! `lensrig capture`, `lensrig check-config` and `lensrig estimate --session`: the rig
//! commands that record or read a capture session (see `lensrig::rig::session`).

use anyhow::{bail, Context, Result};
use clap::Args;
use lensrig::estimate::{estimate, Estimate, EstimateOptions};
use lensrig::image::io::read_pair;
use lensrig::image::Plane;
use lensrig::image::io::read_image;
use lensrig::rig::config::{self, RigConfig};
use lensrig::rig::session::{self, CaptureOptions, PairRecord, Rig, SessionRecord};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct CaptureArgs {
    /// Rig config (TOML), e.g. rig-configs/mock.toml.
    #[arg(long)]
    pub rig: PathBuf,
    /// Session directory to create (never overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Serial port of the controller, overriding the config.
    #[arg(long)]
    pub port: Option<PathBuf>,
    /// Print every move and capture and check the limits; touch no device.
    #[arg(long)]
    pub dry_run: bool,
    /// Continue an interrupted session in --out after its last finished pair.
    #[arg(long)]
    pub resume: bool,
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CheckConfigArgs {
    /// Rig config (TOML).
    pub config: PathBuf,
}

/// Loads a rig config; the error names the file, line and key.
pub fn load_config(path: &Path) -> Result<RigConfig> {
    Ok(config::load(path)?)
}

pub fn run_check_config(a: &CheckConfigArgs) -> Result<()> {
    let cfg = load_config(&a.config)?;
    if cfg.camera.kind == config::CameraKind::Mock {
        lensrig::rig::camera::mock::MockOptics::from_config(&cfg).map_err(|e| anyhow::anyhow!("{}: {e}", a.config.display()))?;
    }
    if let Some(t) = &cfg.target {
        lensrig::target::TargetSpec::load(&t.path).with_context(|| format!("{}: target.path", a.config.display()))?;
    }
    let s = &cfg.axes.stage;
    println!(
        "{}: ok ({:?} camera {}x{}, {:?} controller, aperture {} open {} / pinhole {} mm, stage {} at {} position(s))",
        a.config.display(),
        cfg.camera.kind,
        cfg.camera.width,
        cfg.camera.height,
        cfg.controller.kind,
        cfg.axes.aperture.axis,
        cfg.axes.aperture.open,
        cfg.axes.aperture.pinhole,
        s.axis,
        s.positions.len()
    );
    Ok(())
}

/// Captures a session with the rig a config describes; returns the rig (for truth checks on
/// a mock) and the session record.
pub fn capture_session(rig_path: &Path, out: &Path, port: Option<&Path>, resume: bool, progress: bool) -> Result<(RigConfig, Rig, SessionRecord)> {
    let cfg = load_config(rig_path)?;
    if !resume && out.exists() {
        return Err(session::SessionError::Exists(out.to_path_buf()).into());
    }
    if resume && !out.join("session.toml").is_file() {
        bail!("--resume: {} is not a session (no session.toml)", out.display());
    }
    if progress {
        eprintln!("connecting to the rig ({:?} controller, {:?} camera)…", cfg.controller.kind, cfg.camera.kind);
    }
    let mut rig = Rig::from_config(&cfg, port)?;
    let rec = session::capture(&mut rig, &cfg, rig_path, out, &CaptureOptions { resume, progress })?;
    Ok((cfg, rig, rec))
}

pub fn run_capture(a: &CaptureArgs) -> Result<()> {
    if a.dry_run {
        let cfg = load_config(&a.rig)?;
        for l in session::dry_run(&cfg)? {
            println!("{l}");
        }
        println!("dry run: limits ok, nothing was moved or captured");
        return Ok(());
    }
    let (_, _, rec) = capture_session(&a.rig, &a.out, a.port.as_deref(), a.resume, !a.quiet)?;
    println!("session {}: {} pair(s), {}", a.out.display(), rec.pairs.len(), rec.status);
    Ok(())
}

/// The mean of a dark frame per channel (the black level to subtract).
fn dark_level(path: &Path) -> Result<Vec<f32>> {
    let d = read_image(path)?;
    Ok(d.planes.iter().map(|p: &Plane| (p.data.iter().map(|&v| v as f64).sum::<f64>() / p.data.len() as f64) as f32).collect())
}

/// Estimates one profile per finished pair of a session into `out/<pair key>/`.
pub fn estimate_session(dir: &Path, out: &Path, opts: &EstimateOptions, progress: bool) -> Result<Vec<(PairRecord, Estimate)>> {
    let rec = session::load_session(dir)?;
    if rec.pairs.is_empty() {
        bail!("session {} has no finished pairs (status: {})", dir.display(), rec.status);
    }
    let mut done = Vec::new();
    for p in &rec.pairs {
        let pd = dir.join(&p.dir);
        let (open_p, pin_p) = (pd.join(&p.open), pd.join(&p.pinhole));
        let (mut o, mut pin) = read_pair(&open_p, &pin_p)?;
        let om = session::load_frame_record(&pd.join("open.toml"))?;
        let pm = session::load_frame_record(&pd.join("pinhole.toml"))?;
        let transfer: lensrig::image::Transfer = om.transfer.parse().map_err(|e| anyhow::anyhow!("{}: transfer: {e}", pd.join("open.toml").display()))?;
        o.transfer = transfer;
        pin.transfer = transfer;
        let mut opts = opts.clone();
        if let Some(d) = &p.dark {
            opts.black_level = dark_level(&pd.join(d))?;
        }
        if progress {
            eprintln!("estimating {} (open {} µs at {} mm, pinhole {} µs at {} mm)", p.key, om.exposure_us, om.aperture_mm, pm.exposure_us, pm.aperture_mm);
        }
        let mut est = estimate(&o, &pin, &opts).with_context(|| format!("pair {}", p.key))?;
        est.profile.meta.source.open = Some(open_p.display().to_string());
        est.profile.meta.source.pinhole = Some(pin_p.display().to_string());
        est.profile.meta.note = format!(
            "session {} pair {}: stage {} mm; aperture open at {} mm ({} µs), pinhole at {} mm ({} µs)",
            dir.display(),
            p.key,
            p.stage_mm,
            om.aperture_mm,
            om.exposure_us,
            pm.aperture_mm,
            pm.exposure_us
        );
        est.profile.save(&out.join(&p.key))?;
        done.push((p.clone(), est));
    }
    Ok(done)
}
