//! The binary's panic hook: one line naming the command and where to report, status 70.

use std::process::Command;

#[test]
fn a_panic_prints_one_line_and_exits_70() {
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig"))
        .args(["check-config", "--help"])
        .env("LENSRIG_INJECT_PANIC", "1")
        .env_remove("RUST_BACKTRACE")
        .output()
        .expect("run lensrig");
    assert_eq!(o.status.code(), Some(70));
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(e.trim_end().lines().count(), 1, "{e}");
    assert!(e.contains("internal error (a bug) while running `lensrig check-config --help`"), "{e}");
    assert!(e.contains("injected by LENSRIG_INJECT_PANIC=1 second line") && e.contains("issue tracker"), "{e}");
    assert!(o.stdout.is_empty());
}

#[test]
fn without_the_fault_the_command_runs() {
    let o = Command::new(env!("CARGO_BIN_EXE_lensrig")).args(["--version"]).env("LENSRIG_INJECT_PANIC", "0").output().expect("run lensrig");
    assert_eq!(o.status.code(), Some(0));
}
