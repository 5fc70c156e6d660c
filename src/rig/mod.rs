//! The calibration rig: a motion controller ([`controller`]) that moves the aperture and the
//! stage, and a camera ([`camera`]) that records frames, configured by one TOML file
//! ([`config`]).
//!
//! # Conventions
//! - Axis positions are millimetres in the controller's **machine** coordinates (grbl `MPos`),
//!   never work coordinates, so a rig config stays valid whatever offsets a user set.
//! - Devices sit behind small traits ([`controller::Controller`], [`camera::Camera`]); backends
//!   are named for what they talk to (`GrblController`, `V4lCamera`).
//! - Errors are typed per device and carry the port/device path.

pub mod camera;
pub mod config;
pub mod controller;
pub mod devices;
pub mod events;
pub mod session;
