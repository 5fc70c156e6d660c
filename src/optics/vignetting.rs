//! Relative illumination (vignetting) of the simulated lens, in lensfun's `pa` model.
//!
//! # Model (`pa`, as lensfun defines it)
//! `V(r) = 1 + k1·r² + k2·r⁴ + k3·r⁶` multiplies the irradiance the lens delivers at a pixel,
//! `r` the distance from the image centre `((w−1)/2, (h−1)/2)` in units of half the diagonal
//! of `(w−1) × (h−1)` pixels (lensfun's normalisation for vignetting, the one
//! [`crate::export::lensfun::vignetting_norm`] uses and `tests/lensfun.rs` checks against
//! liblensfun). `V(0) = 1`: the centre is the reference. The mock camera applies it to every
//! frame at every aperture (a lens's natural falloff; the aperture dependence of mechanical
//! vignetting is not modelled), after the blur, so a flat field measures it directly.

use crate::image::Plane;

/// lensfun's `pa` vignetting polynomial `[k1, k2, k3]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PaVignetting {
    pub k: [f64; 3],
}

impl PaVignetting {
    /// `r²` (lensfun units) of pixel `(x, y)` in a `width × height` image.
    pub fn r2(x: f64, y: f64, width: usize, height: usize) -> f64 {
        let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
        let s = 2.0 / ((width as f64 - 1.0).hypot(height as f64 - 1.0));
        ((x - cx).powi(2) + (y - cy).powi(2)) * s * s
    }

    /// `V` at pixel `(x, y)` (1 on axis).
    pub fn gain(&self, x: f64, y: f64, width: usize, height: usize) -> f64 {
        let r2 = Self::r2(x, y, width, height);
        1.0 + r2 * (self.k[0] + r2 * (self.k[1] + r2 * self.k[2]))
    }

    /// Multiplies `p` by `V`.
    pub fn apply(&self, p: &mut Plane) {
        let (w, h) = (p.width, p.height);
        for y in 0..h {
            for x in 0..w {
                p.data[y * w + x] *= self.gain(x as f64, y as f64, w, h) as f32;
            }
        }
    }

    /// Checks that `V` stays positive and at most 1.5 over the whole image (`r ≤ 1`), so a
    /// flat field through it is a physical irradiance.
    ///
    /// # Errors
    /// [`VignettingOutOfRange`], naming the radius where `V` leaves `(0, 1.5]`.
    pub fn check(&self) -> Result<(), VignettingOutOfRange> {
        for i in 0..=100 {
            let r2 = (i as f64 / 100.0).powi(2);
            let v = 1.0 + r2 * (self.k[0] + r2 * (self.k[1] + r2 * self.k[2]));
            if !(v.is_finite() && v > 0.0 && v <= 1.5) {
                return Err(VignettingOutOfRange { k: self.k, value: v, radius: r2.sqrt() });
            }
        }
        Ok(())
    }
}

/// A `pa` polynomial whose `V` leaves `(0, 1.5]` somewhere on `r ∈ [0, 1]`.
#[derive(Debug, thiserror::Error)]
#[error("pa vignetting {k:?} gives {value:.3} at r = {radius:.2} (must stay in (0, 1.5])")]
pub struct VignettingOutOfRange {
    pub k: [f64; 3],
    pub value: f64,
    pub radius: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pa_gain_is_one_on_axis_and_the_polynomial_at_the_corner() {
        let v = PaVignetting { k: [-0.3, 0.05, -0.01] };
        let (w, h) = (384, 288);
        assert!((v.gain(191.5, 143.5, w, h) - 1.0).abs() < 1e-12);
        // a corner pixel centre is at r = 1 exactly
        assert!((v.gain(0.0, 0.0, w, h) - (1.0 - 0.3 + 0.05 - 0.01)).abs() < 1e-12);
        // half way along the diagonal: r² = 1/4
        let g = v.gain(191.5 + 95.75, 143.5 + 71.75, w, h);
        assert!((g - (1.0 - 0.3 / 4.0 + 0.05 / 16.0 - 0.01 / 64.0)).abs() < 1e-12, "{g}");
        // the same normalisation as the lensfun export
        let s = crate::export::lensfun::vignetting_norm(w, h);
        assert!((PaVignetting::r2(10.0, 20.0, w, h) - ((181.5f64).powi(2) + (123.5f64).powi(2)) * s * s).abs() < 1e-12);
        let mut p = Plane::filled(w, h, 0.5);
        v.apply(&mut p);
        assert!((p.get(0, 0) as f64 - 0.5 * 0.74).abs() < 1e-6);
        assert!(v.check().is_ok());
        assert!(PaVignetting { k: [-1.2, 0.0, 0.0] }.check().is_err());
    }
}
