//! A synthetic simple lens for tests and benchmarks until the physical lens simulator lands:
//! per-channel defocus discs with a Gaussian halo, larger away from the best-focused channel
//! (axial chromatic aberration), growing towards the field corners (field curvature) and shifted
//! radially per channel (lateral chromatic aberration).
//!
//! Also a deterministic Gaussian noise source, so tests are reproducible without a RNG crate.

use crate::image::Plane;
use crate::optics::psf_grid::PsfGrid;

/// Shape of the synthetic lens.
#[derive(Clone, Debug)]
pub struct SyntheticLens {
    /// Odd kernel side.
    pub kernel_size: usize,
    /// Disc radius (pixels) of the best channel on axis.
    pub base_radius: f32,
    /// Extra radius factor per channel step away from the best channel.
    pub chromatic: f32,
    /// Relative radius growth at the corners (`1 + field_growth · r²`, `r` = 1 at a corner).
    pub field_growth: f32,
    /// Lateral colour: radial shift in pixels at the corner per channel step.
    pub lateral_shift: f32,
    /// Index of the sharpest channel.
    pub best_channel: usize,
}

impl SyntheticLens {
    /// A lens whose kernels fit `kernel_size`, the middle channel sharpest.
    pub fn new(kernel_size: usize, channels: usize) -> Self {
        let r = (kernel_size as f32 - 1.0) / 2.0;
        Self {
            kernel_size,
            base_radius: 0.3 * r,
            chromatic: 0.45,
            field_growth: 0.5,
            lateral_shift: 0.12 * r,
            best_channel: channels / 2,
        }
    }

    /// The kernel of `channel` at field point `(x, y)` of a `width × height` image.
    pub fn kernel(&self, channel: usize, x: f64, y: f64, width: usize, height: usize) -> Plane {
        let k = self.kernel_size;
        let c = (k as f32 - 1.0) / 2.0;
        let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
        let rmax = (cx * cx + cy * cy).sqrt().max(1.0);
        let (fx, fy) = (((x - cx) / rmax) as f32, ((y - cy) / rmax) as f32);
        let r2 = fx * fx + fy * fy;
        let step = channel as f32 - self.best_channel as f32;
        let radius = (self.base_radius * (1.0 + self.chromatic * step.abs()) * (1.0 + self.field_growth * r2)).min(c - 1.0).max(0.5);
        let (sx, sy) = (self.lateral_shift * step * fx, self.lateral_shift * step * fy);
        let halo = 0.6 * radius + 0.5;
        let mut p = Plane::from_fn(k, k, |u, v| {
            let (dx, dy) = (u as f32 - c - sx, v as f32 - c - sy);
            let d = (dx * dx + dy * dy).sqrt();
            let disc = (radius + 0.5 - d).clamp(0.0, 1.0); // anti-aliased edge
            let g = (-(d * d) / (2.0 * halo * halo)).exp();
            0.75 * disc / (radius * radius) + 0.25 * g / (halo * halo)
        });
        let s = p.sum() as f32;
        p.scale(1.0 / s);
        p
    }

    /// A `columns × rows` grid of this lens's kernels for `channels` channels.
    pub fn grid(&self, width: usize, height: usize, channels: usize, columns: usize, rows: usize) -> PsfGrid {
        let centers = PsfGrid::regular_centers(width, height, columns, rows);
        let kernels = (0..channels).map(|ch| centers.iter().map(|c| self.kernel(ch, c[0], c[1], width, height)).collect()).collect();
        PsfGrid {
            kernel_size: self.kernel_size,
            columns,
            rows,
            centers,
            channels: crate::image::default_channel_names(channels),
            kernels,
        }
    }
}

/// A smooth, red-dominant fundus-like scene on the linear axis, `[R, G, B]` (procedural, CC0;
/// data/scenes-extra/README.md): an orange-red disc with a soft field stop, a brighter optic
/// disc, four darker vessels 2.5–5 px wide, a faint mottle; green ≈ 0.1–0.4, blue ≈ 0.04–0.2.
pub fn fundus(w: usize, h: usize) -> Vec<Plane> {
    let (cx, cy, rad) = (w as f32 / 2.0, h as f32 / 2.0, 0.47 * h as f32);
    let (dx0, dy0) = (cx + 0.22 * w as f32, cy - 0.05 * h as f32); // optic disc
    // vessels: smooth curves y = y_i + a_i sin(x / p_i + φ_i), 2.5–5 px wide
    let vessels = [(0.30f32, 28.0f32, 140.0f32, 0.3f32, 4.5f32), (0.45, 40.0, 210.0, 1.7, 3.0), (0.62, 35.0, 170.0, 2.9, 5.0), (0.75, 22.0, 120.0, 4.1, 2.5)];
    let mut planes = vec![Plane::new(w, h), Plane::new(w, h), Plane::new(w, h)];
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32, y as f32);
            let r = ((fx - cx).powi(2) + (fy - cy).powi(2)).sqrt() / rad;
            // soft circular field stop and a vignetted fundus
            let stop = (1.0 - (r - 0.97) / 0.03).clamp(0.0, 1.0);
            let base = 0.55 + 0.25 * (1.0 - r * r).max(0.0);
            let d2 = ((fx - dx0).powi(2) + (fy - dy0).powi(2)) / (0.07 * h as f32).powi(2);
            let disc = (-d2).exp();
            let mut vessel = 0.0f32;
            for (yi, a, p, ph, wd) in vessels {
                let yc = yi * h as f32 + a * (fx / p + ph).sin() + 0.1 * (fx - cx);
                vessel = vessel.max((-((fy - yc) / wd).powi(2)).exp());
            }
            let mottle = 0.03 * ((fx / 37.0).sin() * (fy / 53.0).cos() + (fx / 71.0 + fy / 89.0).sin());
            let red = (base + mottle + 0.2 * disc) * (1.0 - 0.35 * vessel);
            let green = (0.12 + 0.5 * mottle + 0.3 * disc) * (1.0 - 0.6 * vessel);
            let blue = (0.04 + 0.15 * disc) * (1.0 - 0.3 * vessel);
            planes[0].set(x, y, (stop * red).clamp(0.0, 1.0));
            planes[1].set(x, y, (stop * green).clamp(0.0, 1.0));
            planes[2].set(x, y, (stop * blue).clamp(0.0, 1.0));
        }
    }
    planes
}

/// Deterministic standard normal samples (SplitMix64 + Box–Muller).
pub struct GaussianNoise {
    state: u64,
    spare: Option<f32>,
}

impl GaussianNoise {
    pub fn new(seed: u64) -> Self {
        Self { state: seed ^ 0x9E37_79B9_7F4A_7C15, spare: None }
    }

    fn uniform(&mut self) -> f64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// One N(0, 1) sample.
    pub fn sample(&mut self) -> f32 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let (a, b) = (self.uniform(), self.uniform());
        let r = (-2.0 * a.ln()).sqrt();
        let t = 2.0 * std::f64::consts::PI * b;
        self.spare = Some((r * t.sin()) as f32);
        (r * t.cos()) as f32
    }

    /// Adds `sigma`-scaled noise to every pixel.
    pub fn add_to(&mut self, p: &mut Plane, sigma: f32) {
        for v in &mut p.data {
            *v += sigma * self.sample();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_sum_to_one_and_vary_by_channel_and_field() {
        let lens = SyntheticLens::new(15, 3);
        let g = lens.grid(120, 90, 3, 3, 3);
        let second_moment = |k: &Plane| -> f32 {
            let c = (k.width as f32 - 1.0) / 2.0;
            let mut m = 0.0;
            for v in 0..k.height {
                for u in 0..k.width {
                    m += k.get(u, v) * ((u as f32 - c).powi(2) + (v as f32 - c).powi(2));
                }
            }
            m
        };
        for ch in &g.kernels {
            for k in ch {
                assert!((k.sum() - 1.0).abs() < 1e-4);
            }
        }
        // green (1) is sharpest at the centre tile (4); corners blur more than the centre
        let m: Vec<f32> = (0..3).map(|c| second_moment(&g.kernels[c][4])).collect();
        assert!(m[1] < m[0] && m[1] < m[2], "{m:?}");
        assert!(second_moment(&g.kernels[1][0]) > second_moment(&g.kernels[1][4]));
    }

    #[test]
    fn noise_has_unit_variance() {
        let mut n = GaussianNoise::new(3);
        let s: Vec<f32> = (0..20000).map(|_| n.sample()).collect();
        let mean = s.iter().sum::<f32>() / s.len() as f32;
        let var = s.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / s.len() as f32;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05, "{mean} {var}");
    }
}
