//! The black box: every robot keeps its last minutes in memory, and freezes them into an MCAP
//! file when something goes wrong.
//!
//! * [`channel`]: the box's channels, their JSON schemas, and each state-plane frame as a JSON
//!   message (the bus traffic byte for byte, base64).
//! * [`frame_tree`]: the body's frames (arms, lift, base) from the joint states, for a viewer's
//!   3D panel.
//! * [`ring`]: the last minutes in memory, sealed in zstd segments, the oldest dropped beyond
//!   the span or the byte cap; nothing reaches the SD card until a box is frozen.
//! * [`frozen`]: a box as an MCAP file (zstd chunks, each flushed and synced as it finishes),
//!   read back linearly as far as it is whole, and recovered after a crash.
//! * [`shelf`]: the boxes on disk, numbered across restarts (never ordered by the wall clock),
//!   the oldest removed beyond the cap whatever their state.
//! * [`trigger`]: what freezes a box (protection events, an obstruction, a protective stop, the
//!   driver's safe state, the operator).
//! * [`recorder`]: the core: messages into the ring and the open box, a trigger opening a box
//!   with the ring's window, the box finished when its window has passed (time passed in).
//! * [`export`]: a box's joint states as the model lab's CSV, and what a box holds.
//! * [`lead_up`]: what led to a box's event (its joint's figures and the protections before
//!   it), for the fleet's statistics.
//! * [`config`]: the recorder's configuration, `blackbox.toml`.
//!
//! The process (`nori-blackbox`, feature `process`) moves frames from the state plane into the
//! recorder; the driver hands it the wire through a queue that overwrites its oldest frame, so
//! a slow, hung or dead recorder never holds the control loop (`docs/blackbox.md`).

pub mod channel;
pub mod config;
pub mod export;
pub mod frame_tree;
pub mod frozen;
pub mod lead_up;
pub mod recorder;
pub mod ring;
pub mod shelf;
pub mod trigger;
