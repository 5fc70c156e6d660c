//! Optics: PSF grids, the forward model (sharp → predicted capture) and the physical lens
//! simulator used as the rig's digital twin.

pub mod capture;
pub mod distortion;
pub mod field_operator;
pub mod forward;
pub mod kernel_operator;
pub mod lens;
pub mod psf_grid;
pub mod vignetting;
