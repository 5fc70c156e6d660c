//! `cargo +nightly fuzz run rig_config`: the body is `rig_config` in `fuzz/targets.rs`.
#![no_main]

#[path = "../targets.rs"]
mod targets;

libfuzzer_sys::fuzz_target!(|data: &[u8]| targets::rig_config(data));
