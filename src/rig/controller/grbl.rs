//! [`GrblController`]: the grbl 1.1 client over any `Read + Write` transport, and
//! [`SerialController`], the same over a real serial port.
//!
//! Streaming is *send-response*: one line out, then exactly one `ok`/`error:N` back; every
//! other line received meanwhile is a push message (status report, `ALARM:N`, `[MSG:…]`,
//! banner) and updates the client's view of the machine. Motion end is synchronised with
//! `G4 P0`, whose `ok` grbl sends only once the planner is empty, then confirmed by a status
//! report in `Idle`.
//!
//! # Conventions
//! - The transport's `read` must return within a few tens of milliseconds when no data
//!   arrives (`TimedOut`/`WouldBlock`); the client keeps its own deadlines from [`Timeouts`](super::Timeouts).
//!   `Ok(0)`, `BrokenPipe`, `ConnectionReset`, `NotConnected` and `UnexpectedEof` mean the
//!   link is gone ([`ControllerError::Disconnected`]).
//! - `?` is polled at most every 200 ms (grbl recommends ≤ 5 Hz) and **never during homing**
//!   (grbl does not answer it then).
//! - After a critical alarm (`ALARM:1`/`ALARM:2`) grbl answers nothing until a soft reset;
//!   [`Controller::status`] then returns the last known position in `Alarm` without polling.
//!
//! # Quirks
//! - Opening a USB serial port usually resets an Arduino-based board (DTR); its banner arrives
//!   1–2 s later. Boards that do not reset get a soft reset after the banner timeout.
//! - After a homing failure grbl sends `ALARM:N`, `ok`, then a fresh banner: the client waits
//!   for the `ok` so that line counting stays in step.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use super::protocol::{frame, parse_line, Alarm, Axis, Command, MachineState, Message, Motion, Position, Realtime, StatusReport};
use super::{Controller, ControllerError, ControllerEvent, ControllerOptions, RecoveryPolicy, Status};

/// A [`GrblController`] on a serial port.
pub type SerialController = GrblController<Box<dyn serialport::SerialPort>>;

const MIN_POLL: Duration = Duration::from_millis(200);

/// The grbl client. See the module docs for the protocol rules it follows.
pub struct GrblController<T: Read + Write> {
    port: T,
    name: String,
    opts: ControllerOptions,
    rx: Vec<u8>,
    last: Option<Status>,
    last_wco: Option<Position>,
    /// A critical alarm seen and not yet cleared by a reset.
    critical: Option<Alarm>,
    /// The last alarm of any kind (for messages).
    last_alarm: Option<Alarm>,
    /// Status reports received (for tests and diagnostics).
    reports: usize,
    /// Unparseable lines received so far.
    noise_total: usize,
    /// Events not yet taken by [`Controller::take_events`].
    events: Vec<ControllerEvent>,
    /// The last unparseable line (for the error when nothing else arrives).
    last_noise: Option<String>,
}

/// How a request waits for its response.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Wait {
    /// A non-motion line: noise triggers a resync (`?`, wait for a clean report).
    Response,
    /// `G4 P0` after a move: `?` every poll interval; noise triggers a resync.
    Motion,
    /// `$H`: grbl answers no `?` while homing, so noise is only logged.
    Homing,
}

/// After a resync, how long a clean report must stand without the pending response before
/// the unreadable line is taken to have been that response.
const RESYNC_GRACE: Duration = Duration::from_millis(150);
/// Least time between two `?` sent to re-poll after an unreadable report.
const REPOLL: Duration = Duration::from_millis(50);

/// A request waiting for its response (see [`GrblController::request`]).
struct Pending<'a> {
    line: &'a str,
    timeout: Duration,
    deadline: Instant,
    /// Between `?` polls.
    interval: Duration,
    /// Poll `?` while waiting (for motion).
    poll: bool,
    wait: Wait,
    next_poll: Instant,
    /// Messages that arrived meanwhile (reports, pushed messages), in order.
    pushes: Vec<Message>,
    /// A non-critical alarm meanwhile: the line's own `ok`/`error` still follows.
    alarm: Option<Alarm>,
    /// The unreadable-line count when the request was sent.
    noise_before: usize,
    /// `Some(time of a clean report since the last unreadable line)` while resynchronising.
    resync: Option<Option<Instant>>,
}

impl<'a> Pending<'a> {
    fn new(line: &'a str, timeout: Duration, wait: Wait, interval: Duration, noise_before: usize) -> Self {
        let start = Instant::now();
        Self {
            line,
            timeout,
            deadline: start + timeout,
            interval,
            poll: wait == Wait::Motion,
            wait,
            next_poll: start + interval,
            pushes: Vec::new(),
            alarm: None,
            noise_before,
            resync: None,
        }
    }

    /// While resynchronising, a lost report is asked for again like a motion poll.
    fn polling(&self) -> bool {
        (self.poll || self.resync.is_some()) && self.alarm.is_none()
    }

    /// When to stop waiting for the next message.
    fn wake(&self) -> Instant {
        let mut wake = if self.polling() { self.next_poll.min(self.deadline) } else { self.deadline };
        if let Some(Some(clean)) = self.resync {
            wake = wake.min(clean + RESYNC_GRACE);
        }
        wake
    }
}

impl SerialController {
    /// Opens `path` at `baud` (8N1, no flow control) and performs the banner handshake (and
    /// homing when `options.home_on_start`).
    ///
    /// # Errors
    /// [`ControllerError::Open`] naming the path when the port is missing or busy; then as
    /// [`GrblController::connect`].
    pub fn open(path: &str, baud: u32, options: ControllerOptions) -> Result<Self, ControllerError> {
        let port = serialport::new(path, baud).timeout(Duration::from_millis(20)).open().map_err(|source| {
            let hint = match source.kind() {
                serialport::ErrorKind::NoDevice => " (busy: another program, e.g. a serial monitor or ModemManager, has it open)",
                serialport::ErrorKind::Io(io::ErrorKind::NotFound) => " (no such device: is the board plugged in? see /dev/serial/by-id/)",
                serialport::ErrorKind::Io(io::ErrorKind::PermissionDenied) => " (permission denied: is the user in the 'dialout' group?)",
                _ => "",
            };
            ControllerError::Open { port: path.to_string(), hint: hint.to_string(), source }
        })?;
        Self::connect(port, path, options)
    }
}

impl<T: Read + Write> GrblController<T> {
    /// Takes over a connected transport: waits for the banner (soft-resetting once if none
    /// comes), reads the machine state, and homes when configured.
    ///
    /// # Errors
    /// [`ControllerError::Timeout`] when no banner arrives even after a reset; any error of
    /// the initial status request or homing.
    pub fn connect(port: T, name: &str, options: ControllerOptions) -> Result<Self, ControllerError> {
        let mut c = Self {
            port,
            name: name.to_string(),
            opts: options,
            rx: Vec::new(),
            last: None,
            last_wco: None,
            critical: None,
            last_alarm: None,
            reports: 0,
            noise_total: 0,
            events: Vec::new(),
            last_noise: None,
        };
        if !c.wait_banner()? {
            c.write(&[Realtime::SoftReset.byte()])?;
            if !c.wait_banner()? {
                return Err(c.timeout("grbl banner (after open and after a soft reset)", c.opts.timeouts.banner * 2));
            }
        }
        c.status()?;
        if c.opts.home_on_start {
            // before any motion: a board with homing disabled would answer `$H` with error:5
            let settings = c.settings()?;
            if settings.get(&22).is_some_and(|v| *v == 0.0) {
                return Err(ControllerError::HomingDisabled { port: c.name.clone() });
            }
            c.home()?;
        }
        Ok(c)
    }

    /// The board's `$$` settings by number (values as numbers; a value that does not parse
    /// is left out).
    ///
    /// # Errors
    /// As [`GrblController::command`].
    pub fn settings(&mut self) -> Result<std::collections::BTreeMap<u16, f64>, ControllerError> {
        let lines = self.command(&Command::Settings)?;
        Ok(lines
            .into_iter()
            .filter_map(|m| match m {
                Message::Setting { number, value } => value.trim().parse().ok().map(|v| (number, v)),
                _ => None,
            })
            .collect())
    }

    /// The port name or path used in errors.
    pub fn port_name(&self) -> &str {
        &self.name
    }

    /// The options in force.
    pub fn options(&self) -> &ControllerOptions {
        &self.opts
    }

    /// The last status known without asking the board.
    pub fn last_status(&self) -> Option<Status> {
        self.last
    }

    /// Status reports received so far.
    pub fn reports_received(&self) -> usize {
        self.reports
    }

    /// Unparseable lines received so far (each is also a `corrupt-line` event).
    pub fn noise_received(&self) -> usize {
        self.noise_total
    }

    /// Sends one line and waits for its response; returns the push messages received
    /// meanwhile (e.g. the `$N=v` lines of `$$`). No limit checks, no recovery: a raw escape
    /// hatch for setup and diagnostics.
    ///
    /// # Errors
    /// As the response: a grbl error, an alarm, a timeout, a lost link.
    pub fn command(&mut self, cmd: &Command) -> Result<Vec<Message>, ControllerError> {
        let t = self.opts.timeouts.response;
        self.request(&cmd.encode(), t, Wait::Response)
    }

    /// Gives the transport back.
    pub fn into_inner(self) -> T {
        self.port
    }

    fn timeout(&self, waiting_for: &str, after: Duration) -> ControllerError {
        ControllerError::Timeout { port: self.name.clone(), waiting_for: waiting_for.to_string(), after }
    }

    fn io_err(&self, e: io::Error) -> ControllerError {
        match e.kind() {
            io::ErrorKind::BrokenPipe
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::NotConnected
            | io::ErrorKind::UnexpectedEof => ControllerError::Disconnected { port: self.name.clone() },
            _ => ControllerError::Io { port: self.name.clone(), source: e },
        }
    }

    fn write(&mut self, bytes: &[u8]) -> Result<(), ControllerError> {
        self.port.write_all(bytes).and_then(|_| self.port.flush()).map_err(|e| self.io_err(e))
    }

    /// Reads until one full line is buffered or `deadline` passes.
    fn read_line(&mut self, deadline: Instant) -> Result<Option<String>, ControllerError> {
        let mut buf = [0u8; 256];
        loop {
            if let Some(end) = self.rx.iter().position(|&b| b == b'\n') {
                let raw: Vec<u8> = self.rx.drain(..=end).collect();
                // non-UTF-8 bytes (noise, a wrong baud rate) become U+FFFD: the line then
                // parses as `Unknown` and is handled as noise
                let text = String::from_utf8_lossy(&raw).into_owned();
                let line = text.trim_end_matches(['\r', '\n']);
                if line.is_empty() {
                    continue;
                }
                return Ok(Some(line.to_string()));
            }
            if self.rx.len() > 256 {
                // no newline in 256 bytes: not a grbl line (its longest is ~90 bytes)
                let text = String::from_utf8_lossy(&self.rx).to_string();
                self.rx.clear();
                return Ok(Some(text));
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            match self.port.read(&mut buf) {
                Ok(0) => return Err(ControllerError::Disconnected { port: self.name.clone() }),
                Ok(n) => self.rx.extend_from_slice(&buf[..n]),
                Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted) => {}
                Err(e) => return Err(self.io_err(e)),
            }
        }
    }

    /// The next message (push messages already applied to the client's state).
    fn next_message(&mut self, deadline: Instant) -> Result<Option<Message>, ControllerError> {
        let Some(line) = self.read_line(deadline)? else { return Ok(None) };
        let msg = parse_line(&line);
        match &msg {
            Message::Status(r) => self.apply_status(r),
            Message::Alarm(a) => {
                self.last_alarm = Some(*a);
                if a.is_critical() {
                    self.critical = Some(*a);
                }
                if let Some(s) = self.last.as_mut() {
                    s.state = MachineState::Alarm;
                }
            }
            Message::Unknown(_) | Message::MalformedStatus(_) => {
                self.noise_total += 1;
                self.last_noise = Some(line.clone());
                self.event("corrupt-line", format!("{line:?}"));
            }
            _ => {}
        }
        Ok(Some(msg))
    }

    fn event(&mut self, kind: &'static str, detail: String) {
        self.events.push(ControllerEvent { kind, detail });
    }

    /// The error for a wait that ended without anything usable: unreadable lines when some
    /// arrived meanwhile (`noise_before` = the count when the wait began), else a timeout.
    fn nothing_parseable(&mut self, noise_before: usize, waiting_for: &str, after: Duration) -> ControllerError {
        match (&self.last_noise, self.noise_total > noise_before) {
            (Some(text), true) => ControllerError::Garbage { port: self.name.clone(), text: text.clone() },
            _ => self.timeout(waiting_for, after),
        }
    }

    fn apply_status(&mut self, r: &StatusReport) {
        self.reports += 1;
        if let Some(w) = r.wco {
            self.last_wco = Some(w);
        }
        let mpos = r.machine_position(self.last_wco).or(self.last.map(|s| s.mpos)).unwrap_or_default();
        self.last = Some(Status { state: r.state, mpos });
    }

    /// Waits for `Grbl …`; true when seen. Earlier lines (boot noise, a half line) are skipped.
    fn wait_banner(&mut self) -> Result<bool, ControllerError> {
        let deadline = Instant::now() + self.opts.timeouts.banner;
        loop {
            let line = match self.read_line(deadline) {
                Ok(Some(l)) => l,
                Ok(None) => return Ok(false),
                Err(ControllerError::Garbage { .. }) => continue,
                Err(e) => return Err(e),
            };
            if let Message::Banner { .. } = parse_line(&line) {
                // A reset clears grbl's critical lock; a locked board will say so next.
                self.critical = None;
                self.drain_after_banner()?;
                return Ok(true);
            }
        }
    }

    /// Collects the `[MSG:…]` lines that follow a banner without waiting long.
    fn drain_after_banner(&mut self) -> Result<(), ControllerError> {
        let deadline = Instant::now() + Duration::from_millis(50);
        while let Some(m) = self.next_message(deadline)? {
            if let Message::Msg(text) = &m {
                if text.contains("to unlock") {
                    if let Some(s) = self.last.as_mut() {
                        s.state = MachineState::Alarm;
                    }
                }
            }
        }
        Ok(())
    }

    /// Sends `line` and waits up to `timeout` for its `ok`/`error:N`, polling `?` while
    /// waiting for motion.
    ///
    /// An unreadable line meanwhile may have been the response itself. The client then
    /// resynchronises as senders do: it asks for a report (`?`) and waits for a clean one
    /// (for motion: a clean `Idle`). If the response still has not come [`RESYNC_GRACE`]
    /// after that report, the unreadable line was the response: it is taken as `ok` (a
    /// `response-assumed` event; the final position check of a move still guards it). No
    /// received bytes are dropped: lines end at `\n`, so the line after a corrupt one is
    /// whole, and discarding the buffer could throw away the response itself.
    fn request(&mut self, line: &str, timeout: Duration, wait: Wait) -> Result<Vec<Message>, ControllerError> {
        self.write(&frame(line))?;
        let mut p = Pending::new(line, timeout, wait, self.opts.poll_interval.max(MIN_POLL), self.noise_total);
        loop {
            let done = match self.next_message(p.wake())? {
                Some(m) => self.on_pending_message(&mut p, m)?,
                None => self.on_pending_silence(&mut p)?,
            };
            if done {
                break;
            }
        }
        if let Some(a) = p.alarm {
            return Err(ControllerError::Alarm { port: self.name.clone(), alarm: a });
        }
        Ok(p.pushes)
    }

    /// One message while `p` is pending (see [`GrblController::request`]): `true` when it
    /// was the response (`ok`), an error for `error:N`, a critical alarm or a restart.
    fn on_pending_message(&mut self, p: &mut Pending, m: Message) -> Result<bool, ControllerError> {
        let line = p.line;
        match m {
            Message::Ok => return Ok(true),
            Message::Error(error) => {
                return Err(ControllerError::Grbl { port: self.name.clone(), command: line.to_string(), error });
            }
            Message::Alarm(a) => {
                if a.is_critical() {
                    // grbl answers nothing more until a reset.
                    return Err(ControllerError::Alarm { port: self.name.clone(), alarm: a });
                }
                p.alarm = Some(a); // the line's own `ok`/`error` still follows
            }
            Message::Banner { .. } => {
                self.critical = None;
                return Err(ControllerError::Protocol {
                    port: self.name.clone(),
                    detail: format!("controller restarted while {line:?} was pending"),
                });
            }
            Message::Unknown(_) | Message::MalformedStatus(_) => {
                if p.wait != Wait::Homing && p.alarm.is_none() {
                    if p.resync.is_none() {
                        self.event("resync", format!("unreadable line while {line:?} was pending: sent '?', waiting for a clean report"));
                    }
                    p.resync = Some(None);
                    self.write(&[Realtime::StatusQuery.byte()])?;
                    p.next_poll = Instant::now() + p.interval;
                }
            }
            Message::Status(r) => {
                if let Some(clean) = p.resync.as_mut() {
                    if !p.poll || r.state == MachineState::Idle {
                        clean.get_or_insert_with(Instant::now);
                    }
                }
                p.pushes.push(Message::Status(r));
            }
            m => p.pushes.push(m),
        }
        Ok(false)
    }

    /// Nothing arrived before `p`'s wake-up time: `true` when the response is taken as
    /// given after a resync, an error at the deadline, else a poll when one is due.
    fn on_pending_silence(&mut self, p: &mut Pending) -> Result<bool, ControllerError> {
        let line = p.line;
        let now = Instant::now();
        if let Some(Some(clean)) = p.resync {
            if now >= clean + RESYNC_GRACE || now >= p.deadline {
                self.event("response-assumed", format!("no response to {line:?} after a clean report: the unreadable line was taken as its `ok`"));
                return Ok(true);
            }
        }
        if now >= p.deadline {
            if let Some(a) = p.alarm {
                return Err(ControllerError::Alarm { port: self.name.clone(), alarm: a });
            }
            return Err(self.nothing_parseable(p.noise_before, &format!("response to {line:?}"), p.timeout));
        }
        if p.polling() && now >= p.next_poll {
            self.write(&[Realtime::StatusQuery.byte()])?;
            p.next_poll = now + p.interval;
        }
        Ok(false)
    }

    /// Sends `?` and waits for a clean report. An unreadable report is answered with
    /// another `?` (at most every [`REPOLL`]), a report that never comes (lost on the line)
    /// with another `?` after the poll interval; a stray `ok`/`error` (its line was taken
    /// as answered after a resync) is logged and skipped. Fails only when no clean report
    /// arrives within the response timeout.
    fn query(&mut self) -> Result<Status, ControllerError> {
        self.write(&[Realtime::StatusQuery.byte()])?;
        let timeout = self.opts.timeouts.response;
        let mut last_poll = Instant::now();
        let deadline = last_poll + timeout;
        let noise_before = self.noise_total;
        let interval = self.opts.poll_interval.max(MIN_POLL);
        let mut repoll = last_poll + interval;
        loop {
            let wake = repoll.min(deadline);
            match self.next_message(wake)? {
                Some(Message::Status(_)) => return self.last.ok_or_else(|| self.timeout("status report", timeout)),
                Some(Message::Alarm(a)) if a.is_critical() => {
                    return Err(ControllerError::Alarm { port: self.name.clone(), alarm: a });
                }
                Some(m @ (Message::Ok | Message::Error(_))) => {
                    self.event("stray-response", format!("{m:?} received while no line was pending: skipped"));
                }
                Some(Message::Unknown(_) | Message::MalformedStatus(_)) => {
                    repoll = repoll.min(last_poll + REPOLL);
                }
                Some(_) => {}
                None => {
                    let now = Instant::now();
                    if now >= deadline {
                        return Err(self.nothing_parseable(noise_before, "status report", timeout));
                    }
                    if now >= repoll {
                        self.write(&[Realtime::StatusQuery.byte()])?;
                        last_poll = now;
                        repoll = now + interval;
                    }
                }
            }
        }
    }

    fn locked(&self, reason: String, hint: &str) -> ControllerError {
        ControllerError::Locked { port: self.name.clone(), reason, hint: hint.to_string() }
    }

    /// Brings the machine to a state that accepts G-code, as the policy allows.
    fn ensure_ready(&mut self) -> Result<(), ControllerError> {
        if let Some(a) = self.critical {
            if self.opts.recovery != RecoveryPolicy::Reset {
                return Err(self.locked(a.to_string(), "call reset() (and re-home) to continue"));
            }
            self.reset()?;
            if self.opts.home_on_start {
                self.home()?;
            }
        }
        let s = self.query()?;
        match s.state {
            MachineState::Idle => Ok(()),
            MachineState::Alarm => {
                if self.opts.recovery == RecoveryPolicy::Manual {
                    let reason = self.last_alarm.map_or_else(|| "homing lock after power-up or reset".to_string(), |a| a.to_string());
                    return Err(self.locked(reason, "home, or call unlock(), or set recovery = \"unlock\""));
                }
                self.unlock()
            }
            other => Err(ControllerError::Protocol { port: self.name.clone(), detail: format!("machine is busy ({other}); expected Idle") }),
        }
    }

    /// Refuses targets outside the configured limits (nothing is sent).
    fn check_targets(&self, targets: &[(Axis, f64)]) -> Result<(), ControllerError> {
        if targets.is_empty() {
            return Err(ControllerError::Protocol { port: self.name.clone(), detail: "move_to with no axes".into() });
        }
        for (i, &(axis, target)) in targets.iter().enumerate() {
            if targets[..i].iter().any(|(a, _)| *a == axis) {
                return Err(ControllerError::Protocol { port: self.name.clone(), detail: format!("axis {axis} given twice") });
            }
            if self.opts.limits.is_empty() && target.is_finite() {
                continue;
            }
            let (min, max) = self.opts.limits.iter().find(|l| l.axis == axis).map_or((f64::NAN, f64::NAN), |l| (l.min, l.max));
            if !(target.is_finite() && target >= min && target <= max) {
                return Err(ControllerError::LimitViolation { port: self.name.clone(), axis, target, min, max });
            }
        }
        Ok(())
    }
}

impl<T: Read + Write> Controller for GrblController<T> {
    fn home(&mut self) -> Result<Status, ControllerError> {
        if let Some(a) = self.critical {
            if self.opts.recovery != RecoveryPolicy::Reset {
                return Err(self.locked(a.to_string(), "call reset() before homing"));
            }
            self.reset()?;
        }
        let t = self.opts.timeouts.homing;
        // No `?` while homing: grbl would not answer.
        self.request(&Command::Home.encode(), t, Wait::Homing)?;
        self.last_alarm = None;
        self.query()
    }

    fn move_to(&mut self, targets: &[(Axis, f64)]) -> Result<Status, ControllerError> {
        self.check_targets(targets)?;
        self.ensure_ready()?;
        let line = Command::MoveMachine { motion: Motion::Rapid, targets: targets.to_vec() }.encode();
        let response = self.opts.timeouts.response;
        self.request(&line, response, Wait::Response)?;
        let motion = self.opts.timeouts.motion;
        self.request(&Command::Dwell(0.0).encode(), motion, Wait::Motion)?;
        // The planner is empty; grbl may still report Run for a moment.
        let deadline = Instant::now() + response;
        let status = loop {
            let s = self.query()?;
            if s.state == MachineState::Idle {
                break s;
            }
            if Instant::now() >= deadline {
                return Err(self.timeout("Idle state after motion", response));
            }
            std::thread::sleep(MIN_POLL);
        };
        // A report garbled into another valid number (a dropped digit) cannot be told from
        // a real one; a disagreeing final position is asked again before it counts.
        let mut status = status;
        for attempt in 0.. {
            let off = targets.iter().find(|&&(axis, target)| (status.mpos.get(axis) - target).abs() > self.opts.position_tolerance);
            let Some(&(axis, target)) = off else { break };
            if attempt == 2 {
                let got = status.mpos.get(axis);
                return Err(ControllerError::Protocol { port: self.name.clone(), detail: format!("{axis} ended at {got:.3} mm, target {target:.3} mm") });
            }
            std::thread::sleep(REPOLL);
            status = self.query()?;
        }
        Ok(status)
    }

    fn status(&mut self) -> Result<Status, ControllerError> {
        if self.critical.is_some() {
            let mpos = self.last.map(|s| s.mpos).unwrap_or_default();
            return Ok(Status { state: MachineState::Alarm, mpos });
        }
        self.query()
    }

    fn unlock(&mut self) -> Result<(), ControllerError> {
        if let Some(a) = self.critical {
            return Err(self.locked(a.to_string(), "a critical alarm needs reset() before unlock()"));
        }
        let t = self.opts.timeouts.response;
        self.request(&Command::Unlock.encode(), t, Wait::Response)?;
        self.last_alarm = None;
        if let Some(s) = self.last.as_mut() {
            s.state = MachineState::Idle;
        }
        Ok(())
    }

    fn take_events(&mut self) -> Vec<ControllerEvent> {
        std::mem::take(&mut self.events)
    }

    fn reset(&mut self) -> Result<(), ControllerError> {
        self.rx.clear();
        self.write(&[Realtime::SoftReset.byte()])?;
        if !self.wait_banner()? {
            let t = self.opts.timeouts.banner;
            return Err(self.timeout("grbl banner after a soft reset", t));
        }
        self.critical = None;
        self.query().map(|_| ())
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::super::sim::{spawn_pty, SimHandle, SimOptions};
    use super::super::{AxisLimit, Timeouts};
    use super::*;
    use std::sync::atomic::Ordering;

    fn quick_opts() -> ControllerOptions {
        ControllerOptions {
            timeouts: Timeouts {
                banner: Duration::from_millis(500),
                response: Duration::from_millis(400),
                motion: Duration::from_secs(5),
                homing: Duration::from_secs(5),
            },
            limits: vec![
                AxisLimit { axis: Axis::X, min: -150.0, max: 0.0 },
                AxisLimit { axis: Axis::Y, min: -150.0, max: 0.0 },
                AxisLimit { axis: Axis::Z, min: -20.0, max: 0.0 },
            ],
            ..ControllerOptions::default()
        }
    }

    fn rig(sim: SimOptions, opts: ControllerOptions) -> (SimHandle, SerialController) {
        let (h, path) = spawn_pty(sim).unwrap();
        let c = SerialController::open(&path, 115_200, opts).unwrap();
        (h, c)
    }

    #[test]
    fn banner_handshake_and_status() {
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        let s = c.status().unwrap();
        assert_eq!(s, Status { state: MachineState::Idle, mpos: Position::ZERO });
        let info = c.command(&Command::BuildInfo).unwrap();
        assert_eq!(info, vec![Message::Version("1.1h.20190830:".into()), Message::Options("V,15,128".into())]);
        let dump = c.command(&Command::Settings).unwrap();
        assert!(dump.contains(&Message::Setting { number: 110, value: "60000.000".into() }));
        drop(h);
    }

    #[test]
    fn moves_end_at_target_with_plausible_duration() {
        // 100 mm/s rapids, 1000 mm/s² accel: 30 mm takes 30/100 + 100/1000 = 0.4 s.
        let sim = SimOptions::default().with(110, 6000.0).with(120, 1000.0).with(112, 6000.0).with(122, 1000.0);
        let (h, mut c) = rig(sim, quick_opts());
        let t0 = Instant::now();
        let s = c.move_to(&[(Axis::X, -30.0)]).unwrap();
        let dt = t0.elapsed().as_secs_f64();
        assert_eq!(s.state, MachineState::Idle);
        assert_eq!(s.mpos, Position([-30.0, 0.0, 0.0]));
        assert!((0.38..1.2).contains(&dt), "move took {dt} s");
        assert_eq!(h.state().mpos, Position([-30.0, 0.0, 0.0]));
        let s = c.move_to(&[(Axis::Z, -2.5), (Axis::X, -10.0)]).unwrap();
        assert_eq!(s.mpos, Position([-10.0, 0.0, -2.5]));
        let lines = h.state().received_lines.clone();
        assert!(lines.contains(&"G53G0X-30.000".to_string()), "{lines:?}");
        assert!(lines.contains(&"G4P0".to_string()));
        // G4 sync: every move was followed by a dwell before the next move.
        let moves: Vec<usize> = lines.iter().enumerate().filter(|(_, l)| l.starts_with("G53")).map(|(i, _)| i).collect();
        for i in moves {
            assert_eq!(lines[i + 1], "G4P0");
        }
    }

    #[test]
    fn homing_sends_no_status_queries_while_homing() {
        let sim = SimOptions::fast().with(22, 1.0).with(27, 1.0);
        let (h, path) = spawn_pty(sim).unwrap();
        let opts = ControllerOptions { home_on_start: true, ..quick_opts() };
        let mut c = SerialController::open(&path, 115_200, opts).unwrap();
        let s = c.status().unwrap();
        assert_eq!(s, Status { state: MachineState::Idle, mpos: Position([-1.0; 3]) });
        let st = h.state();
        assert!(st.homed);
        assert!(!st.realtime_received.iter().any(|&(b, s)| b == b'?' && s == MachineState::Home), "{:?}", st.realtime_received);
    }

    #[test]
    fn power_up_lock_follows_the_policy() {
        let sim = SimOptions::fast().with(22, 1.0);
        let (h, path) = spawn_pty(sim.clone()).unwrap();
        let mut c = SerialController::open(&path, 115_200, quick_opts()).unwrap();
        assert_eq!(c.status().unwrap().state, MachineState::Alarm);
        let e = c.move_to(&[(Axis::X, -1.0)]).unwrap_err();
        assert!(matches!(e, ControllerError::Locked { .. }), "{e}");
        assert!(!h.state().received_lines.iter().any(|l| l == "$X"), "manual policy must not unlock");
        c.unlock().unwrap();
        c.move_to(&[(Axis::X, -1.0)]).unwrap();
        drop((c, h));

        let (h, path) = spawn_pty(sim).unwrap();
        let opts = ControllerOptions { recovery: RecoveryPolicy::Unlock, ..quick_opts() };
        let mut c = SerialController::open(&path, 115_200, opts).unwrap();
        assert_eq!(c.move_to(&[(Axis::Y, -2.0)]).unwrap().mpos, Position([0.0, -2.0, 0.0]));
        assert!(h.state().received_lines.iter().any(|l| l == "$X"));
    }

    #[test]
    fn soft_limit_precheck_sends_nothing() {
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        let counts = || {
            let st = h.state();
            (st.received_lines.len(), st.realtime_received.len())
        };
        // let any status poll still in flight from the handshake land before the baseline
        std::thread::sleep(Duration::from_millis(150));
        let before = counts();
        for bad in [(Axis::Z, -25.0), (Axis::X, 0.5), (Axis::Y, f64::NAN)] {
            let e = c.move_to(&[bad]).unwrap_err();
            assert!(matches!(e, ControllerError::LimitViolation { axis, .. } if axis == bad.0), "{e}");
        }
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(counts(), before);
        let msg = c.move_to(&[(Axis::Z, -25.0)]).unwrap_err().to_string();
        assert!(msg.contains("/dev/pts/") && msg.contains("Z") && msg.contains("-25") && msg.contains("nothing was sent"), "{msg}");
    }

    #[test]
    fn firmware_soft_limit_alarm_locks_until_reset_policy() {
        // The firmware's travel (10 mm) is tighter than the client's limits (150 mm).
        let sim = SimOptions::fast().with(22, 1.0).with(20, 1.0).with(130, 10.0);
        let (h, path) = spawn_pty(sim.clone()).unwrap();
        let opts = ControllerOptions { recovery: RecoveryPolicy::Unlock, ..quick_opts() };
        let mut c = SerialController::open(&path, 115_200, opts).unwrap();
        let t0 = Instant::now();
        let e = c.move_to(&[(Axis::X, -20.0)]).unwrap_err();
        assert!(matches!(e, ControllerError::Alarm { alarm: Alarm::SoftLimit, .. }), "{e}");
        assert!(t0.elapsed() < Duration::from_millis(400));
        assert_eq!(c.status().unwrap().state, MachineState::Alarm);
        let e = c.move_to(&[(Axis::X, -1.0)]).unwrap_err();
        assert!(matches!(e, ControllerError::Locked { .. }), "{e}");
        assert!(matches!(c.unlock().unwrap_err(), ControllerError::Locked { .. }));
        c.reset().unwrap();
        c.unlock().unwrap();
        assert_eq!(c.move_to(&[(Axis::X, -1.0)]).unwrap().mpos.get(Axis::X), -1.0);
        drop((c, h));

        // With the reset policy the *next* command recovers on its own.
        let (_h, path) = spawn_pty(sim).unwrap();
        let opts = ControllerOptions { recovery: RecoveryPolicy::Reset, ..quick_opts() };
        let mut c = SerialController::open(&path, 115_200, opts).unwrap();
        assert!(matches!(c.move_to(&[(Axis::X, -20.0)]).unwrap_err(), ControllerError::Alarm { alarm: Alarm::SoftLimit, .. }));
        assert_eq!(c.move_to(&[(Axis::X, -3.0)]).unwrap().mpos.get(Axis::X), -3.0);
    }

    #[test]
    fn hard_limit_during_move_is_reported_fast() {
        let sim = SimOptions::default().with(110, 600.0); // slow X: 10 mm/s
        let (h, mut c) = rig(sim, quick_opts());
        h.faults.hard_limit_on_move.store(true, Ordering::SeqCst);
        let t0 = Instant::now();
        let e = c.move_to(&[(Axis::X, -50.0)]).unwrap_err();
        assert!(matches!(e, ControllerError::Alarm { alarm: Alarm::HardLimit, .. }), "{e}");
        assert!(t0.elapsed() < Duration::from_millis(500));
        assert!(matches!(c.move_to(&[(Axis::X, -1.0)]).unwrap_err(), ControllerError::Locked { .. }));
        assert!(h.state().critical_alarm);
    }

    #[test]
    fn silent_controller_times_out() {
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        h.faults.silent.store(true, Ordering::SeqCst);
        let t0 = Instant::now();
        let e = c.move_to(&[(Axis::X, -1.0)]).unwrap_err();
        assert!(matches!(e, ControllerError::Timeout { .. }), "{e}");
        let dt = t0.elapsed();
        assert!(dt >= Duration::from_millis(400) && dt < Duration::from_millis(900), "{dt:?}");
        assert!(e.to_string().contains("status report"), "{e}");
    }

    #[test]
    fn garbage_is_a_typed_error() {
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        h.faults.garbage.store(true, Ordering::SeqCst);
        let e = c.status().unwrap_err();
        assert!(matches!(e, ControllerError::Garbage { .. }), "{e}");
    }

    #[test]
    fn garbled_status_reports_are_noise_not_the_end() {
        // the line that ended a real calibration run is logged and followed by another poll
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        let real = "<Run|MPos:-54.056,0.000,-8.000|FS:50,,0|Pn:PXYZRHS>";
        assert!(matches!(parse_line(real), Message::MalformedStatus(_)));
        // 10 %: twenty moves all end where asked, every corrupt line is an event
        h.faults.corrupt_reports_ppm.store(100_000, Ordering::SeqCst);
        for i in 1..=20 {
            let x = -(i as f64);
            assert_eq!(c.move_to(&[(Axis::X, x), (Axis::Z, x / 4.0)]).unwrap().mpos, Position([x, 0.0, x / 4.0]));
        }
        let corrupted = h.state().reports_corrupted;
        let events = c.take_events();
        let noise = events.iter().filter(|e| e.kind == "corrupt-line").count();
        // the first report drawn is corrupted (see the sim's seed); run-on lines can merge two
        assert!(corrupted >= 1 && noise >= 1 && noise <= corrupted, "{corrupted} corrupted, {noise} logged: {events:?}");
        assert_eq!(noise, c.noise_received());
        assert!(c.take_events().is_empty(), "events are taken once");
        // every report garbled: no clean report within the response timeout is a typed error,
        // after re-polls (not after the first bad line)
        h.faults.corrupt_reports_ppm.store(1_000_000, Ordering::SeqCst);
        let t0 = Instant::now();
        let e = c.status().unwrap_err();
        assert!(matches!(e, ControllerError::Garbage { .. }), "{e}");
        assert!(t0.elapsed() >= Duration::from_millis(400), "{:?}", t0.elapsed());
        assert!(c.take_events().iter().filter(|e| e.kind == "corrupt-line").count() >= 2);
        h.faults.corrupt_reports_ppm.store(0, Ordering::SeqCst);
        assert_eq!(c.status().unwrap().mpos, Position([-20.0, 0.0, -5.0]));
    }

    #[test]
    fn a_response_lost_in_noise_is_resynchronised() {
        // a transport that swallows the first `ok` into an unreadable line
        struct Swallow {
            inner: Box<dyn serialport::SerialPort>,
            armed: bool,
            pending: Vec<u8>,
        }
        impl Read for Swallow {
            fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
                let mut tmp = [0u8; 256];
                let n = self.inner.read(&mut tmp)?;
                self.pending.extend_from_slice(&tmp[..n]);
                if self.armed {
                    if let Some(i) = self.pending.windows(4).position(|w| w == b"ok\r\n") {
                        self.pending.splice(i..i + 2, b"o\xFFk".iter().copied());
                        self.armed = false;
                    }
                }
                let m = self.pending.len().min(buf.len());
                buf[..m].copy_from_slice(&self.pending[..m]);
                self.pending.drain(..m);
                Ok(m)
            }
        }
        impl Write for Swallow {
            fn write(&mut self, b: &[u8]) -> io::Result<usize> {
                self.inner.write(b)
            }
            fn flush(&mut self) -> io::Result<()> {
                self.inner.flush()
            }
        }
        let (h, path) = spawn_pty(SimOptions::fast()).unwrap();
        let port = serialport::new(&path, 115_200).timeout(Duration::from_millis(20)).open().unwrap();
        let mut c = GrblController::connect(Swallow { inner: port, armed: false, pending: Vec::new() }, &path, quick_opts()).unwrap();
        c.port.armed = true;
        let s = c.move_to(&[(Axis::X, -3.0)]).unwrap();
        assert_eq!(s.mpos, Position([-3.0, 0.0, 0.0]));
        let kinds: Vec<&str> = c.take_events().iter().map(|e| e.kind).collect();
        assert_eq!(kinds, ["corrupt-line", "resync", "response-assumed"]);
        // line counting stays in step: the next move gets its own responses
        assert_eq!(c.move_to(&[(Axis::X, -4.0)]).unwrap().mpos, Position([-4.0, 0.0, 0.0]));
        assert!(c.take_events().is_empty());
        assert_eq!(h.state().mpos, Position([-4.0, 0.0, 0.0]));
    }

    #[test]
    fn disconnect_is_a_typed_error() {
        let (h, mut c) = rig(SimOptions::fast(), quick_opts());
        h.faults.disconnect.store(true, Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(30));
        let t0 = Instant::now();
        let e = c.status().unwrap_err();
        assert!(matches!(e, ControllerError::Disconnected { .. }), "{e}");
        assert!(t0.elapsed() < Duration::from_millis(450));
    }

    #[test]
    fn missing_and_busy_ports_name_the_path() {
        let e = SerialController::open("/dev/does-not-exist-lensrig", 115_200, quick_opts()).err().unwrap();
        let msg = e.to_string();
        assert!(matches!(e, ControllerError::Open { .. }));
        assert!(msg.contains("/dev/does-not-exist-lensrig") && msg.contains("no such device"), "{msg}");
        let (_h, path) = spawn_pty(SimOptions::fast()).unwrap();
        let _first = SerialController::open(&path, 115_200, quick_opts()).unwrap();
        let e = SerialController::open(&path, 115_200, quick_opts()).err().unwrap();
        let msg = e.to_string();
        assert!(msg.contains(&path) && msg.contains("busy"), "{msg}");
    }

    #[test]
    fn homing_without_switches_is_a_clear_alarm() {
        let sim = SimOptions::fast().with(22, 1.0).with(130, 20.0).with(131, 20.0).with(132, 20.0);
        let (h, path) = spawn_pty(sim).unwrap();
        h.faults.homing_switch_missing.store(true, Ordering::SeqCst);
        let mut c = SerialController::open(&path, 115_200, quick_opts()).unwrap();
        let e = c.home().unwrap_err();
        assert!(matches!(e, ControllerError::Alarm { alarm: Alarm::HomingFailApproach, .. }), "{e}");
        let msg = e.to_string();
        assert!(msg.contains(&path) && msg.contains("ALARM:9") && msg.contains("limit switch"), "{msg}");
        assert!(!h.state().realtime_received.iter().any(|&(b, s)| b == b'?' && s == MachineState::Home));
    }

    #[test]
    fn first_boot_with_a_blank_eeprom_connects() {
        let (_h, path) = spawn_pty(SimOptions { blank_eeprom: true, ..SimOptions::fast() }).unwrap();
        let mut c = SerialController::open(&path, 115_200, quick_opts()).unwrap();
        assert_eq!(c.status().unwrap().state, MachineState::Idle);
        assert_eq!(c.move_to(&[(Axis::X, -1.0)]).unwrap().mpos.get(Axis::X), -1.0);
    }

    #[test]
    fn no_banner_triggers_one_soft_reset() {
        let (h, path) = spawn_pty(SimOptions::fast()).unwrap();
        // Consume the power-up banner with a first client, then connect a second one.
        drop(SerialController::open(&path, 115_200, quick_opts()).unwrap());
        let mut c = SerialController::open(&path, 115_200, quick_opts()).unwrap();
        assert_eq!(c.status().unwrap().state, MachineState::Idle);
        assert!(h.state().realtime_received.iter().any(|&(b, _)| b == 0x18));
    }
}
