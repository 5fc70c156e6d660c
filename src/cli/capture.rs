//! `lensrig capture`: run a capture session on the rig (moves in mm, exposures in µs, frames
//! on disk; see `lensrig::rig::session`), or print the plan with `--dry-run`.

use super::args::RigArgs;
use anyhow::{bail, Result};
use clap::Args;
use lensrig::rig::config::{self, RigConfig};
use lensrig::rig::session::{self, CaptureOptions, Rig, SessionRecord};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct CaptureArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Session directory to create (never overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Print every move and capture and check the limits; touch no device.
    #[arg(long)]
    pub dry_run: bool,
    #[arg(long)]
    pub quiet: bool,
}

/// Captures a session with the rig `rig` describes into `out`; returns the config, the rig
/// (for truth checks on a mock) and the session record.
pub fn capture_session(rig: &RigArgs, out: &Path, progress: bool) -> Result<(RigConfig, Rig, SessionRecord)> {
    let cfg = config::load(&rig.rig)?;
    if !rig.resume && out.exists() {
        return Err(session::SessionError::Exists(out.to_path_buf()).into());
    }
    if rig.resume && !out.join("session.toml").is_file() {
        bail!("--resume: {} is not a session (no session.toml)", out.display());
    }
    if progress {
        eprintln!("connecting to the rig ({:?} controller, {:?} camera)…", cfg.controller.kind, cfg.camera.kind);
    }
    let mut r = Rig::from_config(&cfg, rig.port.as_deref())?;
    let rec = session::capture(&mut r, &cfg, &rig.rig, out, &CaptureOptions { resume: rig.resume, progress })?;
    Ok((cfg, r, rec))
}

pub fn run(a: &CaptureArgs) -> Result<()> {
    if a.dry_run {
        let cfg = config::load(&a.rig.rig)?;
        for l in session::dry_run(&cfg)? {
            println!("{l}");
        }
        println!("dry run: limits ok, nothing was moved or captured");
        return Ok(());
    }
    let (_, _, rec) = capture_session(&a.rig, &a.out, !a.quiet)?;
    println!("session {}: {} pair(s), {}", a.out.display(), rec.pairs.len(), rec.status);
    Ok(())
}
