//! The lift motor's duty-cycle budget (a thermal budget, enforced by the supervisor).
//!
//! Desk-lift column motors are rated for intermittent use, e.g. 2 minutes on per 18 off (10 %):
//! their windings heat while they run and cool while they rest, and a motor run past its
//! rating cooks like any servo. The budget is that heat as running time: it fills one second
//! per second of running and drains at `on / off` per second of rest. Full, it refuses further
//! travel (a move in progress is stopped) until `resume` seconds of running have drained out
//! again, and says when that will be: a caller is told "in 2 min 15 s", not just "no".

/// The rating: minutes on per minutes off, and the running time a refusal waits to regain.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DutyRating {
    /// Longest continuous running from cold, s (the rating's "on").
    pub on_s: f64,
    /// Rest that running time needs, s (the rating's "off").
    pub off_s: f64,
    /// Running time regained before a full budget allows travel again, s.
    pub resume_s: f64,
}

impl DutyRating {
    /// A typical desk column's: 2 min on, 18 min off; travel allowed again with 30 s regained.
    pub const DESK_COLUMN: DutyRating = DutyRating {
        on_s: 120.0,
        off_s: 1080.0,
        resume_s: 30.0,
    };

    /// The name of the first value that is not a positive number (or a resume not below on).
    pub fn invalid(&self) -> Option<&'static str> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.on_s) {
            Some("on-s")
        } else if !positive(self.off_s) {
            Some("off-s")
        } else if !(positive(self.resume_s) && self.resume_s <= self.on_s) {
            Some("resume-s")
        } else {
            None
        }
    }
}

/// Whether travel is allowed now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Allowance {
    /// Allowed: this much running is left before the budget is spent, s.
    Allowed {
        /// Running time left, s.
        left_s: f64,
    },
    /// Refused until this much rest has passed, s.
    Refused {
        /// Rest still needed, s.
        wait_s: f64,
    },
}

/// The budget of one motor.
#[derive(Debug, Clone, PartialEq)]
pub struct DutyBudget {
    rating: DutyRating,
    /// Heat as running time, s: 0 cold, `on_s` spent.
    used_s: f64,
    /// Spent and not yet regained `resume_s`.
    exhausted: bool,
}

impl DutyBudget {
    /// A cold motor.
    pub fn new(rating: DutyRating) -> DutyBudget {
        DutyBudget {
            rating,
            used_s: 0.0,
            exhausted: false,
        }
    }

    /// The motor ran (`running`) or rested for `dt_s` seconds.
    pub fn update(&mut self, running: bool, dt_s: f64) {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return;
        }
        let r = &self.rating;
        self.used_s = if running {
            self.used_s + dt_s
        } else {
            self.used_s - dt_s * r.on_s / r.off_s
        }
        .clamp(0.0, r.on_s);
        // (Within a nanosecond: sums of small steps fall a rounding short of the rating.)
        if self.used_s >= r.on_s - 1e-9 {
            self.exhausted = true;
        } else if self.used_s <= r.on_s - r.resume_s + 1e-9 {
            self.exhausted = false;
        }
    }

    /// Whether travel is allowed, and for how long or after how much rest.
    pub fn allowance(&self) -> Allowance {
        let r = &self.rating;
        if self.exhausted {
            let to_drain = self.used_s - (r.on_s - r.resume_s);
            Allowance::Refused {
                wait_s: (to_drain * r.off_s / r.on_s).max(0.0),
            }
        } else {
            Allowance::Allowed {
                left_s: r.on_s - self.used_s,
            }
        }
    }

    /// Heat as running time, s.
    pub fn used_s(&self) -> f64 {
        self.used_s
    }

    /// Whether it is spent (and has not yet regained the resume time).
    pub fn exhausted(&self) -> bool {
        self.exhausted
    }

    /// The trip record's line that keeps this budget across a restart, saved at `now_ns`
    /// (CLOCK_MONOTONIC): the heat it holds and `ahead_s` more (the running the motor may do
    /// before the next save), so the record never holds less heat than the motor.
    pub fn record_line(&self, ahead_s: f64, now_ns: u64) -> String {
        let used = (self.used_s + ahead_s).min(self.rating.on_s);
        format!(
            "{RECORD_PREFIX}{used:.3} {} {now_ns}",
            u8::from(self.exhausted)
        )
    }

    /// The budget a record line kept, rested until `now_ns`: since the save less
    /// `unsaved_s` (the running the line covers after its save: up to its next save, and on the
    /// last allowance after a crash), or, when the clock has started again since (a reboot),
    /// since the boot. The lift does not move without a live allowance, so the rest of the
    /// time between is rest; it is at most the rest there was. `None` when the line is not a
    /// budget's.
    pub fn restore(
        rating: DutyRating,
        line: &str,
        now_ns: u64,
        unsaved_s: f64,
    ) -> Option<DutyBudget> {
        let mut fields = line.strip_prefix(RECORD_PREFIX)?.split_whitespace();
        let used_s: f64 = fields.next()?.parse().ok()?;
        let exhausted = match fields.next()? {
            "0" => false,
            "1" => true,
            _ => return None,
        };
        let at_ns: u64 = fields.next()?.parse().ok()?;
        if fields.next().is_some() || !(used_s.is_finite() && used_s >= 0.0) {
            return None;
        }
        // A line whose heat (with what it covers) reaches the rating is a spent budget, whatever
        // it was when saved: the motor may have spent it since.
        let used_s = used_s.min(rating.on_s);
        let mut b = DutyBudget {
            rating,
            used_s,
            exhausted: exhausted || used_s >= rating.on_s - 1e-9,
        };
        let since_ns = if at_ns <= now_ns {
            now_ns - at_ns
        } else {
            now_ns
        };
        b.update(false, since_ns as f64 * 1e-9 - unsaved_s);
        Some(b)
    }
}

/// The trip record's line of the lift motor's budget starts with this (`telemetry::latch`
/// reserves `@` for the record's own lines): heat as running time, s; spent (1) or not (0);
/// when it was saved, CLOCK_MONOTONIC ns.
pub const RECORD_PREFIX: &str = "@lift-duty ";

#[cfg(test)]
mod tests {
    use super::*;

    fn run(b: &mut DutyBudget, running: bool, seconds: f64) {
        for _ in 0..(seconds * 10.0).round() as usize {
            b.update(running, 0.1);
        }
    }

    #[test]
    fn two_minutes_on_then_refused_until_thirty_seconds_are_regained() {
        let mut b = DutyBudget::new(DutyRating::DESK_COLUMN);
        run(&mut b, true, 119.0);
        assert!(
            matches!(b.allowance(), Allowance::Allowed { left_s } if (left_s - 1.0).abs() < 1e-6)
        );
        run(&mut b, true, 1.0);
        // Spent: 30 s of running to regain at 1/9 s per s of rest is 270 s.
        let Allowance::Refused { wait_s } = b.allowance() else {
            panic!("not refused: {:?}", b.allowance());
        };
        assert!((wait_s - 270.0).abs() < 1e-6, "{wait_s}");
        run(&mut b, false, 200.0);
        let Allowance::Refused { wait_s } = b.allowance() else {
            panic!("allowed too early");
        };
        assert!((wait_s - 70.0).abs() < 1e-6, "{wait_s}");
        run(&mut b, false, 70.0);
        assert!(
            matches!(b.allowance(), Allowance::Allowed { left_s } if (left_s - 30.0).abs() < 1e-6)
        );
    }

    #[test]
    fn short_runs_within_the_rating_never_spend_it() {
        // 10 s up, 90 s rest: 10 % duty, for an hour.
        let mut b = DutyBudget::new(DutyRating::DESK_COLUMN);
        for _ in 0..36 {
            run(&mut b, true, 10.0);
            run(&mut b, false, 90.0);
        }
        assert!(b.used_s() < 1e-6, "{}", b.used_s());
        // 30 s up, 30 s rest: 50 %, spent within a few cycles.
        let mut c = 0;
        while matches!(b.allowance(), Allowance::Allowed { .. }) {
            run(&mut b, true, 30.0);
            run(&mut b, false, 30.0);
            c += 1;
            assert!(c < 10, "never spent at 50 % duty");
        }
        assert!(c >= 4, "spent after {c} cycles");
    }

    #[test]
    fn a_budget_kept_in_the_record_comes_back_rested_only_as_long_as_it_was() {
        let mut b = DutyBudget::new(DutyRating::DESK_COLUMN);
        run(&mut b, true, 120.0);
        assert!(b.exhausted());
        let line = b.record_line(0.5, 1_000_000_000_000);
        assert_eq!(line, "@lift-duty 120.000 1 1000000000000");
        // Back 90 s later: 10 s regained, still spent, 180 s of rest to go.
        let r =
            DutyBudget::restore(DutyRating::DESK_COLUMN, &line, 1_090_000_000_000, 0.0).unwrap();
        assert!(r.exhausted() && (r.used_s() - 110.0).abs() < 1e-6, "{r:?}");
        // After a reboot (the clock started again): only the time since the boot is rest.
        let r = DutyBudget::restore(DutyRating::DESK_COLUMN, &line, 9_000_000_000, 0.0).unwrap();
        assert!((r.used_s() - 119.0).abs() < 1e-6, "{r:?}");
        // The running the line covers after its save is no rest: 9 s since it, 0.7 s unsaved.
        let r =
            DutyBudget::restore(DutyRating::DESK_COLUMN, &line, 1_009_000_000_000, 0.7).unwrap();
        assert!((r.used_s() - (120.0 - 8.3 / 9.0)).abs() < 1e-6, "{r:?}");
        // The margin ahead is saved, up to the rating.
        let mut b = DutyBudget::new(DutyRating::DESK_COLUMN);
        run(&mut b, true, 10.0);
        assert!(b.record_line(0.5, 0).starts_with("@lift-duty 10.500 0 "));
        for bad in [
            "@lift-duty",
            "@lift-duty NaN 0 1",
            "@lift-duty -1 0 1",
            "@lift-duty 3 2 1",
            "@lift-duty 3 0 1 extra",
            "@operator-stop",
        ] {
            assert_eq!(
                DutyBudget::restore(DutyRating::DESK_COLUMN, bad, 5, 0.0),
                None,
                "{bad}"
            );
        }
    }

    #[test]
    fn bad_ratings_and_times_are_refused_or_ignored() {
        let bad = DutyRating {
            resume_s: 200.0,
            ..DutyRating::DESK_COLUMN
        };
        assert_eq!(bad.invalid(), Some("resume-s"));
        assert_eq!(DutyRating::DESK_COLUMN.invalid(), None);
        let mut b = DutyBudget::new(DutyRating::DESK_COLUMN);
        b.update(true, f64::NAN);
        b.update(true, -5.0);
        assert_eq!(b.used_s(), 0.0);
    }
}
