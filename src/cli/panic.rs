//! A panic is a bug report: the hook that turns one into a single line and a distinct status.
//!
//! [`install`] replaces Rust's default panic output (several lines, a backtrace hint) with one
//! line on stderr that says what lensrig was doing (the command and its arguments), what
//! panicked and where, and where to report it; then the process exits with [`PANIC_STATUS`]
//! (70, `EX_SOFTWARE` of sysexits.h), distinct from 2 (bad input) and 0 (success). Files are
//! only ever renamed into place when complete (see `lensrig::fsutil`), so whatever a panic
//! interrupts leaves no half-written file; a capture session resumes from its journal.
//!
//! `RUST_BACKTRACE=1` still prints the backtrace after the line, for the report.
//! `LENSRIG_INJECT_PANIC=1` panics right after the hook is installed: the end-to-end test of
//! the hook, and a way for a user to see what a bug report looks like.

/// Exit status after a panic (an internal error: a bug, not bad input).
pub const PANIC_STATUS: i32 = 70;

/// Where bugs are reported.
pub const REPORT_TO: &str = "the lensrig issue tracker (attach this line, the command and, if you can, the input files)";

/// The one line printed for a panic while running `doing`.
pub fn report_line(doing: &str, message: &str, location: Option<String>) -> String {
    let one_line = |s: &str| s.split_whitespace().collect::<Vec<_>>().join(" ");
    let at = location.map(|l| format!(" at {l}")).unwrap_or_default();
    format!(
        "lensrig: internal error (a bug) while running `{}`: {}{at}; please report it to {REPORT_TO}",
        one_line(doing),
        one_line(message)
    )
}

fn message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-text payload".to_string()
    }
}

/// Installs the hook; `args` is the command line (the program name is dropped).
pub fn install(args: impl IntoIterator<Item = String>) {
    let doing = args.into_iter().skip(1).collect::<Vec<_>>().join(" ");
    let doing = if doing.is_empty() { "lensrig".to_string() } else { format!("lensrig {doing}") };
    std::panic::set_hook(Box::new(move |info| {
        let loc = info.location().map(|l| format!("{}:{}", l.file(), l.line()));
        eprintln!("{}", report_line(&doing, &message(info.payload()), loc));
        if std::env::var_os("RUST_BACKTRACE").is_some_and(|v| v != "0") {
            eprintln!("{}", std::backtrace::Backtrace::force_capture());
        }
        std::process::exit(PANIC_STATUS);
    }));
    if std::env::var_os("LENSRIG_INJECT_PANIC").is_some_and(|v| v == "1") {
        panic!("injected by LENSRIG_INJECT_PANIC=1\nsecond line");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_report_is_one_line_with_the_command_and_where_to_report() {
        let l = report_line("lensrig estimate --open a.png", "index out of\nbounds", Some("src/x.rs:3".into()));
        assert_eq!(l.lines().count(), 1);
        assert!(l.contains("`lensrig estimate --open a.png`") && l.contains("index out of bounds at src/x.rs:3") && l.contains(REPORT_TO), "{l}");
        assert_ne!(PANIC_STATUS, 2);
    }
}
