//! `cargo +nightly fuzz run grbl_line`: the body is `grbl_line` in `fuzz/targets.rs`.
#![no_main]

#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::grbl_line(data));
