//! The diagnosis on disk: `report.json`, `predicted_base.png` / `predicted_final.png` (16-bit,
//! the wide-open file's size, channels and encoding), `residual_base.png` /
//! `residual_final.png` (normalised residual `z`, −5 black … 0 mid-grey … +5 white, one colour
//! per channel), `index.html` (tables, the residual maps and inline-SVG plots of the curves
//! that pointed to each effect) and `profile/` (the corrected profile with its
//! `[corrections]` table). Files are replaced atomically.

use super::analysis::{residual_image, Analysis, Curve};
use super::{Diagnosis, Figures};
use crate::fsutil::{write_atomic, Overwrite};
use crate::image::io::{write_png16, write_png8};
use crate::image::Image;
use serde_json::json;
use std::fmt::Write as _;
use std::path::Path;

/// Why the report could not be written: the calibration report's error type, shared.
pub use crate::report::ReportError;

/// Where the inputs came from (for the report's header).
#[derive(Clone, Debug, Default)]
pub struct Sources {
    pub open: String,
    pub pinhole: String,
    pub profile: Option<String>,
}

fn stored_image(d: &Diagnosis, planes: Vec<crate::image::Plane>) -> Image {
    let mut img = Image::new(planes);
    img.channels = d.open.channels.clone();
    img.format = d.open.format;
    img.transfer = d.open.transfer;
    img.raw = d.open.raw.clone();
    img
}

/// The JSON report.
pub fn report_json(d: &Diagnosis, src: &Sources) -> serde_json::Value {
    json!({
        "format": "lensrig-diagnosis",
        "version": 1,
        "software": format!("lensrig {}", env!("CARGO_PKG_VERSION")),
        "created": crate::timestamp_utc(),
        "open": src.open,
        "pinhole": src.pinhole,
        "profile": src.profile,
        "verdict": d.verdict,
        "noise": d.noise,
        "base": d.base_figures(),
        "final": d.final_figures(),
        "effects": d.effects,
        "rounds": d.rounds,
        "cross_validation": { "held_out_reduced_chi2": d.cross_validation.0, "in_sample_reduced_chi2": d.cross_validation.1 },
        "low_band": { "base": d.low_band[0], "final": d.low_band[1] },
        "analysis": { "base": d.base_analysis, "final": d.final_analysis },
        "files": {
            "predicted_base": "predicted_base.png", "predicted_final": "predicted_final.png",
            "residual_base": "residual_base.png", "residual_final": "residual_final.png",
            "profile": "profile/profile.toml", "html": "index.html"
        }
    })
}

impl Diagnosis {
    pub fn base_figures(&self) -> Figures {
        Figures::of(&self.base)
    }
    pub fn final_figures(&self) -> Figures {
        Figures::of(&self.final_fit)
    }
}

/// Checks that `dir` may receive a diagnosis report: it is missing, empty, or holds a previous
/// diagnosis (its `report.json` says `"format": "lensrig-diagnosis"`). Anything else (a
/// calibration run's `index.html`, a profile, captures) is refused, so a report never
/// replaces another command's files. Called before the diagnosis starts, so a wrong `--out`
/// fails in a second rather than after the fit.
///
/// # Errors
/// [`ReportError::Foreign`] naming the first file found, or the I/O error listing `dir`.
pub fn check_report_dir(dir: &Path) -> Result<(), ReportError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(source) => return Err(ReportError::Io { path: dir.into(), source }),
    };
    let mut names: Vec<String> = entries.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    if names.is_empty() {
        return Ok(());
    }
    let is_diagnosis = std::fs::read_to_string(dir.join("report.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .is_some_and(|v| v["format"] == "lensrig-diagnosis");
    if is_diagnosis {
        return Ok(());
    }
    names.sort();
    let first = names.iter().find(|n| *n == "index.html").unwrap_or(&names[0]).clone();
    let found = if names.len() == 1 { first } else { format!("{first} and {} other file(s)", names.len() - 1) };
    Err(ReportError::Foreign { path: dir.into(), found, kind: "diagnosis report" })
}

/// Writes every report file into `dir` (created if missing; refused by [`check_report_dir`]
/// when it holds anything but a previous diagnosis).
///
/// # Errors
/// I/O errors naming the file; [`ReportError::Foreign`] for a directory of other files.
pub fn write_report(d: &Diagnosis, dir: &Path, src: &Sources) -> Result<(), ReportError> {
    check_report_dir(dir)?;
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Io { path: dir.into(), source })?;
    let p = |n: &str| dir.join(n);
    // raw CFA planes are previewed as bilinear RGB (crate::image::raw::for_output)
    let preview = |img: Image, name: &str| crate::image::raw::for_output(&img, &p(name));
    write_png16(&p("predicted_base.png"), &preview(stored_image(d, d.base.predicted.to_vec()), "predicted_base.png")?, Overwrite::Replace)?;
    write_png16(&p("predicted_final.png"), &preview(stored_image(d, d.final_fit.predicted.to_vec()), "predicted_final.png")?, Overwrite::Replace)?;
    for (name, fit) in [("residual_base.png", &d.base), ("residual_final.png", &d.final_fit)] {
        let mut img = Image::new(fit.normalized.iter().map(residual_image).collect());
        img.raw = d.open.raw.clone();
        write_png8(&p(name), &preview(img, name)?, Overwrite::Replace)?;
    }
    d.profile.save(&p("profile"))?;
    let text = serde_json::to_string_pretty(&report_json(d, src))?;
    write_atomic(&p("report.json"), text.as_bytes(), Overwrite::Replace).map_err(|source| ReportError::Io { path: p("report.json"), source })?;
    let html = html(d, src);
    write_atomic(&p("index.html"), html.as_bytes(), Overwrite::Replace).map_err(|source| ReportError::Io { path: p("index.html"), source })?;
    Ok(())
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// One plotted series: `(label, colour, points)`.
pub type Series<'a> = (&'a str, &'a str, Vec<(f64, f64)>);

/// A small line/point plot as inline SVG.
pub fn svg_plot(title: &str, xlabel: &str, ylabel: &str, series: &[Series]) -> String {
    let (wd, ht, ml, mb, mt, mr) = (420.0, 260.0, 58.0, 40.0, 26.0, 12.0);
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|s| s.2.iter().copied()).filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in &pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y1 = y0 + 1.0;
    }
    let pad = 0.05 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let sx = |x: f64| ml + (x - x0) / (x1 - x0) * (wd - ml - mr);
    let sy = |y: f64| ht - mb - (y - y0) / (y1 - y0) * (ht - mb - mt);
    let mut s = String::new();
    let _ = write!(s, "<svg xmlns=\"http://www.w3.org/2000/svg\" class=\"plot\" width=\"{wd}\" height=\"{ht}\" viewBox=\"0 0 {wd} {ht}\"><title>{}</title>", esc(title));
    let _ = write!(s, "<rect x=\"{ml}\" y=\"{mt}\" width=\"{}\" height=\"{}\" fill=\"#fafafa\" stroke=\"#999\"/>", wd - ml - mr, ht - mb - mt);
    let _ = write!(s, "<text x=\"{}\" y=\"16\" font-size=\"13\" text-anchor=\"middle\">{}</text>", wd / 2.0, esc(title));
    let _ = write!(s, "<text x=\"{}\" y=\"{}\" font-size=\"11\" text-anchor=\"middle\">{}</text>", (wd + ml) / 2.0, ht - 6.0, esc(xlabel));
    let _ = write!(s, "<text x=\"12\" y=\"{}\" font-size=\"11\" text-anchor=\"middle\" transform=\"rotate(-90 12 {})\">{}</text>", (ht - mb + mt) / 2.0, (ht - mb + mt) / 2.0, esc(ylabel));
    for (v, anchor, x, y) in [(x0, "start", sx(x0), ht - mb + 13.0), (x1, "end", sx(x1), ht - mb + 13.0)] {
        let _ = write!(s, "<text x=\"{x}\" y=\"{y}\" font-size=\"10\" text-anchor=\"{anchor}\">{}</text>", fmt_num(v));
    }
    for v in [y0, y1] {
        let _ = write!(s, "<text x=\"{}\" y=\"{}\" font-size=\"10\" text-anchor=\"end\">{}</text>", ml - 3.0, sy(v) + 4.0, fmt_num(v));
    }
    for (li, (label, color, data)) in series.iter().enumerate() {
        let path: Vec<String> = data.iter().filter(|p| p.0.is_finite() && p.1.is_finite()).map(|&(x, y)| format!("{:.1},{:.1}", sx(x), sy(y))).collect();
        if !path.is_empty() {
            let _ = write!(s, "<polyline fill=\"none\" stroke=\"{color}\" stroke-width=\"1.6\" points=\"{}\"/>", path.join(" "));
            for p in &path {
                let (px, py) = p.split_once(',').unwrap_or(("0", "0"));
                let _ = write!(s, "<circle cx=\"{px}\" cy=\"{py}\" r=\"2\" fill=\"{color}\"/>");
            }
        }
        let _ = write!(s, "<text x=\"{}\" y=\"{}\" font-size=\"11\" fill=\"{color}\">{}</text>", ml + 8.0, mt + 14.0 + 13.0 * li as f64, esc(label));
    }
    s.push_str("</svg>");
    s
}

fn fmt_num(v: f64) -> String {
    if v != 0.0 && (v.abs() < 1e-2 || v.abs() >= 1e4) { format!("{v:.2e}") } else { format!("{v:.3}") }
}

fn curve_points(c: &Curve, msq: bool) -> Vec<(f64, f64)> {
    c.x.iter().zip(if msq { &c.msq } else { &c.mean }).map(|(&x, &y)| (x, y)).collect()
}

fn figures_row(name: &str, f: &Figures) -> String {
    format!(
        "<tr><td>{name}</td><td>{:.4}</td><td>{:.3e}</td><td>{:.3e}</td><td>{} ({:.0} effective)</td><td>{:.1}</td></tr>",
        f.reduced_chi2, f.rms, f.noise_rms, f.parameters, f.effective_parameters, f.bic
    )
}

fn curves_svg(base: &Analysis, fin: &Analysis) -> String {
    let mut s = String::new();
    for c in &base.curves {
        let f = fin.curves.iter().find(|q| q.name == c.name);
        let mut series = vec![("base: mean z", "#c0392b", curve_points(c, false)), ("base: mean z²", "#e67e22", curve_points(c, true))];
        if let Some(f) = f {
            series.push(("final: mean z", "#2471a3", curve_points(f, false)));
            series.push(("final: mean z²", "#17a589", curve_points(f, true)));
        }
        s.push_str(&svg_plot(&format!("residual against {}", c.name.replace('_', " ")), &c.name.replace('_', " "), "z", &series));
    }
    s
}

fn html(d: &Diagnosis, src: &Sources) -> String {
    let mut h = String::from("<!doctype html><html lang=\"en\"><meta charset=\"utf-8\"><title>lensrig diagnosis</title><style>body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:3px 9px;text-align:left}img{image-rendering:pixelated;border:1px solid #ccc;max-width:48%}.plot{margin:4px}.effect{border-left:4px solid #2471a3;padding-left:1em;margin:1em 0}code{background:#eee;padding:1px 4px}</style><body>");
    let _ = write!(h, "<h1>lensrig diagnosis</h1><p>Wide-open <code>{}</code>, pinhole <code>{}</code>, profile <code>{}</code>.</p>", esc(&src.open), esc(&src.pinhole), esc(src.profile.as_deref().unwrap_or("estimated here")));
    let _ = write!(h, "<h2 id=\"verdict\">Verdict</h2><p><b>{}</b></p>", esc(&d.verdict));
    if let Some(b) = &d.low_band[1] {
        let _ = write!(h, "<p>Low-band test of the final model: {}.</p>", esc(&super::band_text(b)));
    }
    h.push_str("<h2>Fit</h2><table><tr><th>model</th><th>reduced χ²</th><th>residual RMS</th><th>noise floor RMS</th><th>parameters (nominal)</th><th>BIC</th></tr>");
    h.push_str(&figures_row("base", &d.base_figures()));
    for e in &d.effects {
        h.push_str(&figures_row(&format!("+ {}", e.name), &e.after));
    }
    h.push_str(&figures_row("final", &d.final_figures()));
    let held_out = d.cross_validation.0.map_or("not measured (no evaluated pixel on either half)".to_string(), |v| format!("{v:.4}"));
    let _ = write!(h, "</table><p>Cross-validation (fit on one half of a 16-px checkerboard, evaluated on the other): held-out reduced χ² {held_out}, in-sample {:.4}.</p>", d.cross_validation.1);
    h.push_str("<h2 id=\"effects\">Effects found</h2>");
    if d.effects.is_empty() {
        h.push_str("<p>None.</p>");
    }
    for (i, e) in d.effects.iter().enumerate() {
        let _ = write!(
            h,
            "<div class=\"effect\"><h3>{}. <code>{}</code></h3><p><b>Evidence:</b> {}</p><p><b>Where:</b> {}</p><p><b>Parameters:</b> <code>{}</code></p><p>Reduced χ² {:.4} → {:.4}, ΔBIC {:.1}.</p></div>",
            i + 1,
            esc(&e.name),
            esc(&e.evidence),
            esc(&e.location),
            esc(&e.parameters.to_string()),
            e.before.reduced_chi2,
            e.after.reduced_chi2,
            e.delta_bic
        );
    }
    h.push_str("<h2>Residual maps</h2><p>Normalised residual z = (recorded − predicted)/σ, −5 black, 0 grey, +5 white. Before (base model) and after (final model):</p><img src=\"residual_base.png\" alt=\"residual of the base model\"> <img src=\"residual_final.png\" alt=\"residual of the final model\">");
    h.push_str("<h2>Predictions</h2><img src=\"predicted_base.png\" alt=\"prediction of the base model\"> <img src=\"predicted_final.png\" alt=\"prediction of the final model\">");
    h.push_str("<h2>What the residual depends on</h2><div>");
    h.push_str(&curves_svg(&d.base_analysis, &d.final_analysis));
    let hist = |a: &Analysis| -> Vec<(f64, f64)> { a.histogram_edges.windows(2).zip(&a.histogram).map(|(e, &v)| (0.5 * (e[0] + e[1]), v)).collect() };
    let normal: Vec<(f64, f64)> = d.base_analysis.histogram_edges.windows(2).zip(&d.base_analysis.histogram_normal).map(|(e, &v)| (0.5 * (e[0] + e[1]), v)).collect();
    h.push_str(&svg_plot("histogram of z against the normal law", "z", "density", &[("base", "#c0392b", hist(&d.base_analysis)), ("final", "#2471a3", hist(&d.final_analysis)), ("N(0,1)", "#555", normal)]));
    h.push_str(&svg_plot("residual power spectrum (mean over frequencies = reduced χ²; 1 = white noise at the floor)", "cycles/px", "power of z", &[("base", "#c0392b", d.base_analysis.spectrum.clone()), ("final", "#2471a3", d.final_analysis.spectrum.clone()), ("floor", "#555", d.base_analysis.spectrum.iter().map(|&(f, _)| (f, 1.0)).collect())]));
    h.push_str("</div><h2>Noise model</h2><table><tr><th>channel</th><th>a (Var = a·L + b)</th><th>b</th><th>misfit</th><th>misfit if linear</th><th>floor RMS</th><th>measured from</th><th>lost detail ÷ noise</th></tr>");
    for n in &d.noise {
        let tested = if n.law_tested { "" } else { " (not tested)" };
        let _ = write!(h, "<tr><td>{}</td><td>{:.4e}</td><td>{:.4e}</td><td>{:.1}%{tested}</td><td>{:.1}%</td><td>{:.3e}</td><td>{}</td><td>{:.2}</td></tr>", esc(&n.channel), n.a, n.b, 100.0 * n.misfit, 100.0 * n.misfit_linear, n.floor_rms, n.source, n.lost_detail);
    }
    h.push_str("</table><div>");
    for n in &d.noise {
        let pts: Vec<(f64, f64)> = n.curve.bins.iter().map(|b| (b.0, b.1)).collect();
        h.push_str(&svg_plot(&format!("noise variance, channel {}", n.channel), "stored value", "variance", &[("measured bins", "#2471a3", pts)]));
    }
    h.push_str("</div><h2>Candidates per round</h2>");
    for (i, r) in d.rounds.iter().enumerate() {
        let _ = write!(h, "<h3>Round {}</h3><table><tr><th>candidate</th><th>reduced χ²</th><th>ΔBIC vs null refit</th><th>note</th></tr>", i + 1);
        for c in r {
            let [chi2, dbic] = c.figures();
            let _ = write!(h, "<tr><td>{}</td><td>{chi2}</td><td>{dbic}</td><td>{}</td></tr>", esc(&c.name), esc(&c.note));
        }
        h.push_str("</table>");
    }
    h.push_str("<h2>Per-tile residual (final model)</h2><table><tr><th>channel</th><th>column</th><th>row</th><th>mean z</th><th>spread</th><th>reduced χ²</th></tr>");
    for t in &d.final_analysis.tiles {
        let _ = write!(h, "<tr><td>{}</td><td>{}</td><td>{}</td><td>{:+.3}</td><td>{:.3}</td><td>{:.3}</td></tr>", esc(&t.channel), t.column, t.row, t.mean, t.spread, t.reduced_chi2);
    }
    h.push_str("</table><p>The corrected profile is in <code>profile/</code>; its <code>[corrections]</code> table is applied by <code>lensrig simulate</code>.</p>");
    // lets a headless browser (and the tests) see whether every image loaded
    h.push_str("<script>window.addEventListener('load',()=>{const i=[...document.images];document.body.dataset.imagesLoaded=i.filter(x=>x.complete&&x.naturalWidth>0).length+'/'+i.length;});</script></body></html>");
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_directory_is_missing_empty_or_a_previous_diagnosis() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().join("rep");
        check_report_dir(&d).unwrap();
        std::fs::create_dir(&d).unwrap();
        check_report_dir(&d).unwrap();
        std::fs::write(d.join("report.json"), r#"{"format": "lensrig-diagnosis", "version": 1}"#).unwrap();
        std::fs::write(d.join("index.html"), "old diagnosis").unwrap();
        check_report_dir(&d).unwrap();
        // a calibration run: index.html and summary.json, no diagnosis report.json
        let cal = dir.path().join("cal");
        std::fs::create_dir(&cal).unwrap();
        std::fs::write(cal.join("index.html"), "calibration").unwrap();
        std::fs::write(cal.join("summary.json"), "{}").unwrap();
        let e = check_report_dir(&cal).unwrap_err().to_string();
        assert!(e.contains("index.html and 1 other file(s)") && e.contains("not a diagnosis report"), "{e}");
        // a report.json of another format does not pass either
        std::fs::write(cal.join("report.json"), r#"{"format": "lensrig-calibration"}"#).unwrap();
        assert!(matches!(check_report_dir(&cal), Err(ReportError::Foreign { .. })));
        // a damaged report.json is not a diagnosis
        std::fs::write(d.join("report.json"), "{ damaged").unwrap();
        assert!(matches!(check_report_dir(&d), Err(ReportError::Foreign { .. })));
    }
}
