//! The deblur benchmark matrix (issue 12): lenses × noise laws × scenes, one row per cell with
//! PSNR (dB, linear values clipped to [0, 1], whole image) of the blurred input, of the peers
//! (Richardson–Lucy and Wiener with the TRUE PSFs), of lensrig with the true profile and with a
//! profile estimated from a calibration pair, SSIM of lensrig (luminance), and seconds.
//!
//! `cargo run --release --example deblur_matrix -- [--lens L,…] [--noise N,…] [--scene S,…]
//! [--denoise-noise flat|coloured] [--no-estimate]`, or
//! `cargo run --release --example deblur_matrix -- scenes DIR` to write the procedural scenes.
//! `… -- probe L N S [options]`: one cell's error of lensrig (the options given), the blurred
//! input and the cell's best Wiener balance, split by channel, region (black, edges, flat),
//! field position (outer fifth of the frame / inner part) and frequency band. Experiment
//! overrides of lensrig's options: `--set key=value,…` with `denoise`, `kappa` (the solver's κ
//! with the denoiser), `kappa7` (κ without it), `tile`, `no_harm` (on/off), `iterations`,
//! `sure` (on/off: [`DeconvOptions::coloured_sure`]), `response` (`pilot`/`excess`:
//! [`DeconvOptions::coloured_response`]), `lawdata` (on/off: the variance-weighted
//! data term, [`DeconvOptions::law_data_weight`]), `texture` (on/off: the texture return,
//! [`DeconvOptions::texture_return`]), `rwp` / `rwe` (the reweighted-ℓ1 exponent and ε),
//! `steps` (residual steps), `thr` (the denoiser's hard threshold).
//!
//! Every cell is a 1024 × 768 sensor (one profile per lens, as a camera has): the photographs
//! are mirror-tiled or cropped to that size ([`lensrig::image::Plane::window_reflect`]).
//!
//! - lenses: `synth1` (the synthetic singlet, chromatic 0.45, 21-px kernels, 4×4 grid), `synth2`
//!   (chromatic 1.0, 31-px kernels, 5×4 grid), and real designs not made by lensrig
//!   (`../shared/data/lenses/`): `sf11` (N-SF11 singlet, 63 px), `achromat` (35 px), `lac9`
//!   (91 px);
//! - noise: `gauss` (σ = 0.005), `pg15k` (Poisson–Gaussian 15 000 e⁻ / 4 e⁻), `pg3k`
//!   (3 000 e⁻ / 6 e⁻), all clipped to [0, 1];
//! - scenes: the five photographs of `../shared/data/scenes/` (sRGB decoded to linear), `fundus`,
//!   `dark` and `lineart` (procedural, CC0: [`lensrig::deconv::synth`], data/scenes-extra/).
//!
//! **Split.** Tuning subset: `synth1 × gauss ×` the five photographs; every other cell is held
//! out (the `split` column).
//!
//! **Peers** ([`lensrig::deconv::peers`]) get the true PSFs and an oracle choice that favours
//! them: Richardson–Lucy iterations from {10, 30, 100} (100 is run only when 30 beat 10; each run continues the last), Wiener
//! balance from {1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1}, each chosen by PSNR against the
//! sharp scene. lensrig gets the true noise law; its estimated profile comes from
//! [`lensrig::estimate::estimate`] (default options) on one calibration pair per lens × noise
//! (noise target through the lens, exposure 0.75, the cell's noise law), reused across scenes.
//!
//! **Peer cache.** The peers are the slow part and do not depend on lensrig's settings: their
//! PSNRs (and the blurred input's) are kept per cell in `--peer-cache PATH` (default
//! `target/deblur_matrix_peers.tsv`), keyed by [`PEER_VERSION`], lens, noise, scene, noise
//! seed and sensor size, so a second run in another denoiser mode only runs lensrig. Bump
//! [`PEER_VERSION`] when the peers, the forward model or the scenes change. Progress and an
//! ETA per cell go to stderr.

use lensrig::deconv::noise::NoiseSource;
use lensrig::deconv::peers::{richardson_lucy, wiener_tiled, FieldBlur};
use lensrig::deconv::quality::{psnr, ssim_luma};
use lensrig::deconv::synth::SyntheticLens;
use lensrig::deconv::{deblur, DeconvOptions};
use lensrig::estimate::{estimate, EstimateOptions};
use lensrig::fsutil::Overwrite;
use lensrig::image::io::{read_image, write_png8};
use lensrig::image::{Image, Plane, Transfer};
use lensrig::optics::forward::blur_channel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::noise::NoiseLaw;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

const PHOTOS: [&str; 5] = ["astronaut", "chelsea", "coffee", "hubble_deep_field", "rocket"];
const EXTRA: [&str; 3] = ["fundus", "dark", "lineart"];
const LENSES: &str = "/work/shared/data/lenses";
const SENSOR: (usize, usize) = (1024, 768);
const RL_ITERATIONS: [usize; 3] = [10, 30, 100];
const WIENER_BALANCE: [f32; 7] = [1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1];
/// lensrig's options other than the noise and the denoiser's noise model (`--cross-weight`,
/// `--stationary-noise`, `--coloured-windows N`, `--positivity on|off` for experiments; the defaults otherwise).
static BASE: std::sync::OnceLock<DeconvOptions> = std::sync::OnceLock::new();
/// Seed of every cell's noise.
const SEED: u64 = 2013;
/// Version of the peer code and of the cell's input (scene, forward model, noise sampler):
/// part of every cache key.
const PEER_VERSION: &str = "peers-v2:rl10-30-100-nonpos-out:wiener7:fieldblur:seed-noise-v1";

/// The peers' figures of one cell: blurred PSNR, RL PSNR and iterations, Wiener PSNR and balance.
#[derive(Clone, Copy)]
struct Peers {
    blurred: f64,
    rl: f64,
    its: usize,
    wiener: f64,
    balance: f32,
}

/// The peer cache: one line per cell, `key \t blurred \t rl \t its \t wiener \t balance`.
struct PeerCache {
    path: std::path::PathBuf,
    rows: HashMap<String, Peers>,
}

impl PeerCache {
    fn parse(text: &str) -> HashMap<String, Peers> {
        text.lines()
            .filter_map(|l| {
                let f: Vec<&str> = l.split('\t').collect();
                let p = Peers { blurred: f.get(1)?.parse().ok()?, rl: f.get(2)?.parse().ok()?, its: f.get(3)?.parse().ok()?, wiener: f.get(4)?.parse().ok()?, balance: f.get(5)?.parse().ok()? };
                [p.blurred, p.rl, p.wiener].iter().all(|v| v.is_finite()).then(|| (f[0].to_string(), p))
            })
            .collect()
    }

    fn load(path: &Path) -> Self {
        let rows = std::fs::read_to_string(path).map(|t| Self::parse(&t)).unwrap_or_default();
        Self { path: path.to_path_buf(), rows }
    }

    fn key(l: &str, nz: &str, s: &str) -> String {
        let (w, h) = SENSOR;
        format!("{PEER_VERSION}|{l}|{nz}|{s}|{SEED}|{w}x{h}")
    }

    /// Adds a cell and rewrites the file atomically (merged with what another run wrote meanwhile).
    fn insert(&mut self, key: String, p: Peers) -> anyhow::Result<()> {
        let mut rows = std::fs::read_to_string(&self.path).map(|t| Self::parse(&t)).unwrap_or_default();
        rows.extend(self.rows.drain());
        rows.insert(key, p);
        let mut keys: Vec<&String> = rows.keys().collect();
        keys.sort();
        let text: String = keys.iter().map(|k| {
            let p = rows[*k];
            format!("{k}\t{}\t{}\t{}\t{}\t{}\n", p.blurred, p.rl, p.its, p.wiener, p.balance)
        }).collect();
        if let Some(d) = self.path.parent() {
            std::fs::create_dir_all(d)?;
        }
        lensrig::fsutil::write_atomic(&self.path, text.as_bytes(), Overwrite::Replace)?;
        self.rows = rows;
        Ok(())
    }
}

/// The scene's linear planes on the sensor (mirror-tiled/cropped).
fn scene(name: &str) -> anyhow::Result<Vec<Plane>> {
    let (w, h) = SENSOR;
    let planes = match name {
        "fundus" => lensrig::deconv::synth::fundus(w, h),
        "dark" => lensrig::deconv::synth::dark_room(w, h),
        "lineart" => lensrig::deconv::synth::line_art(w, h),
        _ => {
            let mut img = read_image(&Path::new("/work/shared/data/scenes").join(format!("{name}.png")))?;
            img.transfer = Transfer::Srgb;
            img.to_linear().planes
        }
    };
    Ok(planes.iter().map(|p| p.window_reflect(0, 0, w, h)).collect())
}

/// The lens's true PSF grid on the sensor.
fn lens(name: &str) -> anyhow::Result<PsfGrid> {
    let (w, h) = SENSOR;
    let real = |dir: &str| -> anyhow::Result<PsfGrid> { Ok(lensrig::profile::Profile::load(&Path::new(LENSES).join(dir))?.grid) };
    Ok(match name {
        "synth1" => SyntheticLens::new(21, 3).grid(w, h, 3, 4, 4),
        "synth2" => SyntheticLens { chromatic: 1.0, ..SyntheticLens::new(31, 3) }.grid(w, h, 3, 5, 4),
        "sf11" => real("sf11-singlet-25mm-f5.6")?,
        "achromat" => real("achromat-f4")?,
        "lac9" => real("lac9-singlet-stop-behind-f6.3")?,
        l => anyhow::bail!("unknown lens '{l}' (synth1, synth2, sf11, achromat, lac9)"),
    })
}

/// The noise law lensrig is told, and the sampler's (full well e⁻, read noise e⁻) or `None`
/// for white Gaussian σ = 0.005.
fn noise_law(name: &str) -> anyhow::Result<(NoiseLaw, Option<(f64, f64)>)> {
    let pg = |fw: f64, rd: f64| (NoiseLaw::new(vec![1.0 / fw; 3], vec![rd / fw; 3], "given"), Some((fw, rd)));
    Ok(match name {
        "gauss" => (NoiseLaw::white(0.005, 3), None),
        "pg15k" => pg(15_000.0, 4.0),
        "pg3k" => pg(3_000.0, 6.0),
        n => anyhow::bail!("unknown noise '{n}' (gauss, pg15k, pg3k)"),
    })
}

/// `planes` with the noise law's samples added, clipped to [0, 1].
fn add_noise(planes: &mut [Plane], pg: Option<(f64, f64)>, rng: &mut Rng) {
    for p in planes.iter_mut() {
        for v in p.data.iter_mut() {
            let x = match pg {
                Some((fw, rd)) => (rng.poisson(v.max(0.0) as f64 * fw) + rd * rng.normal()) / fw,
                None => *v as f64 + 0.005 * rng.normal(),
            };
            *v = (x as f32).clamp(0.0, 1.0);
        }
    }
}

fn blurred_noisy(sharp: &[Plane], grid: &PsfGrid, pg: Option<(f64, f64)>, seed: u64) -> Vec<Plane> {
    let mut b: Vec<Plane> = sharp.iter().enumerate().map(|(c, p)| blur_channel(p, grid, c)).collect();
    add_noise(&mut b, pg, &mut Rng::new(seed));
    b
}

/// lensrig's profile estimated from one calibration pair through `grid` with the noise law.
fn estimated_grid(grid: &PsfGrid, pg: Option<(f64, f64)>) -> anyhow::Result<PsfGrid> {
    let (w, h) = SENSOR;
    let spec = TargetSpec::new("A4", 300, 4, 7)?;
    let target = render_noise_scene(&spec, w, h, 1.6, 7.0, 5.0).map(|v| 0.75 * v);
    let sharp = vec![target; 3];
    let open = blurred_noisy(&sharp, grid, pg, 31);
    let mut pin = sharp.clone();
    add_noise(&mut pin, pg, &mut Rng::new(32));
    let est = estimate(&Image::new(open), &Image::new(pin), &EstimateOptions::default())?;
    Ok(est.profile.grid)
}

fn clipped(p: &[Plane]) -> Vec<Plane> {
    p.iter().map(|q| q.map(|v| v.clamp(0.0, 1.0))).collect()
}

/// Best Richardson–Lucy PSNR and its iteration count (100 only when 30 beat 10; each run
/// continues the previous one).
fn rl_peer(sharp: &[Plane], blurred: &[Plane], grid: &PsfGrid) -> (f64, usize) {
    let ops: Vec<FieldBlur> = (0..blurred.len()).map(|c| FieldBlur::new(grid, c, blurred[c].width, blurred[c].height)).collect();
    let run = |from: Option<&[Plane]>, its: usize| -> Vec<Plane> { blurred.iter().zip(&ops).enumerate().map(|(c, (b, op))| richardson_lucy(b, op, from.map(|f| &f[c]), &[its]).remove(0)).collect() };
    let x10 = run(None, RL_ITERATIONS[0]);
    let x30 = run(Some(&x10), RL_ITERATIONS[1] - RL_ITERATIONS[0]);
    let (p10, p30) = (psnr(sharp, &clipped(&x10)), psnr(sharp, &clipped(&x30)));
    if p10 >= p30 {
        return (p10, 10);
    }
    let p100 = psnr(sharp, &clipped(&run(Some(&x30), RL_ITERATIONS[2] - RL_ITERATIONS[1])));
    if p100 > p30 {
        (p100, 100)
    } else {
        (p30, 30)
    }
}

/// Best tile-wise Wiener PSNR and its balance.
fn wiener_peer(sharp: &[Plane], blurred: &[Plane], grid: &PsfGrid) -> (f64, f32) {
    let runs: Vec<Vec<Plane>> = blurred.iter().enumerate().map(|(c, b)| wiener_tiled(b, grid, c, &WIENER_BALANCE)).collect();
    WIENER_BALANCE
        .iter()
        .enumerate()
        .map(|(i, &b)| (psnr(sharp, &clipped(&runs.iter().map(|r| r[i].clone()).collect::<Vec<_>>())), b))
        .fold((f64::NEG_INFINITY, 0.0), |a, x| if x.0 > a.0 { x } else { a })
}

/// CPU seconds of this process so far (Linux `/proc/self/stat`, USER_HZ = 100), 0 elsewhere.
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let Some(i) = s.rfind(')') else { return 0.0 };
    let f: Vec<&str> = s[i + 2..].split_whitespace().collect();
    let t = |k: usize| f.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (t(11) + t(12)) / 100.0
}

/// lensrig's result (clipped), wall and CPU seconds.
fn run_lensrig(blurred: &[Plane], grid: &PsfGrid, law: &NoiseLaw, coloured: bool) -> anyhow::Result<(Vec<Plane>, f64, f64)> {
    let base = BASE.get().cloned().unwrap_or_default();
    let opts = DeconvOptions { noise: NoiseSource::Law(law.clone()), coloured_noise: coloured, ..base };
    let (t, c) = (Instant::now(), cpu_seconds());
    let (out, _) = deblur(blurred, grid, &opts, &|_, _| {})?;
    Ok((clipped(&out), t.elapsed().as_secs_f64(), cpu_seconds() - c))
}

/// The peers' figures of a cell, from the cache or run (and cached).
fn cached_peers(l: &str, nz: &str, s: &str, sharp: &[Plane], blurred: &[Plane], grid: &PsfGrid, cache: &mut PeerCache) -> anyhow::Result<Peers> {
    let key = PeerCache::key(l, nz, s);
    Ok(match cache.rows.get(&key) {
        Some(p) => *p,
        None => {
            let (rl, its) = rl_peer(sharp, blurred, grid);
            let (wiener, balance) = wiener_peer(sharp, blurred, grid);
            let p = Peers { blurred: psnr(sharp, &clipped(blurred)), rl, its, wiener, balance };
            cache.insert(key, p)?;
            p
        }
    })
}

/// One table row (and the numbers the summary needs: split held out, lensrig − blurred, margin).
fn cell(l: &str, nz: &str, s: &str, grid: &PsfGrid, est: Option<&PsfGrid>, coloured: bool, cache: &mut PeerCache) -> anyhow::Result<(String, bool, f64, f64)> {
    let sharp = scene(s)?;
    let (law, pg) = noise_law(nz)?;
    let blurred = blurred_noisy(&sharp, grid, pg, SEED);
    let peers = cached_peers(l, nz, s, &sharp, &blurred, grid, cache)?;
    if est.is_none() && std::env::args().any(|x| x == "--peers-only") {
        return Ok((String::new(), false, 0.0, 0.0));
    }
    let (pr, its, pw, bal) = (peers.rl, peers.its, peers.wiener, peers.balance);
    let (out, wall, cpu) = run_lensrig(&blurred, grid, &law, coloured)?;
    let est_db = match est {
        Some(g) => format!("{:.2}", psnr(&sharp, &run_lensrig(&blurred, g, &law, coloured)?.0)),
        None => "–".to_string(),
    };
    let held_out = !(l == "synth1" && nz == "gauss" && PHOTOS.contains(&s));
    let (pb, pl) = (peers.blurred, psnr(&sharp, &out));
    let margin = pl - pr.max(pw);
    let (w, h) = SENSOR;
    let row = format!(
        "| {l} | {nz} | {s} | {w}x{h} | {} | {pb:.2} | {pr:.2} | {pw:.2} | {pl:.2} | {est_db} | {margin:+.2} | {:.3} | {wall:.1} / {cpu:.1} | {its} / {bal:.0e} |",
        if held_out { "held out" } else { "tuning" },
        ssim_luma(&sharp, &out)
    );
    Ok((row, held_out, pl - pb, margin))
}

/// Squared error of `out` against `sharp` (both clipped to [0, 1]) per channel, summed over the
/// `bright` pixels and over the rest, as shares of the whole image's MSE, plus the mean signed
/// error in each region.
fn region_errors(sharp: &[Plane], out: &[Plane], bright: &[bool]) -> Vec<[f64; 4]> {
    let n = bright.len() as f64;
    sharp
        .iter()
        .zip(out)
        .map(|(s, o)| {
            let mut e = [0.0; 4];
            for ((a, b), &m) in s.data.iter().zip(&o.data).zip(bright) {
                let d = (b.clamp(0.0, 1.0) - a.clamp(0.0, 1.0)) as f64;
                let i = if m { 0 } else { 1 };
                e[i] += d * d / n;
                e[i + 2] += d;
            }
            let nb = bright.iter().filter(|m| **m).count().max(1) as f64;
            e[2] /= nb;
            e[3] /= (n - nb).max(1.0);
            e
        })
        .collect()
}

/// The MSE of `out` against `sharp` (clipped to [0, 1]) split by frequency: the error smoothed
/// by a Gaussian of 2 px (below ≈ 0.08 cycles/px: shading, lost contrast of large structures)
/// and the rest (texture, edges and noise), summed over the channels.
fn band_errors(sharp: &[Plane], out: &[Plane]) -> (f64, f64) {
    let (mut lo, mut hi, mut n) = (0.0, 0.0, 0.0);
    for (s, o) in sharp.iter().zip(out) {
        let e = Plane::from_fn(s.width, s.height, |x, y| o.get(x, y).clamp(0.0, 1.0) - s.get(x, y).clamp(0.0, 1.0));
        let low = lensrig::image::filter::gaussian_blur(&e, 2.0);
        for (a, b) in e.data.iter().zip(&low.data) {
            lo += (*b as f64).powi(2);
            hi += ((a - b) as f64).powi(2);
        }
        n += e.data.len() as f64;
    }
    (lo / n, hi / n)
}

/// `regions L N S`: the error of lensrig (defaults, flat denoiser, stationary noise level,
/// cross-channel term off, positivity on/off, denoiser off at κ = 7, and the defaults on the
/// noise-free blurred input: what the regularisation and the denoiser lose without noise) and of
/// Richardson–Lucy (100 iterations) split into bright objects (the sharp scene's
/// luminance, Gaussian-smoothed over 3 px, above 2 × its median) and the background, per
/// channel, and into a low and a high frequency band ([`band_errors`]).
fn regions(l: &str, nz: &str, s: &str) -> anyhow::Result<()> {
    let sharp = scene(s)?;
    let grid = lens(l)?;
    let (law, pg) = noise_law(nz)?;
    let blurred = blurred_noisy(&sharp, &grid, pg, SEED);
    let luma = Plane::sum_of(&sharp);
    let smooth = lensrig::image::filter::gaussian_blur(&luma, 3.0);
    let mut sorted = smooth.data.clone();
    sorted.sort_by(f32::total_cmp);
    let thr = 2.0 * sorted[sorted.len() / 2];
    let bright: Vec<bool> = smooth.data.iter().map(|v| *v > thr).collect();
    println!("{l} × {nz} × {s}: bright region {:.1} % of pixels (smoothed luminance > {thr:.4}); MSE share bright / background and mean signed error bright / background, per channel R, G, B; PSNR", 100.0 * bright.iter().filter(|m| **m).count() as f64 / bright.len() as f64);
    let ops: Vec<FieldBlur> = (0..3).map(|c| FieldBlur::new(&grid, c, blurred[c].width, blurred[c].height)).collect();
    let rl: Vec<Plane> = blurred.iter().zip(&ops).map(|(b, op)| richardson_lucy(b, op, None, &[100]).remove(0)).collect();
    let base = DeconvOptions { noise: NoiseSource::Law(law.clone()), ..DeconvOptions::default() };
    let variants: Vec<(&str, DeconvOptions)> = vec![
        ("lensrig (defaults)", base.clone()),
        ("lensrig, flat denoiser", DeconvOptions { coloured_noise: false, ..base.clone() }),
        ("lensrig, stationary noise", DeconvOptions { local_noise: false, ..base.clone() }),
        ("lensrig, cross-channel off", DeconvOptions { cross_weight: 0.0, ..base.clone() }),
        ("lensrig, positivity toggled", DeconvOptions { positivity: !base.positivity, ..base.clone() }),
        ("lensrig, denoiser off (κ = 7)", DeconvOptions { denoise: 0.0, ..base.clone() }),
    ];
    let mut outs: Vec<(String, Vec<Plane>)> = vec![("blurred".into(), blurred.clone()), ("RL 100".into(), rl)];
    for (name, o) in variants {
        outs.push((name.to_string(), deblur(&blurred, &grid, &o, &|_, _| {})?.0));
    }
    // the same law and settings on the noise-free blurred input (what is lost without noise)
    let clean: Vec<Plane> = sharp.iter().enumerate().map(|(c, p)| blur_channel(p, &grid, c).map(|v| v.clamp(0.0, 1.0))).collect();
    outs.push(("lensrig (defaults), noise-free input".into(), deblur(&clean, &grid, &base, &|_, _| {})?.0));
    for (name, o) in &outs {
        let e = region_errors(&sharp, o, &bright);
        let f = |i: usize| e.iter().map(|c| format!("{:.2e}", c[i])).collect::<Vec<_>>().join(" ");
        let (lo, hi) = band_errors(&sharp, o);
        println!("{name:38} PSNR {:.2} | MSE bright {} | background {} | bias bright {} | background {} | MSE low {lo:.2e} high {hi:.2e}", psnr(&sharp, &clipped(o)), f(0), f(1), f(2), f(3));
    }
    Ok(())
}

/// MSE of `out` against `sharp` (clipped to [0, 1]) per channel in the pixels where `sel` holds,
/// as a share of the whole image's MSE (so the parts of a partition add up).
fn masked_mse(sharp: &[Plane], out: &[Plane], sel: &[bool]) -> Vec<f64> {
    let n = sel.len() as f64;
    sharp.iter().zip(out).map(|(s, o)| s.data.iter().zip(&o.data).zip(sel).filter(|(_, m)| **m).map(|((a, b), _)| ((b.clamp(0.0, 1.0) - a.clamp(0.0, 1.0)) as f64).powi(2) / n).sum()).collect()
}

/// `probe L N S`: lensrig (the options of the command line) against the blurred input and the
/// cell's best Wiener balance, the MSE split by channel, by region (black: sharp luminance
/// < 0.01; edges: the sharp luminance's gradient, smoothed over 2 px, above 4× its median;
/// flat: the rest), by field position (the outer fifth of the frame against the inner part) and by
/// frequency band ([`band_errors`]).
fn probe(l: &str, nz: &str, s: &str) -> anyhow::Result<()> {
    let sharp = scene(s)?;
    let grid = lens(l)?;
    let (law, pg) = noise_law(nz)?;
    let blurred = blurred_noisy(&sharp, &grid, pg, SEED);
    let (w, h) = SENSOR;
    let luma = Plane::sum_of(&sharp).map(|v| v / 3.0);
    let gm = Plane::from_fn(w, h, |x, y| {
        let (xa, xb, ya, yb) = (x.saturating_sub(1), (x + 1).min(w - 1), y.saturating_sub(1), (y + 1).min(h - 1));
        ((luma.get(xb, y) - luma.get(xa, y)).powi(2) + (luma.get(x, yb) - luma.get(x, ya)).powi(2)).sqrt()
    });
    let gm = lensrig::image::filter::gaussian_blur(&gm, 2.0);
    let mut sorted = gm.data.clone();
    sorted.sort_by(f32::total_cmp);
    let thr = 4.0 * sorted[sorted.len() / 2];
    let black: Vec<bool> = luma.data.iter().map(|v| *v < 0.01).collect();
    let edge: Vec<bool> = gm.data.iter().zip(&black).map(|(g, b)| !b && *g > thr).collect();
    let flat: Vec<bool> = black.iter().zip(&edge).map(|(b, e)| !b && !e).collect();
    let outer: Vec<bool> = (0..w * h).map(|i| {
        let (x, y) = (i % w, i / w);
        x < w / 5 || x >= w - w / 5 || y < h / 5 || y >= h - h / 5
    }).collect();
    let inner: Vec<bool> = outer.iter().map(|o| !o).collect();
    let share = |m: &[bool]| 100.0 * m.iter().filter(|v| **v).count() as f64 / m.len() as f64;
    println!("{l} × {nz} × {s}: black {:.1} %, edges {:.1} %, flat {:.1} %, outer frame {:.1} % of pixels; MSE (share of the image's) per channel R G B", share(&black), share(&edge), share(&flat), share(&outer));
    let bal = PeerCache::load(Path::new("/work/cache/peers_m14.tsv")).rows.get(&PeerCache::key(l, nz, s)).map_or(0.01, |p| p.balance);
    let wiener: Vec<Plane> = blurred.iter().enumerate().map(|(c, b)| wiener_tiled(b, &grid, c, &[bal]).remove(0)).collect();
    let (out, wall, cpu) = run_lensrig(&blurred, &grid, &law, BASE.get().map_or(true, |b| b.coloured_noise))?;
    for (name, o) in [("blurred", &blurred), (&*format!("Wiener b={bal:.0e}"), &wiener), (&*format!("lensrig ({wall:.1} s / {cpu:.1} CPU-s)"), &out)] {
        let f = |m: &[bool]| masked_mse(&sharp, o, m).iter().map(|v| format!("{v:.2e}")).collect::<Vec<_>>().join(" ");
        let (lo, hi) = band_errors(&sharp, o);
        let per: Vec<String> = (0..3).map(|c| format!("{:.2}", psnr(&sharp[c..c + 1], &clipped(&o[c..c + 1])))).collect();
        println!("{name:28} PSNR {:.2} ({}) | black {} | edges {} | flat {} | outer {} | inner {} | low {lo:.2e} high {hi:.2e}", psnr(&sharp, &clipped(o)), per.join("/"), f(&black), f(&edge), f(&flat), f(&outer), f(&inner));
    }
    Ok(())
}

fn write_scenes(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let (w, h) = SENSOR;
    for (name, planes) in [("dark", lensrig::deconv::synth::dark_room(w, h)), ("lineart", lensrig::deconv::synth::line_art(w, h))] {
        let mut img = Image::new(planes);
        img.transfer = Transfer::Linear;
        write_png8(&dir.join(format!("{name}.png")), &img.encoded(Transfer::Srgb), Overwrite::Replace)?;
        println!("wrote {}", dir.join(format!("{name}.png")).display());
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    if a.first().is_some_and(|x| x == "scenes") {
        return write_scenes(Path::new(a.get(1).map_or("data/scenes-extra", |s| s.as_str())));
    }
    if a.first().is_some_and(|x| x == "tilerr") {
        for l in ["synth1", "synth2", "sf11", "achromat", "lac9"] {
            let g = lens(l)?;
            let overlap = DeconvOptions::default().overlap;
            let error = |c: usize| lensrig::deconv::tiles::tile_kernel_error(&g, SENSOR.0, SENSOR.1, c, overlap);
            let row: Vec<String> = [32, 48, 64, 80, 96, 128, 160, 192, 256].iter().map(|&c| format!("{c}:{:.3}", error(c))).collect();
            println!("{l} ({}x{} k{}): {}", g.columns, g.rows, g.kernel_size, row.join(" "));
            // the middle grid row's kernels: centroid offset (px) and RMS radius
            let middle = g.columns * (g.rows / 2);
            for (c, ks) in g.kernels.iter().enumerate() {
                let r: Vec<String> = ks[middle..middle + g.columns]
                    .iter()
                    .map(|k| {
                        let (x, y) = lensrig::optics::lens::centroid(k);
                        format!("({x:.2},{y:.2} s{:.2})", lensrig::deconv::second_moment(k).sqrt())
                    })
                    .collect();
                println!("   ch{c} middle row: {}", r.join(" "));
            }
        }
        return Ok(());
    }
    if a.first().is_some_and(|x| x == "regions") && a.len() >= 4 {
        return regions(&a[1], &a[2], &a[3]);
    }
    let probe_cell = (a.first().is_some_and(|x| x == "probe") && a.len() >= 4).then(|| (a[1].clone(), a[2].clone(), a[3].clone()));
    let list = |flag: &str, all: &[&str]| -> Vec<String> {
        a.iter().position(|x| x == flag).and_then(|i| a.get(i + 1)).map_or_else(|| all.iter().map(|s| s.to_string()).collect(), |v| v.split(',').map(str::to_string).collect())
    };
    let lenses = list("--lens", &["synth1", "synth2", "sf11"]);
    let noises = list("--noise", &["pg15k", "gauss", "pg3k"]);
    let all_scenes: Vec<&str> = PHOTOS.iter().chain(&EXTRA).copied().collect();
    let scenes = list("--scene", &all_scenes);
    let default_mode = if DeconvOptions::default().coloured_noise { "coloured" } else { "flat" };
    let coloured = list("--denoise-noise", &[default_mode]).first().is_some_and(|m| m == "coloured");
    let with_estimate = !a.iter().any(|x| x == "--no-estimate");
    let cross_weight: f32 = list("--cross-weight", &["3"])[0].parse()?;
    let local_noise = !a.iter().any(|x| x == "--stationary-noise");
    let coloured_windows: usize = list("--coloured-windows", &["3"])[0].parse()?;
    let positivity = match list("--positivity", &["default"])[0].as_str() {
        "on" => true,
        "off" => false,
        _ => DeconvOptions::default().positivity,
    };
    let mut base = DeconvOptions { cross_weight, local_noise, coloured_windows, positivity, coloured_noise: coloured, ..DeconvOptions::default() };
    // experiment overrides: `--set key=value,…` (denoise, kappa, tile, no_harm, iterations, kappa7, sure, lawdata, texture, rwp, rwe, steps, field, lmin, thr)
    // every comma-separated pair (`list` has split them already; taking only the first dropped the rest)
    for kv in list("--set", &[""]).iter().filter(|kv| !kv.is_empty()) {
        let (k, v) = kv.split_once('=').ok_or_else(|| anyhow::anyhow!("--set {kv}: key=value"))?;
        match k {
            "denoise" => base.denoise = v.parse()?,
            "kappa" => base.denoise_lambda_per_variance = v.parse()?,
            "tile" => base.tile_core = Some(v.parse()?),
            "no_harm" => base.no_harm.enabled = v == "on",
            "iterations" => base.max_iterations = v.parse()?,
            "kappa7" => base.lambda_per_variance = v.parse()?,
            "sure" => base.coloured_sure = v == "on",
            "response" => {
                base.coloured_response = match v {
                    "pilot" => lensrig::deconv::coloured::Response::Pilot,
                    "excess" => lensrig::deconv::coloured::Response::Forward(1.0),
                    _ => anyhow::bail!("--set response={v}: pilot or excess"),
                }
            }
            "lawdata" => base.law_data_weight = v == "on",
            "rwp" => base.reweight_power = v.parse()?,
            "rwe" => base.reweight_eps = v.parse()?,
            "steps" => base.residual_steps = v.parse()?,
            "field" => base.field_passes = v.parse()?,
            "lmin" => base.lambda_min = v.parse()?,
            "texture" => base.texture_return = v == "on",
            "thr" => base.denoiser.threshold = v.parse()?,
            _ => anyhow::bail!("--set: unknown key {k}"),
        }
    }
    eprintln!("options: {base:?}");
    let _ = BASE.set(base);
    eprintln!("coloured windows per axis {coloured_windows}, positivity {positivity}");
    if let Some((l, nz, s)) = probe_cell {
        return probe(&l, &nz, &s);
    }
    let mut cache = PeerCache::load(Path::new(list("--peer-cache", &["target/deblur_matrix_peers.tsv"])[0].as_str()));
    let total = noises.len() * lenses.len() * scenes.len();
    let start = Instant::now();
    println!("cross weight {cross_weight}, local noise {local_noise}; denoiser noise model: {}; PSNR on linear values clipped to [0, 1]; peers with the TRUE PSFs and an oracle choice by PSNR (RL its from {{10, 30, 100}}, Wiener balance from {WIENER_BALANCE:?}); seconds: lensrig (true profile) wall / CPU", if coloured { "coloured" } else { "flat" });
    println!("| lens | noise | scene | size | split | blurred dB | RL dB | Wiener dB | lensrig (true) dB | lensrig (estimated) dB | lensrig − best peer | SSIM (lensrig) | lensrig s (wall / CPU) | RL its / Wiener b |");
    println!("| --- | --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |");
    let mut grids: HashMap<String, PsfGrid> = HashMap::new();
    let (mut below, mut n, mut min_margin) = (0usize, 0usize, f64::INFINITY);
    for nz in &noises {
        for l in &lenses {
            if !grids.contains_key(l) {
                grids.insert(l.clone(), lens(l)?);
            }
            let grid = &grids[l];
            let est = if with_estimate {
                let t = Instant::now();
                let g = estimated_grid(grid, noise_law(nz)?.1)?;
                eprintln!("estimated {l} × {nz}: {}×{} grid, {} px kernels, {:.1} s", g.columns, g.rows, g.kernel_size, t.elapsed().as_secs_f64());
                Some(g)
            } else {
                None
            };
            for s in &scenes {
                let t = Instant::now();
                let cached = cache.rows.contains_key(&PeerCache::key(l, nz, s));
                let (row, held_out, gain, margin) = cell(l, nz, s, grid, est.as_ref(), coloured, &mut cache)?;
                println!("{row}");
                n += 1;
                let per_cell = start.elapsed().as_secs_f64() / n as f64;
                eprintln!(
                    "cell {n}/{total} {l} × {nz} × {s}: {:.0} s (peers {}); ETA {:.0} s",
                    t.elapsed().as_secs_f64(),
                    if cached { "cached" } else { "run" },
                    per_cell * (total - n) as f64
                );
                below += usize::from(gain < 0.0);
                if held_out {
                    min_margin = min_margin.min(margin);
                }
            }
        }
    }
    println!("\ncells: {n}; below the blurred input: {below}; min margin over the best peer on held-out cells: {min_margin:+.2} dB");
    Ok(())
}
