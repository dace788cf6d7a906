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
//!
//! Fixed capacity: inserting and ticking never allocate.

use crate::schema::ActionChunk;
use telemetry::frames::MAX_JOINTS;

/// Most steps the plan holds.
pub const MAX_PLAN_STEPS: usize = 256;

#[derive(Debug, Clone, Copy)]
struct Step {
    t_ns: u64,
    target: [f32; MAX_JOINTS],
}

/// The plan in force.
#[derive(Debug, Clone)]
pub struct Scheduler {
    plan: Vec<Step>,
    scratch: Vec<Step>,
    mask: u32,
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
}

impl Scheduler {
    /// `blend_new`: the new chunk's weight where chunks overlap (1 = replace); `horizon_ns`: how
    /// long the last target may be held after its time.
    pub fn new(blend_new: f32, horizon_ns: u64) -> Self {
        Scheduler {
            plan: Vec::with_capacity(MAX_PLAN_STEPS),
            scratch: Vec::with_capacity(MAX_PLAN_STEPS),
            mask: 0,
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
        let joints = usize::from(chunk.joint_count).min(MAX_JOINTS);
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
        let old_mask = self.mask;
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
            let mut target = [0f32; MAX_JOINTS];
            target[..joints].copy_from_slice(&chunk.targets[k * joints..(k + 1) * joints]);
            if let Some(old) = interpolate(&self.plan, t_ns, false) {
                for (j, value) in target.iter_mut().enumerate().take(joints) {
                    if old_mask & chunk.joint_mask & (1 << j) != 0 {
                        *value = self.blend_new * *value + (1.0 - self.blend_new) * old[j];
                    }
                }
            }
            self.scratch.push(Step { t_ns, target });
        }
        std::mem::swap(&mut self.plan, &mut self.scratch);
        self.mask = chunk.joint_mask;
    }

    /// The goal for robot time `now_ns`, or `None`: nothing planned, or the plan's last step
    /// is more than the horizon old.
    pub fn target(&mut self, now_ns: u64) -> Option<Target> {
        let last = self.plan.last()?;
        if now_ns > last.t_ns.saturating_add(self.horizon_ns) {
            self.plan.clear();
            self.expired += 1;
            return None;
        }
        // Keep one step at or before now: the start of the segment being interpolated.
        let behind = self.plan.iter().take_while(|s| s.t_ns <= now_ns).count();
        if behind > 1 {
            self.plan.drain(..behind - 1);
        }
        interpolate(&self.plan, now_ns, true).map(|position| Target {
            position,
            mask: self.mask,
        })
    }
}

/// The plan's target at `t_ns`: linear between steps; outside the plan, the nearest end if
/// `extend`, else nothing.
fn interpolate(plan: &[Step], t_ns: u64, extend: bool) -> Option<[f32; MAX_JOINTS]> {
    let (first, last) = (plan.first()?, plan.last()?);
    if t_ns <= first.t_ns {
        return (extend || t_ns == first.t_ns).then_some(first.target);
    }
    if t_ns >= last.t_ns {
        return (extend || t_ns == last.t_ns).then_some(last.target);
    }
    let i = plan.iter().position(|s| s.t_ns > t_ns)?;
    let (a, b) = (&plan[i - 1], &plan[i]);
    let f = (t_ns - a.t_ns) as f32 / (b.t_ns - a.t_ns) as f32;
    let mut out = a.target;
    for (o, (x, y)) in out.iter_mut().zip(a.target.iter().zip(&b.target)) {
        *o = x + f * (y - x);
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::SCHEMA_VERSION;

    const MS: u64 = 1_000_000;

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
    fn a_chunk_entirely_in_the_past_changes_nothing() {
        let mut s = Scheduler::new(0.5, 100 * MS);
        s.insert(&chunk(1, 1000, 20, &[1.0, 1.0]), 1000 * MS);
        s.insert(&chunk(2, 1000, 20, &[9.0, 9.0]), 1100 * MS);
        assert_eq!(s.dropped_past_steps(), 2);
        assert_eq!(at(&mut s, 1030), Some(1.0));
    }
}
