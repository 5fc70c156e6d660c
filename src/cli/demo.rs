//! `lensrig demo`: the whole core on simulated data, no hardware.
//!
//! Renders a calibration pair of the noise target through the simulated lens (wide open and
//! a pinhole reference), estimates a profile, and measures it against the simulator's truth:
//! the median relative L2 error of the kernels at the tile centres, and the cross-validation
//! figure — the profile predicts a *second, independent* pair's wide-open image from its
//! pinhole image, and the prediction's residual RMS is compared with that image's true noise
//! RMS. Writes the captures, the profile, `summary.json` and `index.html` into `--out`.

use super::predict;
use anyhow::{Context, Result};
use clap::Args;
use lensrig::estimate::{estimate, relative_error, EstimateOptions};
use lensrig::fsutil::{write_atomic, Overwrite};
use lensrig::image::io::{write_png16, write_png8};
use lensrig::image::{Image, Plane};
use lensrig::optics::capture::{render, Rendered, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::rng::Rng;
use lensrig::target::{render_noise_scene, TargetSpec};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Run directory to write (created; existing files in it are replaced).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 512)]
    pub width: usize,
    #[arg(long, default_value_t = 384)]
    pub height: usize,
    /// Wide-open f-number of the simulated lens.
    #[arg(long, default_value_t = 5.6)]
    pub f_number: f64,
    /// Pinhole reference: "ideal" (perfectly sharp) or an f-number such as 22.
    #[arg(long, default_value = "ideal")]
    pub pinhole: String,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Kernel size (odd); default: the simulator's suggestion.
    #[arg(long)]
    pub kernel: Option<usize>,
    /// Tile side; default: chosen by `estimate`.
    #[arg(long)]
    pub tile: Option<usize>,
    #[arg(long, default_value_t = 150)]
    pub max_iterations: usize,
    /// Relative step at which a window's iterations stop.
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Iterations of the joint refinement with the interpolated forward model (0: off).
    #[arg(long, default_value_t = 40)]
    pub joint_iterations: usize,
    /// Fit window side around each PSF centre; default: chosen by `estimate`.
    #[arg(long)]
    pub window: Option<usize>,
    /// Scale of the TV weight.
    #[arg(long, default_value_t = 1.0)]
    pub lambda_scale: f64,
    #[arg(long)]
    pub quiet: bool,
}

fn render_pair(lens: &LensModel, a: &DemoArgs, k: usize, seed: u64) -> Result<(Rendered, Rendered)> {
    let spec = TargetSpec::new("A4", 300, 4, seed)?;
    let scene = render_noise_scene(&spec, a.width, a.height, 1.6, 7.0, 5.0);
    let scene: Vec<Plane> = vec![scene; lens.bands.len()];
    let sensor = Sensor::default();
    let open = render(&scene, lens, &Shot::lens(a.f_number, 0.75, 9, 7, k), &sensor, &mut Rng::new(seed * 2 + 1));
    let pin_shot = if a.pinhole == "ideal" {
        Shot::ideal(0.75)
    } else {
        let n: f64 = a.pinhole.parse().with_context(|| format!("--pinhole must be 'ideal' or an f-number, got '{}'", a.pinhole))?;
        Shot::lens(n, 0.75, 9, 7, k)
    };
    let pin = render(&scene, lens, &pin_shot, &sensor, &mut Rng::new(seed * 2 + 2));
    Ok((open, pin))
}

/// Normalises each kernel of a mosaic to its own peak, for viewing.
pub fn psf_mosaic(grid: &PsfGrid, c: usize) -> Image {
    let k = grid.kernel_size;
    let mut m = Plane::new(grid.columns * (k + 2), grid.rows * (k + 2));
    for t in 0..grid.tile_count() {
        let mut kk = grid.kernels[c][t].clone();
        let mx = kk.max().max(1e-12);
        kk.scale(1.0 / mx);
        let kk = kk.map(|v| v.max(0.0).sqrt());
        m.paste(&kk, ((t % grid.columns) * (k + 2) + 1) as isize, ((t / grid.columns) * (k + 2) + 1) as isize);
    }
    Image::new(vec![m])
}

pub fn run(a: &DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    let lens = LensModel::demo(a.width, a.height);
    let k = a.kernel.unwrap_or_else(|| lens.suggested_kernel_size(a.f_number));
    if !a.quiet {
        eprintln!("rendering calibration pairs ({}x{}, f/{}, pinhole {}, kernel {k})", a.width, a.height, a.f_number, a.pinhole);
    }
    let (open, pin) = render_pair(&lens, a, k, a.seed)?;
    let (open2, pin2) = render_pair(&lens, a, k, a.seed + 1000)?;
    let p = |n: &str| a.out.join(n);
    write_png16(&p("open.png"), &open.image, Overwrite::Replace)?;
    write_png16(&p("pinhole.png"), &pin.image, Overwrite::Replace)?;
    write_png16(&p("open2.png"), &open2.image, Overwrite::Replace)?;
    write_png16(&p("pinhole2.png"), &pin2.image, Overwrite::Replace)?;

    let opts = EstimateOptions { kernel_size: Some(k), tile: a.tile, max_iterations: a.max_iterations, tolerance: a.tolerance, window: a.window, joint_iterations: a.joint_iterations, lambda_scale: a.lambda_scale, progress: !a.quiet, ..Default::default() };
    let mut est = estimate(&open.image, &pin.image, &opts)?;
    est.profile.meta.source.open = Some("open.png".into());
    est.profile.meta.source.pinhole = Some("pinhole.png".into());
    est.profile.meta.note = "estimated by `lensrig demo` from simulated captures".into();
    est.profile.save(&p("profile"))?;

    // accuracy against the truth at the tile centres
    let truth = open.psfs.as_ref().context("the wide-open render has no PSFs")?;
    let g = &est.profile.grid;
    let mut errs = Vec::new();
    for c in 0..g.channels.len() {
        for t in 0..g.tile_count() {
            let [x, y] = g.centers[t];
            errs.push(relative_error(&g.kernels[c][t], &truth.kernel_at(c, x, y)));
        }
    }
    let mut sorted = errs.clone();
    sorted.sort_by(|x, y| x.total_cmp(y));
    let median = sorted[sorted.len() / 2];

    // the truth as a profile too: for side-by-side viewing, and as the floor of what kernels on
    // this tile grid can predict
    let mut truth_grid = g.clone();
    for c in 0..g.channels.len() {
        for t in 0..g.tile_count() {
            let [x, y] = g.centers[t];
            truth_grid.kernels[c][t] = truth.kernel_at(c, x, y);
        }
    }
    // cross-validation on the independent pair, interior only (a kernel radius from the edges)
    let pred = predict(&est.profile, &pin2.image, Path::new("pinhole2.png"))?;
    write_png16(&p("predicted2.png"), &pred, Overwrite::Replace)?;
    let (resid_rms, noise_rms) = residual_vs_noise(&pred, &open2, k / 2);
    let ratio = resid_rms / noise_rms;
    let truth_profile = lensrig::profile::Profile { meta: est.profile.meta.clone(), grid: truth_grid.clone() };
    let pred_truth = predict(&truth_profile, &pin2.image, Path::new("pinhole2.png"))?;
    let ratio_truth = residual_vs_noise(&pred_truth, &open2, k / 2).0 / noise_rms;
    for (c, name) in g.channels.iter().enumerate() {
        write_png8(&p(&format!("psf-{name}-estimated.png")), &psf_mosaic(g, c), Overwrite::Replace)?;
        write_png8(&p(&format!("psf-{name}-truth.png")), &psf_mosaic(&truth_grid, c), Overwrite::Replace)?;
    }
    let summary = serde_json::json!({
        "width": a.width, "height": a.height, "f_number": a.f_number, "pinhole": a.pinhole,
        "kernel_size": k, "columns": g.columns, "rows": g.rows,
        "median_relative_error": median, "max_relative_error": sorted[sorted.len() - 1],
        "relative_errors": errs,
        "cross_validation": { "residual_rms": resid_rms, "noise_rms": noise_rms, "ratio": ratio, "ratio_true_kernels_same_grid": ratio_truth },
        "exposure_ratio": est.profile.meta.exposure_ratio,
        "estimate_seconds": est.profile.meta.estimation.seconds,
    });
    write_atomic(&p("summary.json"), serde_json::to_string_pretty(&summary)?.as_bytes(), Overwrite::Replace)?;
    let mut html = String::from("<!doctype html><meta charset=utf-8><title>lensrig demo</title><style>body{font-family:sans-serif;margin:2em}img{image-rendering:pixelated;border:1px solid #ccc;max-width:45%}td{padding:4px 12px}</style>");
    html.push_str(&format!(
        "<h1>lensrig demo</h1><p>Simulated lens at f/{}, pinhole reference: {}, {}x{} px, {} px kernels on {}x{} tiles.</p>\
         <table><tr><td>median relative L2 error of the kernels (truth at tile centres)</td><td><b>{:.1}%</b></td></tr>\
         <tr><td>cross-validation: residual RMS / true noise RMS on an independent pair</td><td><b>{:.3}</b></td></tr>\
         <tr><td>the same with the true kernels at the same tile centres (the tile model's floor)</td><td>{:.3}</td></tr>\
         <tr><td>estimation time</td><td>{:.1} s</td></tr></table>",
        a.f_number, a.pinhole, a.width, a.height, k, g.columns, g.rows, median * 100.0, ratio, ratio_truth, est.profile.meta.estimation.seconds
    ));
    for name in &g.channels {
        html.push_str(&format!("<h2>Channel {name}: estimated (left) and true (right) PSFs, each scaled to its peak, square-root display</h2><img src=\"psf-{name}-estimated.png\"> <img src=\"psf-{name}-truth.png\">"));
    }
    write_atomic(&p("index.html"), html.as_bytes(), Overwrite::Replace)?;
    println!(
        "median kernel error {:.1}% (max {:.1}%), cross-validation residual/noise {:.3} (true kernels on this grid: {:.3}); report: {}",
        median * 100.0,
        sorted[sorted.len() - 1] * 100.0,
        ratio,
        ratio_truth,
        p("index.html").display()
    );
    Ok(())
}

/// RMS of `pred − recorded` and the RMS of the recorded image's true noise, over the interior
/// (`margin` pixels from every edge), all channels.
fn residual_vs_noise(pred: &Image, recorded: &Rendered, margin: usize) -> (f64, f64) {
    let (w, h) = (pred.width(), pred.height());
    let (mut res2, mut var, mut n) = (0.0f64, 0.0f64, 0usize);
    for c in 0..pred.channel_count() {
        for y in margin..h - margin {
            for x in margin..w - margin {
                let d = (pred.planes[c].get(x, y) - recorded.image.planes[c].get(x, y)) as f64;
                res2 += d * d;
                var += recorded.variance[c].get(x, y) as f64;
                n += 1;
            }
        }
    }
    ((res2 / n as f64).sqrt(), (var / n as f64).sqrt())
}
