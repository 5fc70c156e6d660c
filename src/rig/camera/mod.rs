//! Camera (placeholder while decode lands).
