//! A small deterministic random source (PCG-XSH-RR 64/32) with the distributions the simulator
//! and targets need. Seeded explicitly everywhere so every simulated capture is reproducible.

/// PCG32 generator.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    inc: u64,
    spare_normal: Option<f64>,
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        let mut r = Self { state: 0, inc: (seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) << 1) | 1, spare_normal: None };
        r.next_u32();
        r.state = r.state.wrapping_add(seed ^ 0x853c_49e6_748f_ea9b);
        r.next_u32();
        r
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        let hi = (self.next_u32() >> 5) as u64; // 27 bits
        let lo = (self.next_u32() >> 6) as u64; // 26 bits
        ((hi << 26) | lo) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [a, b).
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.uniform()
    }

    /// Standard normal (Box–Muller, the spare value cached).
    pub fn normal(&mut self) -> f64 {
        if let Some(v) = self.spare_normal.take() {
            return v;
        }
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (2.0 * std::f64::consts::PI * u2).sin_cos();
        self.spare_normal = Some(r * s);
        r * c
    }

    /// Poisson with mean `lambda` (exact inversion below 30, a continuity-corrected normal
    /// approximation above, whose error is far below the read noise of any sensor modelled).
    pub fn poisson(&mut self, lambda: f64) -> f64 {
        if lambda <= 0.0 {
            return 0.0;
        }
        if lambda < 30.0 {
            let l = (-lambda).exp();
            let mut k = 0.0;
            let mut p = 1.0;
            loop {
                p *= self.uniform();
                if p <= l {
                    return k;
                }
                k += 1.0;
            }
        }
        (lambda + lambda.sqrt() * self.normal() + 0.5).floor().max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_are_right() {
        let mut r = Rng::new(7);
        let n = 200_000;
        let (mut s, mut s2) = (0.0, 0.0);
        for _ in 0..n {
            let v = r.normal();
            s += v;
            s2 += v * v;
        }
        assert!((s / n as f64).abs() < 0.01);
        assert!((s2 / n as f64 - 1.0).abs() < 0.02);
        for &lam in &[0.5, 4.0, 25.0, 400.0] {
            let (mut m, mut v) = (0.0, 0.0);
            let k = 50_000;
            let xs: Vec<f64> = (0..k).map(|_| r.poisson(lam)).collect();
            for x in &xs {
                m += x;
            }
            m /= k as f64;
            for x in &xs {
                v += (x - m).powi(2);
            }
            v /= k as f64;
            assert!((m - lam).abs() < 0.05 * lam.sqrt() + 0.02, "mean {m} for {lam}");
            assert!((v / lam - 1.0).abs() < 0.05, "var {v} for {lam}");
        }
    }

    #[test]
    fn seeds_differ_and_repeat() {
        let a: Vec<u32> = (0..4).map({ let mut r = Rng::new(1); move |_| r.next_u32() }).collect();
        let b: Vec<u32> = (0..4).map({ let mut r = Rng::new(1); move |_| r.next_u32() }).collect();
        let c: Vec<u32> = (0..4).map({ let mut r = Rng::new(2); move |_| r.next_u32() }).collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }
}
