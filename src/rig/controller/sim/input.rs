//! The simulated firmware's receive side: real-time bytes (`?`, `!`, `~`, `0x18`, `0x85`)
//! act at once; the rest enters the 128-byte RX buffer, and grbl's protocol layer (comments
//! and whitespace dropped, upper-cased, at most 79 characters) hands each line to the `$`
//! commands (`system`) or the G-code parser (`gcode`).

use std::time::Instant;

use super::super::protocol::{GrblError, MachineState, LINE_BUFFER_SIZE, RX_BUFFER_SIZE};
use super::Firmware;

impl Firmware {
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

    pub(super) fn process_lines(&mut self, now: Instant) {
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
}
