//! The deblur benchmark matrix (issue 12), partial: lenses × noise laws × scenes, one line per
//! cell with PSNR (dB, linear values, whole image) of the blurred input and of lensrig, and
//! lensrig's wall seconds (shared machine).
//!
//! `cargo run --release --example deblur_matrix -- [--lens L,…] [--noise N,…] [--scene S,…]
//! [--denoise-noise flat|coloured]`
//!
//! - lenses: `synth1` (the benchmark's synthetic singlet: chromatic 0.45, 21-px kernels, 4×4
//!   grid), `synth2` (chromatic 1.0, 31-px kernels, 5×4 grid: red and blue well out of focus),
//!   `sf11` (the real-design N-SF11 singlet, `../shared/data/lenses/sf11-singlet-25mm-f5.6`,
//!   1024 × 768 only; scenes are mirror-tiled or cropped to that size for it);
//! - noise: `gauss` (σ = 0.005), `pg15k` (Poisson–Gaussian 15 000 e⁻ / 4 e⁻), `pg3k`
//!   (3 000 e⁻ / 6 e⁻);
//! - scenes: the five photographs of `../shared/data/scenes/` (sRGB decoded to linear) and
//!   `fundus` ([`lensrig::deconv::synth::fundus`], 1024 × 768).
//!
//! **Split.** Tuning subset: `synth1 × gauss ×` the five photographs (the defaults were chosen
//! there); every other cell is held out. The `split` column says which. lensrig is given the
//! **true** PSFs and the true noise law; no peers (Richardson–Lucy, Wiener) and no estimated
//! profile yet.

use lensrig::deconv::noise::NoiseSource;
use lensrig::deconv::synth::SyntheticLens;
use lensrig::deconv::{deblur, DeconvOptions};
use lensrig::image::io::read_image;
use lensrig::image::{Plane, Transfer};
use lensrig::optics::forward::blur_channel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::noise::NoiseLaw;
use std::path::Path;
use std::time::Instant;

const PHOTOS: [&str; 5] = ["astronaut", "chelsea", "coffee", "hubble_deep_field", "rocket"];
const SF11: &str = "/work/shared/data/lenses/sf11-singlet-25mm-f5.6";

/// The scene's linear planes at its own size, or at `size` (mirror-tiled/cropped).
fn scene(name: &str, size: Option<(usize, usize)>) -> anyhow::Result<Vec<Plane>> {
    let planes = if name == "fundus" {
        lensrig::deconv::synth::fundus(1024, 768)
    } else {
        let mut img = read_image(&Path::new("/work/shared/data/scenes").join(format!("{name}.png")))?;
        img.transfer = Transfer::Srgb;
        img.to_linear().planes
    };
    Ok(match size {
        Some((w, h)) => planes.iter().map(|p| p.window_reflect(0, 0, w, h)).collect(),
        None => planes,
    })
}

/// The lens's PSF grid for a `w × h` image (and the size it needs, if fixed).
fn lens(name: &str, w: usize, h: usize) -> anyhow::Result<PsfGrid> {
    Ok(match name {
        "synth1" => SyntheticLens::new(21, 3).grid(w, h, 3, 4, 4),
        "synth2" => SyntheticLens { chromatic: 1.0, ..SyntheticLens::new(31, 3) }.grid(w, h, 3, 5, 4),
        "sf11" => lensrig::profile::Profile::load(Path::new(SF11))?.grid,
        l => anyhow::bail!("unknown lens '{l}' (synth1, synth2, sf11)"),
    })
}

/// (full well e⁻, read noise e⁻), or `None` for white Gaussian σ = 0.005.
fn noise_law(name: &str) -> anyhow::Result<(NoiseLaw, Option<(f64, f64)>)> {
    let pg = |fw: f64, rd: f64| (NoiseLaw::new(vec![1.0 / fw; 3], vec![rd / fw; 3], "given"), Some((fw, rd)));
    Ok(match name {
        "gauss" => (NoiseLaw::white(0.005, 3), None),
        "pg15k" => pg(15_000.0, 4.0),
        "pg3k" => pg(3_000.0, 6.0),
        n => anyhow::bail!("unknown noise '{n}' (gauss, pg15k, pg3k)"),
    })
}

fn psnr(a: &[Plane], b: &[Plane]) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for (p, q) in a.iter().zip(b) {
        se += p.data.iter().zip(&q.data).map(|(u, v)| ((u - v) as f64).powi(2)).sum::<f64>();
        n += p.data.len();
    }
    10.0 * (n as f64 / se.max(1e-30)).log10()
}

fn cell(l: &str, nz: &str, s: &str, coloured_noise: bool) -> anyhow::Result<String> {
    let size = (l == "sf11").then_some((1024, 768));
    let sharp = scene(s, size)?;
    let (w, h) = (sharp[0].width, sharp[0].height);
    let grid = lens(l, w, h)?;
    let (law, pg) = noise_law(nz)?;
    let mut rng = lensrig::rng::Rng::new(2013);
    let blurred: Vec<Plane> = sharp
        .iter()
        .enumerate()
        .map(|(c, p)| {
            let mut b = blur_channel(p, &grid, c);
            for v in b.data.iter_mut() {
                let x = match pg {
                    Some((fw, rd)) => (rng.poisson(v.max(0.0) as f64 * fw) + rd * rng.normal()) / fw,
                    None => *v as f64 + 0.005 * rng.normal(),
                };
                *v = (x as f32).clamp(0.0, 1.0);
            }
            b
        })
        .collect();
    let opts = DeconvOptions { noise: NoiseSource::Law(law), coloured_noise, ..DeconvOptions::default() };
    let t = Instant::now();
    let (out, _) = deblur(&blurred, &grid, &opts, &|_, _| {})?;
    let secs = t.elapsed().as_secs_f64();
    let split = if l == "synth1" && nz == "gauss" && s != "fundus" { "tuning" } else { "held out" };
    Ok(format!("| {l} | {nz} | {s} | {w}x{h} | {split} | {:.2} | {:.2} | {secs:.1} |", psnr(&sharp, &blurred), psnr(&sharp, &out)))
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let list = |flag: &str, all: &[&str]| -> Vec<String> {
        a.iter().position(|x| x == flag).and_then(|i| a.get(i + 1)).map_or_else(|| all.iter().map(|s| s.to_string()).collect(), |v| v.split(',').map(str::to_string).collect())
    };
    let lenses = list("--lens", &["synth1", "synth2", "sf11"]);
    let noises = list("--noise", &["gauss", "pg15k", "pg3k"]);
    let mut all_scenes: Vec<&str> = PHOTOS.to_vec();
    all_scenes.push("fundus");
    let scenes = list("--scene", &all_scenes);
    let coloured = list("--denoise-noise", &["flat"]).first().is_some_and(|m| m == "coloured");
    println!("denoiser noise model: {}", if coloured { "coloured" } else { "flat" });
    println!("| lens | noise | scene | size | split | blurred dB | lensrig dB | lensrig s |");
    println!("| --- | --- | --- | --- | --- | ---: | ---: | ---: |");
    for l in &lenses {
        for nz in &noises {
            for s in &scenes {
                println!("{}", cell(l, nz, s, coloured)?);
            }
        }
    }
    Ok(())
}
