//! The robot's lidar (a Slamtec RPLIDAR C1): revolutions from its serial port onto the state
//! plane (`nori-lidar`).
//!
//! Pure parts: [`protocol`] (the device's serial protocol, sans-IO) and [`scan`] (revolutions
//! from measurements, each checked). With the `process` feature: the configuration, the serial
//! link and the loop.
//!
//! * `config`, `process` (feature `process`): the configuration and the loop.

pub mod protocol;
pub mod scan;

#[cfg(feature = "process")]
pub mod config;
#[cfg(feature = "process")]
pub mod process;
