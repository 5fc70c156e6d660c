//! The physical lens simulator: field-dependent, per-channel PSFs from a wavefront model.
//!
//! # Model
//! A thin singlet with a circular pupil. The wavefront error over the normalised pupil
//! `p = (px, py)`, `ρ = |p| ≤ 1`, at normalised field `H = |h|` (1 = half the sensor diagonal,
//! direction `ĥ`), is the Seidel sum
//!
//! `W(p) = W020·ρ² + W040·ρ⁴ + W131·H·ρ²·(p·ĥ) + W222·H²·(p·ĥ)² + W220·H²·ρ² + W_λ·ρ²`
//!
//! (defocus, spherical, coma, astigmatism, field curvature, chromatic focal shift), in
//! micrometres. The Seidel coefficients are given at a reference f-number `N₀`; stopping down to
//! `N` shrinks the pupil by `N₀/N`, so a term in `ρⁿ` scales by `(N₀/N)ⁿ`.
//!
//! **Chromatic focal shift** from the glass's dispersion (Cauchy fit to `n_d` and the Abbe
//! number `V_d`): a thin lens's focal length goes as `1/(n(λ) − 1)`, so the focus moves by
//! `Δz(λ) = f·((n(λ_f) − 1)/(n(λ) − 1) − 1)` from the focus wavelength `λ_f`, a defocus of
//! `W_λ = −Δz / (8N²)`.
//!
//! **Diffraction**: the PSF at wavelength `λ` is `|F{P·exp(i2πW/λ)}|²` sampled at `dx = λN/D·M/M`
//! (Fourier optics, Fraunhofer), computed on a grid fine enough (odd oversampling `os`, pupil
//! diameter `D ≤ M/2` samples) that neither the PSF nor its autocorrelation aliases, then
//! integrated over square pixels (100% fill factor). With diffraction off, the PSF is the
//! geometric spot: pupil rays displaced by `ε = 2N·∇W` and binned on the same grid.
//!
//! Each colour channel integrates several wavelengths with weights ([`Band`]). Kernels are
//! cropped to `k × k` and normalised to sum 1 (energy beyond the kernel is stray light and
//! belongs to the glare model, not to the PSF).
//!
//! # Conventions
//! Field positions are sensor pixels, the optical axis at the sensor centre
//! `((w−1)/2, (h−1)/2)`; kernels follow [`crate::solve::conv`] (centre = the chief ray).

use super::psf_grid::PsfGrid;
use crate::image::Plane;
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::FftPlanner;
use serde::{Deserialize, Serialize};

/// An optical glass by its d-line index and Abbe number.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Glass {
    pub n_d: f64,
    pub abbe: f64,
}

impl Glass {
    /// Schott N-BK7, the usual cheap singlet.
    pub const BK7: Glass = Glass { n_d: 1.5168, abbe: 64.17 };

    /// Refractive index at `lambda_nm` from a two-term Cauchy fit through `n_d` (587.6 nm) and
    /// the F–C dispersion `(n_d − 1)/V_d` (486.1 / 656.3 nm).
    pub fn index(&self, lambda_nm: f64) -> f64 {
        let (lf, lc, ld) = (0.4861, 0.6563, 0.5876);
        let dn = (self.n_d - 1.0) / self.abbe;
        let b = dn / (1.0 / (lf * lf) - 1.0 / (lc * lc));
        let a = self.n_d - b / (ld * ld);
        let l = lambda_nm / 1000.0;
        a + b / (l * l)
    }
}

/// The wavelengths one colour channel integrates, with relative weights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Band {
    pub name: String,
    /// `(wavelength in nm, weight)`
    pub wavelengths: Vec<(f64, f64)>,
}

/// Three-wavelength approximations of a typical RGB sensor's channels.
pub fn rgb_bands() -> Vec<Band> {
    vec![
        Band { name: "R".into(), wavelengths: vec![(595.0, 0.3), (620.0, 0.45), (650.0, 0.25)] },
        Band { name: "G".into(), wavelengths: vec![(510.0, 0.3), (540.0, 0.45), (570.0, 0.25)] },
        Band { name: "B".into(), wavelengths: vec![(440.0, 0.3), (465.0, 0.45), (490.0, 0.25)] },
    ]
}

/// A single luminance channel (for monochrome sensors).
pub fn mono_band() -> Vec<Band> {
    vec![Band { name: "Y".into(), wavelengths: vec![(500.0, 0.25), (550.0, 0.5), (600.0, 0.25)] }]
}

/// Seidel wavefront coefficients in micrometres at the reference f-number (field terms at
/// `H = 1`). Any term set to zero is switched off.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Aberrations {
    pub defocus_um: f64,
    pub spherical_um: f64,
    pub coma_um: f64,
    pub astigmatism_um: f64,
    pub field_curvature_um: f64,
}

/// A simple lens in front of a sensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LensModel {
    pub focal_length_mm: f64,
    /// The f-number at which [`Aberrations`] are given.
    pub reference_f_number: f64,
    pub pixel_pitch_um: f64,
    /// Sensor size in pixels (sets the field normalisation and optical centre).
    pub width: usize,
    pub height: usize,
    pub aberrations: Aberrations,
    /// Chromatic focal shift from this glass; `None` switches it off.
    pub glass: Option<Glass>,
    /// The wavelength the sensor is focused for.
    pub focus_wavelength_nm: f64,
    /// Fourier-optics PSFs when true, geometric spots when false.
    pub diffraction: bool,
    pub bands: Vec<Band>,
}

impl LensModel {
    /// A plano-convex BK7 singlet like the paper's, scaled to a small sensor: blur of a few to
    /// ~20 pixels at f/4, chromatic, with coma and astigmatism towards the corners.
    pub fn demo(width: usize, height: usize) -> Self {
        Self {
            focal_length_mm: 16.0,
            reference_f_number: 4.0,
            pixel_pitch_um: 5.0,
            width,
            height,
            aberrations: Aberrations { defocus_um: 0.0, spherical_um: 1.2, coma_um: 1.0, astigmatism_um: 1.0, field_curvature_um: 0.8 },
            glass: Some(Glass::BK7),
            focus_wavelength_nm: 540.0,
            diffraction: true,
            bands: rgb_bands(),
        }
    }

    /// Channel names in order.
    pub fn channel_names(&self) -> Vec<String> {
        self.bands.iter().map(|b| b.name.clone()).collect()
    }

    fn half_diagonal(&self) -> f64 {
        0.5 * ((self.width as f64).powi(2) + (self.height as f64).powi(2)).sqrt()
    }

    /// Normalised field vector of a pixel position.
    pub fn field(&self, x: f64, y: f64) -> (f64, f64) {
        let cx = (self.width as f64 - 1.0) / 2.0;
        let cy = (self.height as f64 - 1.0) / 2.0;
        let hd = self.half_diagonal();
        ((x - cx) / hd, (y - cy) / hd)
    }

    /// The wavefront coefficients `[W020, W040, W131·H, W222·H², W220·H²]` at f-number `n`
    /// and wavelength `lambda_nm`, plus the field direction.
    fn coefficients(&self, n: f64, lambda_nm: f64, hx: f64, hy: f64) -> ([f64; 5], (f64, f64)) {
        let a = &self.aberrations;
        let r = self.reference_f_number / n;
        let h = (hx * hx + hy * hy).sqrt();
        let dir = if h > 1e-12 { (hx / h, hy / h) } else { (1.0, 0.0) };
        let mut w020 = a.defocus_um * r * r;
        if let Some(g) = self.glass {
            let f_um = self.focal_length_mm * 1000.0;
            let dz = f_um * ((g.index(self.focus_wavelength_nm) - 1.0) / (g.index(lambda_nm) - 1.0) - 1.0);
            w020 += -dz / (8.0 * n * n);
        }
        (
            [w020, a.spherical_um * r.powi(4), a.coma_um * r.powi(3) * h, a.astigmatism_um * r * r * h * h, a.field_curvature_um * r * r * h * h],
            dir,
        )
    }

    /// Wavefront `W` (µm) and its gradient at pupil point `(px, py)`.
    fn wavefront(c: &[f64; 5], dir: (f64, f64), px: f64, py: f64) -> (f64, f64, f64) {
        let rho2 = px * px + py * py;
        let pd = px * dir.0 + py * dir.1;
        let w = (c[0] + c[4]) * rho2 + c[1] * rho2 * rho2 + c[2] * rho2 * pd + c[3] * pd * pd;
        // gradients
        let gx = 2.0 * (c[0] + c[4]) * px + 4.0 * c[1] * rho2 * px + c[2] * (2.0 * px * pd + rho2 * dir.0) + 2.0 * c[3] * pd * dir.0;
        let gy = 2.0 * (c[0] + c[4]) * py + 4.0 * c[1] * rho2 * py + c[2] * (2.0 * py * pd + rho2 * dir.1) + 2.0 * c[3] * pd * dir.1;
        (w, gx, gy)
    }

    /// Largest geometric spot radius (µm) over the pupil, sampled.
    fn spot_radius_um(c: &[f64; 5], dir: (f64, f64), n: f64) -> f64 {
        let mut r: f64 = 0.0;
        for i in 0..=24 {
            for j in 0..=24 {
                let (px, py) = (i as f64 / 12.0 - 1.0, j as f64 / 12.0 - 1.0);
                if px * px + py * py <= 1.0 {
                    let (_, gx, gy) = Self::wavefront(c, dir, px, py);
                    r = r.max(2.0 * n * (gx * gx + gy * gy).sqrt());
                }
            }
        }
        r
    }

    /// The PSF of channel `band` at f-number `n` and pixel position `(x, y)`, `k × k`, sum 1.
    pub fn psf(&self, n: f64, band: usize, x: f64, y: f64, k: usize) -> Plane {
        assert!(k % 2 == 1, "kernel size must be odd");
        let (hx, hy) = self.field(x, y);
        let mut out = Plane::new(k, k);
        let b = &self.bands[band];
        let wsum: f64 = b.wavelengths.iter().map(|w| w.1).sum();
        for &(lambda, weight) in &b.wavelengths {
            let p = if self.diffraction { self.psf_fourier(n, lambda, hx, hy, k) } else { self.psf_geometric(n, lambda, hx, hy, k) };
            for (o, v) in out.data.iter_mut().zip(&p.data) {
                *o += (weight / wsum) as f32 * v;
            }
        }
        let s = out.sum() as f32;
        if s > 0.0 {
            out.scale(1.0 / s);
        }
        out
    }

    /// One wavelength, Fourier optics, `k × k`, normalised to the total energy (so the crop
    /// keeps the fraction of energy inside the kernel).
    fn psf_fourier(&self, n: f64, lambda_nm: f64, hx: f64, hy: f64, k: usize) -> Plane {
        let (c, dir) = self.coefficients(n, lambda_nm, hx, hy);
        let lam_um = lambda_nm / 1000.0;
        let pitch = self.pixel_pitch_um;
        // odd oversampling with dx <= λN/2
        let mut os = (2.0 * pitch / (lam_um * n)).ceil().max(3.0) as usize;
        if os % 2 == 0 {
            os += 1;
        }
        let dx = pitch / os as f64;
        let spot = Self::spot_radius_um(&c, dir, n);
        let extent_um = (k as f64 * pitch).max(2.0 * (spot + 6.0 * lam_um * n)) * 1.3;
        let m = crate::solve::fft::good_size((extent_um / dx).ceil() as usize).max(64);
        let d = m as f64 * dx / (lam_um * n); // pupil diameter in samples (<= m/2)
        let mut field = vec![Complex32::new(0.0, 0.0); m * m];
        let half = m as f64 / 2.0;
        let k2pi = 2.0 * std::f64::consts::PI / lam_um;
        for j in 0..m {
            let py = (j as f64 - half) * 2.0 / d;
            if py.abs() > 1.0 {
                continue;
            }
            for i in 0..m {
                let px = (i as f64 - half) * 2.0 / d;
                if px * px + py * py <= 1.0 {
                    let (w, _, _) = Self::wavefront(&c, dir, px, py);
                    let ph = k2pi * w;
                    // ifftshift so the pupil centre sits at index 0
                    let ii = (i + m / 2) % m;
                    let jj = (j + m / 2) % m;
                    field[jj * m + ii] = Complex32::new(ph.cos() as f32, ph.sin() as f32);
                }
            }
        }
        fft2_complex_inplace(&mut field, m);
        // intensity, fftshift so zero displacement is at (m/2, m/2)
        let mut inten = vec![0.0f32; m * m];
        let mut total = 0.0f64;
        for j in 0..m {
            for i in 0..m {
                let v = field[j * m + i].norm_sqr();
                inten[((j + m / 2) % m) * m + (i + m / 2) % m] = v;
                total += v as f64;
            }
        }
        bin_to_pixels(&inten, m, os, k, total)
    }

    /// One wavelength, geometric spot (ray bundle through a 401-sample pupil grid).
    fn psf_geometric(&self, n: f64, lambda_nm: f64, hx: f64, hy: f64, k: usize) -> Plane {
        let (c, dir) = self.coefficients(n, lambda_nm, hx, hy);
        let os = 5usize;
        let m = k * os + 2 * os;
        let dx = self.pixel_pitch_um / os as f64;
        let mut inten = vec![0.0f32; m * m];
        let samples = 401;
        let mut total = 0.0f64;
        for j in 0..samples {
            let py = 2.0 * (j as f64 + 0.5) / samples as f64 - 1.0;
            for i in 0..samples {
                let px = 2.0 * (i as f64 + 0.5) / samples as f64 - 1.0;
                if px * px + py * py > 1.0 {
                    continue;
                }
                total += 1.0;
                let (_, gx, gy) = Self::wavefront(&c, dir, px, py);
                let (ex, ey) = (2.0 * n * gx / dx, 2.0 * n * gy / dx);
                let (fx, fy) = (m as f64 / 2.0 + ex, m as f64 / 2.0 + ey);
                let (x0, y0) = (fx.floor(), fy.floor());
                let (tx, ty) = ((fx - x0) as f32, (fy - y0) as f32);
                for (dxi, dyi, w) in [(0, 0, (1.0 - tx) * (1.0 - ty)), (1, 0, tx * (1.0 - ty)), (0, 1, (1.0 - tx) * ty), (1, 1, tx * ty)] {
                    let (xi, yi) = (x0 as isize + dxi, y0 as isize + dyi);
                    if xi >= 0 && yi >= 0 && (xi as usize) < m && (yi as usize) < m {
                        inten[yi as usize * m + xi as usize] += w;
                    }
                }
            }
        }
        bin_to_pixels(&inten, m, os, k, total)
    }

    /// PSFs of every channel at the centres of a `columns × rows` grid over the sensor.
    pub fn psf_grid(&self, n: f64, columns: usize, rows: usize, k: usize) -> PsfGrid {
        let centers = PsfGrid::regular_centers(self.width, self.height, columns, rows);
        self.psf_grid_at(n, centers, columns, rows, k)
    }

    /// [`Self::psf_grid`] on a lattice whose outer centres lie on the frame's edges
    /// ([`PsfGrid::edge_centers`]), so the blend follows the lens out to the corners.
    pub fn psf_grid_to_edges(&self, n: f64, columns: usize, rows: usize, k: usize) -> PsfGrid {
        self.psf_grid_at(n, PsfGrid::edge_centers(self.width, self.height, columns, rows), columns, rows, k)
    }

    /// PSFs of every channel at given rectilinear grid centres.
    pub fn psf_grid_at(&self, n: f64, centers: Vec<[f64; 2]>, columns: usize, rows: usize, k: usize) -> PsfGrid {
        let jobs: Vec<(usize, usize)> = (0..self.bands.len()).flat_map(|b| (0..centers.len()).map(move |t| (b, t))).collect();
        let psfs: Vec<Plane> = jobs.par_iter().map(|&(b, t)| self.psf(n, b, centers[t][0], centers[t][1], k)).collect();
        let mut kernels = vec![Vec::with_capacity(centers.len()); self.bands.len()];
        for ((b, _), p) in jobs.into_iter().zip(psfs) {
            kernels[b].push(p);
        }
        PsfGrid { kernel_size: k, columns, rows, centers, channels: self.channel_names(), kernels }
    }

    /// A kernel size that holds the largest PSF of the field at f-number `n` (odd, with margin).
    pub fn suggested_kernel_size(&self, n: f64) -> usize {
        let mut r: f64 = 0.0;
        for b in &self.bands {
            for &(l, _) in &b.wavelengths {
                for &(x, y) in &[(0.0, 0.0), (self.width as f64 - 1.0, self.height as f64 - 1.0), ((self.width as f64 - 1.0) / 2.0, (self.height as f64 - 1.0) / 2.0)] {
                    let (hx, hy) = self.field(x, y);
                    let (c, dir) = self.coefficients(n, l, hx, hy);
                    let airy = if self.diffraction { 2.44 * l / 1000.0 * n } else { 0.0 };
                    r = r.max((Self::spot_radius_um(&c, dir, n) + airy) / self.pixel_pitch_um);
                }
            }
        }
        let k = (2.0 * r * 1.15).ceil() as usize + 3;
        k | 1
    }
}

/// Integrates an `m × m` oversampled intensity (zero displacement at `(m/2, m/2)`) over
/// `os × os` pixel cells into a `k × k` kernel, normalised by `total`.
fn bin_to_pixels(inten: &[f32], m: usize, os: usize, k: usize, total: f64) -> Plane {
    let c = (k as isize - 1) / 2;
    let h = (os as isize - 1) / 2;
    let mid = (m / 2) as isize;
    Plane::from_fn(k, k, |u, v| {
        let cx = mid + (u as isize - c) * os as isize;
        let cy = mid + (v as isize - c) * os as isize;
        let mut acc = 0.0f64;
        for yy in cy - h..=cy + h {
            if yy < 0 || yy >= m as isize {
                continue;
            }
            for xx in cx - h..=cx + h {
                if xx >= 0 && xx < m as isize {
                    acc += inten[yy as usize * m + xx as usize] as f64;
                }
            }
        }
        (acc / total.max(1e-300)) as f32
    })
}

/// In-place forward 2-D complex FFT of an `m × m` row-major array.
fn fft2_complex_inplace(a: &mut [Complex32], m: usize) {
    let mut planner = FftPlanner::<f32>::new();
    let fft = planner.plan_fft_forward(m);
    let mut scratch = vec![Complex32::new(0.0, 0.0); fft.get_inplace_scratch_len()];
    fft.process_with_scratch(a, &mut scratch); // all rows
    let mut t = vec![Complex32::new(0.0, 0.0); m * m];
    for j in 0..m {
        for i in 0..m {
            t[i * m + j] = a[j * m + i];
        }
    }
    fft.process_with_scratch(&mut t, &mut scratch); // all columns
    for j in 0..m {
        for i in 0..m {
            a[j * m + i] = t[i * m + j];
        }
    }
}

/// Second-moment radius of a kernel (pixels), a size measure used in tests and reports.
pub fn rms_radius(k: &Plane) -> f64 {
    let s = k.sum().max(1e-30);
    let (mut mx, mut my) = (0.0, 0.0);
    for y in 0..k.height {
        for x in 0..k.width {
            let v = k.get(x, y) as f64;
            mx += v * x as f64;
            my += v * y as f64;
        }
    }
    mx /= s;
    my /= s;
    let mut r2 = 0.0;
    for y in 0..k.height {
        for x in 0..k.width {
            r2 += k.get(x, y) as f64 * ((x as f64 - mx).powi(2) + (y as f64 - my).powi(2));
        }
    }
    (r2 / s).sqrt()
}

/// Centroid of a kernel relative to its centre pixel, `(dx, dy)` in pixels.
pub fn centroid(k: &Plane) -> (f64, f64) {
    let s = k.sum().max(1e-30);
    let c = (k.width as f64 - 1.0) / 2.0;
    let (mut mx, mut my) = (0.0, 0.0);
    for y in 0..k.height {
        for x in 0..k.width {
            let v = k.get(x, y) as f64;
            mx += v * (x as f64 - c);
            my += v * (y as f64 - c);
        }
    }
    (mx / s, my / s)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ideal(width: usize) -> LensModel {
        LensModel {
            focal_length_mm: 16.0,
            reference_f_number: 8.0,
            pixel_pitch_um: 2.0,
            width,
            height: width,
            aberrations: Aberrations::default(),
            glass: None,
            focus_wavelength_nm: 550.0,
            diffraction: true,
            bands: vec![Band { name: "Y".into(), wavelengths: vec![(550.0, 1.0)] }],
        }
    }

    #[test]
    fn bk7_dispersion() {
        let g = Glass::BK7;
        assert!((g.index(587.6) - 1.5168).abs() < 1e-4);
        let dn = g.index(486.1) - g.index(656.3);
        assert!((dn - (1.5168 - 1.0) / 64.17).abs() < 1e-5);
        assert!(g.index(450.0) > g.index(650.0));
    }

    #[test]
    fn airy_pattern_has_the_right_size() {
        // Diffraction-limited: first dark ring at 1.22 λN. At f/8, 550 nm: 5.37 µm = 2.68 px.
        // The second moment of an Airy pattern diverges slowly; check the encircled energy:
        // ~84% inside the first dark ring.
        let lens = ideal(64);
        let k = lens.psf(8.0, 0, 31.5, 31.5, 21);
        let c = 10.0;
        let r0 = 1.22 * 0.55 * 8.0 / 2.0;
        let mut inside = 0.0;
        for y in 0..21 {
            for x in 0..21 {
                if ((x as f64 - c).powi(2) + (y as f64 - c).powi(2)).sqrt() <= r0 {
                    inside += k.get(x, y) as f64;
                }
            }
        }
        // pixel integration and the kernel crop blur the ring slightly
        assert!(inside > 0.70 && inside < 0.92, "encircled energy {inside}");
        let (cx, cy) = centroid(&k);
        assert!(cx.abs() < 0.02 && cy.abs() < 0.02);
    }

    #[test]
    fn defocus_blur_matches_geometric_optics() {
        // Pure defocus W020 gives a uniform disc of radius ε = 2N·2·W020 = 4N·W020.
        let mut lens = ideal(64);
        lens.aberrations.defocus_um = 1.0; // at f/8: 32 µm = 16 px radius... use f/4 reference
        lens.reference_f_number = 4.0;
        lens.pixel_pitch_um = 4.0;
        let n = 4.0;
        let radius_px = 4.0 * n * 1.0 / lens.pixel_pitch_um; // 4 px
        for diffraction in [false, true] {
            lens.diffraction = diffraction;
            let k = lens.psf(n, 0, 31.5, 31.5, 15);
            // a uniform disc of radius R has rms radius R/√2
            let r = rms_radius(&k);
            assert!((r - radius_px / 2f64.sqrt()).abs() < 0.35, "diffraction={diffraction}: rms {r}");
        }
    }

    #[test]
    fn stopping_down_shrinks_aberrations_and_coma_is_radial() {
        let lens = LensModel::demo(320, 240);
        let open = lens.psf(4.0, 1, 300.0, 220.0, 31);
        let stopped = lens.psf(16.0, 1, 300.0, 220.0, 31);
        assert!(rms_radius(&stopped) < 0.6 * rms_radius(&open), "{} vs {}", rms_radius(&stopped), rms_radius(&open));
        // coma displaces the centroid along the field direction (towards the bottom-right corner)
        let (cx, cy) = centroid(&open);
        assert!(cx.abs() > 0.05 && cx.signum() == cy.signum(), "centroid {cx},{cy}");
        // chromatic: blue and red differ from green on axis
        let g = rms_radius(&lens.psf(4.0, 1, 159.5, 119.5, 31));
        let b = rms_radius(&lens.psf(4.0, 2, 159.5, 119.5, 31));
        assert!(b > g * 1.3, "blue {b} vs green {g}");
    }
}
