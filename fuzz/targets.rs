//! The fuzz target bodies, shared by the `cargo fuzz` targets (`fuzz/fuzz_targets/*.rs`, nightly)
//! and the stable driver (`examples/fuzz_stable.rs`, see `scripts/fuzz.sh`).
//!
//! The rule for every loader: no panic, no hang, no unbounded allocation, and every failure is a
//! one-line error. Each body feeds `data` to one loader and asserts that an error's message is a
//! single line and that an accepted input holds only what the loader promises.

#![allow(dead_code)]

use lensrig::image::validate::{check_values, InvalidPixels};
use std::path::Path;

/// Every target's name, in the order the driver and the script run them.
pub const TARGETS: [&str; 5] = ["image", "profile", "rig_config", "session", "grbl_line"];

fn one_line(e: &dyn std::fmt::Display) {
    let s = e.to_string();
    assert!(!s.trim_end().contains('\n'), "multi-line error: {s}");
}

/// Runs target `name` on `data` (unknown names do nothing).
pub fn run(name: &str, data: &[u8]) {
    match name {
        "image" => image(data),
        "profile" => profile(data),
        "rig_config" => rig_config(data),
        "session" => session(data),
        "grbl_line" => grbl_line(data),
        _ => {}
    }
}

/// PNG/TIFF decoding plus the value check under both policies.
pub fn image(data: &[u8]) {
    match lensrig::image::io::decode_image(Path::new("fuzz.img"), data) {
        Err(e) => one_line(&e),
        Ok(img) => {
            assert!(img.planes.iter().all(|p| p.data.len() == p.width * p.height));
            let mut a = img.clone();
            if let Err(e) = check_values(&mut a, InvalidPixels::Refuse) {
                assert!(!e.to_string().contains('\n'));
            }
            let mut b = img;
            let r = check_values(&mut b, InvalidPixels::Mask).expect("masking never fails");
            assert!(b.planes.iter().all(|p| p.data.iter().all(|v| v.is_finite())));
            assert_eq!(r.masked, r.non_finite());
        }
    }
}

/// A profile: `profile.toml` text, a NUL byte, then the bytes every channel's mosaic reads.
pub fn profile(data: &[u8]) {
    let split = data.iter().position(|&b| b == 0).unwrap_or(data.len());
    let (toml, mosaic) = (&data[..split], data.get(split + 1..).unwrap_or(&[]));
    let read = |p: &Path| -> std::io::Result<Vec<u8>> {
        if p.file_name().is_some_and(|n| n == "profile.toml") {
            Ok(toml.to_vec())
        } else {
            Ok(mosaic.to_vec())
        }
    };
    match lensrig::profile::Profile::load_with(Path::new("fuzz-profile"), &read) {
        Err(e) => one_line(&e),
        Ok(p) => p.validate(Path::new("fuzz-profile")).expect("a loaded profile is valid"),
    }
}

/// A rig config (TOML, parsed and validated).
pub fn rig_config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Err(e) = lensrig::rig::config::parse(text, Path::new("fuzz-rig.toml")) {
        one_line(&e);
    }
}

/// Session sidecars: `session.toml` and a frame's `.toml`.
pub fn session(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Err(e) = toml::from_str::<lensrig::rig::session::SessionRecord>(text) {
        one_line(&lensrig::toml_error(text, &e));
    }
    if let Err(e) = toml::from_str::<lensrig::rig::session::FrameRecord>(text) {
        one_line(&lensrig::toml_error(text, &e));
    }
}

/// The grbl line parser (status reports, responses, alarms, messages).
pub fn grbl_line(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    for line in text.split('\n') {
        let _ = lensrig::rig::controller::protocol::parse_line(line);
        if let Err(e) = lensrig::rig::controller::protocol::parse_status(line) {
            one_line(&e);
        }
    }
}
