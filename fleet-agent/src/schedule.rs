//! The action scheduler: turns accepted chunks into one goal per tick, on the robot's clock.
//!
//! - Steps already in the past when a chunk arrives are dropped.
//! - Where a new chunk overlaps the plan in force, the two are blended, as LeRobot's async
//!   inference aggregates overlapping chunks: `w·new + (1 − w)·old` at each new step, with the
//!   old plan interpolated at that step's time. Old steps before the new chunk's first step stay.
//! - Between steps the target is interpolated linearly; before the first step it is the first
//!   step's target.
//! - After the last step the last target is held for at most `horizon`; past it nothing is
//!   forwarded, so on a network loss the driver keeps its last goal: the robot holds.
//! - Every step keeps the joint mask of the chunk it came from, and only masked joints carry a
//!   value (the others are zero and never forwarded): every value that leaves the scheduler
//!   was range-checked by the gate, or is a blend or interpolation of such values. Between two
//!   steps only the joints both command are forwarded. The lift's height and the base's twist
//!   are two more such axes, present only in the steps of chunks that command them.
//!
//! Fixed capacity: inserting and ticking never allocate.

use crate::schema::ActionChunk;
use telemetry::frames::MAX_JOINTS;

/// Most steps the plan holds.
pub const MAX_PLAN_STEPS: usize = 256;

#[derive(Debug, Clone, Copy)]
struct Step {
    t_ns: u64,
    /// What the step commands (its chunk's mask and body axes).
    goal: Target,
}

/// The plan in force.
#[derive(Debug, Clone)]
pub struct Scheduler {
    plan: Vec<Step>,
    scratch: Vec<Step>,
    blend_new: f32,
    horizon_ns: u64,
    dropped_past_steps: u64,
    expired: u64,
}

/// One tick's goal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    /// Per joint, rad (only the masked joints are meaningful).
    pub position: [f32; MAX_JOINTS],
    /// Joints commanded.
    pub mask: u32,
    /// The lift's height, m, when commanded.
    pub lift_m: Option<f32>,
    /// The base's forward speed (m/s) and turn rate (rad/s), when commanded.
    pub base_twist: Option<[f32; 2]>,
}

impl Target {
    /// Whether it commands anything.
    pub fn commands_anything(&self) -> bool {
        self.mask != 0 || self.lift_m.is_some() || self.base_twist.is_some()
    }
}

impl Scheduler {
    /// `blend_new`: the new chunk's weight where chunks overlap (1 = replace); `horizon_ns`: how
    /// long the last target may be held after its time.
    pub fn new(blend_new: f32, horizon_ns: u64) -> Self {
        Scheduler {
            plan: Vec::with_capacity(MAX_PLAN_STEPS),
            scratch: Vec::with_capacity(MAX_PLAN_STEPS),
            blend_new: blend_new.clamp(0.0, 1.0),
            horizon_ns,
            dropped_past_steps: 0,
            expired: 0,
        }
    }

    /// Steps dropped because they were already past on arrival.
    pub fn dropped_past_steps(&self) -> u64 {
        self.dropped_past_steps
    }

    /// Plans that ran out (horizon passed with no new chunk): the robot held.
    pub fn expired(&self) -> u64 {
        self.expired
    }

    /// Steps still planned.
    pub fn planned_steps(&self) -> usize {
        self.plan.len()
    }

    /// Forgets the plan (the robot holds).
    pub fn clear(&mut self) {
        self.plan.clear();
    }

    /// Adds an accepted chunk (see [`crate::gate`]) at robot time `now_ns`.
    pub fn insert(&mut self, chunk: &ActionChunk, now_ns: u64) {
        let first_new = chunk
            .step_offsets_ns
            .iter()
            .position(|&o| chunk.observation_ns.saturating_add(o) >= now_ns);
        let Some(first_new) = first_new else {
            self.dropped_past_steps += chunk.step_offsets_ns.len() as u64;
            return;
        };
        self.dropped_past_steps += first_new as u64;
        let new_start = chunk.observation_ns + chunk.step_offsets_ns[first_new];
        self.scratch.clear();
        // The old plan until the new one starts.
        for s in &self.plan {
            if s.t_ns >= now_ns && s.t_ns < new_start && self.scratch.len() < MAX_PLAN_STEPS {
                self.scratch.push(*s);
            }
        }
        for (k, &offset) in chunk.step_offsets_ns.iter().enumerate().skip(first_new) {
            if self.scratch.len() == MAX_PLAN_STEPS {
                break;
            }
            let t_ns = chunk.observation_ns + offset;
            let mut goal = step_of(chunk, k);
            if let Some(old) = interpolate(&self.plan, t_ns, false) {
                let w = self.blend_new;
                let blend = |new: f32, old: f32| w * new + (1.0 - w) * old;
                for (j, value) in goal.position.iter_mut().enumerate() {
                    if old.mask & goal.mask & (1 << j) != 0 {
                        *value = blend(*value, old.position[j]);
                    }
                }
                if let (Some(new), Some(old)) = (&mut goal.lift_m, old.lift_m) {
                    *new = blend(*new, old);
                }
                if let (Some(new), Some(old)) = (&mut goal.base_twist, old.base_twist) {
                    *new = [blend(new[0], old[0]), blend(new[1], old[1])];
                }
            }
            self.scratch.push(Step { t_ns, goal });
        }
        std::mem::swap(&mut self.plan, &mut self.scratch);
    }

    /// The goal at robot time `now_ns`, or `None` when there is no plan or it expired. Steps
    /// behind `now_ns` (but the one just passed, which interpolation needs) are dropped.
    pub fn target(&mut self, now_ns: u64) -> Option<Target> {
        let last = self.plan.last()?;
        if now_ns > last.t_ns.saturating_add(self.horizon_ns) {
            self.plan.clear();
            self.expired += 1;
            return None;
        }
        let behind = self.plan.iter().take_while(|s| s.t_ns <= now_ns).count();
        if behind > 1 {
            self.plan.drain(..behind - 1);
        }
        interpolate(&self.plan, now_ns, true).filter(Target::commands_anything)
    }
}

/// Step `k` of `chunk`: only the masked joints carry a value (the others are zero), the lift
/// and the base when the chunk commands them.
fn step_of(chunk: &ActionChunk, k: usize) -> Target {
    let joints = usize::from(chunk.joint_count).min(MAX_JOINTS);
    let mut position = [0f32; MAX_JOINTS];
    let values = chunk
        .targets
        .get(k * joints..(k + 1) * joints)
        .unwrap_or(&[]);
    for (j, (t, &v)) in position.iter_mut().zip(values).enumerate() {
        if chunk.joint_mask & (1 << j) != 0 {
            *t = v;
        }
    }
    Target {
        position,
        mask: chunk.joint_mask,
        lift_m: chunk.lift_m.get(k).copied(),
        base_twist: chunk.base_twist.get(2 * k..2 * k + 2).map(|t| [t[0], t[1]]),
    }
}

/// The plan's goal at `t_ns`: a step's own at its time, linear between steps for what both
/// command; outside the plan, the nearest end if `extend`, else nothing.
fn interpolate(plan: &[Step], t_ns: u64, extend: bool) -> Option<Target> {
    let (first, last) = (plan.first()?, plan.last()?);
    if t_ns <= first.t_ns {
        return (extend || t_ns == first.t_ns).then_some(first.goal);
    }
    if t_ns >= last.t_ns {
        return (extend || t_ns == last.t_ns).then_some(last.goal);
    }
    let i = plan.iter().position(|s| s.t_ns > t_ns)?;
    let (a, b) = (&plan[i - 1], &plan[i]);
    if t_ns == a.t_ns {
        return Some(a.goal);
    }
    let f = (t_ns - a.t_ns) as f32 / (b.t_ns - a.t_ns) as f32;
    let lerp = |x: f32, y: f32| x + f * (y - x);
    let (a, b) = (&a.goal, &b.goal);
    let mask = a.mask & b.mask;
    let mut position = [0f32; MAX_JOINTS];
    for (j, (o, (x, y))) in position
        .iter_mut()
        .zip(a.position.iter().zip(&b.position))
        .enumerate()
    {
        if mask & (1 << j) != 0 {
            *o = lerp(*x, *y);
        }
    }
    Some(Target {
        position,
        mask,
        lift_m: a.lift_m.zip(b.lift_m).map(|(x, y)| lerp(x, y)),
        base_twist: a
            .base_twist
            .zip(b.base_twist)
            .map(|(x, y)| [lerp(x[0], y[0]), lerp(x[1], y[1])]),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::SCHEMA_VERSION;

    use telemetry::clock::MS;

    /// One joint; steps every 20 ms from `start_ms` after the observation at `obs_ms`.
    fn chunk(seq: u64, obs_ms: u64, start_ms: u64, targets: &[f32]) -> ActionChunk {
        ActionChunk {
            version: SCHEMA_VERSION,
            seq,
            observation_ns: obs_ms * MS,
            step_offsets_ns: (0..targets.len() as u64)
                .map(|k| (start_ms + 20 * k) * MS)
                .collect(),
            joint_count: 1,
            joint_mask: 1,
            targets: targets.to_vec(),
            lift_m: Vec::new(),
            base_twist: Vec::new(),
        }
    }

    fn at(s: &mut Scheduler, ms: u64) -> Option<f32> {
        s.target(ms * MS).map(|t| t.position[0])
    }

    #[test]
    fn steps_in_the_past_are_dropped_and_the_rest_interpolated() {
        let mut s = Scheduler::new(1.0, 100 * MS);
        // Steps at 1020, 1040, 1060, 1080; it arrives at 1050.
        s.insert(&chunk(1, 1000, 20, &[1.0, 2.0, 3.0, 4.0]), 1050 * MS);
        assert_eq!(s.dropped_past_steps(), 2);
        assert_eq!(
            at(&mut s, 1050),
            Some(3.0),
            "before the first kept step: that step"
        );
        assert_eq!(at(&mut s, 1070), Some(3.5));
        assert_eq!(at(&mut s, 1080), Some(4.0));
    }

    #[test]
    fn the_last_target_is_held_only_until_the_horizon_then_nothing() {
        let mut s = Scheduler::new(1.0, 100 * MS);
        s.insert(&chunk(1, 1000, 20, &[1.0, 2.0]), 1000 * MS);
        assert_eq!(at(&mut s, 1140), Some(2.0));
        assert_eq!(at(&mut s, 1141), None, "no target older than the horizon");
        assert_eq!(s.expired(), 1);
        assert_eq!(at(&mut s, 1100), None, "an expired plan does not come back");
        assert_eq!(s.planned_steps(), 0);
    }

    #[test]
    fn overlapping_chunks_are_blended_and_the_old_plan_runs_until_the_new_starts() {
        let mut s = Scheduler::new(0.75, 100 * MS);
        // Old plan: 0 at 1020, 1040, 1060, 1080, 1100.
        s.insert(&chunk(1, 1000, 20, &[0.0; 5]), 1000 * MS);
        // New plan from 1060: 1.0 at 1060, 1080, 1100, 1120.
        s.insert(&chunk(2, 1030, 30, &[1.0; 4]), 1035 * MS);
        assert_eq!(
            at(&mut s, 1040),
            Some(0.0),
            "old plan before the new one starts"
        );
        assert_eq!(at(&mut s, 1060), Some(0.75), "overlap: 0.75·new + 0.25·old");
        assert_eq!(at(&mut s, 1100), Some(0.75));
        assert_eq!(
            at(&mut s, 1120),
            Some(1.0),
            "beyond the old plan: the new one alone"
        );
    }

    #[test]
    fn the_lift_and_base_are_interpolated_blended_and_end_with_the_plan() {
        let close = |a: f32, b: f32| (a - b).abs() < 1e-6;
        let mut s = Scheduler::new(0.5, 100 * MS);
        // Body only (no joint): steps at 1020 and 1040.
        let mut c = chunk(1, 1000, 20, &[0.0, 0.0]);
        c.joint_mask = 0;
        c.lift_m = vec![0.2, 0.4];
        c.base_twist = vec![0.1, 0.0, 0.2, 1.0];
        s.insert(&c, 1000 * MS);
        let t = s.target(1030 * MS).unwrap();
        assert_eq!(t.mask, 0, "no joint commanded");
        assert!(close(t.lift_m.unwrap(), 0.3), "{t:?}");
        let [v, w] = t.base_twist.unwrap();
        assert!(close(v, 0.15) && close(w, 0.5), "{t:?}");
        // A chunk for the base alone from 1040: blended with the old plan there; the lift is
        // not commanded where the new plan runs (it holds its last height by itself).
        let mut d = chunk(2, 1030, 10, &[0.0]);
        d.joint_mask = 0;
        d.base_twist = vec![0.4, 0.0];
        s.insert(&d, 1035 * MS);
        let t = s.target(1040 * MS).unwrap();
        let [v, w] = t.base_twist.unwrap();
        assert!(close(v, 0.3) && close(w, 0.5), "0.5·new + 0.5·old: {t:?}");
        assert_eq!(t.lift_m, None);
        assert!(s.target(1140 * MS).is_some());
        assert_eq!(
            s.target(1141 * MS),
            None,
            "past the horizon nothing: the base's commands stop and it brakes"
        );
    }

    #[test]
    fn a_chunk_entirely_in_the_past_changes_nothing() {
        let mut s = Scheduler::new(0.5, 100 * MS);
        s.insert(&chunk(1, 1000, 20, &[1.0, 1.0]), 1000 * MS);
        s.insert(&chunk(2, 1000, 20, &[9.0, 9.0]), 1100 * MS);
        assert_eq!(s.dropped_past_steps(), 2);
        assert_eq!(at(&mut s, 1030), Some(1.0));
    }

    #[test]
    fn a_joint_added_to_the_mask_never_follows_a_value_the_gate_did_not_check() {
        let mut s = Scheduler::new(1.0, 100 * MS);
        // Two joints; the first chunk commands joint 0 only and carries an unchecked 99 for
        // joint 1 (uncommanded values are not range-checked by the gate).
        let mut first = chunk(1, 1000, 20, &[0.1, 99.0, 0.2, 99.0, 0.3, 99.0]);
        first.joint_count = 2;
        first.step_offsets_ns.truncate(3);
        s.insert(&first, 1000 * MS);
        // The second commands both joints from 1060 on.
        let mut second = chunk(2, 1030, 30, &[0.5, 0.4, 0.6, 0.4]);
        second.joint_count = 2;
        second.joint_mask = 0b11;
        second.step_offsets_ns.truncate(2);
        s.insert(&second, 1035 * MS);
        let mut both = false;
        for ms in (1035..=1200).step_by(5) {
            if let Some(t) = s.target(ms * MS) {
                both |= t.mask == 0b11;
                if t.mask & 0b10 != 0 {
                    assert_eq!(
                        t.position[1], 0.4,
                        "at {ms} ms joint 1 follows only checked values"
                    );
                } else {
                    assert_eq!(t.position[1], 0.0, "an uncommanded joint carries no value");
                }
                if ms < 1060 {
                    assert_eq!(t.mask, 0b01, "before the second chunk starts: joint 0 only");
                }
            }
        }
        assert!(both, "from 1060 on both joints are commanded");
    }
}
