//! Cameras: the [`Camera`] trait, the frames it returns, and pixel-format decoding.
//!
//! - [`decode`]: pure raw-buffer → [`Image`] decoders for the V4L2 formats a rig meets.
//! - [`v4l`]: [`V4lCamera`] on Linux V4L2 devices (opening a real device needs cargo
//!   feature `v4l2`; the camera logic is built and tested without it, on a fake device).
//! - [`mock`]: [`MockCamera`], rendering the target through the simulated lens at the
//!   aperture and stage position the controller reports.
//!
//! # Conventions
//! - A [`Frame`] holds the image **as recorded**: values on the full-scale axis, gamma-encoded
//!   when the device sends encoded data ([`FrameMeta::transfer`] says which). Averages over
//!   several frames are taken on *linear* values and re-encoded with the same transfer, so
//!   averaging never bends the tone curve.
//! - [`Camera::format`] is what the driver actually applied, not what was asked.
//! - Frames that follow a control change (exposure, gain) or a scene change
//!   ([`Camera::invalidate`]) are dropped before the next capture.

pub mod decode;
pub mod mock;
pub mod v4l;

use std::fmt;
use std::path::PathBuf;
use std::time::{Duration, SystemTime};

use crate::image::{Image, Plane, Transfer};

pub use self::mock::MockCamera;
pub use self::v4l::V4lCamera;

/// A V4L2 pixel format code (`*b"YUYV"`, `*b"Y16 "`).
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct FourCc(pub [u8; 4]);

impl FourCc {
    /// From 1–4 characters, space padded (`"Y16"` → `"Y16 "`).
    pub fn from_str_padded(s: &str) -> FourCc {
        let mut f = [b' '; 4];
        for (d, b) in f.iter_mut().zip(s.bytes()) {
            *d = b;
        }
        FourCc(f)
    }
}

impl fmt::Display for FourCc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s: String = self.0.iter().map(|&b| if b.is_ascii_graphic() || b == b' ' { b as char } else { '?' }).collect();
        write!(f, "'{s}'")
    }
}

impl fmt::Debug for FourCc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(self, f)
    }
}

/// The format the device delivers, as negotiated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameFormat {
    pub width: u32,
    pub height: u32,
    pub fourcc: FourCc,
    pub transfer: Transfer,
}

/// What was true when a frame was recorded.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameMeta {
    /// Wall-clock time of the first averaged frame.
    pub time: SystemTime,
    /// Exposure actually applied (µs; V4L2 rounds to 100 µs).
    pub exposure_us: u32,
    pub gain: f64,
    pub frames_averaged: usize,
    /// Frames dropped before this capture (after control or scene changes).
    pub frames_discarded: usize,
    pub transfer: Transfer,
    pub fourcc: FourCc,
    /// Driver sequence number of the first averaged frame, when the device gives one.
    pub sequence: Option<u32>,
}

impl FrameMeta {
    /// The metadata of a capture that averaged `frames.0` frames after dropping `frames.1`.
    pub fn new(time: SystemTime, exposure_us: u32, gain: f64, frames: (usize, usize), transfer: Transfer, fourcc: FourCc, sequence: Option<u32>) -> Self {
        Self { time, exposure_us, gain, frames_averaged: frames.0, frames_discarded: frames.1, transfer, fourcc, sequence }
    }
}

/// One capture: an image and its metadata.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub image: Image,
    pub meta: FrameMeta,
    /// Per channel, the temporal variance of *one* frame's stored values at every pixel (the
    /// unbiased sample variance over the averaged frames; `None` for a single frame). The
    /// variance of the stored average is this divided by `frames_averaged` (exactly for linear
    /// data, to first order for encoded data).
    pub temporal_variance: Option<Vec<Plane>>,
}

/// Per-pixel sums of stored values and their squares over repeated frames: the temporal
/// variance behind [`Frame::temporal_variance`].
#[derive(Debug, Default)]
pub struct Repeats {
    sum: Vec<Vec<f64>>,
    sum_sq: Vec<Vec<f64>>,
    dims: Vec<(usize, usize)>,
    count: usize,
}

impl Repeats {
    /// Adds one frame's planes (stored values); planes of another shape than the first frame's
    /// are ignored (the averager reports that mismatch).
    pub fn add(&mut self, planes: &[Plane]) {
        if self.count == 0 {
            self.sum = planes.iter().map(|p| vec![0.0; p.data.len()]).collect();
            self.sum_sq = self.sum.clone();
            self.dims = planes.iter().map(|p| (p.width, p.height)).collect();
        } else if planes.len() != self.sum.len() || planes.iter().zip(&self.dims).any(|(p, d)| (p.width, p.height) != *d) {
            return;
        }
        for ((s, q), p) in self.sum.iter_mut().zip(self.sum_sq.iter_mut()).zip(planes) {
            for ((a, b), &v) in s.iter_mut().zip(q.iter_mut()).zip(&p.data) {
                *a += v as f64;
                *b += (v as f64) * (v as f64);
            }
        }
        self.count += 1;
    }

    /// The unbiased per-pixel variance, `(Σv² − (Σv)²/n)/(n − 1)`; `None` below two frames.
    pub fn variance(&self) -> Option<Vec<Plane>> {
        if self.count < 2 {
            return None;
        }
        let n = self.count as f64;
        Some(
            self.sum
                .iter()
                .zip(&self.sum_sq)
                .zip(&self.dims)
                .map(|((s, q), &(w, h))| Plane { width: w, height: h, data: s.iter().zip(q).map(|(&a, &b)| ((b - a * a / n) / (n - 1.0)).max(0.0) as f32).collect() })
                .collect(),
        )
    }
}

/// The temporal noise curve of one frame: pixels binned by the level of the averaged image
/// (equal counts, `bins` bins; clipped or black pixels left out), each bin's mean level and
/// mean single-frame variance, both on the stored axis: `[level, variance, pixels]` rows.
pub fn temporal_noise_curve(mean: &Plane, variance: &Plane, bins: usize) -> Vec<[f64; 3]> {
    let mut px: Vec<(f32, f32)> = mean.data.iter().zip(&variance.data).filter(|(&m, _)| m > 0.002 && m < 0.995).map(|(&m, &v)| (m, v)).collect();
    if px.is_empty() || bins == 0 {
        return Vec::new();
    }
    px.sort_by(|a, b| a.0.total_cmp(&b.0));
    let per = px.len().div_ceil(bins);
    px.chunks(per)
        .map(|c| {
            let n = c.len() as f64;
            [c.iter().map(|p| p.0 as f64).sum::<f64>() / n, c.iter().map(|p| p.1 as f64).sum::<f64>() / n, n]
        })
        .collect()
}

/// A camera, as the capture code sees it.
pub trait Camera {
    /// The negotiated format.
    fn format(&self) -> FrameFormat;

    /// Sets the exposure (manual mode); returns the value the device applied.
    ///
    /// # Errors
    /// The control is missing, out of range or rejected.
    fn set_exposure(&mut self, us: u32) -> Result<u32, CameraError>;

    /// Sets the analogue gain (manual mode); returns the value the device applied.
    ///
    /// # Errors
    /// As [`Camera::set_exposure`].
    fn set_gain(&mut self, gain: f64) -> Result<f64, CameraError>;

    /// Records `frames` frames (≥ 1) and returns their average, after dropping the frames
    /// owed since the last control or scene change.
    ///
    /// # Errors
    /// A timeout, a lost device, an undecodable buffer.
    fn capture(&mut self, frames: usize) -> Result<Frame, CameraError>;

    /// The scene changed (an axis moved): frames already queued are stale and will be dropped
    /// before the next capture.
    fn invalidate(&mut self);

    /// One line naming the device, driver and format, for logs and session metadata.
    fn describe(&self) -> String;
}

/// Everything that can go wrong with a camera. Each variant names the device.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("cannot open camera {device}{hint}")]
    Open {
        device: PathBuf,
        hint: String,
        #[source]
        source: std::io::Error,
    },
    #[error("camera {device}: pixel format {wanted} is not supported (device offers: {}; lensrig decodes: {})",
        list(.offered), list(&decode::SUPPORTED))]
    UnsupportedFormat { device: PathBuf, wanted: FourCc, offered: Vec<FourCc> },
    #[error("camera {device}: control {control}: {detail}")]
    Control {
        device: PathBuf,
        control: String,
        detail: String,
        #[source]
        source: Option<std::io::Error>,
    },
    #[error("camera {device}: no frame within {after:?}")]
    Timeout { device: PathBuf, after: Duration },
    #[error("camera {device}: frame does not decode")]
    Decode {
        device: PathBuf,
        #[source]
        source: decode::DecodeError,
    },
    #[error("camera {device}: {what}")]
    InvalidArgument { device: PathBuf, what: String },
    /// Frames averaged into one capture differ in size, channels or transfer.
    #[error("camera {device}: {source}")]
    FrameMismatch {
        device: PathBuf,
        #[source]
        source: FrameMismatch,
    },
    #[error("camera {device}: I/O error")]
    Io {
        device: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

fn list(f: &[FourCc]) -> String {
    if f.is_empty() {
        return "none".into();
    }
    f.iter().map(ToString::to_string).collect::<Vec<_>>().join(", ")
}

/// What frames averaged together must share: size, channel count and transfer curve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameShape {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub transfer: Transfer,
}

impl FrameShape {
    pub fn of(img: &Image) -> Self {
        Self { width: img.width(), height: img.height(), channels: img.channel_count(), transfer: img.transfer }
    }
}

impl std::fmt::Display for FrameShape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}x{}x{} ({})", self.width, self.height, self.channels, self.transfer.name())
    }
}

/// A frame that cannot be averaged with the first one ([`Averager::add`]).
#[derive(Debug, thiserror::Error)]
#[error("frame {got} differs from the first {first}")]
pub struct FrameMismatch {
    pub got: FrameShape,
    pub first: FrameShape,
}

/// Averages frames on linear values and re-encodes the mean with the frames' transfer.
#[derive(Debug, Default)]
pub struct Averager {
    sum: Vec<Vec<f64>>,
    template: Option<Image>,
    count: usize,
}

impl Averager {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one frame.
    ///
    /// # Errors
    /// A frame whose size, channel count or transfer differs from the first
    /// ([`FrameMismatch`] says how).
    pub fn add(&mut self, img: &Image) -> Result<(), FrameMismatch> {
        if let Some(t) = &self.template {
            let (got, first) = (FrameShape::of(img), FrameShape::of(t));
            if got != first {
                return Err(FrameMismatch { got, first });
            }
        } else {
            self.sum = img.planes.iter().map(|p| vec![0.0; p.len()]).collect();
            self.template = Some(img.clone());
        }
        for (acc, p) in self.sum.iter_mut().zip(&img.planes) {
            for (a, &v) in acc.iter_mut().zip(&p.data) {
                *a += img.transfer.decode(v) as f64;
            }
        }
        self.count += 1;
        Ok(())
    }

    /// Frames added so far.
    pub fn count(&self) -> usize {
        self.count
    }

    /// The mean, encoded like the inputs; `None` before the first frame.
    pub fn finish(self) -> Option<Image> {
        let mut img = self.template?;
        let n = self.count as f64;
        for (p, acc) in img.planes.iter_mut().zip(&self.sum) {
            *p = Plane { width: p.width, height: p.height, data: acc.iter().map(|&s| img.transfer.encode((s / n) as f32)).collect() };
        }
        Some(img)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fourcc_display_and_padding() {
        assert_eq!(FourCc::from_str_padded("Y16"), FourCc(*b"Y16 "));
        assert_eq!(FourCc(*b"YUYV").to_string(), "'YUYV'");
        let e = CameraError::UnsupportedFormat { device: "/dev/video3".into(), wanted: FourCc(*b"Y16 "), offered: vec![FourCc(*b"H264"), FourCc(*b"NV12")] };
        let m = e.to_string();
        assert!(m.contains("/dev/video3") && m.contains("'Y16 '") && m.contains("'H264', 'NV12'") && m.contains("'YUYV'"), "{m}");
    }

    #[test]
    fn repeats_give_the_unbiased_variance_and_binned_curve() {
        let mut r = Repeats::default();
        assert!(r.variance().is_none());
        for v in [0.1f32, 0.3, 0.2] {
            r.add(&[Plane::filled(4, 1, v), Plane::filled(4, 1, 2.0 * v)]);
        }
        // a frame of another shape is ignored
        r.add(&[Plane::filled(3, 1, 9.0)]);
        let var = r.variance().unwrap();
        // sample variance of 0.1, 0.3, 0.2 is 0.01; doubled values: 0.04
        assert!((var[0].data[0] - 0.01).abs() < 1e-6 && (var[1].data[3] - 0.04).abs() < 1e-6, "{var:?}");
        let mean = Plane { width: 4, height: 1, data: vec![0.1, 0.2, 0.3, 1.0] };
        let v = Plane { width: 4, height: 1, data: vec![1.0, 2.0, 3.0, 99.0] };
        // the clipped pixel is left out; two bins of the three others (equal counts, by level)
        let c = temporal_noise_curve(&mean, &v, 2);
        assert_eq!(c.len(), 2);
        assert!((c[0][0] - 0.15).abs() < 1e-6 && (c[0][1] - 1.5).abs() < 1e-6 && c[0][2] == 2.0, "{c:?}");
        assert!((c[1][0] - 0.3).abs() < 1e-6 && (c[1][1] - 3.0).abs() < 1e-6, "{c:?}");
    }

    #[test]
    fn averager_is_linear_and_keeps_encoding() {
        let mut a = Averager::new();
        let mut img = Image::new(vec![Plane::filled(2, 1, 0.0)]);
        img.transfer = Transfer::Srgb;
        a.add(&img).unwrap();
        img.planes[0] = Plane::filled(2, 1, 1.0);
        a.add(&img).unwrap();
        assert_eq!(a.count(), 2);
        let mut wrong = Image::new(vec![Plane::filled(3, 1, 0.0)]);
        wrong.transfer = Transfer::Srgb;
        assert!(a.add(&wrong).unwrap_err().to_string().contains("differs"));
        let out = a.finish().unwrap();
        assert_eq!(out.transfer, Transfer::Srgb);
        // Mean of linear 0 and 1 is 0.5 linear = 0.7354 encoded, not 0.5.
        assert!((out.planes[0].data[0] - 0.735_356_6).abs() < 1e-5);
        assert!(Averager::new().finish().is_none());
    }
}
