//! `lensrig demo`: the whole core on simulated data, no hardware.
//!
//! Renders a calibration pair of the noise target through the simulated lens (wide open and
//! a pinhole reference), estimates a profile, and measures it against the simulator's truth:
//! the median relative L2 error of the kernels at the tile centres, and the cross-validation
//! figure — the profile predicts a *second, independent* pair's wide-open image from its
//! pinhole image, and the prediction's residual RMS (full scale, interior a kernel radius from
//! the edges) is compared with that image's true noise RMS. Writes the captures, the profile,
//! `summary.json` and `index.html` into `--out`.

use super::args::EstimateArgs;
use super::html::{html_head, psf_mosaic};
use anyhow::{Context, Result};
use clap::Args;
use lensrig::diagnose::simulate::predict;
use lensrig::estimate::{estimate, kernel_errors, median_max, Estimate};
use lensrig::fsutil::{write_atomic, Overwrite};
use lensrig::image::io::{write_png16, write_png8};
use lensrig::image::{Image, Plane};
use lensrig::optics::capture::{render, Rendered, Sensor, Shot};
use lensrig::optics::lens::LensModel;
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::Profile;
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
    #[command(flatten)]
    pub estimation: EstimateArgs,
    #[arg(long)]
    pub quiet: bool,
}

/// The two renders of one calibration pair (wide open, pinhole) of target seed `seed`.
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

/// What the demo measured.
struct Figures {
    errors: Vec<f64>,
    median: f64,
    max: f64,
    /// Residual RMS / true noise RMS of the prediction of the independent pair.
    ratio: f64,
    resid_rms: f64,
    noise_rms: f64,
    /// The same with the true kernels at the same tile centres (the tile model's floor).
    ratio_truth: f64,
    truth_grid: PsfGrid,
}

/// Kernel errors against the truth and the cross-validation on the independent pair
/// (writes `predicted2.png`).
fn measure(out: &Path, est: &Estimate, truth: &PsfGrid, open2: &Rendered, pin2: &Rendered, k: usize) -> Result<Figures> {
    let g = &est.profile.grid;
    let errors = kernel_errors(g, truth);
    let (median, max) = median_max(&errors);
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
    let pred = predict(&est.profile, &pin2.image).context("pinhole2.png")?;
    write_png16(&out.join("predicted2.png"), &pred, Overwrite::Replace)?;
    let (resid_rms, noise_rms) = residual_vs_noise(&pred, open2, k / 2);
    let truth_profile = Profile { meta: est.profile.meta.clone(), grid: truth_grid.clone() };
    let pred_truth = predict(&truth_profile, &pin2.image).context("pinhole2.png")?;
    let ratio_truth = residual_vs_noise(&pred_truth, open2, k / 2).0 / noise_rms;
    Ok(Figures { errors, median, max, ratio: resid_rms / noise_rms, resid_rms, noise_rms, ratio_truth, truth_grid })
}

/// `summary.json`, the PSF mosaics and `index.html`.
fn write_report(out: &Path, a: &DemoArgs, k: usize, est: &Estimate, f: &Figures) -> Result<()> {
    let g = &est.profile.grid;
    let p = |n: &str| out.join(n);
    for (c, name) in g.channels.iter().enumerate() {
        write_png8(&p(&format!("psf-{name}-estimated.png")), &psf_mosaic(g, c), Overwrite::Replace)?;
        write_png8(&p(&format!("psf-{name}-truth.png")), &psf_mosaic(&f.truth_grid, c), Overwrite::Replace)?;
    }
    let summary = serde_json::json!({
        "width": a.width, "height": a.height, "f_number": a.f_number, "pinhole": a.pinhole,
        "kernel_size": k, "columns": g.columns, "rows": g.rows,
        "median_relative_error": f.median, "max_relative_error": f.max,
        "relative_errors": f.errors,
        "cross_validation": { "residual_rms": f.resid_rms, "noise_rms": f.noise_rms, "ratio": f.ratio, "ratio_true_kernels_same_grid": f.ratio_truth },
        "exposure_ratio": est.profile.meta.exposure_ratio,
        "estimate_seconds": est.profile.meta.estimation.seconds,
    });
    write_atomic(&p("summary.json"), serde_json::to_string_pretty(&summary)?.as_bytes(), Overwrite::Replace)?;
    let mut html = html_head("lensrig demo", "4px 12px", "");
    html.push_str(&format!(
        "<h1>lensrig demo</h1><p>Simulated lens at f/{}, pinhole reference: {}, {}x{} px, {} px kernels on {}x{} tiles.</p>\
         <table><tr><td>median relative L2 error of the kernels (truth at tile centres)</td><td><b>{:.1}%</b></td></tr>\
         <tr><td>cross-validation: residual RMS / true noise RMS on an independent pair</td><td><b>{:.3}</b></td></tr>\
         <tr><td>the same with the true kernels at the same tile centres (the tile model's floor)</td><td>{:.3}</td></tr>\
         <tr><td>estimation time</td><td>{:.1} s</td></tr></table>",
        a.f_number, a.pinhole, a.width, a.height, k, g.columns, g.rows, f.median * 100.0, f.ratio, f.ratio_truth, est.profile.meta.estimation.seconds
    ));
    for name in &g.channels {
        html.push_str(&format!("<h2>Channel {name}: estimated (left) and true (right) PSFs, each scaled to its peak, square-root display</h2><img src=\"psf-{name}-estimated.png\"> <img src=\"psf-{name}-truth.png\">"));
    }
    write_atomic(&p("index.html"), html.as_bytes(), Overwrite::Replace)?;
    Ok(())
}

pub fn run(a: &DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    let lens = LensModel::demo(a.width, a.height);
    let k = a.estimation.kernel.unwrap_or_else(|| lens.suggested_kernel_size(a.f_number));
    if !a.quiet {
        eprintln!("rendering calibration pairs ({}x{}, f/{}, pinhole {}, kernel {k})", a.width, a.height, a.f_number, a.pinhole);
    }
    let (open, pin) = render_pair(&lens, a, k, a.seed)?;
    let (open2, pin2) = render_pair(&lens, a, k, a.seed + 1000)?;
    let p = |n: &str| a.out.join(n);
    for (name, r) in [("open.png", &open), ("pinhole.png", &pin), ("open2.png", &open2), ("pinhole2.png", &pin2)] {
        write_png16(&p(name), &r.image, Overwrite::Replace)?;
    }
    let mut opts = a.estimation.options();
    opts.kernel_size = Some(k);
    opts.progress = !a.quiet;
    let mut est = estimate(&open.image, &pin.image, &opts)?;
    est.profile.meta.source.open = Some("open.png".into());
    est.profile.meta.source.pinhole = Some("pinhole.png".into());
    est.profile.meta.note = "estimated by `lensrig demo` from simulated captures".into();
    est.profile.save(&p("profile"))?;

    let truth = open.psfs.as_ref().context("the wide-open render has no PSFs")?;
    let f = measure(&a.out, &est, truth, &open2, &pin2, k)?;
    write_report(&a.out, a, k, &est, &f)?;
    println!(
        "median kernel error {:.1}% (max {:.1}%), cross-validation residual/noise {:.3} (true kernels on this grid: {:.3}); report: {}",
        f.median * 100.0,
        f.max * 100.0,
        f.ratio,
        f.ratio_truth,
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
