//! Revolutions from scan nodes, each revolution checked for holes before it is published.
//! Pure: nodes and receive times in, frames out.
//!
//! The nodes come from [`crate::protocol::Decoder`], which lets out only nodes confirmed by
//! their neighbours (each a small step past the one before, or across 0° with S set). So:
//! * a revolution ends where the angle steps back (a lidar turns one way), whether or not its
//!   S node arrived;
//! * a revolution whose coverage has a hole wider than `max_gap_deg` (a scan cut short, data
//!   lost on the line) is dropped and counted, never published: a consumer that keeps a robot
//!   off obstacles must not read a missing sector as free space. So is the partial revolution
//!   the stream starts in.

use crate::protocol::{Node, FULL_TURN_Q6};
use telemetry::sensors::{LidarScan, ScanPoint, MAX_SCAN_POINTS};

/// What a revolution must satisfy to be published.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanLimits {
    /// Returns nearer than this are reported as no return (the C1's blind zone is 5 cm).
    pub min_range_m: f64,
    /// Returns farther than this are reported as no return.
    pub max_range_m: f64,
    /// Widest hole allowed in a revolution's coverage, degrees.
    pub max_gap_deg: f64,
}

impl ScanLimits {
    /// The limits for an RPLIDAR C1 (0.05–12 m; nodes 0.72° apart at 10 Hz, 0.86° at 12 Hz).
    pub const C1: ScanLimits = ScanLimits {
        min_range_m: 0.05,
        max_range_m: 12.0,
        max_gap_deg: 5.0,
    };
}

/// What the assembler did, cumulative.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "process", derive(serde::Serialize))]
pub struct ScanCounters {
    /// Revolutions published.
    pub scans: u64,
    /// Points in published revolutions.
    pub points: u64,
    /// Revolutions dropped for a hole in their coverage (including the first, partial one).
    pub short_scans: u64,
    /// Returns outside the range limits, reported as no return.
    pub out_of_range: u64,
    /// Points beyond what a frame holds ([`MAX_SCAN_POINTS`]), not kept.
    pub overflow_points: u64,
}

/// Builds revolutions; two frames are allocated once and reused.
pub struct Assembler {
    limits: ScanLimits,
    filling: Box<LidarScan>,
    done: Box<LidarScan>,
    /// Angle of the last accepted node of the revolution being filled.
    last_q6: Option<u16>,
    /// First angle of the revolution being filled.
    first_q6: u16,
    /// Widest step so far in the revolution being filled, 1/64 degree.
    widest_q6: u16,
    /// Whether the revolution being filled began at a revolution boundary (not mid-turn).
    whole: bool,
    /// Whether it had more points than a frame holds.
    overflowed: bool,
    counters: ScanCounters,
}

impl Assembler {
    /// An assembler keeping `limits`.
    pub fn new(limits: ScanLimits) -> Self {
        Assembler {
            limits,
            filling: Box::default(),
            done: Box::default(),
            last_q6: None,
            first_q6: 0,
            widest_q6: 0,
            whole: false,
            overflowed: false,
            counters: ScanCounters::default(),
        }
    }

    /// What happened so far.
    pub fn counters(&self) -> ScanCounters {
        self.counters
    }

    /// The last published revolution (its `resyncs` is the caller's to fill).
    pub fn scan_mut(&mut self) -> &mut LidarScan {
        &mut self.done
    }

    /// Forgets the revolution being filled (the stream was restarted): the next one to
    /// publish starts at the next revolution boundary.
    pub fn restart(&mut self) {
        self.filling.point_count = 0;
        self.last_q6 = None;
        self.whole = false;
    }

    /// Takes one node received at `now_ns`; returns true when it completed a revolution that
    /// is now in [`Assembler::scan_mut`].
    pub fn push(&mut self, node: Node, now_ns: u64) -> bool {
        let Some(last) = self.last_q6 else {
            // The first node after a (re)start: a revolution begins here, whole only if this
            // is the device's first node of a turn.
            self.begin(node, now_ns, node.start);
            return false;
        };
        if node.start || node.angle_q6 <= last {
            // A lidar turns one way: a step back is a new turn, its S node seen or lost.
            let published = self.finish();
            self.begin(node, now_ns, true);
            return published;
        }
        self.accept(node, now_ns);
        false
    }

    fn begin(&mut self, node: Node, now_ns: u64, whole: bool) {
        self.filling.point_count = 0;
        self.filling.start_ns = now_ns;
        self.first_q6 = node.angle_q6;
        self.widest_q6 = 0;
        self.whole = whole;
        self.overflowed = false;
        self.last_q6 = None;
        self.accept(node, now_ns);
    }

    fn accept(&mut self, node: Node, now_ns: u64) {
        if let Some(last) = self.last_q6 {
            self.widest_q6 = self.widest_q6.max(node.angle_q6.saturating_sub(last));
        }
        self.last_q6 = Some(node.angle_q6);
        let n = self.filling.point_count as usize;
        if n >= MAX_SCAN_POINTS {
            self.counters.overflow_points += 1;
            self.overflowed = true;
            return;
        }
        let mut range = node.distance_m();
        let mut quality = node.quality;
        if range != 0.0 && !(self.limits.min_range_m..=self.limits.max_range_m).contains(&range) {
            self.counters.out_of_range += 1;
            (range, quality) = (0.0, 0);
        }
        // Clockwise on the wire; counter-clockwise (x forward, y left, z up) on the plane.
        let cw = f64::from(node.angle_q6) / 64.0;
        let ccw = if cw == 0.0 { 0.0 } else { 360.0 - cw };
        self.filling.points[n] = ScanPoint {
            angle_rad: ccw.to_radians() as f32,
            range_m: range as f32,
            quality,
            reserved: [0; 3],
        };
        self.filling.point_count += 1;
        self.filling.end_ns = now_ns;
    }

    /// Ends the revolution being filled; true if it was published.
    fn finish(&mut self) -> bool {
        let last = self.last_q6.unwrap_or(self.first_q6);
        let closing_q6 = (self.first_q6 + FULL_TURN_Q6).saturating_sub(last);
        let widest_deg = f64::from(self.widest_q6.max(closing_q6)) / 64.0;
        if !self.whole || self.overflowed || widest_deg > self.limits.max_gap_deg {
            self.counters.short_scans += 1;
            return false;
        }
        self.counters.scans += 1;
        self.counters.points += u64::from(self.filling.point_count);
        self.filling.seq = self.counters.scans - 1;
        self.filling.short_scans = saturate(self.counters.short_scans);
        std::mem::swap(&mut self.filling, &mut self.done);
        true
    }
}

/// A cumulative count as the scan frame's 32-bit field holds it (stuck at the top, not wrapped).
pub(crate) fn saturate(n: u64) -> u32 {
    n.min(u64::from(u32::MAX)) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 500 nodes a turn (0.72°, as a C1 at 10 Hz), starting at `from` of them; range 2 m.
    fn turn(from: usize) -> Vec<Node> {
        (from..500)
            .map(|i| Node {
                start: i == 0,
                quality: 40,
                angle_q6: (i as f64 * 0.72 * 64.0).round() as u16 + 3,
                distance_q2: 8000,
            })
            .collect()
    }

    /// Pushes `nodes`, 200 µs apart from `t0`; returns the revolutions published.
    fn feed(a: &mut Assembler, nodes: &[Node], t0: u64) -> Vec<LidarScan> {
        let mut out = Vec::new();
        for (i, n) in nodes.iter().enumerate() {
            if a.push(*n, t0 + i as u64 * 200_000) {
                out.push(*a.scan_mut());
            }
        }
        out
    }

    #[test]
    fn whole_turns_are_published_and_the_partial_first_is_not() {
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(200);
        nodes.extend(turn(0));
        nodes.extend(turn(0));
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 1_000);
        assert_eq!(scans.len(), 2);
        let c = a.counters();
        assert_eq!((c.scans, c.short_scans), (2, 1));
        let s = &scans[1];
        assert_eq!((s.seq, s.point_count), (1, 500));
        assert_eq!(s.start_ns, 1_000 + 800 * 200_000);
        assert_eq!(s.end_ns, s.start_ns + 499 * 200_000);
        let hz = s.rotation_hz().unwrap();
        assert!((hz - 1e9 / (499.0 * 200_000.0)).abs() < 1e-9);
        // Clockwise on the wire, counter-clockwise on the plane: 90° cw is 270° ccw.
        let quarter = s.points()[125];
        assert!(
            (quarter.angle_rad.to_degrees() - 270.0).abs() < 0.05,
            "{quarter:?}"
        );
        assert!((quarter.range_m - 2.0).abs() < 1e-6);
        assert_eq!(quarter.quality, 40);
        // Measured order: the ccw bearing falls through the turn.
        assert!(s.points()[1].angle_rad > s.points()[2].angle_rad);
    }

    #[test]
    fn a_lost_start_node_still_ends_the_turn() {
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(0);
        nodes.extend(turn(0).into_iter().skip(1));
        nodes.extend(turn(0).into_iter().take(2));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2, "{:?}", a.counters());
        assert_eq!(scans[1].point_count, 499);
    }

    #[test]
    fn a_turn_cut_early_ends_where_the_angle_steps_back() {
        // Cut at 50°, its next S node lost: the step back from 50° to 1.4° still ends it.
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(0);
        nodes.extend(turn(0).into_iter().take(70));
        nodes.extend(turn(2));
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2, "{:?}", a.counters());
        assert_eq!(a.counters().short_scans, 1);
        assert_eq!(scans[1].point_count, 498);
        // A lidar turns one way: a node that repeats its predecessor's angle starts a new
        // (partial, dropped) turn rather than folding into this one.
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(0);
        let mut second = turn(0);
        second.insert(100, second[99]);
        nodes.extend(second);
        nodes.extend(turn(0).into_iter().take(1));
        assert_eq!(feed(&mut a, &nodes, 0).len(), 1);
        assert_eq!(a.counters().short_scans, 2);
    }

    #[test]
    fn a_small_hole_is_kept_and_a_wide_one_drops_the_turn() {
        let limits = ScanLimits::C1;
        // Six nodes lost: a 5.04° step, over the widest hole (the turn is dropped).
        let mut a = Assembler::new(limits);
        let mut nodes = turn(0);
        let mut holed = turn(0);
        holed.drain(100..106);
        nodes.extend(holed);
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 1);
        assert_eq!(a.counters().short_scans, 1);
        // Five lost (4.32°): published.
        let mut a = Assembler::new(limits);
        let mut nodes = turn(0);
        let mut holed = turn(0);
        holed.drain(100..105);
        nodes.extend(holed);
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2, "{:?}", a.counters());
        assert_eq!(scans[1].point_count, 495);
        // A turn cut short (its last third never sent) is dropped.
        let mut a = Assembler::new(limits);
        let mut nodes = turn(0);
        nodes.extend(turn(0).into_iter().take(330));
        nodes.extend(turn(0));
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2);
        assert_eq!(a.counters().short_scans, 1, "the cut one");
        assert_eq!(scans[1].short_scans, 1);
        assert_eq!(scans[1].seq, 1);
    }

    #[test]
    fn a_hole_exactly_as_wide_as_allowed_is_kept_and_counts_add_up() {
        // Exactly 46 q6 apart: one node missing leaves a hole of 92 q6 = 1.4375°.
        let exact = |skip: Option<u16>| {
            (0..500u16).filter(move |&i| Some(i) != skip).map(|i| Node {
                start: i == 0,
                quality: 40,
                angle_q6: i * 46,
                distance_q2: 8000,
            })
        };
        let limits = ScanLimits {
            max_gap_deg: 92.0 / 64.0,
            ..ScanLimits::C1
        };
        let mut a = Assembler::new(limits);
        let mut nodes: Vec<Node> = exact(Some(10)).collect();
        nodes.extend(exact(Some(300)));
        nodes.extend(exact(Some(0)).take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2, "{:?}", a.counters());
        assert_eq!(a.counters().points, 998);
        // Two turns cut short, then a whole one: its frame carries the count.
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(0);
        nodes.extend(turn(0).into_iter().take(200));
        nodes.extend(turn(0).into_iter().take(200));
        nodes.extend(turn(0));
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 2);
        assert_eq!(scans[1].short_scans, 2);
        assert_eq!(a.counters().points, 1000);
    }

    #[test]
    fn returns_outside_the_range_limits_become_no_return() {
        let mut a = Assembler::new(ScanLimits::C1);
        let mut nodes = turn(0);
        let mut second = turn(0);
        second[10].distance_q2 = 100; // 2.5 cm, in the blind zone
        second[11].distance_q2 = 60_000; // 15 m
        second[12].distance_q2 = 0; // no return: not counted
        nodes.extend(second);
        nodes.extend(turn(0).into_iter().take(1));
        let scans = feed(&mut a, &nodes, 0);
        let p = scans[1].points();
        assert_eq!((p[10].range_m, p[10].quality), (0.0, 0));
        assert_eq!((p[11].range_m, p[11].quality), (0.0, 0));
        assert_eq!(p[12].range_m, 0.0);
        assert_eq!(p[13].range_m, 2.0);
        assert_eq!(a.counters().out_of_range, 2);
    }

    #[test]
    fn a_turn_larger_than_a_frame_is_dropped_and_a_restart_forgets_the_partial_turn() {
        let mut a = Assembler::new(ScanLimits::C1);
        let dense: Vec<Node> = (0..1200)
            .map(|i| Node {
                start: i == 0,
                quality: 40,
                angle_q6: (i * 19) as u16,
                distance_q2: 8000,
            })
            .collect();
        let mut nodes = dense.clone();
        nodes.extend(dense.clone());
        nodes.push(dense[0]);
        assert!(feed(&mut a, &nodes, 0).is_empty());
        assert_eq!(
            a.counters().overflow_points,
            2 * (1200 - MAX_SCAN_POINTS as u64)
        );
        let mut a = Assembler::new(ScanLimits::C1);
        feed(&mut a, &turn(0)[..300], 0);
        a.restart();
        // After a restart the stream resumes mid-turn: that turn is partial, not published.
        let mut nodes = turn(300);
        nodes.extend(turn(0));
        nodes.push(turn(0)[0]);
        let scans = feed(&mut a, &nodes, 0);
        assert_eq!(scans.len(), 1);
        assert_eq!(a.counters().short_scans, 1);
    }
}
