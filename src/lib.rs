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

pub mod fsutil;
pub mod image;
pub mod rig;
pub mod solve;
