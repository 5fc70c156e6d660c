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

/// Paints an anti-aliased stroke from `a` to `b` (pixels) of width `width` with value `ink`
/// into every plane (the darker of the current value and the ink wins where it covers).
fn stroke(planes: &mut [Plane], a: (f32, f32), b: (f32, f32), width: f32, ink: f32) {
    let (w, h) = (planes[0].width as f32, planes[0].height as f32);
    let pad = width / 2.0 + 1.0;
    let (xa, xb) = ((a.0.min(b.0) - pad).max(0.0) as usize, (a.0.max(b.0) + pad).min(w - 1.0).max(0.0) as usize);
    let (ya, yb) = ((a.1.min(b.1) - pad).max(0.0) as usize, (a.1.max(b.1) + pad).min(h - 1.0).max(0.0) as usize);
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let len2 = (dx * dx + dy * dy).max(1e-6);
    for y in ya..=yb {
        for x in xa..=xb {
            let (px, py) = (x as f32 - a.0, y as f32 - a.1);
            let t = ((px * dx + py * dy) / len2).clamp(0.0, 1.0);
            let d = ((px - t * dx).powi(2) + (py - t * dy).powi(2)).sqrt();
            let cover = (width / 2.0 + 0.5 - d).clamp(0.0, 1.0);
            if cover > 0.0 {
                for p in planes.iter_mut() {
                    let v = p.get(x, y);
                    p.set(x, y, v + cover * (ink.min(v) - v));
                }
            }
        }
    }
}

/// Line art on the linear axis, `[R, G, B]` equal (procedural, CC0; data/scenes-extra/README.md):
/// black strokes (0.02) on white paper (0.85): rows of glyph-like shapes built from a 3 × 5
/// segment alphabet at cell heights 10–64 px (stroke widths 1–6 px, one or two rows each), a star of 48 spokes and
/// concentric circles.
pub fn line_art(w: usize, h: usize) -> Vec<Plane> {
    let mut planes = vec![Plane::filled(w, h, 0.85); 3];
    let mut rng = crate::rng::Rng::new(1212);
    // segment alphabet on a 2 × 4 lattice of nodes (x ∈ {0, 1}, y ∈ {0, 1, 2}) and diagonals
    let segs: [((f32, f32), (f32, f32)); 10] = [((0.0, 0.0), (1.0, 0.0)), ((0.0, 0.5), (1.0, 0.5)), ((0.0, 1.0), (1.0, 1.0)), ((0.0, 0.0), (0.0, 0.5)), ((0.0, 0.5), (0.0, 1.0)), ((1.0, 0.0), (1.0, 0.5)), ((1.0, 0.5), (1.0, 1.0)), ((0.0, 0.0), (1.0, 1.0)), ((1.0, 0.0), (0.0, 1.0)), ((0.5, 0.0), (0.5, 1.0))];
    let mut top = 8.0f32;
    let scales = [(10.0f32, 1.0f32), (10.0, 1.0), (14.0, 1.3), (14.0, 1.3), (20.0, 2.0), (20.0, 2.0), (30.0, 3.0), (30.0, 3.0), (44.0, 4.0), (64.0, 6.0), (44.0, 4.0)];
    for (cell, width) in scales {
        let gw = 0.6 * cell;
        let mut x = 8.0f32;
        while x + gw < 0.62 * w as f32 && top + cell < h as f32 - 4.0 {
            for (i, (a, b)) in segs.iter().enumerate() {
                if rng.uniform() < if i >= 7 { 0.2 } else { 0.45 } {
                    stroke(&mut planes, (x + a.0 * gw, top + a.1 * cell), (x + b.0 * gw, top + b.1 * cell), width, 0.02);
                }
            }
            x += gw + 0.5 * cell;
        }
        top += 1.35 * cell;
    }
    // a star of spokes and concentric circles on the right
    let (cx, cy, rad) = (0.81 * w as f32, 0.3 * h as f32, 0.16 * w as f32);
    for i in 0..48 {
        let a = i as f32 * std::f32::consts::PI / 24.0;
        stroke(&mut planes, (cx + 0.08 * rad * a.cos(), cy + 0.08 * rad * a.sin()), (cx + rad * a.cos(), cy + rad * a.sin()), 1.5, 0.02);
    }
    let (qx, qy) = (0.81 * w as f32, 0.75 * h as f32);
    for (k, r) in [6.0f32, 12.0, 20.0, 30.0, 42.0, 56.0, 72.0, 90.0].iter().enumerate() {
        let n = (r * 0.8) as usize + 12;
        for s in 0..n {
            let (a0, a1) = (s as f32 * std::f32::consts::TAU / n as f32, (s + 1) as f32 * std::f32::consts::TAU / n as f32);
            stroke(&mut planes, (qx + r * a0.cos(), qy + r * a0.sin()), (qx + r * a1.cos(), qy + r * a1.sin()), 1.0 + k as f32 * 0.5, 0.02);
        }
    }
    planes
}

/// A dark, low-light scene on the linear axis, `[R, G, B]` (procedural, CC0;
/// data/scenes-extra/README.md): a dim room (wall and floor 0.01–0.05 with soft shading, a few
/// dim coloured objects with edges), a faintly lit window (≈ 0.25), and small bright highlights
/// (lamps and specular points at 1.0, clipped) with soft glows. Mean level ≈ 0.03.
pub fn dark_room(w: usize, h: usize) -> Vec<Plane> {
    let (fw, fh) = (w as f32, h as f32);
    let lamps = [(0.18f32, 0.22f32, 5.0f32, [1.0f32, 0.8, 0.5]), (0.55, 0.12, 3.0, [1.0, 1.0, 0.9]), (0.86, 0.35, 4.0, [0.7, 0.8, 1.0]), (0.4, 0.7, 2.0, [1.0, 1.0, 1.0]), (0.68, 0.82, 1.5, [1.0, 0.9, 0.8])];
    // dim boxes: (x0, y0, x1, y1) as image fractions, colour
    let boxes = [(0.08f32, 0.55f32, 0.3f32, 0.9f32, [0.05f32, 0.02, 0.015]), (0.35, 0.45, 0.5, 0.95, [0.02, 0.04, 0.02]), (0.58, 0.5, 0.8, 0.75, [0.015, 0.02, 0.05]), (0.6, 0.2, 0.75, 0.4, [0.25, 0.24, 0.2])];
    let mut planes = vec![Plane::new(w, h), Plane::new(w, h), Plane::new(w, h)];
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f32 / fw, y as f32 / fh);
            let floor = v > 0.62;
            let shade = if floor { 0.018 + 0.02 * (v - 0.62) } else { 0.012 + 0.018 * (1.0 - (u - 0.5).abs()) };
            let mut c = [shade * 1.05, shade, shade * 0.9];
            let texture = 0.004 * ((x as f32 / 7.0).sin() * (y as f32 / 11.0).cos()) + if floor && (x / 48 + y / 24) % 2 == 0 { 0.006 } else { 0.0 };
            for (x0, y0, x1, y1, col) in boxes {
                if u >= x0 && u < x1 && v >= y0 && v < y1 {
                    c = col;
                }
            }
            for (lx, ly, r, col) in lamps {
                let d2 = (x as f32 - lx * fw).powi(2) + (y as f32 - ly * fh).powi(2);
                let core = (r + 0.5 - d2.sqrt()).clamp(0.0, 1.0);
                let glow = 0.06 * (-d2 / (2.0 * (6.0 * r).powi(2))).exp();
                for k in 0..3 {
                    c[k] = c[k] * (1.0 - core) + core * col[k] + glow * col[k];
                }
            }
            for (p, v) in planes.iter_mut().zip(c) {
                p.set(x, y, (v + texture).clamp(0.0, 1.0));
            }
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
    fn dark_room_is_dark_with_bright_highlights() {
        let p = dark_room(320, 240);
        let mean = p.iter().map(|q| q.mean()).sum::<f64>() / 3.0;
        assert!(mean > 0.015 && mean < 0.06, "mean {mean}");
        assert!(p.iter().all(|q| q.max() >= 0.99), "no clipped highlight");
    }

    #[test]
    fn line_art_has_black_strokes_on_white_paper() {
        let p = line_art(400, 300);
        let dark = p[0].data.iter().filter(|v| **v < 0.1).count() as f64 / p[0].data.len() as f64;
        assert!(dark > 0.02 && dark < 0.4, "ink share {dark}");
        assert!((p[0].max() - 0.85).abs() < 1e-6 && p[0].min() < 0.03);
    }

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
