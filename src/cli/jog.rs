//! `lensrig jog --rig CONFIG`: move the rig's axes by hand to find the positions a config
//! needs (`axes.aperture.open`, `pinhole`, `axes.stage.positions`), printing the machine
//! position after every move.
//!
//! Keys are read a line at a time (type, then Enter), so the handling reads any `BufRead`
//! and a test drives it with scripted input. In a line, each character is one key:
//! `a` selects the aperture axis, `s` the stage axis (or the axis letter `x`/`y`/`z` of one
//! of them); `+`/`-` move the selected axis by one step (rapid, absolute machine target
//! `G53 G0`, checked against the config's ranges before anything is sent); `*`/`/` make the
//! step 10× larger/smaller (0.001–100 mm); `p` prints the position; `h` runs the homing
//! cycle; `q` quits. Positions are machine coordinates in mm, as the config wants them.

use anyhow::{Context, Result};
use clap::Args;
use lensrig::rig::config::{ControllerKind, RigConfig};
use lensrig::rig::controller::sim::{spawn_pty, SimOptions};
use lensrig::rig::controller::{Axis, Controller, Position, SerialController};
use std::io::{BufRead, Write};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct JogArgs {
    /// Rig config (TOML): the controller, the two axes and their ranges.
    #[arg(long)]
    pub rig: PathBuf,
    /// Serial port of the controller, overriding the config.
    #[arg(long)]
    pub port: Option<String>,
    /// Initial step (mm).
    #[arg(long, default_value_t = 1.0)]
    pub step: f64,
}

pub fn run(a: &JogArgs) -> Result<()> {
    let cfg = lensrig::rig::config::load(&a.rig)?;
    let mut _sim = None;
    let port = match (&a.port, cfg.controller.kind) {
        (Some(p), _) => p.clone(),
        (None, ControllerKind::Serial) => cfg.controller.port.clone().unwrap_or_default(),
        (None, ControllerKind::Sim) => {
            let o = if cfg.controller.home_on_start { SimOptions::fast().with(22, 1.0) } else { SimOptions::fast() };
            let (h, path) = spawn_pty(o).context("cannot start the simulated controller")?;
            _sim = Some(h);
            path
        }
    };
    let mut ctl = SerialController::open(&port, cfg.controller.baud, cfg.controller_options())?;
    let stdin = std::io::stdin();
    jog(&mut ctl, &cfg, stdin.lock(), std::io::stdout(), a.step)?;
    Ok(())
}

fn show(out: &mut impl Write, p: Position, axis: Axis, step: f64) -> std::io::Result<()> {
    writeln!(out, "X {:.3}  Y {:.3}  Z {:.3}   (axis {axis}, step {step} mm)", p.0[0], p.0[1], p.0[2])
}

/// Runs the key loop (see the module docs) until `q` or the end of `input`; returns the
/// last machine position. A refused or failed move is printed and the loop goes on; a lost
/// link ends it.
pub fn jog(ctl: &mut dyn Controller, cfg: &RigConfig, input: impl BufRead, mut out: impl Write, step: f64) -> Result<Position> {
    let (ap, st) = (cfg.axes.aperture.axis, cfg.axes.stage.axis);
    let mut axis = st;
    let mut step = step.clamp(0.001, 100.0);
    let mut pos = ctl.status()?.mpos;
    writeln!(out, "keys (then Enter): a = aperture axis {ap}, s = stage axis {st}; + / - move one step; * / / step ×10 / ÷10; p position; h home; q quit")?;
    show(&mut out, pos, axis, step)?;
    for line in input.lines() {
        for key in line?.chars() {
            match key {
                'a' => axis = ap,
                's' => axis = st,
                'x' | 'y' | 'z' | 'X' | 'Y' | 'Z' => match Axis::from_letter(key) {
                    Some(a) if a == ap || a == st => axis = a,
                    _ => writeln!(out, "{} is not an axis of this rig (aperture {ap}, stage {st})", key.to_ascii_uppercase())?,
                },
                '*' => step = (step * 10.0).min(100.0),
                '/' => step = (step / 10.0).max(0.001),
                '+' | '-' => {
                    let target = pos.get(axis) + if key == '+' { step } else { -step };
                    // round to the controller's 0.001 mm so steps do not accumulate float error
                    let target = (target * 1000.0).round() / 1000.0;
                    match ctl.move_to(&[(axis, target)]) {
                        Ok(s) => pos = s.mpos,
                        Err(e @ lensrig::rig::controller::ControllerError::Disconnected { .. }) => return Err(e.into()),
                        Err(e) => writeln!(out, "refused: {e}")?,
                    }
                }
                'p' => pos = ctl.status()?.mpos,
                'h' => match ctl.home() {
                    Ok(s) => pos = s.mpos,
                    Err(e) => writeln!(out, "homing failed: {e}")?,
                },
                'q' => {
                    show(&mut out, pos, axis, step)?;
                    return Ok(pos);
                }
                c if c.is_whitespace() => continue,
                c => {
                    writeln!(out, "unknown key {c:?}")?;
                    continue;
                }
            }
            show(&mut out, pos, axis, step)?;
        }
    }
    Ok(pos)
}
