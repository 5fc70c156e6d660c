//! Helpers shared by the integration tests: the real binary, its outcomes, temporary
//! directories and variants of `rig-configs/mock.toml`. Each test crate uses a subset.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `lensrig` binary under test.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_lensrig"))
}

/// Runs the binary with `args`.
pub fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("run lensrig")
}

/// Asserts that a run succeeded; returns its stdout.
pub fn succeeded(o: Output) -> String {
    assert!(o.status.success(), "failed: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Runs the binary, asserts success, returns stdout.
pub fn ok(args: &[&str]) -> String {
    let o = run(args);
    assert!(o.status.success(), "lensrig {args:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Runs the binary, asserts that it failed, returns stderr.
pub fn fails(args: &[&str]) -> String {
    let o = run(args);
    assert!(!o.status.success(), "lensrig {args:?} should fail");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Runs the binary, asserts exit status 2 with a one-line cause on stderr (the contract of
/// `main` for errors a command returns), returns stderr.
pub fn fails_one_line(args: &[&str]) -> String {
    let o = run(args);
    assert_eq!(o.status.code(), Some(2), "lensrig {args:?} should exit 2");
    let e = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(e.trim_end().lines().count(), 1, "one-line cause expected: {e}");
    e
}

/// The repository root.
pub fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `rig-configs/mock.toml`.
pub fn mock() -> PathBuf {
    root().join("rig-configs/mock.toml")
}

/// A fresh (removed) directory `lensrig-<prefix>-<pid>-<name>` in the system temp dir.
pub fn tmp(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lensrig-{prefix}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// Writes `dir/rig.toml`: mock.toml with an absolute target path and `edit` applied.
pub fn mock_config(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let text = std::fs::read_to_string(mock()).unwrap();
    let target = root().join("targets/a4-noise-300dpi.toml");
    let text = edit(text.replace("\"../targets/a4-noise-300dpi.toml\"", &format!("{:?}", target.display().to_string())));
    let p = dir.join("rig.toml");
    std::fs::write(&p, text).unwrap();
    p
}
