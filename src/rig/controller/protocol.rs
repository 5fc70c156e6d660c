//! GRBL 1.1 wire protocol: pure encoders and parsers, no I/O.
//!
//! Owns the byte-level vocabulary the controller client ([`super::grbl`]) and the simulated
//! firmware ([`super::sim`]) share: one parsed [`Message`] per received line, the typed
//! [`GrblError`] and [`Alarm`] tables, the [`StatusReport`] format, and encoders for the few
//! commands a calibration rig needs.
//!
//! # Conventions
//! - Lines from grbl end in `\r\n`; [`parse_line`] accepts a line with or without them. Lines
//!   sent to grbl end in a single `\n` ([`frame`]).
//! - Exactly one *response* (`ok` or `error:N`) answers each line sent; everything else is a
//!   *push message* ([`Message::is_response`]).
//! - Positions are millimetres in **machine** coordinates (`MPos`). With default homing
//!   direction, machine space is negative: `[-max_travel, 0]`. `WPos = MPos − WCO`.
//! - Numbers are formatted with three decimals, as grbl does in mm mode.
//! - Realtime commands ([`Realtime`]) are single bytes sent without a newline; they never enter
//!   grbl's line buffer.

use std::fmt;

/// A machine axis of a three-axis grbl build.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    /// All axes in grbl's report order.
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];

    /// Index into an `[x, y, z]` triple.
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }

    /// The G-code letter.
    pub fn letter(self) -> char {
        ['X', 'Y', 'Z'][self.index()]
    }

    /// The axis named by a G-code letter (upper or lower case).
    pub fn from_letter(c: char) -> Option<Axis> {
        match c.to_ascii_uppercase() {
            'X' => Some(Axis::X),
            'Y' => Some(Axis::Y),
            'Z' => Some(Axis::Z),
            _ => None,
        }
    }
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.letter())
    }
}

/// A point in X, Y, Z millimetres.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Position(pub [f64; 3]);

impl Position {
    pub const ZERO: Position = Position([0.0; 3]);

    pub fn get(&self, axis: Axis) -> f64 {
        self.0[axis.index()]
    }

    pub fn set(&mut self, axis: Axis, v: f64) {
        self.0[axis.index()] = v;
    }

    /// Component-wise `self − other`.
    pub fn sub(&self, other: &Position) -> Position {
        Position([self.0[0] - other.0[0], self.0[1] - other.0[1], self.0[2] - other.0[2]])
    }

    /// Component-wise `self + other`.
    pub fn add(&self, other: &Position) -> Position {
        Position([self.0[0] + other.0[0], self.0[1] + other.0[1], self.0[2] + other.0[2]])
    }

    /// Largest absolute component difference.
    pub fn max_abs_diff(&self, other: &Position) -> f64 {
        (0..3).map(|i| (self.0[i] - other.0[i]).abs()).fold(0.0, f64::max)
    }

    /// `x,y,z` with three decimals, as in a status report.
    pub fn format(&self) -> String {
        format!("{},{},{}", fmt_num(self.0[0]), fmt_num(self.0[1]), fmt_num(self.0[2]))
    }

    fn parse(s: &str) -> Option<Position> {
        let mut it = s.split(',');
        let mut p = [0.0; 3];
        for v in &mut p {
            *v = parse_f64(it.next()?)?;
        }
        // Builds with more axes report more values; a rig uses the first three.
        Some(Position(p))
    }
}

/// Formats a number as grbl does in mm mode (`%.3f`), without a negative zero.
pub fn fmt_num(v: f64) -> String {
    let s = format!("{v:.3}");
    if s == "-0.000" { "0.000".to_string() } else { s }
}

fn parse_f64(s: &str) -> Option<f64> {
    let s = s.trim();
    // Rust's parser accepts "inf"/"nan"; grbl never sends them.
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit() || b == b'.' || b == b'-' || b == b'+') {
        return None;
    }
    s.parse().ok()
}

/// The machine state field of a status report.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MachineState {
    Idle,
    Run,
    /// `Hold:0` hold complete, `Hold:1` decelerating.
    Hold(u8),
    Jog,
    Alarm,
    /// `Door:0..3`.
    Door(u8),
    Check,
    Home,
    Sleep,
}

impl MachineState {
    /// Parses `Idle`, `Hold:1`, … ; `Hold` and `Door` without a sub-state read as `:0`.
    pub fn parse(s: &str) -> Option<MachineState> {
        let (name, sub) = match s.split_once(':') {
            Some((n, sub)) => (n, Some(sub.parse::<u8>().ok()?)),
            None => (s, None),
        };
        let plain = |st| if sub.is_none() { Some(st) } else { None };
        match name {
            "Idle" => plain(MachineState::Idle),
            "Run" => plain(MachineState::Run),
            "Hold" => Some(MachineState::Hold(sub.unwrap_or(0))),
            "Jog" => plain(MachineState::Jog),
            "Alarm" => plain(MachineState::Alarm),
            "Door" => Some(MachineState::Door(sub.unwrap_or(0))),
            "Check" => plain(MachineState::Check),
            "Home" => plain(MachineState::Home),
            "Sleep" => plain(MachineState::Sleep),
            _ => None,
        }
    }

    /// True while the machine may move (`Run`, `Jog`, `Home`, a decelerating hold).
    pub fn is_moving(self) -> bool {
        matches!(self, MachineState::Run | MachineState::Jog | MachineState::Home | MachineState::Hold(1))
    }
}

impl fmt::Display for MachineState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MachineState::Idle => f.write_str("Idle"),
            MachineState::Run => f.write_str("Run"),
            MachineState::Hold(n) => write!(f, "Hold:{n}"),
            MachineState::Jog => f.write_str("Jog"),
            MachineState::Alarm => f.write_str("Alarm"),
            MachineState::Door(n) => write!(f, "Door:{n}"),
            MachineState::Check => f.write_str("Check"),
            MachineState::Home => f.write_str("Home"),
            MachineState::Sleep => f.write_str("Sleep"),
        }
    }
}

/// Which position field a report carried (`$10` bit 0 selects).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ReportedPosition {
    Machine(Position),
    Work(Position),
}

/// A parsed `<...>` real-time status report. Optional fields are `None` when absent.
#[derive(Clone, Debug, PartialEq)]
pub struct StatusReport {
    pub state: MachineState,
    pub position: ReportedPosition,
    /// `FS:feed,spindle` or `F:feed` (spindle `None`).
    pub feed: Option<f64>,
    pub spindle: Option<f64>,
    /// Triggered input pins, e.g. `"PXYZRHS"`.
    pub pins: Option<String>,
    /// Work coordinate offset; grbl sends it only every 10–30 reports.
    pub wco: Option<Position>,
    /// `Ov:feed,rapid,spindle` percentages.
    pub overrides: Option<[u32; 3]>,
    /// `Bf:blocks,bytes` free planner blocks and RX bytes.
    pub buffer: Option<(u32, u32)>,
    /// `Ln:n` line number.
    pub line: Option<u32>,
    /// `A:SFM` accessory states.
    pub accessories: Option<String>,
}

impl StatusReport {
    /// A report with only the two mandatory fields.
    pub fn new(state: MachineState, mpos: Position) -> Self {
        Self {
            state,
            position: ReportedPosition::Machine(mpos),
            feed: None,
            spindle: None,
            pins: None,
            wco: None,
            overrides: None,
            buffer: None,
            line: None,
            accessories: None,
        }
    }

    /// The machine position, converting `WPos` with this report's `WCO` or else `last_wco`
    /// (`MPos = WPos + WCO`). `None` for a `WPos` report when no offset is known yet.
    pub fn machine_position(&self, last_wco: Option<Position>) -> Option<Position> {
        match self.position {
            ReportedPosition::Machine(p) => Some(p),
            ReportedPosition::Work(w) => self.wco.or(last_wco).map(|wco| w.add(&wco)),
        }
    }

    /// The work position (`WPos = MPos − WCO`), when it can be derived.
    pub fn work_position(&self, last_wco: Option<Position>) -> Option<Position> {
        match self.position {
            ReportedPosition::Work(w) => Some(w),
            ReportedPosition::Machine(m) => self.wco.or(last_wco).map(|wco| m.sub(&wco)),
        }
    }

    /// Formats the report exactly as grbl does (field order of grbl 1.1h's `report_realtime_status`).
    pub fn format(&self) -> String {
        let mut s = format!("<{}", self.state);
        match self.position {
            ReportedPosition::Machine(p) => s += &format!("|MPos:{}", p.format()),
            ReportedPosition::Work(p) => s += &format!("|WPos:{}", p.format()),
        }
        if let Some((b, r)) = self.buffer {
            s += &format!("|Bf:{b},{r}");
        }
        if let Some(n) = self.line {
            s += &format!("|Ln:{n}");
        }
        match (self.feed, self.spindle) {
            (Some(f), Some(sp)) => s += &format!("|FS:{},{}", fmt_rate(f), fmt_rate(sp)),
            (Some(f), None) => s += &format!("|F:{}", fmt_rate(f)),
            _ => {}
        }
        if let Some(p) = &self.pins {
            s += &format!("|Pn:{p}");
        }
        if let Some(w) = self.wco {
            s += &format!("|WCO:{}", w.format());
        }
        if let Some([a, b, c]) = self.overrides {
            s += &format!("|Ov:{a},{b},{c}");
        }
        if let Some(a) = &self.accessories {
            s += &format!("|A:{a}");
        }
        s.push('>');
        s
    }
}

fn fmt_rate(v: f64) -> String {
    // grbl prints rates as integers in mm mode.
    format!("{}", v.round() as i64)
}

/// Why a status report could not be parsed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("malformed status report field {field:?} in {report:?}")]
pub struct StatusParseError {
    pub report: String,
    pub field: String,
}

/// Parses `<State|MPos:…|…>`; the first field is the state, then a position field, then the
/// optional fields in any order. Unknown optional fields are ignored (newer builds add some).
///
/// # Errors
/// [`StatusParseError`] naming the first field that does not parse, a missing state or
/// position, or a duplicate position.
pub fn parse_status(line: &str) -> Result<StatusReport, StatusParseError> {
    let err = |field: &str| StatusParseError { report: line.to_string(), field: field.to_string() };
    let inner = line
        .trim_end_matches(['\r', '\n'])
        .strip_prefix('<')
        .and_then(|s| s.strip_suffix('>'))
        .ok_or_else(|| err("<>"))?;
    let mut fields = inner.split('|');
    let state_field = fields.next().unwrap_or("");
    let state = MachineState::parse(state_field).ok_or_else(|| err(state_field))?;
    let mut report = StatusReport::new(state, Position::ZERO);
    let mut have_pos = false;
    for field in fields {
        let (key, value) = field.split_once(':').ok_or_else(|| err(field))?;
        match key {
            "MPos" | "WPos" => {
                if have_pos {
                    return Err(err(field));
                }
                let p = Position::parse(value).ok_or_else(|| err(field))?;
                report.position = if key == "MPos" { ReportedPosition::Machine(p) } else { ReportedPosition::Work(p) };
                have_pos = true;
            }
            "FS" => {
                let (f, s) = value.split_once(',').ok_or_else(|| err(field))?;
                report.feed = Some(parse_f64(f).ok_or_else(|| err(field))?);
                report.spindle = Some(parse_f64(s).ok_or_else(|| err(field))?);
            }
            "F" => report.feed = Some(parse_f64(value).ok_or_else(|| err(field))?),
            "Pn" => report.pins = Some(value.to_string()),
            "WCO" => report.wco = Some(Position::parse(value).ok_or_else(|| err(field))?),
            "Ov" => {
                let v: Vec<u32> = value.split(',').map(|x| x.parse().ok()).collect::<Option<_>>().ok_or_else(|| err(field))?;
                let arr: [u32; 3] = v.try_into().map_err(|_| err(field))?;
                report.overrides = Some(arr);
            }
            "Bf" => {
                let (b, r) = value.split_once(',').ok_or_else(|| err(field))?;
                report.buffer = Some((b.parse().map_err(|_| err(field))?, r.parse().map_err(|_| err(field))?));
            }
            "Ln" => report.line = Some(value.parse().map_err(|_| err(field))?),
            "A" => report.accessories = Some(value.to_string()),
            _ => {}
        }
    }
    if !have_pos {
        return Err(err("MPos/WPos"));
    }
    Ok(report)
}

macro_rules! code_table {
    (
        $(#[$meta:meta])* $name:ident, $unknown_doc:literal,
        $( $code:literal => $variant:ident, $short:literal, $long:literal; )*
    ) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum $name {
            $( #[doc = $long] $variant, )*
            #[doc = $unknown_doc]
            Unknown(u8),
        }

        impl $name {
            /// The numeric code as it appears on the wire.
            pub fn code(self) -> u8 {
                match self {
                    $( $name::$variant => $code, )*
                    $name::Unknown(c) => c,
                }
            }

            /// The typed value for a code; codes outside the table map to `Unknown`.
            pub fn from_code(code: u8) -> Self {
                match code {
                    $( $code => $name::$variant, )*
                    c => $name::Unknown(c),
                }
            }

            /// The official short name (grbl's csv tables).
            pub fn short(self) -> &'static str {
                match self {
                    $( $name::$variant => $short, )*
                    $name::Unknown(_) => "Unknown",
                }
            }

            /// The official description (grbl's csv tables).
            pub fn description(self) -> &'static str {
                match self {
                    $( $name::$variant => $long, )*
                    $name::Unknown(_) => "Code not in the grbl 1.1 table.",
                }
            }
        }
    };
}

code_table! {
    /// A grbl 1.1 `error:N` code.
    GrblError, "A code outside the grbl 1.1 table.",
    1 => ExpectedCommandLetter, "Expected command letter", "G-code words consist of a letter and a value. Letter was not found.";
    2 => BadNumberFormat, "Bad number format", "Missing the expected G-code word value or numeric value format is not valid.";
    3 => InvalidStatement, "Invalid statement", "Grbl '$' system command was not recognized or supported.";
    4 => NegativeValue, "Value < 0", "Negative value received for an expected positive value.";
    5 => HomingDisabled, "Setting disabled", "Homing cycle failure. Homing is not enabled via settings.";
    6 => StepPulseTooShort, "Value < 3 usec", "Minimum step pulse time must be greater than 3usec.";
    7 => EepromReadFail, "EEPROM read fail. Using defaults", "An EEPROM read failed. Auto-restoring affected EEPROM to default values.";
    8 => NotIdle, "Not idle", "Grbl '$' command cannot be used unless Grbl is IDLE. Ensures smooth operation during a job.";
    9 => GcodeLock, "G-code lock", "G-code commands are locked out during alarm or jog state.";
    10 => SoftLimitsNeedHoming, "Homing not enabled", "Soft limits cannot be enabled without homing also enabled.";
    11 => LineOverflow, "Line overflow", "Max characters per line exceeded. Received command line was not executed.";
    12 => StepRateTooHigh, "Step rate > 30kHz", "Grbl '$' setting value cause the step rate to exceed the maximum supported.";
    13 => CheckDoor, "Check Door", "Safety door detected as opened and door state initiated.";
    14 => LineLengthExceeded, "Line length exceeded", "Build info or startup line exceeded EEPROM line length limit. Line not stored.";
    15 => TravelExceeded, "Travel exceeded", "Jog target exceeds machine travel. Jog command has been ignored.";
    16 => InvalidJog, "Invalid jog command", "Jog command has no '=' or contains prohibited g-code.";
    17 => LaserNeedsPwm, "Setting disabled", "Laser mode requires PWM output.";
    20 => UnsupportedCommand, "Unsupported command", "Unsupported or invalid g-code command found in block.";
    21 => ModalGroupViolation, "Modal group violation", "More than one g-code command from same modal group found in block.";
    22 => UndefinedFeedRate, "Undefined feed rate", "Feed rate has not yet been set or is undefined.";
    23 => IntegerRequired, "Invalid gcode ID:23", "G-code command in block requires an integer value.";
    24 => MultipleAxisCommands, "Invalid gcode ID:24", "More than one g-code command that requires axis words found in block.";
    25 => RepeatedWord, "Invalid gcode ID:25", "Repeated g-code word found in block.";
    26 => NoAxisWords, "Invalid gcode ID:26", "No axis words found in block for g-code command or current modal state which requires them.";
    27 => InvalidLineNumber, "Invalid gcode ID:27", "Line number value is invalid.";
    28 => MissingValueWord, "Invalid gcode ID:28", "G-code command is missing a required value word.";
    29 => WcsUnsupported, "Invalid gcode ID:29", "G59.x work coordinate systems are not supported.";
    30 => G53InvalidMotionMode, "Invalid gcode ID:30", "G53 only allowed with G0 and G1 motion modes.";
    31 => UnusedAxisWords, "Invalid gcode ID:31", "Axis words found in block when no command or current modal state uses them.";
    32 => ArcNoAxisWords, "Invalid gcode ID:32", "G2 and G3 arcs require at least one in-plane axis word.";
    33 => InvalidTarget, "Invalid gcode ID:33", "Motion command target is invalid.";
    34 => ArcRadiusInvalid, "Invalid gcode ID:34", "Arc radius value is invalid.";
    35 => ArcNoOffsetWords, "Invalid gcode ID:35", "G2 and G3 arcs require at least one in-plane offset word.";
    36 => UnusedValueWords, "Invalid gcode ID:36", "Unused value words found in block.";
    37 => ToolLengthOffsetAxis, "Invalid gcode ID:37", "G43.1 dynamic tool length offset is not assigned to configured tool length axis.";
    38 => ToolNumberTooLarge, "Invalid gcode ID:38", "Tool number greater than max supported value.";
}

code_table! {
    /// A grbl 1.1 `ALARM:N` code.
    Alarm, "A code outside the grbl 1.1 table.",
    1 => HardLimit, "Hard limit", "Hard limit has been triggered. Machine position is likely lost due to sudden halt. Re-homing is highly recommended.";
    2 => SoftLimit, "Soft limit", "Soft limit alarm. G-code motion target exceeds machine travel. Machine position retained. Alarm may be safely unlocked.";
    3 => AbortDuringCycle, "Abort during cycle", "Reset while in motion. Machine position is likely lost due to sudden halt. Re-homing is highly recommended.";
    4 => ProbeFailInitial, "Probe fail", "Probe fail. Probe is not in the expected initial state before starting probe cycle when G38.2 and G38.3 is not triggered and G38.4 and G38.5 is triggered.";
    5 => ProbeFailContact, "Probe fail", "Probe fail. Probe did not contact the workpiece within the programmed travel for G38.2 and G38.4.";
    6 => HomingFailReset, "Homing fail", "Homing fail. The active homing cycle was reset.";
    7 => HomingFailDoor, "Homing fail", "Homing fail. Safety door was opened during homing cycle.";
    8 => HomingFailPullOff, "Homing fail", "Homing fail. Pull off travel failed to clear limit switch. Try increasing pull-off setting or check wiring.";
    9 => HomingFailApproach, "Homing fail", "Homing fail. Could not find limit switch within search distances. Try increasing max travel, decreasing pull-off distance, or check wiring.";
    10 => HomingFailDualAxis, "Homing fail", "Homing fail. On dual axis machines, could not find the second limit switch for self-squaring.";
}

impl Alarm {
    /// Hard and soft limit alarms: grbl prints `[MSG:Reset to continue]` and ignores every
    /// input, `?` included, until a soft reset (`0x18`).
    pub fn is_critical(self) -> bool {
        matches!(self, Alarm::HardLimit | Alarm::SoftLimit)
    }
}

impl fmt::Display for GrblError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error:{} ({})", self.code(), self.description())
    }
}

impl fmt::Display for Alarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ALARM:{} ({})", self.code(), self.description())
    }
}

/// One line received from grbl.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    /// `ok`: the line was executed or queued.
    Ok,
    /// `error:N`: the line was rejected.
    Error(GrblError),
    /// `<...>`: a real-time status report.
    Status(StatusReport),
    /// `<...>` that does not parse.
    MalformedStatus(StatusParseError),
    /// `ALARM:N`.
    Alarm(Alarm),
    /// `[MSG:text]`.
    Msg(String),
    /// `[GC:modal state]` (answer to `$G`).
    ParserState(String),
    /// `[VER:version:info]`.
    Version(String),
    /// `[OPT:codes,blocks,bytes]`.
    Options(String),
    /// Any other bracketed feedback (`[G54:…]`, `[PRB:…]`, `[echo:…]`, …), text inside brackets.
    Feedback(String),
    /// `$N=value` from a `$$` dump.
    Setting { number: u16, value: String },
    /// `Grbl 1.1h ['$' for help]`: the firmware (re)started.
    Banner { version: String },
    /// `>line:ok` startup-line execution.
    StartupLine(String),
    /// Anything else (line noise, wrong baud rate, another firmware).
    Unknown(String),
}

impl Message {
    /// `ok` and `error:N` answer a line; everything else is pushed.
    pub fn is_response(&self) -> bool {
        matches!(self, Message::Ok | Message::Error(_))
    }
}

/// Parses one received line (trailing `\r\n` optional). Never fails: unrecognised text is
/// [`Message::Unknown`].
pub fn parse_line(line: &str) -> Message {
    let line = line.trim_end_matches(['\r', '\n']);
    if line == "ok" {
        return Message::Ok;
    }
    if let Some(code) = line.strip_prefix("error:") {
        return match code.parse::<u8>() {
            Ok(c) => Message::Error(GrblError::from_code(c)),
            Err(_) => Message::Unknown(line.to_string()),
        };
    }
    if let Some(code) = line.strip_prefix("ALARM:") {
        return match code.parse::<u8>() {
            Ok(c) => Message::Alarm(Alarm::from_code(c)),
            Err(_) => Message::Unknown(line.to_string()),
        };
    }
    if line.starts_with('<') {
        return match parse_status(line) {
            Ok(r) => Message::Status(r),
            Err(e) => Message::MalformedStatus(e),
        };
    }
    if let Some(inner) = line.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
        let (tag, body) = inner.split_once(':').unwrap_or((inner, ""));
        return match tag {
            "MSG" => Message::Msg(body.to_string()),
            "GC" => Message::ParserState(body.to_string()),
            "VER" => Message::Version(body.to_string()),
            "OPT" => Message::Options(body.to_string()),
            _ => Message::Feedback(inner.to_string()),
        };
    }
    if let Some(rest) = line.strip_prefix("Grbl ") {
        let version = rest.split_whitespace().next().unwrap_or("").to_string();
        if !version.is_empty() {
            return Message::Banner { version };
        }
    }
    if let Some(rest) = line.strip_prefix('$') {
        if let Some((n, v)) = rest.split_once('=') {
            if let Ok(number) = n.parse::<u16>() {
                return Message::Setting { number, value: v.to_string() };
            }
        }
    }
    if let Some(rest) = line.strip_prefix('>') {
        return Message::StartupLine(rest.to_string());
    }
    Message::Unknown(line.to_string())
}

/// Single-byte real-time commands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Realtime {
    /// `?` status report request.
    StatusQuery,
    /// `~` cycle start / resume.
    CycleStart,
    /// `!` feed hold.
    FeedHold,
    /// `0x18` (Ctrl-X) soft reset.
    SoftReset,
    /// `0x85` jog cancel.
    JogCancel,
}

impl Realtime {
    pub fn byte(self) -> u8 {
        match self {
            Realtime::StatusQuery => b'?',
            Realtime::CycleStart => b'~',
            Realtime::FeedHold => b'!',
            Realtime::SoftReset => 0x18,
            Realtime::JogCancel => 0x85,
        }
    }

    pub fn from_byte(b: u8) -> Option<Realtime> {
        match b {
            b'?' => Some(Realtime::StatusQuery),
            b'~' => Some(Realtime::CycleStart),
            b'!' => Some(Realtime::FeedHold),
            0x18 => Some(Realtime::SoftReset),
            0x85 => Some(Realtime::JogCancel),
            _ => None,
        }
    }

    /// True for every byte grbl 1.1 intercepts as real-time (including overrides this module
    /// does not name): such bytes must never appear inside a line.
    pub fn is_realtime_byte(b: u8) -> bool {
        matches!(b, b'?' | b'~' | b'!' | 0x18) || b >= 0x80
    }
}

/// A move's speed: rapid (`G0`, each axis at its `$11x` max rate) or feed (`G1 F…`, mm/min).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Motion {
    Rapid,
    Feed(f64),
}

/// Line commands a rig sends. [`Command::encode`] gives the text without the newline.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// `G90` absolute distance mode.
    Absolute,
    /// `G91` relative distance mode.
    Relative,
    /// `G0`/`G1` in the current distance mode.
    Move { motion: Motion, targets: Vec<(Axis, f64)> },
    /// `G53 G0`/`G53 G1`: absolute **machine** coordinates regardless of work offsets and G91.
    MoveMachine { motion: Motion, targets: Vec<(Axis, f64)> },
    /// `G4 P<s>`: dwell; `G4 P0` answers only once the planner is empty (motion sync).
    Dwell(f64),
    /// `$H` homing cycle.
    Home,
    /// `$X` kill alarm lock.
    Unlock,
    /// `$$` settings dump.
    Settings,
    /// `$N=value`.
    SetSetting(u16, f64),
    /// `$I` build info.
    BuildInfo,
    /// `$G` parser state.
    ParserState,
    /// `$J=G91 …` relative jog at `feed` mm/min.
    JogRelative { targets: Vec<(Axis, f64)>, feed: f64 },
}

impl Command {
    /// The line to send, without its newline.
    pub fn encode(&self) -> String {
        fn words(targets: &[(Axis, f64)]) -> String {
            targets.iter().map(|(a, v)| format!(" {}{}", a.letter(), fmt_num(*v))).collect()
        }
        fn motion(m: Motion, targets: &[(Axis, f64)]) -> String {
            match m {
                Motion::Rapid => format!("G0{}", words(targets)),
                Motion::Feed(f) => format!("G1{} F{}", words(targets), fmt_num(f)),
            }
        }
        match self {
            Command::Absolute => "G90".into(),
            Command::Relative => "G91".into(),
            Command::Move { motion: m, targets } => motion(*m, targets),
            Command::MoveMachine { motion: m, targets } => format!("G53 {}", motion(*m, targets)),
            Command::Dwell(s) => {
                if *s == 0.0 {
                    "G4 P0".into()
                } else {
                    format!("G4 P{}", fmt_num(*s))
                }
            }
            Command::Home => "$H".into(),
            Command::Unlock => "$X".into(),
            Command::Settings => "$$".into(),
            Command::SetSetting(n, v) => {
                if v.fract() == 0.0 && v.abs() < 1e9 {
                    format!("${n}={}", *v as i64)
                } else {
                    format!("${n}={}", fmt_num(*v))
                }
            }
            Command::BuildInfo => "$I".into(),
            Command::ParserState => "$G".into(),
            Command::JogRelative { targets, feed } => format!("$J=G91{} F{}", words(targets), fmt_num(*feed)),
        }
    }
}

/// A line ready to send: the text plus `\n`.
pub fn frame(line: &str) -> Vec<u8> {
    let mut v = Vec::with_capacity(line.len() + 1);
    v.extend_from_slice(line.as_bytes());
    v.push(b'\n');
    v
}

/// The banner grbl 1.1h prints on power-up and after a soft reset, including its leading
/// blank line.
pub const BANNER: &str = "\r\nGrbl 1.1h ['$' for help]\r\n";

/// grbl's line buffer length; a longer line is answered `error:11`.
pub const LINE_BUFFER_SIZE: usize = 80;

/// grbl's serial receive buffer.
pub const RX_BUFFER_SIZE: usize = 128;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn responses() {
        assert_eq!(parse_line("ok\r\n"), Message::Ok);
        assert_eq!(parse_line("error:2"), Message::Error(GrblError::BadNumberFormat));
        assert_eq!(parse_line("error:9\r\n"), Message::Error(GrblError::GcodeLock));
        assert_eq!(parse_line("error:99"), Message::Error(GrblError::Unknown(99)));
        assert_eq!(parse_line("error:x"), Message::Unknown("error:x".into()));
        assert!(parse_line("ok").is_response());
        assert!(!parse_line("ALARM:1").is_response());
    }

    #[test]
    fn error_table_is_complete_and_round_trips() {
        for c in (1..=17).chain(20..=38) {
            let e = GrblError::from_code(c);
            assert!(!matches!(e, GrblError::Unknown(_)), "code {c} missing");
            assert_eq!(e.code(), c);
            assert!(!e.description().is_empty());
        }
        for c in [0u8, 18, 19, 39, 255] {
            assert_eq!(GrblError::from_code(c), GrblError::Unknown(c));
        }
        assert_eq!(GrblError::from_code(11).short(), "Line overflow");
        assert_eq!(GrblError::from_code(15).short(), "Travel exceeded");
        assert_eq!(GrblError::from_code(5).to_string(), "error:5 (Homing cycle failure. Homing is not enabled via settings.)");
    }

    #[test]
    fn alarm_table_and_criticality() {
        for c in 1..=10 {
            let a = Alarm::from_code(c);
            assert_eq!(a.code(), c);
            assert!(!matches!(a, Alarm::Unknown(_)));
            assert_eq!(a.is_critical(), c <= 2, "alarm {c}");
        }
        assert_eq!(parse_line("ALARM:2\r\n"), Message::Alarm(Alarm::SoftLimit));
        assert_eq!(parse_line("ALARM:3"), Message::Alarm(Alarm::AbortDuringCycle));
        assert_eq!(parse_line("ALARM:11"), Message::Alarm(Alarm::Unknown(11)));
        assert_eq!(Alarm::HardLimit.short(), "Hard limit");
    }

    #[test]
    fn push_messages_from_grbl_md() {
        assert_eq!(parse_line("Grbl 1.1h ['$' for help]\r\n"), Message::Banner { version: "1.1h".into() });
        assert_eq!(parse_line("[MSG:'$H'|'$X' to unlock]"), Message::Msg("'$H'|'$X' to unlock".into()));
        assert_eq!(parse_line("[MSG:Caution: Unlocked]"), Message::Msg("Caution: Unlocked".into()));
        assert_eq!(parse_line("[MSG:Reset to continue]"), Message::Msg("Reset to continue".into()));
        assert_eq!(parse_line("[VER:1.1h.20190830:]"), Message::Version("1.1h.20190830:".into()));
        assert_eq!(parse_line("[OPT:V,15,128]"), Message::Options("V,15,128".into()));
        assert_eq!(
            parse_line("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"),
            Message::ParserState("G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0".into())
        );
        assert_eq!(parse_line("[G54:0.000,0.000,0.000]"), Message::Feedback("G54:0.000,0.000,0.000".into()));
        assert_eq!(parse_line("$0=10"), Message::Setting { number: 0, value: "10".into() });
        assert_eq!(parse_line("$27=1.000\r\n"), Message::Setting { number: 27, value: "1.000".into() });
        assert_eq!(parse_line(">G20G54:ok"), Message::StartupLine("G20G54:ok".into()));
        assert_eq!(parse_line("garbage"), Message::Unknown("garbage".into()));
        assert_eq!(parse_line("$H"), Message::Unknown("$H".into()));
    }

    #[test]
    fn status_reports_from_grbl_md() {
        let m = parse_line("<Idle|MPos:0.000,0.000,0.000|FS:0,0|Pn:PXYZRHS|WCO:0.000,0.000,0.000>");
        let Message::Status(r) = m else { panic!("{m:?}") };
        assert_eq!(r.state, MachineState::Idle);
        assert_eq!(r.position, ReportedPosition::Machine(Position::ZERO));
        assert_eq!((r.feed, r.spindle), (Some(0.0), Some(0.0)));
        assert_eq!(r.pins.as_deref(), Some("PXYZRHS"));
        assert_eq!(r.wco, Some(Position::ZERO));

        let r = parse_status("<Run|MPos:0.000,0.000,0.000|FS:54,0|Pn:PXYZRHS|Ov:100,100,100>").unwrap();
        assert_eq!(r.state, MachineState::Run);
        assert_eq!(r.overrides, Some([100, 100, 100]));
        assert_eq!(r.feed, Some(54.0));

        let r = parse_status("<Idle|MPos:10.000,0.000,0.000|FS:0,0|Pn:PXYZRHS>").unwrap();
        assert_eq!(r.machine_position(None), Some(Position([10.0, 0.0, 0.0])));
        assert_eq!(parse_status("<Hold:1|MPos:1.000,2.000,3.000|FS:0,0>").unwrap().state, MachineState::Hold(1));
        assert_eq!(parse_status("<Door:3|MPos:1.000,2.000,3.000|FS:0,0>").unwrap().state, MachineState::Door(3));
        for s in ["Idle", "Run", "Jog", "Alarm", "Check", "Home", "Sleep", "Hold:0", "Door:0"] {
            let r = parse_status(&format!("<{s}|MPos:0.000,0.000,0.000>")).unwrap();
            assert_eq!(r.state.to_string(), s);
        }
    }

    #[test]
    fn status_optional_fields_any_order_and_wpos() {
        let r = parse_status("<Jog|WPos:1.000,2.000,-3.500|Ln:42|WCO:-1.000,0.500,0.000|A:SFM|Bf:15,128|F:300>").unwrap();
        assert_eq!(r.state, MachineState::Jog);
        assert_eq!(r.position, ReportedPosition::Work(Position([1.0, 2.0, -3.5])));
        assert_eq!(r.line, Some(42));
        assert_eq!(r.buffer, Some((15, 128)));
        assert_eq!(r.feed, Some(300.0));
        assert_eq!(r.spindle, None);
        assert_eq!(r.accessories.as_deref(), Some("SFM"));
        // MPos = WPos + WCO
        assert_eq!(r.machine_position(None), Some(Position([0.0, 2.5, -3.5])));
        let no_wco = parse_status("<Idle|WPos:1.000,2.000,3.000|FS:0,0>").unwrap();
        assert_eq!(no_wco.machine_position(None), None);
        assert_eq!(no_wco.machine_position(Some(Position([1.0, 1.0, 1.0]))), Some(Position([2.0, 3.0, 4.0])));
        // WPos = MPos − WCO
        let m = parse_status("<Idle|MPos:5.000,5.000,5.000|WCO:1.000,2.000,3.000>").unwrap();
        assert_eq!(m.work_position(None), Some(Position([4.0, 3.0, 2.0])));
    }

    #[test]
    fn malformed_status_is_reported_not_panicked() {
        for bad in ["<>", "<Idle>", "<Bogus|MPos:0,0,0>", "<Idle|MPos:a,b,c>", "<Idle|MPos:1,2>", "<Idle|FS:1|MPos:0,0,0>", "<Idle|MPos:0,0,0|MPos:0,0,0>", "<Run:1|MPos:0,0,0>"] {
            assert!(matches!(parse_line(bad), Message::MalformedStatus(_)), "{bad}");
        }
    }

    #[test]
    fn encoders() {
        let t = vec![(Axis::X, 10.0), (Axis::Z, -2.5)];
        assert_eq!(Command::Move { motion: Motion::Rapid, targets: t.clone() }.encode(), "G0 X10.000 Z-2.500");
        assert_eq!(Command::Move { motion: Motion::Feed(300.0), targets: vec![(Axis::Y, 0.0004)] }.encode(), "G1 Y0.000 F300.000");
        assert_eq!(Command::MoveMachine { motion: Motion::Rapid, targets: t }.encode(), "G53 G0 X10.000 Z-2.500");
        assert_eq!(Command::Move { motion: Motion::Rapid, targets: vec![(Axis::X, -0.0001)] }.encode(), "G0 X0.000");
        assert_eq!(Command::Dwell(0.0).encode(), "G4 P0");
        assert_eq!(Command::Dwell(0.01).encode(), "G4 P0.010");
        assert_eq!(Command::Home.encode(), "$H");
        assert_eq!(Command::Unlock.encode(), "$X");
        assert_eq!(Command::Settings.encode(), "$$");
        assert_eq!(Command::BuildInfo.encode(), "$I");
        assert_eq!(Command::ParserState.encode(), "$G");
        assert_eq!(Command::Absolute.encode(), "G90");
        assert_eq!(Command::Relative.encode(), "G91");
        assert_eq!(Command::SetSetting(22, 1.0).encode(), "$22=1");
        assert_eq!(Command::SetSetting(27, 1.5).encode(), "$27=1.500");
        assert_eq!(Command::JogRelative { targets: vec![(Axis::X, -2.0)], feed: 300.0 }.encode(), "$J=G91 X-2.000 F300.000");
        assert_eq!(frame("$H"), b"$H\n");
        assert_eq!(Realtime::StatusQuery.byte(), b'?');
        assert_eq!(Realtime::CycleStart.byte(), b'~');
        assert_eq!(Realtime::FeedHold.byte(), b'!');
        assert_eq!(Realtime::SoftReset.byte(), 0x18);
        assert_eq!(Realtime::JogCancel.byte(), 0x85);
        for r in [Realtime::StatusQuery, Realtime::CycleStart, Realtime::FeedHold, Realtime::SoftReset, Realtime::JogCancel] {
            assert_eq!(Realtime::from_byte(r.byte()), Some(r));
            assert!(Realtime::is_realtime_byte(r.byte()));
        }
        assert!(!Realtime::is_realtime_byte(b'G'));
    }

    fn arb_state() -> impl Strategy<Value = MachineState> {
        prop_oneof![
            Just(MachineState::Idle),
            Just(MachineState::Run),
            (0u8..2).prop_map(MachineState::Hold),
            Just(MachineState::Jog),
            Just(MachineState::Alarm),
            (0u8..4).prop_map(MachineState::Door),
            Just(MachineState::Check),
            Just(MachineState::Home),
            Just(MachineState::Sleep),
        ]
    }

    fn arb_pos() -> impl Strategy<Value = Position> {
        // Thousandths, so the three-decimal text represents the value exactly.
        prop::array::uniform3(-999_999i32..999_999).prop_map(|a| Position(a.map(|v| v as f64 / 1000.0)))
    }

    fn arb_report() -> impl Strategy<Value = StatusReport> {
        (
            arb_state(),
            arb_pos(),
            any::<bool>(),
            proptest::option::of((0u32..100_000, proptest::option::of(0u32..30_000))),
            proptest::option::of("[PXYZDHRS]{1,8}"),
            proptest::option::of(arb_pos()),
            proptest::option::of(prop::array::uniform3(10u32..200)),
            proptest::option::of((0u32..16, 0u32..128)),
            proptest::option::of(0u32..100_000),
            proptest::option::of("[SCFM]{1,4}"),
        )
            .prop_map(|(state, p, work, fs, pins, wco, ov, bf, ln, acc)| StatusReport {
                state,
                position: if work { ReportedPosition::Work(p) } else { ReportedPosition::Machine(p) },
                feed: fs.map(|(f, _)| f as f64),
                spindle: fs.and_then(|(_, s)| s.map(|s| s as f64)),
                pins,
                wco,
                overrides: ov,
                buffer: bf,
                line: ln,
                accessories: acc,
            })
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
            let s = String::from_utf8_lossy(&bytes);
            for line in s.split('\n') {
                let _ = parse_line(line);
            }
        }

        #[test]
        fn arbitrary_status_like_lines_never_panic(body in "[A-Za-z0-9:|,.\\-]{0,80}") {
            let _ = parse_line(&format!("<{body}>"));
        }

        #[test]
        fn status_round_trips(r in arb_report()) {
            let text = r.format();
            let parsed = parse_status(&text).map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(parsed, r);
        }
    }
}
