//! Commissioning and service of the servo buses, as the end of the production line and a
//! customer with a replacement servo use them (`nori servo …`). Nothing here runs while the
//! driver has the bus: the serial port is opened exclusively, so one of the two is refused.
//!
//! * [`scan`]: what is on a bus: every servo's id, model, firmware, line rate and the EEPROM
//!   settings the stack relies on, found by unicast and broadcast ping at every rate the
//!   servos support; duplicated ids and servos at the wrong rate found and named.
//! * [`settings`]: the control table a servo answered, decoded (identity and EEPROM).
//! * [`setup`]: a new servo given its joint's id, the bus's rate and the driver's EEPROM,
//!   found alone or at the factory's id; refused when the id is taken, the servo not alone, at
//!   another joint's id, or the wrong model.
//! * [`findings`]: a scan judged against the driver's configuration: what is missing, at the
//!   wrong rate or id, of the wrong model, and which EEPROM setting differs from what the
//!   driver writes.
//! * [`calibrate`]: a joint's travel swept by hand (across the encoder's wrap) and the
//!   calibration chosen from it, refused when the travel is not the description's.
//! * [`by_hand`]: a calibration by hand over the line: the joints taken (torque off, offsets
//!   cleared), read while the operator sweeps them, the chosen calibration written and read
//!   back, or every servo given back what it held.
//! * [`automatic`]: the arm calibrating itself: each joint in the description's order swept in
//!   speed mode at a low torque limit into each stop, found by the supervisor's stall rule, the
//!   calibration chosen as by hand; any refusal drives the joint back and gives every servo
//!   back what it held.
//! * [`session`]: what both do to a servo: take it, write with the Lock around it and read
//!   back, give back what it held.
//! * [`record`]: the calibration written as a versioned file, atomically, the previous one
//!   kept, and what changed said joint by joint.

pub mod automatic;
pub mod by_hand;
pub mod calibrate;
pub mod findings;
pub mod record;
pub mod scan;
pub mod session;
pub mod settings;
pub mod setup;
