//! A simulated grbl 1.1h firmware that speaks the real wire bytes.
//!
//! [`Firmware`] is the pure core: feed it received bytes and the current time, call
//! [`Firmware::tick`], take the bytes it would transmit. [`spawn`] runs it on a thread over any
//! `Read + Write` (a serial port, a pty master), and [`spawn_pty`] creates a pseudo-terminal
//! pair so a client can open the slave by path through `serialport`, exactly as it would open
//! real hardware.
//!
//! # What is simulated (matching `GRBL.md`)
//! - Banner `\r\nGrbl 1.1h ['$' for help]\r\n` on start and after `0x18`; a soft reset flushes
//!   the receive buffer; with `$22=1` the firmware powers up in `Alarm` and prints
//!   `[MSG:'$H'|'$X' to unlock]`.
//! - Send-response: exactly one `ok`/`error:N` per line; `\r\n` line endings; lines longer than
//!   79 characters (after grbl's whitespace stripping) give `error:11`.
//! - `$$` (real defaults), `$N=v` (with error:3/2/4/6/10 checks), `$I`, `$G`, `$#`, `$X`, `$H`,
//!   `$J=` jogs (error:15 outside travel with soft limits on, `0x85` cancel).
//! - `G0`/`G1`/`G4`/`G53`/`G90`/`G91` (+ no-op `G17 G21 G54 G94 M5 M9 S T N`) with motion in
//!   real time: each block runs a trapezoid profile limited by `$110..112` (mm/min) and
//!   `$120..122` (mm/s²); `?` reports `Run` and an advancing `MPos`; `G4 P…` answers `ok` only
//!   once the planner is empty. Planner of 15 blocks: a full planner delays the `ok`.
//! - Homing (`$H`): `error:5` when `$22=0`; otherwise state `Home`, **no answer to `?`**,
//!   duration from `$24`/`$25`/`$26`/`$27` and [`SimOptions::home_seek_mm`]; ends at
//!   `MPos = −$27` on every axis (machine space `[−$13x, 0]`).
//! - Soft limits (`$20=1`): a target outside `[−$13x, 0]` raises `ALARM:2` +
//!   `[MSG:Reset to continue]`, after which nothing (not even `?`) is answered until `0x18`;
//!   then `Alarm` until `$X`/`$H`. A reset while moving raises `ALARM:3` (`ALARM:6` while homing).
//! - Feed hold `!` (`Hold:1` while decelerating, then `Hold:0`) and resume `~`.
//!
//! - Check mode `$C` (`[MSG:Enabled]`; G-code is parsed and limit-checked but nothing moves;
//!   a soft-limit target still raises `ALARM:2`; `$C` again prints `[MSG:Disabled]`, `ok` and
//!   resets). `$$` is refused (`error:8`) only in `Run`/`Hold`; `$#`, `$I`, `$H` and setting
//!   writes need `Idle` or `Alarm` (`error:8`, checked before `error:5`); `$X` outside `Alarm`
//!   has no effect and answers `ok`.
//! - [`SimOptions::blank_eeprom`]: first boot prints `error:7` and the `$$` dump before the
//!   banner.
//!
//! # Not simulated
//! Inches `G20`, arcs, probing, spindle/coolant, overrides, the EEPROM startup lines `$N`,
//! `$RST`, `$SLP`, the safety door, the input-pin field `Pn:` (no switch is ever pressed while
//! a report can be read), the serial timing of 115200 baud.
//!
//! # Layout
//! This file holds the board's state ([`Firmware`]), its start-up and resets; the rest by
//! concern: `input` (real-time bytes, the RX buffer, grbl's line layer), `system` (`$`
//! commands and settings), `gcode` (parsing and executing blocks), `motion` (planner,
//! trapezoid integration, homing, [`Firmware::tick`]), `report` (status reports and their
//! corruption fault) and `transport` (the firmware thread over a port or a pty).
//!
//! # Faults
//! [`Faults`] can be flipped by a test while the firmware runs: stop answering (as if hung),
//! turn every transmitted line into noise, drop the port (disconnect), raise a hard-limit
//! `ALARM:1` during the next (or current) move, unplug the limit switches (homing ends in
//! `ALARM:9`, then `ok`, banner and `Alarm`).

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU32};
use std::time::{Duration, Instant};

use super::protocol::{Alarm, GrblError, MachineState, Position, BANNER};

mod gcode;
mod input;
mod motion;
mod report;
mod system;
mod transport;

pub use transport::{spawn, SimHandle, SimObserver};
#[cfg(unix)]
pub use transport::spawn_pty;

/// Faults a test can inject while the firmware runs (all default off).
#[derive(Debug, Default)]
pub struct Faults {
    /// Ignore all input and transmit nothing (a hung board, a cable with only TX broken).
    pub silent: AtomicBool,
    /// Replace every transmitted line with non-UTF-8 noise (wrong baud rate, EMI).
    pub garbage: AtomicBool,
    /// Drop the port and end the firmware thread (USB cable pulled).
    pub disconnect: AtomicBool,
    /// One-shot: trigger a hard limit (`ALARM:1`) as soon as the machine is in `Run` or `Jog`.
    pub hard_limit_on_move: AtomicBool,
    /// The limit switches never trigger (unplugged): a homing cycle searches 1.5 × max
    /// travel, then fails with `ALARM:9`.
    pub homing_switch_missing: AtomicBool,
    /// Corrupt this fraction of status reports, in parts per million (10 000 = 1 %), as a
    /// noisy line does: a dropped or doubled delimiter (`FS:50,,0`), a number character
    /// replaced by noise, or the report run into the line around it (interleaved output,
    /// which can swallow an `ok`). Every corruption makes the line unparseable; the count is
    /// [`SimState::reports_corrupted`].
    pub corrupt_reports_ppm: AtomicU32,
}

/// What the test harness can observe of the firmware (the truth, not what was reported).
#[derive(Clone, Debug)]
pub struct SimState {
    pub state: MachineState,
    /// The true machine position.
    pub mpos: Position,
    /// Waiting for `0x18` after a critical alarm.
    pub critical_alarm: bool,
    pub homed: bool,
    pub settings: BTreeMap<u16, f64>,
    /// Every line executed, after whitespace stripping and upper-casing.
    pub received_lines: Vec<String>,
    /// Every real-time byte received, with the state it arrived in.
    pub realtime_received: Vec<(u8, MachineState)>,
    /// Status reports transmitted.
    pub status_reports_sent: usize,
    /// Of those, corrupted by [`Faults::corrupt_reports_ppm`].
    pub reports_corrupted: usize,
}

/// Start-up configuration of the simulated board.
#[derive(Clone, Debug)]
pub struct SimOptions {
    /// Settings stored in "EEPROM" before power-up, applied over the grbl defaults.
    pub settings: Vec<(u16, f64)>,
    /// Distance each axis travels before its switch triggers during homing (mm).
    pub home_seek_mm: f64,
    /// Initial true machine position.
    pub initial_position: Position,
    /// First boot with a blank EEPROM: `error:7` and the `$$` dump before the banner.
    pub blank_eeprom: bool,
}

impl Default for SimOptions {
    fn default() -> Self {
        Self { settings: Vec::new(), home_seek_mm: 5.0, initial_position: Position::ZERO, blank_eeprom: false }
    }
}

impl SimOptions {
    /// A quick machine for tests: 60 000 mm/min rapids, 20 000 mm/s² accel, fast homing.
    pub fn fast() -> Self {
        let mut s = Self::default();
        for n in [110, 111, 112] {
            s.settings.push((n, 60_000.0));
        }
        for n in [120, 121, 122] {
            s.settings.push((n, 20_000.0));
        }
        s.settings.extend([(24, 6000.0), (25, 6000.0), (26, 1.0)]);
        s
    }

    /// Adds (or overrides) a setting.
    pub fn with(mut self, number: u16, value: f64) -> Self {
        self.settings.push((number, value));
        self
    }
}

/// The grbl 1.1h defaults (`$$` on a fresh EEPROM, from `GRBL.md`).
pub fn default_settings() -> BTreeMap<u16, f64> {
    let mut m = BTreeMap::new();
    for (n, v) in [
        (0, 10.0),
        (1, 25.0),
        (2, 0.0),
        (3, 0.0),
        (4, 0.0),
        (5, 0.0),
        (6, 0.0),
        (10, 1.0),
        (11, 0.010),
        (12, 0.002),
        (13, 0.0),
        (20, 0.0),
        (21, 0.0),
        (22, 0.0),
        (23, 0.0),
        (24, 25.0),
        (25, 500.0),
        (26, 250.0),
        (27, 1.0),
        (30, 1000.0),
        (31, 0.0),
        (32, 0.0),
    ] {
        m.insert(n, v);
    }
    for base in [100, 110, 120, 130] {
        let v = match base {
            100 => 250.0,
            110 => 500.0,
            120 => 10.0,
            _ => 200.0,
        };
        for i in 0..3 {
            m.insert(base + i, v);
        }
    }
    m
}

const PLANNER_BLOCKS: usize = 15;
const EPS: f64 = 1e-9;

#[derive(Clone, Debug)]
struct Block {
    target: [f64; 3],
    /// mm/min requested (G1/jog) or `None` for rapids.
    feed: Option<f64>,
}

#[derive(Clone, Debug)]
struct Active {
    start: [f64; 3],
    unit: [f64; 3],
    length: f64,
    s: f64,
    v: f64,
    vmax: f64,
    accel: f64,
}

#[derive(Clone, Debug)]
struct Homing {
    start: Instant,
    duration: Duration,
    from: [f64; 3],
    to: [f64; 3],
}

#[derive(Clone, Debug)]
enum Pending {
    /// A block waiting for a free planner slot; `ok` when queued.
    Planner(Block, bool),
    /// `G4 P…`: wait for motion end, then `secs`, then `ok`.
    Dwell { secs: f64, until: Option<Instant> },
    /// `$H` in progress; `ok` at the end.
    Homing,
}

/// The firmware core: bytes and time in, bytes out.
pub struct Firmware {
    settings: BTreeMap<u16, f64>,
    state: MachineState,
    critical: bool,
    homed: bool,
    pos: [f64; 3],
    planned: [f64; 3],
    absolute: bool,
    motion_g1: bool,
    feed: f64,
    queue: VecDeque<Block>,
    active: Option<Active>,
    jogging: bool,
    hold: bool,
    jog_cancel: bool,
    rx: VecDeque<u8>,
    pending: Option<Pending>,
    homing: Option<Homing>,
    status_requested: bool,
    wco_counter: u32,
    ovr_counter: u32,
    home_seek_mm: f64,
    last_tick: Option<Instant>,
    out: Vec<u8>,
    log_lines: Vec<String>,
    log_realtime: Vec<(u8, MachineState)>,
    reports_sent: usize,
    reports_corrupted: usize,
    /// xorshift state of the line-noise fault.
    noise_rng: u64,
    /// [`Faults::homing_switch_missing`], as of the last tick.
    switches_missing: bool,
}

impl Firmware {
    /// Powers up: banner, and the unlock message when homing locks the machine.
    pub fn new(options: &SimOptions) -> Self {
        let mut settings = default_settings();
        for &(n, v) in &options.settings {
            settings.insert(n, v);
        }
        let mut fw = Self {
            settings,
            state: MachineState::Idle,
            critical: false,
            homed: false,
            pos: options.initial_position.0,
            planned: options.initial_position.0,
            absolute: true,
            motion_g1: false,
            feed: 0.0,
            queue: VecDeque::new(),
            active: None,
            jogging: false,
            hold: false,
            jog_cancel: false,
            rx: VecDeque::new(),
            pending: None,
            homing: None,
            status_requested: false,
            wco_counter: 0,
            ovr_counter: 0,
            home_seek_mm: options.home_seek_mm,
            last_tick: None,
            out: Vec::new(),
            log_lines: Vec::new(),
            log_realtime: Vec::new(),
            reports_sent: 0,
            reports_corrupted: 0,
            // chosen so that the first report drawn at a rate ≥ 1 % is corrupted: a test meets one
            noise_rng: 0x9E37_79B9_7F4A_7C0A,
            switches_missing: false,
        };
        if fw.setting(22) != 0.0 {
            fw.state = MachineState::Alarm;
        }
        if options.blank_eeprom {
            // settings_init(): report the read failure, restore defaults, dump them (no `ok`).
            fw.error(GrblError::EepromReadFail);
            fw.settings_dump();
        }
        fw.boot_messages();
        fw
    }

    fn setting(&self, n: u16) -> f64 {
        self.settings.get(&n).copied().unwrap_or(0.0)
    }

    fn boot_messages(&mut self) {
        self.out.extend_from_slice(BANNER.as_bytes());
        if self.state == MachineState::Alarm {
            self.line("[MSG:'$H'|'$X' to unlock]");
        }
    }

    fn line(&mut self, s: &str) {
        self.out.extend_from_slice(s.as_bytes());
        self.out.extend_from_slice(b"\r\n");
    }

    fn ok(&mut self) {
        self.line("ok");
    }

    fn error(&mut self, e: GrblError) {
        self.line(&format!("error:{}", e.code()));
    }

    /// Bytes the firmware would transmit since the last call.
    pub fn take_output(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.out)
    }

    /// The true machine position.
    pub fn position(&self) -> Position {
        Position(self.pos)
    }

    pub fn state(&self) -> MachineState {
        self.state
    }

    /// `0x18`: `ALARM:6` while homing, `ALARM:3` while moving; motion, buffers and modal state
    /// are cleared, then the banner.
    fn soft_reset(&mut self) {
        let moving = self.active.is_some() || !self.queue.is_empty();
        if self.homing.is_some() {
            self.line("ALARM:6");
            self.state = MachineState::Alarm;
        } else if moving && !self.critical {
            self.line("ALARM:3");
            self.state = MachineState::Alarm;
        }
        if self.critical {
            self.state = MachineState::Alarm;
            self.critical = false;
        }
        if !matches!(self.state, MachineState::Alarm) {
            self.state = MachineState::Idle;
        }
        self.rx.clear();
        self.abort_motion();
        self.jog_cancel = false;
        self.absolute = true;
        self.motion_g1 = false;
        self.feed = 0.0;
        self.wco_counter = 0;
        self.ovr_counter = 0;
        self.boot_messages();
    }

    /// A critical alarm (soft or hard limit): motion stops and nothing is answered until
    /// `0x18`.
    fn critical_alarm(&mut self, alarm: Alarm) {
        self.abort_motion();
        self.state = MachineState::Alarm;
        self.critical = true;
        self.line(&format!("ALARM:{}", alarm.code()));
        self.line("[MSG:Reset to continue]");
    }

    /// Drops the planner, the active block, homing, the pending line, a hold and a pending
    /// `?`; the planned position becomes the true one.
    fn abort_motion(&mut self) {
        self.queue.clear();
        self.active = None;
        self.homing = None;
        self.pending = None;
        self.hold = false;
        self.jogging = false;
        self.status_requested = false;
        self.planned = self.pos;
    }

    fn snapshot_into(&mut self, s: &mut SimState) {
        s.state = self.state;
        s.mpos = Position(self.pos);
        s.critical_alarm = self.critical;
        s.homed = self.homed;
        if s.settings != self.settings {
            s.settings = self.settings.clone();
        }
        s.received_lines.append(&mut self.log_lines);
        s.realtime_received.append(&mut self.log_realtime);
        s.status_reports_sent = self.reports_sent;
        s.reports_corrupted = self.reports_corrupted;
    }

    fn snapshot(&mut self) -> SimState {
        let mut s = SimState {
            state: self.state,
            mpos: Position(self.pos),
            critical_alarm: false,
            homed: false,
            settings: BTreeMap::new(),
            received_lines: Vec::new(),
            realtime_received: Vec::new(),
            status_reports_sent: 0,
            reports_corrupted: 0,
        };
        self.snapshot_into(&mut s);
        s
    }
}

#[cfg(test)]
mod tests {
    use super::super::protocol::RX_BUFFER_SIZE;
    use super::gcode::parse_number;
    use std::sync::atomic::Ordering;
    use super::*;

    /// Drives a firmware with explicit time; returns the text it transmitted.
    struct Bench {
        fw: Firmware,
        t: Instant,
        faults: Faults,
    }

    impl Bench {
        fn new(opts: SimOptions) -> Self {
            let mut b = Self { fw: Firmware::new(&opts), t: Instant::now(), faults: Faults::default() };
            b.fw.tick(b.t, &b.faults);
            b
        }
        fn send(&mut self, bytes: &[u8]) -> String {
            self.fw.receive(bytes, self.t);
            self.fw.tick(self.t, &self.faults);
            String::from_utf8(self.fw.take_output()).unwrap()
        }
        fn advance(&mut self, secs: f64) -> String {
            let end = self.t + Duration::from_secs_f64(secs);
            while self.t < end {
                self.t += Duration::from_millis(1);
                self.fw.tick(self.t, &self.faults);
            }
            String::from_utf8(self.fw.take_output()).unwrap()
        }
    }

    #[test]
    fn banner_status_and_info_match_grbl_md() {
        let mut b = Bench::new(SimOptions::default());
        assert_eq!(String::from_utf8(b.fw.take_output()).unwrap(), "\r\nGrbl 1.1h ['$' for help]\r\n");
        assert_eq!(b.send(b"?"), "<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n");
        assert_eq!(b.send(b"?"), "<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>\r\n");
        assert_eq!(b.send(b"?"), "<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n");
        assert_eq!(b.send(b"$I\n"), "[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n");
        assert_eq!(b.send(b"$G\n"), "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n");
        assert_eq!(b.send(b"foo\n"), "error:2\r\n");
        assert_eq!(b.send(b"$H\n"), "error:5\r\n");
        assert_eq!(b.send(b"\x18"), "\r\nGrbl 1.1h ['$' for help]\r\n");
    }

    #[test]
    fn settings_dump_has_real_defaults() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        let dump = b.send(b"$$\n");
        let lines: Vec<&str> = dump.lines().collect();
        assert_eq!(&lines[..4], &["$0=10", "$1=25", "$2=0", "$3=0"]);
        for expect in ["$11=0.010", "$12=0.002", "$22=0", "$24=25.000", "$25=500.000", "$26=250", "$27=1.000", "$30=1000", "$100=250.000", "$112=500.000", "$122=10.000", "$132=200.000"] {
            assert!(lines.contains(&expect), "{expect} missing in {dump}");
        }
        assert_eq!(lines.last(), Some(&"ok"));
        assert_eq!(lines.len(), 34 + 1);
        assert_eq!(b.send(b"$20=1\n"), "error:10\r\n");
        assert_eq!(b.send(b"$0=2\n"), "error:6\r\n");
        assert_eq!(b.send(b"$27=-1\n"), "error:4\r\n");
        assert_eq!(b.send(b"$27=abc\n"), "error:2\r\n");
        assert_eq!(b.send(b"$99=1\n"), "error:3\r\n");
        assert_eq!(b.send(b"$Q\n"), "error:3\r\n");
        assert_eq!(b.send(b"$27=2.5\n"), "ok\r\n");
        assert!(b.send(b"$$\n").contains("$27=2.500\r\n"));
    }

    #[test]
    fn gcode_errors() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        assert_eq!(b.send(b"G0 G1 X1\n"), "error:21\r\n");
        assert_eq!(b.send(b"G1 X1\n"), "error:22\r\n");
        assert_eq!(b.send(b"G2 X1\n"), "error:20\r\n");
        assert_eq!(b.send(b"X1 X2\n"), "error:25\r\n");
        assert_eq!(b.send(b"G4\n"), "error:28\r\n");
        assert_eq!(b.send(b"1X\n"), "error:1\r\n");
        assert_eq!(b.send(b"G4 P-1\n"), "error:4\r\n");
        assert_eq!(b.send(b"G90 (comment) ; trailing\n"), "ok\r\n");
        let long = format!("G0 X1{}\n", "0".repeat(80));
        assert_eq!(b.send(long.as_bytes()), "error:11\r\n");
        assert_eq!(b.send(b"\n"), "ok\r\n");
    }

    #[test]
    fn rapid_move_follows_a_trapezoid_and_g4_waits() {
        let mut b = Bench::new(SimOptions::default()); // 500 mm/min, 10 mm/s²
        b.fw.take_output();
        assert_eq!(b.send(b"G0 X-10\n"), "ok\r\n");
        assert!(b.send(b"G4 P0\n").is_empty(), "G4 must wait for motion end");
        assert!(b.send(b"?").starts_with("<Run|MPos:0.000,"));
        // 10 mm at 8.333 mm/s with 10 mm/s²: 10/8.333 + 8.333/10 = 2.033 s.
        let out = b.advance(1.0);
        assert!(out.is_empty());
        let r = b.send(b"?");
        assert!(r.starts_with("<Run|MPos:-"), "{r}");
        assert!(b.advance(0.9).is_empty());
        let rest = b.advance(0.25);
        assert_eq!(rest, "ok\r\n");
        assert_eq!(b.fw.position(), Position([-10.0, 0.0, 0.0]));
        assert!(b.send(b"?").starts_with("<Idle|MPos:-10.000,0.000,0.000|FS:0,0"));
    }

    #[test]
    fn homing_locks_reports_and_ends_at_minus_pull_off() {
        let mut b = Bench::new(SimOptions::fast().with(22, 1.0));
        assert_eq!(String::from_utf8(b.fw.take_output()).unwrap(), "\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
        assert_eq!(b.send(b"G0 X-1\n"), "error:9\r\n");
        assert_eq!(b.send(b"$H\n"), "");
        assert_eq!(b.fw.state(), MachineState::Home);
        assert_eq!(b.send(b"?"), "", "no status during homing");
        let out = b.advance(1.0);
        assert_eq!(out, "ok\r\n");
        assert_eq!(b.fw.position(), Position([-1.0; 3]));
        assert!(b.send(b"?").starts_with("<Idle|MPos:-1.000,-1.000,-1.000"));
    }

    #[test]
    fn soft_limit_is_critical_until_reset_then_alarm_until_unlock() {
        let mut b = Bench::new(SimOptions::fast().with(22, 1.0).with(20, 1.0).with(130, 20.0));
        b.fw.take_output();
        assert_eq!(b.send(b"$X\n"), "[MSG:Caution: Unlocked]\r\nok\r\n");
        assert_eq!(b.send(b"G0 X1\n"), "ALARM:2\r\n[MSG:Reset to continue]\r\n");
        assert_eq!(b.send(b"?"), "");
        assert_eq!(b.send(b"$X\n"), "");
        assert_eq!(b.send(b"\x18"), "\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
        assert!(b.send(b"?").starts_with("<Alarm|"));
        assert_eq!(b.send(b"$X\n"), "[MSG:Caution: Unlocked]\r\nok\r\n");
        assert_eq!(b.send(b"$J=G91 X-30 F300\n"), "error:15\r\n");
        assert_eq!(b.send(b"$J=G91 X-2 F30000\n"), "ok\r\n");
        assert!(b.send(b"?").starts_with("<Jog|"));
        assert_eq!(b.send(b"G0 X-1\n"), "error:9\r\n");
        b.send(&[0x85]);
        b.advance(0.1);
        assert_eq!(b.fw.state(), MachineState::Idle);
        assert!(b.fw.position().get(super::super::protocol::Axis::X) > -2.0);
    }

    #[test]
    fn reset_while_moving_raises_alarm_3() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        b.send(b"G0 X-50\n");
        b.advance(0.2);
        assert_eq!(b.send(b"\x18"), "ALARM:3\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
        assert!(b.send(b"?").starts_with("<Alarm|"));
        assert_eq!(b.send(b"G0 X0\n"), "error:9\r\n");
    }

    #[test]
    fn feed_hold_and_resume() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        b.send(b"G0 X-10\n");
        b.advance(0.5);
        b.send(b"!");
        assert_eq!(b.fw.state(), MachineState::Hold(1));
        b.advance(1.0);
        assert_eq!(b.fw.state(), MachineState::Hold(0));
        let held = b.fw.position();
        b.advance(0.5);
        assert_eq!(b.fw.position(), held);
        b.send(b"~");
        assert_eq!(b.fw.state(), MachineState::Run);
        b.advance(4.0);
        assert_eq!(b.fw.state(), MachineState::Idle);
        assert_eq!(b.fw.position(), Position([-10.0, 0.0, 0.0]));
    }

    #[test]
    fn hard_limit_fault_during_move() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        b.send(b"G0 X-10\n");
        b.faults.hard_limit_on_move.store(true, Ordering::SeqCst);
        assert_eq!(b.advance(0.01), "ALARM:1\r\n[MSG:Reset to continue]\r\n");
        assert_eq!(b.send(b"?"), "");
    }

    #[test]
    fn system_commands_follow_grbls_state_rules() {
        let mut b = Bench::new(SimOptions::default()); // homing disabled
        b.fw.take_output();
        assert_eq!(b.send(b"$X\n"), "ok\r\n", "$X outside Alarm has no effect");
        assert_eq!(b.send(b"$XY\n"), "error:3\r\n");
        b.send(b"G0 X-10\n");
        b.advance(0.2);
        assert_eq!(b.fw.state(), MachineState::Run);
        // grbl checks Idle/Alarm before it looks at the homing setting: error:8, not error:5
        assert_eq!(b.send(b"$H\n"), "error:8\r\n");
        assert_eq!(b.send(b"$#\n"), "error:8\r\n");
        assert_eq!(b.send(b"$I\n"), "error:8\r\n");
        assert_eq!(b.send(b"$$\n"), "error:8\r\n");
        assert_eq!(b.send(b"$27=2\n"), "error:8\r\n");
        assert_eq!(b.send(b"$C\n"), "error:8\r\n");
        assert_eq!(b.send(b"$X\n"), "ok\r\n");
        assert_eq!(b.send(b"$G\n"), "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n");
        b.send(b"!");
        assert_eq!(b.send(b"$$\n"), "error:8\r\n", "blocked in Hold too");
        b.send(b"~");
        b.advance(5.0);
        assert_eq!(b.fw.state(), MachineState::Idle);
        // during a jog the settings dump is allowed (jog is neither cycle nor hold)
        assert_eq!(b.send(b"$J=G91 X-5 F300\n"), "ok\r\n");
        assert_eq!(b.fw.state(), MachineState::Jog);
        let dump = b.send(b"$$\n");
        assert!(dump.starts_with("$0=10\r\n") && dump.ends_with("$132=200.000\r\nok\r\n"), "{dump}");
        assert_eq!(b.send(b"$#\n"), "error:8\r\n");
        // the status mask: $10=0 reports WPos, $10=2 adds Bf: (planner blocks, RX bytes free)
        b.send(&[0x85]);
        b.advance(0.5);
        assert_eq!(b.send(b"$10=2\n"), "ok\r\n");
        let r = b.send(b"?");
        assert!(r.starts_with("<Idle|WPos:") && r.contains("|Bf:15,128|FS:0,0"), "{r}");
    }

    #[test]
    fn settings_dump_format_is_one_per_line_in_order() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        let dump = b.send(b"$$\n");
        let want = "$0=10 $1=25 $2=0 $3=0 $4=0 $5=0 $6=0 $10=1 $11=0.010 $12=0.002 $13=0 $20=0 $21=0 $22=0 \
                    $23=0 $24=25.000 $25=500.000 $26=250 $27=1.000 $30=1000 $31=0 $32=0 \
                    $100=250.000 $101=250.000 $102=250.000 $110=500.000 $111=500.000 $112=500.000 \
                    $120=10.000 $121=10.000 $122=10.000 $130=200.000 $131=200.000 $132=200.000 ok";
        let want: String = want.split_whitespace().map(|l| format!("{l}\r\n")).collect();
        assert_eq!(dump, want);
    }

    #[test]
    fn check_mode_parses_without_moving_and_leaving_resets() {
        let mut b = Bench::new(SimOptions::fast().with(22, 1.0).with(20, 1.0).with(130, 20.0));
        b.fw.take_output();
        assert_eq!(b.send(b"$C\n"), "error:8\r\n", "not from Alarm");
        b.send(b"$X\n");
        assert_eq!(b.send(b"$C\n"), "[MSG:Enabled]\r\nok\r\n");
        assert!(b.send(b"?").starts_with("<Check|MPos:0.000,0.000,0.000|"));
        assert_eq!(b.send(b"G0 X-5\n"), "ok\r\n");
        assert_eq!(b.send(b"G4 P5\n"), "ok\r\n", "dwells are skipped");
        assert_eq!(b.send(b"foo\n"), "error:2\r\n");
        b.advance(0.5);
        assert_eq!(b.fw.position(), Position::ZERO, "nothing moves in check mode");
        assert_eq!(b.send(b"$C\n"), "[MSG:Disabled]\r\nok\r\n\r\nGrbl 1.1h ['$' for help]\r\n");
        assert!(b.send(b"?").starts_with("<Idle|"));
        // a soft-limit target is still a critical alarm in check mode
        b.send(b"$C\n");
        assert_eq!(b.send(b"G0 X1\n"), "ALARM:2\r\n[MSG:Reset to continue]\r\n");
        assert_eq!(b.send(b"?"), "");
        assert_eq!(b.send(b"\x18"), "\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
    }

    #[test]
    fn homing_without_switches_ends_in_alarm_9_then_reset_into_alarm() {
        let mut b = Bench::new(SimOptions::fast().with(22, 1.0).with(130, 20.0).with(131, 20.0).with(132, 20.0));
        b.fw.take_output();
        b.faults.homing_switch_missing.store(true, Ordering::SeqCst);
        assert_eq!(b.send(b"$H\n"), "");
        // searches 1.5 × 20 mm at 6000 mm/min = 0.3 s, answering no `?` meanwhile
        assert_eq!(b.advance(0.25), "");
        assert_eq!(b.send(b"?"), "");
        assert_eq!(b.advance(0.1), "ALARM:9\r\nok\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
        assert_eq!(b.fw.state(), MachineState::Alarm);
        assert!(b.send(b"?").starts_with("<Alarm|"));
        assert_eq!(b.send(b"G0 X-1\n"), "error:9\r\n");
        assert_eq!(b.send(b"$X\n"), "[MSG:Caution: Unlocked]\r\nok\r\n");
    }

    #[test]
    fn soft_reset_flushes_the_receive_buffer_and_the_line_buffer_is_bounded() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        // half a line, then ^X: the half line is gone (the newline after it is an empty line)
        assert_eq!(b.send(b"G0 X-5"), "");
        assert_eq!(b.send(b"\x18"), "\r\nGrbl 1.1h ['$' for help]\r\n");
        assert_eq!(b.send(b"\n"), "ok\r\n");
        b.advance(0.5);
        assert_eq!(b.fw.position(), Position::ZERO);
        // the 128-byte RX buffer drops what overflows it while a line waits for the planner:
        // fill the planner with 15 blocks, then a 16th waits, then overflow the buffer
        for i in 0..16 {
            b.send(format!("G0 X-{}\n", i + 1).as_bytes());
        }
        let flood = "G0X-1\n".repeat(40); // 240 bytes
        b.send(flood.as_bytes());
        let r = b.send(b"?");
        assert!(r.starts_with("<Run|"), "{r}");
        assert_eq!(b.fw.rx.len(), RX_BUFFER_SIZE, "the RX buffer holds at most 128 bytes");
    }

    #[test]
    fn reset_during_homing_raises_alarm_6() {
        let mut b = Bench::new(SimOptions::default().with(22, 1.0));
        b.fw.take_output();
        b.send(b"$H\n");
        b.advance(0.1);
        assert_eq!(b.send(b"\x18"), "ALARM:6\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n");
        assert!(b.send(b"?").starts_with("<Alarm|"));
    }

    #[test]
    fn blank_eeprom_first_boot_reports_error_7_and_the_defaults_before_the_banner() {
        let mut b = Bench::new(SimOptions { blank_eeprom: true, ..SimOptions::default() });
        let boot = String::from_utf8(b.fw.take_output()).unwrap();
        assert!(boot.starts_with("error:7\r\n$0=10\r\n$1=25\r\n"), "{boot}");
        assert!(boot.ends_with("$132=200.000\r\n\r\nGrbl 1.1h ['$' for help]\r\n"), "{boot}");
        assert!(!boot.contains("ok"));
    }

    #[test]
    fn duplicate_status_queries_are_merged_and_reports_carry_wco_and_ov_periodically() {
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        assert_eq!(b.send(b"???").matches('<').count(), 1);
        // idle: WCO every 10 reports, Ov every 10 (on the report after WCO)
        let reports: Vec<String> = (0..20).map(|_| b.send(b"?")).collect();
        let wco: Vec<usize> = reports.iter().enumerate().filter(|(_, r)| r.contains("|WCO:")).map(|(i, _)| i).collect();
        let ov: Vec<usize> = reports.iter().enumerate().filter(|(_, r)| r.contains("|Ov:")).map(|(i, _)| i).collect();
        // (the first report, answering `???`, carried WCO; the one after it Ov)
        assert_eq!(wco, vec![9, 19]);
        assert_eq!(ov, vec![0, 10]);
        // busy: `Run` reports carry the feed and, with a planner block, no WCO for 30 reports
        b.send(b"G0 X-50\n");
        b.advance(0.5);
        let r = b.send(b"?");
        assert!(r.starts_with("<Run|MPos:-") && !r.contains("|FS:0,"), "{r}");
    }

    #[test]
    fn corrupted_reports_never_parse_and_rates_hold() {
        use super::super::protocol::{parse_line, Message};
        let mut b = Bench::new(SimOptions::default());
        b.fw.take_output();
        b.send(b"G0 X-50\n");
        b.faults.corrupt_reports_ppm.store(1_000_000, Ordering::SeqCst);
        let mut out = Vec::new();
        for _ in 0..300 {
            b.fw.receive(b"?", b.t);
            b.fw.tick(b.t, &b.faults);
            out.extend(b.fw.take_output());
            b.t += Duration::from_millis(5);
        }
        let text = String::from_utf8_lossy(&out);
        assert!(text.contains(",,") || text.contains("||") || text.contains("::"), "a doubled delimiter appears");
        for line in text.split("\r\n").filter(|l| !l.is_empty()) {
            assert!(!matches!(parse_line(line), Message::Status(_)), "{line:?} parses");
        }
        assert_eq!(b.fw.reports_corrupted, 300);
        // 10 %: about one report in ten
        let mut b = Bench::new(SimOptions::default());
        b.faults.corrupt_reports_ppm.store(100_000, Ordering::SeqCst);
        for _ in 0..2000 {
            b.fw.receive(b"?", b.t);
            b.fw.tick(b.t, &b.faults);
            b.fw.take_output();
        }
        assert!((150..=250).contains(&b.fw.reports_corrupted), "{}", b.fw.reports_corrupted);
    }

    #[test]
    fn parse_number_is_strtod_like() {
        assert_eq!(parse_number("10X"), Some((10.0, "X")));
        assert_eq!(parse_number("-2.5"), Some((-2.5, "")));
        assert_eq!(parse_number(".5"), Some((0.5, "")));
        assert_eq!(parse_number("OO"), None);
        assert_eq!(parse_number("-"), None);
    }
}
