//! Diagnosis inputs from a capture session (`lensrig diagnose --session`): every finished
//! pair with the transfer curve, dark level and frame counts of its metadata.
//!
//! A dark frame's per-channel mean (full-scale units) is subtracted from both captures of
//! linear data, so the sensor's own black level is not reported as a mismatch. The
//! reference's relative noise variance is `frames averaged (open) / frames averaged
//! (pinhole)`; when the open frame's sidecar carries a temporal noise curve (one frame's
//! variance per level), it becomes the noise model divided by the frames averaged, its levels
//! shifted by the subtracted dark level.

use super::noise::NoiseCurve;
use super::DiagnoseOptions;
use crate::estimate::session::{dark_levels, read_pair, SessionEstimateError, SessionPair};
use crate::image::Transfer;
use crate::rig::session::{FrameRecord, PairRecord};
use std::path::Path;

/// Reads one pair of a session and the options to diagnose it with (`base` plus the pair's
/// frame counts and noise curve); the captures come back with the dark level subtracted.
///
/// # Errors
/// Unreadable frames, sidecars or dark frame, naming the file.
pub fn pair_inputs(session_dir: &Path, pair: &PairRecord, base: &DiagnoseOptions) -> Result<(SessionPair, DiagnoseOptions), SessionEstimateError> {
    let mut sp = read_pair(session_dir, pair)?;
    let mut dark: Vec<f32> = Vec::new();
    if let (Some(d), Transfer::Linear) = (&pair.dark, sp.transfer) {
        let levels = dark_levels(&sp.dir.join(d))?;
        dark = (0..sp.open.channel_count()).map(|c| levels.get(c).or(levels.first()).copied().unwrap_or(0.0)).collect();
        for img in [&mut sp.open, &mut sp.pinhole] {
            for (c, plane) in img.planes.iter_mut().enumerate() {
                let level = dark.get(c).copied().unwrap_or(0.0);
                plane.data.iter_mut().for_each(|v| *v = (*v - level).max(0.0));
            }
        }
    }
    let mut opts = base.clone();
    let (om, pm) = (&sp.open_record, &sp.pinhole_record);
    opts.pinhole_variance_scale = om.frames_averaged.max(1) as f64 / pm.frames_averaged.max(1) as f64;
    opts.repeat_noise = repeat_noise(om, sp.transfer, &dark);
    Ok((sp, opts))
}

/// The temporal noise of one frame over the averaged frames (the average's variance is that
/// over the frame count); a dark level subtracted from linear data shifts the levels.
fn repeat_noise(om: &FrameRecord, transfer: Transfer, dark: &[f32]) -> Option<Vec<NoiseCurve>> {
    let t = om.temporal_noise.as_ref()?;
    let shift = if transfer == Transfer::Linear { dark.to_vec() } else { vec![0.0; t.len()] };
    let n = om.frames_averaged.max(1) as f64;
    Some(
        t.iter()
            .enumerate()
            .map(|(c, rows)| {
                let d = shift.get(c).or(shift.first()).copied().unwrap_or(0.0) as f64;
                NoiseCurve { bins: rows.iter().map(|r| ((r[0] - d).max(0.0), r[1] / n, r[2] as usize)).collect() }
            })
            .collect(),
    )
}
