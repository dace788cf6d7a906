//! The robot's cameras: frames from V4L2 devices (or the simulator's sockets) onto the state
//! plane as RGB24, one process per camera (`nori-camera --camera NAME`).
//!
//! Pure parts, also used by the simulator, the fleet agent and the black box: [`convert`] (YUYV
//! and MJPEG to RGB, and the reverse the simulated cameras need), [`mode`] (the limits every
//! camera keeps), [`stream`] (the framing of a camera on a byte stream) and [`thumbnail`] (small
//! JPEGs of a frame). With the `process` feature: the sources ([`source`], [`v4l2`]), the
//! configuration and the loop.
//!
//! * `config`, `process` (feature `process`): the configuration and the loop.

pub mod convert;
pub mod mode;
pub mod stream;
pub mod thumbnail;

#[cfg(feature = "process")]
pub mod config;
#[cfg(feature = "process")]
pub mod process;
#[cfg(feature = "process")]
pub mod source;
#[cfg(feature = "process")]
pub mod v4l2;
