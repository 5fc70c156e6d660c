//! `lensrig calibrate`: capture a session with the rig, estimate one profile per stage
//! position, and write an HTML report (`RUN_DIR/index.html`): per profile the
//! [`lensrig::report`] section (PSF grids per channel, MTF50 maps, MTF curves, lateral-colour
//! arrows, longitudinal colour, sub-pixel encircled energy; files in `report/<key>/`) and
//! previews of the captures. On a mock rig the kernels and their MTF50 are also compared with
//! the simulator's truth (`summary.json`).
//!
//! When the rig's focal length and pixel pitch are known (a mock rig's lens, or `[lens]`
//! `focal_length_mm` and `pixel_pitch_um`), `RUN_DIR/lens.xml` is the lensfun database file
//! of the first stage position's profile ([`super::export::lensfun_export`]): TCA from an
//! R, G, B profile, and `pa` vignetting from the session's flat field (`[plan.flat]`) minus its
//! dark frame, at the open f-number and a stated focus distance of 1000 m (the flat field is
//! taken at one focus). The report shows the measured relative illumination (against the
//! mock's truth on a mock rig).
//!
//! Distortion: when the rig's target file and its nominal layout on the sensor are known
//! (`[target.layout]` in the rig config, or on a mock rig without it the simulated lens's
//! `pixels_per_cell` and stage offset), the first stage position's pinhole
//! capture (its G channel, or the channel mean) is registered to the target file
//! ([`lensrig::target::locate`]) and lensfun's ptlens
//! fit is stored as `profiles/<key>/distortion.toml`; `lens.xml` then carries
//! `<distortion model="ptlens">`. The report shows the fit (and, on a mock rig, its error
//! against the simulator's truth).

use super::args::{EstimateArgs, RigArgs};
use super::capture::capture_session;
use super::export::{crop_factor, lensfun_export, FlatField};
use super::report::{facts_of, RigFacts};
use lensrig::profile::set::{Calibration, ProfileSet};
use anyhow::{Context, Result};
use clap::Args;
use lensrig::estimate::session::estimate_session;
use lensrig::estimate::{kernel_errors, median_max, Estimate};
use lensrig::fsutil::{write_atomic, Overwrite};
use lensrig::image::io::{read_image, write_png8};
use lensrig::optics::psf_grid::PsfGrid;
use lensrig::report::ProfileReport;
use lensrig::export::lensfun::LensInfo;
use lensrig::rig::camera::mock::MockOptics;
use lensrig::rig::config::RigConfig;
use lensrig::rig::session::{PairRecord, SessionRecord};
use lensrig::target::locate::{field_difference, locate, LocateOptions, MeasuredDistortion, Nominal};
use lensrig::target::TargetSpec;
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
/// tile centres (`truth`: the grid the mock renders at the open aperture).
pub fn truth_error(truth: &PsfGrid, g: &PsfGrid) -> (f64, f64) {
    median_max(&kernel_errors(g, truth))
}

/// Per channel, the median over tiles and both directions of |MTF50 / truth − 1|.
fn mtf50_vs_truth(r: &ProfileReport, t: &ProfileReport) -> Vec<f64> {
    (0..r.channels.len())
        .map(|c| {
            let mut d: Vec<f64> = r.tiles.iter().zip(&t.tiles).flat_map(|(a, b)| [(a.mtf50_tan[c] / b.mtf50_tan[c] - 1.0).abs(), (a.mtf50_sag[c] / b.mtf50_sag[c] - 1.0).abs()]).filter(|v| v.is_finite()).collect();
            d.sort_by(f64::total_cmp);
            d.get(d.len() / 2).copied().unwrap_or(0.0)
        })
        .collect()
}

/// The truth sampled at a profile's own tile centres (as [`truth_error`] compares kernels).
fn truth_at_centres(truth: &PsfGrid, g: &PsfGrid) -> PsfGrid {
    PsfGrid {
        kernel_size: truth.kernel_size,
        columns: g.columns,
        rows: g.rows,
        centers: g.centers.clone(),
        channels: truth.channels.clone(),
        kernels: (0..truth.channels.len()).map(|c| g.centers.iter().map(|&[x, y]| truth.kernel_at(c, x, y)).collect()).collect(),
    }
}

/// One pair's report: its HTML section, its `summary.json` entry and its (median, max)
/// kernel error against a mock's truth.
struct PairReport {
    html: String,
    json: serde_json::Value,
    truth: Option<(f64, f64)>,
}

/// The report section of one pair (the [`lensrig::report`] section and capture previews,
/// written under `report/<key>/`) and its `summary.json` entry.
fn pair_section(out: &Path, session_dir: &Path, p: &PairRecord, est: &Estimate, truth_grid: Option<&PsfGrid>, facts: &RigFacts) -> Result<PairReport> {
    let prof = &est.profile;
    let g = &prof.grid;
    let dir = out.join("report").join(&p.key);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let ratios: Vec<String> = prof.meta.exposure_ratio.iter().map(|r| lensrig::report::significant(*r, 3)).collect();
    let mut html = format!(
        "<h2>{} (stage {} mm)</h2><p>Profile <code>profiles/{}/</code>: {}x{} tiles, {} px kernels, exposure ratio (open/pinhole) {}.</p>",
        p.key, p.stage_mm, p.key, g.columns, g.rows, g.kernel_size, ratios.join(", ")
    );
    let truth = truth_grid.map(|t| truth_error(t, g));
    if let Some((med, max)) = truth {
        html.push_str(&format!("<p>Against the simulator's truth at the tile centres: median relative L2 kernel error <b>{:.1}%</b> (max {:.1}%).</p>", med * 100.0, max * 100.0));
    }
    let (w, h) = (prof.meta.source.width, prof.meta.source.height);
    let rep = lensrig::report::analyse(g, w, h, facts.pixel_pitch_um).with_restoration_tiles(g);
    lensrig::report::write_assets(&dir, g, &rep)?;
    let mtf_truth = truth_grid.map(|t| mtf50_vs_truth(&rep, &lensrig::report::analyse(&truth_at_centres(t, g), w, h, None)));
    if let Some(d) = &mtf_truth {
        let s: Vec<String> = rep.channels.iter().zip(d).map(|(c, v)| format!("{c} {:.1} %", v * 100.0)).collect();
        html.push_str(&format!("<p>MTF50 against the simulator's truth, median |relative difference| over tiles and directions: {}.</p>", s.join(", ")));
    }
    html.push_str(&lensrig::report::html_section(&rep, &format!("report/{}/", p.key)));
    html.push_str("<p>Captures (open, pinhole):</p>");
    for role in ["open", "pinhole"] {
        let img = read_image(&session_dir.join(&p.dir).join(format!("{role}.png")))?;
        let mx = img.planes.iter().flat_map(|q| q.data.iter().copied()).fold(1e-6f32, f32::max);
        let mut prev = img.clone();
        prev.planes.iter_mut().for_each(|q| q.data.iter_mut().for_each(|v| *v = (*v / mx).sqrt()));
        let f = format!("report/{}/{role}.png", p.key);
        write_png8(&out.join(&f), &prev, Overwrite::Replace)?;
        html.push_str(&format!("<img class=capture src=\"{f}\" title=\"{role}\" alt=\"{role} capture\"> "));
    }
    let json = serde_json::json!({
        "key": p.key, "stage_mm": p.stage_mm, "profile": format!("profiles/{}", p.key),
        "columns": g.columns, "rows": g.rows, "kernel_size": g.kernel_size,
        "exposure_ratio": prof.meta.exposure_ratio,
        "truth_median_relative_error": truth.map(|t| t.0), "truth_max_relative_error": truth.map(|t| t.1),
        "mtf50_median_relative_difference_vs_truth": mtf_truth,
    });
    Ok(PairReport { html, json, truth })
}

/// Focus distance (m) written with the flat field's vignetting: the flat field is taken at one
/// focus, stated rather than measured.
const FLAT_DISTANCE_M: f64 = 1000.0;

/// Radii (lensfun units: 1 = half the diagonal) the report tabulates relative illumination at.
const FALLOFF_RADII: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// Writes `lens.xml` (see the module docs) and returns its report section and `summary.json`
/// entry (`null` when no file was written).
fn lensfun_section(out: &Path, session_dir: &Path, rec: &SessionRecord, ests: &[(PairRecord, Estimate)], facts: &RigFacts, optics: Option<&MockOptics>) -> Result<(String, serde_json::Value)> {
    let Some((p, est)) = ests.first() else { return Ok((String::new(), serde_json::Value::Null)) };
    let prof = &est.profile;
    let (w, h) = (prof.meta.source.width, prof.meta.source.height);
    let mut html = String::from("<h2>Lens data for other tools</h2>");
    let (Some(focal), Some(pitch)) = (facts.focal_length_mm, facts.pixel_pitch_um) else {
        html.push_str("<p>No lensfun file: the rig config gives no focal length and pixel pitch (<code>[lens] focal_length_mm</code>, <code>pixel_pitch_um</code>).</p>");
        return Ok((html, serde_json::Value::Null));
    };
    let flat = match &rec.flat {
        Some(f) => {
            let dir = session_dir.join(&f.dir);
            let path = dir.join(&f.flat);
            let image = read_image(&path).with_context(|| format!("cannot read the flat field {}", path.display()))?;
            let dark = match &f.dark {
                Some(d) => Some(read_image(&dir.join(d)).with_context(|| format!("cannot read the flat field's dark frame in {}", dir.display()))?),
                None => None,
            };
            Some(FlatField { path, image, dark })
        }
        None => None,
    };
    let info = LensInfo {
        maker: "lensrig".into(),
        model: "Simple lens".into(),
        mount: "Generic".into(),
        focal_mm: focal,
        crop_factor: crop_factor(pitch, w, h),
        aperture: facts.f_number_open.unwrap_or(0.0),
        distance_m: FLAT_DISTANCE_M,
        width: w,
        height: h,
    };
    let profile_dir = out.join("profiles").join(&p.key);
    let e = lensfun_export(&profile_dir, prof, &info, flat.as_ref())?;
    write_atomic(&out.join("lens.xml"), e.xml.as_bytes(), Overwrite::Replace)?;
    let blocks: Vec<&str> = [e.distortion.as_ref().map(|_| "distortion (ptlens)"), e.tca.map(|_| "tca (poly3)"), e.vignetting.map(|_| "vignetting (pa)")].into_iter().flatten().collect();
    html.push_str(&format!(
        "<p><code>lens.xml</code>: a lensfun database file (lens \"lensrig / Simple lens\", focal {} mm, crop factor {}) with {} from <code>profiles/{}/</code>{}; copy it to <code>~/.local/share/lensfun/</code>.</p>",
        lensrig::report::significant(focal, 3),
        lensrig::report::significant(info.crop_factor, 3),
        if blocks.is_empty() { "no calibration block".to_string() } else { blocks.join(", ") },
        p.key,
        if e.vignetting.is_some() { " and the flat field <code>session/flat/</code>" } else { "" }
    ));
    let truth = optics.map(|o| o.vignetting.map_or([0.0; 3], |v| v.k));
    let mut vig_json = serde_json::Value::Null;
    if let (Some(v), Some(f)) = (&e.vignetting, &flat) {
        let at = |k: &[f64; 3], r: f64| {
            let r2 = r * r;
            1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
        };
        html.push_str("<p>Relative illumination from the flat field (lensfun <code>pa</code>, r = 1 at half the diagonal):</p><table><tr><th>r</th><th>measured</th>");
        if truth.is_some() {
            html.push_str("<th>simulator's truth</th>");
        }
        html.push_str("</tr>");
        let mut worst = 0.0f64;
        for r in FALLOFF_RADII {
            html.push_str(&format!("<tr><td>{r:.2}</td><td>{:.3}</td>", at(&v.k, r)));
            if let Some(t) = &truth {
                html.push_str(&format!("<td>{:.3}</td>", at(t, r)));
                worst = worst.max((at(&v.k, r) - at(t, r)).abs());
            }
            html.push_str("</tr>");
        }
        html.push_str(&format!("</table><p>k1 {:.4}, k2 {:.4}, k3 {:.4}; RMS fit residual {:.2} % of the centre over {} blocks.</p>", v.k[0], v.k[1], v.k[2], v.residual * 100.0, v.samples));
        let mx = f.image.planes.iter().flat_map(|q| q.data.iter().copied()).fold(1e-6f32, f32::max);
        let mut prev = f.image.clone();
        prev.planes.iter_mut().for_each(|q| q.data.iter_mut().for_each(|x| *x /= mx));
        write_png8(&out.join("report/flat.png"), &prev, Overwrite::Replace)?;
        html.push_str("<img class=capture src=\"report/flat.png\" title=\"flat field\" alt=\"flat-field capture\">");
        vig_json = serde_json::json!({
            "k": v.k, "residual": v.residual, "truth_k": truth,
            "max_abs_difference_vs_truth": truth.map(|_| worst),
        });
    }
    let json = serde_json::json!({ "file": "lens.xml", "profile": format!("profiles/{}", p.key), "distortion": e.distortion.is_some(), "tca": e.tca.map(|t| serde_json::json!({"red": t.red, "blue": t.blue})), "vignetting": vig_json });
    Ok((html, json))
}

/// Measures the lens's distortion from the first pair's pinhole capture (see the module docs),
/// stores it as `profiles/<key>/distortion.toml`, and returns its report section and
/// `summary.json` entry. A registration that fails is reported, not fatal.
fn distortion_section(out: &Path, session_dir: &Path, cfg: &RigConfig, ests: &[(PairRecord, Estimate)], optics: Option<&MockOptics>) -> Result<(String, serde_json::Value)> {
    let mut html = String::from("<h2>Geometric distortion</h2>");
    let (Some((p, _)), Some(t)) = (ests.first(), cfg.target.as_ref()) else {
        html.push_str("<p>Not measured: registering the pinhole capture to the target file needs the target (<code>[target]</code>).</p>");
        return Ok((html, serde_json::Value::Null));
    };
    // the nominal layout: the config's [target.layout], else the mock lens's own
    let nominal = match (&t.layout, optics) {
        (Some(l), _) => {
            let (u0, v0) = l.origin_at(p.stage_mm);
            Nominal { pixels_per_cell: l.pixels_per_cell, u0, v0 }
        }
        (None, Some(o)) => {
            let (u0, v0) = o.target_origin(p.stage_mm);
            Nominal { pixels_per_cell: o.pixels_per_cell, u0, v0 }
        }
        (None, None) => {
            html.push_str("<p>Not measured: registering the pinhole capture to the target file needs the target's nominal layout on the sensor (<code>[target.layout]</code> in the rig config).</p>");
            return Ok((html, serde_json::Value::Null));
        }
    };
    let spec = TargetSpec::load(&t.path).with_context(|| format!("cannot read the target {}", t.path.display()))?;
    let path = session_dir.join(&p.dir).join(&p.pinhole);
    let img = read_image(&path).with_context(|| format!("cannot read {}", path.display()))?;
    // lensfun's distortion is the green channel's geometry (TCA is R and B against G)
    let mean = match img.channels.iter().position(|c| c == "G") {
        Some(g) => img.planes[g].clone(),
        None => {
            let mut m = img.planes[0].clone();
            for q in &img.planes[1..] {
                m.data.iter_mut().zip(&q.data).for_each(|(a, v)| *a += v);
            }
            let n = img.planes.len() as f32;
            m.data.iter_mut().for_each(|a| *a /= n);
            m
        }
    };
    let fit = match locate(&mean, &spec, &nominal, &LocateOptions::default()) {
        Ok(f) => f,
        Err(e) => {
            html.push_str(&format!("<p>Not measured: {e}.</p>"));
            return Ok((html, serde_json::json!({ "error": e.to_string() })));
        }
    };
    let rec = MeasuredDistortion::of(&fit, &path, &t.path);
    rec.save(&out.join("profiles").join(&p.key))?;
    html.push_str(&format!(
        "<p>lensfun <code>ptlens</code> from the pinhole capture of <code>{}</code> registered to the target file: a {:.5}, b {:.5}, c {:.5} ({} of {} tiles, RMS residual {:.3} px; {:.3} px per target cell, rotation {:.3}°). Displacement in the corner {:.2} px. Stored in <code>profiles/{}/distortion.toml</code>.</p>",
        p.key, fit.ptlens.a, fit.ptlens.b, fit.ptlens.c, fit.tiles_used, fit.tiles.len(), fit.rms_residual_px, fit.pixels_per_cell, fit.rotation_deg, corner_px(&fit.ptlens, fit.width, fit.height), p.key
    ));
    let mut json = serde_json::json!({
        "file": format!("profiles/{}/distortion.toml", p.key), "a": fit.ptlens.a, "b": fit.ptlens.b, "c": fit.ptlens.c,
        "tiles_used": fit.tiles_used, "tiles": fit.tiles.len(), "rms_residual_px": fit.rms_residual_px,
    });
    if let Some(o) = optics {
        let truth = o.distortion.unwrap_or_default();
        let (max, rms) = field_difference(&fit.ptlens, &truth, fit.width, fit.height);
        html.push_str(&format!(
            "<p>Against the simulator's truth (a {}, b {}, c {}; corner displacement {:.2} px): displacement field error max {:.3} px, RMS {:.3} px over the {}×{} frame.</p>",
            truth.a, truth.b, truth.c, corner_px(&truth, fit.width, fit.height), max, rms, fit.width, fit.height
        ));
        json["truth"] = serde_json::json!([truth.a, truth.b, truth.c]);
        json["field_error_max_px"] = serde_json::json!(max);
        json["field_error_rms_px"] = serde_json::json!(rms);
    }
    Ok((html, json))
}

/// When the stage refocuses (`[axes.stage] focus_distance_m`), collects the calibrations as a
/// profile set, `profiles/index.toml` keyed like lensfun (focal length, f-number, focus
/// distance), which `deblur --profile DIR/profiles --distance D --aperture N` and `report` read.
fn profile_set_section(out: &Path, cfg: &RigConfig, ests: &[(PairRecord, Estimate)], facts: &RigFacts) -> Result<(String, serde_json::Value)> {
    let s = &cfg.axes.stage;
    let Some(dist) = &s.focus_distance_m else {
        return Ok((String::new(), serde_json::Value::Null));
    };
    let mut html = String::from("<h2>Profile set</h2>");
    let (Some(focal), Some(aperture)) = (facts.focal_length_mm, facts.f_number_open) else {
        html.push_str("<p>No profile set: the rig config gives no focal length or wide-open f-number (<code>[lens] focal_length_mm</code>, <code>f_number_open</code>).</p>");
        return Ok((html, serde_json::Value::Null));
    };
    let mut cals = Vec::new();
    for (p, _) in ests {
        // the position's index in the plan gives its focus distance
        let Some(i) = s.positions.iter().position(|v| (v - p.stage_mm).abs() < 1e-6) else { continue };
        cals.push(Calibration { focal, aperture, distance: dist[i], profile: p.key.clone() });
    }
    if cals.is_empty() {
        return Ok((html + "<p>No profile set: no calibration matches a stage position.</p>", serde_json::Value::Null));
    }
    let dir = out.join("profiles");
    ProfileSet::new(cals.clone()).save(&dir).with_context(|| format!("cannot write the profile set in {}", dir.display()))?;
    let rows: String = cals.iter().map(|c| format!("<tr><td>{}</td><td>{}</td><td>f/{}</td><td>{} mm</td></tr>", c.profile, c.distance, c.aperture, c.focal)).collect();
    html.push_str(&format!(
        "<p><code>profiles/index.toml</code>: {} calibration(s). <code>lensrig deblur --profile profiles --distance D --aperture N</code> blends the two nearest in 1/distance, or takes the nearest and says which.</p><table><tr><th>profile</th><th>distance (m)</th><th>aperture</th><th>focal</th></tr>{rows}</table>",
        cals.len()
    ));
    let json = serde_json::json!({ "file": "profiles/index.toml", "calibrations": cals.iter().map(|c| serde_json::json!({"profile": c.profile, "distance_m": c.distance, "aperture": c.aperture, "focal_mm": c.focal})).collect::<Vec<_>>() });
    Ok((html, json))
}

/// The displacement (pixels) a distortion gives the frame's top-left corner.
fn corner_px(d: &lensrig::optics::distortion::PtLens, width: usize, height: usize) -> f64 {
    let (x, y) = d.displacement_px(0.0, 0.0, width, height);
    x.hypot(y)
}

pub fn run(a: &CalibrateArgs) -> Result<()> {
    let t0 = Instant::now();
    let progress = !a.quiet;
    // `--out` is created by the session capture, after the config has loaded and the rig is
    // open, so that a refused config or a missing device leaves nothing behind.
    let session_dir = a.out.join("session");
    let (cfg, rig, rec) = capture_session(&a.rig, &session_dir, progress)?;
    let t_capture = t0.elapsed().as_secs_f64();
    let optics = rig.mock_optics.clone();
    drop(rig);
    let mut opts = a.estimation.options();
    opts.kernel_size = opts.kernel_size.or(optics.as_ref().map(|o| o.kernel_size));
    opts.progress = progress;
    let ests = estimate_session(&session_dir, &a.out.join("profiles"), &opts, progress)?;
    let mut html = String::from("<!doctype html><meta charset=utf-8><title>lensrig calibration</title><style>");
    html.push_str(lensrig::report::STYLE);
    html.push_str("img.capture{max-width:45%}</style>");
    html.push_str(&format!(
        "<h1>lensrig calibration</h1><p>Rig config <code>{}</code>; camera: {}; session <code>session/</code> ({} pair(s), {}).</p>",
        a.rig.rig.display(),
        rec.camera,
        rec.pairs.len(),
        rec.status
    ));
    let truth_grid = optics.as_ref().map(|o| o.truth_grid(o.f_number_open));
    let facts = facts_of(&cfg);
    let mut pairs_json = Vec::new();
    let mut medians = Vec::new();
    for (p, est) in &ests {
        let r = pair_section(&a.out, &session_dir, p, est, truth_grid.as_ref(), &facts)?;
        html.push_str(&r.html);
        pairs_json.push(r.json);
        medians.extend(r.truth.map(|t| t.0));
    }
    let (dist_html, dist_json) = distortion_section(&a.out, &session_dir, &cfg, &ests, optics.as_ref())?;
    let (lens_html, lens_json) = lensfun_section(&a.out, &session_dir, &rec, &ests, &facts, optics.as_ref())?;
    let (set_html, set_json) = profile_set_section(&a.out, &cfg, &ests, &facts)?;
    html.push_str(&dist_html);
    html.push_str(&lens_html);
    html.push_str(&set_html);
    let seconds = t0.elapsed().as_secs_f64();
    let summary = serde_json::json!({
        "rig": a.rig.rig.display().to_string(), "session": "session", "pairs": pairs_json, "distortion": dist_json, "lensfun": lens_json, "profile_set": set_json,
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
