//! SVG plots of a [`ProfileReport`]: a field map of one value per tile, MTF curves, lateral
//! colour arrows. Plain SVG 1.1 text, no scripts, no external fonts; coordinates in SVG user
//! units (1 = 1 CSS px). Values are printed with [`super::fixed`] rounding.

use super::{fixed, mtf, ProfileReport};
use std::fmt::Write as _;

fn colour(name: &str) -> &'static str {
    match name {
        "R" => "#d62728",
        "G" => "#2ca02c",
        "B" => "#1f77b4",
        _ => "#333333",
    }
}

/// A white → blue shade for `t ∈ [0, 1]`.
fn shade(t: f64) -> String {
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 0.0 };
    let r = (255.0 - 200.0 * t) as u8;
    let g = (255.0 - 140.0 * t) as u8;
    format!("rgb({r},{g},255)")
}

/// A map of one value per tile over the sensor (cells coloured by value, value printed).
pub fn field_map(r: &ProfileReport, values: &[f64], title: &str) -> String {
    let (cw, ch) = (64.0, 40.0);
    let (w, h) = (cw * r.columns as f64, ch * r.rows as f64 + 22.0);
    let hi = values.iter().copied().filter(|v| v.is_finite()).fold(1e-9, f64::max);
    let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">");
    let _ = write!(s, "<text x=\"2\" y=\"15\">{title}</text>");
    for (t, v) in values.iter().enumerate() {
        let (x, y) = ((t % r.columns) as f64 * cw, (t / r.columns) as f64 * ch + 22.0);
        let _ = write!(s, "<rect x=\"{x}\" y=\"{y}\" width=\"{cw}\" height=\"{ch}\" fill=\"{}\" stroke=\"#fff\"/><text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{}</text>", shade(v / hi), x + cw / 2.0, y + ch / 2.0 + 4.0, fixed(*v, 3));
    }
    s.push_str("</svg>");
    s
}

/// MTF curves of channel `c`: centre, mean of the edge midpoints, mean of the corners;
/// tangential solid, sagittal dashed.
pub fn mtf_curves(r: &ProfileReport, c: usize) -> String {
    let (w, h, l, b, t, rt) = (420.0, 280.0, 44.0, 36.0, 22.0, 110.0);
    let (pw, ph) = (w - l - rt, h - t - b);
    let fs = mtf::curve_frequencies();
    let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"11\">");
    let _ = write!(s, "<text x=\"{l}\" y=\"14\">{} MTF</text>", r.channels[c]);
    // axes and grid
    for i in 0..=5 {
        let x = l + pw * i as f64 / 5.0;
        let _ = write!(s, "<line x1=\"{x}\" y1=\"{t}\" x2=\"{x}\" y2=\"{}\" stroke=\"#ddd\"/><text x=\"{x}\" y=\"{}\" text-anchor=\"middle\">{}</text>", t + ph, t + ph + 14.0, fixed(0.1 * i as f64, 1));
        let y = t + ph * (1.0 - i as f64 / 5.0);
        let _ = write!(s, "<line x1=\"{l}\" y1=\"{y}\" x2=\"{}\" y2=\"{y}\" stroke=\"#ddd\"/><text x=\"{}\" y=\"{}\" text-anchor=\"end\">{}</text>", l + pw, l - 4.0, y + 4.0, fixed(0.2 * i as f64, 1));
    }
    let _ = write!(s, "<line x1=\"{l}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"#999\" stroke-dasharray=\"2,3\"/>", t + ph * 0.5, l + pw, t + ph * 0.5);
    let _ = write!(s, "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">cycles/pixel</text>", l + pw / 2.0, h - 4.0);
    let groups: [(&str, &str, f64); 3] = [("centre", "centre", 1.0), ("edge", "edges", 0.7), ("corner", "corners", 0.4)];
    for (gi, (prefix, label, alpha)) in groups.iter().enumerate() {
        let sets: Vec<_> = r.curves.iter().filter(|cs| cs.position.starts_with(prefix)).collect();
        if sets.is_empty() {
            continue;
        }
        for (dir, dash) in [(0usize, ""), (1, " stroke-dasharray=\"5,3\"")] {
            let mean: Vec<f64> = (0..fs.len()).map(|i| sets.iter().map(|cs| if dir == 0 { cs.tangential[c][i] } else { cs.sagittal[c][i] }).sum::<f64>() / sets.len() as f64).collect();
            let pts: Vec<String> = fs.iter().zip(&mean).map(|(f, m)| format!("{:.1},{:.1}", l + pw * f / 0.5, t + ph * (1.0 - m.clamp(0.0, 1.0)))).collect();
            let _ = write!(s, "<polyline fill=\"none\" stroke=\"{}\" stroke-opacity=\"{alpha}\" stroke-width=\"{}\"{dash} points=\"{}\"/>", colour(&r.channels[c]), 2.5 - gi as f64 * 0.5, pts.join(" "));
        }
        let y = t + 14.0 + 16.0 * gi as f64;
        let _ = write!(s, "<line x1=\"{}\" y1=\"{y}\" x2=\"{}\" y2=\"{y}\" stroke=\"{}\" stroke-opacity=\"{alpha}\" stroke-width=\"2\"/><text x=\"{}\" y=\"{}\">{label}</text>", l + pw + 8.0, l + pw + 30.0, colour(&r.channels[c]), l + pw + 34.0, y + 4.0);
    }
    let y = t + 14.0 + 16.0 * 3.0;
    let _ = write!(s, "<text x=\"{}\" y=\"{y}\">solid: tan</text><text x=\"{}\" y=\"{}\">dashed: sag</text>", l + pw + 8.0, l + pw + 8.0, y + 14.0);
    s.push_str("</svg>");
    s
}

/// Lateral colour arrows: at each tile, the R and B centroids minus the reference channel's,
/// magnified so the longest arrow is about a third of a tile.
pub fn lateral_arrows(r: &ProfileReport) -> String {
    let scale_px = 480.0 / r.width.max(1) as f64;
    let (w, h) = (480.0, r.height as f64 * scale_px + 24.0);
    let tile_len = (w / r.columns.max(1) as f64).min((h - 24.0) / r.rows.max(1) as f64);
    let mx = (0..r.tiles.len()).flat_map(|t| (0..r.channels.len()).map(move |c| (c, t))).map(|(c, t)| { let (x, y) = r.lateral(c, t); x.hypot(y) }).fold(0.0, f64::max);
    // magnification: a round number so the figure reads "×50"
    let raw = if mx > 1e-6 { tile_len / 3.0 / (mx * scale_px) } else { 1.0 };
    let mag = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0].iter().copied().filter(|m| *m <= raw).fold(1.0, f64::max);
    let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">");
    s.push_str("<defs>");
    for (id, col) in [("R", colour("R")), ("B", colour("B")), ("Y", colour("Y"))] {
        let _ = write!(s, "<marker id=\"h{id}\" markerWidth=\"6\" markerHeight=\"6\" refX=\"5\" refY=\"3\" orient=\"auto\"><path d=\"M0,0 L6,3 L0,6 z\" fill=\"{col}\"/></marker>");
    }
    s.push_str("</defs>");
    let _ = write!(s, "<text x=\"2\" y=\"15\">lateral colour vs {} (arrows ×{mag}, longest {} px)</text>", r.channels[r.reference], fixed(mx, 2));
    let _ = write!(s, "<rect x=\"0\" y=\"24\" width=\"{w}\" height=\"{}\" fill=\"none\" stroke=\"#999\"/>", h - 24.0);
    for (t, f) in r.tiles.iter().enumerate() {
        let (x0, y0) = (f.x * scale_px, f.y * scale_px + 24.0);
        let _ = write!(s, "<circle cx=\"{x0:.1}\" cy=\"{y0:.1}\" r=\"1.5\" fill=\"#666\"/>");
        for c in 0..r.channels.len() {
            if c == r.reference {
                continue;
            }
            let (dx, dy) = r.lateral(c, t);
            let id = match r.channels[c].as_str() {
                "R" => "R",
                "B" => "B",
                _ => "Y",
            };
            let _ = write!(s, "<line x1=\"{x0:.1}\" y1=\"{y0:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"{}\" stroke-width=\"1.5\" marker-end=\"url(#h{id})\"/>", x0 + dx * mag * scale_px, y0 + dy * mag * scale_px, colour(&r.channels[c]));
        }
    }
    s.push_str("</svg>");
    s
}
