//! Scoring an estimated PSF grid against a truth grid (the estimation test bed, issue 16;
//! docs/estimation.md "Test bed").
//!
//! # Truth at an estimated centre
//! The truth at an estimated centre `(x, y)` is the truth grid's Catmull–Rom blend at that point
//! ([`PsfGrid::kernel_at`]), the blend `simulate` applies point by point
//! ([`crate::optics::forward`]), so it is the kernel the rendered wide-open data hold there.
//!
//! # Alignment rule
//! None. The profile format fixes a kernel's geometry absolutely: `K[v][u]` is the light landing
//! at offset `(u − c, v − c)` px with `c = (k − 1)/2`, so a kernel displaced by a sub-pixel shift
//! predicts a displaced image and is wrong, not equivalent. Kernels of different sizes are
//! compared on the larger square, each embedded about its centre pixel (zero outside its own
//! support); nothing is shifted, rescaled or renormalised.
//!
//! # Units
//! Errors are relative L2, `‖b − b_true‖₂ / ‖b_true‖₂` (a fraction, 0.05 = 5 %); centres in
//! pixels (pixel centres at integers).

use crate::image::Plane;
use crate::optics::capture::{render, Blur, Rendered, Sensor, Shot};
use crate::optics::lens::LensModel;
use crate::optics::psf_grid::PsfGrid;
use crate::rng::Rng;
use crate::target::{render_noise_scene, TargetError, TargetSpec};

/// A `w × h` calibration pair through `truth` as the test bed renders it: the A4 noise target
/// of pattern `seed` (wide open: blurred by the truth grid the way `simulate` blends it;
/// pinhole: the sharp target), both at `exposure` through `sensor`, with noise streams
/// `2·seed + 1` and `2·seed + 2`.
///
/// # Errors
/// The target specification ([`TargetSpec::new`]).
pub fn noise_target_pair(truth: &PsfGrid, w: usize, h: usize, seed: u64, sensor: &Sensor, exposure: f64) -> Result<(Rendered, Rendered), TargetError> {
    let spec = TargetSpec::new("A4", 300, 4, seed)?;
    let scene = render_noise_scene(&spec, w, h, 1.6, 7.0, 5.0);
    let mut lens = LensModel::demo(w, h);
    lens.bands.retain(|b| truth.channels.contains(&b.name));
    let scene: Vec<Plane> = vec![scene; lens.bands.len()];
    let open = render(&scene, &lens, &Shot { blur: Blur::Grid(truth.clone()), ..Shot::ideal(exposure) }, sensor, &mut Rng::new(seed * 2 + 1));
    let pin = render(&scene, &lens, &Shot::ideal(exposure), sensor, &mut Rng::new(seed * 2 + 2));
    Ok((open, pin))
}

/// `k` embedded about its centre in a `size × size` square (`size ≥ k`, both odd), zero
/// outside; a larger `k` is cropped about its centre.
pub fn embed_centered(k: &Plane, size: usize) -> Plane {
    let off = size as isize / 2 - k.width as isize / 2;
    let mut out = Plane::new(size, size);
    out.paste(k, off, off);
    out
}

/// Relative L2 error `‖a − b‖ / ‖b‖` of two centred kernels of any odd sizes, compared on the
/// larger square (module docs: no alignment).
pub fn relative_error_centered(a: &Plane, b: &Plane) -> f64 {
    let n = a.width.max(b.width);
    super::relative_error(&embed_centered(a, n), &embed_centered(b, n))
}

/// Per channel of `est` (matched to `truth` by name; a channel the truth lacks scores
/// nothing), the relative L2 error of every tile's kernel against the truth blended at that
/// tile's centre, tiles in grid order.
pub fn errors_against_truth(est: &PsfGrid, truth: &PsfGrid) -> Vec<Vec<f64>> {
    est.channels
        .iter()
        .enumerate()
        .map(|(c, name)| match truth.channels.iter().position(|n| n == name) {
            Some(tc) => (0..est.tile_count())
                .map(|t| {
                    let [x, y] = est.centers[t];
                    relative_error_centered(&est.kernels[c][t], &truth.kernel_at(tc, x, y))
                })
                .collect(),
            None => vec![],
        })
        .collect()
}

/// Points per axis of [`field_errors_against_truth`]'s lattice.
pub const FIELD_POINTS: (usize, usize) = (13, 10);

/// Per channel (as [`errors_against_truth`]), the relative L2 error of `est`'s blended kernel
/// against `truth`'s blended kernel at the points of a fixed [`FIELD_POINTS`] lattice whose
/// outer points lie a kernel radius `r` (the larger grid's) inside a `w × h` frame's edges:
/// `x_i = r + i·(w − 1 − 2r)/12`, likewise in `y`. Unlike the errors at the estimated centres it
/// does not depend on where the estimate put its centres, so two layouts compare on the same
/// points, and it reaches into the band between the outer centres and the frame's edges that the
/// data (valid from a kernel radius inside the edges) still see.
pub fn field_errors_against_truth(est: &PsfGrid, truth: &PsfGrid, w: usize, h: usize) -> Vec<Vec<f64>> {
    let r = est.kernel_size.max(truth.kernel_size) / 2;
    let (fw, fh) = (w.saturating_sub(2 * r).max(1), h.saturating_sub(2 * r).max(1));
    let points: Vec<[f64; 2]> = PsfGrid::edge_centers(fw, fh, FIELD_POINTS.0, FIELD_POINTS.1).into_iter().map(|[x, y]| [x + r as f64, y + r as f64]).collect();
    est.channels
        .iter()
        .enumerate()
        .map(|(c, name)| match truth.channels.iter().position(|n| n == name) {
            Some(tc) => points.iter().map(|&[x, y]| relative_error_centered(&est.kernel_at(c, x, y), &truth.kernel_at(tc, x, y))).collect(),
            None => vec![],
        })
        .collect()
}

/// The short name of the simulator's singlet in the test bed (`lensrig bench --testbed
/// --only`): `sim1`, `sim2` for the chromatic strengths ×1, ×2 at 1024×768, `sim1-4000x3000`
/// at another size (`strength` rounded to a whole number).
pub fn simulator_short_name(strength: f64, size: Option<(usize, usize)>) -> String {
    let base = format!("sim{}", strength.round());
    size.map_or(base.clone(), |(w, h)| format!("{base}-{w}x{h}"))
}

/// Whether a test-bed lens is selected by `lensrig bench --testbed --only TEXT`: every lens
/// without `only`, else a lens whose full name (`simulator singlet, chromatic ×2`) or short
/// name (`sim2`, [`simulator_short_name`]; a truth lens's short name is its file name)
/// contains the text.
pub fn lens_selected(name: &str, short: &str, only: Option<&str>) -> bool {
    only.map_or(true, |o| name.contains(o) || short.contains(o))
}

/// The cross-validation of a profile on an independent test-bed pair, as sums over the
/// channels of interior means (pixels at least `margin` from every edge; full scale²):
///
/// - `residual`: `Σ_c mean (pred_c − j_c)²`, the profile's prediction from the recorded pinhole
///   against the recorded wide-open capture;
/// - `open_noise`: `Σ_c mean Var[j_c]`, the wide-open capture's true noise variance;
/// - `pinhole_noise`: `Σ_c mean (P_c(ĩ) − P_c(i))²`, the pinhole's own noise carried into the
///   prediction by the **true** kernels `P` (`ĩ` the recorded pinhole, `i` its noise-free
///   signal): the part of the residual that no kernel estimate can remove.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CrossValidation {
    pub residual: f64,
    pub open_noise: f64,
    pub pinhole_noise: f64,
}

impl CrossValidation {
    /// Gathers the sums from the profile's prediction `pred`, the truth's predictions from the
    /// recorded pinhole (`truth_noisy`) and from its noise-free signal (`truth_clean`), the
    /// recorded wide-open capture `open` and its noise variance `variance`, all per channel.
    pub fn from_planes(pred: &[Plane], truth_noisy: &[Plane], truth_clean: &[Plane], open: &[Plane], variance: &[Plane], margin: usize) -> Self {
        Self { residual: pooled_mean_square(pred, open, margin), open_noise: pooled_mean(variance, margin), pinhole_noise: pooled_mean_square(truth_noisy, truth_clean, margin) }
    }

    /// Residual RMS ÷ the wide-open capture's noise RMS, `√(residual / open_noise)`: 1 for a
    /// perfect model only when the pinhole is noise-free.
    pub fn ratio_open(&self) -> f64 {
        (self.residual / self.open_noise.max(1e-300)).sqrt()
    }

    /// Residual RMS ÷ the noise the true kernels leave, `√(residual / (open_noise +
    /// pinhole_noise))`: ≈ 1 for the true kernels whatever the lens; the excess is the model's.
    pub fn ratio(&self) -> f64 {
        (self.residual / (self.open_noise + self.pinhole_noise).max(1e-300)).sqrt()
    }
}

/// The interior box of a `w × h` plane: pixels at least `margin` from every edge.
fn interior(p: &Plane, margin: usize) -> impl Iterator<Item = usize> + '_ {
    let (w, h) = (p.width, p.height);
    (margin..h.saturating_sub(margin)).flat_map(move |y| (margin..w.saturating_sub(margin)).map(move |x| y * w + x))
}

/// `Σ_c mean_interior (a_c − b_c)²` (planes paired by index, equal sizes).
pub fn pooled_mean_square(a: &[Plane], b: &[Plane], margin: usize) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| {
            let (s, n) = interior(p, margin).fold((0.0f64, 0usize), |(s, n), i| (s + ((p.data[i] - q.data[i]) as f64).powi(2), n + 1));
            s / n.max(1) as f64
        })
        .sum()
}

/// `Σ_c mean_interior v_c`.
pub fn pooled_mean(v: &[Plane], margin: usize) -> f64 {
    v.iter()
        .map(|p| {
            let (s, n) = interior(p, margin).fold((0.0f64, 0usize), |(s, n), i| (s + p.data[i] as f64, n + 1));
            s / n.max(1) as f64
        })
        .sum()
}

/// The `p`-quantile (`0 ≤ p ≤ 1`, nearest rank on the sorted values) of `v`; `None` when empty.
pub fn quantile(v: &[f64], p: f64) -> Option<f64> {
    let mut s: Vec<f64> = v.to_vec();
    s.sort_by(f64::total_cmp);
    let last = s.len().checked_sub(1)?;
    let i = ((p.clamp(0.0, 1.0) * last as f64).round() as usize).min(last);
    Some(s[i])
}

#[cfg(test)]
mod tests {
    #[test]
    fn only_accepts_full_and_short_names() {
        let sim2 = ("simulator singlet, chromatic ×2", simulator_short_name(2.0, None));
        let big = ("simulator singlet, chromatic ×1, 4000x3000", simulator_short_name(1.0, Some((4000, 3000))));
        assert_eq!((sim2.1.as_str(), big.1.as_str()), ("sim2", "sim1-4000x3000"));
        for (only, want) in [(None, true), (Some("sim2"), true), (Some("×2"), true), (Some("sim"), true), (Some("sim1"), false), (Some("achromat"), false)] {
            assert_eq!(lens_selected(sim2.0, &sim2.1, only), want, "{only:?}");
        }
        assert!(lens_selected(big.0, &big.1, Some("sim1")) && lens_selected(big.0, &big.1, Some("4000x3000")));
        assert!(lens_selected("achromat-f4", "achromat-f4", Some("achromat")) && !lens_selected("achromat-f4", "achromat-f4", Some("sim2")));
    }

    use super::*;

    fn gauss(k: usize, cx: f32, cy: f32, s: f32) -> Plane {
        let c = (k / 2) as f32;
        let mut p = Plane::from_fn(k, k, |x, y| {
            let (dx, dy) = (x as f32 - c - cx, y as f32 - c - cy);
            (-(dx * dx + dy * dy) / (2.0 * s * s)).exp()
        });
        let sum = p.sum() as f32;
        p.scale(1.0 / sum);
        p
    }

    /// A grid whose kernels vary linearly with x: `b(x) = (1 − x/W)·A + (x/W)·B`.
    fn linear_grid(w: usize, h: usize, columns: usize, rows: usize, k: usize) -> PsfGrid {
        let centers = PsfGrid::regular_centers(w, h, columns, rows);
        let (a, b) = (gauss(k, 0.0, 0.0, 1.0), gauss(k, 1.0, -0.5, 2.5));
        let kernels = vec![centers.iter().map(|&[x, _]| mix(&a, &b, x / w as f64)).collect()];
        PsfGrid { kernel_size: k, columns, rows, centers, channels: vec!["G".into()], kernels }
    }

    fn mix(a: &Plane, b: &Plane, t: f64) -> Plane {
        Plane::from_fn(a.width, a.height, |x, y| ((1.0 - t) as f32) * a.get(x, y) + t as f32 * b.get(x, y))
    }

    /// The truth scored against itself is exact; a grid on other centres gets the truth
    /// blended at its own centres: Catmull–Rom reproduces a linear field, so an estimate equal to
    /// the analytic kernel there scores ~0, while the nearest truth tile's kernel does not.
    #[test]
    fn truth_is_interpolated_at_the_estimated_centres() {
        let (w, h, k) = (700, 500, 9);
        let truth = linear_grid(w, h, 7, 5, k);
        assert!(errors_against_truth(&truth, &truth)[0].iter().all(|&e| e < 1e-6));
        // a 4 × 3 grid: its interior centres fall between the truth's
        let est = linear_grid(w, h, 4, 3, k);
        let e = &errors_against_truth(&est, &truth)[0];
        // only centres inside the truth's outer centres are reproduced exactly (beyond them
        // the blend is constant by definition)
        let xs = truth.column_xs();
        for (t, &[x, _]) in est.centers.iter().enumerate() {
            if x >= xs[0] && x <= xs[xs.len() - 1] {
                assert!(e[t] < 1e-5, "tile {t} at x={x}: {}", e[t]);
            }
        }
        // the nearest truth tile is a different kernel: scoring against it would be wrong
        let [x, y] = est.centers[1];
        let nearest = truth.centers.iter().enumerate().min_by(|a, b| {
            let d = |c: &[f64; 2]| (c[0] - x).powi(2) + (c[1] - y).powi(2);
            d(a.1).total_cmp(&d(b.1))
        });
        let nearest = nearest.map_or(0, |n| n.0);
        assert!(relative_error_centered(&est.kernels[0][1], &truth.kernels[0][nearest]) > 0.01);
    }

    /// The field errors score the blend on a fixed lattice: the truth against itself is exact
    /// on any layout, and of two estimates of a linear field, the one that holds its kernels
    /// constant beyond tile centres (the band between the outer centres and the frame's edges)
    /// scores worse there than one whose outer centres lie on the edges, while both are exact
    /// at their own centres.
    #[test]
    fn field_errors_count_the_band_beyond_the_outer_centres() {
        let (w, h, k) = (700, 500, 9);
        let (a, b) = (gauss(k, 0.0, 0.0, 1.0), gauss(k, 1.0, -0.5, 2.5));
        let on = |centers: Vec<[f64; 2]>, cols: usize, rows: usize| {
            let kernels = vec![centers.iter().map(|&[x, _]| mix(&a, &b, x / (w - 1) as f64)).collect()];
            PsfGrid { kernel_size: k, columns: cols, rows, centers, channels: vec!["G".into()], kernels }
        };
        let truth = on(PsfGrid::edge_centers(w, h, 9, 7), 9, 7);
        let edge = on(PsfGrid::edge_centers(w, h, 4, 3), 4, 3);
        let tiled = on(PsfGrid::regular_centers(w, h, 4, 3), 4, 3);
        assert!(field_errors_against_truth(&truth, &truth, w, h)[0].iter().all(|&e| e < 1e-6));
        for g in [&edge, &tiled] {
            assert!(errors_against_truth(g, &truth)[0].iter().all(|&e| e < 1e-5));
        }
        let worst = |g: &PsfGrid| field_errors_against_truth(g, &truth, w, h)[0].iter().copied().fold(0.0, f64::max);
        assert_eq!(field_errors_against_truth(&edge, &truth, w, h)[0].len(), FIELD_POINTS.0 * FIELD_POINTS.1);
        assert!(worst(&edge) < 1e-5, "edge-anchored: {}", worst(&edge));
        assert!(worst(&tiled) > 0.05, "tile-centred: {}", worst(&tiled));
    }

    /// Kernels of different sizes compare about their centres; a one-pixel shift is an error
    /// (no alignment), and a channel the truth lacks scores nothing.
    #[test]
    fn sizes_are_embedded_and_shifts_count() {
        let small = gauss(7, 0.0, 0.0, 1.0);
        let big = embed_centered(&small, 15);
        assert!((big.sum() - small.sum()).abs() < 1e-6);
        assert!(relative_error_centered(&small, &big) < 1e-7);
        assert!(relative_error_centered(&big, &small) < 1e-7);
        let shifted = gauss(7, 1.0, 0.0, 1.0);
        assert!(relative_error_centered(&shifted, &big) > 0.5);
        let mut g = linear_grid(300, 200, 3, 2, 7);
        let truth = g.clone();
        g.channels = vec!["R".into()];
        assert!(errors_against_truth(&g, &truth)[0].is_empty());
    }

    /// The true kernels score ≈ 1 against the noise they leave, also when they are sharp and
    /// carry the pinhole's noise into the prediction (the open-noise ratio then exceeds 1);
    /// a wrong kernel scores clearly above 1.
    #[test]
    fn true_kernels_score_one_against_open_and_pinhole_noise() {
        use crate::optics::capture::{render, Blur, Sensor, Shot};
        use crate::optics::lens::LensModel;
        use crate::rng::Rng;
        let (w, h, k) = (160, 120, 7);
        let centers = PsfGrid::regular_centers(w, h, 2, 2);
        let sharp = |s: f32| -> Vec<Plane> { (0..4).map(|t| gauss(k, 0.2 * t as f32 - 0.3, 0.0, s)).collect() };
        let truth = PsfGrid { kernel_size: k, columns: 2, rows: 2, centers: centers.clone(), channels: vec!["G".into()], kernels: vec![sharp(0.5)] };
        let mut lens = LensModel::demo(w, h);
        lens.bands.truncate(1);
        let mut rng = Rng::new(7);
        let scene = vec![Plane::from_fn(w, h, |_, _| 0.2 + 0.6 * rng.uniform() as f32)];
        let sensor = Sensor { full_well_e: 2000.0, read_noise_e: 3.0, bits: 16, transfer: crate::image::Transfer::Linear, noise: true };
        let open = render(&scene, &lens, &Shot { blur: Blur::Grid(truth.clone()), ..Shot::ideal(0.75) }, &sensor, &mut Rng::new(1));
        let pin = render(&scene, &lens, &Shot::ideal(0.75), &sensor, &mut Rng::new(2));
        let through = |g: &PsfGrid, p: &[Plane]| -> Vec<Plane> { vec![crate::optics::forward::blur_channel(&p[0], g, 0)] };
        let (noisy, clean) = (through(&truth, &pin.image.planes), through(&truth, &pin.clean));
        let cv = |g: &PsfGrid| CrossValidation::from_planes(&through(g, &pin.image.planes), &noisy, &clean, &open.image.planes, &open.variance, k / 2);
        let own = cv(&truth);
        assert!((own.ratio() - 1.0).abs() < 0.03, "true kernels: {own:?}");
        assert!(own.ratio_open() > 1.15, "a sharp kernel carries the pinhole's noise: {own:?}");
        let wrong = PsfGrid { kernels: vec![sharp(1.2)], ..truth.clone() };
        assert!(cv(&wrong).ratio() > 1.2, "{:?}", cv(&wrong));
    }

    #[test]
    fn quantiles() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(quantile(&v, 0.5), Some(3.0));
        assert_eq!(quantile(&v, 0.9), Some(5.0));
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&[], 0.5), None);
    }
}
