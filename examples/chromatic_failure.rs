//! Issue 12's headline failure as one deterministic command:
//! `cargo run --release --example chromatic_failure -- OUT_DIR [flat|coloured]`.
//!
//! - **Lens:** the synthetic singlet ([`SyntheticLens`]) with a stronger chromatic shift than
//!   the benchmark's (`chromatic` 1.0 instead of 0.45, 31-px kernels): green is the sharpest
//!   channel, red and blue are defocused to discs of about 9 px radius on axis (about 13 px in
//!   the corners). 5 × 4 PSF grid. The **true** profile is used (no `estimate` run).
//! - **Scene:** [`lensrig::deconv::synth::fundus`] at 1024 × 768, a procedural red-dominant fundus-like image (generated
//!   here, CC0; `data/scenes-extra/README.md`): smooth orange-red disc, a bright optic disc,
//!   darker vessels, dim green and blue.
//! - **Noise:** Poisson–Gaussian, full well 15 000 e⁻, read noise 4 e⁻ (linear full scale).
//! - **Restoration:** `deconv::deblur` with the true noise law (as the profile would carry it),
//!   linear output; the denoiser's noise model is the second argument: `flat` (`denoise × σ_c`,
//!   the former default) or `coloured` (propagated through the solver, [`lensrig::deconv::coloured`]).
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
    let sharp = lensrig::deconv::synth::fundus(W, H);
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
    let coloured_noise = match mode {
        "flat" => false,
        "coloured" => true,
        m => anyhow::bail!("unknown mode '{m}' (flat|coloured)"),
    };
    let opts = DeconvOptions { noise: NoiseSource::Law(law), coloured_noise, ..DeconvOptions::default() };
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
