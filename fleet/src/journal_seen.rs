//! Which events of the robots' journals a receiver has: each event is kept once however often it
//! comes (the robot sends again what was not acknowledged), and "every event through N" is what
//! the store acknowledges. Pure.
//!
//! An event is named by its robot, its journal and its number. Numbers below a message's
//! `held_from` that never came were dropped on the robot at its journal's bound: they are counted
//! lost and no longer awaited.

use std::collections::{BTreeMap, BTreeSet};

/// Numbers above the contiguous run remembered at most per journal: a robot cannot grow the
/// receiver without bound by skipping numbers (beyond it, the oldest are forgotten, and a
/// store's database still refuses their copies).
const ABOVE_KEPT: usize = 65_536;

/// One journal's received events.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct JournalSeen {
    /// Every event through this number is had (received, or lost for good).
    through: u64,
    /// Events received above `through`.
    above: BTreeSet<u64>,
    lost: u64,
}

/// What one message was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Taken {
    /// An event not had before.
    New,
    /// A copy of one had.
    Copy,
}

impl JournalSeen {
    /// A journal had through `through` (a store restarting from what it stored).
    pub fn through(through: u64) -> JournalSeen {
        JournalSeen {
            through,
            ..JournalSeen::default()
        }
    }

    /// Event `seq` came, the robot holding everything unacknowledged from `held_from` on.
    /// Number 0 (an event the robot could not journal) is always new.
    pub fn take(&mut self, seq: u64, held_from: u64) -> Taken {
        let fresh = seq != 0 && seq > self.through && !self.above.contains(&seq);
        if fresh {
            self.above.insert(seq);
        }
        // Below `held_from`, what never came will not come.
        let gone = held_from.saturating_sub(1);
        if gone > self.through {
            let had = self.above.range(..=gone).count() as u64;
            self.lost += gone - self.through - had;
            self.above = self.above.split_off(&(gone + 1));
            self.through = gone;
        }
        while self.above.first() == Some(&(self.through + 1)) {
            self.above.pop_first();
            self.through += 1;
        }
        while self.above.len() > ABOVE_KEPT {
            self.above.pop_first();
        }
        if fresh || seq == 0 {
            Taken::New
        } else {
            Taken::Copy
        }
    }

    /// Every event through this number is had.
    pub fn had_through(&self) -> u64 {
        self.through
    }

    /// Events given up as lost (dropped on the robot before they came).
    pub fn lost(&self) -> u64 {
        self.lost
    }
}

/// Every robot's journals.
#[derive(Debug, Default)]
pub struct FleetJournals {
    journals: BTreeMap<(String, u64), JournalSeen>,
}

impl FleetJournals {
    /// The journal `journal` of `robot`.
    pub fn of(&mut self, robot: &str, journal: u64) -> &mut JournalSeen {
        self.journals
            .entry((robot.to_string(), journal))
            .or_default()
    }

    /// Starts `robot`'s `journal` from what was stored before.
    pub fn restore(&mut self, robot: &str, journal: u64, seen: JournalSeen) {
        self.journals.insert((robot.to_string(), journal), seen);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_event_is_new_once_in_any_order_and_the_run_closes_over_gaps_filled() {
        let mut j = JournalSeen::default();
        assert_eq!(j.take(1, 1), Taken::New);
        assert_eq!(j.take(3, 1), Taken::New);
        assert_eq!(j.had_through(), 1, "2 is awaited");
        assert_eq!(j.take(3, 1), Taken::Copy);
        assert_eq!(j.take(1, 1), Taken::Copy);
        assert_eq!(j.take(2, 1), Taken::New);
        assert_eq!(j.had_through(), 3);
        assert_eq!(j.take(2, 1), Taken::Copy);
        assert_eq!(j.lost(), 0);
    }

    #[test]
    fn numbers_the_robot_no_longer_holds_are_counted_lost_not_awaited() {
        let mut j = JournalSeen::through(4);
        assert_eq!(j.take(7, 5), Taken::New);
        assert_eq!(j.had_through(), 4);
        // The robot dropped 5 and 6 at its bound: it holds from 8 now.
        assert_eq!(j.take(9, 8), Taken::New);
        assert_eq!((j.had_through(), j.lost()), (7, 2));
        assert_eq!(j.take(8, 8), Taken::New);
        assert_eq!(j.had_through(), 9);
        // An unnumbered event is always new and moves nothing.
        assert_eq!(j.take(0, 10), Taken::New);
        assert_eq!((j.had_through(), j.lost()), (9, 2));
    }

    #[test]
    fn journals_are_told_apart_by_robot_and_identity() {
        let mut f = FleetJournals::default();
        assert_eq!(f.of("a", 1).take(1, 1), Taken::New);
        assert_eq!(f.of("a", 2).take(1, 1), Taken::New);
        assert_eq!(f.of("b", 1).take(1, 1), Taken::New);
        assert_eq!(f.of("a", 1).take(1, 1), Taken::Copy);
        f.restore("c", 9, JournalSeen::through(5));
        assert_eq!(f.of("c", 9).take(5, 1), Taken::Copy);
    }
}
