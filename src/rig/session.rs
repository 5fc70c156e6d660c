//! The assembled rig ([`Rig`]), the capture plan ([`plan`]) and capture sessions on disk
//! ([`capture`]).
//!
//! # Plan
//! For each stage position: move the stage; then for the aperture in `[open, pinhole]`: move
//! the aperture, settle, set the exposure and capture `frames_to_average` frames. The open
//! exposure starts at `camera.exposure_us`; with `plan.auto_bracket` a single test frame is
//! taken and the exposure scaled down until the 99.9th percentile is below 0.95 full scale
//! (after [`MAX_BRACKET_STEPS`] reductions, or at 1 µs, the capture stops with
//! [`SessionError::Saturated`] rather than record a clipped frame).
//! The pinhole exposure is the open exposure × `plan.pinhole_exposure_scale` (capped at 10 s).
//! With `plan.dark_frames > 0` a **bias/dark frame** is recorded after the pinhole: the
//! average of that many frames at the shortest exposure (1 µs), aperture at pinhole — the
//! black level `estimate --session` subtracts. (A capped lens is not needed at 1 µs.)
//!
//! With `[plan.flat]` a **flat field** follows the pairs: the stage moves to
//! `plan.flat.stage_mm` (a diffuser or uniform white card), the aperture opens, and the frame
//! is taken like an open frame (auto-bracketed, `frames_to_average`, drift-checked against the
//! session's first flat, plus a dark frame when the plan takes them). It is one more step of
//! the plan with the pairs' guarantees: captured into `flat.partial/`, renamed when complete,
//! retried after faults, redone on resume when unfinished, kept when finished.
//!
//! # Pause instead of fail
//! A pair that meets a fault retrying can get past ([`SessionError::pause_cause`]: a camera
//! timeout, a lost port, a grbl alarm, a silent or unreadable controller, illumination drift
//! beyond `retry.drift_tolerance`) is logged, paused `retry.pause_ms`, the rig recovered
//! ([`Rig::recover`]) and the pair taken again from an empty `.partial` directory and its
//! first move, at most `retry.max_tries` times; then [`SessionError::GaveUp`].
//!
//! The camera never sees the plan: after each move the controller's status report is read
//! and written to the shared [`PositionSource`].
//!
//! # Session directory
//! ```text
//! SESSION/session.toml                 what ran, with what, and how it ended
//! SESSION/rig.toml                     a copy of the rig config
//! SESSION/events.jsonl                 pauses, retries, recoveries, unreadable lines (super::events)
//! SESSION/pairs/000-stage-X-20.000/    one finished pair:
//!     open.png open.toml pinhole.png pinhole.toml [dark.png dark.toml]
//! SESSION/flat/                        the flat-field step ([plan.flat]):
//!     flat.png flat.toml [dark.png dark.toml]
//! ```
//! Frames are lossless 16-bit PNGs, each with a TOML sidecar ([`FrameRecord`]). Every file
//! is written atomically. A pair is captured into `NNN-….partial/` and renamed when both
//! frames and their metadata are on disk, so a pair directory without `.partial` is always
//! complete. An existing session directory is never overwritten; `resume` deletes
//! `.partial` directories (unfinished pairs are redone) and continues after the last finished
//! pair, leaving finished pairs untouched.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::camera::mock::{CameraFaults, MockCamera, MockError, MockOptics, PositionSource};
use super::camera::{Camera, CameraError, Frame};
use super::config::{CameraKind, ControllerKind, RigConfig};
use super::controller::sim::{spawn_pty, SimHandle, SimOptions};
use super::controller::{Axis, Controller, ControllerError, ControllerOptions, MachineState, Position, SerialController, Status};
use super::events::{EventLog, EventLogError};
use crate::fsutil::{write_atomic, Overwrite};
use crate::image::io::{write_png16, ImageError};

/// Anything that stops a capture.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error(transparent)]
    Controller(#[from] ControllerError),
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Events(#[from] EventLogError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// The disk (or the process's file-size limit) is full: finished pairs are intact, the
    /// unfinished one stays in its `.partial` directory and `--resume` redoes it.
    #[error("{path}: no space to write the capture ({source}); the pairs finished so far are intact: free some space, then run the same capture with --resume")]
    DiskFull {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// Auto-bracketing gave up: the open frame still clips.
    #[error("pair {pair}: the open frame still clips at {exposure_us} µs (99.9th percentile {p999:.3} of full scale) after {MAX_BRACKET_STEPS} exposure reductions; reduce the light or the gain")]
    Saturated { pair: String, exposure_us: u32, p999: f32 },
    /// The light changed during the session by more than `retry.drift_tolerance`.
    #[error("pair {pair}: illumination drift: the {role} frame's light is {change:+.1} % of the session's first {role} frame (tolerance ±{tolerance:.1} %)")]
    Drift { pair: String, role: String, change: f64, tolerance: f64 },
    /// A pair met faults `tries` times (`retry.max_tries`); the last one is the source.
    #[error("{source} (pair {pair}: gave up after {tries} tries; see events.jsonl)")]
    GaveUp {
        pair: String,
        tries: u32,
        #[source]
        source: Box<SessionError>,
    },
    #[error("cannot start the simulated controller")]
    SimStart {
        #[source]
        source: io::Error,
    },
    /// The mock camera's `[lens]`/`[target]` settings.
    #[error(transparent)]
    MockCamera(MockError),
    #[error("camera.kind = \"v4l2\" needs lensrig built with `--features v4l2`")]
    NoV4l2,
    #[error("{axis} target {target} mm outside the configured range [{min}, {max}] mm")]
    OutOfRange { axis: Axis, target: f64, min: f64, max: f64 },
    #[error("cannot encode {path}")]
    Encode {
        path: PathBuf,
        #[source]
        source: toml::ser::Error,
    },
    #[error("session {0} already exists; pass --resume to continue it, or choose another --out (sessions are never overwritten)")]
    Exists(PathBuf),
    #[error("{config} differs from the config this session was captured with ({copy}); resume with the same config")]
    ConfigChanged { config: PathBuf, copy: PathBuf },
    /// A session or sidecar file that does not parse (`detail` has the line and key).
    #[error("{path}: {detail}")]
    Parse { path: PathBuf, detail: String },
    #[error("{0} is missing")]
    Missing(PathBuf),
    #[error("{path}: unreadable frame")]
    UnreadableFrame {
        path: PathBuf,
        #[source]
        source: ImageError,
    },
    #[error("{0}: empty frame")]
    EmptyFrame(PathBuf),
}

impl SessionError {
    /// The fault class a pause names in the event log, or `None` when retrying cannot help
    /// (a full disk, a rejected command, a config error, saturation).
    pub fn pause_cause(&self) -> Option<&'static str> {
        use crate::rig::controller::GrblError;
        match self {
            SessionError::Controller(c) => match c {
                ControllerError::Disconnected { .. } | ControllerError::Io { .. } | ControllerError::Open { .. } => Some("disconnect"),
                ControllerError::Alarm { .. } | ControllerError::Locked { .. } => Some("alarm"),
                ControllerError::Grbl { error: GrblError::GcodeLock, .. } => Some("alarm"),
                ControllerError::Timeout { .. } => Some("controller-timeout"),
                ControllerError::Garbage { .. } => Some("unreadable"),
                ControllerError::Protocol { .. } => Some("protocol"),
                ControllerError::Grbl { .. } | ControllerError::LimitViolation { .. } | ControllerError::HomingDisabled { .. } => None,
            },
            SessionError::Camera(CameraError::Timeout { .. }) => Some("camera-timeout"),
            SessionError::Drift { .. } => Some("drift"),
            _ => None,
        }
    }
}

/// Exposure reductions auto-bracketing tries before [`SessionError::Saturated`].
pub const MAX_BRACKET_STEPS: usize = 12;

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> SessionError + '_ {
    move |source| file_error(path.to_path_buf(), source)
}

/// `ENOSPC`, `EFBIG` (a file-size limit), `EDQUOT`: the disk cannot take more data.
fn is_disk_full(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(27 | 28 | 122))
}

fn file_error(path: PathBuf, source: io::Error) -> SessionError {
    if is_disk_full(&source) {
        SessionError::DiskFull { path, source }
    } else {
        SessionError::Io { path, source }
    }
}

/// A camera and a controller, injected, plus what the simulated parts expose to tests.
pub struct Rig {
    pub camera: Box<dyn Camera>,
    pub controller: Box<dyn Controller>,
    /// Written after every move from the controller's status report; read by a mock camera.
    pub position: PositionSource,
    /// The simulated firmware (`controller.kind = "sim"`): its faults and true state.
    pub sim: Option<SimHandle>,
    /// The mock camera's fault switches and optics (`camera.kind = "mock"`).
    pub camera_faults: Option<Arc<CameraFaults>>,
    pub mock_optics: Option<MockOptics>,
    /// The controller's port path.
    pub port: String,
    /// How to open the port again after a disconnect (baud, options); `None`: no reconnect.
    pub reconnect: Option<(u32, ControllerOptions)>,
}

impl Rig {
    /// Injects a camera and a controller.
    pub fn new(camera: Box<dyn Camera>, controller: Box<dyn Controller>, position: PositionSource, port: String) -> Self {
        Self { camera, controller, position, sim: None, camera_faults: None, mock_optics: None, port, reconnect: None }
    }

    /// Builds the rig a config describes: `controller.kind = "sim"` runs the simulated grbl
    /// firmware on a pseudo-terminal and opens its slave path as a serial port; `"serial"`
    /// opens `controller.port` or `port_override`.
    ///
    /// # Errors
    /// A port or camera that cannot be opened, bad `[lens]` keys, a failed homing cycle.
    pub fn from_config(cfg: &RigConfig, port_override: Option<&Path>) -> Result<Rig, SessionError> {
        let mut sim = None;
        let port = match (port_override, cfg.controller.kind) {
            (Some(p), _) => p.display().to_string(),
            (None, ControllerKind::Serial) => cfg.controller.port.clone().unwrap_or_default(),
            (None, ControllerKind::Sim) => {
                let mut o = SimOptions::fast();
                if cfg.controller.home_on_start {
                    o = o.with(22, 1.0);
                }
                let (h, path) = spawn_pty(o).map_err(|source| SessionError::SimStart { source })?;
                sim = Some(h);
                path
            }
        };
        let ctl = SerialController::open(&port, cfg.controller.baud, cfg.controller_options())?;
        let position: PositionSource = Arc::new(Mutex::new(Position::ZERO));
        let (camera, faults, optics): (Box<dyn Camera>, _, _) = match cfg.camera.kind {
            CameraKind::Mock => {
                let c = MockCamera::new(cfg, position.clone()).map_err(SessionError::MockCamera)?;
                let (f, o) = (c.faults.clone(), c.optics().clone());
                (Box::new(c), Some(f), Some(o))
            }
            CameraKind::V4l2 => (open_v4l(cfg)?, None, None),
        };
        let mut rig = Rig::new(camera, Box::new(ctl), position, port);
        rig.sim = sim;
        rig.camera_faults = faults;
        rig.mock_optics = optics;
        rig.reconnect = Some((cfg.controller.baud, cfg.controller_options()));
        Ok(rig)
    }

    /// Moves one axis and publishes the position of the (clean, confirmed) final report.
    fn move_axis(&mut self, axis: Axis, mm: f64) -> Result<Status, SessionError> {
        let st = self.controller.move_to(&[(axis, mm)])?;
        *self.position.lock().unwrap_or_else(|e| e.into_inner()) = st.mpos;
        self.camera.invalidate();
        Ok(st)
    }

    /// Appends what the controller met since the last call to the event log.
    ///
    /// # Errors
    /// The log cannot be written.
    pub fn drain_events(&mut self, log: &mut EventLog) -> Result<(), SessionError> {
        for e in self.controller.take_events() {
            log.record(e.kind, &e.detail)?;
        }
        Ok(())
    }

    /// Brings the rig back after a fault of class `cause` ([`SessionError::pause_cause`]):
    /// a lost port is opened again (the board then homes if the config says so, its position
    /// being lost with its power); an alarm, a silent or unreadable controller gets a soft
    /// reset, then a homing cycle when the config homes (`rehome`) or `$X` (`unlock`);
    /// camera timeouts and drift need nothing but the pause. Each step is an event.
    ///
    /// # Errors
    /// The step failed (the port is still gone, the board does not answer).
    pub fn recover(&mut self, cause: &str, log: &mut EventLog) -> Result<(), SessionError> {
        let home = self.reconnect.as_ref().is_some_and(|(_, o)| o.home_on_start);
        match cause {
            "disconnect" => {
                let Some((baud, opts)) = self.reconnect.clone() else { return Ok(()) };
                let ctl = SerialController::open(&self.port, baud, opts)?;
                self.controller = Box::new(ctl);
                log.record("reconnect", &format!("{} open again{}", self.port, if home { ", homed" } else { "" }))?;
            }
            "alarm" | "controller-timeout" | "unreadable" | "protocol" => {
                let r = self.controller.reset();
                self.drain_events(log)?;
                r?;
                log.record("reset", &format!("{}: soft reset (0x18)", self.port))?;
                if home {
                    let st = self.controller.home();
                    self.drain_events(log)?;
                    let st = st?;
                    log.record("rehome", &format!("homed: machine position {}", st.mpos.format()))?;
                } else if self.controller.status()?.state == MachineState::Alarm {
                    self.controller.unlock()?;
                    log.record("unlock", "$X: alarm lock cleared (no homing configured: positions are as the board reports them)")?;
                }
            }
            _ => {}
        }
        self.drain_events(log)?;
        self.camera.invalidate();
        Ok(())
    }
}

#[cfg(feature = "v4l2")]
fn open_v4l(cfg: &RigConfig) -> Result<Box<dyn Camera>, SessionError> {
    use super::camera::decode::ColorMode;
    use super::camera::v4l::{V4lCamera, V4lSettings};
    let c = &cfg.camera;
    let s = V4lSettings {
        device: c.device.clone().unwrap_or_default(),
        fourcc: super::camera::FourCc(c.fourcc()),
        width: c.width,
        height: c.height,
        exposure_us: c.exposure_us,
        gain: c.gain,
        discard_after_change: c.discard_after_change as usize,
        color: ColorMode::Luma,
        frame_timeout: Duration::from_millis(c.frame_timeout_ms),
    };
    Ok(Box::new(V4lCamera::open(&s)?))
}

#[cfg(not(feature = "v4l2"))]
fn open_v4l(_cfg: &RigConfig) -> Result<Box<dyn Camera>, SessionError> {
    Err(SessionError::NoV4l2)
}

/// One stage position of the plan.
#[derive(Clone, Debug, PartialEq)]
pub struct PairPlan {
    pub index: usize,
    pub stage_mm: f64,
    /// Directory name under `pairs/`, also the profile key: `000-stage-X-20.000`.
    pub key: String,
}

/// The pairs a config asks for, in order.
pub fn plan(cfg: &RigConfig) -> Vec<PairPlan> {
    let s = &cfg.axes.stage;
    s.positions.iter().enumerate().map(|(i, &p)| PairPlan { index: i, stage_mm: p, key: format!("{i:03}-stage-{}{p:+.3}", s.axis) }).collect()
}

/// Every move and capture of the plan, one line each, after checking every target against the
/// axis ranges. Touches no device.
///
/// # Errors
/// A target outside its axis range (naming the axis, the value and the range).
pub fn dry_run(cfg: &RigConfig) -> Result<Vec<String>, SessionError> {
    let (a, s) = (&cfg.axes.aperture, &cfg.axes.stage);
    let check = |axis: Axis, v: f64, min: f64, max: f64| {
        if v >= min && v <= max {
            Ok(())
        } else {
            Err(SessionError::OutOfRange { axis, target: v, min, max })
        }
    };
    let c = &cfg.camera;
    let mut out = vec![format!("connect {:?} controller{}, home: {}", cfg.controller.kind, cfg.controller.port.as_deref().map(|p| format!(" on {p}")).unwrap_or_default(), cfg.controller.home_on_start)];
    for p in plan(cfg) {
        check(s.axis, p.stage_mm, s.min, s.max)?;
        check(a.axis, a.open, a.min, a.max)?;
        check(a.axis, a.pinhole, a.min, a.max)?;
        out.push(format!("pair {}: move stage {} to {:.3} mm", p.key, s.axis, p.stage_mm));
        out.push(format!("  move aperture {} to {:.3} mm (open), settle {} ms", a.axis, a.open, cfg.plan.settle_ms));
        out.push(format!(
            "  capture open: exposure {} µs{}, gain {}, average {} frame(s)",
            c.exposure_us,
            if cfg.plan.auto_bracket { " (auto-bracketed down until < 0.95 full scale)" } else { "" },
            c.gain,
            c.frames_to_average
        ));
        out.push(format!("  move aperture {} to {:.3} mm (pinhole), settle {} ms", a.axis, a.pinhole, cfg.plan.settle_ms));
        out.push(format!("  capture pinhole: exposure open × {} (≤ 10 s), average {} frame(s)", cfg.plan.pinhole_exposure_scale, c.frames_to_average));
        if cfg.plan.dark_frames > 0 {
            out.push(format!("  capture dark: exposure 1 µs, average {} frame(s)", cfg.plan.dark_frames));
        }
        out.push(format!("  write pairs/{}/ (open, pinhole{})", p.key, if cfg.plan.dark_frames > 0 { ", dark" } else { "" }));
    }
    if let Some(f) = &cfg.plan.flat {
        check(s.axis, f.stage_mm, s.min, s.max)?;
        out.push(format!("flat field: move stage {} to {:.3} mm (uniform target), aperture {} to {:.3} mm (open), settle {} ms", s.axis, f.stage_mm, a.axis, a.open, cfg.plan.settle_ms));
        out.push(format!(
            "  capture flat: exposure {} µs{}, average {} frame(s){}",
            c.exposure_us,
            if cfg.plan.auto_bracket { " (auto-bracketed)" } else { "" },
            c.frames_to_average,
            if cfg.plan.dark_frames > 0 { format!("; dark: 1 µs, {} frame(s)", cfg.plan.dark_frames) } else { String::new() }
        ));
        out.push(format!("  write {FLAT_DIR}/"));
    }
    Ok(out)
}

/// `session.toml`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SessionRecord {
    pub software: String,
    /// The rig config as given, and its copy in the session.
    pub rig_config: String,
    pub rig_config_copy: String,
    pub camera: String,
    pub camera_format: FormatRecord,
    pub controller_port: String,
    pub target: Option<String>,
    pub started: String,
    pub finished: Option<String>,
    /// `running` (or killed while running), `complete`, or `failed: <error>`.
    pub status: String,
    /// Times the session was resumed.
    #[serde(default)]
    pub resumed: Vec<String>,
    #[serde(default)]
    pub pairs: Vec<PairRecord>,
    /// The flat-field step, once finished (`[plan.flat]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flat: Option<FlatRecord>,
}

/// The finished flat-field step.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct FlatRecord {
    pub stage_mm: f64,
    /// Relative to the session directory (`flat`).
    pub dir: String,
    pub flat: String,
    pub dark: Option<String>,
}

/// Directory of the flat-field step in a session.
pub const FLAT_DIR: &str = "flat";

fn flat_record(cfg: &RigConfig) -> Option<FlatRecord> {
    let f = cfg.plan.flat.as_ref()?;
    Some(FlatRecord { stage_mm: f.stage_mm, dir: FLAT_DIR.into(), flat: "flat.png".into(), dark: (cfg.plan.dark_frames > 0).then(|| "dark.png".to_string()) })
}

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct FormatRecord {
    pub width: u32,
    pub height: u32,
    pub fourcc: String,
    pub transfer: String,
}

/// One finished pair.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct PairRecord {
    pub index: usize,
    pub key: String,
    pub stage_mm: f64,
    /// Relative to the session directory.
    pub dir: String,
    pub open: String,
    pub pinhole: String,
    pub dark: Option<String>,
}

/// The sidecar of one frame (`open.toml`, …).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct FrameRecord {
    pub role: String,
    pub time: String,
    pub exposure_us: u32,
    pub gain: f64,
    /// Positions as reported by the controller (machine coordinates, mm).
    pub aperture_mm: f64,
    pub stage_mm: f64,
    pub frames_averaged: usize,
    pub frames_discarded: usize,
    pub transfer: String,
    pub fourcc: String,
    pub sequence: Option<u32>,
    /// The temporal noise of one frame, per channel, measured from the averaged frames:
    /// `[level, variance, pixels]` rows on the stored axis (equal-count level bins; see
    /// [`super::camera::temporal_noise_curve`]). Absent for a single frame. `lensrig diagnose
    /// --session` uses it as the noise model (divided by `frames_averaged`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temporal_noise: Option<Vec<Vec<[f64; 3]>>>,
}

/// Reads `session.toml`.
///
/// # Errors
/// Missing or unreadable file.
pub fn load_session(dir: &Path) -> Result<SessionRecord, SessionError> {
    let p = dir.join("session.toml");
    let text = fs::read_to_string(&p).map_err(io_err(&p))?;
    toml::from_str(&text).map_err(|e| SessionError::Parse { path: p.clone(), detail: crate::toml_error(&text, &e) })
}

/// Reads a frame's sidecar.
///
/// # Errors
/// Missing or unreadable file.
pub fn load_frame_record(path: &Path) -> Result<FrameRecord, SessionError> {
    let text = fs::read_to_string(path).map_err(io_err(path))?;
    toml::from_str(&text).map_err(|e| SessionError::Parse { path: path.to_path_buf(), detail: crate::toml_error(&text, &e) })
}

fn save_record(dir: &Path, rec: &SessionRecord) -> Result<(), SessionError> {
    let p = dir.join("session.toml");
    let text = toml::to_string_pretty(rec).map_err(|source| SessionError::Encode { path: p.clone(), source })?;
    write_atomic(&p, text.as_bytes(), Overwrite::Replace).map_err(io_err(&p))
}

/// How to run [`capture`].
#[derive(Clone, Debug)]
pub struct CaptureOptions {
    pub resume: bool,
    /// Progress lines on stderr.
    pub progress: bool,
}

/// Captures (or resumes) a session into `out` with `rig`, following `cfg`.
///
/// # Errors
/// An existing `out` without `resume`; any device or file error (the session's status says
/// `failed: …`; finished pairs stay on disk).
pub fn capture(rig: &mut Rig, cfg: &RigConfig, config_path: &Path, out: &Path, o: &CaptureOptions) -> Result<SessionRecord, SessionError> {
    let config_text = fs::read_to_string(config_path).map_err(io_err(config_path))?;
    let mut rec = if o.resume {
        let mut rec = load_session(out)?;
        let copy = fs::read_to_string(out.join("rig.toml")).map_err(io_err(&out.join("rig.toml")))?;
        if copy != config_text {
            return Err(SessionError::ConfigChanged { config: config_path.to_path_buf(), copy: out.join("rig.toml") });
        }
        rec.resumed.push(crate::timestamp_utc());
        rec
    } else {
        if out.exists() {
            return Err(SessionError::Exists(out.to_path_buf()));
        }
        fs::create_dir_all(out.join("pairs")).map_err(io_err(out))?;
        write_atomic(&out.join("rig.toml"), config_text.as_bytes(), Overwrite::Never).map_err(io_err(&out.join("rig.toml")))?;
        let f = rig.camera.format();
        SessionRecord {
            software: format!("lensrig {}", env!("CARGO_PKG_VERSION")),
            rig_config: config_path.display().to_string(),
            rig_config_copy: "rig.toml".into(),
            camera: rig.camera.describe(),
            camera_format: FormatRecord { width: f.width, height: f.height, fourcc: f.fourcc.to_string(), transfer: f.transfer.name().into() },
            controller_port: rig.port.clone(),
            target: cfg.target.as_ref().map(|t| t.path.display().to_string()),
            started: crate::timestamp_utc(),
            ..Default::default()
        }
    };
    rec.status = "running".into();
    rec.finished = None;
    let pairs = plan(cfg);
    let pairs_dir = out.join("pairs");
    fs::create_dir_all(&pairs_dir).map_err(io_err(&pairs_dir))?;
    if o.resume {
        recover(out, cfg, &pairs, &mut rec, o.progress)?;
    }
    save_record(out, &rec)?;
    let mut log = EventLog::open(out)?;
    log.record("session-start", if o.resume { "resumed" } else { "started" })?;
    let result = run_pairs(rig, cfg, out, &pairs, &mut rec, o, &mut log);
    rec.finished = Some(crate::timestamp_utc());
    rec.status = match &result {
        Ok(()) => "complete".into(),
        Err(e) => format!("failed: {e}"),
    };
    // best effort: a full disk fails this too, and the capture's error says so
    let _ = rig.drain_events(&mut log).and_then(|()| Ok(log.record("session-end", &rec.status)?));
    match (result, save_record(out, &rec)) {
        (Ok(()), Ok(())) => Ok(rec),
        // the capture's own error matters more than a status that could not be written
        // (a full disk fails both)
        (Err(e), _) | (Ok(()), Err(e)) => Err(e),
    }
}

/// The files a finished pair directory holds under `cfg`.
fn pair_files(cfg: &RigConfig) -> Vec<&'static str> {
    let mut v = vec!["open.png", "open.toml", "pinhole.png", "pinhole.toml"];
    if cfg.plan.dark_frames > 0 {
        v.extend(["dark.png", "dark.toml"]);
    }
    v
}

/// The files a finished flat-field directory holds under `cfg`.
fn flat_files(cfg: &RigConfig) -> Vec<&'static str> {
    let mut v = vec!["flat.png", "flat.toml"];
    if cfg.plan.dark_frames > 0 {
        v.extend(["dark.png", "dark.toml"]);
    }
    v
}

/// Checks that a finished pair directory holds every frame and sidecar, that the sidecars
/// parse and that the PNGs decode to the session's frame size.
///
/// # Errors
/// [`SessionError::Missing`], [`SessionError::Parse`], [`SessionError::UnreadableFrame`] or
/// [`SessionError::EmptyFrame`] naming the first bad file.
pub fn verify_pair(dir: &Path, cfg: &RigConfig) -> Result<(), SessionError> {
    verify_files(dir, &pair_files(cfg))
}

/// As [`verify_pair`], for the flat-field directory.
///
/// # Errors
/// As [`verify_pair`].
pub fn verify_flat(dir: &Path, cfg: &RigConfig) -> Result<(), SessionError> {
    verify_files(dir, &flat_files(cfg))
}

fn verify_files(dir: &Path, files: &[&str]) -> Result<(), SessionError> {
    for &f in files {
        let p = dir.join(f);
        if !p.is_file() {
            return Err(SessionError::Missing(p));
        }
        if f.ends_with(".toml") {
            load_frame_record(&p)?;
        } else {
            let img = crate::image::io::read_image(&p).map_err(|source| SessionError::UnreadableFrame { path: p.clone(), source })?;
            let (w, h) = (img.width() as u32, img.height() as u32);
            if w == 0 || h == 0 {
                return Err(SessionError::EmptyFrame(p));
            }
        }
    }
    Ok(())
}

/// Brings a resumed session's directory back to "finished pairs only": removes unfinished
/// `.partial` pairs and temporary files a kill left behind, verifies every finished pair
/// (a damaged one is moved aside to `KEY.damaged[-N]`, never deleted, and captured again),
/// and records finished pairs the session file missed (a kill between the pair's rename
/// and the `session.toml` update).
fn recover(out: &Path, cfg: &RigConfig, pairs: &[PairPlan], rec: &mut SessionRecord, progress: bool) -> Result<(), SessionError> {
    let pairs_dir = out.join("pairs");
    for dir in [out, pairs_dir.as_path()] {
        for e in fs::read_dir(dir).map_err(io_err(dir))? {
            let p = e.map_err(io_err(dir))?.path();
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let stray_tmp = name.starts_with('.') && name.contains(".tmp-") && p.is_file();
            let partial = p.extension().is_some_and(|x| x == "partial") && p.is_dir();
            if stray_tmp || partial {
                if progress {
                    eprintln!("removing {} left by an interrupted capture", p.display());
                }
                if partial {
                    fs::remove_dir_all(&p).map_err(io_err(&p))?;
                } else {
                    fs::remove_file(&p).map_err(io_err(&p))?;
                }
            }
        }
    }
    for p in pairs {
        let dir = pairs_dir.join(&p.key);
        if !dir.is_dir() {
            continue;
        }
        if let Err(e) = verify_pair(&dir, cfg) {
            let aside = (0..)
                .map(|n| pairs_dir.join(if n == 0 { format!("{}.damaged", p.key) } else { format!("{}.damaged-{n}", p.key) }))
                .find(|d| !d.exists())
                .unwrap_or_else(|| pairs_dir.join(format!("{}.damaged", p.key)));
            if progress {
                eprintln!("pair {} is damaged ({e}); moved to {} and captured again", p.key, aside.display());
            }
            fs::rename(&dir, &aside).map_err(io_err(&aside))?;
            continue;
        }
        if !rec.pairs.iter().any(|r| r.key == p.key) {
            if progress {
                eprintln!("pair {} finished but was not yet recorded in session.toml: recorded", p.key);
            }
            rec.pairs.push(pair_record(p, cfg.plan.dark_frames > 0));
        }
    }
    rec.pairs.retain(|r| pairs_dir.join(&r.key).is_dir());
    rec.pairs.sort_by_key(|r| r.index);
    let flat_dir = out.join(FLAT_DIR);
    if cfg.plan.flat.is_some() && flat_dir.is_dir() {
        if let Err(e) = verify_flat(&flat_dir, cfg) {
            let aside = (0..).map(|n| out.join(format!("{FLAT_DIR}.damaged{}", if n == 0 { String::new() } else { format!("-{n}") }))).find(|d| !d.exists()).unwrap_or_else(|| out.join("flat.damaged"));
            if progress {
                eprintln!("the flat field is damaged ({e}); moved to {} and captured again", aside.display());
            }
            fs::rename(&flat_dir, &aside).map_err(io_err(&aside))?;
        } else if rec.flat.is_none() {
            rec.flat = flat_record(cfg);
        }
    }
    if !flat_dir.is_dir() {
        rec.flat = None;
    }
    Ok(())
}

fn pair_record(p: &PairPlan, dark: bool) -> PairRecord {
    PairRecord {
        index: p.index,
        key: p.key.clone(),
        stage_mm: p.stage_mm,
        dir: format!("pairs/{}", p.key),
        open: "open.png".into(),
        pinhole: "pinhole.png".into(),
        dark: dark.then(|| "dark.png".to_string()),
    }
}

fn run_pairs(rig: &mut Rig, cfg: &RigConfig, out: &Path, pairs: &[PairPlan], rec: &mut SessionRecord, o: &CaptureOptions, log: &mut EventLog) -> Result<(), SessionError> {
    rig.camera.set_gain(cfg.camera.gain)?;
    let mut light = LightReference::default();
    for p in pairs {
        let final_dir = out.join("pairs").join(&p.key);
        if final_dir.is_dir() {
            if o.progress {
                eprintln!("pair {}/{} {}: already captured", p.index + 1, pairs.len(), p.key);
            }
            continue;
        }
        if o.progress {
            eprintln!("pair {}/{} {}: stage {} → {:.3} mm", p.index + 1, pairs.len(), p.key, cfg.axes.stage.axis, p.stage_mm);
        }
        let tmp = out.join("pairs").join(format!("{}.partial", p.key));
        capture_with_retries(rig, cfg, &p.key, &tmp, log, o, |rig, tmp| capture_pair(rig, cfg, p, tmp, &mut light, o))?;
        fs::rename(&tmp, &final_dir).map_err(io_err(&final_dir))?;
        if let Ok(d) = fs::File::open(out.join("pairs")) {
            let _ = d.sync_all();
        }
        rec.pairs.push(pair_record(p, cfg.plan.dark_frames > 0));
        // in plan order, also when a damaged pair was captured again after later ones
        rec.pairs.sort_by_key(|r| r.index);
        save_record(out, rec)?;
    }
    let Some(flat) = &cfg.plan.flat else { return Ok(()) };
    let final_dir = out.join(FLAT_DIR);
    if final_dir.is_dir() {
        if o.progress {
            eprintln!("flat field: already captured");
        }
        return Ok(());
    }
    if o.progress {
        eprintln!("flat field: stage {} → {:.3} mm (uniform target)", cfg.axes.stage.axis, flat.stage_mm);
    }
    let tmp = out.join(format!("{FLAT_DIR}.partial"));
    capture_with_retries(rig, cfg, FLAT_DIR, &tmp, log, o, |rig, tmp| capture_flat(rig, cfg, flat.stage_mm, tmp, &mut light, o))?;
    fs::rename(&tmp, &final_dir).map_err(io_err(&final_dir))?;
    if let Ok(d) = fs::File::open(out) {
        let _ = d.sync_all();
    }
    rec.flat = flat_record(cfg);
    save_record(out, rec)
}

/// One try of the flat-field step: stage to the uniform target, aperture open, one
/// auto-bracketed averaged frame, dark.
fn capture_flat(rig: &mut Rig, cfg: &RigConfig, stage_mm: f64, tmp: &Path, light: &mut LightReference, o: &CaptureOptions) -> Result<(), SessionError> {
    let (a, s) = (&cfg.axes.aperture, &cfg.axes.stage);
    let n = cfg.camera.frames_to_average as usize;
    rig.move_axis(s.axis, stage_mm)?;
    rig.move_axis(a.axis, a.open)?;
    std::thread::sleep(Duration::from_millis(cfg.plan.settle_ms));
    open_exposure(rig, cfg, FLAT_DIR, o)?;
    let f = rig.camera.capture(n)?;
    light.check(FLAT_DIR, "flat", &f, cfg.retry.drift_tolerance)?;
    write_frame(tmp, "flat", &f, rig, a, s)?;
    capture_dark(rig, cfg, tmp, a, s)?;
    if o.progress {
        eprintln!("  flat {} µs, {} frame(s): saved", f.meta.exposure_us, n);
    }
    Ok(())
}

/// Captures one step (a pair, or the flat field; `key` names it) into `tmp` with `step`,
/// pausing and retrying after faults (see [`RetryConfig`](super::config::RetryConfig)):
/// each try starts from an empty `tmp` and the step's first move, so a finished step holds
/// exactly one frame of each role, taken in one go.
fn capture_with_retries(
    rig: &mut Rig,
    cfg: &RigConfig,
    key: &str,
    tmp: &Path,
    log: &mut EventLog,
    o: &CaptureOptions,
    mut step: impl FnMut(&mut Rig, &Path) -> Result<(), SessionError>,
) -> Result<(), SessionError> {
    let r = &cfg.retry;
    let pause = Duration::from_millis(r.pause_ms);
    let label = if key == FLAT_DIR { "flat field".to_string() } else { format!("pair {key}") };
    let mut tries = 0;
    let give_up = |tries: u32, e: SessionError, log: &mut EventLog| {
        let _ = log.record("gave-up", &format!("{label}: {tries} tries: {e}"));
        if tries > 1 { SessionError::GaveUp { pair: key.to_string(), tries, source: Box::new(e) } } else { e }
    };
    loop {
        tries += 1;
        if tmp.exists() {
            fs::remove_dir_all(tmp).map_err(io_err(tmp))?;
        }
        fs::create_dir_all(tmp).map_err(io_err(tmp))?;
        let result = step(rig, tmp);
        rig.drain_events(log)?;
        let e = match result {
            Ok(()) => {
                if tries > 1 {
                    log.record("recovered", &format!("{label}: complete on try {tries}"))?;
                }
                return Ok(());
            }
            Err(e) => e,
        };
        let Some(cause) = e.pause_cause() else { return Err(e) };
        if tries >= r.max_tries {
            return Err(give_up(tries, e, log));
        }
        log.record("pause", &format!("{label}: {cause}: {e}; try {tries} of {} failed, waiting {} ms", r.max_tries, r.pause_ms))?;
        if o.progress {
            eprintln!("  {cause}: {e}; pausing {} ms, then try {} of {}", r.pause_ms, tries + 1, r.max_tries);
        }
        std::thread::sleep(pause);
        // the recovery itself may fail for a while (a port still unplugged): each failure
        // uses up a try
        while let Err(re) = rig.recover(cause, log) {
            tries += 1;
            if tries >= r.max_tries || re.pause_cause().is_none() {
                log.record("recovery-failed", &format!("{label}: {re}"))?;
                // the fault is the cause to name; the failed recovery is in the log
                return Err(give_up(tries, e, log));
            }
            log.record("pause", &format!("{label}: recovery from {cause} failed: {re}; waiting {} ms", r.pause_ms))?;
            std::thread::sleep(pause);
        }
        log.record("retry", &format!("{label}: try {} of {}", tries + 1, r.max_tries))?;
    }
}

/// The session's first light level per role (mean linear value per µs of exposure), the
/// reference of the drift check.
#[derive(Debug, Default)]
struct LightReference {
    levels: Vec<(String, f64)>,
}

impl LightReference {
    /// Compares a frame's light with the first frame of its role (which becomes the
    /// reference when there is none yet).
    fn check(&mut self, pair: &str, role: &str, f: &Frame, tolerance: f64) -> Result<(), SessionError> {
        if tolerance <= 0.0 || f.meta.exposure_us == 0 {
            return Ok(());
        }
        let t = f.image.transfer;
        let (sum, n) = f.image.planes.iter().flat_map(|p| p.data.iter()).fold((0.0f64, 0usize), |(s, n), &v| (s + t.decode(v) as f64, n + 1));
        let level = sum / n.max(1) as f64 / f.meta.exposure_us as f64;
        let Some(&(_, first)) = self.levels.iter().find(|(r, _)| r == role) else {
            self.levels.push((role.to_string(), level));
            return Ok(());
        };
        let change = level / first - 1.0;
        if first > 0.0 && change.abs() > tolerance {
            return Err(SessionError::Drift { pair: pair.to_string(), role: role.to_string(), change: 100.0 * change, tolerance: 100.0 * tolerance });
        }
        Ok(())
    }
}

/// One try of one pair: stage, open (auto-bracketed), pinhole, dark.
fn capture_pair(rig: &mut Rig, cfg: &RigConfig, p: &PairPlan, tmp: &Path, light: &mut LightReference, o: &CaptureOptions) -> Result<(), SessionError> {
    let (a, s) = (&cfg.axes.aperture, &cfg.axes.stage);
    let settle = Duration::from_millis(cfg.plan.settle_ms);
    let n = cfg.camera.frames_to_average as usize;
    let tol = cfg.retry.drift_tolerance;
    rig.move_axis(s.axis, p.stage_mm)?;
    // open
    rig.move_axis(a.axis, a.open)?;
    std::thread::sleep(settle);
    let exp = open_exposure(rig, cfg, &p.key, o)?;
    let open = rig.camera.capture(n)?;
    light.check(&p.key, "open", &open, tol)?;
    write_frame(tmp, "open", &open, rig, a, s)?;
    // pinhole
    rig.move_axis(a.axis, a.pinhole)?;
    std::thread::sleep(settle);
    let pexp = ((exp as f64 * cfg.plan.pinhole_exposure_scale).round() as u32).clamp(1, 10_000_000);
    rig.camera.set_exposure(pexp)?;
    let pin = rig.camera.capture(n)?;
    light.check(&p.key, "pinhole", &pin, tol)?;
    write_frame(tmp, "pinhole", &pin, rig, a, s)?;
    capture_dark(rig, cfg, tmp, a, s)?;
    if o.progress {
        eprintln!("  open {} µs, pinhole {} µs, {} frame(s) each: saved", open.meta.exposure_us, pin.meta.exposure_us, n);
    }
    Ok(())
}

/// Sets the open frame's exposure: `camera.exposure_us`, auto-bracketed down when the plan
/// asks. Returns the exposure applied.
fn open_exposure(rig: &mut Rig, cfg: &RigConfig, key: &str, o: &CaptureOptions) -> Result<u32, SessionError> {
    let mut exp = rig.camera.set_exposure(cfg.camera.exposure_us)?;
    if !cfg.plan.auto_bracket {
        return Ok(exp);
    }
    for attempt in 0.. {
        let f = rig.camera.capture(1)?;
        let p999 = percentile(&f, 0.999);
        if p999 < 0.95 {
            break;
        }
        if attempt == MAX_BRACKET_STEPS || exp <= 1 {
            return Err(SessionError::Saturated { pair: key.to_string(), exposure_us: exp, p999 });
        }
        let factor = if p999 >= 0.999 { 0.5 } else { 0.9 / p999 as f64 };
        exp = ((exp as f64 * factor) as u32).max(1);
        exp = rig.camera.set_exposure(exp)?;
        if o.progress {
            eprintln!("  open frame clips (99.9th percentile {p999:.3}); exposure → {exp} µs");
        }
    }
    Ok(exp)
}

fn percentile(f: &Frame, q: f64) -> f32 {
    let mut v: Vec<f32> = f.image.planes.iter().flat_map(|p| p.data.iter().map(|&x| f.image.transfer.decode(x))).collect();
    v.sort_by(f32::total_cmp);
    // an empty frame cannot clip
    v.get((v.len().saturating_sub(1) as f64 * q) as usize).copied().unwrap_or(0.0)
}

/// The dark frame (`[plan] dark_frames` frames averaged at the shortest exposure) next to a
/// capture, when the plan asks for one.
fn capture_dark(rig: &mut Rig, cfg: &RigConfig, dir: &Path, a: &super::config::ApertureAxis, s: &super::config::StageAxis) -> Result<(), SessionError> {
    if cfg.plan.dark_frames > 0 {
        rig.camera.set_exposure(1)?;
        let d = rig.camera.capture(cfg.plan.dark_frames as usize)?;
        write_frame(dir, "dark", &d, rig, a, s)?;
    }
    Ok(())
}

fn write_frame(dir: &Path, role: &str, f: &Frame, rig: &Rig, a: &super::config::ApertureAxis, s: &super::config::StageAxis) -> Result<(), SessionError> {
    let pos = *rig.position.lock().unwrap_or_else(|e| e.into_inner());
    write_png16(&dir.join(format!("{role}.png")), &f.image, Overwrite::Never).map_err(|e| match e {
        ImageError::Write { path, source } if is_disk_full(&source) => SessionError::DiskFull { path, source },
        e => SessionError::Image(e),
    })?;
    let m = &f.meta;
    let r = FrameRecord {
        role: role.into(),
        // written right after the capture; seconds precision
        time: crate::timestamp_utc(),
        exposure_us: m.exposure_us,
        gain: m.gain,
        aperture_mm: pos.get(a.axis),
        stage_mm: pos.get(s.axis),
        frames_averaged: m.frames_averaged,
        frames_discarded: m.frames_discarded,
        transfer: m.transfer.name().into(),
        fourcc: m.fourcc.to_string(),
        sequence: m.sequence,
        temporal_noise: f.temporal_variance.as_ref().map(|v| f.image.planes.iter().zip(v).map(|(m, v)| super::camera::temporal_noise_curve(m, v, 16)).collect()),
    };
    let p = dir.join(format!("{role}.toml"));
    let text = toml::to_string_pretty(&r).map_err(|source| SessionError::Encode { path: p.clone(), source })?;
    write_atomic(&p, text.as_bytes(), Overwrite::Never).map_err(io_err(&p))
}
