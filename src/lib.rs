//! # lensrig
//!
//! Replace an expensive objective with one simple lens and fix its aberrations in software:
//! drive a calibration rig, measure the lens's point-spread functions (PSFs) from a wide-open /
//! pinhole pair of a printed noise target (Heide et al. 2013, Sec. 6), write a lens profile,
//! restore images with it, and diagnose where the forward model and the recording disagree.
//!
//! ## Data flow
//! rig → session on disk → [`estimate`] → [`profile`] → deconvolution / diagnosis. Each stage
//! reads and writes files a user can inspect, so each can be rerun alone.
//!
//! ## Conventions (read these before touching pixels)
//! - **Axes**: planes are row-major, `x` right, `y` down, `(0,0)` the top-left pixel centre
//!   ([`image`]).
//! - **Values**: `f32` on a full-scale axis (1.0 = the file's largest code). Physics runs on
//!   linear values only; gamma-encoded data is marked [`image::Transfer::Srgb`].
//! - **PSFs**: odd `k × k`, centre `c = (k−1)/2` is zero displacement, applied as a true
//!   convolution `out(x,y) = Σ K[v][u]·sharp(x−(u−c), y−(v−c))`, each kernel sums to 1
//!   ([`solve::conv`]).
//! - **FFT**: unnormalised forward, `1/N` inverse ([`solve::fft`]).
//! - **Field positions**: pixel coordinates of the full image; the optical centre is the image
//!   centre `((w−1)/2, (h−1)/2)` unless a profile says otherwise.

// Index loops over several parallel arrays are the clearest form of the numerics here.
#![allow(clippy::needless_range_loop)]

pub mod deconv;
pub mod diagnose;
pub mod estimate;
pub mod export;
pub mod fsutil;
pub mod image;
pub mod optics;
pub mod rig;
pub mod solve;
pub mod profile;
pub mod report;
pub mod rng;
pub mod target;

/// The current time as an RFC 3339 UTC string (seconds precision), without a date crate.
pub fn timestamp_utc() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    // civil-from-days (Howard Hinnant)
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = if m <= 2 { y + 1 } else { y };
    format!("{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z", rem / 3600, (rem % 3600) / 60, rem % 60)
}

/// Formats a TOML parse error as `line L, column C: message` (the key is in toml's message).
pub fn toml_error(text: &str, e: &toml::de::Error) -> String {
    match e.span() {
        Some(span) => {
            let before = &text[..span.start.min(text.len())];
            let line = before.matches('\n').count() + 1;
            let col = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            format!("line {line}, column {col}: {}", e.message())
        }
        None => e.message().to_string(),
    }
}
