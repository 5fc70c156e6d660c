//! Motion controller.
pub mod protocol;
pub mod sim;
