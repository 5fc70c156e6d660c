//! Noise level of a captured channel, for defaults that need no tuning.
//!
//! Donoho's robust estimator: the finest diagonal Haar detail `(a − b − c + d) / 2` of each
//! 2×2 block holds almost no signal in a blurred image, so its median absolute value divided
//! by 0.6745 estimates the standard deviation of white Gaussian noise. Values are on the
//! plane's own axis (call it on linear data for the solver).

use crate::image::Plane;

/// The estimated noise standard deviation of `p` (0 for planes smaller than 2×2).
pub fn estimate_sigma(p: &Plane) -> f32 {
    let mut d = Vec::with_capacity((p.width / 2) * (p.height / 2));
    for y in (0..p.height.saturating_sub(1)).step_by(2) {
        for x in (0..p.width.saturating_sub(1)).step_by(2) {
            let v = (p.get(x, y) - p.get(x + 1, y) - p.get(x, y + 1) + p.get(x + 1, y + 1)) * 0.5;
            d.push(v.abs());
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    let (_, m, _) = d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m / 0.6745
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_noise_level_on_a_smooth_image() {
        let mut s = 99u64;
        let mut gauss = || {
            // Box–Muller from an LCG
            let mut u = || {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (u(), u());
            ((-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()) as f32
        };
        let p = Plane::from_fn(128, 128, |x, y| 0.3 + 0.2 * ((x as f32) * 0.05).sin() * ((y as f32) * 0.03).cos() + 0.01 * gauss());
        let s = estimate_sigma(&p);
        assert!((s - 0.01).abs() < 0.001, "{s}");
        assert_eq!(estimate_sigma(&Plane::filled(1, 5, 1.0)), 0.0);
    }
}
