//! The simulated lift: the column, its DC motor and the board that drives it, on a
//! pseudo-terminal at `<device dir>/lift`, speaking the board's protocol. Written from the
//! protocol's description (the lift crate's `board` module documents it), not from its code.
//!
//! The board runs the motor at the commanded speed (a speed loop on the halls: the column
//! follows with a 50 ms lag, up to its top speed), stops it at either limit switch in that
//! direction and when no command came for 100 ms (its watchdog), counts the halls (up
//! positive, from where it stood at power-on), and reports every 10 ms. Something under the
//! column (`--lift-obstacle-at M`: a hand at height M) stops it going down there; the motor
//! then stalls and draws its stall current, as the real one would.

use crate::description::LiftDescription;
use crate::device::SerialDevice;
use serde::Serialize;

const START: u8 = 0xA5;
const DRIVE: u8 = 0x01;
const STATUS: u8 = 0x81;
/// The board stops the motor when no DRIVE came for this long, s.
const WATCHDOG_S: f64 = 0.1;
/// A STATUS every, s.
const STATUS_EVERY_S: f64 = 0.01;
/// Physics step, s.
const STEP_S: f64 = 0.001;
/// The motor's current stalled, A.
const STALL_A: f64 = 8.0;

/// What the simulated lift did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LiftReport {
    /// Height now, m above the lower switch.
    pub height_m: f64,
    /// DRIVE frames taken.
    pub drives: u64,
    /// Frames refused (CRC, length, type).
    pub bad_frames: u64,
    /// Times the watchdog stopped a running motor.
    pub watchdog_stops: u64,
    /// Seconds the motor pushed down on the obstacle (the time a hand under it was pressed).
    pub pressed_s: f64,
    /// Longest single press, s.
    pub longest_press_s: f64,
    /// Times the column came down on the obstacle (each press counted once).
    pub presses: u64,
}

/// The column and its board, sans-IO.
#[derive(Debug, Clone)]
pub struct LiftBoard {
    d: LiftDescription,
    h: f64,
    v: f64,
    command: f64,
    last_command: f64,
    t: f64,
    next_status: f64,
    /// Something solid under the column at this height, m.
    pub obstacle_m: Option<f64>,
    rx: Vec<u8>,
    press_s: f64,
    report: LiftReport,
}

fn crc16(bytes: &[u8]) -> u16 {
    // CRC-16/CCITT-FALSE, as the protocol names it.
    bytes.iter().fold(0xFFFF_u16, |mut crc, &b| {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
        crc
    })
}

impl LiftBoard {
    /// The lift of the description, at its start height.
    pub fn new(d: &LiftDescription) -> LiftBoard {
        LiftBoard {
            h: d.start_m,
            d: d.clone(),
            v: 0.0,
            command: 0.0,
            last_command: f64::NEG_INFINITY,
            t: 0.0,
            next_status: 0.0,
            obstacle_m: None,
            rx: Vec::new(),
            press_s: 0.0,
            report: LiftReport::default(),
        }
    }

    /// What it did so far.
    pub fn report(&self) -> LiftReport {
        LiftReport {
            height_m: self.h,
            ..self.report
        }
    }

    fn take_frames(&mut self, now: f64) {
        loop {
            let Some(start) = self.rx.iter().position(|&b| b == START) else {
                self.rx.clear();
                return;
            };
            self.rx.drain(..start);
            if self.rx.len() < 3 {
                return;
            }
            let n = usize::from(self.rx[2]);
            if self.rx.len() < 5 + n {
                if n > 16 {
                    self.report.bad_frames += 1;
                    self.rx.drain(..1);
                    continue;
                }
                return;
            }
            let crc = u16::from_le_bytes([self.rx[3 + n], self.rx[4 + n]]);
            if crc == crc16(&self.rx[1..3 + n]) && self.rx[1] == DRIVE && n == 2 {
                let tenths_mm = i16::from_le_bytes([self.rx[3], self.rx[4]]);
                self.command = f64::from(tenths_mm) * 1e-4;
                self.last_command = now;
                self.report.drives += 1;
                self.rx.drain(..5 + n);
            } else {
                self.report.bad_frames += 1;
                self.rx.drain(..1);
            }
        }
    }

    /// One physics step: the watchdog, the speed loop, the switches, the obstacle.
    fn step(&mut self) -> f64 {
        if self.command != 0.0 && self.t - self.last_command > WATCHDOG_S {
            self.command = 0.0;
            self.report.watchdog_stops += 1;
        }
        let mut target = self
            .command
            .clamp(-self.d.max_speed_m_s, self.d.max_speed_m_s);
        if (target < 0.0 && self.h <= 0.0) || (target > 0.0 && self.h >= self.d.travel_m) {
            target = 0.0;
        }
        self.v += (target - self.v) * (STEP_S / 0.05).min(1.0);
        let next = (self.h + self.v * STEP_S).clamp(0.0, self.d.travel_m);
        let current = match self.obstacle_m {
            Some(o) if self.v < 0.0 && next < o && self.h >= o - 1e-9 => {
                // Pressing down on what is under it: stalled.
                if self.press_s == 0.0 {
                    self.report.presses += 1;
                }
                self.h = o;
                self.v = 0.0;
                self.press_s += STEP_S;
                self.report.pressed_s += STEP_S;
                self.report.longest_press_s = self.report.longest_press_s.max(self.press_s);
                STALL_A
            }
            _ => {
                self.press_s = 0.0;
                self.h = next;
                // Lifting the load costs current; lowering it, little.
                if self.v > 1e-4 {
                    0.6 + 0.06 * self.d.load_kg
                } else if self.v < -1e-4 {
                    0.4
                } else {
                    0.0
                }
            }
        };
        self.t += STEP_S;
        current
    }

    fn status(&self, current_a: f64) -> [u8; 13] {
        let counts = ((self.h - self.d.start_m) * self.d.counts_per_m).round() as i32;
        let mut f = [0u8; 13];
        f[0] = START;
        f[1] = STATUS;
        f[2] = 8;
        f[3..7].copy_from_slice(&counts.to_le_bytes());
        f[7..9].copy_from_slice(&((current_a * 1000.0).round() as u16).to_le_bytes());
        f[9] = u8::from(self.h <= 0.0005) | (u8::from(self.h >= self.d.travel_m - 0.0005) << 1);
        f[10] = 0;
        let crc = crc16(&f[1..11]);
        f[11..13].copy_from_slice(&crc.to_le_bytes());
        f
    }
}

impl SerialDevice for LiftBoard {
    fn receive(&mut self, now: f64, bytes: &[u8]) {
        self.rx.extend_from_slice(bytes);
        self.take_frames(now);
    }

    fn advance(&mut self, now: f64, write: &mut dyn FnMut(&[u8])) {
        while self.t + STEP_S <= now {
            let current = self.step();
            if self.t >= self.next_status {
                self.next_status += STATUS_EVERY_S;
                write(&self.status(current));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::description::RobotDescription;

    fn board() -> LiftBoard {
        LiftBoard::new(RobotDescription::nori_a3().lift.as_ref().unwrap())
    }

    fn drive(b: &mut LiftBoard, now: f64, tenths_mm: i16) {
        let mut f = vec![START, DRIVE, 2];
        f.extend_from_slice(&tenths_mm.to_le_bytes());
        let crc = crc16(&f[1..]);
        f.extend_from_slice(&crc.to_le_bytes());
        b.receive(now, &f);
    }

    fn statuses(b: &mut LiftBoard, now: f64) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        b.advance(now, &mut |bytes| out.push(bytes.to_vec()));
        out
    }

    /// The device's CRC, written apart from the host's (`lift::board`), pinned to the
    /// published check value of CRC-16/CCITT-FALSE as the host's is.
    #[test]
    fn the_boards_crc_is_ccitt_false() {
        assert_eq!(crc16(b"123456789"), 0x29B1);
    }

    #[test]
    fn it_moves_at_the_commanded_speed_reports_every_10_ms_and_stops_without_commands() {
        let mut b = board();
        let mut t = 0.0;
        let mut sent = 0;
        for _ in 0..100 {
            drive(&mut b, t, 300);
            t += 0.01;
            let s = statuses(&mut b, t);
            assert!(s.iter().all(|f| f.len() == 13));
            sent += s.len();
        }
        assert!((99..=101).contains(&sent), "{sent} statuses in 1 s");
        // 1 s at 30 mm/s (after a 50 ms lag).
        assert!(
            (b.report().height_m - 0.3 - 0.0285).abs() < 0.002,
            "{:?}",
            b.report()
        );
        // No command for 100 ms: stopped by the watchdog.
        statuses(&mut b, t + 0.5);
        let h = b.report().height_m;
        statuses(&mut b, t + 1.0);
        assert!((b.report().height_m - h).abs() < 1e-5);
        assert_eq!(b.report().watchdog_stops, 1);
    }

    #[test]
    fn the_switches_and_an_obstacle_stop_it_and_a_corrupt_frame_is_refused() {
        let mut b = board();
        b.obstacle_m = Some(0.25);
        let mut t = 0.0;
        for _ in 0..400 {
            drive(&mut b, t, -300);
            t += 0.01;
            statuses(&mut b, t);
        }
        assert!((b.report().height_m - 0.25).abs() < 1e-9);
        assert!(b.report().pressed_s > 2.0);
        assert_eq!(b.report().presses, 1);
        // Stopped by its watchdog, then driven down on it again: a second press.
        statuses(&mut b, t + 0.3);
        t += 0.3;
        for _ in 0..20 {
            drive(&mut b, t, -300);
            t += 0.01;
            statuses(&mut b, t);
        }
        assert_eq!(b.report().presses, 2);
        let mut f = vec![START, DRIVE, 2, 0x2C, 0x01, 0, 0];
        let crc = crc16(&f[1..5]) ^ 1;
        f[5..7].copy_from_slice(&crc.to_le_bytes());
        b.receive(t, &f);
        assert_eq!(b.report().bad_frames, 1);
    }
}
