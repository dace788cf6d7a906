//! What the supervisor reports, typed: each event names its joint and bus and carries its figure
//! in its own unit. It becomes the state plane's fixed-size `SupervisorEvent` frame (kind, joint,
//! bus, level, value) only at the edge, in [`Event::frame`].

use telemetry::frames::{EventKind, SupervisorEvent};

/// No joint / no bus, in a frame.
pub const NONE: u8 = 0xFF;

/// Who latched a bus off, in a [`Event::ThermalTrip`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TripCause {
    /// The supervisor's own software tier (frame level 3).
    Software,
    /// A latch recorded by an earlier instance, taken up again at start (level 3, no
    /// temperature).
    Restored,
    /// A tier outside the supervisor fired (the firmware, or the driver's last-resort tier),
    /// and the bus is latched like a software trip (level 0).
    Outside,
}

/// One supervisor event.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    /// A joint stalled: current high, position static over the window.
    Stall {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// The current that stalled, A.
        current_a: f32,
    },
    /// A stalled joint gets its one retry at full torque.
    StallRetry {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// Current, A.
        current_a: f32,
    },
    /// A joint's torque was reduced (a gripper's grip, or a joint that stalled again).
    TorqueReduced {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// The new limit, % of full output.
        limit_percent: f32,
    },
    /// A reduced joint got a new target and its torque back.
    TorqueRestored {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// Current, A.
        current_a: f32,
    },
    /// The bus's thermal warning level changed.
    ThermalWarning {
        /// The joint that leads the prediction.
        joint: u8,
        /// The bus.
        bus: u8,
        /// 0 (none) … 3 (critical).
        level: u8,
        /// Predicted time to the trip, s.
        time_to_trip_s: f32,
    },
    /// The whole bus is disabled and latched.
    ThermalTrip {
        /// The hot joint (none for a restored latch or the driver's trip of a bus).
        joint: Option<u8>,
        /// The bus.
        bus: u8,
        /// Who latched it.
        cause: TripCause,
        /// The temperature that tripped it, °C (NaN when restored).
        temperature_c: f32,
    },
    /// A tripped bus was re-enabled after cooling and an explicit command.
    BusReenabled {
        /// The bus.
        bus: u8,
    },
    /// The driver inferred that a firmware protection cut a motor's output.
    OutputLost {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// Its temperature, °C.
        temperature_c: f32,
    },
    /// The supervisor lost the driver (no heartbeat within the bound).
    DriverLost {
        /// Silence so far, s.
        silence_s: f32,
    },
    /// The driver is back: a new process (its pid), or the same one heard again (`None`).
    DriverBack {
        /// The new driver's pid.
        pid: Option<u32>,
    },
    /// A re-enable command was refused: the bus is still hot.
    ReenableRefused {
        /// The bus.
        bus: u8,
        /// Its hottest motor, °C.
        hottest_c: f32,
    },
    /// An operator command was not carried out.
    CommandRefused {
        /// The bus it named.
        bus: u8,
        /// Why (`COMMAND_REFUSED_*`).
        why: u8,
        /// The command's kind.
        command: u8,
    },
    /// A servo reported a firmware protection in its status bits (two frames in a row).
    FirmwareProtection {
        /// Joint index.
        joint: u8,
        /// Its bus.
        bus: u8,
        /// The protection bits (overheat 0x04, over-current 0x08, overload 0x20).
        bits: u8,
        /// Its temperature, °C.
        temperature_c: f32,
    },
    /// The driver's last-resort tier had turned the bus off while no supervisor was heard.
    DriverTrip {
        /// The bus.
        bus: u8,
        /// Its hottest motor, °C.
        hottest_c: f32,
    },
    /// An operator's stop is in force.
    OperatorStop {
        /// Restored from the trip record at start, not commanded now.
        restored: bool,
    },
    /// An operator ended the stop.
    OperatorResume,
}

impl Event {
    /// The state plane's frame for this event, numbered `seq`, at `now_ns`.
    pub fn frame(&self, seq: u64, now_ns: u64) -> SupervisorEvent {
        use Event::*;
        let (kind, joint, bus, level, value) = match *self {
            Stall {
                joint,
                bus,
                current_a,
            } => (EventKind::Stall, joint, bus, 0, current_a),
            StallRetry {
                joint,
                bus,
                current_a,
            } => (EventKind::StallRetry, joint, bus, 0, current_a),
            TorqueReduced {
                joint,
                bus,
                limit_percent,
            } => (EventKind::TorqueReduced, joint, bus, 0, limit_percent),
            TorqueRestored {
                joint,
                bus,
                current_a,
            } => (EventKind::TorqueRestored, joint, bus, 0, current_a),
            ThermalWarning {
                joint,
                bus,
                level,
                time_to_trip_s,
            } => (EventKind::ThermalWarning, joint, bus, level, time_to_trip_s),
            ThermalTrip {
                joint,
                bus,
                cause,
                temperature_c,
            } => {
                let level = match cause {
                    TripCause::Software | TripCause::Restored => 3,
                    TripCause::Outside => 0,
                };
                let joint = joint.unwrap_or(NONE);
                (EventKind::ThermalTrip, joint, bus, level, temperature_c)
            }
            BusReenabled { bus } => (EventKind::BusReenabled, NONE, bus, 0, 0.0),
            OutputLost {
                joint,
                bus,
                temperature_c,
            } => (EventKind::OutputLost, joint, bus, 0, temperature_c),
            DriverLost { silence_s } => (EventKind::DriverLost, NONE, NONE, 0, silence_s),
            DriverBack { pid } => {
                let value = pid.map_or(0.0, |p| p as f32);
                (EventKind::DriverBack, NONE, NONE, 0, value)
            }
            ReenableRefused { bus, hottest_c } => {
                (EventKind::ReenableRefused, NONE, bus, 0, hottest_c)
            }
            CommandRefused { bus, why, command } => (
                EventKind::CommandRefused,
                NONE,
                bus,
                why,
                f32::from(command),
            ),
            FirmwareProtection {
                joint,
                bus,
                bits,
                temperature_c,
            } => (
                EventKind::FirmwareProtection,
                joint,
                bus,
                bits,
                temperature_c,
            ),
            DriverTrip { bus, hottest_c } => (EventKind::DriverTrip, NONE, bus, 0, hottest_c),
            OperatorStop { restored } => {
                (EventKind::OperatorStop, NONE, NONE, restored.into(), 0.0)
            }
            OperatorResume => (EventKind::OperatorResume, NONE, NONE, 0, 0.0),
        };
        SupervisorEvent {
            seq,
            timestamp_ns: now_ns,
            kind: kind as u8,
            joint,
            bus,
            level,
            value,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_event_fills_its_frame_fields_in_their_units() {
        let f = Event::TorqueReduced {
            joint: 2,
            bus: 1,
            limit_percent: 30.0,
        }
        .frame(7, 99);
        assert_eq!(
            (f.seq, f.timestamp_ns, f.kind(), f.joint, f.bus, f.value),
            (7, 99, Some(EventKind::TorqueReduced), 2, 1, 30.0)
        );
        let trip = |cause| Event::ThermalTrip {
            joint: None,
            bus: 0,
            cause,
            temperature_c: 59.2,
        };
        assert_eq!(trip(TripCause::Software).frame(1, 0).level, 3);
        assert_eq!(trip(TripCause::Outside).frame(1, 0).level, 0);
        assert_eq!(trip(TripCause::Restored).frame(1, 0).joint, NONE);
        let back = Event::DriverBack { pid: Some(4242) }.frame(1, 0);
        assert_eq!(
            (back.kind(), back.value),
            (Some(EventKind::DriverBack), 4242.0)
        );
        let refused = Event::CommandRefused {
            bus: 3,
            why: 2,
            command: 9,
        }
        .frame(1, 0);
        assert_eq!((refused.level, refused.value, refused.bus), (2, 9.0, 3));
        let fw = Event::FirmwareProtection {
            joint: 4,
            bus: 0,
            bits: 0x24,
            temperature_c: 60.0,
        }
        .frame(1, 0);
        assert_eq!((fw.level, fw.joint, fw.value), (0x24, 4, 60.0));
    }
}
