//! [`V4lCamera`]: a Linux V4L2 capture device through `v4l` 0.14 (cargo feature `v4l2`).
//!
//! Opens the device, negotiates the configured pixel format and size (recording what the
//! driver actually chose), switches automatic exposure, gain and white balance off, sets
//! exposure and gain **by control ID**, streams through mmap buffers with a poll timeout,
//! drops the frames owed after control or scene changes, averages, and decodes with
//! [`super::decode`].
//!
//! # Quirks
//! - Exposure can only be written after `V4L2_CID_EXPOSURE_AUTO` is set to manual (1);
//!   until then UVC drivers flag it inactive and writes fail with `EACCES`.
//! - Controls are set one per call: `VIDIOC_S_EXT_CTRLS` (which `v4l` uses) rejects a batch
//!   mixing classes (camera class `0x9a…` exposure vs user class `0x98…` gain).
//! - `V4L2_CID_EXPOSURE_ABSOLUTE` counts 100 µs units; the applied value is rounded and
//!   reported back. Cameras without it (e.g. PS3 Eye) use the user-class `V4L2_CID_EXPOSURE`
//!   in driver-specific units, which are taken as µs/100 as well; check your driver.
//! - `set_format` may silently change size or format; a different FourCC than asked is
//!   accepted only when [`super::decode`] supports it, and [`Camera::format`] reports it.
//! - The first frames after a control change still carry the old exposure; the stream is also
//!   deep (4 buffers), so frames recorded before a move are still queued after it. Both are
//!   dropped (`discard_after_change` frames, and at least the queue depth after
//!   [`Camera::invalidate`]).
//! - Webcam YUYV/MJPG is gamma-encoded (and often sharpened/denoised); the frame is marked
//!   [`Transfer::Srgb`](crate::image::Transfer::Srgb) and left encoded.

use std::io;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use v4l::buffer::Type;
use v4l::control::{Control, Value};
use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

use super::decode::{self, ColorMode};
use super::{Averager, Camera, CameraError, Frame, FrameFormat, FrameMeta, FourCc};

/// `V4L2_CID_EXPOSURE_AUTO` (camera class); 1 = `V4L2_EXPOSURE_MANUAL`.
const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
const CID_EXPOSURE: u32 = 0x0098_0911;
const CID_AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
const CID_AUTOGAIN: u32 = 0x0098_0912;
const CID_GAIN: u32 = 0x0098_0913;
const BUFFERS: u32 = 4;

/// How to open a [`V4lCamera`].
#[derive(Clone, Debug, PartialEq)]
pub struct V4lSettings {
    pub device: PathBuf,
    pub fourcc: FourCc,
    pub width: u32,
    pub height: u32,
    pub exposure_us: u32,
    pub gain: f64,
    /// Frames dropped after a control change.
    pub discard_after_change: usize,
    /// Y plane or RGB for colour formats.
    pub color: ColorMode,
    /// Poll timeout for one frame.
    pub frame_timeout: Duration,
}

/// A V4L2 camera. See the module docs for its quirks.
pub struct V4lCamera {
    device: PathBuf,
    dev: Device,
    stream: Option<MmapStream<'static>>,
    format: FrameFormat,
    stride: usize,
    color: ColorMode,
    exposure_us: u32,
    gain: f64,
    discard_after_change: usize,
    owed: usize,
    timeout: Duration,
    card: String,
    driver: String,
}

impl V4lCamera {
    /// Opens and configures the device.
    ///
    /// # Errors
    /// [`CameraError::Open`] naming the path (missing, busy, not a capture device),
    /// [`CameraError::UnsupportedFormat`] listing what the device offers,
    /// [`CameraError::Control`] when manual exposure cannot be set.
    pub fn open(s: &V4lSettings) -> Result<Self, CameraError> {
        let path = s.device.clone();
        let dev = Device::with_path(&path).map_err(|e| open_err(&path, e))?;
        let caps = dev.query_caps().map_err(|e| open_err(&path, e))?;
        let offered: Vec<FourCc> = dev.enum_formats().map_err(|e| open_err(&path, e))?.into_iter().map(|d| FourCc(d.fourcc.repr)).collect();
        if !offered.contains(&s.fourcc) || !decode::SUPPORTED.contains(&s.fourcc) {
            return Err(CameraError::UnsupportedFormat { device: path, wanted: s.fourcc, offered });
        }
        let mut fmt = dev.format().map_err(|e| io_err(&path, e))?;
        fmt.width = s.width;
        fmt.height = s.height;
        fmt.fourcc = FourCC::new(&s.fourcc.0);
        let applied = dev.set_format(&fmt).map_err(|e| io_err(&path, e))?;
        let got = FourCc(applied.fourcc.repr);
        let transfer = decode::transfer_of(got).ok_or_else(|| CameraError::UnsupportedFormat { device: path.clone(), wanted: got, offered: offered.clone() })?;
        let format = FrameFormat { width: applied.width, height: applied.height, fourcc: got, transfer };
        let mut cam = Self {
            device: path,
            dev,
            stream: None,
            format,
            stride: applied.stride as usize,
            color: s.color,
            exposure_us: s.exposure_us,
            gain: s.gain,
            discard_after_change: s.discard_after_change,
            owed: 0,
            timeout: s.frame_timeout,
            card: caps.card,
            driver: caps.driver,
        };
        cam.manual_mode()?;
        cam.set_exposure(s.exposure_us)?;
        cam.set_gain(s.gain)?;
        Ok(cam)
    }

    /// Turns auto exposure, auto gain and auto white balance off where the device has them.
    fn manual_mode(&mut self) -> Result<(), CameraError> {
        let ids: Vec<u32> = self.dev.query_controls().map_err(|e| io_err(&self.device, e))?.iter().map(|d| d.id).collect();
        if ids.contains(&CID_EXPOSURE_AUTO) {
            self.set(CID_EXPOSURE_AUTO, "exposure_auto", Value::Integer(1))?;
        }
        if ids.contains(&CID_AUTOGAIN) {
            self.set(CID_AUTOGAIN, "autogain", Value::Boolean(false))?;
        }
        if ids.contains(&CID_AUTO_WHITE_BALANCE) {
            self.set(CID_AUTO_WHITE_BALANCE, "white_balance_automatic", Value::Boolean(false))?;
        }
        Ok(())
    }

    fn set(&self, id: u32, name: &str, value: Value) -> Result<(), CameraError> {
        // One control per call: a batch must not mix control classes.
        self.dev.set_control(Control { id, value }).map_err(|e| {
            let detail = if e.kind() == io::ErrorKind::PermissionDenied { "rejected (inactive: is auto mode still on?)" } else { "rejected" };
            CameraError::Control { device: self.device.clone(), control: name.into(), detail: detail.into(), source: Some(e) }
        })
    }

    fn read_int(&self, id: u32) -> Option<i64> {
        match self.dev.control(id).ok()?.value {
            Value::Integer(v) => Some(v),
            _ => None,
        }
    }

    fn control_range(&self, id: u32) -> Option<(i64, i64)> {
        let d = self.dev.query_controls().ok()?.into_iter().find(|d| d.id == id)?;
        Some((d.minimum, d.maximum))
    }

    fn stream(&mut self) -> Result<&mut MmapStream<'static>, CameraError> {
        if self.stream.is_none() {
            let mut s = MmapStream::with_buffers(&self.dev, Type::VideoCapture, BUFFERS).map_err(|e| io_err(&self.device, e))?;
            s.set_timeout(self.timeout);
            self.stream = Some(s);
        }
        self.stream.as_mut().ok_or_else(|| CameraError::InvalidArgument { device: self.device.clone(), what: "stream not available".into() })
    }

    /// The next raw frame: bytes (copied) and sequence number.
    fn next_raw(&mut self) -> Result<(Vec<u8>, u32), CameraError> {
        let device = self.device.clone();
        let timeout = self.timeout;
        let stream = self.stream()?;
        match stream.next() {
            Ok((buf, meta)) => {
                let used = (meta.bytesused as usize).min(buf.len());
                let used = if used == 0 { buf.len() } else { used };
                Ok((buf[..used].to_vec(), meta.sequence))
            }
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock) => Err(CameraError::Timeout { device, after: timeout }),
            Err(e) => Err(io_err(&device, e)),
        }
    }
}

fn open_err(path: &Path, e: io::Error) -> CameraError {
    let hint = match e.kind() {
        io::ErrorKind::NotFound => " (no such device: see `v4l2-ctl --list-devices`)",
        io::ErrorKind::PermissionDenied => " (permission denied: is the user in the 'video' group?)",
        _ if e.raw_os_error() == Some(16) => " (busy: another program is streaming from it)",
        _ => "",
    };
    CameraError::Open { device: path.to_path_buf(), hint: hint.into(), source: e }
}

fn io_err(path: &Path, e: io::Error) -> CameraError {
    if e.raw_os_error() == Some(16) {
        return open_err(path, e);
    }
    CameraError::Io { device: path.to_path_buf(), source: e }
}

impl Camera for V4lCamera {
    fn format(&self) -> FrameFormat {
        self.format
    }

    fn set_exposure(&mut self, us: u32) -> Result<u32, CameraError> {
        let (id, name) = if self.control_range(CID_EXPOSURE_ABSOLUTE).is_some() { (CID_EXPOSURE_ABSOLUTE, "exposure_time_absolute") } else { (CID_EXPOSURE, "exposure") };
        let (lo, hi) = self.control_range(id).ok_or_else(|| CameraError::Control {
            device: self.device.clone(),
            control: name.into(),
            detail: "the device has no exposure control".into(),
            source: None,
        })?;
        let units = (us as f64 / 100.0).round() as i64;
        if units < lo || units > hi {
            return Err(CameraError::Control {
                device: self.device.clone(),
                control: name.into(),
                detail: format!("{us} µs is outside the device range [{} µs, {} µs]", lo * 100, hi * 100),
                source: None,
            });
        }
        self.set(id, name, Value::Integer(units))?;
        let applied = self.read_int(id).unwrap_or(units);
        self.exposure_us = (applied.max(0) * 100) as u32;
        self.owed = self.owed.max(self.discard_after_change);
        Ok(self.exposure_us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, CameraError> {
        let Some((lo, hi)) = self.control_range(CID_GAIN) else {
            if gain == 0.0 {
                self.gain = 0.0;
                return Ok(0.0); // no gain control: fixed gain
            }
            return Err(CameraError::Control { device: self.device.clone(), control: "gain".into(), detail: "the device has no gain control".into(), source: None });
        };
        let v = gain.round() as i64;
        if v < lo || v > hi {
            return Err(CameraError::Control { device: self.device.clone(), control: "gain".into(), detail: format!("{gain} is outside [{lo}, {hi}]"), source: None });
        }
        self.set(CID_GAIN, "gain", Value::Integer(v))?;
        self.gain = self.read_int(CID_GAIN).unwrap_or(v) as f64;
        self.owed = self.owed.max(self.discard_after_change);
        Ok(self.gain)
    }

    fn capture(&mut self, frames: usize) -> Result<Frame, CameraError> {
        if frames == 0 {
            return Err(CameraError::InvalidArgument { device: self.device.clone(), what: "capture of 0 frames".into() });
        }
        let discarded = self.owed;
        for _ in 0..self.owed {
            self.next_raw()?;
        }
        self.owed = 0;
        let f = self.format;
        let mut avg = Averager::new();
        let mut first: Option<(SystemTime, u32)> = None;
        for _ in 0..frames {
            let (bytes, seq) = self.next_raw()?;
            if first.is_none() {
                first = Some((SystemTime::now(), seq));
            }
            let img = decode::decode(f.fourcc, f.width as usize, f.height as usize, self.stride, &bytes, self.color)
                .map_err(|source| CameraError::Decode { device: self.device.clone(), source })?;
            avg.add(&img).map_err(|what| CameraError::InvalidArgument { device: self.device.clone(), what })?;
        }
        let (time, seq) = first.unwrap_or((SystemTime::now(), 0));
        let image = avg.finish().ok_or_else(|| CameraError::InvalidArgument { device: self.device.clone(), what: "no frame averaged".into() })?;
        Ok(Frame {
            meta: FrameMeta {
                time,
                exposure_us: self.exposure_us,
                gain: self.gain,
                frames_averaged: frames,
                frames_discarded: discarded,
                transfer: image.transfer,
                fourcc: f.fourcc,
                sequence: Some(seq),
            },
            image,
        })
    }

    fn invalidate(&mut self) {
        self.owed = self.owed.max(self.discard_after_change).max(BUFFERS as usize);
    }

    fn describe(&self) -> String {
        let f = self.format;
        format!("V4L2 {} ({}, {}) {} {}x{} {}", self.device.display(), self.card, self.driver, f.fourcc, f.width, f.height, f.transfer.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Opt-in: `LENSRIG_V4L2_DEVICE=/dev/video0 cargo test --features v4l2 v4l2_device`.
    #[test]
    fn v4l2_device_captures_when_configured() {
        let Ok(dev) = std::env::var("LENSRIG_V4L2_DEVICE") else {
            eprintln!("LENSRIG_V4L2_DEVICE not set; skipping the real-camera test");
            return;
        };
        let fourcc = FourCc::from_str_padded(&std::env::var("LENSRIG_V4L2_FOURCC").unwrap_or_else(|_| "YUYV".into()));
        let s = V4lSettings {
            device: dev.into(),
            fourcc,
            width: 640,
            height: 480,
            exposure_us: 10_000,
            gain: 0.0,
            discard_after_change: 3,
            color: ColorMode::Luma,
            frame_timeout: Duration::from_secs(2),
        };
        let mut cam = V4lCamera::open(&s).unwrap();
        eprintln!("{}", cam.describe());
        let f = cam.capture(2).unwrap();
        assert_eq!(f.meta.frames_averaged, 2);
        assert_eq!(f.meta.frames_discarded, 3);
        assert_eq!((f.image.width(), f.image.height()), (cam.format().width as usize, cam.format().height as usize));
    }

    #[test]
    fn missing_device_names_the_path() {
        let s = V4lSettings {
            device: "/dev/video-lensrig-missing".into(),
            fourcc: FourCc(*b"YUYV"),
            width: 640,
            height: 480,
            exposure_us: 1000,
            gain: 0.0,
            discard_after_change: 3,
            color: ColorMode::Luma,
            frame_timeout: Duration::from_secs(1),
        };
        let e = V4lCamera::open(&s).err().unwrap().to_string();
        assert!(e.contains("/dev/video-lensrig-missing") && e.contains("no such device"), "{e}");
    }
}
