//! `lensrig check-config`: load and validate a rig config (TOML); errors name the file, line
//! and key. A mock camera's optics and the target file are loaded too.

use anyhow::{Context, Result};
use clap::Args;
use lensrig::rig::config;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct CheckConfigArgs {
    /// Rig config (TOML).
    pub config: PathBuf,
}

pub fn run(a: &CheckConfigArgs) -> Result<()> {
    let cfg = config::load(&a.config)?;
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
