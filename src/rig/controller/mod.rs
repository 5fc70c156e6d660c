//! Motion controller.
pub mod protocol;
