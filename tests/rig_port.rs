//! `lensrig capture --port SERIAL_PATH`: the port replaces the configured controller. Tested
//! with a pseudo-terminal pair whose master side runs the simulated grbl firmware in this test
//! process, so the binary talks to "hardware" it did not start, through a real tty.

mod common;

use common::bin;
use lensrig::rig::controller::sim::{spawn_pty, SimOptions};
use lensrig::rig::controller::Axis;
use lensrig::rig::session;
use std::path::{Path, PathBuf};

fn tmp(name: &str) -> PathBuf {
    common::tmp("port", name)
}

/// mock.toml with an absolute target path, small frames, two stage positions.
fn config(dir: &Path) -> PathBuf {
    common::mock_config(dir, |text| {
        text.replace("frames_to_average = 16", "frames_to_average = 1")
            .replace("width = 384", "width = 128")
            .replace("height = 288", "height = 96")
            .replace("positions = [-20.0, -40.0, -60.0]", "positions = [-20.0, -35.0]")
    })
}

fn capture(cfg: &Path, out: &Path, port: &str) -> std::process::Output {
    bin()
        .args(["capture", "--rig", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--port", port, "--quiet"])
        .output()
        .unwrap()
}

#[test]
fn capture_drives_the_firmware_on_the_given_port() {
    let dir = tmp("drive");
    let cfg = config(&dir);
    // the board: homing enabled (mock.toml homes on start), machine space [-200, 0]
    let (board, path) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
    let out = dir.join("session");
    let o = capture(&cfg, &out, &path);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rec = session::load_session(&out).unwrap();
    assert_eq!(rec.status, "complete");
    assert_eq!(rec.controller_port, path);
    assert_eq!(rec.pairs.len(), 2);
    // this firmware, not a simulated one inside the binary, did the work
    let st = board.state();
    assert!(st.homed, "the capture homed the board on the port");
    let lines = &st.received_lines;
    assert!(lines.iter().any(|l| l == "$H"), "{lines:?}");
    // the two pairs, then mock.toml's flat step: the diffuser at X = -90, aperture open (Z = -1)
    for want in ["G53G0X-20.000", "G53G0X-35.000", "G53G0Z-1.000", "G53G0Z-8.000", "G53G0X-90.000"] {
        assert!(lines.iter().any(|l| l == want), "{want} not received: {lines:?}");
    }
    assert_eq!(st.mpos.get(Axis::X), -90.0);
    assert_eq!(st.mpos.get(Axis::Z), -1.0);
    drop(st);
    // the frames record the positions this board reported
    let m = session::load_frame_record(&out.join("pairs/001-stage-X-35.000/pinhole.toml")).unwrap();
    assert_eq!((m.stage_mm, m.aperture_mm), (-35.0, -8.0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn missing_busy_and_silent_ports_fail_clearly() {
    let dir = tmp("faults");
    let cfg = config(&dir);
    let o = capture(&cfg, &dir.join("s1"), "/dev/ttyUSB-lensrig-missing");
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("/dev/ttyUSB-lensrig-missing") && e.contains("no such device"), "{e}");
    assert!(!dir.join("s1").exists(), "nothing is created when the rig cannot be opened");
    // another program holds the port (exclusive open, like a running sender)
    let (_board, path) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
    let held = serialport::new(&path, 115_200).open_native().unwrap();
    let o = capture(&cfg, &dir.join("s2"), &path);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains(&path) && e.contains("busy"), "{e}");
    drop(held);
    // a board that never answers (wrong device on the port): a timeout naming the port
    let (board, path) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
    board.faults.silent.store(true, std::sync::atomic::Ordering::SeqCst);
    let o = capture(&cfg, &dir.join("s3"), &path);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains(&path) && e.contains("within"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_real_rig_example_checks_and_dry_runs_without_touching_a_device() {
    let dir = tmp("example");
    let cfg = Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/example-real.toml");
    let o = bin().args(["check-config", cfg.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.join("never");
    let o = bin().args(["capture", "--rig", cfg.to_str().unwrap(), "--out", out.to_str().unwrap(), "--dry-run"]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("/dev/serial/by-id/") && text.contains("move stage X to -110.000 mm") && text.contains("move aperture Z to -14.500 mm (pinhole)"), "{text}");
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&dir);
}
