//! The simulated firmware's G-code: parsing a block into its words (modal groups, repeated
//! words and jog restrictions checked as grbl does) and executing it: a jog (`$J=`), a dwell
//! (`G4 P…`) or modal changes and a move (`G0`/`G1`, `G53`, `G90`/`G91`), with soft limits.

use super::super::protocol::{Alarm, GrblError, MachineState};
use super::{Block, Firmware, Pending, EPS};

/// The words of one G-code block.
#[derive(Default)]
struct Words {
    /// `Some(false)` G0, `Some(true)` G1.
    motion: Option<bool>,
    /// Non-modal group 0: 4 = dwell, 53 = machine coordinates.
    group0: Option<u32>,
    /// `Some(true)` G90, `Some(false)` G91.
    distance: Option<bool>,
    axes: [Option<f64>; 3],
    feed: Option<f64>,
    p: Option<f64>,
    seen_letters: Vec<char>,
}

impl Words {
    /// Parses a block (`jog`: the text after `$J=`, which allows fewer words).
    fn parse(line: &str, jog: bool) -> Result<Self, GrblError> {
        let mut w = Self::default();
        let mut rest = line;
        while !rest.is_empty() {
            let mut chars = rest.chars();
            let letter = chars.next().unwrap_or(' ');
            if !letter.is_ascii_uppercase() {
                return Err(GrblError::ExpectedCommandLetter);
            }
            let (value, tail) = parse_number(chars.as_str()).ok_or(GrblError::BadNumberFormat)?;
            rest = tail;
            match letter {
                'G' => w.g_word(value, jog)?,
                'M' if !jog => match value as i64 {
                    5 | 9 => {}
                    _ => return Err(GrblError::UnsupportedCommand),
                },
                'X' | 'Y' | 'Z' | 'F' | 'P' | 'N' | 'S' | 'T' => w.value_word(letter, value, jog)?,
                _ => return Err(if jog { GrblError::InvalidJog } else { GrblError::UnsupportedCommand }),
            }
        }
        Ok(w)
    }

    /// A `G` word: one command per modal group.
    fn g_word(&mut self, value: f64, jog: bool) -> Result<(), GrblError> {
        let int = value.trunc();
        if (value - int).abs() > 1e-6 {
            return Err(GrblError::UnsupportedCommand);
        }
        match int as i64 {
            0 | 1 => {
                if jog {
                    return Err(GrblError::InvalidJog);
                }
                if self.motion.is_some() {
                    return Err(GrblError::ModalGroupViolation);
                }
                self.motion = Some(int as i64 == 1);
            }
            4 | 53 => {
                if jog && int as i64 == 4 {
                    return Err(GrblError::InvalidJog);
                }
                if self.group0.is_some() {
                    return Err(GrblError::ModalGroupViolation);
                }
                self.group0 = Some(int as u32);
            }
            90 | 91 => {
                if self.distance.is_some() {
                    return Err(GrblError::ModalGroupViolation);
                }
                self.distance = Some(int as i64 == 90);
            }
            17 | 21 | 54 | 94 if !jog => {}
            21 if jog => {}
            _ => return Err(if jog { GrblError::InvalidJog } else { GrblError::UnsupportedCommand }),
        }
        Ok(())
    }

    /// An axis or value word (`X Y Z F P N S T`), each at most once per block.
    fn value_word(&mut self, letter: char, value: f64, jog: bool) -> Result<(), GrblError> {
        if self.seen_letters.contains(&letter) {
            return Err(GrblError::RepeatedWord);
        }
        self.seen_letters.push(letter);
        match letter {
            'X' => self.axes[0] = Some(value),
            'Y' => self.axes[1] = Some(value),
            'Z' => self.axes[2] = Some(value),
            'F' => {
                if value < 0.0 {
                    return Err(GrblError::NegativeValue);
                }
                self.feed = Some(value)
            }
            'P' => {
                if jog {
                    return Err(GrblError::InvalidJog);
                }
                if value < 0.0 {
                    return Err(GrblError::NegativeValue);
                }
                self.p = Some(value)
            }
            _ => {
                if jog {
                    return Err(GrblError::InvalidJog);
                }
            }
        }
        Ok(())
    }

    fn has_axes(&self) -> bool {
        self.axes.iter().any(Option::is_some)
    }
}

impl Firmware {
    /// Parses and executes one G-code block (`jog`: the text after `$J=`).
    pub(super) fn gcode(&mut self, line: &str, jog: bool) -> Result<(), GrblError> {
        let w = Words::parse(line, jog)?;
        if jog {
            return self.jog_block(&w);
        }
        if w.group0 == Some(4) {
            return self.dwell_block(&w);
        }
        self.motion_block(&w)
    }

    /// `$J=…`: a feed and axis words are required; outside travel with soft limits on is
    /// refused (`error:15`, no alarm).
    fn jog_block(&mut self, w: &Words) -> Result<(), GrblError> {
        let feed = w.feed.ok_or(GrblError::UndefinedFeedRate)?;
        if !w.has_axes() {
            return Err(GrblError::InvalidJog);
        }
        let abs = w.distance.unwrap_or(self.absolute);
        let target = self.target(&w.axes, abs, w.group0 == Some(53));
        if self.setting(20) != 0.0 && !self.within_travel(&target) {
            return Err(GrblError::TravelExceeded);
        }
        self.pending = Some(Pending::Planner(Block { target, feed: Some(feed) }, true));
        Ok(())
    }

    /// `G4 P…`: waits for the planner to empty, then `P` seconds (skipped in check mode).
    fn dwell_block(&mut self, w: &Words) -> Result<(), GrblError> {
        let secs = w.p.ok_or(GrblError::MissingValueWord)?;
        if w.has_axes() {
            return Err(GrblError::UnusedAxisWords);
        }
        if let Some(d) = w.distance {
            self.absolute = d;
        }
        if self.state == MachineState::Check {
            self.ok(); // check mode skips dwells
            return Ok(());
        }
        self.pending = Some(Pending::Dwell { secs, until: None });
        Ok(())
    }

    /// Modal changes, then a move to the block's target if it has axis words (a soft-limit
    /// target raises the critical `ALARM:2`).
    fn motion_block(&mut self, w: &Words) -> Result<(), GrblError> {
        let has_axes = w.has_axes();
        if w.p.is_some() {
            return Err(GrblError::UnusedValueWords);
        }
        if let Some(d) = w.distance {
            self.absolute = d;
        }
        if let Some(f) = w.feed {
            self.feed = f;
        }
        if let Some(m) = w.motion {
            self.motion_g1 = m;
        }
        if w.group0 == Some(53) && w.motion.is_none() && !has_axes {
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
        let target = self.target(&w.axes, self.absolute, w.group0 == Some(53));
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
}

/// Parses a grbl number (`strtod` subset: sign, digits, one dot) at the start of `s`.
pub(super) fn parse_number(s: &str) -> Option<(f64, &str)> {
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
