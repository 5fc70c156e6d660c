//! The `target_tilt` candidate: a keystone between the captures, found in the fitted kernels'
//! centroids ([`super::model`] step 2 has the equation).
//!
//! # Convention
//! Pixels are centred (`d = p − c`, `c` the image centre). A kernel whose centroid sits at `+δ`
//! means `open(p) ≈ pinhole(p − δ)` (the registration convention), so under a homography with
//! perspective row `(g, h)` the kernels at the tile centres follow
//! `δ(d) = d − ψ(d) ≈ d·(g·dx + h·dy)`: the x-displacement `g·dx² + h·dx·dy`, the y one
//! `g·dx·dy + h·dy²`. The centroids are fitted by least squares with a similarity and a
//! translation alongside (`δ = [[p, −q], [q, p]]·d + t + d·(g·dx + h·dy)`): the similarity
//! takes up what the lens's coma and any camera move put in the centroids (both linear in `d`),
//! the quadratic part is the tilt's.

use super::analysis::{where_text, Analysis};
use super::fit::{screen as fit, Data, Fit, FitSettings, Model};
use super::model::{Corrections, TiltCorrection};

/// Proposed only when the keystone moves some corner by at least this many pixels.
const MIN_CORNER_PX: f64 = 0.25;

/// `[g, h]` of the keystone the kernels' centroids follow (module docs), or `None` when the
/// grid cannot determine it (fewer than six tiles, or a singular system).
pub fn centroid_keystone(current: &Fit) -> Option<[f64; 2]> {
    keystone_of_grid(&current.model.grid, current.normalized[0].width, current.normalized[0].height)
}

/// [`centroid_keystone`] of a kernel grid over a `w × h` image.
pub fn keystone_of_grid(g: &crate::optics::psf_grid::PsfGrid, w: usize, h: usize) -> Option<[f64; 2]> {
    if g.tile_count() < 6 {
        return None;
    }
    let (w, h) = (w as f64, h as f64);
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    // unknowns p, q, tx, ty, g, h; lengths in units of the half diagonal keep the system scaled
    let unit = 0.5 * (w * w + h * h).sqrt();
    let mut ata = vec![vec![0.0f64; 6]; 6];
    let mut atb = vec![0.0f64; 6];
    for t in 0..g.tile_count() {
        let (dx, dy) = g.mean_centroid(t);
        let (x, y) = ((g.centers[t][0] - cx) / unit, (g.centers[t][1] - cy) / unit);
        for (row, d) in [([x, -y, 1.0, 0.0, x * x, x * y], dx), ([y, x, 0.0, 1.0, x * y, y * y], dy)] {
            for i in 0..6 {
                atb[i] += row[i] * d;
                for j in 0..6 {
                    ata[i][j] += row[i] * row[j];
                }
            }
        }
    }
    let p = crate::solve::dense::solve(ata, atb, 1e-300)?;
    Some([p[4] / (unit * unit), p[5] / (unit * unit)])
}

/// The largest keystone displacement (pixels) at the image corners for `[g, h]`.
pub fn corner_displacement(k: [f64; 2], w: usize, h: usize) -> f64 {
    let (hx, hy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    [(hx, hy), (hx, -hy), (-hx, hy), (-hx, -hy)].iter().map(|&(x, y)| (x * x + y * y).sqrt() * (k[0] * x + k[1] * y).abs()).fold(0.0, f64::max)
}

/// The current model with every kernel moved by minus the keystone's displacement at its tile
/// centre (the kernels then carry no keystone), and `target_tilt` set to `k` (added to any
/// tilt the current model already has).
pub fn tilt_model(current: &Fit, k: [f64; 2]) -> Model {
    let (w, h) = (current.normalized[0].width as f64, current.normalized[0].height as f64);
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let mut m = super::candidates::moved_kernels(current, &|x, y| {
        let (dx, dy) = (x - cx, y - cy);
        let s = k[0] * dx + k[1] * dy;
        (dx * s, dy * s)
    });
    let t0 = current.model.corrections.target_tilt.unwrap_or(TiltCorrection { g: 0.0, h: 0.0 });
    m.corrections = Corrections { target_tilt: Some(TiltCorrection { g: t0.g + k[0], h: t0.h + k[1] }), ..current.model.corrections.clone() };
    m
}

/// The keystone refined by a fixed point: fit under the current estimate, re-measure the
/// keystone the kernels still follow, add it (at most three times, until it moves the corners
/// by less than a twentieth of a pixel). Returns the model with the refined tilt.
fn refine(data: &Data, current: &Fit, k0: [f64; 2]) -> Model {
    let mut m = tilt_model(current, k0);
    let (w, h) = (data.open.width(), data.open.height());
    for _ in 0..3 {
        let f = fit(data, &m.corrections, &m, FitSettings { rounds: 1, kernel_iterations: 40 });
        let Some(r) = centroid_keystone(&f) else { break };
        m = tilt_model(&f, r);
        if corner_displacement(r, w, h) < 0.05 {
            break;
        }
    }
    m
}

/// The `target_tilt` candidate, when the current model has none, the kernels' centroids
/// follow a keystone of at least [`MIN_CORNER_PX`] at the corners, and that keystone, before
/// its fixed point, already lowers χ² ([`super::candidates::StartGate`]: the current kernels
/// moved by minus the keystone). Where the gate refuses and the keystone moves a corner by at
/// least [`super::registered::MIN_CORNER_PX`], the start is re-estimated under the keystone and
/// pre-fitted, and proposed where it beats the same start without the keystone
/// ([`super::registered::geometric_candidate`]; the keystone is not refined then). The label
/// says which path stopped or proposed it.
pub fn tilt_candidate(data: &Data, current: &Fit, a: &Analysis, gate: &super::candidates::StartGate, registered: &super::registered::RegisteredStarts) -> (Option<super::candidates::Candidate>, &'static str) {
    if current.model.corrections.target_tilt.is_some() {
        return (None, "target_tilt");
    }
    let Some(k0) = centroid_keystone(current) else { return (None, "target_tilt") };
    let (w, h) = (data.open.width(), data.open.height());
    let corner0 = corner_displacement(k0, w, h);
    if corner0 < MIN_CORNER_PX {
        return (None, "target_tilt");
    }
    let start = tilt_model(current, k0);
    let c = super::registered::MapCandidate {
        name: "target_tilt",
        gated: "target_tilt (gated: no χ² gain at the centroids' keystone)",
        registered: "target_tilt (re-estimated start)",
        refused: "target_tilt (gated: re-estimated start, no gain over the same start without the keystone)",
        corrections: &start.corrections,
        moved: &start,
        corner_px: corner0,
    };
    super::registered::geometric_candidate(gate, registered, &c, || keystone_candidate(data, current, a, k0, corner0), |m, cmp| {
        let t = m.corrections.target_tilt.unwrap_or(TiltCorrection { g: 0.0, h: 0.0 });
        let axis = t.h.atan2(t.g).to_degrees();
        let evidence = format!(
            "the fitted kernels' centroids follow a keystone, a displacement growing with the square of the distance from the centre (perspective row g {:+.2e}, h {:+.2e} per px: {corner0:.2} px at the corners), which neither a similarity nor tile-wise kernels follow; kernels {}",
            t.g,
            t.h,
            cmp.text()
        );
        (evidence, format!("growing quadratically towards the edges across an axis at {axis:.0}° (tilt axis at {:.0}°); {}", axis + 90.0, where_text(a)))
    })
}

/// [`tilt_candidate`] after its gate: the keystone refined from `k0` ([`refine`]).
fn keystone_candidate(data: &Data, current: &Fit, a: &Analysis, k0: [f64; 2], corner0: f64) -> Option<super::candidates::Candidate> {
    let (w, h) = (data.open.width(), data.open.height());
    let init = refine(data, current, k0);
    let t = init.corrections.target_tilt?;
    let corner = corner_displacement([t.g, t.h], w, h);
    let axis = t.h.atan2(t.g).to_degrees();
    Some(super::candidates::Candidate {
        name: "target_tilt",
        corrections: init.corrections.clone(),
        evidence: format!(
            "the fitted kernels' centroids follow a keystone, a displacement growing with the square of the distance from the centre (perspective row g {:+.2e}, h {:+.2e} per px: {corner:.2} px at the corners, {corner0:.2} px before refinement), which neither a similarity nor tile-wise kernels follow",
            t.g, t.h
        ),
        location: format!("growing quadratically towards the edges across an axis at {axis:.0}° (tilt axis at {:.0}°); {}", axis + 90.0, where_text(a)),
        init: Some(init),
        deferred: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::psf_grid::PsfGrid;

    /// Kernels shifted by the keystone `d·(g·dx + h·dy)` at their tile centres (plus a
    /// similarity, as coma and a camera move add) give back `(g, h)`.
    #[test]
    fn keystone_from_shifted_kernels() {
        let (w, h, k) = (256usize, 192usize, 15usize);
        let (g0, h0) = (1.1e-4, -0.7e-4);
        let centers = PsfGrid::regular_centers(w, h, 4, 3);
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let kernels = vec![centers
            .iter()
            .map(|c| {
                let (dx, dy) = (c[0] - cx, c[1] - cy);
                let s = g0 * dx + h0 * dy;
                let (sx, sy) = (dx * s + 0.004 * dx - 0.002 * dy + 0.3, dy * s + 0.002 * dx + 0.004 * dy);
                let m = (k as f64 - 1.0) / 2.0;
                crate::image::Plane::from_fn(k, k, |x, y| (-((x as f64 - m - sx).powi(2) + (y as f64 - m - sy).powi(2)) / (2.0 * 1.5 * 1.5)).exp() as f32)
            })
            .collect()];
        let grid = PsfGrid { kernel_size: k, columns: 4, rows: 3, centers, channels: vec!["Y".into()], kernels };
        let got = keystone_of_grid(&grid, w, h).expect("determined");
        assert!((got[0] / g0 - 1.0).abs() < 0.03 && (got[1] / h0 - 1.0).abs() < 0.03, "{got:?} vs [{g0}, {h0}]");
        let corner = corner_displacement(got, w, h);
        assert!(corner > MIN_CORNER_PX, "{corner}");
        assert_eq!(corner_displacement([0.0, 0.0], w, h), 0.0);
    }
}
