//! Estimation from a capture session on disk (`lensrig estimate --session`, `lensrig
//! calibrate`): one profile per finished pair, written to `OUT/<pair key>/`.
//!
//! A pair is read as stored ([`read_pair`]): the wide-open and pinhole frames, their sidecars
//! (`open.toml`, `pinhole.toml`: exposure in µs, aperture and stage positions in mm, frames
//! averaged) and the transfer curve the camera declared. A dark frame's per-channel mean
//! ([`dark_levels`], full-scale units) is the black level subtracted before estimation.

use super::{estimate, Estimate, EstimateError, EstimateOptions};
use crate::image::io::{read_image, ImageError};
use crate::image::{Image, Transfer};
use crate::profile::ProfileError;
use crate::rig::session::{self, FrameRecord, PairRecord, SessionError};
use std::path::{Path, PathBuf};

/// Why a session could not be read or estimated. Every variant names the session, the pair or
/// the file.
#[derive(Debug, thiserror::Error)]
pub enum SessionEstimateError {
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error("session {} has no finished pairs (status: {status})", dir.display())]
    Empty { dir: PathBuf, status: String },
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{}: transfer: {message}", path.display())]
    Transfer { path: PathBuf, message: String },
    #[error("pair {pair}")]
    Estimate { pair: String, #[source] source: EstimateError },
    #[error(transparent)]
    Profile(#[from] ProfileError),
}

/// One finished pair as stored: the two frames (tagged with the declared transfer curve) and
/// their sidecars.
pub struct SessionPair {
    /// The pair's directory.
    pub dir: PathBuf,
    pub open_path: PathBuf,
    pub pinhole_path: PathBuf,
    pub open: Image,
    pub pinhole: Image,
    pub open_record: FrameRecord,
    pub pinhole_record: FrameRecord,
    pub transfer: Transfer,
}

/// Reads a session's record and refuses one without finished pairs.
///
/// # Errors
/// An unreadable `session.toml`, or no finished pair.
pub fn load_finished(dir: &Path) -> Result<session::SessionRecord, SessionEstimateError> {
    let rec = session::load_session(dir)?;
    if rec.pairs.is_empty() {
        return Err(SessionEstimateError::Empty { dir: dir.to_path_buf(), status: rec.status });
    }
    Ok(rec)
}

/// Reads one pair of the session in `session_dir`.
///
/// # Errors
/// Unreadable frames or sidecars, or an unknown transfer curve (naming `open.toml`).
pub fn read_pair(session_dir: &Path, p: &PairRecord) -> Result<SessionPair, SessionEstimateError> {
    let pd = session_dir.join(&p.dir);
    let (open_path, pinhole_path) = (pd.join(&p.open), pd.join(&p.pinhole));
    let (mut open, mut pinhole) = crate::image::io::read_pair(&open_path, &pinhole_path)?;
    let open_record = session::load_frame_record(&pd.join("open.toml"))?;
    let pinhole_record = session::load_frame_record(&pd.join("pinhole.toml"))?;
    let transfer: Transfer = open_record.transfer.parse().map_err(|message| SessionEstimateError::Transfer { path: pd.join("open.toml"), message })?;
    open.transfer = transfer;
    pinhole.transfer = transfer;
    Ok(SessionPair { dir: pd, open_path, pinhole_path, open, pinhole, open_record, pinhole_record, transfer })
}

/// The mean of a dark frame per stored channel (the black level to subtract, full scale).
///
/// # Errors
/// An unreadable frame.
pub fn dark_levels(path: &Path) -> Result<Vec<f32>, ImageError> {
    Ok(read_image(path)?.planes.iter().map(|p| p.mean() as f32).collect())
}

/// Estimates one profile per finished pair of the session in `dir` into `out/<pair key>/`;
/// `opts.black_level` is replaced by a pair's dark frame when it has one.
///
/// # Errors
/// [`SessionEstimateError`]: an unreadable or empty session, a failed estimate (naming the
/// pair), an unwritable profile.
pub fn estimate_session(dir: &Path, out: &Path, opts: &EstimateOptions, progress: bool) -> Result<Vec<(PairRecord, Estimate)>, SessionEstimateError> {
    let rec = load_finished(dir)?;
    let mut done = Vec::new();
    for p in &rec.pairs {
        let sp = read_pair(dir, p)?;
        let mut opts = opts.clone();
        if let Some(d) = &p.dark {
            opts.black_level = dark_levels(&sp.dir.join(d))?;
        }
        let (om, pm) = (&sp.open_record, &sp.pinhole_record);
        if progress {
            eprintln!("estimating {} (open {} µs at {} mm, pinhole {} µs at {} mm)", p.key, om.exposure_us, om.aperture_mm, pm.exposure_us, pm.aperture_mm);
        }
        let mut est = estimate(&sp.open, &sp.pinhole, &opts).map_err(|source| SessionEstimateError::Estimate { pair: p.key.clone(), source })?;
        est.profile.meta.source.open = Some(sp.open_path.display().to_string());
        est.profile.meta.source.pinhole = Some(sp.pinhole_path.display().to_string());
        est.profile.meta.note = format!(
            "session {} pair {}: stage {} mm; aperture open at {} mm ({} µs), pinhole at {} mm ({} µs)",
            dir.display(),
            p.key,
            p.stage_mm,
            om.aperture_mm,
            om.exposure_us,
            pm.aperture_mm,
            pm.exposure_us
        );
        est.profile.save(&out.join(&p.key))?;
        done.push((p.clone(), est));
    }
    Ok(done)
}
