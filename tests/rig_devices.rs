//! `lensrig devices --port` and `lensrig jog` against the simulated grbl firmware on a
//! pseudo-terminal (a real tty the binary opens by path).

use lensrig::rig::controller::sim::{spawn_pty, SimOptions};
use lensrig::rig::controller::Position;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn mock() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs/mock.toml")
}

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lensrig"))
}

#[test]
fn devices_prints_build_info_and_settings_and_names_the_homing_fix_before_any_motion() {
    // a board as shipped: homing disabled ($22=0), soft limits off ($20=0)
    let (board, path) = spawn_pty(SimOptions::fast()).unwrap();
    let o = bin().args(["devices", "--port", &path, "--rig", mock().to_str().unwrap()]).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "an error-level finding fails: {out}");
    assert!(out.contains("[VER:1.1h.20190830:]") && out.contains("[OPT:V,15,128]"), "{out}");
    assert!(out.contains("  $22=0\n") && out.contains("  $130=200.000\n"), "{out}");
    assert!(out.contains("error: $22=0: homing is disabled") && out.contains("`$22=1`"), "{out}");
    assert!(out.contains("warning: $20=0: soft limits are off"), "{out}");
    assert!(err.contains("do not fit") && err.contains("nothing was moved"), "{err}");
    let st = board.state();
    assert!(st.received_lines.iter().all(|l| l.starts_with('$') && l != "$H" && l != "$X"), "only reads: {:?}", st.received_lines);
    assert_eq!(st.mpos, Position::ZERO);
    drop(st);
    // a board set up for the rig: the settings fit
    let (_board, path) = spawn_pty(SimOptions::fast().with(22, 1.0).with(20, 1.0)).unwrap();
    let o = bin().args(["devices", "--port", &path, "--rig", mock().to_str().unwrap()]).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && out.contains("settings fit"), "{out}{}", String::from_utf8_lossy(&o.stderr));
    // a capture with that config against the unprepared board stops before any motion,
    // naming the fix
    let (board, path) = spawn_pty(SimOptions::fast()).unwrap();
    let dir = std::env::temp_dir().join(format!("lensrig-devices-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let o = bin().args(["capture", "--rig", mock().to_str().unwrap(), "--out", dir.join("s").to_str().unwrap(), "--port", &path, "--quiet"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("$22=0") && err.contains("`$22=1`"), "{err}");
    assert!(!board.state().received_lines.iter().any(|l| l.starts_with('G') || l == "$H"), "{:?}", board.state().received_lines);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn devices_lists_serial_ports_without_a_port() {
    let o = bin().args(["devices"]).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("V4L2 cameras") && out.contains("Serial ports"), "{out}");
}

#[test]
fn jog_moves_by_steps_from_scripted_keys_and_prints_the_position() {
    let (board, path) = spawn_pty(SimOptions::fast().with(22, 1.0)).unwrap();
    let mut child = bin()
        .args(["jog", "--rig", mock().to_str().unwrap(), "--port", &path])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // stage (X) two steps down; aperture (Z) one tenth-step down; X beyond its max (0) is
    // refused; Y is not a rig axis; then quit
    child.stdin.take().unwrap().write_all(b"s--\na/-\ns*++++\ny\nq\n").unwrap();
    let o = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", String::from_utf8_lossy(&o.stderr));
    // homed at -1 (pull-off) on every axis
    assert!(out.contains("X -1.000  Y -1.000  Z -1.000"), "{out}");
    assert!(out.contains("X -3.000  Y -1.000  Z -1.000   (axis X, step 1 mm)"), "{out}");
    assert!(out.contains("X -3.000  Y -1.000  Z -1.100   (axis Z, step 0.1 mm)"), "{out}");
    assert!(out.contains("X 0.000  Y -1.000  Z -1.100") && out.contains("refused:") && out.contains("nothing was sent"), "{out}");
    assert!(out.contains("Y is not an axis of this rig"), "{out}");
    assert_eq!(board.state().mpos, Position([0.0, -1.0, -1.1]));
}
