//! Lens data for other tools: a profile's measurements in formats their readers know.
//! Today: [`lensfun`] (a lensfun database file, format version 1).

pub mod lensfun;
