//! Issue 12's headline failure as one deterministic command:
//! `cargo run --release --example chromatic_failure -- OUT_DIR [flat|coloured]`.
//!
//! - **Lens:** the synthetic singlet ([`SyntheticLens`]) with a stronger chromatic shift than
//!   the benchmark's (`chromatic` 1.0 instead of 0.45, 31-px kernels): green is the sharpest
//!   channel, red and blue are defocused to discs of about 9 px radius on axis (about 13 px in
//!   the corners). 5 × 4 PSF grid. The **true** profile is used (no `estimate` run).
//! - **Scene:** `fundus(1024, 768)`, a procedural red-dominant fundus-like image (generated
//!   here, CC0; `data/scenes-extra/README.md`): smooth orange-red disc, a bright optic disc,
//!   darker vessels, dim green and blue.
//! - **Noise:** Poisson–Gaussian, full well 15 000 e⁻, read noise 4 e⁻ (linear full scale).
//! - **Restoration:** `deconv::deblur` with the true noise law (as the profile would carry it),
//!   linear output; the denoiser's noise model is the second argument (default `flat`).
//!
//! Prints PSNR (dB, linear values) of the blurred input and of the output, per channel the
//! error RMS of each relative to the sensor noise RMS, and the share of 32×32 blocks where the
//! output's error exceeds the input's. Writes `sharp.png`, `blurred.png`, `lensrig-<mode>.png`
//! (16-bit linear) to OUT_DIR.

use lensrig::deconv::noise::NoiseSource;
use lensrig::deconv::synth::SyntheticLens;
use lensrig::deconv::{deblur, DeconvOptions};
use lensrig::fsutil::Overwrite;
use lensrig::image::io::write_png16;
use lensrig::image::{Image, Plane, Transfer};
use lensrig::optics::forward::blur_channel;
use lensrig::profile::noise::NoiseLaw;
use std::path::Path;
use std::time::Instant;

const W: usize = 1024;
const H: usize = 768;
const FULL_WELL: f64 = 15_000.0;
const READ_E: f64 = 4.0;

/// A smooth fundus-like scene on the linear axis: `[R, G, B]`.
fn fundus(w: usize, h: usize) -> Vec<Plane> {
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

fn mse(a: &Plane, b: &Plane) -> f64 {
    a.data.iter().zip(&b.data).map(|(u, v)| ((u - v) as f64).powi(2)).sum::<f64>() / a.data.len().max(1) as f64
}

fn psnr(a: &[Plane], b: &[Plane]) -> f64 {
    let m = a.iter().zip(b).map(|(p, q)| mse(p, q)).sum::<f64>() / a.len() as f64;
    10.0 * (1.0 / m).log10()
}

/// Share of 32×32 blocks whose error (all channels) is larger in `out` than in `inp`, and the
/// worst ratio of the two errors.
fn worse_blocks(sharp: &[Plane], inp: &[Plane], out: &[Plane]) -> (f64, f64) {
    let (mut worse, mut total, mut worst) = (0usize, 0usize, 0.0f64);
    for by in (0..H).step_by(32) {
        for bx in (0..W).step_by(32) {
            let (mut ei, mut eo) = (0.0f64, 0.0f64);
            for c in 0..3 {
                for y in by..(by + 32).min(H) {
                    for x in bx..(bx + 32).min(W) {
                        ei += ((inp[c].get(x, y) - sharp[c].get(x, y)) as f64).powi(2);
                        eo += ((out[c].get(x, y) - sharp[c].get(x, y)) as f64).powi(2);
                    }
                }
            }
            total += 1;
            worse += usize::from(eo > ei);
            worst = worst.max(eo / ei.max(1e-30));
        }
    }
    (worse as f64 / total as f64, worst)
}

fn save(dir: &Path, name: &str, planes: &[Plane]) -> anyhow::Result<()> {
    let mut img = Image::new(planes.to_vec());
    img.transfer = Transfer::Linear;
    write_png16(&dir.join(name), &img, Overwrite::Replace)?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let (Some(out), mode) = (a.get(1), a.get(2).map_or("flat", String::as_str)) else {
        anyhow::bail!("usage: chromatic_failure OUT_DIR [flat|coloured]");
    };
    let dir = Path::new(out);
    std::fs::create_dir_all(dir)?;
    let sharp = fundus(W, H);
    let lens = SyntheticLens { chromatic: 1.0, ..SyntheticLens::new(31, 3) };
    let grid = lens.grid(W, H, 3, 5, 4);
    let mut rng = lensrig::rng::Rng::new(12);
    let clean: Vec<Plane> = sharp.iter().enumerate().map(|(c, p)| blur_channel(p, &grid, c)).collect();
    let noisy: Vec<Plane> = clean
        .iter()
        .map(|p| p.map(|v| v).data.iter().map(|v| (((rng.poisson(v.max(0.0) as f64 * FULL_WELL) + READ_E * rng.normal()) / FULL_WELL) as f32).clamp(0.0, 1.0)).collect())
        .zip(&clean)
        .map(|(d, p): (Vec<f32>, &Plane)| Plane::from_vec(p.width, p.height, d).expect("same size"))
        .collect();
    save(dir, "sharp.png", &sharp)?;
    save(dir, "blurred.png", &noisy)?;
    let law = NoiseLaw::new(vec![1.0 / FULL_WELL; 3], vec![READ_E / FULL_WELL; 3], "given");
    let opts = DeconvOptions { noise: NoiseSource::Law(law), ..DeconvOptions::default() };
    if mode != "flat" {
        anyhow::bail!("unknown mode '{mode}' (flat)");
    }
    let t = Instant::now();
    let (restored, report) = deblur(&noisy, &grid, &opts, &|_, _| {})?;
    let secs = t.elapsed().as_secs_f64();
    save(dir, &format!("lensrig-{mode}.png"), &restored)?;
    println!("mode {mode}: deblur {secs:.1} s (shared machine), λ {:?}", report.lambda);
    println!("PSNR (linear): blurred {:.2} dB, lensrig {:.2} dB", psnr(&sharp, &noisy), psnr(&sharp, &restored));
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let sensor = mse(&noisy[c], &clean[c]).sqrt();
        let (ein, eout) = (mse(&noisy[c], &sharp[c]).sqrt(), mse(&restored[c], &sharp[c]).sqrt());
        println!("{name}: sensor noise RMS {sensor:.2e}; error RMS / sensor noise: blurred {:.2}, lensrig {:.2}", ein / sensor, eout / sensor);
    }
    let (frac, worst) = worse_blocks(&sharp, &noisy, &restored);
    println!("32x32 blocks where the output is worse than the input: {:.1} % (worst error ratio {worst:.2})", 100.0 * frac);
    println!("no-harm fallback fraction per channel: {:?}", report.no_harm.fallback_fraction);
    Ok(())
}
