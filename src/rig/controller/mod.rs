//! The motion controller that moves the rig's aperture and stage.
//!
//! - [`protocol`]: pure grbl 1.1 encode/parse (no I/O).
//! - [`grbl`]: [`GrblController`], the client over any `Read + Write` transport, and
//!   [`SerialController`] on a real serial port.
//! - [`sim`]: a simulated grbl 1.1h board speaking the same bytes (tests, `kind = "sim"`).
//!
//! # Conventions
//! - Positions are millimetres in **machine** coordinates (`MPos`); moves are sent as
//!   `G53 G0 …` so work offsets a user set on the board never shift the rig.
//! - With grbl's default homing direction the machine space is negative, `[−max_travel, 0]`,
//!   and homing ends at `−pull_off` on each axis.
//! - Every operation is bounded in time ([`Timeouts`]); none retries silently. A garbled
//!   line is noise, not an error: it is logged ([`Controller::take_events`]), answered
//!   with another poll or a resync, and an operation fails only when nothing parseable
//!   arrives within its timeout. Unlocking (`$X`)
//!   or resetting (`0x18`) after an alarm happens only as the [`RecoveryPolicy`] allows, or
//!   when the caller asks for it.

pub mod grbl;
pub mod protocol;
pub mod sim;

use std::time::Duration;

pub use grbl::{GrblController, SerialController};
pub use protocol::{Alarm, Axis, GrblError, MachineState, Position};

/// Where the machine is and what it is doing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Status {
    pub state: MachineState,
    /// Machine position (mm).
    pub mpos: Position,
}

/// A motion controller, as the capture code sees it.
pub trait Controller {
    /// Runs the homing cycle; returns the status once it is `Idle`.
    ///
    /// # Errors
    /// Homing disabled on the board, a homing alarm, a timeout, a lost link.
    fn home(&mut self) -> Result<Status, ControllerError>;

    /// Moves the named axes to absolute machine positions (rapid) and returns only after the
    /// motion has ended (planner empty, state `Idle`). Targets are checked against the
    /// configured limits **before anything is sent**.
    ///
    /// # Errors
    /// [`ControllerError::LimitViolation`] (nothing sent), an alarm or grbl error, a timeout,
    /// a final position that differs from the target, a lost link.
    fn move_to(&mut self, targets: &[(Axis, f64)]) -> Result<Status, ControllerError>;

    /// Current state and machine position.
    ///
    /// # Errors
    /// A timeout, a lost link, unreadable bytes.
    fn status(&mut self) -> Result<Status, ControllerError>;

    /// Clears a (non-critical) alarm lock with `$X`.
    ///
    /// # Errors
    /// A critical alarm (needs [`Controller::reset`] first), a timeout, a lost link.
    fn unlock(&mut self) -> Result<(), ControllerError>;

    /// Soft-resets the controller (`0x18`) and waits for its banner. Motion stops; the board
    /// may come back in `Alarm`.
    ///
    /// # Errors
    /// No banner within the timeout, a lost link.
    fn reset(&mut self) -> Result<(), ControllerError>;

    /// What happened on the link since the last call that did not stop an operation
    /// (unreadable lines, resynchronisations), oldest first. The session appends them to
    /// its event log.
    fn take_events(&mut self) -> Vec<ControllerEvent> {
        Vec::new()
    }
}

/// Something the client met and got past: kinds `corrupt-line` (an unparseable line; the
/// detail quotes it), `resync` (a `?` sent to find the line's response again),
/// `response-assumed` (the unreadable line was the response), `stray-response` (an
/// `ok`/`error` with no line pending, skipped).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ControllerEvent {
    pub kind: &'static str,
    pub detail: String,
}

/// What the controller client may do on its own after an alarm.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RecoveryPolicy {
    /// Never send `$X` or a reset unasked: a locked machine makes every move fail with
    /// [`ControllerError::Locked`] until the caller calls `unlock()`/`reset()`.
    #[default]
    Manual,
    /// Send `$X` before a move when the board sits in a (non-critical) `Alarm` state, e.g. the
    /// power-up homing lock. Critical alarms still need an explicit reset.
    Unlock,
    /// Also recover from critical alarms (hard/soft limit) before the *next* command: soft
    /// reset, then re-home when homing is configured, else `$X`. The command that hit the
    /// alarm still fails.
    Reset,
}

/// Time limits for each kind of wait.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timeouts {
    /// For the banner after opening the port or a reset.
    pub banner: Duration,
    /// For the response to a non-motion line and for a status report.
    pub response: Duration,
    /// For one move to finish.
    pub motion: Duration,
    /// For the homing cycle.
    pub homing: Duration,
}

impl Default for Timeouts {
    fn default() -> Self {
        Self {
            banner: Duration::from_secs(3),
            response: Duration::from_secs(2),
            motion: Duration::from_secs(120),
            homing: Duration::from_secs(120),
        }
    }
}

/// Software travel limits of one axis, machine coordinates (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisLimit {
    pub axis: Axis,
    pub min: f64,
    pub max: f64,
}

/// How a [`GrblController`] behaves.
#[derive(Clone, Debug, PartialEq)]
pub struct ControllerOptions {
    pub timeouts: Timeouts,
    pub recovery: RecoveryPolicy,
    /// Run `$H` when connecting.
    pub home_on_start: bool,
    /// Targets outside these are refused before sending. Axes without a limit are refused too,
    /// unless `limits` is empty (no checking at all).
    pub limits: Vec<AxisLimit>,
    /// Interval between `?` polls while waiting for motion; clamped to ≥ 200 ms (≤ 5 Hz).
    pub poll_interval: Duration,
    /// Largest accepted |final − target| per axis (mm); grbl quantises to whole steps.
    pub position_tolerance: f64,
}

impl Default for ControllerOptions {
    fn default() -> Self {
        Self {
            timeouts: Timeouts::default(),
            recovery: RecoveryPolicy::Manual,
            home_on_start: false,
            limits: Vec::new(),
            poll_interval: Duration::from_millis(200),
            position_tolerance: 0.01,
        }
    }
}

/// Everything that can go wrong talking to the controller. Each variant names the port.
#[derive(Debug, thiserror::Error)]
pub enum ControllerError {
    #[error("cannot open serial port {port}{hint}")]
    Open {
        port: String,
        hint: String,
        #[source]
        source: serialport::Error,
    },
    #[error("{port}: no {waiting_for} within {after:?}")]
    Timeout { port: String, waiting_for: String, after: Duration },
    #[error("{port}: {alarm}")]
    Alarm { port: String, alarm: Alarm },
    #[error("{port}: machine is locked in Alarm ({reason}); {hint}")]
    Locked { port: String, reason: String, hint: String },
    #[error("{port}: grbl rejected {command:?} with {error}")]
    Grbl { port: String, command: String, error: GrblError },
    /// The config homes on start but the board has homing off: found before any motion.
    #[error("{port}: the rig config homes on start (home_on_start = true) but homing is disabled on the board ($22=0); fix: send `$22=1` to the board (check the limit switches and $23 first), or set home_on_start = false")]
    HomingDisabled { port: String },
    #[error("{port}: disconnected")]
    Disconnected { port: String },
    #[error("{port}: unreadable bytes from the controller (wrong baud rate or line noise?): {text:?}")]
    Garbage { port: String, text: String },
    #[error("{port}: protocol error: {detail}")]
    Protocol { port: String, detail: String },
    #[error("{port}: {axis} target {target} mm outside the configured range [{min}, {max}] mm; nothing was sent")]
    LimitViolation { port: String, axis: Axis, target: f64, min: f64, max: f64 },
    #[error("{port}: I/O error")]
    Io {
        port: String,
        #[source]
        source: std::io::Error,
    },
}
