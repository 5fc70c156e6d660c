//! The MTF and colour report of a lens profile (`lensrig report`, and the per-profile section
//! of `calibrate`'s `index.html`).
//!
//! From a profile's PSF grid it computes, per channel and tile: MTF50 tangential and sagittal
//! ([`mtf`]), the 80 % encircled-energy radius about the centroid to sub-pixel precision, the
//! centroid ([`colour`]); across the field: lateral colour (R and B centroids minus G); on axis:
//! longitudinal colour (per-channel blur size at the tile nearest the optical centre); and MTF
//! curves at the centre, the four edge midpoints and the four corners.
//!
//! # Units and rounding
//! Frequencies in cycles/pixel, and lp/mm when the pixel pitch is known
//! (`lp/mm = c/px · 1000 / pitch_µm`); distances in pixels. Printed numbers carry what the
//! measurement resolves: MTF values and c/px to 3 decimals, lp/mm to 3 significant figures,
//! radii and colour offsets to 0.01 px. CSV files are written with the same rounding; a value
//! that is not finite is written as an empty field, never as `NaN`.
//!
//! # Files ([`write_report`])
//! `index.html`, `mtf50.csv` (one row per tile and channel), `mtf-curves.csv` (long format:
//! position, channel, direction, frequency, MTF), `psf-<CH>.png` (each tile's kernel scaled to
//! its peak, square-root display), `psf-rgb.png` (the channels as one colour image, when the
//! profile has R, G and B), `mtf50-<CH>-{tan,sag}.svg`, `mtf-curves-<CH>.svg`,
//! `lateral-colour.svg`; with the profile's uncertainty mosaics, `uncertainty-<CH>.svg` (field
//! map of the predicted relative L2 error per kernel, per cent) and `uncertainty.csv`.

pub mod colour;
pub mod mtf;
pub mod svg;

use crate::fsutil::{write_atomic, Overwrite};
use crate::image::io::{write_png8, ImageError};
use crate::image::{Image, Plane};
use crate::optics::psf_grid::PsfGrid;
use crate::profile::Profile;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Why a report (the calibration report, or the diagnosis's) could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("cannot write {path}: {source}")]
    Io { path: PathBuf, #[source] source: std::io::Error },
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error(transparent)]
    Profile(#[from] crate::profile::ProfileError),
    #[error("cannot serialise the report: {0}")]
    Json(#[from] serde_json::Error),
    /// The output directory holds files that are not this kind of report (another command's
    /// report or a user's data): nothing is written into it.
    #[error("{path} already holds {found}, which is not a {kind}; nothing was written (choose an empty directory or a previous {kind}'s)")]
    Foreign { path: PathBuf, found: String, kind: &'static str },
}

/// Figures of one tile, per channel (index = channel).
#[derive(Clone, Debug, PartialEq)]
pub struct TileFigures {
    /// Tile centre, pixels.
    pub x: f64,
    pub y: f64,
    /// MTF50 along the radius (tangential) and across it (sagittal), cycles/px.
    pub mtf50_tan: Vec<f64>,
    pub mtf50_sag: Vec<f64>,
    /// 80 % encircled-energy radius about the centroid, px.
    pub ee80: Vec<f64>,
    /// Second-moment radius, px.
    pub rms: Vec<f64>,
    /// Kernel centroid relative to the centre pixel, px.
    pub centroid: Vec<(f64, f64)>,
}

/// MTF curves at one field position.
#[derive(Clone, Debug, PartialEq)]
pub struct CurveSet {
    /// `centre`, `edge-left`, … `corner-bottom-right`.
    pub position: String,
    pub tile: usize,
    /// Per channel, sampled at [`mtf::curve_frequencies`].
    pub tangential: Vec<Vec<f64>>,
    pub sagittal: Vec<Vec<f64>>,
}

/// The whole analysis of one profile.
#[derive(Clone, Debug, PartialEq)]
pub struct ProfileReport {
    pub channels: Vec<String>,
    pub width: usize,
    pub height: usize,
    pub columns: usize,
    pub rows: usize,
    /// Pixel pitch, µm, when known (enables lp/mm).
    pub pitch_um: Option<f64>,
    pub tiles: Vec<TileFigures>,
    pub curves: Vec<CurveSet>,
    /// Index of the tile nearest the optical centre.
    pub axis_tile: usize,
    /// Channel lateral colour is measured against (`G` when present, else the first).
    pub reference: usize,
    /// Predicted relative L2 error per channel and tile (`‖u‖₂ / ‖b‖₂`,
    /// [`crate::estimate::bootstrap::predicted_error`]) when the profile has uncertainty
    /// mosaics ([`crate::profile::uncertainty`]); `None` otherwise.
    pub uncertainty: Option<Vec<Vec<f64>>>,
    /// The tile core (px) `deblur` restores this profile with by default, and the relative
    /// kernel error of restoring each tile with its centre's PSF
    /// ([`crate::deconv::default_tile_core`]; docs/deconvolution.md "Tile size"), when a report
    /// shows them ([`ProfileReport::with_restoration_tiles`]); `None` otherwise.
    pub restoration_tiles: Option<(usize, f64)>,
}

/// Unit radial direction of a field point (x when on axis).
fn radial(x: f64, y: f64, w: usize, h: usize) -> (f64, f64) {
    let (dx, dy) = (x - (w as f64 - 1.0) / 2.0, y - (h as f64 - 1.0) / 2.0);
    let r = dx.hypot(dy);
    if r < 0.05 * (w.min(h) as f64) {
        (1.0, 0.0)
    } else {
        (dx / r, dy / r)
    }
}

fn nearest_tile(g: &PsfGrid, x: f64, y: f64) -> usize {
    (0..g.tile_count())
        .min_by(|&a, &b| {
            let da = (g.centers[a][0] - x).powi(2) + (g.centers[a][1] - y).powi(2);
            let db = (g.centers[b][0] - x).powi(2) + (g.centers[b][1] - y).powi(2);
            da.total_cmp(&db)
        })
        .unwrap_or(0)
}

/// Analyses a PSF grid measured on a `width × height` sensor.
pub fn analyse(g: &PsfGrid, width: usize, height: usize, pitch_um: Option<f64>) -> ProfileReport {
    let nc = g.channels.len();
    let tiles: Vec<TileFigures> = (0..g.tile_count())
        .map(|t| {
            let [x, y] = g.centers[t];
            let (ux, uy) = radial(x, y, width, height);
            let ks: Vec<&Plane> = (0..nc).map(|c| &g.kernels[c][t]).collect();
            TileFigures {
                x,
                y,
                mtf50_tan: ks.iter().map(|k| mtf::kernel_mtf50(k, ux, uy)).collect(),
                mtf50_sag: ks.iter().map(|k| mtf::kernel_mtf50(k, -uy, ux)).collect(),
                ee80: ks.iter().map(|k| colour::encircled_energy_radius(k, 0.8)).collect(),
                rms: ks.iter().map(|k| colour::rms_radius(k)).collect(),
                centroid: ks.iter().map(|k| colour::centroid(k)).collect(),
            }
        })
        .collect();
    let (xm, ym) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    let (xr, yb) = (width as f64 - 1.0, height as f64 - 1.0);
    let positions = [
        ("centre", xm, ym),
        ("edge-left", 0.0, ym),
        ("edge-right", xr, ym),
        ("edge-top", xm, 0.0),
        ("edge-bottom", xm, yb),
        ("corner-top-left", 0.0, 0.0),
        ("corner-top-right", xr, 0.0),
        ("corner-bottom-left", 0.0, yb),
        ("corner-bottom-right", xr, yb),
    ];
    let curves = positions
        .iter()
        .map(|&(name, x, y)| {
            let t = nearest_tile(g, x, y);
            let [tx, ty] = g.centers[t];
            let (ux, uy) = radial(tx, ty, width, height);
            CurveSet {
                position: name.to_string(),
                tile: t,
                tangential: (0..nc).map(|c| mtf::kernel_mtf_curve(&g.kernels[c][t], ux, uy)).collect(),
                sagittal: (0..nc).map(|c| mtf::kernel_mtf_curve(&g.kernels[c][t], -uy, ux)).collect(),
            }
        })
        .collect();
    let reference = g.channels.iter().position(|c| c == "G").unwrap_or(0);
    ProfileReport { channels: g.channels.clone(), width, height, columns: g.columns, rows: g.rows, pitch_um, tiles, curves, axis_tile: nearest_tile(g, xm, ym), reference, uncertainty: None, restoration_tiles: None }
}

impl ProfileReport {
    /// Adds the predicted relative L2 error of every kernel of `g` from its uncertainty map
    /// `unc[channel][tile]` (the `psf-unc-<C>.tiff` mosaics, [`crate::profile::uncertainty`]).
    pub fn with_uncertainty(mut self, g: &PsfGrid, unc: &[Vec<Plane>]) -> Self {
        let e = unc.iter().zip(&g.kernels).map(|(us, ks)| us.iter().zip(ks).map(|(u, k)| crate::estimate::bootstrap::predicted_error(u, k)).collect()).collect();
        self.uncertainty = Some(e);
        self
    }

    /// Adds the tile core `deblur` takes by default for `g` and its tile-centre kernel error
    /// ([`crate::deconv::default_tile_core`]): a few hundred kernel interpolations, left out of
    /// the analyses that only compare MTFs (the truth's, the lensfun export's).
    pub fn with_restoration_tiles(mut self, g: &PsfGrid) -> Self {
        self.restoration_tiles = Some(crate::deconv::default_tile_core(g, self.width, self.height));
        self
    }

    /// Lateral colour of channel `c` at tile `t`: its centroid minus the reference's, px.
    pub fn lateral(&self, c: usize, t: usize) -> (f64, f64) {
        let a = self.tiles[t].centroid[c];
        let r = self.tiles[t].centroid[self.reference];
        (a.0 - r.0, a.1 - r.1)
    }

    /// Cycles/px → lp/mm with the pixel pitch.
    pub fn lp_mm(&self, cpx: f64) -> Option<f64> {
        self.pitch_um.map(|p| cpx * 1000.0 / p)
    }
}

/// Decimal rounding to `d` places; `""` when not finite.
pub fn fixed(v: f64, d: usize) -> String {
    if v.is_finite() {
        format!("{v:.d$}")
    } else {
        String::new()
    }
}

/// Rounding to `s` significant figures; `""` when not finite.
pub fn significant(v: f64, s: usize) -> String {
    if !v.is_finite() {
        return String::new();
    }
    if v == 0.0 {
        return "0".into();
    }
    let mag = v.abs().log10().floor() as i32;
    let d = (s as i32 - 1 - mag).max(0) as usize;
    format!("{v:.d$}")
}

/// `uncertainty.csv` (`tile,row,column,x_px,y_px,channel,predicted_relative_l2`, one row per
/// tile and channel, the error to 4 significant figures), or `None` without uncertainty.
pub fn uncertainty_csv(r: &ProfileReport) -> Option<String> {
    let u = r.uncertainty.as_ref()?;
    let mut s = String::from("tile,row,column,x_px,y_px,channel,predicted_relative_l2\n");
    for (t, f) in r.tiles.iter().enumerate() {
        for (c, ch) in r.channels.iter().enumerate() {
            let v = u.get(c).and_then(|v| v.get(t)).copied().unwrap_or(f64::NAN);
            let _ = writeln!(s, "{t},{},{},{},{},{ch},{}", t / r.columns.max(1), t % r.columns.max(1), fixed(f.x, 2), fixed(f.y, 2), significant(v, 4));
        }
    }
    Some(s)
}

/// `mtf50.csv`: one row per tile and channel.
pub fn mtf50_csv(r: &ProfileReport) -> String {
    let mut s = String::from("tile,x_px,y_px,channel,mtf50_tan_cpx,mtf50_sag_cpx,mtf50_tan_lpmm,mtf50_sag_lpmm,ee80_px,centroid_dx_px,centroid_dy_px,lateral_dx_px,lateral_dy_px\n");
    for (t, f) in r.tiles.iter().enumerate() {
        for (c, name) in r.channels.iter().enumerate() {
            let lp = |v: f64| r.lp_mm(v).map(|x| significant(x, 3)).unwrap_or_default();
            let (lx, ly) = r.lateral(c, t);
            let _ = writeln!(
                s,
                "{t},{},{},{name},{},{},{},{},{},{},{},{},{}",
                fixed(f.x, 1),
                fixed(f.y, 1),
                fixed(f.mtf50_tan[c], 3),
                fixed(f.mtf50_sag[c], 3),
                lp(f.mtf50_tan[c]),
                lp(f.mtf50_sag[c]),
                fixed(f.ee80[c], 2),
                fixed(f.centroid[c].0, 2),
                fixed(f.centroid[c].1, 2),
                fixed(lx, 2),
                fixed(ly, 2)
            );
        }
    }
    s
}

/// `mtf-curves.csv`: long format, one row per position, channel, direction and frequency.
pub fn curves_csv(r: &ProfileReport) -> String {
    let mut s = String::from("position,tile,channel,direction,f_cpx,f_lpmm,mtf\n");
    let fs = mtf::curve_frequencies();
    for cs in &r.curves {
        for (c, name) in r.channels.iter().enumerate() {
            for (dir, curve) in [("tangential", &cs.tangential[c]), ("sagittal", &cs.sagittal[c])] {
                for (f, m) in fs.iter().zip(curve) {
                    let lp = r.lp_mm(*f).map(|x| significant(x, 3)).unwrap_or_default();
                    let _ = writeln!(s, "{},{},{name},{dir},{},{lp},{}", cs.position, cs.tile, fixed(*f, 2), fixed(*m, 3));
                }
            }
        }
    }
    s
}

/// Each tile's kernel scaled to its peak, square-root display, one mosaic for channel `c`.
pub fn psf_mosaic(g: &PsfGrid, c: usize) -> Plane {
    let k = g.kernel_size;
    let mut m = Plane::new(g.columns * (k + 2), g.rows * (k + 2));
    for t in 0..g.tile_count() {
        let mut kk = g.kernels[c][t].clone();
        let mx = kk.max().max(1e-12);
        kk.scale(1.0 / mx);
        let kk = kk.map(|v| v.max(0.0).sqrt());
        m.paste(&kk, ((t % g.columns) * (k + 2) + 1) as isize, ((t / g.columns) * (k + 2) + 1) as isize);
    }
    m
}

/// The R, G, B mosaics as one colour image (each tile scaled to its brightest channel's
/// peak, so colour fringes show), or `None` without all three channels.
pub fn psf_colour_mosaic(g: &PsfGrid) -> Option<Image> {
    let idx: Vec<usize> = ["R", "G", "B"].iter().filter_map(|n| g.channels.iter().position(|c| c == n)).collect();
    if idx.len() != 3 {
        return None;
    }
    let k = g.kernel_size;
    let mut planes = vec![Plane::new(g.columns * (k + 2), g.rows * (k + 2)); 3];
    for t in 0..g.tile_count() {
        let mx = idx.iter().map(|&c| g.kernels[c][t].max()).fold(1e-12f32, f32::max);
        for (p, &c) in planes.iter_mut().zip(&idx) {
            let kk = g.kernels[c][t].map(|v| (v / mx).max(0.0).sqrt());
            p.paste(&kk, ((t % g.columns) * (k + 2) + 1) as isize, ((t / g.columns) * (k + 2) + 1) as isize);
        }
    }
    Some(Image::new(planes))
}

/// Upscales a plane by an integer factor (nearest neighbour), for legible thumbnails.
fn upscale(p: &Plane, f: usize) -> Plane {
    Plane::from_fn(p.width * f, p.height * f, |x, y| p.get(x / f, y / f))
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ReportError + '_ {
    move |source| ReportError::Io { path: path.to_path_buf(), source }
}

/// The HTML fragment of a report (no `<html>` wrapper); asset paths are prefixed with
/// `prefix` (e.g. `"report/stage-20/"`, or `""` next to the files).
pub fn html_section(r: &ProfileReport, prefix: &str) -> String {
    let mut h = String::new();
    let pitch = match r.pitch_um {
        Some(p) => format!("pixel pitch {} µm", significant(p, 3)),
        None => "pixel pitch unknown (lp/mm not given; pass --pixel-pitch-um)".into(),
    };
    let _ = write!(h, "<p>{} channel(s) {}, {}×{} tiles on a {}×{} px sensor, {pitch}. Frequencies in cycles/pixel (c/px){}.</p>", r.channels.len(), r.channels.join(" "), r.columns, r.rows, r.width, r.height, if r.pitch_um.is_some() { " and line pairs per mm" } else { "" });
    // PSF grids
    h.push_str("<h4>PSFs per tile</h4><p>Each tile's kernel scaled to its peak, square-root display.</p><div class=row>");
    if r.channels.len() == 3 && r.channels.iter().all(|c| ["R", "G", "B"].contains(&c.as_str())) {
        let _ = write!(h, "<figure><img src=\"{prefix}psf-rgb.png\" alt=\"PSF grid, colour\"><figcaption>R, G, B together</figcaption></figure>");
    }
    for ch in &r.channels {
        let _ = write!(h, "<figure><img src=\"{prefix}psf-{ch}.png\" alt=\"PSF grid {ch}\"><figcaption>{ch}</figcaption></figure>");
    }
    h.push_str("</div>");
    // MTF50 table on axis + field maps
    h.push_str("<h4>MTF50</h4><table class=num><tr><th>channel</th><th>on axis tan / sag (c/px)</th>");
    if r.pitch_um.is_some() {
        h.push_str("<th>on axis tan / sag (lp/mm)</th>");
    }
    h.push_str("<th>field min … max (c/px)</th><th>80 % EE radius on axis (px)</th><th>RMS radius on axis (px)</th></tr>");
    let a = &r.tiles[r.axis_tile];
    for (c, ch) in r.channels.iter().enumerate() {
        let all: Vec<f64> = r.tiles.iter().flat_map(|t| [t.mtf50_tan[c], t.mtf50_sag[c]]).collect();
        let (lo, hi) = (all.iter().copied().fold(f64::INFINITY, f64::min), all.iter().copied().fold(0.0, f64::max));
        let _ = write!(h, "<tr><td>{ch}</td><td>{} / {}</td>", fixed(a.mtf50_tan[c], 3), fixed(a.mtf50_sag[c], 3));
        if let (Some(t), Some(s)) = (r.lp_mm(a.mtf50_tan[c]), r.lp_mm(a.mtf50_sag[c])) {
            let _ = write!(h, "<td>{} / {}</td>", significant(t, 3), significant(s, 3));
        }
        let _ = write!(h, "<td>{} … {}</td><td>{}</td><td>{}</td></tr>", fixed(lo, 3), fixed(hi, 3), fixed(a.ee80[c], 2), fixed(a.rms[c], 2));
    }
    h.push_str("</table><p>Longitudinal colour: the per-channel blur on axis (EE and RMS radius columns above); a channel focused behind or in front of the others is larger.</p>");
    h.push_str("<p>MTF50 across the field (c/px; tangential = frequency along the radius, sagittal = across it; 0.500 means the modulation is still above one half at Nyquist):</p><div class=row>");
    for ch in &r.channels {
        for d in ["tan", "sag"] {
            let _ = write!(h, "<figure><img src=\"{prefix}mtf50-{ch}-{d}.svg\" alt=\"MTF50 map {ch} {d}\"><figcaption>{ch} {d}</figcaption></figure>");
        }
    }
    h.push_str("</div><h4>MTF curves</h4><p>Centre, mean of the four edge midpoints, mean of the four corners; solid tangential, dashed sagittal. Data: <a href=\"");
    let _ = write!(h, "{prefix}mtf-curves.csv\">mtf-curves.csv</a>, per tile: <a href=\"{prefix}mtf50.csv\">mtf50.csv</a>.</p><div class=row>");
    for ch in &r.channels {
        let _ = write!(h, "<figure><img src=\"{prefix}mtf-curves-{ch}.svg\" alt=\"MTF curves {ch}\"><figcaption>{ch}</figcaption></figure>");
    }
    h.push_str("</div>");
    h.push_str(&uncertainty_html(r, prefix));
    if r.channels.len() > 1 {
        let mx = (0..r.tiles.len())
            .flat_map(|t| (0..r.channels.len()).map(move |c| (c, t)))
            .map(|(c, t)| {
                let (x, y) = r.lateral(c, t);
                x.hypot(y)
            })
            .fold(0.0, f64::max);
        let _ = write!(h, "<h4>Lateral colour</h4><p>Centroid of each channel minus {}'s, per tile (largest {} px); arrows magnified as labelled.</p><img src=\"{prefix}lateral-colour.svg\" alt=\"lateral colour arrows\">", r.channels[r.reference], fixed(mx, 2));
    }
    if let Some((core, e)) = r.restoration_tiles {
        let _ = write!(
            h,
            "<h4>Restoration tiles</h4><p><code>lensrig deblur</code> restores this lens in tiles of {core} px, each with the PSF at its centre; across a tile the PSF differs from that by {} % (relative L2, blend-weighted RMS; docs/deconvolution.md \"Tile size\"){}.</p>",
            fixed(e * 100.0, 1),
            if crate::deconv::tile_error_warns(e) { ": the PSF changes faster across the field than the smallest default tiles follow, so restorations are approximate there (a smaller <code>--tile</code> follows it more closely, at more cost)" } else { "" }
        );
    }
    h
}

/// The uncertainty part of [`html_section`]: the per-channel field maps of the predicted
/// relative L2 error, or a note that the profile has none.
fn uncertainty_html(r: &ProfileReport, prefix: &str) -> String {
    let mut h = String::from("<h4>Uncertainty</h4>");
    let Some(u) = &r.uncertainty else {
        h.push_str("<p>no uncertainty (estimate with --bootstrap N)</p>");
        return h;
    };
    let all: Vec<f64> = u.iter().flatten().copied().filter(|v| v.is_finite()).collect();
    let mut sorted = all.clone();
    sorted.sort_by(f64::total_cmp);
    let med = sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN);
    let _ = write!(h, "<p>Predicted relative L2 error of each kernel, ‖u‖₂ / ‖b‖₂ in per cent (u: the per-pixel root mean square error of psf-unc-&lt;C&gt;.tiff, bootstrap bias and standard deviation; docs/estimation.md \"Uncertainty\"); median {} %. Data: <a href=\"{prefix}uncertainty.csv\">uncertainty.csv</a>.</p><div class=row>", fixed(med * 100.0, 2));
    for ch in &r.channels {
        let _ = write!(h, "<figure><img src=\"{prefix}uncertainty-{ch}.svg\" alt=\"predicted kernel error map {ch}\"><figcaption>{ch}</figcaption></figure>");
    }
    h.push_str("</div>");
    h
}

/// The page style shared by the report and `calibrate`'s index.
pub const STYLE: &str = "body{font-family:sans-serif;margin:2em;max-width:1200px}img{image-rendering:pixelated;border:1px solid #ccc}figure{display:inline-block;margin:4px 8px}figcaption{text-align:center;font-size:85%}table.num td,table.num th{padding:3px 10px;text-align:right}div.row{display:flex;flex-wrap:wrap;align-items:flex-start}";

/// Writes the report files of a profile into `dir` (created) and returns the analysis;
/// `uncertainty` is the profile's `psf-unc-<C>.tiff` mosaics when it has them
/// ([`crate::profile::uncertainty::load_uncertainty`]).
///
/// # Errors
/// A file that cannot be written; [`ReportError::Foreign`] when `dir` holds another
/// command's `index.html`.
pub fn write_report(dir: &Path, p: &Profile, uncertainty: Option<&[Vec<Plane>]>, pitch_um: Option<f64>, title: &str) -> Result<ProfileReport, ReportError> {
    // an index.html without this report's mtf50.csv beside it is another command's report (a
    // calibration run's, a diagnosis's): it is kept, and nothing is written
    if dir.join("index.html").exists() && !dir.join("mtf50.csv").exists() {
        return Err(ReportError::Foreign { path: dir.into(), found: "index.html".into(), kind: "profile report" });
    }
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let g = &p.grid;
    let mut r = analyse(g, p.meta.source.width, p.meta.source.height, pitch_um).with_restoration_tiles(g);
    if let Some(u) = uncertainty {
        r = r.with_uncertainty(g, u);
    }
    write_assets(dir, g, &r)?;
    let html = format!("<!doctype html><meta charset=utf-8><title>{title}</title><style>{STYLE}</style><h1>{title}</h1>{}", html_section(&r, ""));
    let f = dir.join("index.html");
    write_atomic(&f, html.as_bytes(), Overwrite::Replace).map_err(io(&f))?;
    Ok(r)
}

/// Writes the images, plots and CSV files [`html_section`] refers to.
///
/// # Errors
/// A file that cannot be written.
pub fn write_assets(dir: &Path, g: &PsfGrid, r: &ProfileReport) -> Result<(), ReportError> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let zoom = (96 / g.kernel_size.max(1)).clamp(1, 4);
    for (c, ch) in g.channels.iter().enumerate() {
        write_png8(&dir.join(format!("psf-{ch}.png")), &Image::new(vec![upscale(&psf_mosaic(g, c), zoom)]), Overwrite::Replace)?;
    }
    if let Some(rgb) = psf_colour_mosaic(g) {
        let up = Image::new(rgb.planes.iter().map(|p| upscale(p, zoom)).collect());
        write_png8(&dir.join("psf-rgb.png"), &up, Overwrite::Replace)?;
    }
    let mut files: Vec<(String, String)> = vec![("mtf50.csv".into(), mtf50_csv(r)), ("mtf-curves.csv".into(), curves_csv(r))];
    for (c, ch) in r.channels.iter().enumerate() {
        files.push((format!("mtf50-{ch}-tan.svg"), svg::field_map(r, &r.tiles.iter().map(|t| t.mtf50_tan[c]).collect::<Vec<_>>(), &format!("{ch} MTF50 tangential (c/px)"))));
        files.push((format!("mtf50-{ch}-sag.svg"), svg::field_map(r, &r.tiles.iter().map(|t| t.mtf50_sag[c]).collect::<Vec<_>>(), &format!("{ch} MTF50 sagittal (c/px)"))));
        files.push((format!("mtf-curves-{ch}.svg"), svg::mtf_curves(r, c)));
    }
    if r.channels.len() > 1 {
        files.push(("lateral-colour.svg".into(), svg::lateral_arrows(r)));
    }
    if let (Some(u), Some(csv)) = (&r.uncertainty, uncertainty_csv(r)) {
        files.push(("uncertainty.csv".into(), csv));
        for (ch, e) in r.channels.iter().zip(u) {
            let pct: Vec<f64> = e.iter().map(|v| v * 100.0).collect();
            files.push((format!("uncertainty-{ch}.svg"), svg::field_map(r, &pct, &format!("{ch} predicted kernel error (%)"))));
        }
    }
    for (name, text) in files {
        let f = dir.join(name);
        write_atomic(&f, text.as_bytes(), Overwrite::Replace).map_err(io(&f))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::lens::LensModel;

    #[test]
    fn rounding_helpers() {
        assert_eq!(significant(24.567, 3), "24.6");
        assert_eq!(significant(0.0012345, 3), "0.00123");
        assert_eq!(significant(1234.4, 3), "1234");
        assert_eq!(fixed(f64::NAN, 2), "");
        assert_eq!(fixed(0.96488593, 3), "0.965");
    }

    #[test]
    fn report_of_the_demo_lens() {
        let lens = LensModel::demo(192, 144);
        let g = lens.psf_grid(5.6, 3, 3, 21);
        let r = analyse(&g, 192, 144, Some(5.0));
        assert_eq!(r.channels, ["R", "G", "B"]);
        assert_eq!(r.axis_tile, 4);
        // sharper on axis than in the corners (field curvature, coma, astigmatism)
        for c in 0..3 {
            assert!(r.tiles[4].mtf50_tan[c] > r.tiles[0].mtf50_tan[c], "channel {c}");
            assert!(r.tiles[4].ee80[c] < r.tiles[0].ee80[c]);
        }
        // longitudinal colour: the lens focuses green (540 nm); blue is blurred most
        assert!(r.tiles[4].ee80[2] > r.tiles[4].ee80[1]);
        // reference channel has no lateral colour against itself
        assert_eq!(r.lateral(1, 0), (0.0, 0.0));
        // lp/mm
        assert!((r.lp_mm(0.25).unwrap_or(0.0) - 50.0).abs() < 1e-9);
        let csv = mtf50_csv(&r);
        assert_eq!(csv.lines().count(), 1 + 9 * 3);
        assert!(!csv.contains("NaN"));
        let curves = curves_csv(&r);
        assert_eq!(curves.lines().count(), 1 + 9 * 3 * 2 * 51);
        let html = html_section(&r, "x/");
        for f in ["x/psf-rgb.png", "x/psf-B.png", "x/mtf50-G-sag.svg", "x/mtf-curves-R.svg", "x/lateral-colour.svg"] {
            assert!(html.contains(f), "{f}");
        }
        assert!(html.contains("no uncertainty (estimate with --bootstrap N)"));
    }

    #[test]
    fn restoration_tiles_follow_the_field_and_warn_when_it_changes_fast() {
        // a slowly varying lens keeps the spacing rule's tiles, without a warning
        let slow = crate::deconv::synth::SyntheticLens { field_growth: 0.1, lateral_shift: 0.2, ..crate::deconv::synth::SyntheticLens::new(13, 3) }.grid(192, 192, 3, 3, 3);
        let r = analyse(&slow, 192, 192, None).with_restoration_tiles(&slow);
        assert_eq!(r.restoration_tiles, Some(crate::deconv::default_tile_core(&slow, 192, 192)));
        let (core, _) = r.restoration_tiles.expect("added");
        assert_eq!(core, 96);
        let html = html_section(&r, "");
        assert!(html.contains("Restoration tiles") && html.contains("tiles of 96 px") && !html.contains("approximate there"), "{html}");
        // sharp kernels with 3 px of lateral colour: the smallest default tiles, and a warning
        let fast = crate::deconv::synth::SyntheticLens { base_radius: 1.0, chromatic: 0.4, field_growth: 1.5, lateral_shift: 3.0, ..crate::deconv::synth::SyntheticLens::new(13, 3) }.grid(192, 192, 3, 3, 3);
        let r = analyse(&fast, 192, 192, None).with_restoration_tiles(&fast);
        let (core, e) = r.restoration_tiles.expect("added");
        assert_eq!(core, 48);
        assert!(crate::deconv::tile_error_warns(e));
        let html = html_section(&r, "");
        assert!(html.contains("tiles of 48 px") && html.contains("approximate there"), "{html}");
    }

    /// The report replaces its own earlier files but never another command's `index.html`.
    #[test]
    fn report_refuses_a_directory_holding_another_report() {
        use crate::image::{SampleFormat, Transfer};
        use crate::profile::{PsfTable, SourceInfo};
        let (w, h) = (96, 64);
        let grid = LensModel::demo(w, h).psf_grid(4.0, 2, 2, 15);
        let psf = PsfTable { kernel_size: 15, columns: 2, rows: 2, centers: grid.centers.clone(), tile_size: None, files: Default::default() };
        let source = SourceInfo { width: w, height: h, channels: grid.channels.clone(), sample_format: SampleFormat::U16, transfer: Transfer::Linear, open: None, pinhole: None, black_level: vec![] };
        let p = Profile { meta: Profile::new_meta(source, vec![1.0; grid.channels.len()], psf), grid };
        let d = tempfile::tempdir().expect("tempdir");
        let out = d.path().join("rep");
        write_report(&out, &p, None, None, "first").expect("fresh directory");
        write_report(&out, &p, None, None, "second").expect("its own report is replaced");
        assert!(std::fs::read_to_string(out.join("index.html")).expect("html").contains("second"));
        let cal = d.path().join("cal");
        std::fs::create_dir(&cal).expect("dir");
        std::fs::write(cal.join("index.html"), "calibration run").expect("write");
        let e = write_report(&cal, &p, None, None, "x").expect_err("foreign index.html");
        assert!(e.to_string().contains("not a profile report"), "{e}");
        assert_eq!(std::fs::read_to_string(cal.join("index.html")).expect("html"), "calibration run");
        assert_eq!(std::fs::read_dir(&cal).expect("ls").count(), 1);
    }

    /// With uncertainty maps, the report writes one field map per channel and a CSV whose values
    /// are the predicted error of each kernel (`‖u‖/‖b‖`), and the HTML shows the maps.
    #[test]
    fn uncertainty_field_map_holds_the_predicted_errors() {
        let lens = LensModel::demo(192, 144);
        let g = lens.psf_grid(5.6, 3, 2, 15);
        let unc: Vec<Vec<Plane>> = (0..3).map(|c| (0..6).map(|t| g.kernels[c][t].map(|v| v * 0.01 * (1 + c + t) as f32)).collect()).collect();
        let r = analyse(&g, 192, 144, None).with_uncertainty(&g, &unc);
        let d = tempfile::tempdir().expect("tempdir");
        write_assets(d.path(), &g, &r).expect("assets");
        let csv = std::fs::read_to_string(d.path().join("uncertainty.csv")).expect("csv");
        assert_eq!(csv.lines().count(), 1 + 6 * 3);
        for line in csv.lines().skip(1) {
            let f: Vec<&str> = line.split(',').collect();
            let (t, c) = (f[0].parse::<usize>().expect("tile"), r.channels.iter().position(|n| n == f[5]).expect("channel"));
            let want = crate::estimate::bootstrap::predicted_error(&unc[c][t], &g.kernels[c][t]);
            assert!((want - 0.01 * (1 + c + t) as f64).abs() < 1e-6, "{want}");
            assert!((f[6].parse::<f64>().expect("value") - want).abs() < 1e-3 * want, "{line}");
        }
        for (c, ch) in r.channels.iter().enumerate() {
            let svg = std::fs::read_to_string(d.path().join(format!("uncertainty-{ch}.svg"))).expect("svg");
            for t in 0..6 {
                let v = fixed(crate::estimate::bootstrap::predicted_error(&unc[c][t], &g.kernels[c][t]) * 100.0, 3);
                assert!(svg.contains(&format!(">{v}<")), "{ch} tile {t}: {v}");
            }
        }
        let html = html_section(&r, "");
        assert!(html.contains("uncertainty-G.svg") && !html.contains("no uncertainty"));
    }
}
