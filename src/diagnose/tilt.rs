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
    centroid_keystone_fit(current).map(|f| f.k)
}

/// [`centroid_keystone`] with its covariance ([`KeystoneFit`]).
pub fn centroid_keystone_fit(current: &Fit) -> Option<KeystoneFit> {
    keystone_fit_of_grid(&current.model.grid, current.normalized[0].width, current.normalized[0].height)
}

/// [`centroid_keystone`] of a kernel grid over a `w × h` image.
pub fn keystone_of_grid(g: &crate::optics::psf_grid::PsfGrid, w: usize, h: usize) -> Option<[f64; 2]> {
    keystone_fit_of_grid(g, w, h).map(|f| f.k)
}

/// The keystone the kernels' centroids follow with its uncertainty ([`keystone_fit_of_grid`]).
#[derive(Clone, Copy, Debug)]
pub struct KeystoneFit {
    /// `[g, h]`, per pixel.
    pub k: [f64; 2],
    /// The covariance of `[g, h]`: `σ̂² (AᵀA)⁻¹` of the least squares, `σ̂²` the centroids'
    /// mean square about the fit over `2n − 6` degrees of freedom (a lens's own centroid
    /// pattern that the model does not follow counts as scatter, so the error is conservative).
    pub cov: [[f64; 2]; 2],
}

impl KeystoneFit {
    /// The largest corner displacement ([`corner_displacement`]) over its standard error at
    /// that corner (0 for no keystone, ∞ when the error is 0).
    pub fn corner_t(&self, w: usize, h: usize) -> f64 {
        let (hx, hy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let worst = [(hx, hy), (hx, -hy), (-hx, hy), (-hx, -hy)].into_iter().max_by(|a, b| (self.k[0] * a.0 + self.k[1] * a.1).abs().total_cmp(&(self.k[0] * b.0 + self.k[1] * b.1).abs())).unwrap_or((hx, hy));
        let (x, y) = worst;
        let d = (self.k[0] * x + self.k[1] * y).abs();
        let var = x * x * self.cov[0][0] + 2.0 * x * y * self.cov[0][1] + y * y * self.cov[1][1];
        if d == 0.0 {
            0.0
        } else if var > 0.0 {
            d / var.sqrt()
        } else {
            f64::INFINITY
        }
    }
}

/// Whether the centroids of grid `g`'s kernels follow a keystone ([`keystone_fit_of_grid`])
/// that moves a corner of the `w × h` image by at least [`MIN_CORNER_PX`] at
/// [`super::registered::MIN_CORNER_T`] standard errors or more. Where they do, the kernel grid
/// does not grow ([`super::candidates`]' `field_growth`). A lens's own centroid pattern,
/// radial about the centre (distortion, lateral colour: odd in `d`), is orthogonal to the
/// keystone's even one on a grid symmetric about the centre and does not show.
pub fn keystone_shows(g: &crate::optics::psf_grid::PsfGrid, w: usize, h: usize) -> bool {
    keystone_fit_of_grid(g, w, h).is_some_and(|kf| corner_displacement(kf.k, w, h) >= MIN_CORNER_PX && kf.corner_t(w, h) >= super::registered::MIN_CORNER_T)
}

/// [`keystone_of_grid`] with the covariance of the keystone ([`KeystoneFit`]).
pub fn keystone_fit_of_grid(g: &crate::optics::psf_grid::PsfGrid, w: usize, h: usize) -> Option<KeystoneFit> {
    if g.tile_count() < 6 {
        return None;
    }
    let (w, h) = (w as f64, h as f64);
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    // unknowns p, q, tx, ty, g, h; lengths in units of the half diagonal keep the system scaled
    let unit = 0.5 * (w * w + h * h).sqrt();
    let rows: Vec<([f64; 6], f64)> = (0..g.tile_count())
        .flat_map(|t| {
            let (dx, dy) = g.mean_centroid(t);
            let (x, y) = ((g.centers[t][0] - cx) / unit, (g.centers[t][1] - cy) / unit);
            [([x, -y, 1.0, 0.0, x * x, x * y], dx), ([y, x, 0.0, 1.0, x * y, y * y], dy)]
        })
        .collect();
    let ls = crate::solve::dense::least_squares(&rows, 1e-300)?;
    let (c4, c5) = (ls.inverse_column(4)?, ls.inverse_column(5)?);
    let u4 = ls.s2 / unit.powi(4);
    Some(KeystoneFit { k: [ls.p[4] / (unit * unit), ls.p[5] / (unit * unit)], cov: [[u4 * c4[4], u4 * c4[5]], [u4 * c5[4], u4 * c5[5]]] })
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
    let Some(kf) = centroid_keystone_fit(current) else { return (None, "target_tilt") };
    let k0 = kf.k;
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
        corner_t: kf.corner_t(w, h),
        min_corner_px: super::registered::MIN_CORNER_PX,
        defer: None,
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
        assert!(keystone_shows(&grid, w, h), "the field growth's gate");
        // a lens's radial pattern (distortion 2 px at the corners, a scale) on the same grid:
        // no keystone, so the gate lets the grid grow
        let r2 = cx * cx + cy * cy;
        let radial = PsfGrid { kernels: vec![grid.centers.iter().map(|c| {
            let (dx, dy) = (c[0] - cx, c[1] - cy);
            let s = 2.0 / r2.sqrt() * (dx * dx + dy * dy) / r2 + 0.003;
            let m = (k as f64 - 1.0) / 2.0;
            crate::image::Plane::from_fn(k, k, |x, y| (-((x as f64 - m - dx * s).powi(2) + (y as f64 - m - dy * s).powi(2)) / (2.0 * 1.5 * 1.5)).exp() as f32)
        }).collect()], ..grid.clone() };
        let kr = keystone_of_grid(&radial, w, h).expect("determined");
        assert!(corner_displacement(kr, w, h) < 0.05 && !keystone_shows(&radial, w, h), "{kr:?}");
    }

    /// The keystone's standard error ([`KeystoneFit::corner_t`]): a keystone buried in centroid
    /// scatter of its own size stands at a few standard errors at most, the same keystone on
    /// centroids with a tenth of that scatter at ten times as many; the covariance matches the
    /// spread of the fitted keystone over many scatter draws.
    #[test]
    fn keystone_standard_error_follows_the_centroids_scatter() {
        let (w, h, k) = (1024usize, 768usize, 15usize);
        let (g0, h0) = (1.5e-6, 0.5e-6);
        let centers = PsfGrid::regular_centers(w, h, 7, 5);
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let grid_with = |scatter: f64, seed: u64| {
            let mut r = crate::rng::Rng::new(seed);
            let kernels = vec![centers
                .iter()
                .map(|c| {
                    let (dx, dy) = (c[0] - cx, c[1] - cy);
                    let s = g0 * dx + h0 * dy;
                    let (sx, sy) = (dx * s + scatter * r.normal(), dy * s + scatter * r.normal());
                    let m = (k as f64 - 1.0) / 2.0;
                    crate::image::Plane::from_fn(k, k, |x, y| (-((x as f64 - m - sx).powi(2) + (y as f64 - m - sy).powi(2)) / (2.0 * 1.5 * 1.5)).exp() as f32)
                })
                .collect()];
            PsfGrid { kernel_size: k, columns: 7, rows: 5, centers: centers.clone(), channels: vec!["Y".into()], kernels }
        };
        let corner = corner_displacement([g0, h0], w, h);
        let noisy = keystone_fit_of_grid(&grid_with(corner, 3), w, h).expect("determined");
        let quiet = keystone_fit_of_grid(&grid_with(0.1 * corner, 3), w, h).expect("determined");
        let (tn, tq) = (noisy.corner_t(w, h), quiet.corner_t(w, h));
        assert!(tn < 3.0 && tq > 10.0 && tq > 5.0 * tn, "t {tn:.2} with scatter at the keystone's size, {tq:.2} at a tenth");
        // the field growth's gate: the quiet keystone shows, the buried one does not
        assert!(keystone_shows(&grid_with(0.1 * corner, 3), w, h) && !keystone_shows(&grid_with(corner, 3), w, h));
        // the predicted standard error of g against the spread over draws
        let gs: Vec<f64> = (0..200).map(|seed| keystone_fit_of_grid(&grid_with(0.1 * corner, 100 + seed), w, h).expect("determined").k[0]).collect();
        let mean = gs.iter().sum::<f64>() / gs.len() as f64;
        let sd = (gs.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / (gs.len() - 1) as f64).sqrt();
        let predicted = quiet.cov[0][0].sqrt();
        assert!((predicted / sd - 1.0).abs() < 0.35, "predicted se(g) {predicted:.3e}, measured {sd:.3e}");
    }
}
