//! Where the test bed's cross-validation excess comes from (issue 16, branch e14g).
//!
//! `cargo run --release --example cv_floor -- /work/shared/data/lenses/achromat-f4 [est-profile-dir]`
//!
//! Renders the test bed's second pair (seed 2) through a truth profile exactly as
//! `lensrig bench --testbed` does, and prints the cross-validation (residual RMS ÷ the wide-open
//! capture's true noise RMS, channels pooled, `margin` = half the larger kernel) of:
//! the truth grid itself; the truth resampled at another grid's centres; an estimated profile
//! (optional) — each with the recorded (noisy) pinhole and with its noise-free signal; plus the
//! floor the pinhole's noise sets, `√(1 + Σ s²·Var_pin ⊛ b² / Σ Var_open)`, and a map of
//! residual²/variance over an 8 × 6 partition of the field.

use lensrig::diagnose::simulate::predict;
use lensrig::estimate::testbed::noise_target_pair;
use lensrig::image::{Image, Transfer};
use lensrig::optics::capture::{Rendered, Sensor};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::Profile;

const SENSOR: Sensor = Sensor { full_well_e: 15_000.0, read_noise_e: 4.0, bits: 16, transfer: Transfer::Linear, noise: true };

fn pair(truth: &PsfGrid, w: usize, h: usize, seed: u64) -> (Rendered, Rendered) {
    noise_target_pair(truth, w, h, seed, &SENSOR, 0.75).unwrap()
}

/// Pooled residual² and variance per cell of a `cx × cy` partition, inside `margin`.
fn cells(pred: &Image, open: &Rendered, margin: usize, cx: usize, cy: usize) -> (Vec<f64>, Vec<f64>) {
    let (w, h) = (pred.width(), pred.height());
    let (mut r2, mut v) = (vec![0.0; cx * cy], vec![0.0; cx * cy]);
    for c in 0..pred.channel_count() {
        for y in margin..h - margin {
            for x in margin..w - margin {
                let i = (y * cy / h) * cx + x * cx / w;
                let d = (pred.planes[c].get(x, y) - open.image.planes[c].get(x, y)) as f64;
                r2[i] += d * d;
                v[i] += open.variance[c].get(x, y) as f64;
            }
        }
    }
    (r2, v)
}

fn report(name: &str, profile: &Profile, open: &Rendered, pin: &Rendered, margin: usize) {
    let clean = Image::new(pin.clean.clone());
    for (label, sharp) in [("noisy pinhole", &pin.image), ("clean pinhole", &clean)] {
        let mut sharp = sharp.clone();
        sharp.channels = profile.grid.channels.clone();
        let pred = predict(profile, &sharp).unwrap();
        let (cx, cy) = (8, 6);
        let (r2, v) = cells(&pred, open, margin, cx, cy);
        let cv = (r2.iter().sum::<f64>() / v.iter().sum::<f64>()).sqrt();
        println!("{name} / {label}: CV {cv:.4}");
        if label == "clean pinhole" || name.starts_with("truth") {
            for j in 0..cy {
                let row: Vec<String> = (0..cx).map(|i| format!("{:.3}", (r2[j * cx + i] / v[j * cx + i]).sqrt())).collect();
                println!("    {}", row.join(" "));
            }
        }
    }
}

/// The floor set by the pinhole's own noise through the truth kernels.
fn floor(truth: &PsfGrid, open: &Rendered, pin: &Rendered, margin: usize, s: &[f64]) -> f64 {
    let (w, h) = (open.image.width(), open.image.height());
    let (mut num, mut den) = (0.0, 0.0);
    for (c, &sc) in s.iter().enumerate().take(truth.channels.len()) {
        let mut sq = truth.clone();
        for k in &mut sq.kernels[c] {
            k.data.iter_mut().for_each(|v| *v *= *v);
        }
        let prop = lensrig::optics::forward::blur_channel(&pin.variance[c], &sq, c);
        for y in margin..h - margin {
            for x in margin..w - margin {
                num += sc * sc * prop.get(x, y) as f64;
                den += open.variance[c].get(x, y) as f64;
            }
        }
    }
    (1.0 + num / den).sqrt()
}

fn resampled(truth: &PsfGrid, w: usize, h: usize, cols: usize, rows: usize, k: usize) -> PsfGrid {
    let centers = PsfGrid::regular_centers(w, h, cols, rows);
    let kernels = (0..truth.channels.len())
        .map(|c| centers.iter().map(|&[x, y]| lensrig::estimate::testbed::embed_centered(&truth.kernel_at(c, x, y), k)).collect())
        .collect();
    PsfGrid { kernel_size: k, columns: cols, rows, centers, channels: truth.channels.clone(), kernels }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let truth = Profile::load(std::path::Path::new(&args[1])).unwrap();
    let (w, h) = (truth.meta.source.width, truth.meta.source.height);
    let (open, pin) = pair(&truth.grid, w, h, 2);
    // "run": estimate on the test bed's first pair with the default options (as the bench)
    let est = args.get(2).map(|d| {
        if d == "run" {
            let (o1, p1) = pair(&truth.grid, w, h, 1);
            let t0 = std::time::Instant::now();
            let e = lensrig::estimate::estimate(&o1.image, &p1.image, &lensrig::estimate::EstimateOptions::default()).unwrap();
            println!("estimate: {}x{} of {} px in {:.1} s", e.profile.grid.columns, e.profile.grid.rows, e.profile.grid.kernel_size, t0.elapsed().as_secs_f64());
            e.profile
        } else {
            Profile::load(std::path::Path::new(d)).unwrap()
        }
    });
    let k_est = est.as_ref().map_or(truth.grid.kernel_size, |e| e.grid.kernel_size);
    let margin = truth.grid.kernel_size.max(k_est) / 2;
    let s = est.as_ref().map_or(truth.meta.exposure_ratio.clone(), |e| e.meta.exposure_ratio.clone());
    println!("pinhole-noise floor through the truth kernels: {:.4}", floor(&truth.grid, &open, &pin, margin, &s));
    let mut tp = truth.clone();
    tp.meta.exposure_ratio = s.clone();
    report("truth 7x5", &tp, &open, &pin, margin);
    let dims: Vec<(usize, usize)> = match &est {
        Some(e) => vec![(e.grid.columns, e.grid.rows)],
        None => vec![(19, 14)],
    };
    for (c, r) in dims {
        let mut ks = vec![truth.grid.kernel_size, k_est];
        ks.dedup();
        for k in ks {
            let g = resampled(&truth.grid, w, h, c, r, k);
            let p = Profile { meta: tp.meta.clone(), grid: g };
            report(&format!("truth at {c}x{r} centres, {k} px"), &p, &open, &pin, margin);
        }
    }
    if let Some(e) = est {
        report("estimate", &e, &open, &pin, margin);
    }
}
