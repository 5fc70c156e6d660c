//! Registration of a sharp (pinhole) capture to the target file itself, and the lens's
//! geometric distortion from it.
//!
//! The target's noise pattern is known cell for cell ([`TargetSpec::noise_at`]), so the
//! capture can be compared with the scene an ideal, undistorted lens would give:
//! 1. **Coarse lock.** From a nominal layout (`u = u0 + x / pixels_per_cell`, the same for `v`;
//!    the rig knows its magnification only roughly) the expected scene is rendered in a central
//!    crop at scales `1 ± 0.01·k` (`k ≤ 8`) about the image centre; the scale whose phase
//!    correlation ([`crate::estimate::register::phase_correlation`]) gives the highest
//!    normalised cross-correlation (NCC) wins, and its peak corrects the offset.
//! 2. **Tiles.** Over the field, per `64 × 64` tile (stride 32), the displacement `d` with
//!    `capture(p) ≈ expected(p − d)`, and the NCC at the integer peak; tiles below
//!    [`LocateOptions::min_ncc`] (off the noise field, weak peak) are not used.
//! 3. **Fit.** By Gauss–Newton least squares, a similarity (scale, rotation, translation) and
//!    lensfun's ptlens `a, b, c` ([`crate::optics::distortion`], centre at the image centre):
//!    `p ≈ c + D(A·(m − c) + t)`, `m = p − d` the tile's position in the expected scene, `A`
//!    a scaled rotation, `D` the ptlens map in pixels about `c`. One round of outlier
//!    rejection at 3 × the median residual (at least 0.1 px), then a refit. Steps 2 and 3
//!    repeat against the scene rendered through the fit until the map moves < 0.003 px.
//!
//! # Units
//! Pixels (sensor, pixel centres at integers), target cells, lensfun distortion units
//! ([`crate::optics::distortion::radius_norm`]). The fiducials are not used: the noise field
//! covers the frame in the setups this is meant for; tiles that do not see noise are rejected.

use super::{render_noise_scene_mapped, TargetSpec};
use crate::estimate::register::phase_correlation;
use crate::image::Plane;
use crate::optics::distortion::{centre, radius_norm, PtLens};
use crate::solve::dense::gauss_jordan;
use rayon::prelude::*;

/// Where the rig expects the target: undistorted pixel `(x, y)` shows cell coordinates
/// `(u0 + x / pixels_per_cell, v0 + y / pixels_per_cell)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Nominal {
    pub pixels_per_cell: f64,
    pub u0: f64,
    pub v0: f64,
}

/// Tuning of [`locate`].
#[derive(Clone, Copy, Debug)]
pub struct LocateOptions {
    /// Tile side, pixels.
    pub tile: usize,
    /// Tile stride, pixels.
    pub stride: usize,
    /// Largest relative scale error of the nominal the coarse search covers.
    pub scale_range: f64,
    /// A tile is used when its NCC at the peak is at least this.
    pub min_ncc: f64,
    /// Fewer usable tiles than this is an error.
    pub min_tiles: usize,
}

impl Default for LocateOptions {
    fn default() -> Self {
        Self { tile: 64, stride: 32, scale_range: 0.08, min_ncc: 0.3, min_tiles: 12 }
    }
}

/// One tile's measurement: centre `(x, y)`, displacement `(dx, dy)` against the coarsely
/// locked expected scene (the content at `(x, y)` is at `(x − dx, y − dy)` there), NCC of the
/// last pass, and whether the final fit used it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileMatch {
    pub x: f64,
    pub y: f64,
    pub dx: f64,
    pub dy: f64,
    pub ncc: f64,
    pub used: bool,
}

/// The fitted geometry.
#[derive(Clone, Debug)]
pub struct DistortionFit {
    pub ptlens: PtLens,
    /// Undistorted pixels per target cell (the magnification).
    pub pixels_per_cell: f64,
    /// Rotation of the target on the sensor, degrees.
    pub rotation_deg: f64,
    /// Translation of the similarity, pixels (against the coarse lock).
    pub translation_px: [f64; 2],
    /// Scale the coarse search locked at, relative to the nominal.
    pub coarse_scale: f64,
    /// RMS of the fit's residuals over the used tiles, pixels.
    pub rms_residual_px: f64,
    pub tiles_used: usize,
    pub tiles: Vec<TileMatch>,
    pub width: usize,
    pub height: usize,
}

/// Why the capture could not be registered to the target.
#[derive(Debug, thiserror::Error)]
pub enum LocateError {
    #[error("the capture holds non-finite values (NaN or Inf)")]
    NonFinite,
    #[error("the capture is {width}x{height}; registration needs at least {need}x{need} pixels")]
    TooSmall { width: usize, height: usize, need: usize },
    #[error("target not found: the best match of the expected noise in the centre has NCC {best_ncc:.2} (need ≥ {need:.2}); is the target in view, the nominal scale within ±{range_pct:.0} %?")]
    NotFound { best_ncc: f64, need: f64, range_pct: f64 },
    #[error("too few usable tiles: {used} of {total} matched the target (need {need})")]
    TooFewTiles { used: usize, total: usize, need: usize },
}

/// Pearson correlation of `a(p)` with `b(p − s)` over their overlap (`s` integer pixels).
fn ncc(a: &Plane, b: &Plane, sx: isize, sy: isize) -> f64 {
    let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
    for y in 0..a.height as isize {
        for x in 0..a.width as isize {
            let (bx, by) = (x - sx, y - sy);
            if bx < 0 || by < 0 || bx >= b.width as isize || by >= b.height as isize {
                continue;
            }
            let (u, v) = (a.get(x as usize, y as usize) as f64, b.get(bx as usize, by as usize) as f64);
            n += 1.0;
            sa += u;
            sb += v;
            saa += u * u;
            sbb += v * v;
            sab += u * v;
        }
    }
    if n < 16.0 {
        return 0.0;
    }
    let cov = sab / n - sa * sb / (n * n);
    let va = saa / n - (sa / n).powi(2);
    let vb = sbb / n - (sb / n).powi(2);
    if va <= 1e-20 || vb <= 1e-20 {
        0.0
    } else {
        cov / (va * vb).sqrt()
    }
}

/// Displacement and NCC of the capture window `(x0, y0, n × n)` against the expected scene,
/// `cell_of` mapping sensor pixel coordinates to target cell coordinates.
fn match_window(cap: &Plane, spec: &TargetSpec, x0: usize, y0: usize, n: usize, cell_of: impl Fn(f64, f64) -> (f64, f64)) -> (f64, f64, f64) {
    let a = cap.window_reflect(x0 as isize, y0 as isize, n, n);
    let b = render_noise_scene_mapped(spec, n, n, 1.0, 0.0, 0.0, |x, y| cell_of(x + x0 as f64, y + y0 as f64));
    let (dx, dy, _) = phase_correlation(&a, &b);
    (dx, dy, ncc(&a, &b, dx.round() as isize, dy.round() as isize))
}

/// Cell coordinates of pixel `(x, y)` of a straight layout.
fn cells(l: &Nominal, x: f64, y: f64) -> (f64, f64) {
    (l.u0 + x / l.pixels_per_cell, l.v0 + y / l.pixels_per_cell)
}

/// Step 1: the scale (relative to the nominal, about the image centre) and offset that
/// match the central crop best; returns the locked layout, its scale and NCC.
fn coarse_lock(cap: &Plane, spec: &TargetSpec, nominal: &Nominal, o: &LocateOptions) -> (Nominal, f64, f64) {
    let (w, h) = (cap.width, cap.height);
    let n = (w.min(h) / 2).min(128) & !1;
    let (x0, y0) = ((w - n) / 2, (h - n) / 2);
    let (cx, cy) = centre(w, h);
    let (uc, vc) = (nominal.u0 + cx / nominal.pixels_per_cell, nominal.v0 + cy / nominal.pixels_per_cell);
    let steps = (o.scale_range / 0.01).round() as i32;
    let mut best = (*nominal, 1.0, f64::NEG_INFINITY);
    for k in -steps..=steps {
        let s = 1.0 + 0.01 * k as f64;
        let p = nominal.pixels_per_cell * s;
        let l = Nominal { pixels_per_cell: p, u0: uc - cx / p, v0: vc - cy / p };
        let (dx, dy, q) = match_window(cap, spec, x0, y0, n, |x, y| cells(&l, x, y));
        if q > best.2 {
            best = (Nominal { pixels_per_cell: p, u0: l.u0 - dx / p, v0: l.v0 - dy / p }, s, q);
        }
    }
    best
}

/// Step 2: every tile's displacement against the expected scene through the model `th`
/// (straight at first, then the previous fit), as positions in the locked layout.
fn measure_tiles(cap: &Plane, spec: &TargetSpec, l: &Nominal, th: &[f64; 7], o: &LocateOptions) -> Vec<TileMatch> {
    let (w, h) = (cap.width, cap.height);
    let t = o.tile;
    let origins: Vec<(usize, usize)> = (0..=h - t).step_by(o.stride).flat_map(|y0| (0..=w - t).step_by(o.stride).map(move |x0| (x0, y0))).collect();
    // tiles are independent: in parallel, collected in raster order
    origins
        .par_iter()
        .map(|&(x0, y0)| {
            let (dx, dy, q) = match_window(cap, spec, x0, y0, t, |x, y| {
                let (mx, my) = unpredict(th, (x, y), w, h);
                cells(l, mx, my)
            });
            let (x, y) = (x0 as f64 + t as f64 / 2.0 - 0.5, y0 as f64 + t as f64 / 2.0 - 0.5);
            let (mx, my) = unpredict(th, (x - dx, y - dy), w, h);
            TileMatch { x, y, dx: x - mx, dy: y - my, ncc: q, used: q >= o.min_ncc }
        })
        .collect()
}

/// The inverse of [`predict`]: the expected-scene position shown at sensor pixel `p`.
fn unpredict(th: &[f64; 7], p: (f64, f64), w: usize, h: usize) -> (f64, f64) {
    let (cx, cy) = centre(w, h);
    let d = PtLens { a: th[4], b: th[5], c: th[6] };
    let (qx, qy) = d.undistort_px(p.0, p.1, w, h);
    let (qx, qy) = (qx - cx - th[2], qy - cy - th[3]);
    let (al, be) = (1.0 + th[0], th[1]);
    let det = al * al + be * be;
    (cx + (al * qx + be * qy) / det, cy + (-be * qx + al * qy) / det)
}

/// The model's sensor position of expected-scene point `m` under parameters
/// `θ = (α − 1, β, tx, ty, a, b, c)` (see the module docs).
fn predict(th: &[f64; 7], m: (f64, f64), w: usize, h: usize) -> (f64, f64) {
    let (cx, cy) = centre(w, h);
    let (x, y) = (m.0 - cx, m.1 - cy);
    let (al, be) = (1.0 + th[0], th[1]);
    let (qx, qy) = (al * x - be * y + th[2], be * x + al * y + th[3]);
    let d = PtLens { a: th[4], b: th[5], c: th[6] };
    let f = d.ratio(qx.hypot(qy) * radius_norm(w, h));
    (cx + qx * f, cy + qy * f)
}

fn residuals(th: &[f64; 7], tiles: &[&TileMatch], w: usize, h: usize) -> Vec<f64> {
    tiles
        .iter()
        .flat_map(|t| {
            let (px, py) = predict(th, (t.x - t.dx, t.y - t.dy), w, h);
            [px - t.x, py - t.y]
        })
        .collect()
}

/// Step 3: Gauss–Newton (numerical Jacobian) from the identity, no distortion.
fn fit(tiles: &[&TileMatch], w: usize, h: usize) -> [f64; 7] {
    let mut th = [0.0f64; 7];
    for _ in 0..12 {
        let r0 = residuals(&th, tiles, w, h);
        let mut jac = vec![[0.0f64; 7]; r0.len()];
        for k in 0..7 {
            let mut t2 = th;
            let e = 1e-6;
            t2[k] += e;
            for (row, (a, b)) in jac.iter_mut().zip(residuals(&t2, tiles, w, h).iter().zip(&r0)) {
                row[k] = (a - b) / e;
            }
        }
        let mut m = [[0.0f64; 7]; 7];
        let mut g = [0.0f64; 7];
        for (row, r) in jac.iter().zip(&r0) {
            for i in 0..7 {
                g[i] -= row[i] * r;
                for j in 0..7 {
                    m[i][j] += row[i] * row[j];
                }
            }
        }
        let Some(step) = gauss_jordan(m, g, 1e-300) else { break };
        th.iter_mut().zip(step).for_each(|(t, s)| *t += s);
        if step.iter().all(|s| s.abs() < 1e-10) {
            break;
        }
    }
    th
}

/// RMS and per-tile residual lengths of a fit, pixels.
fn tile_residuals(th: &[f64; 7], tiles: &[&TileMatch], w: usize, h: usize) -> Vec<f64> {
    residuals(th, tiles, w, h).chunks(2).map(|c| c[0].hypot(c[1])).collect()
}

/// Measurement passes, at most: the first against the straight layout, each further one
/// against the scene rendered through the previous fit (so the remaining displacements are
/// small and uniform within a tile; the sub-pixel peak interpolation under-reads a shift, so
/// each pass recovers most, not all, of what is left).
const MAX_PASSES: usize = 10;
/// Passes stop when the fitted map moves by less than this along the diagonal, pixels.
const CONVERGED_PX: f64 = 0.003;

/// One pass: tiles through the model `th`, the fit, outlier rejection, the refit. Returns the
/// parameters, the tiles (with `used`) and the RMS residual, pixels.
fn fit_pass(cap: &Plane, spec: &TargetSpec, lock: &Nominal, th0: &[f64; 7], o: &LocateOptions) -> Result<([f64; 7], Vec<TileMatch>, f64), LocateError> {
    let (w, h) = (cap.width, cap.height);
    let mut tiles = measure_tiles(cap, spec, lock, th0, o);
    let too_few = |used: usize, total: usize| LocateError::TooFewTiles { used, total, need: o.min_tiles };
    let good: Vec<usize> = (0..tiles.len()).filter(|&i| tiles[i].used).collect();
    if good.len() < o.min_tiles {
        return Err(too_few(good.len(), tiles.len()));
    }
    let sel: Vec<&TileMatch> = good.iter().map(|&i| &tiles[i]).collect();
    let th = fit(&sel, w, h);
    let res = tile_residuals(&th, &sel, w, h);
    let mut sorted = res.clone();
    sorted.sort_by(f64::total_cmp);
    let cut = (3.0 * sorted[sorted.len() / 2]).max(0.1);
    let keep: Vec<usize> = good.iter().zip(&res).filter(|(_, &r)| r <= cut).map(|(&i, _)| i).collect();
    if keep.len() < o.min_tiles {
        return Err(too_few(keep.len(), tiles.len()));
    }
    tiles.iter_mut().for_each(|t| t.used = false);
    keep.iter().for_each(|&i| tiles[i].used = true);
    let sel: Vec<&TileMatch> = keep.iter().map(|&i| &tiles[i]).collect();
    let th = fit(&sel, w, h);
    let res = tile_residuals(&th, &sel, w, h);
    let rms = (res.iter().map(|r| r * r).sum::<f64>() / res.len() as f64).sqrt();
    Ok((th, tiles, rms))
}

/// Registers a sharp capture to the target and fits the similarity and ptlens distortion (see
/// the module docs). `capture` is one plane (e.g. the mean of the channels), linear.
///
/// # Errors
/// Non-finite input, a capture too small for the tiles, no match of the target in the centre
/// ([`LocateError::NotFound`]), fewer than `min_tiles` usable tiles.
pub fn locate(capture: &Plane, spec: &TargetSpec, nominal: &Nominal, o: &LocateOptions) -> Result<DistortionFit, LocateError> {
    let (w, h) = (capture.width, capture.height);
    if capture.data.iter().any(|v| !v.is_finite()) || ![nominal.pixels_per_cell, nominal.u0, nominal.v0].iter().all(|v| v.is_finite()) {
        return Err(LocateError::NonFinite);
    }
    let need = 2 * o.tile;
    if w < need || h < need {
        return Err(LocateError::TooSmall { width: w, height: h, need });
    }
    let (lock, coarse_scale, q) = coarse_lock(capture, spec, nominal, o);
    if q < o.min_ncc {
        return Err(LocateError::NotFound { best_ncc: q, need: o.min_ncc, range_pct: o.scale_range * 100.0 });
    }
    let mut pass = fit_pass(capture, spec, &lock, &[0.0; 7], o)?;
    for _ in 1..MAX_PASSES {
        let th = pass.0;
        pass = fit_pass(capture, spec, &lock, &th, o)?;
        let moved = (0..=8).map(|i| i as f64 / 8.0).map(|f| {
            let p = (f * (w as f64 - 1.0), f * (h as f64 - 1.0));
            let (a, b) = (unpredict(&th, p, w, h), unpredict(&pass.0, p, w, h));
            (a.0 - b.0).hypot(a.1 - b.1)
        });
        if moved.fold(0.0, f64::max) < CONVERGED_PX {
            break;
        }
    }
    let (th, tiles, rms) = pass;
    let tiles_used = tiles.iter().filter(|t| t.used).count();
    let (al, be) = (1.0 + th[0], th[1]);
    Ok(DistortionFit {
        ptlens: PtLens { a: th[4], b: th[5], c: th[6] },
        pixels_per_cell: lock.pixels_per_cell * al.hypot(be),
        rotation_deg: be.atan2(al).to_degrees(),
        translation_px: [th[2], th[3]],
        coarse_scale,
        rms_residual_px: rms,
        tiles_used,
        tiles,
        width: w,
        height: h,
    })
}

/// Largest and RMS difference, pixels, between the displacement fields of two ptlens models
/// over a 17 × 13 grid spanning a `width × height` frame (corners included).
pub fn field_difference(a: &PtLens, b: &PtLens, width: usize, height: usize) -> (f64, f64) {
    let (mut worst, mut ss, mut n) = (0.0f64, 0.0, 0.0);
    for j in 0..=12 {
        for i in 0..=16 {
            let (x, y) = (i as f64 * (width as f64 - 1.0) / 16.0, j as f64 * (height as f64 - 1.0) / 12.0);
            let (ax, ay) = a.displacement_px(x, y, width, height);
            let (bx, by) = b.displacement_px(x, y, width, height);
            let e = (ax - bx).hypot(ay - by);
            worst = worst.max(e);
            ss += e * e;
            n += 1.0;
        }
    }
    (worst, (ss / n).sqrt())
}

/// File name of a distortion measurement in a profile directory.
pub const DISTORTION_FILE: &str = "distortion.toml";

/// A distortion measurement as stored with a profile (`PROFILE/distortion.toml`, see
/// `docs/profile-format.md`): lensfun ptlens coefficients for a `width × height` sensor and
/// how they were measured.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeasuredDistortion {
    /// Always `"ptlens"` (lensfun's model).
    pub model: String,
    pub a: f64,
    pub b: f64,
    pub c: f64,
    pub width: usize,
    pub height: usize,
    /// UTC time of the measurement.
    pub measured: String,
    /// The sharp capture that was registered.
    pub capture: String,
    /// The target description it was registered to.
    pub target: String,
    pub tiles_used: usize,
    pub tiles_total: usize,
    pub rms_residual_px: f64,
    pub pixels_per_cell: f64,
    pub rotation_deg: f64,
}

/// Why a distortion record could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum DistortionFileError {
    #[error("{path}: {source}")]
    Io { path: std::path::PathBuf, #[source] source: std::io::Error },
    #[error("{path}: {problem}")]
    Invalid { path: std::path::PathBuf, problem: String },
}

impl MeasuredDistortion {
    /// The record of a fit of `capture` against `target`.
    pub fn of(f: &DistortionFit, capture: &std::path::Path, target: &std::path::Path) -> Self {
        Self {
            model: "ptlens".into(),
            a: f.ptlens.a,
            b: f.ptlens.b,
            c: f.ptlens.c,
            width: f.width,
            height: f.height,
            measured: crate::timestamp_utc(),
            capture: capture.display().to_string(),
            target: target.display().to_string(),
            tiles_used: f.tiles_used,
            tiles_total: f.tiles.len(),
            rms_residual_px: f.rms_residual_px,
            pixels_per_cell: f.pixels_per_cell,
            rotation_deg: f.rotation_deg,
        }
    }

    pub fn ptlens(&self) -> PtLens {
        PtLens { a: self.a, b: self.b, c: self.c }
    }

    /// Writes `dir/distortion.toml` atomically (replacing an older measurement).
    ///
    /// # Errors
    /// Non-finite numbers (never written), I/O.
    pub fn save(&self, dir: &std::path::Path) -> Result<(), DistortionFileError> {
        let path = dir.join(DISTORTION_FILE);
        let invalid = |problem: String| DistortionFileError::Invalid { path: path.clone(), problem };
        if let Some(k) = crate::fsutil::first_non_finite(self) {
            return Err(invalid(format!("non-finite value in {k}")));
        }
        let text = format!("# lensrig distortion measurement (lensfun ptlens, r_d = r_u·(a·r_u³ + b·r_u² + c·r_u + 1 − a − b − c)); see docs/profile-format.md\n{}", toml::to_string_pretty(self).map_err(|e| invalid(e.to_string()))?);
        crate::fsutil::write_atomic(&path, text.as_bytes(), crate::fsutil::Overwrite::Replace).map_err(|source| DistortionFileError::Io { path, source })
    }

    /// Reads `dir/distortion.toml`; `Ok(None)` when the profile holds no measurement.
    ///
    /// # Errors
    /// Unreadable or invalid file, another model than ptlens, non-finite or folding
    /// coefficients.
    pub fn load(dir: &std::path::Path) -> Result<Option<Self>, DistortionFileError> {
        let path = dir.join(DISTORTION_FILE);
        if !path.is_file() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|source| DistortionFileError::Io { path: path.clone(), source })?;
        let invalid = |problem: String| DistortionFileError::Invalid { path: path.clone(), problem };
        let m: Self = toml::from_str(&text).map_err(|e| invalid(crate::toml_error(&text, &e)))?;
        if m.model != "ptlens" {
            return Err(invalid(format!("model {:?}: only \"ptlens\" is known", m.model)));
        }
        m.ptlens().check(m.width, m.height).map_err(|e| invalid(e.to_string()))?;
        Ok(Some(m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::target::render_noise_scene_mapped;

    fn spec() -> TargetSpec {
        TargetSpec::new("A4", 300, 4, 7).unwrap()
    }

    fn capture(d: &PtLens, ppc: f64, w: usize, h: usize) -> Plane {
        render_noise_scene_mapped(&spec(), w, h, ppc, 30.0, 20.0, |x, y| d.undistort_px(x, y, w, h))
    }

    /// A known barrel distortion is recovered through a 4 % wrong nominal scale; the field
    /// error stays within 0.1 px over the frame.
    #[test]
    fn recovers_a_known_distortion_through_a_wrong_nominal_scale() {
        let (w, h) = (384, 288);
        let truth = PtLens { a: 0.01, b: -0.03, c: 0.0 };
        let cap = capture(&truth, 1.6, w, h);
        let nominal = Nominal { pixels_per_cell: 1.6 * 1.04, u0: 30.0, v0: 20.0 };
        let f = locate(&cap, &spec(), &nominal, &LocateOptions::default()).unwrap();
        let (max, rms) = field_difference(&f.ptlens, &truth, w, h);
        eprintln!("ptlens {:?} vs truth {truth:?}: field error max {max:.3} px, rms {rms:.3} px; {} tiles, residual {:.3} px", f.ptlens, f.tiles_used, f.rms_residual_px);
        assert!(max < 0.1, "field error {max} px (rms {rms}); fit {f:?}");
        assert!((f.pixels_per_cell / 1.6 - 1.0).abs() < 2e-3 && f.rotation_deg.abs() < 0.05, "{f:?}");
        assert!(f.tiles_used >= 60 && f.rms_residual_px < 0.1, "{} tiles, rms {}", f.tiles_used, f.rms_residual_px);
    }

    #[test]
    fn typed_errors() {
        let (w, h) = (256, 192);
        let cap = capture(&PtLens::NONE, 1.6, w, h);
        let o = LocateOptions::default();
        let good = Nominal { pixels_per_cell: 1.6, u0: 30.0, v0: 20.0 };
        let mut nan = cap.clone();
        nan.data[5] = f32::NAN;
        assert!(matches!(locate(&nan, &spec(), &good, &o), Err(LocateError::NonFinite)));
        // another target (seed) is not found
        let other = TargetSpec { seed: 8, ..spec() };
        assert!(matches!(locate(&cap, &other, &good, &o), Err(LocateError::NotFound { .. })));
        // a capture that shows the target only in its centre has too few tiles
        let mut part = cap.clone();
        for y in 0..h {
            for x in 0..w {
                if (x as f64 - 127.5).abs() > 70.0 || (y as f64 - 95.5).abs() > 70.0 {
                    part.data[y * w + x] = 0.5;
                }
            }
        }
        let strict = LocateOptions { min_tiles: 40, ..o };
        assert!(matches!(locate(&part, &spec(), &good, &strict), Err(LocateError::TooFewTiles { .. })), "{:?}", locate(&part, &spec(), &good, &strict).map(|f| f.tiles_used));
        assert!(matches!(locate(&Plane::filled(100, 100, 0.5), &spec(), &good, &o), Err(LocateError::TooSmall { .. })));
    }

    #[test]
    fn the_record_round_trips_and_rejects_bad_files() {
        let (w, h) = (256, 192);
        let cap = capture(&PtLens { a: 0.0, b: -0.02, c: 0.0 }, 1.6, w, h);
        let f = locate(&cap, &spec(), &Nominal { pixels_per_cell: 1.6, u0: 30.0, v0: 20.0 }, &LocateOptions::default()).unwrap();
        let d = tempfile::tempdir().unwrap();
        assert!(MeasuredDistortion::load(d.path()).unwrap().is_none());
        let m = MeasuredDistortion::of(&f, std::path::Path::new("pinhole.png"), std::path::Path::new("t.toml"));
        m.save(d.path()).unwrap();
        assert_eq!(MeasuredDistortion::load(d.path()).unwrap(), Some(m.clone()));
        let text = std::fs::read_to_string(d.path().join(DISTORTION_FILE)).unwrap();
        std::fs::write(d.path().join(DISTORTION_FILE), text.replace("model = \"ptlens\"", "model = \"poly3\"")).unwrap();
        assert!(MeasuredDistortion::load(d.path()).unwrap_err().to_string().contains("poly3"));
        std::fs::write(d.path().join(DISTORTION_FILE), format!("{text}extra = 1\n")).unwrap();
        assert!(MeasuredDistortion::load(d.path()).is_err());
        assert!(MeasuredDistortion { a: f64::NAN, ..m }.save(d.path()).is_err());
    }
}
