//! `lensrig devices`: what a user wiring a real rig needs to see. Without `--port`: the V4L2
//! cameras (formats, frame sizes, controls, in `v4l2-ctl`'s words; needs feature `v4l2`) and
//! the serial ports (by-id names first). With `--port`: connect to the grbl board there
//! (no homing, no motion), print its build info (`$I`) and settings (`$$`), and with
//! `--rig` check them against the config; an error-level finding exits with status 2.

use anyhow::{bail, Context, Result};
use clap::Args;
use lensrig::rig::controller::protocol::{Command, Message};
use lensrig::rig::controller::{ControllerOptions, SerialController};
use lensrig::rig::devices::{check_board, serial_ports, Severity};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct DevicesArgs {
    /// Connect to the grbl board on this serial port and print its build info and settings.
    #[arg(long)]
    pub port: Option<String>,
    /// With --port: check the board's settings against this rig config.
    #[arg(long, requires = "port")]
    pub rig: Option<PathBuf>,
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
}

pub fn run(a: &DevicesArgs) -> Result<()> {
    match &a.port {
        Some(port) => board(a, port),
        None => {
            list_cameras();
            println!("Serial ports (put the by-id path in controller.port: it survives re-plugging):");
            let ports = serial_ports();
            if ports.is_empty() {
                println!("  none found");
            }
            for p in ports {
                match p.device {
                    Some(d) => println!("  {} -> {}", p.path.display(), d.display()),
                    None => println!("  {}", p.path.display()),
                }
            }
            Ok(())
        }
    }
}

#[cfg(feature = "v4l2")]
fn list_cameras() {
    use lensrig::rig::camera::v4l::{list_ctrls, list_formats_ext, open_device};
    let mut devs: Vec<PathBuf> = std::fs::read_dir("/dev").map(|d| d.filter_map(|e| e.ok()).map(|e| e.path()).collect()).unwrap_or_default();
    devs.retain(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("video")));
    devs.sort();
    println!("V4L2 cameras:");
    if devs.is_empty() {
        println!("  none found\n");
    }
    for p in devs {
        println!("{}:", p.display());
        match open_device(&p) {
            Ok(dev) => {
                if let Ok((card, driver)) = dev.identify() {
                    println!("\tCard: {card} (driver {driver})");
                }
                match list_formats_ext(dev.as_ref()) {
                    Ok(t) => print!("{t}"),
                    Err(e) => println!("\t(formats: {e})"),
                }
                match list_ctrls(dev.as_ref()) {
                    Ok(t) => println!("{t}"),
                    Err(e) => println!("\t(controls: {e})\n"),
                }
            }
            Err(e) => println!("\tcannot open: {e}\n"),
        }
    }
}

#[cfg(not(feature = "v4l2"))]
fn list_cameras() {
    println!("V4L2 cameras: not listed (lensrig was built without the `v4l2` feature; `v4l2-ctl --list-devices` lists them)\n");
}

fn board(a: &DevicesArgs, port: &str) -> Result<()> {
    let cfg = a.rig.as_deref().map(lensrig::rig::config::load).transpose()?;
    // timeouts from the config when given; never home or unlock: nothing moves
    let mut opts = cfg.as_ref().map(|c| c.controller_options()).unwrap_or_default();
    opts.home_on_start = false;
    opts = ControllerOptions { recovery: Default::default(), ..opts };
    let mut ctl = SerialController::open(port, a.baud, opts)?;
    println!("{port}: grbl build info ($I):");
    for m in ctl.command(&Command::BuildInfo).context("$I")? {
        match m {
            Message::Version(v) => println!("  [VER:{v}]"),
            Message::Options(o) => println!("  [OPT:{o}]"),
            other => println!("  {other:?}"),
        }
    }
    println!("{port}: settings ($$):");
    for m in ctl.command(&Command::Settings).context("$$")? {
        if let Message::Setting { number, value } = m {
            println!("  ${number}={value}");
        }
    }
    let Some(cfg) = cfg else { return Ok(()) };
    let rig = a.rig.as_deref().map(|p| p.display().to_string()).unwrap_or_default();
    let findings = check_board(&ctl.settings()?, &cfg);
    if findings.is_empty() {
        println!("{port}: settings fit {rig}");
        return Ok(());
    }
    for f in &findings {
        let level = if f.severity == Severity::Error { "error" } else { "warning" };
        println!("{level}: {}", f.message);
    }
    let errors = findings.iter().filter(|f| f.severity == Severity::Error).count();
    if errors > 0 {
        bail!("{port}: {errors} setting(s) do not fit {rig} (see above); nothing was moved");
    }
    Ok(())
}
