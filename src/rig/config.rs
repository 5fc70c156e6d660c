//! The rig configuration: one TOML file naming the camera, the controller, the two axes, the
//! capture plan, the target and (for the mock rig) the simulated lens.
//!
//! [`load`] parses with `deny_unknown_fields` everywhere, then [`RigConfig::validate`]s. Every
//! error names the file, the line and column, and the dotted key (`camera.width`), so a typo is
//! found without guessing. See `rig-configs/mock.toml` and `rig-configs/example-real.toml`.
//!
//! # Conventions
//! - Axis positions are millimetres in **machine** coordinates (grbl `MPos`); with grbl's
//!   default homing direction they are ≤ 0.
//! - Relative paths (`target.path`) are relative to the config file's directory;
//!   [`load`] resolves them.
//! - `[lens]` is a free-form table read by the mock camera; this module only checks it is a
//!   table.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::controller::{Axis, AxisLimit, ControllerOptions, RecoveryPolicy, Timeouts};

/// A whole rig.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigConfig {
    pub camera: CameraConfig,
    pub controller: ControllerConfig,
    pub axes: AxesConfig,
    #[serde(default)]
    pub plan: PlanConfig,
    pub target: Option<TargetConfig>,
    /// How a capture pauses and retries instead of failing.
    #[serde(default)]
    pub retry: RetryConfig,
    /// Free-form parameters of the simulated lens (mock rigs).
    pub lens: Option<toml::Table>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraKind {
    Mock,
    V4l2,
}

/// `[camera]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    pub kind: CameraKind,
    /// Device path (`kind = "v4l2"`).
    pub device: Option<PathBuf>,
    /// Preferred V4L2 FourCC, 1–4 ASCII characters, space padded (`"Y16"` = `"Y16 "`).
    #[serde(default = "default_pixel_format")]
    pub pixel_format: String,
    pub width: u32,
    pub height: u32,
    pub exposure_us: u32,
    #[serde(default)]
    pub gain: f64,
    /// Frames averaged into one capture.
    #[serde(default = "one")]
    pub frames_to_average: u32,
    /// Frames dropped after any exposure, gain or axis change.
    #[serde(default = "three")]
    pub discard_after_change: u32,
    /// Longest wait for one frame (ms) before the capture counts as a camera timeout; allow
    /// the longest exposure plus the device's latency.
    #[serde(default = "d_frame_timeout")]
    pub frame_timeout_ms: u64,
}

impl CameraConfig {
    /// The pixel format as a 4-byte FourCC (space padded).
    pub fn fourcc(&self) -> [u8; 4] {
        let mut f = [b' '; 4];
        for (d, s) in f.iter_mut().zip(self.pixel_format.bytes()) {
            *d = s;
        }
        f
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ControllerKind {
    Sim,
    Serial,
}

/// `[controller]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerConfig {
    pub kind: ControllerKind,
    /// Serial port (`kind = "serial"`), preferably a `/dev/serial/by-id/…` path.
    pub port: Option<String>,
    #[serde(default = "default_baud")]
    pub baud: u32,
    #[serde(default)]
    pub home_on_start: bool,
    #[serde(default)]
    pub recovery: RecoveryPolicy,
    #[serde(default)]
    pub timeouts: TimeoutsConfig,
}

/// `[controller.timeouts]`, all in milliseconds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimeoutsConfig {
    #[serde(default = "d_banner")]
    pub banner_ms: u64,
    #[serde(default = "d_response")]
    pub response_ms: u64,
    #[serde(default = "d_motion")]
    pub motion_ms: u64,
    #[serde(default = "d_homing")]
    pub homing_ms: u64,
}

impl Default for TimeoutsConfig {
    fn default() -> Self {
        Self { banner_ms: d_banner(), response_ms: d_response(), motion_ms: d_motion(), homing_ms: d_homing() }
    }
}

/// `[axes]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxesConfig {
    pub aperture: ApertureAxis,
    pub stage: StageAxis,
}

/// `[axes.aperture]`: the axis that turns the iris (or moves a pinhole slide).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApertureAxis {
    pub axis: Axis,
    /// Position of the wide-open aperture.
    pub open: f64,
    /// Position of the pinhole (stopped-down) aperture.
    pub pinhole: f64,
    pub min: f64,
    pub max: f64,
}

/// `[axes.stage]`: the axis that moves the target or the lens (focus/field positions).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageAxis {
    pub axis: Axis,
    /// Positions to capture at.
    pub positions: Vec<f64>,
    pub min: f64,
    pub max: f64,
    /// Focus distance (metres) at each position, when the stage refocuses: `calibrate` then
    /// collects the calibrations as a profile set (`profiles/index.toml`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focus_distance_m: Option<Vec<f64>>,
}

/// `[plan]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanConfig {
    /// Wait after each move before capturing.
    #[serde(default = "d_settle")]
    pub settle_ms: u64,
    /// Dark frames (lens capped) per exposure setting.
    #[serde(default)]
    pub dark_frames: u32,
    /// Adjust exposure so the brightest pixel lands below clipping.
    #[serde(default)]
    pub auto_bracket: bool,
    /// Pinhole exposure = open exposure × this (> 0).
    #[serde(default = "d_scale")]
    pub pinhole_exposure_scale: f64,
    /// The optional flat-field step (`[plan.flat]`), taken after the pairs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flat: Option<FlatStep>,
}

impl Default for PlanConfig {
    fn default() -> Self {
        Self { settle_ms: d_settle(), dark_frames: 0, auto_bracket: false, pinhole_exposure_scale: d_scale(), flat: None }
    }
}

/// `[plan.flat]`: a flat-field capture for the lens's vignetting (lensfun's `pa` model):
/// the stage moves to `stage_mm`, where a diffuser or a uniform white card fills the view,
/// the aperture opens, and one frame is captured like an open frame (same averaging,
/// auto-bracketing, drift check, dark frame). The session keeps it in `flat/`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlatStep {
    /// Stage position (mm, machine coordinates) of the uniform target; at least
    /// [`FLAT_CLEARANCE_MM`] from every pair position.
    pub stage_mm: f64,
}

/// Least distance (mm) between the flat step's stage position and a pair position.
pub const FLAT_CLEARANCE_MM: f64 = 0.5;

/// `[retry]`: what a capture does when a pair meets a fault it can get past (a camera
/// timeout, a serial disconnect, a grbl alarm, an unreadable controller, illumination
/// drift): log a `pause`, wait `pause_ms`, recover (reconnect, reset, re-home or unlock as
/// the fault needs) and capture the pair again from its first move, at most `max_tries`
/// times in all.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RetryConfig {
    /// Tries per pair, the first included (1 = fail at the first fault).
    #[serde(default = "d_tries")]
    pub max_tries: u32,
    /// Wait before each retry and between reconnection attempts (ms).
    #[serde(default = "d_pause")]
    pub pause_ms: u64,
    /// Largest relative change of a frame's light (mean linear level per µs of exposure)
    /// against the session's first frame of the same role (open or pinhole) before the
    /// pair is taken again; 0 turns the check off.
    #[serde(default = "d_drift")]
    pub drift_tolerance: f64,
}

impl Default for RetryConfig {
    fn default() -> Self {
        Self { max_tries: d_tries(), pause_ms: d_pause(), drift_tolerance: d_drift() }
    }
}

/// `[target]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetConfig {
    /// The target description file (resolved against the config's directory by [`load`]).
    pub path: PathBuf,
    /// Where the target sits on the sensor, roughly (`[target.layout]`): what registering the
    /// pinhole capture to the target file starts from, so `calibrate` can measure distortion.
    #[serde(default)]
    pub layout: Option<TargetLayout>,
}

/// `[target.layout]`: the nominal layout of the target's noise field on the sensor. Units are
/// the target's noise cells (`u` along its width, `v` along its height, cell `(0, 0)` the
/// noise field's top-left corner) and sensor pixels (`x` right, `y` down, pixel centres at
/// integers). At stage position `s` mm, sensor pixel `(x, y)` sees about cell
/// `u = origin[0] − cells_per_mm·s + x / pixels_per_cell`, `v = origin[1] + y / pixels_per_cell`
/// (lens distortion, what is measured, moves it from there).
/// The registration locks within ±8 % of `pixels_per_cell` and a few cells of `origin`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetLayout {
    /// Sensor pixels per target noise cell (magnification), at the stage positions.
    pub pixels_per_cell: f64,
    /// Target cell `(u, v)` at sensor pixel `(0, 0)` with the stage at 0 mm.
    pub origin: [f64; 2],
    /// Target cells the view moves along `u` per mm of stage travel (0 when the stage
    /// refocuses instead of sliding the target).
    #[serde(default)]
    pub cells_per_mm: f64,
}

impl TargetLayout {
    /// The target cell `(u0, v0)` at sensor pixel `(0, 0)` with the stage at `stage_mm`.
    pub fn origin_at(&self, stage_mm: f64) -> (f64, f64) {
        (self.origin[0] - self.cells_per_mm * stage_mm, self.origin[1])
    }
}

fn default_pixel_format() -> String {
    "YUYV".into()
}
fn one() -> u32 {
    1
}
fn three() -> u32 {
    3
}
fn default_baud() -> u32 {
    115_200
}
fn d_banner() -> u64 {
    3000
}
fn d_response() -> u64 {
    2000
}
fn d_motion() -> u64 {
    120_000
}
fn d_homing() -> u64 {
    120_000
}
fn d_frame_timeout() -> u64 {
    5000
}
fn d_tries() -> u32 {
    3
}
fn d_pause() -> u64 {
    2000
}
fn d_drift() -> f64 {
    0.1
}
fn d_settle() -> u64 {
    200
}
fn d_scale() -> f64 {
    1.0
}

/// A config that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read rig config {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// TOML syntax, an unknown key, a wrong type, a missing key.
    #[error("{path}:{line}:{column}: {key}: {message}")]
    Parse { path: PathBuf, line: usize, column: usize, key: String, message: String },
    /// Parsed, but inconsistent (a position outside its range, equal axis letters, …).
    /// `line` is 0 when the key is not written in the file.
    #[error("{path}:{line}: {key}: {message}")]
    Invalid { path: PathBuf, line: usize, key: String, message: String },
}

/// Reads, parses and validates a rig config.
///
/// # Errors
/// [`ConfigError::Read`] when the file cannot be read, [`ConfigError::Parse`] for TOML and
/// schema errors, [`ConfigError::Invalid`] for inconsistent values; all name the file, the
/// line and the key.
pub fn load(path: &Path) -> Result<RigConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_path_buf(), source })?;
    let mut cfg = parse(&text, path)?;
    if let Some(t) = cfg.target.as_mut() {
        if t.path.is_relative() {
            if let Some(dir) = path.parent() {
                t.path = dir.join(&t.path);
            }
        }
    }
    Ok(cfg)
}

/// Parses and validates config text; `path` is only used in messages.
///
/// # Errors
/// As [`load`], without `Read`.
pub fn parse(text: &str, path: &Path) -> Result<RigConfig, ConfigError> {
    let cfg: RigConfig = toml::from_str(text).map_err(|e| {
        let (line, column, key) = match e.span() {
            Some(span) => {
                let (line, column) = line_col(text, span.start);
                (line, column, key_at(text, line, span.start))
            }
            None => (0, 0, String::new()),
        };
        // toml's message repeats the source excerpt; keep its first line.
        let message = e.message().lines().next().unwrap_or("").to_string();
        let key = if key.is_empty() { missing_field(&message).unwrap_or_default() } else { key };
        ConfigError::Parse { path: path.to_path_buf(), line, column, key, message }
    })?;
    cfg.validate().map_err(|(key, message)| ConfigError::Invalid { path: path.to_path_buf(), line: find_key_line(text, &key), key, message })?;
    Ok(cfg)
}

impl RigConfig {
    /// Checks values that parse but cannot work. Returns the dotted key and a message.
    ///
    /// # Errors
    /// The first inconsistency found.
    pub fn validate(&self) -> Result<(), (String, String)> {
        self.validate_camera()?;
        self.validate_controller()?;
        self.validate_axes()?;
        self.validate_plan()
    }

    /// `[camera]`: device, FourCC, size, exposure, gain, averaging, timeout.
    fn validate_camera(&self) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((k.to_string(), m));
        let c = &self.camera;
        if c.kind == CameraKind::V4l2 && c.device.is_none() {
            return bad("camera.device", "a v4l2 camera needs `device = \"/dev/videoN\"`".into());
        }
        if c.pixel_format.is_empty() || c.pixel_format.len() > 4 || !c.pixel_format.bytes().all(|b| b.is_ascii_graphic() || b == b' ') {
            return bad("camera.pixel_format", format!("{:?} is not a FourCC (1–4 ASCII characters)", c.pixel_format));
        }
        if c.width == 0 || c.height == 0 {
            return bad(if c.width == 0 { "camera.width" } else { "camera.height" }, "must be positive".into());
        }
        if c.exposure_us == 0 {
            return bad("camera.exposure_us", "must be positive".into());
        }
        if !(c.gain.is_finite() && c.gain >= 0.0) {
            return bad("camera.gain", format!("{} must be ≥ 0", c.gain));
        }
        if c.frames_to_average == 0 {
            return bad("camera.frames_to_average", "must be at least 1".into());
        }
        if c.frame_timeout_ms == 0 {
            return bad("camera.frame_timeout_ms", "must be positive".into());
        }
        Ok(())
    }

    /// `[retry]` and `[controller]`: tries, drift tolerance, port, baud, timeouts.
    fn validate_controller(&self) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((k.to_string(), m));
        let r = &self.retry;
        if r.max_tries == 0 {
            return bad("retry.max_tries", "must be at least 1 (1 = no retry)".into());
        }
        if !(r.drift_tolerance.is_finite() && r.drift_tolerance >= 0.0) {
            return bad("retry.drift_tolerance", format!("{} must be ≥ 0 (0 = off)", r.drift_tolerance));
        }
        let k = &self.controller;
        if k.kind == ControllerKind::Serial && k.port.as_deref().map_or(true, str::is_empty) {
            return bad("controller.port", "a serial controller needs `port = \"/dev/ttyUSB0\"` (or a /dev/serial/by-id path)".into());
        }
        if k.baud == 0 {
            return bad("controller.baud", "must be positive (grbl 1.1: 115200)".into());
        }
        let t = &k.timeouts;
        for (name, v) in [("banner_ms", t.banner_ms), ("response_ms", t.response_ms), ("motion_ms", t.motion_ms), ("homing_ms", t.homing_ms)] {
            if v == 0 {
                return bad(&format!("controller.timeouts.{name}"), "must be positive".into());
            }
        }
        Ok(())
    }

    /// `[axes]`: distinct axes, non-empty ranges, apertures and stage positions inside them.
    fn validate_axes(&self) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((k.to_string(), m));
        let (a, s) = (&self.axes.aperture, &self.axes.stage);
        if a.axis == s.axis {
            return bad("axes.stage.axis", format!("aperture and stage both use axis {}", a.axis));
        }
        for (prefix, min, max) in [("axes.aperture", a.min, a.max), ("axes.stage", s.min, s.max)] {
            if !(min.is_finite() && max.is_finite() && min < max) {
                return bad(&format!("{prefix}.max"), format!("range [{min}, {max}] is empty (min must be < max)"));
            }
        }
        for (key, v) in [("axes.aperture.open", a.open), ("axes.aperture.pinhole", a.pinhole)] {
            if !(v >= a.min && v <= a.max) {
                return bad(key, format!("{v} mm is outside [{}, {}]", a.min, a.max));
            }
        }
        if a.open == a.pinhole {
            return bad("axes.aperture.pinhole", "equals `open`: the pair needs two different apertures".into());
        }
        if s.positions.is_empty() {
            return bad("axes.stage.positions", "needs at least one position".into());
        }
        if let Some(v) = s.positions.iter().find(|v| !(**v >= s.min && **v <= s.max)) {
            return bad("axes.stage.positions", format!("{v} mm is outside [{}, {}]", s.min, s.max));
        }
        if let Some(d) = &s.focus_distance_m {
            if d.len() != s.positions.len() {
                return bad("axes.stage.focus_distance_m", format!("has {} values for {} positions (one focus distance per position)", d.len(), s.positions.len()));
            }
            if let Some(v) = d.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
                return bad("axes.stage.focus_distance_m", format!("{v} must be a finite distance > 0 (metres)"));
            }
        }
        Ok(())
    }

    /// `[plan]` (with its flat step) and `[target]`.
    fn validate_plan(&self) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((k.to_string(), m));
        let (p, s) = (&self.plan, &self.axes.stage);
        if !(p.pinhole_exposure_scale.is_finite() && p.pinhole_exposure_scale > 0.0) {
            return bad("plan.pinhole_exposure_scale", format!("{} must be > 0", p.pinhole_exposure_scale));
        }
        if let Some(f) = &p.flat {
            if !(f.stage_mm >= s.min && f.stage_mm <= s.max) {
                return bad("plan.flat.stage_mm", format!("{} mm is outside the stage range [{}, {}]", f.stage_mm, s.min, s.max));
            }
            if let Some(v) = s.positions.iter().find(|v| (**v - f.stage_mm).abs() < FLAT_CLEARANCE_MM) {
                return bad("plan.flat.stage_mm", format!("{} mm is within {FLAT_CLEARANCE_MM} mm of the pair position {v} mm: the uniform target must sit elsewhere on the stage", f.stage_mm));
            }
        }
        if let Some(t) = &self.target {
            if t.path.as_os_str().is_empty() {
                return bad("target.path", "is empty".into());
            }
            if let Some(l) = &t.layout {
                if !(l.pixels_per_cell.is_finite() && l.pixels_per_cell > 0.0) {
                    return bad("target.layout.pixels_per_cell", format!("{} must be a finite number > 0", l.pixels_per_cell));
                }
                if !l.origin.iter().all(|v| v.is_finite()) {
                    return bad("target.layout.origin", format!("{:?} must be two finite numbers (target cells)", l.origin));
                }
                if !l.cells_per_mm.is_finite() {
                    return bad("target.layout.cells_per_mm", format!("{} must be finite", l.cells_per_mm));
                }
            }
        }
        Ok(())
    }

    /// Controller options derived from this config: the two axes' ranges as limits,
    /// timeouts, recovery policy and homing.
    pub fn controller_options(&self) -> ControllerOptions {
        let (a, s) = (&self.axes.aperture, &self.axes.stage);
        let t = &self.controller.timeouts;
        ControllerOptions {
            timeouts: Timeouts {
                banner: Duration::from_millis(t.banner_ms),
                response: Duration::from_millis(t.response_ms),
                motion: Duration::from_millis(t.motion_ms),
                homing: Duration::from_millis(t.homing_ms),
            },
            recovery: self.controller.recovery,
            home_on_start: self.controller.home_on_start,
            limits: vec![AxisLimit { axis: a.axis, min: a.min, max: a.max }, AxisLimit { axis: s.axis, min: s.min, max: s.max }],
            ..ControllerOptions::default()
        }
    }
}

/// 1-based line and column of a byte offset.
fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let before = &text.as_bytes()[..offset];
    let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
    let col = offset - before.iter().rposition(|&b| b == b'\n').map_or(0, |p| p + 1) + 1;
    (line, col)
}

/// The dotted key written on `line` (1-based), prefixed with its `[section]`; the section
/// itself when the line is a header.
fn key_at(text: &str, line: usize, _offset: usize) -> String {
    let lines: Vec<&str> = text.lines().collect();
    let Some(l) = lines.get(line.saturating_sub(1)) else { return String::new() };
    let section = lines[..line.saturating_sub(1)].iter().rev().find_map(|l| header(l)).unwrap_or_default();
    if let Some(h) = header(l) {
        return h;
    }
    match l.split_once('=') {
        Some((k, _)) => {
            let k = k.trim().trim_matches('"');
            if section.is_empty() { k.to_string() } else { format!("{section}.{k}") }
        }
        None => section,
    }
}

fn header(line: &str) -> Option<String> {
    let t = line.trim();
    let inner = t.strip_prefix('[')?.split(']').next()?;
    Some(inner.trim_matches('[').trim().to_string())
}

/// `missing field `x`` → `x`.
fn missing_field(message: &str) -> Option<String> {
    let rest = message.strip_prefix("missing field `")?;
    Some(rest.split('`').next()?.to_string())
}

/// The line where a dotted key is written (`[a.b]` + `c = …`), or the section's header line,
/// or 0.
fn find_key_line(text: &str, dotted: &str) -> usize {
    let (section, key) = dotted.rsplit_once('.').unwrap_or(("", dotted));
    let mut current = String::new();
    let mut header_line = 0;
    for (i, l) in text.lines().enumerate() {
        if let Some(h) = header(l) {
            current = h;
            if current == section {
                header_line = i + 1;
            }
            continue;
        }
        if current == section {
            if let Some((k, _)) = l.split_once('=') {
                if k.trim().trim_matches('"') == key {
                    return i + 1;
                }
            }
        }
    }
    header_line
}

#[cfg(test)]
mod tests {
    use super::*;

    const MOCK: &str = include_str!("../../rig-configs/mock.toml");
    const REAL: &str = include_str!("../../rig-configs/example-real.toml");

    fn err(text: &str) -> String {
        parse(text, Path::new("rigs/bench.toml")).unwrap_err().to_string()
    }

    #[test]
    fn shipped_configs_load() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("rig-configs");
        let m = load(&dir.join("mock.toml")).unwrap();
        assert_eq!(m.camera.kind, CameraKind::Mock);
        assert_eq!(m.controller.kind, ControllerKind::Sim);
        assert!(m.lens.is_some());
        assert!(m.target.as_ref().unwrap().path.starts_with(&dir));
        let r = load(&dir.join("example-real.toml")).unwrap();
        assert_eq!(r.camera.kind, CameraKind::V4l2);
        assert_eq!(r.camera.fourcc(), *b"YUYV");
        assert_eq!(r.controller.recovery, RecoveryPolicy::Manual);
        let o = r.controller_options();
        assert_eq!(o.limits.len(), 2);
        assert_eq!(o.timeouts.response, Duration::from_millis(r.controller.timeouts.response_ms));
    }

    #[test]
    fn unknown_key_names_file_line_and_key() {
        let text = MOCK.replacen("exposure_us =", "exposure_usec =", 1);
        let line = text.lines().position(|l| l.starts_with("exposure_usec")).unwrap() + 1;
        let e = err(&text);
        assert!(e.starts_with(&format!("rigs/bench.toml:{line}:")), "{e}");
        assert!(e.contains("camera.exposure_usec") && e.contains("unknown field"), "{e}");
    }

    #[test]
    fn wrong_type_names_file_line_and_key() {
        let text = MOCK.replacen("width = ", "width = \"wide\" #", 1);
        let line = text.lines().position(|l| l.starts_with("width")).unwrap() + 1;
        let e = err(&text);
        assert!(e.starts_with(&format!("rigs/bench.toml:{line}:")), "{e}");
        assert!(e.contains("camera.width") && e.contains("invalid type"), "{e}");
    }

    #[test]
    fn broken_toml_names_file_line_and_key() {
        let text = MOCK.replacen("settle_ms = ", "settle_ms = = ", 1);
        let line = text.lines().position(|l| l.starts_with("settle_ms")).unwrap() + 1;
        let e = err(&text);
        assert!(e.starts_with(&format!("rigs/bench.toml:{line}:")), "{e}");
        assert!(e.contains("plan.settle_ms"), "{e}");
    }

    #[test]
    fn wrong_enum_value_and_missing_key() {
        let e = err(&MOCK.replacen("recovery = \"unlock\"", "recovery = \"yolo\"", 1));
        assert!(e.contains("controller.recovery") && e.contains("yolo"), "{e}");
        let e = err(&MOCK.replacen("height = ", "# height = ", 1));
        assert!(e.contains("height") && e.contains("missing field"), "{e}");
    }

    #[test]
    fn validation_messages_name_the_key_and_line() {
        let text = MOCK.replacen("pinhole = -8.0", "pinhole = -80.0", 1);
        let line = text.lines().position(|l| l.starts_with("pinhole")).unwrap() + 1;
        let e = err(&text);
        assert_eq!(e, format!("rigs/bench.toml:{line}: axes.aperture.pinhole: -80 mm is outside [-10, 0]"));
        let e = err(&MOCK.replacen("axis = \"X\"", "axis = \"Z\"", 1));
        assert!(e.contains("axes.stage.axis") && e.contains("both use axis Z"), "{e}");
        let e = err(&MOCK.replacen("frames_to_average = 16", "frames_to_average = 0", 1));
        assert!(e.contains("camera.frames_to_average"), "{e}");
        let e = err(&MOCK.replacen("positions = [", "positions = [5.0, ", 1));
        assert!(e.contains("axes.stage.positions") && e.contains("5 mm"), "{e}");
        let e = err(&REAL.replacen("port = ", "# port = ", 1));
        assert!(e.contains("controller.port"), "{e}");
        let e = err(&MOCK.replacen("pinhole_exposure_scale = 16.0", "pinhole_exposure_scale = 0.0", 1));
        assert!(e.contains("plan.pinhole_exposure_scale"), "{e}");
    }

    #[test]
    fn retry_and_camera_timeouts_have_defaults_and_refuse_unknown_keys() {
        let m = parse(MOCK, Path::new("m.toml")).unwrap();
        assert_eq!(m.camera.frame_timeout_ms, 5000);
        let r = parse(REAL, Path::new("r.toml")).unwrap();
        assert_eq!(r.retry, RetryConfig { max_tries: 3, pause_ms: 5000, drift_tolerance: 0.1 });
        assert_eq!(m.retry, RetryConfig { max_tries: 3, pause_ms: 200, drift_tolerance: 0.1 });
        assert_eq!(r.camera.frame_timeout_ms, 8000);
        let e = err(&MOCK.replacen("pause_ms = 200", "pause_ms = 200\nmax_retries = 2", 1));
        assert!(e.contains("retry.max_retries") && e.contains("unknown field"), "{e}");
        let e = err(&MOCK.replacen("max_tries = 3", "max_tries = 0", 1));
        assert!(e.contains("retry.max_tries") && e.contains("at least 1"), "{e}");
        let e = err(&MOCK.replacen("discard_after_change = 2", "discard_after_change = 2\nframe_timeout_ms = 0", 1));
        assert!(e.contains("camera.frame_timeout_ms"), "{e}");
    }

    /// `[plan.flat]` parses, refuses unknown keys with their dotted name, and must sit inside
    /// the stage range and clear of every pair position.
    #[test]
    fn flat_step_is_checked() {
        let m = parse(MOCK, Path::new("m.toml")).unwrap();
        assert_eq!(m.plan.flat, Some(FlatStep { stage_mm: -90.0 }));
        let text = MOCK.replacen("stage_mm = -90.0", "stage_mm = -90.0\nstage = 1", 1);
        let line = text.lines().position(|l| l.starts_with("stage = 1")).unwrap() + 1;
        let e = err(&text);
        assert!(e.starts_with(&format!("rigs/bench.toml:{line}:")) && e.contains("plan.flat.stage") && e.contains("unknown field"), "{e}");
        let e = err(&MOCK.replacen("stage_mm = -90.0", "stage_mm = -190.0", 1));
        assert!(e.contains("plan.flat.stage_mm") && e.contains("outside the stage range"), "{e}");
        let e = err(&MOCK.replacen("stage_mm = -90.0", "stage_mm = -40.2", 1));
        assert!(e.contains("plan.flat.stage_mm") && e.contains("pair position -40 mm"), "{e}");
        let none = parse(&MOCK.replacen("[plan.flat]", "[plan.flatx]", 1), Path::new("m.toml"));
        assert!(none.is_err());
    }

    #[test]
    fn missing_file_names_the_path() {
        let e = load(Path::new("/nonexistent/rig.toml")).unwrap_err().to_string();
        assert!(e.contains("/nonexistent/rig.toml"), "{e}");
    }

    #[test]
    fn line_col_is_one_based() {
        assert_eq!(line_col("ab\ncd", 0), (1, 1));
        assert_eq!(line_col("ab\ncd", 4), (2, 2));
    }
}
