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
//! # Faults
//! [`Faults`] can be flipped by a test while the firmware runs: stop answering (as if hung),
//! turn every transmitted line into noise, drop the port (disconnect), raise a hard-limit
//! `ALARM:1` during the next (or current) move, unplug the limit switches (homing ends in
//! `ALARM:9`, then `ok`, banner and `Alarm`).

use std::collections::{BTreeMap, VecDeque};
use std::io::{self, Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::protocol::{fmt_num, Alarm, GrblError, MachineState, Position, ReportedPosition, StatusReport, BANNER, LINE_BUFFER_SIZE, RX_BUFFER_SIZE};

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

fn is_integer_setting(n: u16) -> bool {
    matches!(n, 0..=6 | 10 | 13 | 20..=23 | 26 | 30..=32)
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

    /// Handles received bytes: real-time bytes act at once, the rest enters the 128-byte RX
    /// buffer (excess bytes are dropped, as on the board).
    pub fn receive(&mut self, bytes: &[u8], now: Instant) {
        for &b in bytes {
            if self.critical {
                self.log_realtime.push((b, self.state));
                if b == 0x18 {
                    self.soft_reset();
                }
                continue;
            }
            match b {
                b'?' | b'~' | b'!' | 0x18 | 0x80..=0xFF => {
                    self.log_realtime.push((b, self.state));
                    self.realtime(b);
                }
                _ => {
                    if self.rx.len() < RX_BUFFER_SIZE {
                        self.rx.push_back(b);
                    }
                }
            }
        }
        self.process_lines(now);
    }

    fn realtime(&mut self, b: u8) {
        match b {
            b'?' if self.state != MachineState::Home => self.status_requested = true,
            b'!' => match self.state {
                MachineState::Run => {
                    self.hold = true;
                    self.state = MachineState::Hold(1);
                }
                MachineState::Jog => self.jog_cancel = true,
                _ => {}
            },
            b'~' => {
                if matches!(self.state, MachineState::Hold(_)) {
                    self.hold = false;
                    self.state = if self.active.is_some() || !self.queue.is_empty() { MachineState::Run } else { MachineState::Idle };
                }
            }
            0x85 if self.state == MachineState::Jog => self.jog_cancel = true,
            0x18 => self.soft_reset(),
            _ => {}
        }
    }

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
        self.queue.clear();
        self.active = None;
        self.homing = None;
        self.pending = None;
        self.hold = false;
        self.jogging = false;
        self.jog_cancel = false;
        self.status_requested = false;
        self.planned = self.pos;
        self.absolute = true;
        self.motion_g1 = false;
        self.feed = 0.0;
        self.wco_counter = 0;
        self.ovr_counter = 0;
        self.boot_messages();
    }

    fn critical_alarm(&mut self, alarm: Alarm) {
        self.queue.clear();
        self.active = None;
        self.homing = None;
        self.pending = None;
        self.hold = false;
        self.jogging = false;
        self.planned = self.pos;
        self.state = MachineState::Alarm;
        self.critical = true;
        self.status_requested = false;
        self.line(&format!("ALARM:{}", alarm.code()));
        self.line("[MSG:Reset to continue]");
    }

    fn process_lines(&mut self, now: Instant) {
        while self.pending.is_none() && !self.critical {
            let Some(end) = self.rx.iter().position(|&b| b == b'\n' || b == b'\r') else { break };
            let raw: Vec<u8> = self.rx.drain(..=end).collect();
            let raw = &raw[..raw.len() - 1];
            self.exec_raw_line(raw, now);
        }
    }

    fn exec_raw_line(&mut self, raw: &[u8], now: Instant) {
        // grbl's protocol layer: drop whitespace/control characters and comments, upper-case.
        let mut line = String::new();
        let mut in_paren = false;
        let mut count = 0usize;
        let mut overflow = false;
        for &c in raw {
            if in_paren {
                if c == b')' {
                    in_paren = false;
                }
                continue;
            }
            match c {
                b'(' => in_paren = true,
                b';' => break,
                0..=b' ' => {}
                _ => {
                    if count >= LINE_BUFFER_SIZE - 1 {
                        overflow = true;
                    } else {
                        line.push((c as char).to_ascii_uppercase());
                        count += 1;
                    }
                }
            }
        }
        self.log_lines.push(line.clone());
        if overflow {
            return self.error(GrblError::LineOverflow);
        }
        if line.is_empty() {
            return self.ok();
        }
        if let Some(sys) = line.strip_prefix('$') {
            let sys = sys.to_string();
            return self.system(&sys, now);
        }
        if matches!(self.state, MachineState::Alarm | MachineState::Jog) {
            return self.error(GrblError::GcodeLock);
        }
        match self.gcode(&line, false) {
            Ok(()) => {}
            Err(e) => self.error(e),
        }
        self.process_pending(now);
    }

    fn idle_or_alarm(&self) -> bool {
        matches!(self.state, MachineState::Idle | MachineState::Alarm)
    }

    fn system(&mut self, cmd: &str, now: Instant) {
        match cmd {
            "" => {
                self.line("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]");
                self.ok()
            }
            "$" => {
                // grbl blocks the dump only during a cycle or hold (it takes too long to print)
                if matches!(self.state, MachineState::Run | MachineState::Hold(_)) {
                    return self.error(GrblError::NotIdle);
                }
                self.settings_dump();
                self.ok()
            }
            "C" => {
                if self.state == MachineState::Check {
                    // leaving check mode resets grbl (mc_reset): ok, then the banner
                    self.line("[MSG:Disabled]");
                    self.ok();
                    self.state = MachineState::Idle;
                    self.soft_reset();
                    return;
                }
                if self.state != MachineState::Idle {
                    return self.error(GrblError::NotIdle);
                }
                self.state = MachineState::Check;
                self.line("[MSG:Enabled]");
                self.ok()
            }
            // `$#`, `$I`, `$H` and setting writes need Idle or Alarm (grbl checks that first)
            "#" | "I" | "H" if !self.idle_or_alarm() => self.error(GrblError::NotIdle),
            "I" => {
                self.line("[VER:1.1h.20190830:]");
                self.line("[OPT:V,15,128]");
                self.ok()
            }
            "G" => {
                let g = format!(
                    "[GC:G{} G54 G17 G21 G{} G94 M5 M9 T0 F{} S0]",
                    if self.motion_g1 { 1 } else { 0 },
                    if self.absolute { 90 } else { 91 },
                    self.feed.round() as i64
                );
                self.line(&g);
                self.ok()
            }
            "#" => {
                for l in [
                    "[G54:0.000,0.000,0.000]",
                    "[G55:0.000,0.000,0.000]",
                    "[G56:0.000,0.000,0.000]",
                    "[G57:0.000,0.000,0.000]",
                    "[G58:0.000,0.000,0.000]",
                    "[G59:0.000,0.000,0.000]",
                    "[G28:0.000,0.000,0.000]",
                    "[G30:0.000,0.000,0.000]",
                    "[G92:0.000,0.000,0.000]",
                    "[TLO:0.000]",
                    "[PRB:0.000,0.000,0.000:0]",
                ] {
                    self.line(l);
                }
                self.ok()
            }
            "X" => {
                // outside Alarm `$X` has no effect (and still answers ok)
                if self.state == MachineState::Alarm {
                    self.line("[MSG:Caution: Unlocked]");
                    self.state = MachineState::Idle;
                }
                self.ok()
            }
            "H" => {
                if self.setting(22) == 0.0 {
                    return self.error(GrblError::HomingDisabled);
                }
                self.start_homing(now);
            }
            _ => {
                if let Some(jog) = cmd.strip_prefix("J=") {
                    if !matches!(self.state, MachineState::Idle | MachineState::Jog) {
                        return self.error(GrblError::NotIdle);
                    }
                    let jog = jog.to_string();
                    match self.gcode(&jog, true) {
                        Ok(()) => {}
                        Err(e) => self.error(e),
                    }
                    return self.process_pending(now);
                }
                if let Some((n, v)) = cmd.split_once('=') {
                    return match self.set_setting(n, v) {
                        Ok(()) => self.ok(),
                        Err(e) => self.error(e),
                    };
                }
                self.error(GrblError::InvalidStatement)
            }
        }
    }

    fn settings_dump(&mut self) {
        let lines: Vec<String> = self
            .settings
            .iter()
            .map(|(&n, &v)| if is_integer_setting(n) { format!("${n}={}", v as i64) } else { format!("${n}={}", fmt_num(v)) })
            .collect();
        for l in lines {
            self.line(&l);
        }
    }

    /// A failed homing cycle (not critical): `ALARM:N`, the `$H` line's `ok`, then grbl resets
    /// into `Alarm` (banner and unlock message).
    fn homing_alarm(&mut self, alarm: Alarm) {
        self.homing = None;
        self.pending = None;
        self.planned = self.pos;
        self.line(&format!("ALARM:{}", alarm.code()));
        self.ok();
        self.state = MachineState::Alarm;
        self.soft_reset();
    }

    fn set_setting(&mut self, n: &str, v: &str) -> Result<(), GrblError> {
        let n: u16 = n.parse().map_err(|_| GrblError::InvalidStatement)?;
        let (value, rest) = parse_number(v).ok_or(GrblError::BadNumberFormat)?;
        if !rest.is_empty() {
            return Err(GrblError::BadNumberFormat);
        }
        if !self.idle_or_alarm() {
            return Err(GrblError::NotIdle);
        }
        if !self.settings.contains_key(&n) {
            return Err(GrblError::InvalidStatement);
        }
        if value < 0.0 {
            return Err(GrblError::NegativeValue);
        }
        let value = if is_integer_setting(n) { value.trunc() } else { value };
        match n {
            0 if value < 3.0 => return Err(GrblError::StepPulseTooShort),
            20 if value != 0.0 && self.setting(22) == 0.0 => return Err(GrblError::SoftLimitsNeedHoming),
            22 if value == 0.0 => {
                // grbl also clears soft limits when homing is disabled.
                self.settings.insert(20, 0.0);
            }
            _ => {}
        }
        self.settings.insert(n, value);
        Ok(())
    }

    fn start_homing(&mut self, now: Instant) {
        let pull = self.setting(27);
        let seek = self.setting(25).max(1e-3) / 60.0;
        let feed = self.setting(24).max(1e-3) / 60.0;
        let debounce = self.setting(26) / 1000.0;
        // Two cycles (Z, then X+Y): seek, pull off, locate slowly, pull off.
        let per_cycle = self.home_seek_mm / seek + pull / seek + 2.0 * pull / feed + 2.0 * debounce;
        let duration = Duration::from_secs_f64((2.0 * per_cycle).max(0.0));
        self.homing = Some(Homing { start: now, duration, from: self.pos, to: [-pull; 3] });
        self.state = MachineState::Home;
        self.pending = Some(Pending::Homing);
    }

    /// Parses and executes one G-code block (`jog`: the text after `$J=`).
    fn gcode(&mut self, line: &str, jog: bool) -> Result<(), GrblError> {
        let mut rest = line;
        let mut motion: Option<bool> = None; // Some(false) G0, Some(true) G1
        let mut group0: Option<u32> = None; // 4 = dwell, 53 = machine coords
        let mut distance: Option<bool> = None;
        let mut axes: [Option<f64>; 3] = [None; 3];
        let mut feed: Option<f64> = None;
        let mut p: Option<f64> = None;
        let mut seen_letters = Vec::new();
        while !rest.is_empty() {
            let mut chars = rest.chars();
            let letter = chars.next().unwrap_or(' ');
            if !letter.is_ascii_uppercase() {
                return Err(GrblError::ExpectedCommandLetter);
            }
            let (value, tail) = parse_number(chars.as_str()).ok_or(GrblError::BadNumberFormat)?;
            rest = tail;
            match letter {
                'G' => {
                    let int = value.trunc();
                    if (value - int).abs() > 1e-6 {
                        return Err(GrblError::UnsupportedCommand);
                    }
                    match int as i64 {
                        0 | 1 => {
                            if jog {
                                return Err(GrblError::InvalidJog);
                            }
                            if motion.is_some() {
                                return Err(GrblError::ModalGroupViolation);
                            }
                            motion = Some(int as i64 == 1);
                        }
                        4 | 53 => {
                            if jog && int as i64 == 4 {
                                return Err(GrblError::InvalidJog);
                            }
                            if group0.is_some() {
                                return Err(GrblError::ModalGroupViolation);
                            }
                            group0 = Some(int as u32);
                        }
                        90 | 91 => {
                            if distance.is_some() {
                                return Err(GrblError::ModalGroupViolation);
                            }
                            distance = Some(int as i64 == 90);
                        }
                        17 | 21 | 54 | 94 if !jog => {}
                        21 if jog => {}
                        _ => return Err(if jog { GrblError::InvalidJog } else { GrblError::UnsupportedCommand }),
                    }
                }
                'M' if !jog => match value as i64 {
                    5 | 9 => {}
                    _ => return Err(GrblError::UnsupportedCommand),
                },
                'X' | 'Y' | 'Z' | 'F' | 'P' | 'N' | 'S' | 'T' => {
                    if seen_letters.contains(&letter) {
                        return Err(GrblError::RepeatedWord);
                    }
                    seen_letters.push(letter);
                    match letter {
                        'X' => axes[0] = Some(value),
                        'Y' => axes[1] = Some(value),
                        'Z' => axes[2] = Some(value),
                        'F' => {
                            if value < 0.0 {
                                return Err(GrblError::NegativeValue);
                            }
                            feed = Some(value)
                        }
                        'P' => {
                            if jog {
                                return Err(GrblError::InvalidJog);
                            }
                            if value < 0.0 {
                                return Err(GrblError::NegativeValue);
                            }
                            p = Some(value)
                        }
                        _ => {
                            if jog {
                                return Err(GrblError::InvalidJog);
                            }
                        }
                    }
                }
                _ => return Err(if jog { GrblError::InvalidJog } else { GrblError::UnsupportedCommand }),
            }
        }
        let has_axes = axes.iter().any(Option::is_some);
        if jog {
            let feed = feed.ok_or(GrblError::UndefinedFeedRate)?;
            if !has_axes {
                return Err(GrblError::InvalidJog);
            }
            let abs = distance.unwrap_or(self.absolute);
            let target = self.target(&axes, abs, group0 == Some(53));
            if self.setting(20) != 0.0 && !self.within_travel(&target) {
                return Err(GrblError::TravelExceeded);
            }
            self.pending = Some(Pending::Planner(Block { target, feed: Some(feed) }, true));
            return Ok(());
        }
        if group0 == Some(4) {
            let secs = p.ok_or(GrblError::MissingValueWord)?;
            if has_axes {
                return Err(GrblError::UnusedAxisWords);
            }
            if let Some(d) = distance {
                self.absolute = d;
            }
            if self.state == MachineState::Check {
                self.ok(); // check mode skips dwells
                return Ok(());
            }
            self.pending = Some(Pending::Dwell { secs, until: None });
            return Ok(());
        }
        if p.is_some() {
            return Err(GrblError::UnusedValueWords);
        }
        if let Some(d) = distance {
            self.absolute = d;
        }
        if let Some(f) = feed {
            self.feed = f;
        }
        if let Some(m) = motion {
            self.motion_g1 = m;
        }
        if group0 == Some(53) && motion.is_none() && !has_axes {
            return Err(GrblError::NoAxisWords);
        }
        if !has_axes {
            // Modal changes only.
            self.ok();
            return Ok(());
        }
        if self.motion_g1 && self.feed <= 0.0 {
            return Err(GrblError::UndefinedFeedRate);
        }
        let target = self.target(&axes, self.absolute, group0 == Some(53));
        if self.setting(20) != 0.0 && !self.within_travel(&target) {
            self.critical_alarm(Alarm::SoftLimit);
            return Ok(());
        }
        if self.state == MachineState::Check {
            // check mode: parsed and checked, nothing moves
            self.planned = target;
            self.ok();
            return Ok(());
        }
        let feed = if self.motion_g1 { Some(self.feed) } else { None };
        self.pending = Some(Pending::Planner(Block { target, feed }, false));
        Ok(())
    }

    fn target(&self, axes: &[Option<f64>; 3], absolute: bool, machine: bool) -> [f64; 3] {
        let mut t = self.planned;
        for i in 0..3 {
            if let Some(v) = axes[i] {
                t[i] = if absolute || machine { v } else { self.planned[i] + v };
            }
        }
        t
    }

    fn within_travel(&self, t: &[f64; 3]) -> bool {
        (0..3).all(|i| {
            let travel = self.setting(130 + i as u16);
            t[i] <= EPS && t[i] >= -travel - EPS
        })
    }

    fn process_pending(&mut self, now: Instant) {
        match self.pending.take() {
            Some(Pending::Planner(block, jog)) => {
                if self.queue.len() + usize::from(self.active.is_some()) < PLANNER_BLOCKS {
                    self.planned = block.target;
                    self.queue.push_back(block);
                    self.jogging = jog;
                    if !self.hold {
                        self.state = if jog { MachineState::Jog } else { MachineState::Run };
                    }
                    self.ok();
                } else {
                    self.pending = Some(Pending::Planner(block, jog));
                }
            }
            Some(Pending::Dwell { secs, until }) => {
                if self.active.is_some() || !self.queue.is_empty() {
                    self.pending = Some(Pending::Dwell { secs, until });
                    return;
                }
                let until = until.unwrap_or_else(|| now + Duration::from_secs_f64(secs));
                if now >= until {
                    self.ok();
                } else {
                    self.pending = Some(Pending::Dwell { secs, until: Some(until) });
                }
            }
            Some(Pending::Homing) => {
                let Some(h) = self.homing.clone() else { return };
                let t = now.saturating_duration_since(h.start);
                if t >= h.duration && !self.switches_missing {
                    self.pos = h.to;
                    self.planned = h.to;
                    self.homing = None;
                    self.homed = true;
                    self.state = MachineState::Idle;
                    self.ok();
                } else {
                    let f = (t.as_secs_f64() / h.duration.as_secs_f64().max(1e-9)).min(1.0);
                    // Towards the switches (+), then back to −pull-off; good enough for reports
                    // nobody can read (no `?` during homing).
                    for i in 0..3 {
                        self.pos[i] = h.from[i] + (h.to[i] - h.from[i]) * f;
                    }
                    self.pending = Some(Pending::Homing);
                }
            }
            None => {}
        }
    }

    fn start_block(&mut self, block: &Block) -> Active {
        let start = self.pos;
        let d: Vec<f64> = (0..3).map(|i| block.target[i] - start[i]).collect();
        let length = d.iter().map(|x| x * x).sum::<f64>().sqrt();
        let mut unit = [0.0; 3];
        let mut vmax = f64::INFINITY;
        let mut accel = f64::INFINITY;
        if length > 0.0 {
            for i in 0..3 {
                unit[i] = d[i] / length;
                if unit[i].abs() > 1e-12 {
                    let rate = self.setting(110 + i as u16) / 60.0;
                    let acc = self.setting(120 + i as u16);
                    vmax = vmax.min(rate / unit[i].abs());
                    accel = accel.min(acc / unit[i].abs());
                }
            }
        }
        if let Some(f) = block.feed {
            vmax = vmax.min(f / 60.0);
        }
        Active { start, unit, length, s: 0.0, v: 0.0, vmax: vmax.max(1e-6), accel: accel.max(1e-6) }
    }

    /// Advances motion, homing and pending lines to `now`, and answers a pending `?`.
    pub fn tick(&mut self, now: Instant, faults: &Faults) {
        let last = self.last_tick.unwrap_or(now);
        self.last_tick = Some(now);
        let mut dt = now.saturating_duration_since(last).as_secs_f64().min(0.5);
        if !self.critical && matches!(self.state, MachineState::Run | MachineState::Jog | MachineState::Hold(1)) && faults.hard_limit_on_move.swap(false, Ordering::SeqCst) {
            self.critical_alarm(Alarm::HardLimit);
        }
        self.switches_missing = faults.homing_switch_missing.load(Ordering::SeqCst);
        if let Some(h) = &self.homing {
            if self.switches_missing {
                // grbl searches 1.5 × the largest max travel at the seek rate
                let travel = (0..3).map(|i| self.setting(130 + i)).fold(0.0, f64::max);
                let search = Duration::from_secs_f64(1.5 * travel / (self.setting(25).max(1e-3) / 60.0));
                if now.saturating_duration_since(h.start) >= search {
                    self.homing_alarm(Alarm::HomingFailApproach);
                }
            }
        }
        while dt > 0.0 && !self.critical {
            let h = dt.min(0.0005);
            dt -= h;
            if !self.step(h) {
                break;
            }
        }
        self.process_pending(now);
        self.process_lines(now);
        if self.status_requested {
            self.status_requested = false;
            let r = self.report();
            self.reports_sent += 1;
            // the generator only advances while the fault is on
            let ppm = faults.corrupt_reports_ppm.load(Ordering::SeqCst) as u64;
            if ppm > 0 && self.noise() % 1_000_000 < ppm {
                self.reports_corrupted += 1;
                self.corrupt_line(&r);
            } else {
                self.line(&r);
            }
        }
    }

    fn noise(&mut self) -> u64 {
        let x = &mut self.noise_rng;
        *x ^= *x << 13;
        *x ^= *x >> 7;
        *x ^= *x << 17;
        *x
    }

    /// Transmits `report` damaged as a noisy line would (see [`Faults::corrupt_reports_ppm`]).
    fn corrupt_line(&mut self, report: &str) {
        let mut b = report.as_bytes().to_vec();
        let pick = |fw: &mut Self, b: &[u8], f: &dyn Fn(u8) -> bool| {
            let idx: Vec<usize> = (0..b.len()).filter(|&i| f(b[i])).collect();
            let n = fw.noise() as usize;
            idx.get(n % idx.len().max(1)).copied()
        };
        match self.noise() % 4 {
            0 => {
                if let Some(i) = pick(self, &b, &|c| b"|,:<>".contains(&c)) {
                    b.remove(i);
                }
            }
            1 => {
                if let Some(i) = pick(self, &b, &|c| b"|,:".contains(&c)) {
                    b.insert(i, b[i]);
                }
            }
            2 => {
                if let Some(i) = pick(self, &b, &|c| c.is_ascii_digit() || c == b'.' || c == b'-') {
                    b[i] = if self.noise() % 2 == 0 { 0xFF } else { b'#' };
                }
            }
            _ => {
                // interleaved: into the middle of the line sent just before, else run into
                // whatever comes next
                let text_end = self.out.len().saturating_sub(2);
                if self.out.ends_with(b"\r\n") && text_end > 0 {
                    let start = self.out[..text_end].iter().rposition(|&c| c == b'\n').map_or(0, |p| p + 1);
                    if text_end - start >= 2 {
                        let mid = start + (text_end - start) / 2;
                        self.out.splice(mid..mid, b);
                        return;
                    }
                }
                self.out.extend_from_slice(&b);
                return;
            }
        }
        self.out.extend_from_slice(&b);
        self.out.extend_from_slice(b"\r\n");
    }

    /// One integration step; false when nothing moves.
    fn step(&mut self, h: f64) -> bool {
        if self.active.is_none() {
            if self.hold || self.jog_cancel {
                if self.jog_cancel {
                    self.finish_jog_cancel();
                }
                return false;
            }
            let Some(block) = self.queue.pop_front() else { return false };
            let a = self.start_block(&block);
            self.active = Some(a);
        }
        let stopping = self.hold || self.jog_cancel;
        let Some(a) = self.active.as_mut() else { return false };
        let remaining = (a.length - a.s).max(0.0);
        let v_new = if stopping {
            (a.v - a.accel * h).max(0.0)
        } else {
            let v_target = a.vmax.min((2.0 * a.accel * remaining).sqrt());
            if a.v < v_target { (a.v + a.accel * h).min(v_target) } else { v_target }
        };
        let ds = 0.5 * (a.v + v_new) * h;
        a.v = v_new;
        let done = !stopping && (remaining <= ds + 1e-9 || remaining < 1e-9);
        a.s = if done { a.length } else { (a.s + ds).min(a.length) };
        let s = a.s;
        let (start, unit, v) = (a.start, a.unit, a.v);
        for i in 0..3 {
            self.pos[i] = start[i] + unit[i] * s;
        }
        if done {
            // Land exactly on the programmed target (the planner works in steps; so do we).
            if let Some(a) = self.active.take() {
                for i in 0..3 {
                    self.pos[i] = a.start[i] + a.unit[i] * a.length;
                }
            }
            if self.queue.is_empty() {
                self.jogging = false;
                if !self.hold {
                    self.state = MachineState::Idle;
                }
            }
        } else if stopping && v <= 0.0 {
            if self.jog_cancel {
                self.finish_jog_cancel();
            } else {
                self.state = MachineState::Hold(0);
                // Resume restarts the rest of this block from rest.
                if let Some(a) = self.active.take() {
                    let target: [f64; 3] = std::array::from_fn(|i| a.start[i] + a.unit[i] * a.length);
                    let rest = Block { target, feed: Some(a.vmax * 60.0) };
                    self.queue.push_front(rest);
                }
            }
            return false;
        }
        true
    }

    fn finish_jog_cancel(&mut self) {
        self.active = None;
        self.queue.clear();
        self.jog_cancel = false;
        self.jogging = false;
        self.planned = self.pos;
        self.state = MachineState::Idle;
        if matches!(self.pending, Some(Pending::Planner(_, true))) {
            self.pending = None;
        }
    }

    fn report(&mut self) -> String {
        let mask = self.setting(10) as i64;
        let mut r = StatusReport::new(self.state, Position(self.pos));
        if mask & 1 == 0 {
            r.position = ReportedPosition::Work(Position(self.pos));
        }
        if mask & 2 != 0 {
            let free = PLANNER_BLOCKS - self.queue.len().min(PLANNER_BLOCKS);
            r.buffer = Some((free as u32, (RX_BUFFER_SIZE - self.rx.len()) as u32));
        }
        let v = self.active.as_ref().map_or(0.0, |a| a.v * 60.0);
        r.feed = Some(v);
        r.spindle = Some(0.0);
        let busy = matches!(self.state, MachineState::Run | MachineState::Hold(_) | MachineState::Jog | MachineState::Home | MachineState::Door(_));
        if self.wco_counter > 0 {
            self.wco_counter -= 1;
        } else {
            self.wco_counter = if busy { 29 } else { 9 };
            if self.ovr_counter == 0 {
                self.ovr_counter = 1;
            }
            r.wco = Some(Position::ZERO);
        }
        if self.ovr_counter > 0 {
            self.ovr_counter -= 1;
        } else {
            self.ovr_counter = if busy { 19 } else { 9 };
            r.overrides = Some([100, 100, 100]);
        }
        r.format()
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

/// Parses a grbl number (`strtod` subset: sign, digits, one dot) at the start of `s`.
fn parse_number(s: &str) -> Option<(f64, &str)> {
    let b = s.as_bytes();
    let mut i = 0;
    if i < b.len() && (b[i] == b'-' || b[i] == b'+') {
        i += 1;
    }
    let mut digits = 0;
    let mut dot = false;
    while i < b.len() {
        if b[i].is_ascii_digit() {
            digits += 1;
        } else if b[i] == b'.' && !dot {
            dot = true;
        } else {
            break;
        }
        i += 1;
    }
    if digits == 0 {
        return None;
    }
    let v: f64 = s[..i].parse().ok()?;
    Some((v, &s[i..]))
}

/// A running simulated board.
pub struct SimHandle {
    pub faults: Arc<Faults>,
    state: Arc<Mutex<SimState>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    _keepalive: Option<Box<dyn Send>>,
}

/// A view of a running board that another thread can hold: its faults and true state.
#[derive(Clone)]
pub struct SimObserver {
    pub faults: Arc<Faults>,
    state: Arc<Mutex<SimState>>,
}

impl SimObserver {
    /// The firmware's true state (locks briefly).
    pub fn state(&self) -> MutexGuard<'_, SimState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl SimHandle {
    /// A cloneable view of the board for another thread.
    pub fn observer(&self) -> SimObserver {
        SimObserver { faults: self.faults.clone(), state: self.state.clone() }
    }

    /// The firmware's true state (locks briefly).
    pub fn state(&self) -> MutexGuard<'_, SimState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Stops the firmware thread and waits for it.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Runs the firmware on a thread over `port`.
///
/// `port.read` must return within a few milliseconds when no data arrives (`TimedOut`,
/// `WouldBlock` or `Ok(0)`), or simulated motion stalls.
pub fn spawn<T: Read + Write + Send + 'static>(port: T, options: SimOptions) -> SimHandle {
    let mut fw = Firmware::new(&options);
    let state = Arc::new(Mutex::new(fw.snapshot()));
    let faults = Arc::new(Faults::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (state, faults, stop) = (state.clone(), faults.clone(), stop.clone());
        std::thread::spawn(move || run(port, fw, &state, &faults, &stop))
    };
    SimHandle { faults, state, stop, thread: Some(thread), _keepalive: None }
}

/// Creates a pseudo-terminal, runs the firmware on its master side, and returns the slave's
/// path for a client to open with `serialport::new(path, 115200)`.
///
/// # Errors
/// When no pty can be allocated.
#[cfg(unix)]
pub fn spawn_pty(options: SimOptions) -> io::Result<(SimHandle, String)> {
    use serialport::SerialPort;
    let (mut master, slave) = serialport::TTYPort::pair().map_err(io::Error::from)?;
    let path = slave.name().ok_or_else(|| io::Error::other("pty slave has no name"))?;
    master.set_timeout(Duration::from_millis(2)).map_err(io::Error::from)?;
    let mut handle = spawn(master, options);
    // Keep one slave descriptor open so the master never sees a hang-up between clients.
    handle._keepalive = Some(Box::new(slave));
    Ok((handle, path))
}

fn garble(bytes: &[u8]) -> Vec<u8> {
    let mut x: u32 = 0x9E37_79B9;
    bytes
        .iter()
        .map(|&b| {
            if b == b'\n' {
                return b'\n';
            }
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            0x80 | (x as u8) // never valid ASCII, rarely valid UTF-8
        })
        .collect()
}

fn run<T: Read + Write>(mut port: T, mut fw: Firmware, state: &Mutex<SimState>, faults: &Faults, stop: &AtomicBool) {
    let mut buf = [0u8; 256];
    loop {
        if stop.load(Ordering::SeqCst) || faults.disconnect.load(Ordering::SeqCst) {
            return; // drops the port
        }
        let silent = faults.silent.load(Ordering::SeqCst);
        match port.read(&mut buf) {
            Ok(0) => std::thread::sleep(Duration::from_millis(1)),
            Ok(n) => {
                if !silent {
                    fw.receive(&buf[..n], Instant::now());
                }
            }
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted) => {}
            // A pty master reads EIO while no client has the slave open: wait for one.
            Err(_) => std::thread::sleep(Duration::from_millis(2)),
        }
        fw.tick(Instant::now(), faults);
        let out = fw.take_output();
        if !out.is_empty() && !faults.silent.load(Ordering::SeqCst) {
            let out = if faults.garbage.load(Ordering::SeqCst) { garble(&out) } else { out };
            // A client that stopped reading must not wedge the firmware: drop what won't fit.
            let _ = port.write_all(&out).and_then(|_| port.flush());
        }
        if let Ok(mut s) = state.lock() {
            fw.snapshot_into(&mut s);
        }
    }
}

#[cfg(test)]
mod tests {
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
