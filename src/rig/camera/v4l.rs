//! [`V4lCamera`]: a Linux V4L2 capture device.
//!
//! Opens the device, negotiates the configured pixel format and size (recording what the
//! driver actually chose), switches automatic exposure, gain and white balance off, sets
//! exposure and gain **by control ID**, streams through mmap buffers with a poll timeout,
//! drops the frames owed after control or scene changes, averages, and decodes with
//! [`super::decode`].
//!
//! The camera logic talks to the device only through [`V4lDevice`], the handful of V4L2 calls
//! it makes. [`list_formats_ext`] and [`list_ctrls`] print what a device offers in
//! `v4l2-ctl`'s words (`lensrig devices`). With cargo feature `v4l2`, `V4lCamera::open` runs them as ioctls through `v4l`
//! 0.14; without it (and in the unit tests, which use a fake device that behaves like a UVC
//! camera) the logic still builds and is tested: [`V4lCamera::with_device`].
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

use super::decode::{self, ColorMode};
use super::{Averager, Camera, CameraError, Frame, FrameFormat, FrameMeta, FourCc, Repeats};

/// `V4L2_CID_EXPOSURE_AUTO` (camera class); 1 = `V4L2_EXPOSURE_MANUAL`.
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// `V4L2_CID_EXPOSURE_ABSOLUTE` (camera class), 100 µs units.
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_CID_EXPOSURE` (user class), driver units.
pub const CID_EXPOSURE: u32 = 0x0098_0911;
pub const CID_AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
pub const CID_AUTOGAIN: u32 = 0x0098_0912;
pub const CID_GAIN: u32 = 0x0098_0913;
/// mmap buffers in the stream (frames that can be queued before a capture reads them).
pub const BUFFERS: u32 = 4;

/// A pixel format as set or applied (`VIDIOC_S_FMT`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceFormat {
    pub width: u32,
    pub height: u32,
    pub fourcc: FourCc,
    /// Bytes per line (0 = packed).
    pub stride: u32,
}

/// A control the device has and its range (`VIDIOC_QUERYCTRL`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ControlRange {
    pub id: u32,
    pub minimum: i64,
    pub maximum: i64,
}

/// A control value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ControlValue {
    Integer(i64),
    Boolean(bool),
}

/// The V4L2 calls [`V4lCamera`] makes. Errors are the driver's `errno` as [`io::Error`]
/// (`EBUSY`, `EACCES` for an inactive control, `TimedOut` when no frame arrives).
pub trait V4lDevice {
    /// Card and driver names (`VIDIOC_QUERYCAP`).
    fn identify(&self) -> io::Result<(String, String)>;
    /// The pixel formats offered (`VIDIOC_ENUM_FMT`).
    fn formats(&self) -> io::Result<Vec<FourCc>>;
    /// Asks for a format; returns what the driver applied (it may differ).
    fn set_format(&mut self, want: DeviceFormat) -> io::Result<DeviceFormat>;
    /// The controls the device has.
    fn controls(&self) -> io::Result<Vec<ControlRange>>;
    /// Sets one control (one per call: a batch must not mix control classes).
    fn set_control(&mut self, id: u32, value: ControlValue) -> io::Result<()>;
    /// Reads one integer control.
    fn control(&self, id: u32) -> io::Result<i64>;
    /// The next frame (bytes used, sequence number); starts streaming on the first call.
    fn next_frame(&mut self, timeout: Duration) -> io::Result<(Vec<u8>, u32)>;

    /// Discrete frame sizes offered for `fourcc` (`VIDIOC_ENUM_FRAMESIZES`); empty when the
    /// backend does not enumerate them.
    fn frame_sizes(&self, _fourcc: FourCc) -> io::Result<Vec<(u32, u32)>> {
        Ok(Vec::new())
    }

    /// The controls with names, types and current values, as `v4l2-ctl --list-ctrls` shows
    /// them. The default derives them from [`V4lDevice::controls`], [`V4lDevice::control`]
    /// and the names of the IDs lensrig knows.
    fn describe_controls(&self) -> io::Result<Vec<ControlDesc>> {
        Ok(self
            .controls()?
            .into_iter()
            .map(|c| {
                let (name, kind) = known_control(c.id);
                ControlDesc { id: c.id, name: name.into(), kind, minimum: c.minimum, maximum: c.maximum, step: 1, default: None, value: self.control(c.id).ok() }
            })
            .collect())
    }
}

/// A control as `VIDIOC_QUERYCTRL` describes it, plus its current value.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ControlDesc {
    pub id: u32,
    /// v4l2-ctl's name (`exposure_time_absolute`).
    pub name: String,
    /// `int`, `bool` or `menu`.
    pub kind: &'static str,
    pub minimum: i64,
    pub maximum: i64,
    pub step: i64,
    pub default: Option<i64>,
    pub value: Option<i64>,
}

/// v4l2-ctl's name and type of a control ID lensrig uses.
fn known_control(id: u32) -> (&'static str, &'static str) {
    match id {
        CID_EXPOSURE_AUTO => ("auto_exposure", "menu"),
        CID_EXPOSURE_ABSOLUTE => ("exposure_time_absolute", "int"),
        CID_EXPOSURE => ("exposure", "int"),
        CID_AUTO_WHITE_BALANCE => ("white_balance_automatic", "bool"),
        CID_AUTOGAIN => ("gain_automatic", "bool"),
        CID_GAIN => ("gain", "int"),
        _ => ("unknown", "int"),
    }
}

/// The listing of `v4l2-ctl --list-formats-ext`: every format with its frame sizes.
///
/// # Errors
/// The device's `errno`.
pub fn list_formats_ext(dev: &dyn V4lDevice) -> io::Result<String> {
    let mut out = String::from("ioctl: VIDIOC_ENUM_FMT\n\tType: Video Capture\n\n");
    for (i, f) in dev.formats()?.into_iter().enumerate() {
        let what = match &f.0 {
            b"YUYV" => "YUYV 4:2:2",
            b"MJPG" => "Motion-JPEG, compressed",
            b"GREY" => "8-bit Greyscale",
            b"Y16 " => "16-bit Greyscale",
            b"RGB3" => "24-bit RGB 8-8-8",
            _ => "",
        };
        let decodes = if decode::SUPPORTED.contains(&f) { "" } else { "  [lensrig cannot decode]" };
        let what = if what.is_empty() { String::new() } else { format!(" ({what})") };
        out += &format!("\t[{i}]: {f}{what}{decodes}\n");
        for (w, h) in dev.frame_sizes(f)? {
            out += &format!("\t\tSize: Discrete {w}x{h}\n");
        }
    }
    Ok(out)
}

/// The listing of `v4l2-ctl --list-ctrls`: user-class then camera-class controls, each
/// with its range, default and current value.
///
/// # Errors
/// The device's `errno`.
pub fn list_ctrls(dev: &dyn V4lDevice) -> io::Result<String> {
    let mut ctrls = dev.describe_controls()?;
    ctrls.sort_by_key(|c| c.id);
    let mut out = String::new();
    let mut class = 0;
    for c in ctrls {
        if c.id >> 16 != class {
            class = c.id >> 16;
            out += match class {
                0x98 => "\nUser Controls\n\n",
                0x9a => "\nCamera Controls\n\n",
                _ => "\nOther Controls\n\n",
            };
        }
        let range = if c.kind == "bool" { String::new() } else { format!("min={} max={} ", c.minimum, c.maximum) };
        let step = if c.kind == "int" { format!("step={} ", c.step) } else { String::new() };
        let default = c.default.map(|d| format!("default={d} ")).unwrap_or_default();
        let value = c.value.map(|v| format!("value={v}")).unwrap_or_default();
        out += &format!("{:>31} {:#010x} {:<8} : {range}{step}{default}{value}\n", c.name, c.id, format!("({})", c.kind));
    }
    Ok(out)
}

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
    dev: Box<dyn V4lDevice>,
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
    /// Opens and configures the device at `s.device` (feature `v4l2`).
    ///
    /// # Errors
    /// [`CameraError::Open`] naming the path (missing, busy, not a capture device), and the
    /// errors of [`V4lCamera::with_device`].
    #[cfg(feature = "v4l2")]
    pub fn open(s: &V4lSettings) -> Result<Self, CameraError> {
        let dev = real::RealDevice::open(&s.device).map_err(|e| open_err(&s.device, e))?;
        Self::with_device(Box::new(dev), s)
    }

    /// Configures an opened device: negotiates the format, switches the automatic controls
    /// off, then sets exposure and gain.
    ///
    /// # Errors
    /// [`CameraError::UnsupportedFormat`] listing what the device offers (the wanted format is
    /// not offered, or the driver substituted one lensrig cannot decode),
    /// [`CameraError::Control`] when manual exposure cannot be set, [`CameraError::Open`] for
    /// a busy device.
    pub fn with_device(mut dev: Box<dyn V4lDevice>, s: &V4lSettings) -> Result<Self, CameraError> {
        let path = s.device.clone();
        let (card, driver) = dev.identify().map_err(|e| open_err(&path, e))?;
        let offered = dev.formats().map_err(|e| open_err(&path, e))?;
        if !offered.contains(&s.fourcc) || !decode::SUPPORTED.contains(&s.fourcc) {
            return Err(CameraError::UnsupportedFormat { device: path, wanted: s.fourcc, offered });
        }
        let applied = dev.set_format(DeviceFormat { width: s.width, height: s.height, fourcc: s.fourcc, stride: 0 }).map_err(|e| io_err(&path, e))?;
        let got = applied.fourcc;
        // a substitute the driver picked is accepted only when lensrig can decode it
        let Some(transfer) = decode::transfer_of(got) else {
            return Err(CameraError::UnsupportedFormat { device: path, wanted: got, offered });
        };
        let format = FrameFormat { width: applied.width, height: applied.height, fourcc: got, transfer };
        let mut cam = Self {
            device: path,
            dev,
            format,
            stride: applied.stride as usize,
            color: s.color,
            exposure_us: s.exposure_us,
            gain: s.gain,
            discard_after_change: s.discard_after_change,
            owed: 0,
            timeout: s.frame_timeout,
            card,
            driver,
        };
        cam.manual_mode()?;
        cam.set_exposure(s.exposure_us)?;
        cam.set_gain(s.gain)?;
        Ok(cam)
    }

    /// Turns auto exposure, auto gain and auto white balance off where the device has them.
    fn manual_mode(&mut self) -> Result<(), CameraError> {
        let ids: Vec<u32> = self.dev.controls().map_err(|e| io_err(&self.device, e))?.iter().map(|d| d.id).collect();
        if ids.contains(&CID_EXPOSURE_AUTO) {
            self.set(CID_EXPOSURE_AUTO, "exposure_auto", ControlValue::Integer(1))?;
        }
        if ids.contains(&CID_AUTOGAIN) {
            self.set(CID_AUTOGAIN, "autogain", ControlValue::Boolean(false))?;
        }
        if ids.contains(&CID_AUTO_WHITE_BALANCE) {
            self.set(CID_AUTO_WHITE_BALANCE, "white_balance_automatic", ControlValue::Boolean(false))?;
        }
        Ok(())
    }

    fn set(&mut self, id: u32, name: &str, value: ControlValue) -> Result<(), CameraError> {
        let device = self.device.clone();
        self.dev.set_control(id, value).map_err(|e| {
            let detail = if e.kind() == io::ErrorKind::PermissionDenied { "rejected (inactive: is auto mode still on?)" } else { "rejected" };
            CameraError::Control { device, control: name.into(), detail: detail.into(), source: Some(e) }
        })
    }

    fn control_range(&self, id: u32) -> Option<(i64, i64)> {
        let d = self.dev.controls().ok()?.into_iter().find(|d| d.id == id)?;
        Some((d.minimum, d.maximum))
    }

    /// The next raw frame: bytes and sequence number.
    fn next_raw(&mut self) -> Result<(Vec<u8>, u32), CameraError> {
        match self.dev.next_frame(self.timeout) {
            Ok(f) => Ok(f),
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock) => Err(CameraError::Timeout { device: self.device.clone(), after: self.timeout }),
            Err(e) => Err(io_err(&self.device, e)),
        }
    }
}

/// Opens a device for listing only (no format or control is changed).
///
/// # Errors
/// The device cannot be opened.
#[cfg(feature = "v4l2")]
pub fn open_device(path: &Path) -> io::Result<Box<dyn V4lDevice>> {
    Ok(Box::new(real::RealDevice::open(path)?))
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
        self.set(id, name, ControlValue::Integer(units))?;
        let applied = self.dev.control(id).unwrap_or(units);
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
        self.set(CID_GAIN, "gain", ControlValue::Integer(v))?;
        self.gain = self.dev.control(CID_GAIN).unwrap_or(v) as f64;
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
        let mut repeats = Repeats::default();
        let mut first: Option<(SystemTime, u32)> = None;
        for _ in 0..frames {
            let (bytes, seq) = self.next_raw()?;
            if first.is_none() {
                first = Some((SystemTime::now(), seq));
            }
            let img = decode::decode(f.fourcc, f.width as usize, f.height as usize, self.stride, &bytes, self.color)
                .map_err(|source| CameraError::Decode { device: self.device.clone(), source })?;
            avg.add(&img).map_err(|source| CameraError::FrameMismatch { device: self.device.clone(), source })?;
            repeats.add(&img.planes);
        }
        let (time, seq) = first.unwrap_or((SystemTime::now(), 0));
        let image = avg.finish().ok_or_else(|| CameraError::InvalidArgument { device: self.device.clone(), what: "no frame averaged".into() })?;
        Ok(Frame {
            meta: FrameMeta::new(time, self.exposure_us, self.gain, (frames, discarded), image.transfer, f.fourcc, Some(seq)),
            image,
            temporal_variance: repeats.variance(),
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

/// [`V4lDevice`] on a real device through `v4l` 0.14.
#[cfg(feature = "v4l2")]
mod real {
    use std::io;
    use std::path::Path;
    use std::time::Duration;

    use ::v4l::buffer::Type;
    use ::v4l::control::{Control, Value};
    use ::v4l::io::mmap::Stream as MmapStream;
    use ::v4l::io::traits::CaptureStream;
    use ::v4l::video::Capture;
    use ::v4l::{Device, FourCC};

    use super::{ControlDesc, ControlRange, ControlValue, DeviceFormat, V4lDevice, BUFFERS};
    use crate::rig::camera::FourCc;

    pub struct RealDevice {
        dev: Device,
        stream: Option<MmapStream<'static>>,
    }

    /// v4l2-ctl's spelling of a driver's control name: lower case, runs of other characters
    /// as one `_` ("Exposure Time, Absolute" → `exposure_time_absolute`).
    fn v4l2_ctl_name(name: &str) -> String {
        let mut out = String::new();
        for ch in name.chars() {
            if ch.is_ascii_alphanumeric() {
                out.push(ch.to_ascii_lowercase());
            } else if !out.ends_with('_') && !out.is_empty() {
                out.push('_');
            }
        }
        out.trim_end_matches('_').to_string()
    }

    impl RealDevice {
        pub fn open(path: &Path) -> io::Result<Self> {
            Ok(Self { dev: Device::with_path(path)?, stream: None })
        }
    }

    impl V4lDevice for RealDevice {
        fn identify(&self) -> io::Result<(String, String)> {
            let caps = self.dev.query_caps()?;
            Ok((caps.card, caps.driver))
        }

        fn formats(&self) -> io::Result<Vec<FourCc>> {
            Ok(self.dev.enum_formats()?.into_iter().map(|d| FourCc(d.fourcc.repr)).collect())
        }

        fn set_format(&mut self, want: DeviceFormat) -> io::Result<DeviceFormat> {
            let mut fmt = self.dev.format()?;
            fmt.width = want.width;
            fmt.height = want.height;
            fmt.fourcc = FourCC::new(&want.fourcc.0);
            let a = self.dev.set_format(&fmt)?;
            Ok(DeviceFormat { width: a.width, height: a.height, fourcc: FourCc(a.fourcc.repr), stride: a.stride })
        }

        fn controls(&self) -> io::Result<Vec<ControlRange>> {
            Ok(self.dev.query_controls()?.into_iter().map(|d| ControlRange { id: d.id, minimum: d.minimum, maximum: d.maximum }).collect())
        }

        fn set_control(&mut self, id: u32, value: ControlValue) -> io::Result<()> {
            let value = match value {
                ControlValue::Integer(v) => Value::Integer(v),
                ControlValue::Boolean(b) => Value::Boolean(b),
            };
            self.dev.set_control(Control { id, value })
        }

        fn control(&self, id: u32) -> io::Result<i64> {
            match self.dev.control(id)?.value {
                Value::Integer(v) => Ok(v),
                Value::Boolean(b) => Ok(i64::from(b)),
                _ => Err(io::Error::new(io::ErrorKind::InvalidData, format!("control {id:#x} is not an integer"))),
            }
        }

        /// Discrete sizes as listed; a stepwise range as its smallest and largest size (what
        /// `v4l2-ctl --list-formats-ext` prints as "Stepwise MINxMIN - MAXxMAX").
        fn frame_sizes(&self, fourcc: FourCc) -> io::Result<Vec<(u32, u32)>> {
            use ::v4l::framesize::FrameSizeEnum;
            let mut sizes = Vec::new();
            for f in self.dev.enum_framesizes(FourCC::new(&fourcc.0))? {
                match f.size {
                    FrameSizeEnum::Discrete(d) => sizes.push((d.width, d.height)),
                    FrameSizeEnum::Stepwise(s) => {
                        sizes.push((s.min_width, s.min_height));
                        sizes.push((s.max_width, s.max_height));
                    }
                }
            }
            Ok(sizes)
        }

        /// The driver's own names, types, steps and defaults (`VIDIOC_QUERY_EXT_CTRL`) and the
        /// current value of every integer, boolean and menu control; control classes and
        /// buttons are skipped, as `v4l2-ctl --list-ctrls` lists them only as headings.
        fn describe_controls(&self) -> io::Result<Vec<ControlDesc>> {
            use ::v4l::control::Type as T;
            let mut out = Vec::new();
            for d in self.dev.query_controls()? {
                let kind = match d.typ {
                    T::Integer | T::Integer64 => "int",
                    T::Boolean => "bool",
                    T::Menu | T::IntegerMenu => "menu",
                    _ => continue,
                };
                let name = v4l2_ctl_name(&d.name);
                let value = self.control(d.id).ok();
                out.push(ControlDesc { id: d.id, name, kind, minimum: d.minimum, maximum: d.maximum, step: d.step as i64, default: Some(d.default), value });
            }
            Ok(out)
        }

        fn next_frame(&mut self, timeout: Duration) -> io::Result<(Vec<u8>, u32)> {
            if self.stream.is_none() {
                let mut s = MmapStream::with_buffers(&self.dev, Type::VideoCapture, BUFFERS)?;
                s.set_timeout(timeout);
                self.stream = Some(s);
            }
            let Some(stream) = self.stream.as_mut() else { return Err(io::Error::other("stream not available")) };
            let (buf, meta) = stream.next()?;
            let used = (meta.bytesused as usize).min(buf.len());
            let used = if used == 0 { buf.len() } else { used };
            Ok((buf[..used].to_vec(), meta.sequence))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeMap, VecDeque};
    use std::sync::{Arc, Mutex};

    /// A fake UVC-like camera: it logs every call; exposure can only be written once auto
    /// exposure is manual (`EACCES` before, like UVC drivers); the driver snaps the frame size
    /// to a size it supports; and frames leave the sensor `lag` frames after the exposure they
    /// were taken with (the pipeline and queued buffers), so the first frames after a change
    /// still carry the old exposure. Each GREY pixel is the exposure in 100 µs units (≤ 255).
    struct FakeUvc {
        log: Arc<Mutex<Vec<String>>>,
        offered: Vec<FourCc>,
        /// (fourcc asked, fourcc applied): a driver substituting another format.
        substitute: Option<(FourCc, FourCc)>,
        sizes: Vec<(u32, u32)>,
        controls: Vec<ControlRange>,
        values: BTreeMap<u32, i64>,
        format: DeviceFormat,
        lag: usize,
        pipeline: VecDeque<i64>,
        sequence: u32,
        /// `next_frame` fails with this errno-like kind.
        fail_frames: Option<io::ErrorKind>,
        busy: bool,
    }

    fn uvc() -> (FakeUvc, Arc<Mutex<Vec<String>>>) {
        let log = Arc::new(Mutex::new(Vec::new()));
        let controls = vec![
            ControlRange { id: CID_EXPOSURE_AUTO, minimum: 0, maximum: 3 },
            ControlRange { id: CID_EXPOSURE_ABSOLUTE, minimum: 1, maximum: 5000 },
            ControlRange { id: CID_GAIN, minimum: 0, maximum: 255 },
            ControlRange { id: CID_AUTO_WHITE_BALANCE, minimum: 0, maximum: 1 },
        ];
        let mut values = BTreeMap::new();
        values.insert(CID_EXPOSURE_AUTO, 3); // aperture priority, the UVC default
        values.insert(CID_EXPOSURE_ABSOLUTE, 156);
        values.insert(CID_GAIN, 64);
        values.insert(CID_AUTO_WHITE_BALANCE, 1);
        let f = FakeUvc {
            log: log.clone(),
            offered: vec![FourCc(*b"YUYV"), FourCc(*b"MJPG"), FourCc(*b"GREY")],
            substitute: None,
            sizes: vec![(640, 480), (320, 240), (8, 4)],
            controls,
            values,
            format: DeviceFormat { width: 640, height: 480, fourcc: FourCc(*b"YUYV"), stride: 1280 },
            lag: 3,
            pipeline: VecDeque::new(),
            sequence: 0,
            fail_frames: None,
            busy: false,
        };
        (f, log)
    }

    impl FakeUvc {
        fn note(&self, s: String) {
            self.log.lock().unwrap().push(s);
        }
    }

    impl V4lDevice for FakeUvc {
        fn identify(&self) -> io::Result<(String, String)> {
            Ok(("Fake UVC".into(), "uvcvideo".into()))
        }
        fn formats(&self) -> io::Result<Vec<FourCc>> {
            Ok(self.offered.clone())
        }
        fn set_format(&mut self, want: DeviceFormat) -> io::Result<DeviceFormat> {
            if self.busy {
                return Err(io::Error::from_raw_os_error(16));
            }
            self.note(format!("set_format {} {}x{}", want.fourcc, want.width, want.height));
            // the largest supported size not above the request (or the smallest)
            let (w, h) = self.sizes.iter().copied().filter(|&(w, h)| w <= want.width && h <= want.height).max().unwrap_or((8, 4));
            let fourcc = match self.substitute {
                Some((asked, got)) if asked == want.fourcc => got,
                _ => want.fourcc,
            };
            let bpp = if fourcc == FourCc(*b"GREY") { 1 } else { 2 };
            self.format = DeviceFormat { width: w, height: h, fourcc, stride: w * bpp + 4 }; // padded lines
            Ok(self.format)
        }
        fn controls(&self) -> io::Result<Vec<ControlRange>> {
            Ok(self.controls.clone())
        }
        fn set_control(&mut self, id: u32, value: ControlValue) -> io::Result<()> {
            self.note(format!("set {id:#x} {value:?}"));
            let v = match value {
                ControlValue::Integer(v) => v,
                ControlValue::Boolean(b) => i64::from(b),
            };
            if id == CID_EXPOSURE_ABSOLUTE && self.values.get(&CID_EXPOSURE_AUTO) != Some(&1) {
                return Err(io::Error::from_raw_os_error(13)); // EACCES: inactive
            }
            let r = self.controls.iter().find(|c| c.id == id).ok_or_else(|| io::Error::from_raw_os_error(22))?;
            // drivers clamp (and exposure snaps to even units on this one)
            let v = v.clamp(r.minimum, r.maximum);
            let v = if id == CID_EXPOSURE_ABSOLUTE { v - v % 2 } else { v };
            self.values.insert(id, v);
            Ok(())
        }
        fn control(&self, id: u32) -> io::Result<i64> {
            self.values.get(&id).copied().ok_or_else(|| io::Error::from_raw_os_error(22))
        }
        fn frame_sizes(&self, _fourcc: FourCc) -> io::Result<Vec<(u32, u32)>> {
            Ok(self.sizes.clone())
        }
        fn next_frame(&mut self, _timeout: Duration) -> io::Result<(Vec<u8>, u32)> {
            if let Some(k) = self.fail_frames {
                return Err(io::Error::new(k, "fake"));
            }
            let now = self.values.get(&CID_EXPOSURE_ABSOLUTE).copied().unwrap_or(0);
            if self.pipeline.is_empty() {
                for _ in 0..self.lag {
                    self.pipeline.push_back(now);
                }
            }
            self.pipeline.push_back(now);
            let exposure = self.pipeline.pop_front().unwrap_or(now);
            let f = self.format;
            let bpp = if f.fourcc == FourCc(*b"GREY") { 1 } else { 2 };
            let mut bytes = vec![0u8; (f.stride * f.height) as usize];
            for y in 0..f.height as usize {
                for x in 0..(f.width * bpp) as usize {
                    // YUYV: Y bytes carry the value, chroma bytes neutral
                    bytes[y * f.stride as usize + x] = if bpp == 2 && x % 2 == 1 { 128 } else { exposure.min(255) as u8 };
                }
            }
            self.sequence += 1;
            self.note(format!("frame {}", self.sequence));
            Ok((bytes, self.sequence))
        }
    }

    fn settings(fourcc: &[u8; 4]) -> V4lSettings {
        V4lSettings {
            device: "/dev/video-fake".into(),
            fourcc: FourCc(*fourcc),
            width: 10,
            height: 5,
            exposure_us: 10_000,
            gain: 0.0,
            discard_after_change: 3,
            color: ColorMode::Luma,
            frame_timeout: Duration::from_secs(1),
        }
    }

    fn sets(log: &Arc<Mutex<Vec<String>>>) -> Vec<String> {
        log.lock().unwrap().iter().filter(|l| l.starts_with("set ")).cloned().collect()
    }

    #[test]
    fn auto_modes_go_off_before_exposure_is_written_one_control_per_call() {
        let (dev, log) = uvc();
        let cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        assert_eq!(
            sets(&log),
            vec![
                format!("set {CID_EXPOSURE_AUTO:#x} Integer(1)"),
                format!("set {CID_AUTO_WHITE_BALANCE:#x} Boolean(false)"),
                format!("set {CID_EXPOSURE_ABSOLUTE:#x} Integer(100)"),
                format!("set {CID_GAIN:#x} Integer(0)"),
            ]
        );
        // the format is set before any control
        assert!(log.lock().unwrap()[0].starts_with("set_format 'GREY'"));
        assert_eq!(cam.exposure_us, 10_000);
    }

    #[test]
    fn the_negotiated_format_is_what_the_driver_applied() {
        let (dev, _) = uvc();
        let cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        // asked 10×5, the driver snapped to 8×4 with padded lines
        assert_eq!(cam.format(), FrameFormat { width: 8, height: 4, fourcc: FourCc(*b"GREY"), transfer: crate::image::Transfer::Linear });
        assert!(cam.describe().contains("'GREY' 8x4 linear") && cam.describe().contains("/dev/video-fake"), "{}", cam.describe());
        // a format the device does not offer: the error lists what it does
        let (dev, _) = uvc();
        let e = V4lCamera::with_device(Box::new(dev), &settings(b"Y16 ")).err().unwrap().to_string();
        assert!(e.contains("Y16") && e.contains("'YUYV', 'MJPG', 'GREY'") && e.contains("/dev/video-fake"), "{e}");
        // the driver substitutes a decodable format: recorded as applied (sRGB for YUYV)
        let (mut dev, _) = uvc();
        dev.substitute = Some((FourCc(*b"GREY"), FourCc(*b"YUYV")));
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        assert_eq!((cam.format().fourcc, cam.format().transfer), (FourCc(*b"YUYV"), crate::image::Transfer::Srgb));
        let f = cam.capture(1).unwrap();
        assert_eq!((f.image.width(), f.image.height(), f.meta.fourcc), (8, 4, FourCc(*b"YUYV")));
        // ... or one lensrig cannot decode: refused
        let (mut dev, _) = uvc();
        dev.offered.push(FourCc(*b"H264"));
        dev.substitute = Some((FourCc(*b"GREY"), FourCc(*b"H264")));
        let e = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).err().unwrap().to_string();
        assert!(e.contains("'H264' is not supported"), "{e}");
    }

    #[test]
    fn frames_after_a_control_or_scene_change_are_dropped() {
        let (dev, log) = uvc();
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        let level = |f: &Frame| (f.image.planes[0].data[0] * 255.0).round() as i64;
        // the exposure set at open is owed 3 frames: the first recorded frame already has it
        let f = cam.capture(1).unwrap();
        assert_eq!((level(&f), f.meta.frames_discarded, f.meta.exposure_us), (100, 3, 10_000));
        // the applied (snapped) value is recorded, not the one asked
        assert_eq!(cam.set_exposure(15_100).unwrap(), 15_000);
        let f = cam.capture(2).unwrap();
        assert_eq!((level(&f), f.meta.frames_discarded, f.meta.exposure_us, f.meta.frames_averaged), (150, 3, 15_000, 2));
        // no change since: nothing dropped
        let f = cam.capture(1).unwrap();
        assert_eq!(f.meta.frames_discarded, 0);
        // a move: every queued buffer is stale
        cam.invalidate();
        assert_eq!(cam.capture(1).unwrap().meta.frames_discarded, BUFFERS as usize);
        // sequence numbers advance by what was read, dropped frames included
        let frames = log.lock().unwrap().iter().filter(|l| l.starts_with("frame ")).count();
        assert_eq!(frames, (3 + 1) + (3 + 2) + 1 + (4 + 1));
    }

    #[test]
    fn without_dropping_the_first_frames_would_carry_the_old_exposure() {
        // the oracle behind the test above: the fake really lags
        let (dev, _) = uvc();
        let mut s = settings(b"GREY");
        s.discard_after_change = 0;
        let mut cam = V4lCamera::with_device(Box::new(dev), &s).unwrap();
        cam.capture(5).unwrap();
        cam.set_exposure(20_000).unwrap();
        let f = cam.capture(1).unwrap();
        assert_eq!((f.image.planes[0].data[0] * 255.0).round() as i64, 100);
    }

    #[test]
    fn control_errors_name_the_control_and_range() {
        let (dev, _) = uvc();
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        let e = cam.set_exposure(600_000).unwrap_err().to_string();
        assert!(e.contains("exposure_time_absolute") && e.contains("[100 µs, 500000 µs]"), "{e}");
        let e = cam.set_gain(300.0).unwrap_err().to_string();
        assert!(e.contains("gain") && e.contains("[0, 255]"), "{e}");
        // a camera without the camera-class exposure (PS3 Eye) uses the user-class one
        let (mut dev, log) = uvc();
        dev.controls.retain(|c| c.id != CID_EXPOSURE_ABSOLUTE && c.id != CID_EXPOSURE_AUTO && c.id != CID_GAIN);
        dev.controls.push(ControlRange { id: CID_EXPOSURE, minimum: 0, maximum: 255 });
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        assert!(sets(&log).contains(&format!("set {CID_EXPOSURE:#x} Integer(100)")), "{:?}", sets(&log));
        // no gain control: gain 0 is fine, anything else is refused
        assert_eq!(cam.set_gain(0.0).unwrap(), 0.0);
        assert!(cam.set_gain(2.0).unwrap_err().to_string().contains("no gain control"));
        // the exposure auto control stuck in aperture priority: EACCES explained
        let (mut dev, _) = uvc();
        dev.controls.retain(|c| c.id != CID_EXPOSURE_AUTO);
        let e = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).err().unwrap().to_string();
        assert!(e.contains("exposure_time_absolute") && e.contains("inactive"), "{e}");
    }

    #[test]
    fn listings_use_v4l2_ctl_vocabulary() {
        let (mut dev, log) = uvc();
        dev.offered.push(FourCc(*b"H264"));
        let f = list_formats_ext(&dev).unwrap();
        assert!(f.starts_with("ioctl: VIDIOC_ENUM_FMT\n\tType: Video Capture\n"), "{f}");
        assert!(f.contains("\t[0]: 'YUYV' (YUYV 4:2:2)\n\t\tSize: Discrete 640x480\n\t\tSize: Discrete 320x240\n"), "{f}");
        assert!(f.contains("\t[1]: 'MJPG' (Motion-JPEG, compressed)\n"), "{f}");
        assert!(f.contains("\t[3]: 'H264'  [lensrig cannot decode]\n"), "{f}");
        assert!(f.contains("\t[2]: 'GREY' (8-bit Greyscale)\n"), "{f}");
        let c = list_ctrls(&dev).unwrap();
        let user = c.find("User Controls").unwrap();
        let camera = c.find("Camera Controls").unwrap();
        assert!(user < camera, "{c}");
        assert!(c.contains("         exposure_time_absolute 0x009a0902 (int)    : min=1 max=5000 step=1 value=156\n"), "{c}");
        assert!(c.contains("                  auto_exposure 0x009a0901 (menu)   : min=0 max=3 value=3\n"), "{c}");
        assert!(c.contains("        white_balance_automatic 0x0098090c (bool)   : value=1\n"), "{c}");
        assert!(c.contains("                           gain 0x00980913 (int)    : min=0 max=255 step=1 value=64\n"), "{c}");
        // listing only reads: nothing was set, no format changed, no frame taken
        assert!(log.lock().unwrap().is_empty());
    }

    #[test]
    fn timeouts_and_busy_devices_are_typed_errors() {
        let (mut dev, _) = uvc();
        dev.fail_frames = Some(io::ErrorKind::TimedOut);
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        let e = cam.capture(1).unwrap_err();
        assert!(matches!(e, CameraError::Timeout { .. }), "{e}");
        assert!(e.to_string().contains("/dev/video-fake") && e.to_string().contains("no frame within 1s"), "{e}");
        let (mut dev, _) = uvc();
        dev.busy = true;
        let e = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).err().unwrap().to_string();
        assert!(e.contains("busy"), "{e}");
        let (dev, _) = uvc();
        let mut cam = V4lCamera::with_device(Box::new(dev), &settings(b"GREY")).unwrap();
        assert!(matches!(cam.capture(0), Err(CameraError::InvalidArgument { .. })));
    }

    /// Opt-in: `LENSRIG_V4L2_DEVICE=/dev/video0 cargo test --features v4l2 v4l2_device`.
    #[cfg(feature = "v4l2")]
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

    #[cfg(feature = "v4l2")]
    #[test]
    fn missing_device_names_the_path() {
        let mut s = settings(b"YUYV");
        s.device = "/dev/video-lensrig-missing".into();
        let e = V4lCamera::open(&s).err().unwrap().to_string();
        assert!(e.contains("/dev/video-lensrig-missing") && e.contains("no such device"), "{e}");
    }
}
