//! The simulated firmware's status reports (`$10` mask, planner and RX buffer space, `WCO:`
//! and `Ov:` every few reports as grbl sends them) and the line-noise fault that corrupts them
//! ([`super::Faults::corrupt_reports_ppm`]).

use super::super::protocol::{MachineState, Position, ReportedPosition, StatusReport, RX_BUFFER_SIZE};
use super::{Firmware, PLANNER_BLOCKS};

impl Firmware {
    pub(super) fn report(&mut self) -> String {
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

    pub(super) fn noise(&mut self) -> u64 {
        let x = &mut self.noise_rng;
        *x ^= *x << 13;
        *x ^= *x >> 7;
        *x ^= *x << 17;
        *x
    }

    /// Transmits `report` damaged as a noisy line would (see [`Faults::corrupt_reports_ppm`]).
    pub(super) fn corrupt_line(&mut self, report: &str) {
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
}
