//! The no-harm rule (docs/deconvolution.md "No harm", docs/method.md §9): in flat regions
//! the restored image is never noisier than the input; where it would be, the result falls back
//! towards the input, and the report says where.
//!
//! # Rule
//! Per channel, on the linear axis, with `h(p) = p − G_d * p` (`d` = [`NoHarmOptions::detail`]:
//! a high-pass that keeps everything above ≈ `0.5/d` cycles/px, which includes the low band
//! where a far-defocused channel's amplified noise lies) and local energies
//! `e(p) = G_s * h(p)²` (`s` = [`NoHarmOptions::smooth`]):
//! - the expected input noise energy is `c_h · v(x̄)`, `v` the noise law's variance at the
//!   local mean `x̄` and `c_h = Σ (δ − G_d)²` the high-pass' white-noise gain;
//! - a pixel is flat to the degree `φ = clamp((2 t − e_in)/t, 0, 1)`, `t = flat · c_h v`
//!   (1 where the input's detail is no more than noise, 0 where it is clearly signal);
//! - the blend weight is `w = 1 − φ (1 − min(1, e_in / e_out))`, smoothed by `G_s`, and the
//!   result `y = j + w (x − j)` (`j` the input, `x` the restoration);
//! - a second pass measures `e(y)` and, where it still exceeds `e_in`, scales `w` by
//!   `(e_in / e(y))²`.
//!
//! Nothing here is fitted: `flat` (2) is a statistical margin on a noise-only energy, `s` a
//! locality scale.

use crate::image::filter::gaussian_blur;
use crate::image::Plane;

/// Settings of the rule.
#[derive(Clone, Debug)]
pub struct NoHarmOptions {
    /// Apply it.
    pub enabled: bool,
    /// A region is flat while its input detail energy is below `flat ×` the noise's.
    pub flat: f32,
    /// Scale of the high-pass (Gaussian σ, px).
    pub detail: f32,
    /// Locality of the energies and of the blend weight (Gaussian σ, px).
    pub smooth: f32,
}

impl Default for NoHarmOptions {
    fn default() -> Self {
        Self { enabled: true, flat: 1.0, detail: 6.0, smooth: 8.0 }
    }
}

/// Where the rule fell back.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct NoHarmReport {
    /// Per channel: the share of pixels whose blend weight is below 0.5.
    pub fallback_fraction: Vec<f32>,
    /// Per channel: the bounding box `[x0, y0, x1, y1]` (exclusive end) of those pixels.
    pub fallback_box: Vec<Option<[usize; 4]>>,
}

impl NoHarmReport {
    /// One line per channel that fell back somewhere (for the log).
    pub fn describe(&self, names: &[String]) -> Vec<String> {
        let mut out = Vec::new();
        for (c, (f, b)) in self.fallback_fraction.iter().zip(&self.fallback_box).enumerate() {
            if let (Some([x0, y0, x1, y1]), true) = (b, *f > 0.0) {
                let name = names.get(c).map_or("?", |s| s.as_str());
                out.push(format!(
                    "channel {name}: restoration noisier than the input in flat regions; fell back towards the input on {:.1} % of the image, within x {x0}..{x1}, y {y0}..{y1}",
                    100.0 * f
                ));
            }
        }
        out
    }
}

/// A Gaussian blur of a `w × h` array with mirror boundaries (an image edge is no wrap).
fn blur_mirror(v: &[f32], w: usize, h: usize, s: f32) -> Vec<f32> {
    gaussian_blur(&Plane { width: w, height: h, data: v.to_vec() }, s as f64).data
}

/// `p − G_d * p`.
fn high_pass(p: &[f32], w: usize, h: usize, d: f32) -> Vec<f32> {
    let low = blur_mirror(p, w, h, d);
    p.iter().zip(&low).map(|(a, b)| a - b).collect()
}

/// `G_s * h(p)²`.
fn energy(p: &[f32], w: usize, h: usize, o: &NoHarmOptions) -> Vec<f32> {
    let hp: Vec<f32> = high_pass(p, w, h, o.detail).iter().map(|v| v * v).collect();
    blur_mirror(&hp, w, h, o.smooth)
}

/// The high-pass' white-noise gain `Σ (δ − G_d)²`.
fn high_pass_gain(d: f32) -> f32 {
    let n = 2 * (3.0 * d).ceil() as usize + 3;
    let mut p = vec![0.0f32; n * n];
    p[(n / 2) * n + n / 2] = 1.0;
    high_pass(&p, n, n, d).iter().map(|v| v * v).sum()
}

/// Applies the rule to `output` (linear, restored from `input`); `variance(c, x)` is the input
/// noise variance of channel `c` at linear level `x`.
pub fn apply(input: &[Plane], output: &mut [Plane], variance: &dyn Fn(usize, f32) -> f32, opts: &NoHarmOptions) -> NoHarmReport {
    let mut report = NoHarmReport::default();
    let ch = high_pass_gain(opts.detail);
    for (c, (j, x)) in input.iter().zip(output.iter_mut()).enumerate() {
        let (w, h) = (j.width, j.height);
        let e_in = energy(&j.data, w, h, opts);
        let e_out = energy(&x.data, w, h, opts);
        let mean = blur_mirror(&j.data, w, h, opts.smooth);
        let phi: Vec<f32> = e_in
            .iter()
            .zip(&mean)
            .map(|(e, m)| {
                let t = (opts.flat * ch * variance(c, *m)).max(1e-20);
                ((2.0 * t - e) / t).clamp(0.0, 1.0)
            })
            .collect();
        let raw: Vec<f32> = phi.iter().zip(e_in.iter().zip(&e_out)).map(|(f, (a, b))| 1.0 - f * (1.0 - (a / b.max(1e-20)).min(1.0))).collect();
        let mut wgt = blur_mirror(&raw, w, h, opts.smooth);
        let blend = |wgt: &[f32]| -> Vec<f32> { j.data.iter().zip(&x.data).zip(wgt).map(|((a, b), k)| a + k * (b - a)).collect() };
        let first = blend(&wgt);
        let e_first = energy(&first, w, h, opts);
        for ((k, f), (a, b)) in wgt.iter_mut().zip(&phi).zip(e_in.iter().zip(&e_first)) {
            if *f > 0.0 && b > a {
                *k *= (a / b).powi(2);
            }
        }
        x.data = blend(&wgt);
        let (mut n, mut bx) = (0usize, [usize::MAX, usize::MAX, 0, 0]);
        for (i, k) in wgt.iter().enumerate() {
            if *k < 0.5 {
                n += 1;
                let (px, py) = (i % w, i / w);
                bx = [bx[0].min(px), bx[1].min(py), bx[2].max(px + 1), bx[3].max(py + 1)];
            }
        }
        report.fallback_fraction.push(n as f32 / (w * h).max(1) as f32);
        report.fallback_box.push((n > 0).then_some(bx));
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn std_in(p: &Plane, x0: usize, x1: usize, y0: usize, y1: usize) -> f64 {
        let v: Vec<f64> = (y0..y1).flat_map(|y| (x0..x1).map(move |x| (x, y))).map(|(x, y)| p.get(x, y) as f64).collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|a| (a - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
    }

    /// A restoration that triples the noise of a flat patch is pulled back to at most the
    /// input's noise there; on a textured patch, where it sharpens, it is kept.
    #[test]
    fn flat_regions_never_get_noisier_and_texture_is_kept() {
        let (w, h) = (256, 96);
        let mut rng = Rng::new(8);
        let sigma = 0.01f32;
        let texture = |x: usize, y: usize| if x < 128 { 0.3 + 0.2 * ((x / 4 + y / 4) % 2) as f32 } else { 0.4 };
        let input = Plane::from_fn(w, h, |x, y| texture(x, y) + sigma * rng.normal() as f32);
        let restored = Plane::from_fn(w, h, |x, y| texture(x, y) + 3.0 * sigma * rng.normal() as f32);
        let mut out = vec![restored.clone()];
        let rep = apply(std::slice::from_ref(&input), &mut out, &|_, _| sigma * sigma, &NoHarmOptions::default());
        let (si, so) = (std_in(&input, 170, 250, 8, 88), std_in(&out[0], 170, 250, 8, 88));
        assert!(so <= si, "flat: out {so:.4} > in {si:.4}");
        // the checkerboard half keeps the restoration (its edges are signal, not noise)
        let moved = (8..88).flat_map(|y| (8..96).map(move |x| (x, y))).filter(|&(x, y)| (out[0].get(x, y) - restored.get(x, y)).abs() < 1e-6).count();
        assert!(moved as f32 > 0.9 * 80.0 * 88.0, "{moved}");
        let b = rep.fallback_box[0].unwrap();
        assert!(b[0] >= 100 && rep.fallback_fraction[0] > 0.3, "{rep:?}");
        assert!(rep.describe(&["R".into()])[0].contains("channel R"));
    }
}
