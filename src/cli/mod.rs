//! The command line: arguments → the library's option types → one function per command, one
//! file per command.
//!
//! Every command returns `anyhow::Result`; `main` prints the one-line cause on stderr and
//! exits with status 2 on error, 0 on success. Flags shared by several commands live in
//! [`args`] and are flattened into each command's arguments.

pub mod args;
pub mod bench;
pub mod calibrate;
pub mod capture;
pub mod check_config;
pub mod deblur;
pub mod demo;
pub mod devices;
pub mod diagnose;
pub mod estimate;
pub mod export;
pub mod html;
pub mod jog;
pub mod panic;
pub mod report;
pub mod simulate;
pub mod target;

use anyhow::{bail, Result};
use clap::{Parser, Subcommand};
use std::path::Path;

#[derive(Parser, Debug)]
#[command(name = "lensrig", version, about = "Measure a simple lens on a calibration rig, write its profile, restore and diagnose images")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Write a printable random-noise calibration target (PNG + TOML description).
    Target(target::TargetArgs),
    /// Estimate a lens profile (per-tile, per-channel PSFs) from a wide-open / pinhole pair.
    Estimate(estimate::EstimateCommandArgs),
    /// Predict the wide-open capture from a sharp (pinhole) image through a profile.
    Simulate(simulate::SimulateArgs),
    /// Render a calibration pair with the lens simulator, estimate its profile and compare
    /// with the truth (no hardware needed).
    Demo(demo::DemoArgs),
    /// Time PSF estimation on the benchmark sizes and print a table.
    Bench(bench::BenchArgs),
    /// Restore an image taken through the profiled lens (cross-channel deconvolution).
    Deblur(deblur::DeblurArgs),
    /// Run a capture session on the rig (moves, exposures, frames on disk).
    Capture(capture::CaptureArgs),
    /// Load and validate a rig config; errors name the file, line and key.
    CheckConfig(check_config::CheckConfigArgs),
    /// Capture with the rig, estimate a profile per stage position, write an HTML report.
    Calibrate(calibrate::CalibrateArgs),
    /// Find where the profile's simulation and the recording disagree, name the missing
    /// physics, model it and refit (report.json, predictions and an HTML report).
    Diagnose(diagnose::DiagnoseArgs),
    /// List cameras (V4L2 formats, sizes, controls) and serial ports; with --port, print a
    /// grbl board's build info and settings and check them against --rig.
    Devices(devices::DevicesArgs),
    /// Move the rig's axes from the keyboard and print the machine position.
    Jog(jog::JogArgs),
    /// MTF and colour report of a profile or profile set.
    Report(report::ReportArgs),
    /// Lens data for other tools (lensfun).
    #[command(subcommand)]
    Export(export::ExportCommand),
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Target(a) => target::run(&a),
        Command::Estimate(a) => estimate::run(&a),
        Command::Simulate(a) => simulate::run(&a),
        Command::Demo(a) => demo::run(&a),
        Command::Bench(a) => bench::run(&a),
        Command::Deblur(a) => deblur::run(&a),
        Command::Capture(a) => capture::run(&a),
        Command::CheckConfig(a) => check_config::run(&a),
        Command::Calibrate(a) => calibrate::run(&a),
        Command::Diagnose(a) => diagnose::run(&a),
        Command::Devices(a) => devices::run(&a),
        Command::Jog(a) => jog::run(&a),
        Command::Report(a) => report::run(&a),
        Command::Export(c) => export::run(&c),
    }
}

/// Refuses to replace an existing output file unless `--force` was given (checked before any
/// work, so a long run never ends in a refused write).
pub fn refuse_existing(out: &Path, force: bool) -> Result<()> {
    if !force && out.exists() {
        bail!("{} already exists and is never overwritten (use --force to replace it)", out.display());
    }
    Ok(())
}

/// Refuses an even `--kernel` (or one below `min`) before any work.
pub fn check_kernel(kernel: Option<usize>, min: usize) -> Result<()> {
    match kernel {
        Some(k) if k % 2 == 0 || k < min => {
            if min > 1 {
                bail!("--kernel must be odd and at least {min}, got {k}")
            }
            bail!("--kernel must be odd, got {k}")
        }
        _ => Ok(()),
    }
}
