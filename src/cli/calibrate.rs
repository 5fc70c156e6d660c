//! `lensrig calibrate`: capture a session with the rig, estimate one profile per stage
//! position, and write an HTML report (`RUN_DIR/index.html`): the PSF grid per channel, an
//! encircled-energy (80 %) radius map across the field (pixels), and previews of the
//! captures. On a mock rig the kernels are also compared with the simulator's truth
//! (`summary.json`: median and max relative L2 error at the tile centres).

use super::args::{EstimateArgs, RigArgs};
use super::capture::capture_session;
use super::report::{html_head, psf_mosaic};
use anyhow::{Context, Result};
use clap::Args;
use lensrig::estimate::session::estimate_session;
use lensrig::estimate::{energy_radius, kernel_errors, median_max, Estimate};
use lensrig::fsutil::{write_atomic, Overwrite};
use lensrig::image::io::{read_image, write_png8};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::profile::Profile;
use lensrig::rig::camera::mock::MockOptics;
use lensrig::rig::session::PairRecord;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Args, Debug)]
#[command(mut_arg("max_iterations", |a| a.default_value("300")))]
pub struct CalibrateArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Run directory: session/, profiles/, index.html, summary.json.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub estimation: EstimateArgs,
    #[arg(long)]
    pub quiet: bool,
}

/// Median and max relative L2 error of a profile's kernels against the mock's truth at the
/// tile centres (the f-number the mock renders at the open aperture).
pub fn truth_error(optics: &MockOptics, g: &PsfGrid) -> (f64, f64) {
    median_max(&kernel_errors(g, &optics.truth_grid(optics.f_number_open)))
}

fn ee_map(p: &Profile, c: usize) -> String {
    let g = &p.grid;
    let r: Vec<f64> = g.kernels[c].iter().map(|k| energy_radius(k, 0.8)).collect();
    let mx = r.iter().copied().fold(1e-9, f64::max);
    let mut s = String::from("<table class=ee>");
    for row in 0..g.rows {
        s.push_str("<tr>");
        for col in 0..g.columns {
            let v = r[row * g.columns + col];
            let shade = (255.0 * (1.0 - 0.7 * v / mx)) as u8;
            s.push_str(&format!("<td style=\"background:rgb(255,{shade},{shade})\">{v:.1}</td>"));
        }
        s.push_str("</tr>");
    }
    s.push_str("</table>");
    s
}

/// One pair's report: its HTML section, its `summary.json` entry and its (median, max)
/// kernel error against a mock's truth.
struct PairReport {
    html: String,
    json: serde_json::Value,
    truth: Option<(f64, f64)>,
}

/// The report section of one pair (PSF mosaics, encircled-energy map, capture previews,
/// written under `report/<key>/`) and its `summary.json` entry.
fn pair_section(out: &Path, session_dir: &Path, p: &PairRecord, est: &Estimate, optics: Option<&MockOptics>) -> Result<PairReport> {
    let prof = &est.profile;
    let g = &prof.grid;
    let dir = out.join("report").join(&p.key);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut html = format!(
        "<h2>{} (stage {} mm)</h2><p>Profile <code>profiles/{}/</code>: {}x{} tiles, {} px kernels, exposure ratio {:?}.</p>",
        p.key, p.stage_mm, p.key, g.columns, g.rows, g.kernel_size, prof.meta.exposure_ratio
    );
    let truth = optics.map(|o| truth_error(o, g));
    if let Some((med, max)) = truth {
        html.push_str(&format!("<p>Against the simulator's truth at the tile centres: median relative L2 kernel error <b>{:.1}%</b> (max {:.1}%).</p>", med * 100.0, max * 100.0));
    }
    for (c, name) in g.channels.iter().enumerate() {
        let f = format!("report/{}/psf-{name}.png", p.key);
        write_png8(&out.join(&f), &psf_mosaic(g, c), Overwrite::Replace)?;
        html.push_str(&format!("<h3>Channel {name}</h3><p>PSFs per tile (each scaled to its peak, square-root display):</p><img src=\"{f}\"><p>80% encircled-energy radius (px) across the field:</p>{}", ee_map(prof, c)));
    }
    html.push_str("<p>Captures (open, pinhole):</p>");
    for role in ["open", "pinhole"] {
        let img = read_image(&session_dir.join(&p.dir).join(format!("{role}.png")))?;
        let mx = img.planes.iter().flat_map(|q| q.data.iter().copied()).fold(1e-6f32, f32::max);
        let mut prev = img.clone();
        prev.planes.iter_mut().for_each(|q| q.data.iter_mut().for_each(|v| *v = (*v / mx).sqrt()));
        let f = format!("report/{}/{role}.png", p.key);
        write_png8(&out.join(&f), &prev, Overwrite::Replace)?;
        html.push_str(&format!("<img src=\"{f}\" title=\"{role}\"> "));
    }
    let json = serde_json::json!({
        "key": p.key, "stage_mm": p.stage_mm, "profile": format!("profiles/{}", p.key),
        "columns": g.columns, "rows": g.rows, "kernel_size": g.kernel_size,
        "exposure_ratio": prof.meta.exposure_ratio,
        "truth_median_relative_error": truth.map(|t| t.0), "truth_max_relative_error": truth.map(|t| t.1),
    });
    Ok(PairReport { html, json, truth })
}

pub fn run(a: &CalibrateArgs) -> Result<()> {
    let t0 = Instant::now();
    let progress = !a.quiet;
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    let session_dir = a.out.join("session");
    let (cfg, rig, rec) = capture_session(&a.rig, &session_dir, progress)?;
    let t_capture = t0.elapsed().as_secs_f64();
    let optics = rig.mock_optics.clone();
    drop(rig);
    let mut opts = a.estimation.options();
    opts.kernel_size = opts.kernel_size.or(optics.as_ref().map(|o| o.kernel_size));
    opts.progress = progress;
    let ests = estimate_session(&session_dir, &a.out.join("profiles"), &opts, progress)?;
    let mut html = html_head("lensrig calibration", "4px 10px", "table.ee td{text-align:right;font-size:80%}");
    html.push_str(&format!(
        "<h1>lensrig calibration</h1><p>Rig config <code>{}</code>; camera: {}; session <code>session/</code> ({} pair(s), {}).</p>",
        a.rig.rig.display(),
        rec.camera,
        rec.pairs.len(),
        rec.status
    ));
    let mut pairs_json = Vec::new();
    let mut medians = Vec::new();
    for (p, est) in &ests {
        let r = pair_section(&a.out, &session_dir, p, est, optics.as_ref())?;
        html.push_str(&r.html);
        pairs_json.push(r.json);
        medians.extend(r.truth.map(|t| t.0));
    }
    let seconds = t0.elapsed().as_secs_f64();
    let summary = serde_json::json!({
        "rig": a.rig.rig.display().to_string(), "session": "session", "pairs": pairs_json,
        "mock_f_number_open": optics.as_ref().map(|o| o.f_number_open),
        "mock_f_number_pinhole": optics.as_ref().map(|o| o.f_number_pinhole),
        "capture_seconds": t_capture, "seconds": seconds,
        "camera": cfg.camera.kind,
    });
    write_atomic(&a.out.join("summary.json"), serde_json::to_string_pretty(&summary)?.as_bytes(), Overwrite::Replace)?;
    write_atomic(&a.out.join("index.html"), html.as_bytes(), Overwrite::Replace)?;
    let truth = if medians.is_empty() { String::new() } else { format!(", median kernel error vs truth {:?}", medians.iter().map(|m| format!("{:.1}%", m * 100.0)).collect::<Vec<_>>()) };
    println!("calibrated {} stage position(s) in {seconds:.1} s{truth}; report: {}", ests.len(), a.out.join("index.html").display());
    Ok(())
}
