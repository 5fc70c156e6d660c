//! The simulated firmware's motion in real time: the 15-block planner and pending lines
//! (a full planner or a dwell delays the `ok`), trapezoid profiles integrated in 0.5 ms steps
//! limited by `$110..112` (mm/min) and `$120..122` (mm/s²), feed hold and jog cancel,
//! homing's duration and its missing-switch fault, and [`Firmware::tick`], which also answers
//! a pending `?`.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::super::protocol::{Alarm, MachineState};
use super::{Active, Block, Faults, Firmware, Pending, PLANNER_BLOCKS};

impl Firmware {
    pub(super) fn process_pending(&mut self, now: Instant) {
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
}
