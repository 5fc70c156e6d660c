//! Geometric distortion of the lens in lensfun's `ptlens` model.
//!
//! # Model (`ptlens`, as lensfun 0.3 defines it)
//! `r_d = r_u·(a·r_u³ + b·r_u² + c·r_u + 1 − a − b − c)`: a point of the ideal (undistorted,
//! rectilinear) image at radius `r_u` from the image centre is seen on the sensor at radius
//! `r_d`, along the same direction. Radii are about the image centre `((w−1)/2, (h−1)/2)` in
//! lensfun's distortion/TCA unit ([`radius_norm`]: one unit is about half the **shorter** side,
//! the unit [`crate::export::lensfun::tca_norm`] uses and `tests/lensfun.rs` checks against
//! liblensfun). `r_u = 1` is a fixed point, so the model does not change the scale there;
//! `b < 0` is barrel distortion, `b > 0` pincushion. The equation is in `docs/method.md`
//! ("Geometric distortion").
//!
//! The mock camera renders through the inverse: for each sensor (distorted) pixel it samples
//! the scene at the undistorted position ([`PtLens::undistort_px`], Newton's method on the
//! cubic), which needs the map to be monotonic over the frame ([`PtLens::check`]).

/// lensfun's `ptlens` coefficients.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PtLens {
    pub a: f64,
    pub b: f64,
    pub c: f64,
}

/// Pixels → lensfun distortion units for a `width × height` image: one unit is half the
/// diagonal of `(w−1) × (h−1)` divided by `hypot(aspect, 1)`, about half the shorter side.
pub fn radius_norm(width: usize, height: usize) -> f64 {
    let ar = width.max(height) as f64 / width.min(height).max(1) as f64;
    2.0 * ar.hypot(1.0) / ((width as f64 - 1.0).hypot(height as f64 - 1.0))
}

/// The image corner's radius in lensfun units (`hypot(aspect, 1)`, 5/3 at 4:3).
pub fn corner_radius(width: usize, height: usize) -> f64 {
    (width as f64 - 1.0).hypot(height as f64 - 1.0) / 2.0 * radius_norm(width, height)
}

/// A `ptlens` map that folds over (is not monotonic) inside the frame.
#[derive(Debug, thiserror::Error)]
#[error("ptlens distortion a={a}, b={b}, c={c} is not monotonic over the frame: dr_d/dr_u = {slope:.3} at r_u = {radius:.3} (the corner is at r_d = {corner:.3})")]
pub struct NotMonotonic {
    pub a: f64,
    pub b: f64,
    pub c: f64,
    pub slope: f64,
    pub radius: f64,
    pub corner: f64,
}

impl PtLens {
    /// No distortion.
    pub const NONE: PtLens = PtLens { a: 0.0, b: 0.0, c: 0.0 };

    /// `r_d / r_u` at `r_u` (lensfun units).
    pub fn ratio(&self, ru: f64) -> f64 {
        ((self.a * ru + self.b) * ru + self.c) * ru + 1.0 - self.a - self.b - self.c
    }

    /// `r_d(r_u)`.
    pub fn forward(&self, ru: f64) -> f64 {
        ru * self.ratio(ru)
    }

    /// `dr_d/dr_u` at `r_u`.
    pub fn slope(&self, ru: f64) -> f64 {
        ((4.0 * self.a * ru + 3.0 * self.b) * ru + 2.0 * self.c) * ru + 1.0 - self.a - self.b - self.c
    }

    /// `r_u(r_d)` by Newton's method from `r_u = r_d`; valid where [`Self::check`] holds.
    pub fn inverse(&self, rd: f64) -> f64 {
        let mut ru = rd;
        for _ in 0..20 {
            let s = self.slope(ru);
            if s.abs() < 1e-12 {
                break;
            }
            let step = (self.forward(ru) - rd) / s;
            ru -= step;
            if step.abs() < 1e-13 {
                break;
            }
        }
        ru
    }

    /// Checks that `r_d(r_u)` rises monotonically from the centre until it has passed the
    /// frame's corner (with 5 % to spare), so every sensor pixel has one undistorted position.
    ///
    /// # Errors
    /// [`NotMonotonic`] with the radius where the slope first drops to ≤ 0.05 (or the
    /// coefficients are not finite).
    pub fn check(&self, width: usize, height: usize) -> Result<(), NotMonotonic> {
        let corner = corner_radius(width, height);
        let err = |slope: f64, radius: f64| NotMonotonic { a: self.a, b: self.b, c: self.c, slope, radius, corner };
        if ![self.a, self.b, self.c].iter().all(|v| v.is_finite()) {
            return Err(err(f64::NAN, 0.0));
        }
        let step = corner / 400.0;
        let mut ru = 0.0;
        while self.forward(ru) < 1.05 * corner {
            let s = self.slope(ru);
            if s <= 0.05 || ru > 4.0 * corner {
                return Err(err(s, ru));
            }
            ru += step;
        }
        Ok(())
    }

    /// The sensor position of the undistorted pixel `(x, y)` of a `width × height` image.
    pub fn distort_px(&self, x: f64, y: f64, width: usize, height: usize) -> (f64, f64) {
        let (cx, cy) = centre(width, height);
        let k = radius_norm(width, height);
        let m = self.ratio((x - cx).hypot(y - cy) * k);
        (cx + (x - cx) * m, cy + (y - cy) * m)
    }

    /// The undistorted position of the sensor pixel `(x, y)` (the inverse of
    /// [`Self::distort_px`]).
    pub fn undistort_px(&self, x: f64, y: f64, width: usize, height: usize) -> (f64, f64) {
        let (cx, cy) = centre(width, height);
        let k = radius_norm(width, height);
        let rd = (x - cx).hypot(y - cy) * k;
        if rd < 1e-12 {
            return (x, y);
        }
        let m = self.inverse(rd) / rd;
        (cx + (x - cx) * m, cy + (y - cy) * m)
    }

    /// The displacement the distortion causes at sensor pixel `(x, y)`: where it is seen minus
    /// where an ideal lens would show it, `(x, y) − undistort(x, y)`, pixels.
    pub fn displacement_px(&self, x: f64, y: f64, width: usize, height: usize) -> (f64, f64) {
        let (u, v) = self.undistort_px(x, y, width, height);
        (x - u, y - v)
    }

    /// Whether all three coefficients are zero.
    pub fn is_none(&self) -> bool {
        *self == Self::NONE
    }
}

/// The image centre `((w−1)/2, (h−1)/2)` in pixels.
pub fn centre(width: usize, height: usize) -> (f64, f64) {
    ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values_and_the_fixed_point() {
        let d = PtLens { a: 0.01, b: -0.02, c: 0.005 };
        // r_u = 1 is a fixed point of every ptlens map
        assert!((d.forward(1.0) - 1.0).abs() < 1e-15);
        // r_u = 0.5: 0.5·(0.01/8 − 0.02/4 + 0.005/2 + 1.005)
        assert!((d.forward(0.5) - 0.5 * (0.00125 - 0.005 + 0.0025 + 1.005)).abs() < 1e-15);
        // the 4:3 unit: about half the shorter side, the corner at hypot(4/3, 1) = 5/3
        assert!((radius_norm(384, 288) * 143.5 - 1.0).abs() < 1e-3);
        assert!((corner_radius(384, 288) - 5.0 / 3.0).abs() < 1e-12);
        // barrel (b < 0) pulls the corner inwards
        let barrel = PtLens { a: 0.0, b: -0.02, c: 0.0 };
        let (x, y) = barrel.distort_px(0.0, 0.0, 384, 288);
        assert!(x > 0.0 && y > 0.0 && (x / y - 191.5 / 143.5).abs() < 1e-9);
        assert!((barrel.distort_px(191.5, 143.5, 384, 288).0 - 191.5).abs() < 1e-12);
    }

    #[test]
    fn round_trip_over_the_frame() {
        let d = PtLens { a: 0.015, b: -0.03, c: 0.01 };
        let (w, h) = (384, 288);
        let mut worst = 0.0f64;
        for j in 0..=12 {
            for i in 0..=16 {
                let (x, y) = (i as f64 * 383.0 / 16.0, j as f64 * 287.0 / 12.0);
                let (u, v) = d.undistort_px(x, y, w, h);
                let (x2, y2) = d.distort_px(u, v, w, h);
                worst = worst.max((x2 - x).hypot(y2 - y));
            }
        }
        assert!(worst < 1e-9, "{worst}");
        let (dx, dy) = d.displacement_px(0.0, 0.0, w, h);
        assert!(dx.hypot(dy) > 0.5, "{dx} {dy}");
    }

    #[test]
    fn monotonicity_check_rejects_folding_maps() {
        assert!(PtLens { a: 0.0, b: -0.02, c: 0.0 }.check(384, 288).is_ok());
        assert!(PtLens::NONE.check(384, 288).is_ok());
        // strong barrel: r_d = r_u·(1 + b(r_u² − 1)) peaks at r_u = sqrt((1 − b)/(3·(−b)))
        let e = PtLens { a: 0.0, b: -0.3, c: 0.0 }.check(384, 288).unwrap_err();
        assert!(e.radius < 5.0 / 3.0 && e.slope <= 0.05, "{e}");
        assert!(PtLens { a: f64::NAN, b: 0.0, c: 0.0 }.check(384, 288).is_err());
    }
}
