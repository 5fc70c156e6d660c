//! `lensrig simulate` as a library function: the wide-open capture a profile predicts from a
//! sharp (pinhole) image.
//!
//! The sharp image is taken as stored in the profile's source encoding: decoded with the
//! source transfer curve, the source black level (full-scale units, per channel or one for
//! all) subtracted, blurred through the profile's PSF grid ([`crate::optics::forward`]),
//! scaled by the exposure ratio, the black level added back and re-encoded. A profile refitted
//! by `lensrig diagnose` (a non-empty `[corrections]` table) predicts with its physics instead
//! ([`super::model::apply_corrections`]). Sizes are pixels; values full scale.

use super::model::{apply_corrections, CorrectionError};
use crate::image::Image;
use crate::optics::forward::blur_channel;
use crate::profile::Profile;

/// Why a prediction could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PredictError {
    #[error("image is {got_width}x{got_height} but the profile was estimated from {width}x{height} images")]
    Size { got_width: usize, got_height: usize, width: usize, height: usize },
    #[error("image has {got} channel(s), the profile {expected}")]
    Channels { got: usize, expected: usize },
    #[error("applying the profile's [corrections]")]
    Corrections(#[source] CorrectionError),
}

/// The wide-open image `profile` predicts from `sharp`, in the profile's encoding and sample
/// format.
///
/// # Errors
/// [`PredictError`] when the image's size or channel count differs from the profile's source,
/// or its corrections cannot be applied.
pub fn predict(profile: &Profile, sharp: &Image) -> Result<Image, PredictError> {
    let src = &profile.meta.source;
    if sharp.width() != src.width || sharp.height() != src.height {
        return Err(PredictError::Size { got_width: sharp.width(), got_height: sharp.height(), width: src.width, height: src.height });
    }
    if sharp.channel_count() != profile.grid.channels.len() {
        return Err(PredictError::Channels { got: sharp.channel_count(), expected: profile.grid.channels.len() });
    }
    if !profile.meta.corrections.is_empty() {
        // a profile refitted by `lensrig diagnose`: its physics applies (module docs of
        // `diagnose::model`)
        return apply_corrections(profile, sharp).map_err(PredictError::Corrections);
    }
    let black = &src.black_level;
    let planes: Vec<_> = sharp
        .planes
        .iter()
        .enumerate()
        .map(|(c, p)| {
            let b = black.get(c).or(black.first()).copied().unwrap_or(0.0);
            let lin = p.map(|v| src.transfer.decode(v) - b);
            let mut out = blur_channel(&lin, &profile.grid, c);
            let s = profile.meta.exposure_ratio[c] as f32;
            out.data.iter_mut().for_each(|v| *v = src.transfer.encode(*v * s + b));
            out
        })
        .collect();
    let mut img = Image::new(planes);
    img.channels = profile.grid.channels.clone();
    img.transfer = src.transfer;
    img.format = src.sample_format;
    Ok(img)
}
