//! Nori Lab: the robot in the browser. A page served on loopback shows the robot posed live
//! from the state plane (the one robot description's kinematics), each motor's temperature,
//! current and protection state on the model, and lets an operator drive the arms (joint
//! sliders, a tool target dragged in 3D through the arm's inverse kinematics) and stop the
//! robot. Its parts:
//!
//! - [`teleop`] (pure): the page's commands → goal frames, within the calibrated ranges, at a
//!   bounded speed, under a dead-man;
//! - [`scene`] (pure): what the page draws, as JSON;
//! - [`page`] (pure): the page's messages, and who may connect (token, host, origin);
//! - [`messages`] (pure): what the lab sends a page, typed;
//! - [`stop_button`] (pure): a stop or resume press answered only once the supervisor shows it
//!   heard it;
//! - [`server`]: HTTP and WebSocket on std's TCP, a thread per page, never blocking the loop;
//! - [`recording`]: episodes recorded from the page by `nori record` itself;
//! - [`process`]: the lab's loop against a [`process::LabIo`] (the binary's plane, pages,
//!   cameras and recorder; a test's queues), time read from it;
//! - the binary `nori-lab` (`nori lab`): the state plane in, goals and the supervisor's
//!   commands out.

pub mod messages;
pub mod page;
pub mod process;
pub mod recording;
pub mod scene;
pub mod server;
pub mod stop_button;
pub mod teleop;
