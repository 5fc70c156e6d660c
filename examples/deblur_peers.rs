//! Benchmark runner for `lensrig deblur` against scikit-image peers (driven by
//! `scripts/bench-deblur.sh`).
//!
//! `prepare OUT [SCENE.png ...]`: for every scene (8-bit sRGB PNG), decode to linear, blur with
//! the synthetic chromatic field-varying lens ([`lensrig::deconv::synth::SyntheticLens`], 4×4 PSF
//! grid, 21×21 kernels), add Gaussian noise (σ = 0.005 linear), clip, re-encode sRGB and write
//! `OUT/<scene>/blurred.png` (16-bit), the lens profile `OUT/<scene>/profile/`, the true PSFs as
//! `psfs.json` for the peers, then restore it as `lensrig deblur` does (`restore_file`, in process) and
//! record its wall time.
//!
//! `report OUT [SCENE.png ...]`: PSNR (dB, sRGB-encoded values in [0, 1], whole image) of every
//! method's output (`<method>.png`, or `<method>.tiff` from the peers) against the sharp scene, and the recorded wall
//! seconds (and lensrig's CPU seconds: user + system over all threads), as a table.
//!
//! `enlarge SCENE.png WIDTH HEIGHT OUT.png`: a `WIDTH × HEIGHT` test scene made by mirror-tiling
//! a scene (for the 1-MP and 12-MP timing rows; `LR_NO_RUN=1 prepare` then blurs it without
//! restoring, so `run` can be timed on its own under `/usr/bin/time -v`).

use lensrig::deconv::capture::{restore_file, RestoreFile};
use lensrig::deconv::synth::{GaussianNoise, SyntheticLens};
use lensrig::fsutil::Overwrite;
use lensrig::image::io::{read_image, write_png16, write_tiff_f32};
use lensrig::image::{Image, Transfer};
use lensrig::optics::forward::blur_channel;
use lensrig::profile::{Profile, PsfTable, SourceInfo};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

const NOISE: f32 = 0.005;
const KERNEL: usize = 21;
const GRID: usize = 4;
const METHODS: [&str; 4] = ["blurred", "lensrig", "richardson_lucy", "wiener"];

fn scene_name(p: &Path) -> String {
    p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

fn prepare(out: &Path, scene: &Path) -> anyhow::Result<()> {
    let dir = out.join(scene_name(scene));
    std::fs::create_dir_all(&dir)?;
    let mut img = read_image(scene)?;
    img.transfer = Transfer::Srgb;
    let lin = img.to_linear();
    let (w, h) = (lin.width(), lin.height());
    let lens = SyntheticLens::new(KERNEL, 3);
    let mut grid = lens.grid(w, h, 3, GRID, GRID);
    // LR_UNIFORM=1: one PSF per channel (the centre's) over the whole field, to separate solver
    // quality from the field variation (diagnosis runs only)
    if std::env::var("LR_UNIFORM").is_ok_and(|v| v == "1") {
        for (c, ks) in grid.kernels.iter_mut().enumerate() {
            let k0 = lens.kernel(c, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0, w, h);
            ks.iter_mut().for_each(|k| *k = k0.clone());
        }
    }
    let mut noise = GaussianNoise::new(2013);
    let blurred: Vec<_> = lin
        .planes
        .iter()
        .enumerate()
        .map(|(c, p)| {
            let mut b = blur_channel(p, &grid, c);
            noise.add_to(&mut b, NOISE);
            b.map(|v| v.clamp(0.0, 1.0))
        })
        .collect();
    let mut bimg = Image::new(blurred);
    bimg.transfer = Transfer::Linear;
    let enc = bimg.encoded(Transfer::Srgb);
    write_png16(&dir.join("blurred.png"), &enc, Overwrite::Replace)?;
    // the same values as float TIFF for the Python peers (Pillow reads 16-bit RGB PNGs as 8-bit)
    let mut ftiff = enc.clone();
    ftiff.format = lensrig::image::SampleFormat::F32;
    write_tiff_f32(&dir.join("blurred.tiff"), &ftiff, Overwrite::Replace)?;
    let source = SourceInfo {
        width: w,
        height: h,
        channels: grid.channels.clone(),
        sample_format: lensrig::image::SampleFormat::U16,
        transfer: Transfer::Srgb,
        open: None,
        pinhole: None,
        black_level: vec![],
    };
    let table = PsfTable { kernel_size: KERNEL, columns: GRID, rows: GRID, centers: grid.centers.clone(), tile_size: None, files: BTreeMap::new() };
    let profile = Profile { meta: Profile::new_meta(source, vec![1.0; 3], table), grid: grid.clone() };
    profile.save(&dir.join("profile"))?;
    let psfs = serde_json::json!({
        "kernel_size": KERNEL,
        "columns": GRID,
        "rows": GRID,
        "centers": grid.centers,
        "kernels": grid.kernels.iter().map(|ch| ch.iter().map(|k| k.data.clone()).collect::<Vec<_>>()).collect::<Vec<_>>(),
        "noise_sigma_linear": NOISE,
    });
    std::fs::write(dir.join("psfs.json"), serde_json::to_string(&psfs)?)?;
    // LR_DARK / LR_TILE / LR_ITERS / LR_FLAT_DENOISE override the defaults (for profiling runs only)
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f32>().ok());
    let d = lensrig::deconv::DeconvOptions::default();
    let opts = lensrig::deconv::DeconvOptions {
        lambda: env("LR_LAMBDA").map(|v| vec![v]),
        dark_weight: env("LR_DARK").unwrap_or(d.dark_weight),
        max_iterations: env("LR_ITERS").map_or(d.max_iterations, |v| v as usize),
        saturation: Some(0.99),
        tile_core: env("LR_TILE").map(|v| v as usize),
        // LR_FLAT_DENOISE=1: the former flat-σ denoiser (before/after comparisons)
        coloured_noise: std::env::var("LR_FLAT_DENOISE").map_or(d.coloured_noise, |v| v != "1"),
        ..d
    };
    let (profile, input, restored) = (dir.join("profile"), dir.join("blurred.png"), dir.join("lensrig.png"));
    let job = RestoreFile { profile: &profile, input: &input, out: &restored, transfer: None, overwrite: Overwrite::Replace, progress: false, invalid: lensrig::image::validate::InvalidPixels::Refuse, distance: None, aperture: None };
    if std::env::var("LR_NO_RUN").is_ok_and(|v| v == "1") {
        return Ok(());
    }
    let (t, cpu0) = (Instant::now(), cpu_seconds());
    restore_file(&job, &opts)?;
    let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - cpu0);
    std::fs::write(dir.join("lensrig.time"), format!("{secs:.2}\n"))?;
    std::fs::write(dir.join("lensrig.cpu"), format!("{cpu:.2}\n"))?;
    std::fs::write(dir.join("blurred.time"), "0\n")?;
    eprintln!("{}: {w}x{h}, lensrig {secs:.2} s wall, {cpu:.2} s CPU", scene_name(scene));
    Ok(())
}

/// `run OUT SCENE...`: restores an already prepared scene with options from `LR_*` environment
/// variables (tuning runs; the benchmark itself uses `prepare`), prints PSNR against the sharp
/// scene and the peers' PSNR.
fn experiment(out: &Path, scene: &Path) -> anyhow::Result<()> {
    let dir = out.join(scene_name(scene));
    let profile = Profile::load(&dir.join("profile"))?;
    let mut img = read_image(&dir.join("blurred.png"))?;
    img.transfer = Transfer::Srgb;
    let lin = img.to_linear();
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    let d = lensrig::deconv::DeconvOptions::default();
    let opts = lensrig::deconv::DeconvOptions {
        lambda: env("LR_LAMBDA").map(|v| vec![v as f32]),
        lambda_per_variance: env("LR_KAPPA").map_or(d.lambda_per_variance, |v| v as f32),
        cross_weight: env("LR_CROSS").map_or(d.cross_weight, |v| v as f32),
        dark_weight: env("LR_DARK").map_or(d.dark_weight, |v| v as f32),
        residual_steps: env("LR_RES").map_or(d.residual_steps, |v| v as usize),
        field_passes: env("LR_FIELD").map_or(d.field_passes, |v| v as usize),
        max_levels: env("LR_LEVELS").map_or(d.max_levels, |v| v as usize),
        max_iterations: env("LR_ITERS").map_or(d.max_iterations, |v| v as usize),
        tolerance: env("LR_TOL").unwrap_or(d.tolerance),
        admm_rho: env("LR_RHO").map_or(d.admm_rho, |v| v as f32),
        admm_cg_iterations: env("LR_CG").map_or(d.admm_cg_iterations, |v| v as usize),
        step_balance: env("LR_BAL").map_or(d.step_balance, |v| v as f32),
        tile_core: env("LR_TILE").map(|v| v as usize),
        overlap: env("LR_OVERLAP").map_or(d.overlap, |v| v as usize),
        margin: env("LR_MARGIN").map(|v| v as usize).or(d.margin),
        // the CLI delivers sRGB here, so the prior is weighted for it (LR_GAMMA=0: uniform)
        output_transfer: if env("LR_GAMMA").is_some_and(|g| g <= 0.0) { None } else { Some(Transfer::Srgb) },
        transfer_weight: env("LR_GAMMA").map_or(d.transfer_weight, |v| v as f32),
        reweight_power: env("LR_RWP").map_or(d.reweight_power, |v| v as f32),
        reweight_eps: env("LR_RWE").map_or(d.reweight_eps, |v| v as f32),
        order2_weight: env("LR_D2").map_or(d.order2_weight, |v| v as f32),
        cross_local: env("LR_BLOC").map_or(d.cross_local, |v| v as f32),
        unknown_boundary: env("LR_UB").map_or(d.unknown_boundary, |v| v > 0.0),
        data_split_rho: env("LR_VRHO").map_or(d.data_split_rho, |v| v as f32),
        denoise: env("LR_DN").map_or(d.denoise, |v| v as f32),
        texture_return: env("LR_TEXTURE").map_or(d.texture_return, |v| v > 0.0),
        denoise_lambda_per_variance: env("LR_DNKAPPA").map_or(d.denoise_lambda_per_variance, |v| v as f32),
        denoiser: {
            let n = &d.denoiser;
            lensrig::deconv::denoise::DenoiseOptions {
                step: env("LR_DNSTEP").map_or(n.step, |v| v as usize),
                threshold: env("LR_DNTHR").map_or(n.threshold, |v| v as f32),
                chroma: env("LR_DNCHROMA").map_or(n.chroma, |v| v as f32),
                search: env("LR_BMS").map_or(n.search, |v| v as usize),
                bm_channels: env("LR_BMCH").map_or(n.bm_channels, |v| v as usize),
                search_step: env("LR_BMSTEP").map_or(n.search_step, |v| v as usize),
                group: env("LR_BMG").map_or(n.group, |v| v as usize),
                match_tau: env("LR_BMTAU").map_or(n.match_tau, |v| v as f32),
                slope_power: env("LR_DNSP").map_or(n.slope_power, |v| v as f32),
                wiener: env("LR_DNW").map_or(n.wiener, |v| v > 0.0),
                ..n.clone()
            }
        },
        saturation: match env("LR_SAT") {
            Some(v) if v > 1.0 => None,
            Some(v) => Some(v as f32),
            None => d.saturation,
        },
        ..d
    };
    let (t, cpu0) = (Instant::now(), cpu_seconds());
    let (planes, rep) = lensrig::deconv::deblur(&lin.planes, &profile.grid, &opts, &|_, _| {})?;
    let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - cpu0);
    let mut res = Image::new(planes);
    res.transfer = Transfer::Linear;
    let enc = res.encoded(Transfer::Srgb);
    write_png16(&dir.join("experiment.png"), &enc, Overwrite::Replace)?;
    let sharp = read_image(scene)?;
    let peer = |m: &str| read_image(&dir.join(format!("{m}.tiff"))).map(|i| psnr(&i, &sharp)).unwrap_or(f64::NAN);
    println!(
        "{:<18} lensrig {:.3} dB  RL {:.2}  Wiener {:.2}  blurred {:.2} | {secs:.2} s wall {cpu:.2} s CPU | tiles {} window {:?} cp {} λ {:?}",
        scene_name(scene),
        psnr(&enc, &sharp),
        peer("richardson_lucy"),
        peer("wiener"),
        psnr(&img, &sharp),
        rep.tiles,
        rep.window,
        rep.cp_iterations,
        rep.lambda
    );
    Ok(())
}

/// User + system CPU seconds of this process so far (Linux `/proc/self/stat`, clock ticks of
/// 1/100 s; `NaN` elsewhere).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let fields: Vec<&str> = stat.rsplit_once(')').map(|(_, r)| r.split_whitespace().collect()).unwrap_or_default();
    match (fields.get(11).and_then(|v| v.parse::<f64>().ok()), fields.get(12).and_then(|v| v.parse::<f64>().ok())) {
        (Some(u), Some(s)) => (u + s) / 100.0,
        _ => f64::NAN,
    }
}

fn psnr(a: &Image, b: &Image) -> f64 {
    let mut se = 0.0f64;
    let mut n = 0usize;
    for (p, q) in a.planes.iter().zip(&b.planes) {
        for (x, y) in p.data.iter().zip(&q.data) {
            se += ((x.clamp(0.0, 1.0) - y.clamp(0.0, 1.0)) as f64).powi(2);
            n += 1;
        }
    }
    10.0 * (1.0 / (se / n.max(1) as f64).max(1e-20)).log10()
}

fn report(out: &Path, scenes: &[PathBuf]) -> anyhow::Result<()> {
    println!("| scene | size | method | PSNR (dB) | seconds (wall) | CPU seconds |");
    println!("| --- | --- | --- | ---: | ---: | ---: |");
    for scene in scenes {
        let sharp = read_image(scene)?;
        let dir = out.join(scene_name(scene));
        let size = format!("{}x{}", sharp.width(), sharp.height());
        for m in METHODS {
            let tiff = dir.join(format!("{m}.tiff"));
            let file = if tiff.exists() && m != "blurred" { tiff } else { dir.join(format!("{m}.png")) };
            let read = |ext: &str| std::fs::read_to_string(dir.join(format!("{m}.{ext}"))).map(|s| s.trim().to_string()).unwrap_or_else(|_| "-".into());
            let (time, cpu) = (read("time"), read("cpu"));
            match read_image(&file) {
                Ok(img) => println!("| {} | {size} | {m} | {:.2} | {time} | {cpu} |", scene_name(scene), psnr(&img, &sharp)),
                Err(_) => {
                    let why = std::fs::read_to_string(dir.join(format!("{m}.error"))).unwrap_or_else(|_| "no output".into());
                    println!("| {} | {size} | {m} | n/a ({}) | - | - |", scene_name(scene), why.trim());
                }
            }
        }
    }
    Ok(())
}

/// Mirror-tiles `scene` to `width × height` (reflection at every edge, so no seams).
fn enlarge(scene: &Path, width: usize, height: usize, out: &Path) -> anyhow::Result<()> {
    let img = read_image(scene)?;
    let planes = img.planes.iter().map(|p| p.window_reflect(0, 0, width, height)).collect();
    let mut big = Image::new(planes);
    big.transfer = img.transfer;
    write_png16(out, &big, Overwrite::Replace)?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: deblur_peers prepare|report|run OUT_DIR SCENE.png... | enlarge SCENE.png WIDTH HEIGHT OUT.png";
    if args.first().is_some_and(|c| c == "enlarge") {
        anyhow::ensure!(args.len() == 5, usage);
        return enlarge(Path::new(&args[1]), args[2].parse()?, args[3].parse()?, Path::new(&args[4]));
    }
    let (cmd, out) = match (args.first(), args.get(1)) {
        (Some(c), Some(o)) => (c.as_str(), PathBuf::from(o)),
        _ => anyhow::bail!(usage),
    };
    let scenes: Vec<PathBuf> = args[2..].iter().map(PathBuf::from).collect();
    match cmd {
        "prepare" => {
            for s in &scenes {
                prepare(&out, s)?;
            }
            Ok(())
        }
        "report" => report(&out, &scenes),
        "run" => {
            for s in &scenes {
                experiment(&out, s)?;
            }
            Ok(())
        }
        _ => anyhow::bail!(usage),
    }
}
