//! What is plugged in: serial ports (for the grbl board) and a board's settings checked
//! against a rig config. `lensrig devices` prints these; the V4L2 listing is in
//! [`super::camera::v4l`] ([`list_formats_ext`](super::camera::v4l::list_formats_ext),
//! [`list_ctrls`](super::camera::v4l::list_ctrls)).
//!
//! # Conventions
//! - Serial ports are listed by their stable `/dev/serial/by-id/…` name first (it survives
//!   re-plugging and reboots; `/dev/ttyUSB0` does not), then any other port.
//! - Settings are grbl 1.1 `$N` numbers; findings name the setting and the fix to send.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::config::RigConfig;

/// One serial port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SerialPortEntry {
    /// The path to put in `controller.port`.
    pub path: PathBuf,
    /// The device it names (`/dev/ttyUSB0`) when `path` is a by-id link.
    pub device: Option<PathBuf>,
}

/// Serial ports: the links in `by_id_dir` (normally `/dev/serial/by-id`) first, then the
/// `others` not reached through a link.
pub fn serial_ports_in(by_id_dir: &Path, others: &[PathBuf]) -> Vec<SerialPortEntry> {
    let mut v: Vec<SerialPortEntry> = std::fs::read_dir(by_id_dir)
        .map(|d| d.filter_map(Result::ok).map(|e| e.path()).collect::<Vec<_>>())
        .unwrap_or_default()
        .into_iter()
        .map(|path| SerialPortEntry { device: std::fs::canonicalize(&path).ok(), path })
        .collect();
    v.sort_by(|a, b| a.path.cmp(&b.path));
    for o in others {
        let canon = std::fs::canonicalize(o).unwrap_or_else(|_| o.clone());
        if !v.iter().any(|e| e.device.as_ref() == Some(&canon)) {
            v.push(SerialPortEntry { path: o.clone(), device: None });
        }
    }
    v
}

/// The serial ports of this machine (see [`serial_ports_in`]).
pub fn serial_ports() -> Vec<SerialPortEntry> {
    let others: Vec<PathBuf> = serialport::available_ports().unwrap_or_default().into_iter().map(|p| PathBuf::from(p.port_name)).collect();
    serial_ports_in(Path::new("/dev/serial/by-id"), &others)
}

/// How bad a finding is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Severity {
    /// The capture cannot work (it would stop before any motion).
    Error,
    /// It works, but less safely or less well.
    Warning,
}

/// One mismatch between a board's settings and a rig config.
#[derive(Clone, Debug, PartialEq)]
pub struct Finding {
    pub severity: Severity,
    pub message: String,
}

/// Checks a board's `$$` settings against a rig config: homing (`$22`) when the config
/// homes on start, soft limits (`$20`), and the axis ranges against the max travel
/// (`$130`–`$132`, machine space `[−travel, 0]` with homing).
pub fn check_board(settings: &BTreeMap<u16, f64>, cfg: &RigConfig) -> Vec<Finding> {
    let mut f = Vec::new();
    let get = |n: u16| settings.get(&n).copied();
    let homing = get(22).is_some_and(|v| v != 0.0);
    if cfg.controller.home_on_start && !homing {
        f.push(Finding {
            severity: Severity::Error,
            message: "$22=0: homing is disabled on the board, but the rig config homes on start (home_on_start = true); fix: send `$22=1` (check the limit switches and $23 first), or set home_on_start = false".into(),
        });
    }
    if !cfg.controller.home_on_start && homing {
        f.push(Finding {
            severity: Severity::Warning,
            message: "$22=1: the board powers up locked until homed, but the rig config does not home (home_on_start = false); set home_on_start = true, or recovery = \"unlock\"".into(),
        });
    }
    if get(20).is_some_and(|v| v == 0.0) {
        f.push(Finding {
            severity: Severity::Warning,
            message: "$20=0: soft limits are off: the board itself will not refuse a target outside its travel (lensrig still checks the config's ranges); fix: `$20=1` (needs homing, $22=1)".into(),
        });
    }
    if homing {
        let (a, s) = (&cfg.axes.aperture, &cfg.axes.stage);
        for (name, axis, min, max) in [("axes.aperture", a.axis, a.min, a.max), ("axes.stage", s.axis, s.min, s.max)] {
            let n = 130 + axis.index() as u16;
            if let Some(travel) = get(n) {
                if min < -travel || max > 0.0 {
                    f.push(Finding {
                        severity: Severity::Error,
                        message: format!("${n}={travel}: {name} range [{min}, {max}] mm leaves the board's machine space [-{travel}, 0] mm; fix the range or `${n}`"),
                    });
                }
            }
        }
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mock() -> RigConfig {
        crate::rig::config::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/mock.toml")).unwrap()
    }

    #[test]
    fn board_checks_name_the_setting_and_the_fix() {
        let defaults = crate::rig::controller::sim::default_settings();
        let cfg = mock(); // homes on start
        let f = check_board(&defaults, &cfg);
        assert_eq!(f.len(), 2, "{f:?}");
        assert_eq!(f[0].severity, Severity::Error);
        assert!(f[0].message.starts_with("$22=0") && f[0].message.contains("`$22=1`"), "{f:?}");
        assert_eq!(f[1].severity, Severity::Warning);
        assert!(f[1].message.starts_with("$20=0: soft limits are off"));
        // a board set up for the rig: no finding; a too short travel is an error
        let mut good = defaults.clone();
        good.extend([(22, 1.0), (20, 1.0)]);
        assert!(check_board(&good, &cfg).is_empty());
        good.insert(130, 50.0); // X travel 50 mm, the stage range goes to -100
        let f = check_board(&good, &cfg);
        assert!(f.len() == 1 && f[0].message.contains("$130=50") && f[0].message.contains("axes.stage"), "{f:?}");
    }

    #[test]
    fn by_id_links_come_first_and_hide_their_device() {
        let d = tempfile::tempdir().unwrap();
        let dev = d.path().join("ttyUSB7");
        std::fs::write(&dev, b"").unwrap();
        let by_id = d.path().join("by-id");
        std::fs::create_dir(&by_id).unwrap();
        std::os::unix::fs::symlink(&dev, by_id.join("usb-1a86_USB_Serial-if00-port0")).unwrap();
        let other = d.path().join("ttyACM0");
        let v = serial_ports_in(&by_id, &[dev.clone(), other.clone()]);
        assert_eq!(v.len(), 2, "{v:?}");
        assert!(v[0].path.ends_with("usb-1a86_USB_Serial-if00-port0") && v[0].device.as_deref() == std::fs::canonicalize(&dev).ok().as_deref());
        assert_eq!(v[1], SerialPortEntry { path: other, device: None });
    }
}
