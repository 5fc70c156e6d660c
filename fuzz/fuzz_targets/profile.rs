//! `cargo +nightly fuzz run profile`: the body is `profile` in `fuzz/targets.rs`.
#![no_main]

#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::profile(data));
