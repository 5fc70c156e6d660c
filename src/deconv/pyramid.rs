//! Scale space for the coarse-to-fine solve (docs/method.md §5): bicubic 2× downsampling of tile
//! images (periodic, like the tile domain) and of kernels (about their centre, renormalised to
//! sum 1), nearest-neighbour upsampling of results.
//!
//! Coarse pixel `i` covers fine pixels `2i, 2i+1`; its centre is fine coordinate `2i + 0.5`.

use crate::image::filter::keys_cubic;
use crate::image::Plane;

/// Keys cubic (a = −0.5) in `f32` ([`keys_cubic`]).
fn cubic(t: f32) -> f32 {
    keys_cubic(t as f64) as f32
}

/// Taps of the antialiased half-resolution filter at fine offsets `±0.5, ±1.5, ±2.5, ±3.5`
/// from the coarse centre (index 0 is offset −3.5), summing to 1.
fn half_taps() -> [f32; 8] {
    let mut t = [0.0; 8];
    for (i, v) in t.iter_mut().enumerate() {
        *v = cubic((i as f32 - 3.5) / 2.0);
    }
    let s: f32 = t.iter().sum();
    t.iter_mut().for_each(|v| *v /= s);
    t
}

/// Halves a periodic `w × h` array (`w`, `h` even).
pub fn downsample_periodic(v: &[f32], w: usize, h: usize) -> Vec<f32> {
    assert!(w % 2 == 0 && h % 2 == 0, "periodic downsampling needs even sizes");
    let taps = half_taps();
    let (cw, ch) = (w / 2, h / 2);
    // rows first: w -> cw
    let mut tmp = vec![0.0f32; cw * h];
    for y in 0..h {
        for cx in 0..cw {
            let mut acc = 0.0;
            for (i, t) in taps.iter().enumerate() {
                let x = (2 * cx as isize + i as isize - 3).rem_euclid(w as isize) as usize;
                acc += t * v[y * w + x];
            }
            tmp[y * cw + cx] = acc;
        }
    }
    let mut out = vec![0.0f32; cw * ch];
    for cy in 0..ch {
        for (i, t) in taps.iter().enumerate() {
            let y = (2 * cy as isize + i as isize - 3).rem_euclid(h as isize) as usize;
            for cx in 0..cw {
                out[cy * cw + cx] += t * tmp[y * cw + cx];
            }
        }
    }
    out
}

/// A 0/1 mask at half resolution: a coarse pixel keeps weight 1 only when the 4×4 fine pixels
/// its filter reads most from are all 1.
pub fn downsample_mask_periodic(m: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (cw, ch) = (w / 2, h / 2);
    let mut out = vec![1.0f32; cw * ch];
    for cy in 0..ch {
        for cx in 0..cw {
            let mut keep = 1.0f32;
            for dy in -1..3isize {
                for dx in -1..3isize {
                    let x = (2 * cx as isize + dx).rem_euclid(w as isize) as usize;
                    let y = (2 * cy as isize + dy).rem_euclid(h as isize) as usize;
                    keep = keep.min(m[y * w + x]);
                }
            }
            out[cy * cw + cx] = keep;
        }
    }
    out
}

/// Nearest-neighbour 2× upsampling of a `cw × ch` array to `2cw × 2ch`.
pub fn upsample_nearest(v: &[f32], cw: usize, ch: usize) -> Vec<f32> {
    let (w, h) = (2 * cw, 2 * ch);
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            out[y * w + x] = v[(y / 2) * cw + x / 2];
        }
    }
    out
}

/// The kernel at half resolution: odd size `≥ k/2`, same centre, sums to 1 (negative lobes of
/// the cubic are clipped).
pub fn downsample_kernel(k: &Plane) -> Plane {
    let c = (k.width as isize - 1) / 2;
    let cr = (c + 1) / 2 + 1; // coarse radius (covers the filter's reach)
    let kc = (2 * cr + 1) as usize;
    let mut taps = [0.0f32; 7];
    for (i, t) in taps.iter_mut().enumerate() {
        *t = cubic((i as f32 - 3.0) / 2.0);
    }
    let s: f32 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= s);
    let mut out = Plane::from_fn(kc, kc, |u, v| {
        let (du, dv) = (u as isize - cr, v as isize - cr);
        let mut acc = 0.0;
        for (j, ty) in taps.iter().enumerate() {
            for (i, tx) in taps.iter().enumerate() {
                let fx = c + 2 * du + i as isize - 3;
                let fy = c + 2 * dv + j as isize - 3;
                if fx >= 0 && fy >= 0 && (fx as usize) < k.width && (fy as usize) < k.height {
                    acc += tx * ty * k.get(fx as usize, fy as usize);
                }
            }
        }
        acc.max(0.0)
    });
    let s = out.sum() as f32;
    if s > 0.0 {
        out.scale(1.0 / s);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constants_and_ramps_survive_downsampling() {
        let (w, h) = (16, 12);
        let c = vec![0.7; w * h];
        assert!(downsample_periodic(&c, w, h).iter().all(|v| (v - 0.7).abs() < 1e-6));
        // a ramp in x sampled at 2i+0.5 (away from the periodic seam)
        let r: Vec<f32> = (0..w * h).map(|i| (i % w) as f32).collect();
        let d = downsample_periodic(&r, w, h);
        for cx in 2..6 {
            assert!((d[3 * (w / 2) + cx] - (2.0 * cx as f32 + 0.5)).abs() < 1e-4);
        }
        let up = upsample_nearest(&d, w / 2, h / 2);
        assert_eq!(up[5 * w + 7], d[2 * (w / 2) + 3]);
    }

    #[test]
    fn kernel_downsampling_keeps_centre_and_sum() {
        // a centred Gaussian of std 4 becomes a centred Gaussian of std ~2
        let k = Plane::from_fn(21, 21, |x, y| (-((x as f32 - 10.0).powi(2) + (y as f32 - 10.0).powi(2)) / 32.0).exp());
        let d = downsample_kernel(&k);
        assert!(d.width % 2 == 1);
        assert!((d.sum() - 1.0).abs() < 1e-5);
        let c = (d.width - 1) / 2;
        let (mut mx, mut var) = (0.0, 0.0);
        for v in 0..d.height {
            for u in 0..d.width {
                mx += d.get(u, v) * (u as f32 - c as f32);
                var += d.get(u, v) * (u as f32 - c as f32).powi(2);
            }
        }
        assert!(mx.abs() < 1e-4, "centre moved by {mx}");
        assert!((var.sqrt() - 2.0).abs() < 0.3, "std {}", var.sqrt());
    }

    #[test]
    fn mask_downsampling_is_conservative() {
        let (w, h) = (8, 8);
        let mut m = vec![1.0; 64];
        m[3 * 8 + 4] = 0.0;
        let d = downsample_mask_periodic(&m, w, h);
        assert_eq!(d[4 + 2], 0.0); // fine (4, 3) -> coarse (2, 1) in a 4-wide grid
        assert!(d.iter().filter(|v| **v == 0.0).count() >= 1 && d.iter().filter(|v| **v == 1.0).count() >= 8);
    }
}
