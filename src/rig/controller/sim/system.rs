//! The simulated firmware's `$` system commands: help, the settings dump and writes (with
//! grbl's checks), check mode, build info, parser state, offsets, unlock, homing and jogs,
//! each under grbl's state rules.

use std::time::{Duration, Instant};

use super::super::protocol::{fmt_num, Alarm, GrblError, MachineState};
use super::gcode::parse_number;
use super::{Firmware, Homing, Pending};

/// Settings grbl stores as integers.
fn is_integer_setting(n: u16) -> bool {
    matches!(n, 0..=6 | 10 | 13 | 20..=23 | 26 | 30..=32)
}

impl Firmware {
    fn idle_or_alarm(&self) -> bool {
        matches!(self.state, MachineState::Idle | MachineState::Alarm)
    }

    /// Executes `$cmd` (the text after the `$`).
    pub(super) fn system(&mut self, cmd: &str, now: Instant) {
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
            "C" => self.toggle_check_mode(),
            // `$#`, `$I`, `$H` and setting writes need Idle or Alarm (grbl checks that first)
            "#" | "I" | "H" if !self.idle_or_alarm() => self.error(GrblError::NotIdle),
            "I" => {
                self.line("[VER:1.1h.20190830:]");
                self.line("[OPT:V,15,128]");
                self.ok()
            }
            "G" => self.parser_state(),
            "#" => self.offsets(),
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
            _ => self.jog_or_setting(cmd, now),
        }
    }

    /// `$C`: enters check mode from `Idle`; leaving it resets grbl.
    fn toggle_check_mode(&mut self) {
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

    /// `$G`: the parser's modal state.
    fn parser_state(&mut self) {
        let g = format!(
            "[GC:G{} G54 G17 G21 G{} G94 M5 M9 T0 F{} S0]",
            if self.motion_g1 { 1 } else { 0 },
            if self.absolute { 90 } else { 91 },
            self.feed.round() as i64
        );
        self.line(&g);
        self.ok()
    }

    /// `$#`: the coordinate offsets (all zero here).
    fn offsets(&mut self) {
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

    /// `$J=…` (a jog, from `Idle` or `Jog`) or `$N=v` (a setting write); anything else is an
    /// invalid statement.
    fn jog_or_setting(&mut self, cmd: &str, now: Instant) {
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

    pub(super) fn settings_dump(&mut self) {
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
    pub(super) fn homing_alarm(&mut self, alarm: Alarm) {
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
}
