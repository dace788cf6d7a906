//! The model lab: holds the simulation's servo model against measured data, shows where it is
//! wrong, names the physical cause from a catalog, extends the model with it and measures the
//! gain on data the fit never saw.
//!
//! * [`data`]: the telemetry CSV reader (the crate's only file access), time grid, segments,
//!   glitch rejection.
//! * [`thermal`]: the nominal thermal model (τ·dT/dt = T_idle + k·I² − T per motor) and its
//!   extensions, simulated open-loop and fitted by output error.
//! * [`register`]: the temperature register's likelihood (rounding and noise), fitted as a
//!   deviance residual.
//! * [`electrical`]: the supply voltage channel (constant supply, or sagging with bus current).
//! * [`motion`]: the motion channel — measured runs replayed open-loop through the simulator's
//!   servo (firmware loop, motor, gear, friction) with their load; held out run by run.
//! * [`catalog`]: the extensions (`sensor_lag`, `neighbor_coupling`, `copper_tempco`,
//!   `ambient_drift`, `supply_sag`, `current_offset`) and `none`.
//! * [`audit`]: data that lie — channels against the servo's physical ranges and unit
//!   mistakes (fixed when unambiguous, refused when nonsense), stuck sensors, clock jumps.
//! * [`analysis`]: split, calibrate, misfit statistics, the tests that decide the cause.
//! * [`form`]: what an unexplained misfit looks like: a sparse regression of the residual over
//!   a library of terms, chosen by held-out error.
//! * [`verdict`]: why an extension is named or not, as a type.
//! * [`fit`]: Levenberg–Marquardt aware of per-motor block structure.
//! * [`stats`]: RMSE, bias, autocorrelation, Ljung–Box, χ².
//! * [`generate`]: a truth model that hides one effect of random size in measured-like data.
//! * [`bench`]: accuracy and detection limits over many seeds.
//! * [`report`]: a Markdown report with SVG plots, as strings (the caller writes them).
//! * [`replay`]: a black box's bus traffic played into the simulated servos, their replies
//!   held against the recorded ones register by register (`nori sim replay`).
//!
//! The model file the lab writes is [`sim::extension::ModelExtension`], which the simulator loads.

pub mod analysis;
pub mod audit;
pub mod bench;
pub mod catalog;
pub mod data;
pub mod electrical;
pub mod fit;
pub mod form;
pub mod generate;
pub mod motion;
pub mod register;
pub mod replay;
pub mod report;
pub mod stats;
pub mod thermal;
pub mod verdict;

pub use analysis::{analyze, Analysis, AnalysisError, Options, Outcome};
pub use catalog::{Channel, Effect};
pub use data::{load, load_all, DataError, Dataset};
