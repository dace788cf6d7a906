//! The software tier of the two-tier thermal interlock, per bus (paper, "Two-tier thermal
//! interlock").
//!
//! Warnings escalate from each motor's temperature and its trajectory (the time to reach the trip
//! at the present slope), so an operator or scheduler can cut the duty cycle before anything
//! trips. At the trip temperature on any motor the whole bus is disabled, latched; it is
//! re-enabled only by an explicit command once every motor has cooled below a threshold.

use crate::config::ThermalConfig;

/// A re-enable needs every motor of the bus read at most this long ago, s.
pub const REENABLE_READING_MAX_AGE_S: f64 = 1.0;

/// Points of temperature history kept per motor (decimated to fill the slope window).
const HISTORY: usize = 64;

/// One motor's temperature history and slope.
#[derive(Debug, Clone)]
pub struct Trajectory {
    t: [f64; HISTORY],
    temp: [f32; HISTORY],
    len: usize,
    next: usize,
    last_t: f64,
}

impl Default for Trajectory {
    fn default() -> Self {
        Trajectory {
            t: [0.0; HISTORY],
            temp: [0.0; HISTORY],
            len: 0,
            next: 0,
            last_t: f64::NEG_INFINITY,
        }
    }
}

impl Trajectory {
    /// Records a reading at `t` s, keeping one point per `window / HISTORY` seconds.
    fn record(&mut self, t: f64, temp: f32, window: f64) {
        if t - self.last_t < window / HISTORY as f64 {
            return;
        }
        self.last_t = t;
        self.t[self.next] = t;
        self.temp[self.next] = temp;
        self.next = (self.next + 1) % HISTORY;
        self.len = (self.len + 1).min(HISTORY);
    }

    /// Least-squares slope over the history, °C/s; `None` with fewer than 4 points or less than
    /// a quarter of the window (the register is an integer: short spans give noise).
    pub fn slope(&self, window: f64) -> Option<f64> {
        if self.len < 4 {
            return None;
        }
        let n = self.len as f64;
        let pts = || (0..self.len).map(|i| (self.t[i], f64::from(self.temp[i])));
        let (t_min, t_max) = pts().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (t, _)| {
            (a.min(t), b.max(t))
        });
        if t_max - t_min < window / 4.0 {
            return None;
        }
        let (mt, my) = pts().fold((0.0, 0.0), |(a, b), (t, y)| (a + t / n, b + y / n));
        let (sxy, sxx) = pts().fold((0.0, 0.0), |(a, b), (t, y)| {
            (a + (t - mt) * (y - my), b + (t - mt) * (t - mt))
        });
        (sxx > 0.0).then(|| sxy / sxx)
    }
}

/// What happened on a bus this cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ThermalEvent {
    /// The bus's warning level changed (0 = none … 3 = critical).
    Warning {
        /// New level.
        level: u8,
        /// Joint driving the level.
        joint: usize,
        /// Predicted seconds to the trip (infinite when not heating).
        time_to_trip_s: f32,
    },
    /// The software trip: the whole bus is disabled, latched.
    Trip {
        /// The motor that reached the trip.
        joint: usize,
        /// Its temperature, °C.
        temperature_c: f32,
    },
}

/// One bus's thermal state.
#[derive(Debug, Clone)]
pub struct BusThermal {
    joints: Vec<usize>,
    trajectories: Vec<Trajectory>,
    /// Each motor's last reading and when it was read (s).
    last_temp: Vec<Option<(f32, f64)>>,
    /// Current warning level.
    pub level: u8,
    /// Since when a lower level has been computed (de-escalation waits a slope window, so an
    /// integer register's noisy slope does not make the level flap).
    lower_since: Option<f64>,
    /// Latched software trip.
    pub tripped: bool,
}

impl BusThermal {
    /// Watches the joints with these indices.
    pub fn new(joints: Vec<usize>) -> Self {
        let n = joints.len();
        BusThermal {
            joints,
            trajectories: vec![Trajectory::default(); n],
            last_temp: vec![None; n],
            level: 0,
            lower_since: None,
            tripped: false,
        }
    }

    /// The joints of this bus.
    pub fn joints(&self) -> &[usize] {
        &self.joints
    }

    /// Feeds one cycle: `temperature(joint)` is the reading, `None` when missing. `t` in s.
    pub fn update(
        &mut self,
        t: f64,
        temperature: impl Fn(usize) -> Option<f32>,
        c: &ThermalConfig,
    ) -> Option<ThermalEvent> {
        let window = f64::from(c.slope_window_s);
        let mut worst: (u8, usize, f32) =
            (0, self.joints.first().copied().unwrap_or(0), f32::INFINITY);
        let mut trip = None;
        for (k, &joint) in self.joints.iter().enumerate() {
            let Some(temp) = temperature(joint) else {
                continue;
            };
            self.last_temp[k] = Some((temp, t));
            self.trajectories[k].record(t, temp, window);
            if temp >= c.trip_c && trip.is_none() {
                trip = Some((joint, temp));
            }
            let ttt = match self.trajectories[k].slope(window) {
                Some(slope) if slope > 0.0 => {
                    ((f64::from(c.trip_c - temp)).max(0.0) / slope) as f32
                }
                _ => f32::INFINITY,
            };
            let level = (0..3)
                .rev()
                .find(|&l| temp >= c.warn_c[l] || ttt <= c.warn_time_to_trip_s[l])
                .map_or(0, |l| l as u8 + 1);
            if level > worst.0 || (level == worst.0 && ttt < worst.2) {
                worst = (level, joint, ttt);
            }
        }
        if let Some((joint, temperature_c)) = trip {
            if !self.tripped {
                self.tripped = true;
                return Some(ThermalEvent::Trip {
                    joint,
                    temperature_c,
                });
            }
        }
        let change = match worst.0.cmp(&self.level) {
            std::cmp::Ordering::Greater => true,
            std::cmp::Ordering::Equal => {
                self.lower_since = None;
                false
            }
            std::cmp::Ordering::Less => t - *self.lower_since.get_or_insert(t) >= window,
        };
        if change {
            self.level = worst.0;
            self.lower_since = None;
            return Some(ThermalEvent::Warning {
                level: worst.0,
                joint: worst.1,
                time_to_trip_s: worst.2,
            });
        }
        None
    }

    /// Trips the bus from outside (a motor's firmware cutoff was inferred); returns whether it
    /// was a new trip.
    pub fn force_trip(&mut self) -> bool {
        !std::mem::replace(&mut self.tripped, true)
    }

    /// An explicit re-enable at `now` (s): granted when every motor has been read within the
    /// last [`REENABLE_READING_MAX_AGE_S`] and is at or below the threshold (a motor that went
    /// silent may have kept heating: its old reading proves nothing). `Err` carries the hottest
    /// temperature (NaN when a motor has no fresh reading).
    pub fn reenable(&mut self, c: &ThermalConfig, now: f64) -> Result<(), f32> {
        let mut hottest = f32::NEG_INFINITY;
        for reading in &self.last_temp {
            match reading {
                Some((temp, at)) if now - at <= REENABLE_READING_MAX_AGE_S => {
                    hottest = hottest.max(*temp)
                }
                _ => return Err(f32::NAN),
            }
        }
        if hottest > c.reenable_below_c {
            return Err(hottest);
        }
        self.tripped = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SupervisorConfig;
    use telemetry::config::ProcessConfig;

    fn config() -> ThermalConfig {
        SupervisorConfig::embedded().unwrap().thermal
    }

    /// A motor heating along the one-node model's step response, read as an integer register.
    fn heating(t: f64) -> f32 {
        (25.0 + 40.0 * (1.0 - (-t / 600.0).exp())).round() as f32
    }

    #[test]
    fn warnings_escalate_before_the_trip_and_the_trip_latches_the_bus() {
        let c = config();
        let mut bus = BusThermal::new(vec![0, 1]);
        let mut events = vec![];
        let mut t = 0.0;
        while t < 3600.0 {
            let temps = [heating(t), 30.0];
            if let Some(e) = bus.update(t, |j| Some(temps[j]), &c) {
                events.push((t, temps[0], e));
            }
            t += 0.005 * 20.0; // a 200 Hz loop, every 20th frame
        }
        let trip = events
            .iter()
            .find(|(_, _, e)| matches!(e, ThermalEvent::Trip { .. }))
            .expect("tripped");
        assert_eq!(
            trip.1, 59.0,
            "trips at 59 °C, before the 60 °C firmware cutoff"
        );
        let first_warning = events
            .iter()
            .find(|(_, _, e)| matches!(e, ThermalEvent::Warning { level: 1, .. }))
            .unwrap();
        assert!(
            first_warning.1 < 50.0,
            "the trajectory warns before the temperature does: {}",
            first_warning.1
        );
        let levels: Vec<u8> = events
            .iter()
            .filter_map(|(_, _, e)| match e {
                ThermalEvent::Warning { level, .. } => Some(*level),
                _ => None,
            })
            .take_while(|l| *l > 0)
            .collect();
        assert_eq!(levels, [1, 2, 3], "warnings escalate one level at a time");
        assert!(bus.tripped);
        // Still hot: re-enable refused; cooled: granted.
        let last = events.last().map_or(0.0, |e| e.0);
        assert_eq!(bus.reenable(&c, last), Err(65.0));
        for k in 0..10 {
            bus.update(3600.0 + k as f64, |_| Some(45.0), &c);
        }
        assert!(bus.reenable(&c, 3609.5).is_ok());
        assert!(!bus.tripped);
    }

    #[test]
    fn a_reenable_is_not_judged_on_a_motor_that_went_silent() {
        let c = config();
        let mut bus = BusThermal::new(vec![0, 1]);
        bus.update(0.0, |_| Some(59.0), &c);
        assert!(bus.tripped);
        // Both motors cool; then motor 1 goes silent (its old 45 °C is all that is known).
        for k in 1..=10 {
            bus.update(k as f64, |_| Some(45.0), &c);
        }
        for k in 11..=20 {
            bus.update(k as f64, |j| (j == 0).then_some(45.0), &c);
        }
        assert!(
            bus.reenable(&c, 20.0).unwrap_err().is_nan(),
            "a stale reading is refused"
        );
        assert!(bus.tripped);
        bus.update(21.0, |_| Some(45.0), &c);
        assert!(bus.reenable(&c, 21.0).is_ok());
    }

    #[test]
    fn a_steady_temperature_gives_no_warning() {
        let c = config();
        let mut bus = BusThermal::new(vec![0]);
        for k in 0..10_000 {
            assert_eq!(bus.update(k as f64 * 0.1, |_| Some(41.0), &c), None);
        }
    }

    #[test]
    fn one_hot_motor_trips_the_whole_bus_once() {
        let c = config();
        let mut bus = BusThermal::new(vec![4, 5, 6]);
        let e = bus.update(0.0, |j| Some(if j == 5 { 59.0 } else { 30.0 }), &c);
        assert_eq!(
            e,
            Some(ThermalEvent::Trip {
                joint: 5,
                temperature_c: 59.0
            })
        );
        assert!(!matches!(
            bus.update(0.1, |_| Some(59.0), &c),
            Some(ThermalEvent::Trip { .. })
        ));
    }
}
