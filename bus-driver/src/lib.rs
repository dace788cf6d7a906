//! The bus driver: the hard-real-time loop on the servo buses.
//!
//! * [`transport`]: the narrow byte-link trait with deadlines, and the serial implementation
//!   (1 Mbps, FTDI latency-timer check).
//! * [`bus`]: transactions on one bus (SYNC_READ of the feedback block, SYNC_WRITE of goals,
//!   unicast setup reads/writes), replies matched by id, error counts by kind.
//! * [`calibration`]: per-joint ranges; the clamp that keeps every goal inside them and refuses
//!   NaN/inf.
//! * [`approach`]: a joint's approach to the ends of its range, slowed (the servo's own
//!   overshoot stays clear of a stop 2° beyond).
//! * [`backstops`]: the EEPROM settings (firmware over-current, torque and 60 °C temperature
//!   limits) written once with read-compare-write.
//! * [`config`]: the typed configuration, defaults embedded from `deploy/config/`.
//! * [`driver`]: setup, the cycle, goal gating, the supervisor's directives, the safe state;
//!   torque off on every stop.
//! * [`plausibility`]: holds back feedback that jumped further than a servo can move or heat
//!   (two flipped bits can pass the checksum; the servos' own 0 °C / 150 °C glitches do).
//! * [`cutoff`]: inferring from the motor that a firmware protection cut its output.
//! * [`runloop`]: the fixed-rate loop, the supervisor's heartbeat watched.
//! * [`tap`]: the wire tap, every byte sent and received copied for the black box.
//!
//! Safety behaviour: goals are clamped to the calibrated range at the bus layer; a goal frame
//! with a non-finite value, the wrong shape or a stale timestamp is refused whole; a servo that
//! does not answer is marked missing in that cycle's sample (never its previous value); torque is
//! turned off when the loop ends, when the driver is dropped (errors, unwinding panics), and on
//! SIGINT/SIGTERM in the binary.
//!
//! * `rt`: real-time preparation of the control thread (memory locked, priority, cores).

pub mod approach;
pub mod backstops;
pub mod bus;
pub mod calibration;
pub mod config;
pub mod cutoff;
pub mod driver;
pub mod plausibility;
pub mod rt;
pub mod runloop;
pub mod tap;
pub mod transport;

pub use config::LoadedConfig;
pub use driver::Driver;
pub use runloop::{run, LoopIo, RunSummary, Standalone};
pub use transport::{SerialTransport, Transport};
